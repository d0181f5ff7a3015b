// sumoco live viewer, 3D: the map as glTF (SPEC.md 9) and every agent with three.js.
//
// Same WebSocket feed as the 2D page (hello, static, frames with raw protocol messages).
// One InstancedMesh per model class (car, bus, bicycle, pedestrian bodies; wheels; lamps;
// pedestrian legs) so 2,500 agents cost a handful of draw calls. Poses come from the
// chosen physics instance (roll, pitch, steering) and fall back to SUMO's pose; SUMO's
// footprints are drawn as ghost outlines. World frame = glTF frame of the map:
// X = x - ox (east), Y = up, Z = -(y - oy) (south), (ox, oy) the map origin.
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const { unpack, readStep, readPhysics, setStatic } = window.sumocoDecode;
const DEG = Math.PI / 180;
const $ = (id) => document.getElementById(id);
const token = new URLSearchParams(location.search).get('token') || '';

// Classes on the wire (SPEC 3.1): 0 passenger, 1 taxi, 2 bus, 3 bicycle, 4 pedestrian, 5 other.
const CLASS_COLOURS = [0x4fc3f7, 0xfff176, 0x81c784, 0xce93d8, 0xf48fb1, 0xe0e0e0];
const HEIGHT = [0.8, 0.8, 3.0, 1.75, 1.0, 2.6]; // body height [m] per class (cars: below the cabin)
const CLEARANCE = [0.25, 0.25, 0.35, 0.0, 0.8, 0.3]; // body bottom above the road [m]
const WHEEL_R = [0.32, 0.32, 0.5, 0.34, 0, 0.45]; // wheel radius [m]
const TLS_COLOURS = {
  r: 0xff1a1a, R: 0xff1a1a, y: 0xffb300, Y: 0xffb300, g: 0x00c853, G: 0x00ff66,
  s: 0x9ccc65, u: 0xff7043, o: 0xfdd835, O: 0x555555,
};
const SIG_RIGHT = 1, SIG_LEFT = 2, SIG_EMERGENCY = 4, SIG_BRAKE = 8; // SUMO signal bits

const stats = {
  connected: false, hello: null, staticLoaded: false, staticSv: null, mapLoaded: false, mapMeshes: 0, mapSha: '',
  tlsHeads: 0, framesReceived: 0, framesDrawn: 0, renders: 0, errors: 0, lastError: '',
  agents: 0, physicsAgents: 0, ghosts: 0, instances: {}, drawCalls: 0, triangles: 0, fps: 0,
  step: -1, simTime: NaN, rtf: 0, follow: null, instance: null, renderMs: 0, updateMs: 0,
  decodeMs: 0, glRenderer: '', glVendor: '',
};
window.sumoco3d = stats;

function fail(e) {
  stats.errors++;
  stats.lastError = String(e && e.message ? e.message : e);
  console.warn('sumoco 3D viewer:', stats.lastError);
}

// ------------------------------------------------------------------ scene
const host = $('view3d');
const renderer = new THREE.WebGLRenderer({ antialias: window.devicePixelRatio < 2, preserveDrawingBuffer: true });
renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
renderer.setSize(host.clientWidth, host.clientHeight);
host.appendChild(renderer.domElement);
// The GL implementation behind the canvas ("SwiftShader" = software rendering on the CPU), so
// an fps figure can be read against what drew it (sumoco bench viewer, bug reports).
try {
  const gl = renderer.getContext();
  const ext = gl.getExtension('WEBGL_debug_renderer_info');
  stats.glRenderer = String(gl.getParameter(ext ? ext.UNMASKED_RENDERER_WEBGL : gl.RENDERER));
  stats.glVendor = String(gl.getParameter(ext ? ext.UNMASKED_VENDOR_WEBGL : gl.VENDOR));
} catch (e) {
  stats.glRenderer = `unknown (${e})`;
}
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x9fb4c7);
scene.fog = new THREE.Fog(0x9fb4c7, 600, 4000);
const camera = new THREE.PerspectiveCamera(50, host.clientWidth / host.clientHeight, 0.5, 20000);
camera.position.set(60, 80, 90);
const controls = new OrbitControls(camera, renderer.domElement);
controls.maxPolarAngle = Math.PI * 0.49;
controls.enableDamping = false;
scene.add(new THREE.HemisphereLight(0xeef4ff, 0x3b4a30, 1.6));
const sun = new THREE.DirectionalLight(0xffffff, 1.8);
sun.position.set(-300, 500, 200);
scene.add(sun);
const ground = new THREE.Mesh(new THREE.PlaneGeometry(1, 1), new THREE.MeshLambertMaterial({ color: 0x55654a }));
ground.rotation.x = -Math.PI / 2;
ground.position.y = -0.05;
ground.scale.set(20000, 20000, 1);
scene.add(ground);

