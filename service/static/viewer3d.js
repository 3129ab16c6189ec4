// The job view's 3D viewer: a job's upscaled asset (links.model) drawn by three.js under a
// room environment (three's RoomEnvironment prefiltered by PMREM: image-based light made in
// the page, no file), with orbit controls. three.js comes from /vendor/three/ (the npm
// package, served by the service: see the import map in index.html).
//
// It is set up when its container first comes on screen and draws on demand (after a load, a
// resize or a camera move), never in a loop: on a machine without a GPU the browser renders
// WebGL on the CPU.
// window.pbrsrViewer.show(container, url, resolve) loads a model: url is its API path, and
// resolve(path) gives a URL to load that path (or a .gltf's buffer or image beside it) from
// without the API key (app.js's fileUrl: with s3 storage a presigned URL of the bucket, which
// must then allow the dashboard's origin: CORS). .clear(container) drops the model.
// The container's data-state says "loading", "ready" (data-frames counts the draws) or
// "error" (data-error says why).
import * as THREE from "three";
import { DRACOLoader } from "three/addons/loaders/DRACOLoader.js";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { MeshoptDecoder } from "three/addons/libs/meshopt_decoder.module.js";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { RoomEnvironment } from "three/addons/environments/RoomEnvironment.js";

const BACKGROUND = 0x2e2e2e;
const DRACO_DECODER = "/vendor/three/examples/jsm/libs/draco/gltf/";
let draco = null; // one DRACOLoader (its decoder workers) for every model

// The JSON of a .gltf or of a .glb's first chunk.
function gltfJson(data) {
  const bytes = new Uint8Array(data);
  const magic = new TextDecoder().decode(bytes.subarray(0, 4));
  if (magic !== "glTF") return JSON.parse(new TextDecoder().decode(bytes));
  const length = new DataView(data).getUint32(12, true);
  return JSON.parse(new TextDecoder().decode(bytes.subarray(20, 20 + length)));
}

// The model at API path `url`, its relative buffers and images resolved beside it.
async function loadModel(url, resolve) {
  const resp = await fetch(await resolve(url));
  if (!resp.ok) throw new Error(`cannot load the model (${resp.status})`);
  const data = await resp.arrayBuffer();
  const json = gltfJson(data);
  const base = THREE.LoaderUtils.extractUrlBase(url);
  const uris = [...(json.buffers || []), ...(json.images || [])]
    .map((item) => item.uri)
    .filter((uri) => typeof uri === "string" && uri && !/^([a-z][a-z0-9+.-]*:|\/)/i.test(uri));
  const urls = new Map(
    await Promise.all([...new Set(uris)].map(async (uri) => [base + uri, await resolve(base + uri)])),
  );
  const manager = new THREE.LoadingManager();
  manager.setURLModifier((u) => urls.get(u) || u);
  if (!draco) draco = new DRACOLoader().setDecoderPath(DRACO_DECODER);
  const loader = new GLTFLoader(manager).setDRACOLoader(draco).setMeshoptDecoder(MeshoptDecoder);
  return loader.parseAsync(data, base);
}

class ModelView {
  constructor(container) {
    this.container = container;
    // preserveDrawingBuffer: the canvas can be read back (saved, tested) between draws
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.renderer.toneMapping = THREE.NeutralToneMapping;
    this.renderer.setClearColor(BACKGROUND);
    container.replaceChildren(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(BACKGROUND);
    const pmrem = new THREE.PMREMGenerator(this.renderer);
    const room = new RoomEnvironment();
    this.scene.environment = pmrem.fromScene(room, 0.04).texture;
    room.dispose();
    pmrem.dispose();
    this.camera = new THREE.PerspectiveCamera(35, 1, 0.01, 100);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener("change", () => this.draw());
    this.frames = 0;
    this.model = null;
    this.url = null;
    new ResizeObserver(() => this.resize()).observe(container);
    this.resize();
  }

  resize() {
    const w = Math.max(1, this.container.clientWidth);
    const h = Math.max(1, this.container.clientHeight);
    this.renderer.setSize(w, h, true);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.draw();
  }

  draw() {
    this.renderer.render(this.scene, this.camera);
    this.frames += 1;
    this.container.dataset.frames = String(this.frames);
  }

  async show(url, resolve) {
    if (url === this.url) return;
    this.url = url;
    this.container.dataset.state = "loading";
    let gltf;
    try {
      gltf = await loadModel(url, resolve);
    } catch (err) {
      if (url !== this.url) return;
      this.container.dataset.state = "error";
      this.container.dataset.error = String((err && err.message) || err);
      return;
    }
    if (url !== this.url) return; // another job was picked meanwhile
    this.drop();
    this.model = gltf.scene;
    this.scene.add(this.model);
    this.frame(this.model);
    this.container.dataset.state = "ready";
    this.draw();
  }

  // Point the camera at the model's bounding box, from the front and a little above, near
  // enough that its longest side fills the narrower of the two fields of view.
  frame(object) {
    const box = new THREE.Box3().setFromObject(object);
    const centre = box.getCenter(new THREE.Vector3());
    const size = box.getSize(new THREE.Vector3());
    const half = Math.max(size.x, size.y, size.z, 1e-3) / 2;
    const vfov = THREE.MathUtils.degToRad(this.camera.fov);
    const hfov = 2 * Math.atan(Math.tan(vfov / 2) * this.camera.aspect);
    const distance = (half / Math.tan(Math.min(vfov, hfov) / 2) + half) * 1.1;
    const dir = new THREE.Vector3(0.35, 0.45, 1).normalize();
    this.camera.position.copy(centre).addScaledVector(dir, distance);
    this.camera.near = distance / 100;
    this.camera.far = distance * 100;
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(centre);
    this.controls.update();
  }

  drop() {
    if (!this.model) return;
    this.scene.remove(this.model);
    this.model.traverse((node) => {
      if (node.geometry) node.geometry.dispose();
      for (const m of [].concat(node.material || [])) {
        for (const value of Object.values(m)) if (value && value.isTexture) value.dispose();
        m.dispose();
      }
    });
    this.model = null;
  }

  clear() {
    this.url = null;
    this.drop();
    this.container.dataset.state = "idle";
    this.draw();
  }
}

const views = new WeakMap();
function viewOf(container) {
  if (!views.has(container)) views.set(container, new ModelView(container));
  return views.get(container);
}

// Resolves once the container is on screen: WebGL set-up and drawing wait until someone looks.
function onScreen(container) {
  return new Promise((resolve) => {
    const observer = new IntersectionObserver((entries) => {
      if (entries.some((e) => e.isIntersecting)) {
        observer.disconnect();
        resolve();
      }
    });
    observer.observe(container);
  });
}

const wanted = new WeakMap(); // container -> the model URL last asked for
window.pbrsrViewer = {
  // rejects when the browser has no WebGL
  show: async (container, url, resolve) => {
    wanted.set(container, url);
    if (!views.has(container)) await onScreen(container);
    if (wanted.get(container) === url) await viewOf(container).show(url, resolve);
  },
  clear: (container) => {
    wanted.delete(container);
    if (views.has(container)) views.get(container).clear();
  },
};
document.documentElement.dataset.viewer = "ready";
document.dispatchEvent(new Event("pbrsr-viewer-ready"));
