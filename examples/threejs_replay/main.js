// An engine-side example: load the run's glTF map and animate every agent of a run (live
// or `sumoco replay`) in three.js, through `sumoco gateway` (protocol/SPEC.md sections
// 3, 9 and 10). Open index.html?gw=<the gateway's URL, URL-encoded>.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

const hud = document.getElementById("hud");
const gwUrl = new URLSearchParams(location.search).get("gw");
const state = { mapMeshes: 0, agents: 0, steps: 0, physics: 0, error: "" };
window.sumocoExample = state; // read by the tests

// ---------------------------------------------------------------- msgpack (SPEC 3)
function unpack(u8) {
  const dv = new DataView(u8.buffer, u8.byteOffset, u8.byteLength);
  let p = 0;
  const str = (n) => { const s = new TextDecoder().decode(u8.subarray(p, p + n)); p += n; return s; };
  const bin = (n) => { const b = u8.slice(p, p + n); p += n; return b; }; // a copy: aligned for typed arrays
  const arr = (n) => { const a = []; for (let i = 0; i < n; i++) a.push(read()); return a; };
  const map = (n) => { const m = {}; for (let i = 0; i < n; i++) { const k = read(); m[k] = read(); } return m; };
  function read() {
    const b = u8[p++];
    if (b <= 0x7f) return b;
    if (b >= 0xe0) return b - 0x100;
    if ((b & 0xf0) === 0x80) return map(b & 0x0f);
    if ((b & 0xf0) === 0x90) return arr(b & 0x0f);
    if ((b & 0xe0) === 0xa0) return str(b & 0x1f);
    let v;
    switch (b) {
      case 0xc0: return null;
      case 0xc2: return false;
      case 0xc3: return true;
      case 0xc4: v = u8[p]; p += 1; return bin(v);
      case 0xc5: v = dv.getUint16(p); p += 2; return bin(v);
      case 0xc6: v = dv.getUint32(p); p += 4; return bin(v);
      case 0xca: v = dv.getFloat32(p); p += 4; return v;
      case 0xcb: v = dv.getFloat64(p); p += 8; return v;
      case 0xcc: return u8[p++];
      case 0xcd: v = dv.getUint16(p); p += 2; return v;
      case 0xce: v = dv.getUint32(p); p += 4; return v;
      case 0xcf: v = Number(dv.getBigUint64(p)); p += 8; return v;
      case 0xd0: v = dv.getInt8(p); p += 1; return v;
      case 0xd1: v = dv.getInt16(p); p += 2; return v;
      case 0xd2: v = dv.getInt32(p); p += 4; return v;
      case 0xd3: v = Number(dv.getBigInt64(p)); p += 8; return v;
      case 0xd9: v = u8[p]; p += 1; return str(v);
      case 0xda: v = dv.getUint16(p); p += 2; return str(v);
      case 0xdb: v = dv.getUint32(p); p += 4; return str(v);
      case 0xdc: v = dv.getUint16(p); p += 2; return arr(v);
      case 0xdd: v = dv.getUint32(p); p += 4; return arr(v);
      case 0xde: v = dv.getUint16(p); p += 2; return map(v);
      case 0xdf: v = dv.getUint32(p); p += 4; return map(v);
      default: throw new Error("msgpack: unsupported byte 0x" + b.toString(16));
    }
  }
  return read();
}
const f64 = (b) => new Float64Array(b.buffer, b.byteOffset, b.byteLength / 8);
const f32 = (b) => new Float32Array(b.buffer, b.byteOffset, b.byteLength / 4);
const u8col = (b) => b;

// ---------------------------------------------------------------- gateway frames (SPEC 10)
function unpackFrame(buf) {
  const n = new DataView(buf).getUint16(0, true);
  return { key: new TextDecoder().decode(new Uint8Array(buf, 2, n)), payload: new Uint8Array(buf, 2 + n) };
}

// ---------------------------------------------------------------- scene
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setSize(innerWidth, innerHeight);
document.body.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x1d2024);
scene.add(new THREE.HemisphereLight(0xffffff, 0x444444, 2.5));
const sun = new THREE.DirectionalLight(0xffffff, 1.5);
sun.position.set(100, 300, 100);
scene.add(sun);
const camera = new THREE.PerspectiveCamera(50, innerWidth / innerHeight, 0.5, 20000);
camera.position.set(0, 250, 250);
const controls = new OrbitControls(camera, renderer.domElement);
addEventListener("resize", () => {
  camera.aspect = innerWidth / innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(innerWidth, innerHeight);
});

// One instanced box per agent; one draw call for all of them.
const HEIGHT = [1.5, 1.5, 3.0, 1.7, 1.8, 2.5]; // [m] per agent class (SPEC 3.1 cls)
const COLOR = [0x3b82f6, 0xfacc15, 0xef4444, 0x22c55e, 0xe5e7eb, 0xa855f7];
let boxes = null;
function ensureCapacity(n) {
  if (boxes && boxes.count >= n && boxes.instanceMatrix.count >= n) return;
  if (boxes) scene.remove(boxes);
  const cap = Math.max(64, 1 << Math.ceil(Math.log2(n + 1)));
  boxes = new THREE.InstancedMesh(new THREE.BoxGeometry(1, 1, 1), new THREE.MeshStandardMaterial(), cap);
  boxes.name = "agents";
  boxes.frustumCulled = false;
  scene.add(boxes);
}