// ------------------------------------------------------------------ instanced models
// Unit geometries: scaled per instance. Bodies face -Z (north at yaw 0), 1 x 1 x 1 m.
function instanced(name, geometry, material, capacity) {
  const m = new THREE.InstancedMesh(geometry, material, capacity);
  m.name = name;
  m.count = 0;
  m.frustumCulled = false; // instances move everywhere; one bounding sphere would be stale
  m.instanceMatrix.setUsage(THREE.DynamicDrawUsage);
  m.setColorAt(0, new THREE.Color(1, 1, 1));
  m.instanceColor.setUsage(THREE.DynamicDrawUsage);
  scene.add(m);
  return m;
}

const box = new THREE.BoxGeometry(1, 1, 1);
const wheelGeo = new THREE.CylinderGeometry(1, 1, 1, 10).rotateZ(Math.PI / 2); // axle along X
const lampGeo = new THREE.BoxGeometry(1, 1, 1);
const MODELS = {
  car: { classes: [0, 1, 5], mesh: null },
  bus: { classes: [2], mesh: null },
  bicycle: { classes: [3], mesh: null },
  pedestrian: { classes: [4], mesh: null },
};
const MODEL_OF = [];
for (const [name, m] of Object.entries(MODELS)) for (const c of m.classes) MODEL_OF[c] = name;

let capacity = 0;
let bodies, wheels, lamps, legs, cabins, ghosts, tlsLamps;
function allocate(n) {
  capacity = Math.max(256, 1 << Math.ceil(Math.log2(Math.max(n, 1))));
  for (const m of [...Object.values(MODELS).map((x) => x.mesh), wheels, lamps, legs, cabins]) {
    if (m) { scene.remove(m); m.dispose(); }
  }
  const bodyMat = new THREE.MeshLambertMaterial({ color: 0xffffff });
  for (const [name, m] of Object.entries(MODELS)) m.mesh = instanced(name, box, bodyMat, capacity);
  bodies = Object.values(MODELS).map((m) => m.mesh);
  wheels = instanced('wheels', wheelGeo, new THREE.MeshLambertMaterial({ color: 0x1b1b1b }), 4 * capacity);
  lamps = instanced('lamps', lampGeo, new THREE.MeshBasicMaterial({ color: 0xffffff }), 4 * capacity);
  legs = instanced('legs', box, new THREE.MeshLambertMaterial({ color: 0x37474f }), 2 * capacity);
  cabins = instanced('cabins', box, new THREE.MeshLambertMaterial({ color: 0x263238 }), capacity);
}
allocate(256);

// SUMO footprints: ghost outlines, one LineSegments (4 segments per agent).
let ghostPos = new Float32Array(0);
function ghostGeometry(n) {
  if (ghosts) { scene.remove(ghosts); ghosts.geometry.dispose(); }
  ghostPos = new Float32Array(n * 8 * 3);
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.BufferAttribute(ghostPos, 3).setUsage(THREE.DynamicDrawUsage));
  ghosts = new THREE.LineSegments(g, new THREE.LineBasicMaterial({ color: 0xffffff, transparent: true, opacity: 0.55 }));
  ghosts.name = 'ghosts';
  ghosts.frustumCulled = false;
  scene.add(ghosts);
}
ghostGeometry(capacity);
let showGhosts = true;

// ------------------------------------------------------------------ map
let origin = [0, 0];
let mapRoot = null;
let heads = []; // {tls, link, pos: Vector3}
const loader = new GLTFLoader();

