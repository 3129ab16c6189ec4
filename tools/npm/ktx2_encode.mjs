// Encode one RGBA8 image as a KTX2 file with Basis Universal's encoder (the WebAssembly build
// the npm package ktx2-encoder ships) and write the file's bytes on stdout.
//
// usage: node ktx2_encode.mjs '<options JSON>' < pixels.rgba
//
// options: {"width", "height", "codec": "etc1s"|"uastc", "quality" (1-100), "effort" (0-10),
// "srgb" (DFD transfer function, perceptual metrics and sRGB mip filtering), "mipmaps",
// "zstd" (UASTC Zstandard supercompression), "alpha" (store the alpha channel)}.
// stdin: width * height * 4 bytes, rows top to bottom, R G B A.
// Exit status: 0 with the KTX2 bytes on stdout; 2 on bad options or input; 1 when the encoder
// fails. The reason is the last line on stderr, with no path in it.
import { NodeBasisEncoder } from "ktx2-encoder";

// stdout carries the file alone: whatever the WebAssembly module prints goes to stderr
console.log = console.error;

function fail(status, message) {
  process.stderr.write(`${message}\n`);
  process.exit(status);
}

let options;
try {
  options = JSON.parse(process.argv[2] ?? "");
} catch {
  fail(2, "usage: node ktx2_encode.mjs '<options JSON>' < pixels.rgba");
}
const { width, height, codec, quality, effort, srgb, mipmaps, zstd, alpha } = options;
if (!(Number.isInteger(width) && Number.isInteger(height) && width > 0 && height > 0)) {
  fail(2, `bad image size ${width}x${height}`);
}
if (codec !== "etc1s" && codec !== "uastc") fail(2, `unknown codec ${codec}`);

const chunks = [];
for await (const chunk of process.stdin) chunks.push(chunk);
const pixels = new Uint8Array(Buffer.concat(chunks));
if (pixels.length !== width * height * 4) {
  fail(2, `expected ${width * height * 4} bytes of RGBA8 pixels, read ${pixels.length}`);
}

async function encode() {
  const basis = await new NodeBasisEncoder().init();
  const encoder = new basis.BasisEncoder();
  try {
    const format = codec === "etc1s" ? basis.basis_tex_format.cETC1S : basis.basis_tex_format.cUASTC_LDR_4x4;
    encoder.setFormatModeAndQualityEffort(format.value, quality, effort, true);
    encoder.setCreateKTX2File(true);
    encoder.setStatusOutput(false);
    encoder.setDebug(false);
    encoder.setSRGBOptions(srgb);
    encoder.setCheckForAlpha(false);
    encoder.setForceAlpha(alpha);
    encoder.setMipGen(mipmaps);
    encoder.setMipWrapping(false);
    encoder.setKTX2UASTCSupercompression(zstd);
    if (!encoder.setSliceSourceImage(0, pixels, width, height, basis.ldr_image_type.cRGBA32.value)) {
      return null;
    }
    // room for every level uncompressed plus the header; doubled once if that is not enough
    const room = Math.ceil((width * height * 4 * 4) / 3) + 65536;
    for (const capacity of [room, 2 * room]) {
      const output = new Uint8Array(capacity);
      const length = encoder.encode(output);
      if (length > 0) return output.subarray(0, length);
    }
    return null;
  } finally {
    encoder.delete();
  }
}

let encoded;
try {
  encoded = await encode();
} catch (err) {
  fail(1, `Basis Universal's encoder stopped: ${err?.message ?? err}`);
}
if (!encoded) fail(1, `Basis Universal's encoder refused the ${width}x${height} image`);
process.stdout.write(encoded);
