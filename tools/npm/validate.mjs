// Run the Khronos glTF-Validator on one .gltf/.glb and print its report as JSON on stdout.
//
// usage: node validate.mjs <asset path> [maxIssues]
//
// External resources (buffers, images) are loaded only from the asset's own folder: a uri
// with a scheme, an absolute path or one that resolves outside that folder is refused (the
// validator then reports it as an unloadable resource). Exit status: 0 when a report was
// produced (whatever it says), 2 on bad arguments or an unreadable input.
import fs from "node:fs";
import path from "node:path";
import { createRequire } from "node:module";

const require = createRequire(import.meta.url);
const validator = require("gltf-validator");

const [assetArg, maxIssuesArg] = process.argv.slice(2);
if (!assetArg) {
  console.error("usage: node validate.mjs <asset.gltf|asset.glb> [maxIssues]");
  process.exit(2);
}
const assetPath = path.resolve(assetArg);
const folder = fs.realpathSync(path.dirname(assetPath));
let bytes;
try {
  bytes = fs.readFileSync(assetPath);
} catch (err) {
  console.error(`cannot read the asset: ${err.code || err}`);
  process.exit(2);
}

function loadInsideFolder(uri) {
  return new Promise((resolve, reject) => {
    let rel;
    try {
      rel = decodeURIComponent(uri);
    } catch {
      reject(`bad uri encoding: ${uri}`);
      return;
    }
    if (/^[a-zA-Z][a-zA-Z0-9+.-]*:/.test(rel) || rel.startsWith("/") || rel.startsWith("\\")) {
      reject(`refused uri outside the asset's folder: ${uri}`);
      return;
    }
    const target = path.resolve(folder, rel);
    let real;
    try {
      real = fs.realpathSync(target);
    } catch {
      reject(`missing file: ${uri}`);
      return;
    }
    if (real !== folder && !real.startsWith(folder + path.sep)) {
      reject(`refused uri outside the asset's folder: ${uri}`);
      return;
    }
    fs.readFile(real, (err, data) => (err ? reject(String(err.code || err)) : resolve(data)));
  });
}

validator
  .validateBytes(new Uint8Array(bytes), {
    uri: path.basename(assetPath),
    maxIssues: Number(maxIssuesArg || 200),
    writeTimestamp: false,
    externalResourceFunction: loadInsideFolder,
  })
  .then(
    (report) => {
      process.stdout.write(JSON.stringify(report));
      process.exit(0);
    },
    (err) => {
      // the validator could not even detect glTF or GLB: report that as one error
      process.stdout.write(
        JSON.stringify({
          issues: {
            numErrors: 1,
            numWarnings: 0,
            numInfos: 0,
            numHints: 0,
            messages: [{ code: "INVALID_INPUT", message: String(err), severity: 0 }],
          },
        }),
      );
      process.exit(0);
    },
  );