async function loadMap(sha) {
  if (!sha || sha === stats.mapSha) return;
  try {
    const r = await fetch(`map.glb?token=${encodeURIComponent(token)}`, { cache: 'no-store' });
    if (!r.ok) throw new Error(`map.glb: HTTP ${r.status}`);
    const buf = await r.arrayBuffer();
    const gltf = await loader.parseAsync(buf, '');
    if (mapRoot) scene.remove(mapRoot);
    mapRoot = gltf.scene;
    const meta = (mapRoot.userData && mapRoot.userData.sumoco) || {};
    origin = meta.origin || [0, 0];
    // Render around the map origin: drop the root's translation (it carries the origin).
    mapRoot.traverse((o) => { if (o.name === 'sumoco_map') o.position.set(0, 0, 0); });
    scene.add(mapRoot);
    mapRoot.updateMatrixWorld(true);
    let meshes = 0;
    heads = [];
    const lambert = new Map(); // flat, matte surfaces: Lambert looks the same and costs far less per pixel
    mapRoot.traverse((o) => {
      if (o.isMesh) {
        meshes++;
        const m = o.material;
        if (m && m.isMeshStandardMaterial) {
          if (!lambert.has(m)) lambert.set(m, new THREE.MeshLambertMaterial({ color: m.color, side: m.side, name: m.name }));
          o.material = lambert.get(m);
        }
      }
      // Heads by their extras (three.js rewrites '/' in node names).
      const x = o.userData || {};
      if (typeof x.tls === 'string' && Number.isInteger(x.link)) {
        const p = new THREE.Vector3(0, 0, 0.2).applyMatrix4(o.matrixWorld); // in front of the housing
        heads.push({ tls: x.tls, link: x.link, pos: p, matrix: o.matrixWorld.clone(), mesh: o });
      }
    });
    buildTlsLamps();
    stats.mapMeshes = meshes;
    stats.tlsHeads = heads.length;
    stats.mapSha = sha;
    stats.mapLoaded = true;
    $('hud-map').textContent = `${(buf.byteLength / 1024).toFixed(0)} KiB, ${meshes} meshes, ${heads.length} signal heads`;
    if (!userMoved) fit();
  } catch (e) {
    fail(e);
  }
}

let tlsHousings = null;
function buildTlsLamps() {
  if (tlsLamps) { scene.remove(tlsLamps); tlsLamps.dispose(); }
  if (tlsHousings) { scene.remove(tlsHousings); tlsHousings.dispose(); }
  if (!heads.length) { tlsLamps = tlsHousings = null; return; }
  // The GLB has one node per head (for engines to address); drawn here as one instanced mesh.
  const src = heads.find((h) => h.mesh.isMesh);
  if (src) {
    tlsHousings = instanced('tls_housings', src.mesh.geometry, src.mesh.material, heads.length);
    heads.forEach((h, k) => { tlsHousings.setMatrixAt(k, h.matrix); setCol(tlsHousings, k, 0xffffff); });
    tlsHousings.count = heads.length;
    tlsHousings.instanceMatrix.needsUpdate = true;
    for (const h of heads) h.mesh.visible = false;
  }
  tlsLamps = instanced('tls_lamps', new THREE.SphereGeometry(0.32, 10, 8), new THREE.MeshBasicMaterial({ color: 0xffffff }), heads.length);
  const mtx = new THREE.Matrix4();
  heads.forEach((h, k) => { mtx.makeTranslation(h.pos.x, h.pos.y, h.pos.z); tlsLamps.setMatrixAt(k, mtx); });
  tlsLamps.count = heads.length;
  tlsLamps.instanceMatrix.needsUpdate = true;
}

let userMoved = false;
controls.addEventListener('start', () => { userMoved = true; });
function fit() {
  const b = new THREE.Box3();
  if (mapRoot) b.setFromObject(mapRoot);
  else if (step && step.n) for (let i = 0; i < step.n; i++) b.expandByPoint(new THREE.Vector3(step.x[i] - origin[0], 0, -(step.y[i] - origin[1])));
  if (b.isEmpty()) return;
  const c = b.getCenter(new THREE.Vector3());
  const size = Math.max(b.max.x - b.min.x, b.max.z - b.min.z, 40);
  controls.target.copy(c);
  camera.position.set(c.x + size * 0.25, size * 0.75, c.z + size * 0.65);
  camera.far = Math.max(20000, size * 10);
  camera.updateProjectionMatrix();
  controls.update();
}