const sizes = new Map(); // id -> [length, width] from the newest step (physics rows carry none)
let latestStep = null;
let latestPhysics = null;
let physicsKey = null;
const m4 = new THREE.Matrix4(), q = new THREE.Quaternion(), pos = new THREE.Vector3(), scl = new THREE.Vector3();
const yAxis = new THREE.Vector3(0, 1, 0), col = new THREE.Color();

function place(ids, x, y, angleDeg, cls) {
  ensureCapacity(ids.length);
  for (let i = 0; i < ids.length; i++) {
    const [len, wid] = sizes.get(ids[i]) ?? [4.5, 1.8];
    const a = angleDeg[i] * Math.PI / 180;
    const h = HEIGHT[cls[i]] ?? 1.5;
    // SUMO front-bumper centre -> box centre, then SUMO (x, y) -> glTF/three (x, up, -y) (SPEC 9).
    const cx = x[i] - Math.sin(a) * len / 2, cy = y[i] - Math.cos(a) * len / 2;
    pos.set(cx, h / 2, -cy);
    q.setFromAxisAngle(yAxis, -a); // a box facing -Z (north) turned clockwise by the SUMO angle
    scl.set(wid, h, len);
    boxes.setMatrixAt(i, m4.compose(pos, q, scl));
    boxes.setColorAt(i, col.setHex(COLOR[cls[i]] ?? 0x999999));
  }
  boxes.count = ids.length;
  boxes.instanceMatrix.needsUpdate = true;
  if (boxes.instanceColor) boxes.instanceColor.needsUpdate = true;
  state.agents = ids.length;
}

function frame() {
  requestAnimationFrame(frame);
  // Physics poses when a physics side runs, else SUMO's own.
  if (latestPhysics) {
    const a = latestPhysics.agents;
    place(a.id, f64(a.x), f64(a.y), f32(a.heading), u8col(a.cls));
  } else if (latestStep) {
    const a = latestStep.agents;
    place(a.id, f64(a.x), f64(a.y), f32(a.angle), u8col(a.cls));
  }
  controls.update();
  renderer.render(scene, camera);
  hud.textContent = `t ${latestStep ? latestStep.t.toFixed(1) : "-"} s | agents ${state.agents} | ` +
    `map meshes ${state.mapMeshes}${state.error ? " | " + state.error : ""}`;
}
requestAnimationFrame(frame);

function loadMap(reply) {
  new GLTFLoader().parse(reply.glb.slice().buffer, "", (gltf) => {
    scene.add(gltf.scene);
    gltf.scene.traverse((o) => { if (o.isMesh) state.mapMeshes += 1; });
    const box = new THREE.Box3().setFromObject(gltf.scene);
    const c = box.getCenter(new THREE.Vector3()), r = box.getSize(new THREE.Vector3()).length() / 2;
    controls.target.copy(c);
    camera.position.set(c.x, c.y + r, c.z + r);
  }, (e) => { state.error = "map: " + e; });
}

// ---------------------------------------------------------------- gateway connection
if (!gwUrl) {
  state.error = "add ?gw=<gateway URL> (printed by `sumoco gateway`)";
} else {
  const ws = new WebSocket(gwUrl);
  ws.binaryType = "arraybuffer";
  // The map is asked for until it arrives: the run's publisher may not answer yet when the page
  // connects (it starts later, or is slow to declare its queryable), and one lost answer must
  // not leave the page without a map for good.
  let mapAsked = false;
  const askMap = () => {
    if (ws.readyState !== WebSocket.OPEN || mapAsked || state.mapMeshes > 0) return;
    mapAsked = true;
    ws.send(JSON.stringify({ op: "get", key: "sumo/map" }));
  };
  setInterval(askMap, 2000);
  ws.onopen = () => {
    for (const key of ["sumo/step", "physics/*/state"]) ws.send(JSON.stringify({ op: "subscribe", key }));
    askMap();
  };
  ws.onmessage = (ev) => {
    if (typeof ev.data === "string") {
      const m = JSON.parse(ev.data);
      if (m.op === "error") state.error = m.error;
      if (m.op === "error" && String(m.key).endsWith("sumo/map")) mapAsked = false; // no answer: ask again
      return;
    }
    const { key, payload } = unpackFrame(ev.data);
    const msg = unpack(payload);
    if (key.endsWith("/sumo/map")) {
      if (msg.glb) { state.error = ""; loadMap(msg); } else mapAsked = false;
    } else if (key.endsWith("/sumo/step")) {
      const a = msg.agents, len = f32(a.length), wid = f32(a.width);
      sizes.clear();
      a.id.forEach((id, i) => sizes.set(id, [len[i], wid[i]]));
      latestStep = msg;
      state.steps += 1;
    } else if (key.endsWith("/state")) {
      physicsKey = physicsKey ?? key; // several physics instances may run side by side: show one
      if (key !== physicsKey) return;
      latestPhysics = msg;
      state.physics += 1;
    }
  };
  ws.onerror = () => { state.error = "gateway connection failed"; };
  ws.onclose = () => { state.error = state.error || "gateway closed"; };
}