// ------------------------------------------------------------------ feed
let step = null; // newest decoded step
let physics = []; // [{name, msg}]
let pendingFrame = null;
const stepHist = []; // [wall ms, sim s]
let ws = null;
let retryMs = 500;
let leaving = false;

function connect() {
  const url = (location.protocol === 'https:' ? 'wss://' : 'ws://') + location.host + '/ws?token=' + encodeURIComponent(token);
  ws = new WebSocket(url);
  ws.binaryType = 'arraybuffer';
  ws.onopen = () => { stats.connected = true; retryMs = 500; hudConn(); };
  ws.onclose = () => {
    stats.connected = false;
    hudConn();
    if (leaving) return;
    setTimeout(connect, retryMs);
    retryMs = Math.min(retryMs * 2, 5000);
  };
  ws.onmessage = (ev) => {
    let env;
    try { env = unpack(new Uint8Array(ev.data)); } catch (e) { return fail(e); }
    if (env.type === 'frame') {
      stats.framesReceived++;
      pendingFrame = env;
    } else if (env.type === 'static') {
      // On connect and for every new static version: its vType table is the one steps
      // without `vtypes` refer to (SPEC 3.2); the map reloads only when its hash changed.
      try { stats.staticSv = setStatic(unpack(env.static)); } catch (e) { fail(e); }
      stats.staticLoaded = true;
      loadMap(env.map);
    } else if (env.type === 'hello') {
      stats.hello = { run: env.run, root: env.root, max_hz: env.max_hz };
      $('hud-run').textContent = env.run ? `run ${env.run}` : '';
    }
  };
}

// Where this page looks, for the physics level of detail (SPEC.md 3.7): the orbit target in
// SUMO coordinates, twice a second (the physics side drops a camera silent for 5 s).
setInterval(() => {
  if (!ws || ws.readyState !== WebSocket.OPEN || !(mapRoot || step)) return;
  const t = controls.target;
  ws.send(JSON.stringify({ op: 'camera', x: t.x + origin[0], y: origin[1] - t.z }));
  stats.camerasSent = (stats.camerasSent || 0) + 1;
}, 500);
// Leaving the page closes the socket at once (a page kept in the back/forward cache would
// hold it open), so the server retires this page's camera.
addEventListener('pagehide', () => { leaving = true; if (ws) ws.close(); });
addEventListener('pageshow', (ev) => { if (ev.persisted) { leaving = false; connect(); } });

function consumeFrame(now) {
  const env = pendingFrame;
  pendingFrame = null;
  const t0 = performance.now();
  try {
    if (env.step) {
      const s = readStep(unpack(env.step));
      if (step && s.step < step.step) stepHist.length = 0; // SUMO restarted
      s.index = new Map();
      for (let i = 0; i < s.n; i++) s.index.set(s.id[i], i);
      step = s;
      stepHist.push([now, s.t]);
      while (stepHist.length > 2 && now - stepHist[0][0] > 3000) stepHist.shift();
    }
    const next = [];
    const phys = env.physics || {};
    for (const name of Object.keys(phys).sort()) next.push({ name, msg: readPhysics(unpack(phys[name])) });
    physics = next;
    stats.sumoAlive = env.sumo_alive;
  } catch (e) {
    return fail(e);
  }
  stats.decodeMs = performance.now() - t0;
  stats.framesDrawn++;
  if (!userMoved && !mapRoot && stats.framesDrawn === 1) fit();
}

// ------------------------------------------------------------------ per-frame update
const M = new THREE.Matrix4();
const P = new THREE.Matrix4();
const S = new THREE.Matrix4();
const T = new THREE.Matrix4();
const Q = new THREE.Quaternion();
const E = new THREE.Euler(0, 0, 0, 'YXZ');
const V = new THREE.Vector3();
const ONE = new THREE.Vector3(1, 1, 1);
const C = new THREE.Color();
const spin = new Map(); // agent id -> wheel / stride phase [rad]
let instanceIdx = 0; // which physics instance drives the bodies
const pickIds = {}; // model name -> agent id per instance index
let follow = null;
const lastCentre = new THREE.Vector3();

function setMat(mesh, k, m) { m.toArray(mesh.instanceMatrix.array, k * 16); }
function setCol(mesh, k, hex, scale = 1) {
  C.setHex(hex).multiplyScalar(scale);
  C.toArray(mesh.instanceColor.array, k * 3);
}

function update(now, dt) {
  const t0 = performance.now();
  const phys = physics.length ? physics[instanceIdx % physics.length] : null;
  stats.instance = phys ? phys.name : null;
  const src = phys ? phys.msg : step;
  const n = src ? src.n : 0;
  if (n > capacity) { allocate(n); ghostGeometry(capacity); }
  const counts = { car: 0, bus: 0, bicycle: 0, pedestrian: 0 };
  for (const k of Object.keys(MODELS)) pickIds[k] = [];
  let nw = 0, nl = 0, ng = 0, nc = 0;
  const lit = { brake: 0, left: 0, right: 0 }; // vehicles drawn with brake lights / blinkers
  const blinkOn = (now % 700) < 350;
  for (let i = 0; i < n; i++) {
    const id = src.id[i];
    const cls = Math.min(src.cls[i], 5);
    const si = step ? step.index.get(id) : undefined;
    if (phys === null && (step.flags[i] & 1)) continue; // a person riding a vehicle
    const len = si !== undefined ? step.length[si] : [4.5, 4.5, 12, 1.8, 0.3, 5][cls];
    const wid = si !== undefined ? step.width[si] : [1.8, 1.8, 2.5, 0.65, 0.5, 2][cls];
    const sig = si !== undefined ? step.signals[si] : 0;
    const hdg = phys ? src.heading[i] : src.angle[i];
    const roll = phys ? src.roll[i] : 0, pitch = phys ? src.pitch[i] : 0;
    const steer = phys ? src.steer[i] : 0;
    const speed = src.speed[i];
    const a = hdg * DEG;
    const fx = src.x[i] - origin[0], fy = src.y[i] - origin[1];
    const cx = fx - Math.sin(a) * len / 2, cy = fy - Math.cos(a) * len / 2; // body centre
    const h = HEIGHT[cls];
    // Rigid pose: yaw -heading about +Y, pitch about the right axis, roll about forward.
    E.set(pitch * DEG, -a, -roll * DEG, 'YXZ');
    Q.setFromEuler(E);
    P.compose(V.set(cx, 0, -cy), Q, ONE);
    const model = MODEL_OF[cls];
    const mesh = MODELS[model].mesh;
    const k = counts[model]++;
    pickIds[model].push(id);
    // body
    S.makeScale(cls === 3 ? 0.3 : wid, h - (cls === 3 ? 0.9 : 0), len);
    S.setPosition(0, CLEARANCE[cls] + (h - (cls === 3 ? 0.9 : 0)) / 2 + (cls === 3 ? 0.9 : 0), 0);
    M.multiplyMatrices(P, S);
    setMat(mesh, k, M);
    setCol(mesh, k, CLASS_COLOURS[cls]);
    if (model === 'car') {
      // glasshouse: 55 % of the length, set back a little, 0.6 m high
      M.copy(P).multiply(T.makeTranslation(0, CLEARANCE[cls] + h + 0.3, len * 0.08));
      M.multiply(T.makeScale(wid * 0.9, 0.6, len * 0.55));
      setMat(cabins, nc++, M);
    }
    let ph = spin.get(id) || 0;
    if (cls === 4) {
      // Walking: two legs swinging with a stride of ~0.7 m.
      ph += speed * dt / 0.35;
      spin.set(id, ph);
      const swing = Math.min(speed, 2) * 0.35 * Math.sin(ph);
      for (const side of [-1, 1]) {
        // leg = pose x hip x swing x (half a leg down) x size: it pivots at the hip (0.8 m)
        M.copy(P).multiply(T.makeTranslation(side * 0.1, 0.8, 0));
        M.multiply(T.makeRotationX(side * swing));
        M.multiply(T.makeTranslation(0, -0.4, 0));
        M.multiply(T.makeScale(0.14, 0.8, 0.14));
        setMat(legs, nl++, M);
      }
    } else {
      // Wheels: front ones steered, all spinning with the speed.
      const r = WHEEL_R[cls];
      ph += speed * dt / r;
      spin.set(id, ph % (2 * Math.PI));
      const axleF = -len / 2 + Math.min(1.0, len * 0.2), axleR = len / 2 - Math.min(1.0, len * 0.2);
      const wheelsOf = cls === 3
        ? [[0, axleF, true], [0, axleR, false]]
        : [[-wid / 2 + 0.15, axleF, true], [wid / 2 - 0.15, axleF, true], [-wid / 2 + 0.15, axleR, false], [wid / 2 - 0.15, axleR, false]];
      for (const [wx, wz, front] of wheelsOf) {
        E.set(-ph, front ? steer * DEG : 0, 0, 'YXZ');
        Q.setFromEuler(E);
        M.compose(V.set(wx, r, wz), Q, V.clone().set(cls === 3 ? 0.06 : 0.25, r, r));
        M.premultiply(P);
        setMat(wheels, nw++, M);
      }
      if (cls !== 3) {
        // Lamps: rear pair brake (red) / blinkers, front pair blinkers (amber) else dim white.
        const brake = sig & SIG_BRAKE;
        if (brake) lit.brake++;
        if (sig & (SIG_LEFT | SIG_EMERGENCY)) lit.left++;
        if (sig & (SIG_RIGHT | SIG_EMERGENCY)) lit.right++;
        const left = (sig & (SIG_LEFT | SIG_EMERGENCY)) && blinkOn;
        const right = (sig & (SIG_RIGHT | SIG_EMERGENCY)) && blinkOn;
        const y = CLEARANCE[cls] + h * 0.45;
        for (const [lx, lz, isLeft, rear] of [[-wid / 2 + 0.2, len / 2 + 0.02, true, true], [wid / 2 - 0.2, len / 2 + 0.02, false, true],
          [-wid / 2 + 0.2, -len / 2 - 0.02, true, false], [wid / 2 - 0.2, -len / 2 - 0.02, false, false]]) {
          M.makeScale(0.3, 0.14, 0.06);
          M.setPosition(lx, y, lz);
          M.premultiply(P);
          const blink = isLeft ? left : right;
          const colour = blink ? 0xffa000 : rear ? (brake ? 0xff1a1a : 0x4a0000) : 0xcfd8dc;
          setMat(lamps, lampCount, M);
          setCol(lamps, lampCount, colour, blink || (rear && brake) ? 1.6 : 1);
          lampCount++;
        }
      }
    }
    if (follow && follow === id) lastCentre.set(cx, 0, -cy);
  }
  for (const [name, m] of Object.entries(MODELS)) {
    m.mesh.count = counts[name];
    m.mesh.instanceMatrix.needsUpdate = true;
    m.mesh.instanceColor.needsUpdate = true;
  }
  wheels.count = nw; wheels.instanceMatrix.needsUpdate = true;
  legs.count = nl; legs.instanceMatrix.needsUpdate = true;
  cabins.count = nc; cabins.instanceMatrix.needsUpdate = true;
  lamps.count = lampCount; lamps.instanceMatrix.needsUpdate = true; lamps.instanceColor.needsUpdate = true;
  lampCount = 0;
  // Ghost outlines of SUMO's footprints.
  if (step && showGhosts) {
    if (step.n * 24 > ghostPos.length) ghostGeometry(Math.max(capacity, step.n));
    for (let i = 0; i < step.n; i++) {
      const a = step.angle[i] * DEG, L = step.length[i], W = step.width[i];
      const dx = Math.sin(a), dy = Math.cos(a), lx = -dy, ly = dx;
      const fx = step.x[i] - origin[0], fy = step.y[i] - origin[1];
      const c = [[fx + lx * W / 2, fy + ly * W / 2], [fx - lx * W / 2, fy - ly * W / 2],
        [fx - lx * W / 2 - dx * L, fy - ly * W / 2 - dy * L], [fx + lx * W / 2 - dx * L, fy + ly * W / 2 - dy * L]];
      for (let e = 0; e < 4; e++) {
        const p = c[e], q = c[(e + 1) % 4];
        const o = (ng++) * 6;
        ghostPos[o] = p[0]; ghostPos[o + 1] = 0.08; ghostPos[o + 2] = -p[1];
        ghostPos[o + 3] = q[0]; ghostPos[o + 4] = 0.08; ghostPos[o + 5] = -q[1];
      }
    }
  }
  ghosts.geometry.setDrawRange(0, ng * 2);
  ghosts.geometry.attributes.position.needsUpdate = true;
  ghosts.visible = showGhosts;
  // Traffic-light heads in their state.
  if (tlsLamps && step && step.tls && step.tls.id) {
    const at = new Map(step.tls.id.map((id, k) => [id, k]));
    heads.forEach((hd, k) => {
      const j = at.get(hd.tls);
      const letter = j === undefined ? '' : (step.tls.state[j] || '')[hd.link];
      setCol(tlsLamps, k, TLS_COLOURS[letter] || 0x333333);
    });
    tlsLamps.instanceColor.needsUpdate = true;
  }
  stats.agents = step ? step.n : 0;
  stats.physicsAgents = phys ? n : 0;
  stats.ghosts = showGhosts ? ng / 4 : 0;
  stats.instances = { ...counts, wheels: nw, lamps: lamps.count, legs: legs.count, cabins: nc };
  stats.signalled = lit;
  stats.updateMs = performance.now() - t0;
  // Follow camera: move target and camera with the agent.
  if (follow) {
    const d = lastCentre.clone().sub(controls.target);
    controls.target.add(d);
    camera.position.add(d);
  }
}
let lampCount = 0;

// ------------------------------------------------------------------ picking + keys
const ray = new THREE.Raycaster();
function pickAt(clientX, clientY) {
  const r = renderer.domElement.getBoundingClientRect();
  camera.updateMatrixWorld();
  ray.setFromCamera(new THREE.Vector2(((clientX - r.left) / r.width) * 2 - 1, -((clientY - r.top) / r.height) * 2 + 1), camera);
  for (const b of bodies) { b.boundingSphere = null; b.boundingBox = null; } // instances moved since
  return ray.intersectObjects(bodies, false)[0];
}
let downAt = null;
renderer.domElement.addEventListener('pointerdown', (e) => { downAt = [e.clientX, e.clientY]; });
renderer.domElement.addEventListener('pointerup', (e) => {
  stats.clicks = (stats.clicks || 0) + 1;
  if (!downAt || Math.hypot(e.clientX - downAt[0], e.clientY - downAt[1]) > 4) return; // a drag, not a click
  const hit = pickAt(e.clientX, e.clientY);
  stats.lastPick = hit ? `${hit.object.name}#${hit.instanceId}` : `miss at ${e.clientX},${e.clientY}`;
  if (hit && hit.instanceId !== undefined) {
    follow = pickIds[hit.object.name][hit.instanceId] || null;
    userMoved = true;
  } else {
    follow = null;
  }
  stats.follow = follow;
  $('hud-follow').textContent = follow ? `following ${follow} (esc: orbit)` : 'orbit';
});
window.addEventListener('keydown', (e) => {
  if (e.key === 'Escape') { follow = null; stats.follow = null; $('hud-follow').textContent = 'orbit'; }
  if (e.key === 'f') { userMoved = false; fit(); }
  if (e.key === 'i') instanceIdx++;
  if (e.key === 'g') showGhosts = !showGhosts;
  if (e.key === ' ') { paused = !paused; stats.paused = paused; }
});
window.addEventListener('resize', () => {
  renderer.setSize(host.clientWidth, host.clientHeight);
  camera.aspect = host.clientWidth / host.clientHeight;
  camera.updateProjectionMatrix();
});

// ------------------------------------------------------------------ HUD
function hudConn() {
  const el = $('hud-conn');
  if (!stats.connected) { el.textContent = 'disconnected'; el.className = 'conn bad'; return; }
  if (stats.sumoAlive === false) { el.textContent = 'SUMO side gone'; el.className = 'conn bad'; return; }
  el.textContent = 'live';
  el.className = 'conn ok';
}

const frameTimes = [];
let lastHud = 0;
function updateHud(now) {
  while (frameTimes.length && now - frameTimes[0] > 2000) frameTimes.shift();
  stats.fps = frameTimes.length > 1 ? (frameTimes.length - 1) / ((frameTimes[frameTimes.length - 1] - frameTimes[0]) / 1000) : 0;
  if (now - lastHud < 250) return;
  lastHud = now;
  if (stepHist.length > 1) {
    const [w0, t0] = stepHist[0], [w1, t1] = stepHist[stepHist.length - 1];
    stats.rtf = w1 > w0 ? (t1 - t0) / ((w1 - w0) / 1000) : 0;
  }
  hudConn();
  if (step) {
    stats.step = step.step;
    stats.simTime = step.t;
    $('hud-time').textContent = `${step.t.toFixed(1)} s`;
    $('hud-step').textContent = `${step.step}  (dt ${step.dt} s)`;
    $('hud-agents').textContent = `${step.n}`;
  }
  $('hud-rtf').textContent = `${stats.rtf.toFixed(2)}×`;
  $('hud-physics').textContent = physics.length
    ? `${stats.instance} (${physics.map((p) => p.name).join(', ')}; i: switch)` : 'none: SUMO poses';
  $('hud-fps').textContent = `${stats.fps.toFixed(0)} fps, ${stats.drawCalls} draw calls, ${(stats.triangles / 1000).toFixed(0)}k triangles`;
}

// ------------------------------------------------------------------ main loop
let lastNow = performance.now();
let paused = false; // space: hold the picture (frames keep arriving; only the newest is kept)
function frame(now) {
  const dt = Math.min((now - lastNow) / 1000, 0.2);
  lastNow = now;
  try {
    if (pendingFrame && !paused) consumeFrame(now);
    update(now, paused ? 0 : dt);
    controls.update();
    const t0 = performance.now();
    renderer.render(scene, camera);
    stats.renderMs = performance.now() - t0;
    stats.drawCalls = renderer.info.render.calls;
    stats.triangles = renderer.info.render.triangles;
    stats.renders++;
    frameTimes.push(now);
  } catch (e) {
    fail(e);
  }
  updateHud(now);
  requestAnimationFrame(frame);
}

// Exposed for tests and the console.
stats.fit = () => { userMoved = false; fit(); };
stats.follow_ = (id) => { follow = id; stats.follow = id; userMoved = true; };
stats.setAgentsVisible = (v) => { for (const m of [...bodies, wheels, lamps, legs, cabins]) m.visible = v; ghosts.visible = v && showGhosts; };
stats.sceneSummary = () => {
  const out = { meshes: 0, instanced: {} };
  scene.traverse((o) => {
    if (o.isInstancedMesh) out.instanced[o.name] = o.count;
    else if (o.isMesh) out.meshes++;
  });
  return out;
};
// CSS-pixel position of an agent's body centre (null when unknown or behind the camera).
stats.screenOf = (id) => {
  if (!step) return null;
  const i = step.index.get(id);
  if (i === undefined) return null;
  const a = step.angle[i] * DEG, L = step.length[i];
  const p = new THREE.Vector3(step.x[i] - origin[0] - Math.sin(a) * L / 2, 0.8, -(step.y[i] - origin[1] - Math.cos(a) * L / 2));
  camera.updateMatrixWorld();
  p.project(camera);
  if (p.z > 1) return null;
  const r = renderer.domElement.getBoundingClientRect();
  return [(p.x + 1) / 2 * r.width, (1 - p.y) / 2 * r.height];
};
// Every agent in view: [{id, len, p: [x, y] CSS pixels}].
stats.onScreen = () => {
  const out = [];
  if (!step) return out;
  for (let i = 0; i < step.n; i++) {
    const p = stats.screenOf(step.id[i]);
    if (p && p[0] >= 0 && p[1] >= 0 && p[0] <= renderer.domElement.clientWidth && p[1] <= renderer.domElement.clientHeight) {
      out.push({ id: step.id[i], len: step.length[i], p });
    }
  }
  return out;
};
stats.pause = (on) => { paused = !!on; stats.paused = paused; };
stats.pickAt = (x, y) => { const h = pickAt(x, y); return h ? `${h.object.name}#${h.instanceId}` : null; };
stats.lookAtAgent = (id, dist) => {
  const i = step ? step.index.get(id) : undefined;
  if (i === undefined) return false;
  stats.lookAt(step.x[i], step.y[i], dist);
  return true;
};
stats.lookAt = (x, y, dist) => {
  const c = new THREE.Vector3(x - origin[0], 0, -(y - origin[1]));
  controls.target.copy(c);
  camera.position.set(c.x + dist * 0.35, dist * 0.8, c.z + dist * 0.6);
  userMoved = true;
  controls.update();
};

connect();
requestAnimationFrame(frame);
