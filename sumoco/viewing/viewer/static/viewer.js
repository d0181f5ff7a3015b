// sumoco live viewer: draws a run from above on a <canvas>.
//
// The server (sumoco/viewer/server.py) sends msgpack envelopes over a WebSocket:
// hello, static (raw static-data message inside a bin) and frames (raw step message and
// raw physics state per instance inside bins). Everything is decoded here with a small
// msgpack reader; per-agent columns become typed arrays without copying where aligned.
// Only the newest frame is decoded and drawn, once per animation frame.
(() => {
  'use strict';

  const { unpack, column, polyline, readStep, readPhysics, setStatic, vtypeTable } = window.sumocoDecode;

  // ------------------------------------------------------------------ network layers
  const LANE_STYLE = {
    road: { fill: '#464c55', marking: '#9aa1ab' },
    internal: { fill: '#4a5059', marking: null },
    ped: { fill: '#5b554c', marking: null },
    bike: { fill: '#5a4444', marking: null },
  };

  function laneKind(id, allow) {
    if (allow && allow.length) {
      if (allow.every((c) => c === 'pedestrian')) return 'ped';
      if (allow.every((c) => c === 'bicycle')) return 'bike';
    }
    return id.charCodeAt(0) === 58 /* ':' */ ? 'internal' : 'road';
  }

  function buildNetwork(d) {
    if (d.kind !== 'static') throw new Error('expected static data, got ' + d.kind);
    const L = d.lanes;
    const nl = L.n | 0;
    const width = column(L.width, Float32Array, nl, 'lanes.width');
    const shape = polyline(L.shape, nl, 'lanes.shape');
    const groups = new Map(); // "kind|width" -> {kind, width, path}
    let xmin = Infinity, ymin = Infinity, xmax = -Infinity, ymax = -Infinity;
    let lanesDrawn = 0;
    for (let i = 0; i < nl; i++) {
      const a = shape.off[i], b = shape.off[i + 1];
      if (b - a < 2) continue;
      const kind = laneKind(L.id[i], L.allow ? L.allow[i] : null);
      const w = Math.round(width[i] * 20) / 20; // group lanes of (nearly) equal width
      const key = kind + '|' + w;
      let g = groups.get(key);
      if (!g) groups.set(key, (g = { kind, width: w, path: new Path2D() }));
      const xy = shape.xy;
      g.path.moveTo(xy[2 * a], xy[2 * a + 1]);
      for (let j = a; j < b; j++) {
        const x = xy[2 * j], y = xy[2 * j + 1];
        if (j > a) g.path.lineTo(x, y);
        if (x < xmin) xmin = x; if (x > xmax) xmax = x;
        if (y < ymin) ymin = y; if (y > ymax) ymax = y;
      }
      lanesDrawn++;
    }
    const J = d.junctions;
    const nj = J.n | 0;
    const jshape = polyline(J.shape, nj, 'junctions.shape');
    const junctions = new Path2D();
    const centre = new Map();
    for (let i = 0; i < nj; i++) {
      const a = jshape.off[i], b = jshape.off[i + 1];
      if (b - a < 3) continue;
      let sx = 0, sy = 0;
      for (let j = a; j < b; j++) {
        const x = jshape.xy[2 * j], y = jshape.xy[2 * j + 1];
        if (j === a) junctions.moveTo(x, y); else junctions.lineTo(x, y);
        sx += x; sy += y;
      }
      junctions.closePath();
      centre.set(J.id[i], [sx / (b - a), sy / (b - a)]);
    }
    const order = { road: 0, internal: 1, bike: 2, ped: 3 };
    const layers = [...groups.values()].sort((p, q) => order[p.kind] - order[q.kind]);
    let bounds = d.net && d.net.bounds;
    if (!bounds || !(bounds[2] > bounds[0] && bounds[3] > bounds[1])) {
      bounds = xmax > xmin ? [xmin, ymin, xmax, ymax] : null;
    }
    const laneIds = L.id;
    // Signal heads (protocol 1.1 tls_links): a bar across the end of each controlled lane.
    const heads = [];
    const T = d.tls_links;
    if (T && (T.n | 0) > 0) {
      const nt = T.n | 0;
      const tl = column(T.tls, Uint16Array, nt, 'tls_links.tls');
      const lk = column(T.link, Uint16Array, nt, 'tls_links.link');
      const fr = column(T.from_lane, Int32Array, nt, 'tls_links.from_lane');
      const seen = new Set();
      for (let r = 0; r < nt; r++) {
        const i = fr[r];
        const key = tl[r] + '|' + lk[r] + '|' + i;
        if (i < 0 || i >= nl || seen.has(key)) continue;
        seen.add(key);
        const a = shape.off[i], b = shape.off[i + 1];
        if (b - a < 2) continue;
        const x1 = shape.xy[2 * (b - 1)], y1 = shape.xy[2 * (b - 1) + 1];
        const x0 = shape.xy[2 * (b - 2)], y0 = shape.xy[2 * (b - 2) + 1];
        const len = Math.hypot(x1 - x0, y1 - y0) || 1;
        // unit normal to the lane's last segment, half a lane wide
        const nx = -(y1 - y0) / len * width[i] * 0.45, ny = (x1 - x0) / len * width[i] * 0.45;
        heads.push({ tls: tl[r], link: lk[r], ax: x1 - nx, ay: y1 - ny, bx: x1 + nx, by: y1 + ny });
      }
    }
    return {
      run: d.run, layers, junctions, centre, bounds, laneIds, lanesDrawn,
      junctionsDrawn: centre.size, tlsIds: d.tls || [], heads,
    };
  }

  // ------------------------------------------------------------------ state
  const CLASS_NAMES = ['passenger', 'taxi', 'bus', 'bicycle', 'pedestrian', 'other'];
  const CLASS_COLOURS = ['#4fc3f7', '#fff176', '#81c784', '#ce93d8', '#f48fb1', '#e0e0e0'];
  const DEFAULT_SIZE = [[4.5, 1.8], [4.5, 1.8], [12, 2.5], [1.8, 0.65], [0.3, 0.5], [5, 2]];
  const MODE_NAMES = ['physical', 'kinematic', 'external', 'stopping'];
  const PHYS_COLOURS = ['#ff9800', '#e040fb', '#c6ff00', '#ffffff', '#ff6e40', '#18ffff'];
  const TLS_COLOURS = {
    r: '#e53935', R: '#e53935', y: '#ffb300', Y: '#ffb300', g: '#2e7d32', G: '#00e676',
    s: '#9ccc65', u: '#ff7043', o: '#fdd835', O: '#9e9e9e',
  };
  const DEG = Math.PI / 180;

  const stats = {
    connected: false, hello: null, staticLoaded: false, staticSv: null, staticReceived: 0,
    framesReceived: 0, framesDrawn: 0,
    draws: 0, decodeErrors: 0, lastError: '', agentsDrawn: 0, physicsDrawn: 0,
    lookaheadDrawn: 0, lanesDrawn: 0, junctionsDrawn: 0, tlsDrawn: 0,
    step: -1, simTime: NaN, stepHz: 0, frameHz: 0, drawMs: 0, sumoAlive: null,
  };
  window.sumocoViewer = stats;

  const canvas = document.getElementById('view');
  const ctx = canvas.getContext('2d', { alpha: false });
  const tooltip = document.getElementById('tooltip');
  const $ = (id) => document.getElementById(id);

  let net = null; // buildNetwork() result
  let step = null; // readStep() result of the newest frame drawn
  let physics = []; // [{name, colour, msg}]
  const physColour = new Map(); // instance -> colour, stable for the session
  let pendingFrame = null; // newest undecoded frame envelope
  let dirty = true;
  const view = { cx: 0, cy: 0, s: 2, fitted: false, user: false };
  let cssW = 1, cssH = 1, dpr = 1;
  let showPaths = false;
  let mouse = null; // {x, y} css px within the canvas, null when outside
  let drag = null;
  let hoverDirty = false;
  const stepHist = []; // [wall ms, step] for the step rate
  const frameHist = []; // wall ms of drawn frames

  function resize() {
    dpr = window.devicePixelRatio || 1;
    cssW = canvas.clientWidth || window.innerWidth;
    cssH = canvas.clientHeight || window.innerHeight;
    canvas.width = Math.max(1, Math.round(cssW * dpr));
    canvas.height = Math.max(1, Math.round(cssH * dpr));
    dirty = true;
  }

  function fitTo(b) {
    if (!b) return false;
    const w = Math.max(b[2] - b[0], 10), h = Math.max(b[3] - b[1], 10);
    // On a wide screen keep the network clear of the HUD panel on the left.
    const hud = document.getElementById('hud');
    const left = hud && cssW - hud.offsetWidth - 16 > 0.55 * cssW ? hud.offsetWidth + 16 : 0;
    view.s = Math.min((cssW - left) / w, cssH / h) * 0.92;
    view.cx = (b[0] + b[2]) / 2 - left / 2 / view.s;
    view.cy = (b[1] + b[3]) / 2;
    view.fitted = true;
    dirty = true;
    return true;
  }

  function agentBounds() {
    if (!step || step.n === 0) return null;
    let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
    for (let i = 0; i < step.n; i++) {
      const x = step.x[i], y = step.y[i];
      if (x < x0) x0 = x; if (x > x1) x1 = x; if (y < y0) y0 = y; if (y > y1) y1 = y;
    }
    return [x0 - 20, y0 - 20, x1 + 20, y1 + 20];
  }

  function fit() {
    fitTo((net && net.bounds) || agentBounds());
  }

  const toWorld = (px, py) => [view.cx + (px - cssW / 2) / view.s, view.cy - (py - cssH / 2) / view.s];
  const toScreen = (x, y) => [(x - view.cx) * view.s + cssW / 2, cssH / 2 - (y - view.cy) * view.s];

  // ------------------------------------------------------------------ WebSocket
  let ws = null;
  let retryMs = 500;

  function connect() {
    const token = new URLSearchParams(location.search).get('token') || '';
    const url = (location.protocol === 'https:' ? 'wss://' : 'ws://') + location.host + '/ws?token=' +
      encodeURIComponent(token);
    ws = new WebSocket(url);
    ws.binaryType = 'arraybuffer';
    ws.onopen = () => { stats.connected = true; retryMs = 500; hudConn(); };
    ws.onclose = () => {
      stats.connected = false;
      hudConn();
      setTimeout(connect, retryMs);
      retryMs = Math.min(retryMs * 2, 5000);
    };
    ws.onmessage = (ev) => {
      let env;
      try {
        env = unpack(new Uint8Array(ev.data)); // cheap: bins stay views into ev.data
      } catch (e) {
        return fail(e);
      }
      if (env.type === 'frame') {
        stats.framesReceived++;
        pendingFrame = env; // replaces an undrawn one: only the newest is ever decoded
      } else if (env.type === 'static') {
        // Sent on connect and again for every new static version (a vType change, new tls
        // links): the vType table and the signal heads are rebuilt from it.
        try {
          const d = unpack(env.static);
          const next = buildNetwork(d);
          stats.staticSv = setStatic(d);
          const moved = !net || String(net.bounds) !== String(next.bounds);
          net = next;
          stats.staticLoaded = true;
          stats.staticReceived++;
          stats.lanesDrawn = net.lanesDrawn;
          stats.junctionsDrawn = net.junctionsDrawn;
          if (moved && !view.user) fit(); // the same network under a new version keeps the view
          hoverDirty = true;
          dirty = true;
        } catch (e) {
          fail(e);
        }
      } else if (env.type === 'hello') {
        stats.hello = { run: env.run, root: env.root, max_hz: env.max_hz };
        $('hud-run').textContent = env.run ? `run ${env.run}` : '';
      }
    };
  }

  function fail(e) {
    stats.decodeErrors++;
    stats.lastError = String(e && e.message ? e.message : e);
    console.warn('sumoco viewer:', stats.lastError);
  }

  function consumeFrame(now) {
    const env = pendingFrame;
    pendingFrame = null;
    try {
      if (env.step) {
        const s = readStep(unpack(env.step));
        if (step && s.step < step.step) stepHist.length = 0; // SUMO restarted
        step = s;
        if (stepHist.length === 0 || stepHist[stepHist.length - 1][1] !== s.step) stepHist.push([now, s.step]);
      }
      const next = [];
      const phys = env.physics || {};
      for (const name of Object.keys(phys).sort()) {
        if (!physColour.has(name)) physColour.set(name, PHYS_COLOURS[physColour.size % PHYS_COLOURS.length]);
        next.push({ name, colour: physColour.get(name), msg: readPhysics(unpack(phys[name])) });
      }
      physics = next;
      stats.sumoAlive = env.sumo_alive;
    } catch (e) {
      return fail(e);
    }
    frameHist.push(now);
    stats.framesDrawn++;
    if (!view.fitted && !view.user) fit();
    hoverDirty = true;
    dirty = true;
  }

  function rate(hist, now, windowMs, value) {
    while (hist.length && now - (value ? hist[0][0] : hist[0]) > windowMs) hist.shift();
    if (hist.length < 2) return 0;
    const first = hist[0], last = hist[hist.length - 1];
    const dt = ((value ? last[0] : last) - (value ? first[0] : first)) / 1000;
    if (dt <= 0) return 0;
    return value ? (last[1] - first[1]) / dt : (hist.length - 1) / dt;
  }

  // ------------------------------------------------------------------ drawing
  // Appends a vehicle outline with a chamfered nose. (fx, fy) = front-bumper centre,
  // heading deg clockwise from north (SUMO): the body lies `len` behind the front.
  function footprint(c, fx, fy, heading, len, wid) {
    const a = heading * DEG;
    const dx = Math.sin(a), dy = Math.cos(a); // unit heading (east, north)
    const lx = -dy, ly = dx; // unit left
    const hw = wid / 2;
    const nose = Math.min(0.22 * len, hw * 0.8);
    const rx = fx - len * dx, ry = fy - len * dy;
    const nx = fx - nose * dx, ny = fy - nose * dy;
    c.moveTo(rx + hw * lx, ry + hw * ly);
    c.lineTo(nx + hw * lx, ny + hw * ly);
    c.lineTo(fx + 0.55 * hw * lx, fy + 0.55 * hw * ly);
    c.lineTo(fx - 0.55 * hw * lx, fy - 0.55 * hw * ly);
    c.lineTo(nx - hw * lx, ny - hw * ly);
    c.lineTo(rx - hw * lx, ry - hw * ly);
    c.closePath();
  }

  function sizeOf(id, cls) {
    if (step) {
      if (!step.index) step.index = new Map(step.id.map((k, i) => [k, i]));
      const i = step.index.get(id);
      if (i !== undefined) return [step.length[i], step.width[i]];
    }
    return DEFAULT_SIZE[cls] || DEFAULT_SIZE[5];
  }

  function draw() {
    const t0 = performance.now();
    const s = view.s;
    const minLen = 4 / s, minWid = 2.5 / s; // keep agents visible when zoomed out
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.fillStyle = '#1b1f24';
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    // World transform: x east, y north (flipped), metres -> device pixels.
    ctx.setTransform(dpr * s, 0, 0, -dpr * s, dpr * (cssW / 2 - view.cx * s), dpr * (cssH / 2 + view.cy * s));
    ctx.lineCap = 'butt';
    ctx.lineJoin = 'round';
    if (net) {
      ctx.fillStyle = '#3c424a';
      ctx.fill(net.junctions);
      for (const g of net.layers) { // lane markings first: a wider light stroke under the asphalt
        const st = LANE_STYLE[g.kind];
        if (!st.marking) continue;
        ctx.strokeStyle = st.marking;
        ctx.lineWidth = g.width;
        ctx.stroke(g.path);
      }
      for (const g of net.layers) {
        const st = LANE_STYLE[g.kind];
        ctx.strokeStyle = st.fill;
        ctx.lineWidth = st.marking ? Math.max(g.width - 0.3, g.width * 0.85) : g.width;
        ctx.stroke(g.path);
      }
    }
    let agents = 0, phys = 0, las = 0;
    if (step && showPaths && step.path) {
      ctx.beginPath();
      const { off, xy } = step.path;
      for (let i = 0; i < step.n; i++) {
        for (let j = off[i]; j < off[i + 1]; j++) {
          if (j === off[i]) ctx.moveTo(xy[2 * j], xy[2 * j + 1]); else ctx.lineTo(xy[2 * j], xy[2 * j + 1]);
        }
      }
      ctx.strokeStyle = 'rgba(255,255,255,0.35)';
      ctx.lineWidth = 1 / s;
      ctx.stroke();
    }
    // Physics actual: filled, one colour per instance, under the SUMO outlines.
    for (const p of physics) {
      const m = p.msg;
      ctx.beginPath();
      for (let i = 0; i < m.n; i++) {
        const [len, wid] = sizeOf(m.id[i], m.cls[i]);
        footprint(ctx, m.x[i], m.y[i], m.heading[i], Math.max(len, minLen), Math.max(wid, minWid));
      }
      ctx.globalAlpha = 0.85;
      ctx.fillStyle = p.colour;
      ctx.fill();
      ctx.globalAlpha = 1;
      phys += m.n;
    }
    if (step) {
      const n = step.n;
      // SUMO reference: outline in the class colour (faint fill so lone agents read as solid).
      for (let c = 0; c < CLASS_COLOURS.length; c++) {
        let any = false;
        ctx.beginPath();
        for (let i = 0; i < n; i++) {
          const ci = step.cls[i] < CLASS_COLOURS.length ? step.cls[i] : 5;
          if (ci !== c) continue;
          any = true;
          footprint(ctx, step.x[i], step.y[i], step.angle[i], Math.max(step.length[i], minLen),
            Math.max(step.width[i], minWid));
        }
        if (!any) continue;
        ctx.fillStyle = CLASS_COLOURS[c];
        ctx.globalAlpha = physics.length ? 0.12 : 0.3;
        ctx.fill();
        ctx.globalAlpha = 1;
        ctx.strokeStyle = CLASS_COLOURS[c];
        ctx.lineWidth = 1.5 / s;
        ctx.stroke();
      }
      agents = n;
      // Ego vehicles: thick white outline.
      ctx.beginPath();
      let ego = false;
      for (let i = 0; i < n; i++) {
        if (!(step.flags[i] & 2)) continue;
        ego = true;
        footprint(ctx, step.x[i], step.y[i], step.angle[i], Math.max(step.length[i], minLen), Math.max(step.width[i], minWid));
      }
      if (ego) { ctx.strokeStyle = '#ffffff'; ctx.lineWidth = 3 / s; ctx.stroke(); }
      // Look-ahead points: the paper's red spheres.
      const r = Math.max(0.45, 1.8 / s);
      ctx.beginPath();
      for (let i = 0; i < n; i++) {
        if (step.flags[i] & 1) continue; // a person riding a vehicle has no look-ahead of its own
        const x = step.la_x[i], y = step.la_y[i];
        ctx.moveTo(x + r, y);
        ctx.arc(x, y, r, 0, 2 * Math.PI);
        las++;
      }
      ctx.fillStyle = '#ff1744';
      ctx.fill();
    }
    // Screen-space overlays: traffic lights, labels, hover highlight.
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    stats.tlsDrawn = drawTls();
    if (step && s > 9) drawLabels();
    if (hover) drawHover();
    stats.agentsDrawn = agents;
    stats.physicsDrawn = phys;
    stats.lookaheadDrawn = las;
    stats.draws++;
    stats.drawMs = performance.now() - t0;
  }

  // Signal heads at the end of every controlled lane when the static data maps links to
  // lanes (protocol >= 1.1); otherwise one marker per light at its junction: a row of
  // squares, one per link in the order of SUMO's state string, coloured by its letter.
  function drawTls() {
    if (!step || !net || !step.tls || !step.tls.id) return 0;
    const ids = step.tls.id, states = step.tls.state;
    if (net.heads && net.heads.length) {
      const at = new Map(ids.map((id, k) => [id, k]));
      ctx.lineWidth = Math.max(2, 0.8 * view.s);
      ctx.lineCap = 'butt';
      let drawn = 0;
      for (const h of net.heads) {
        const k = at.get(net.tlsIds[h.tls]);
        if (k === undefined) continue;
        const letter = (states[k] || '')[h.link];
        const [ax, ay] = toScreen(h.ax, h.ay);
        const [bx, by] = toScreen(h.bx, h.by);
        ctx.strokeStyle = TLS_COLOURS[letter] || '#9e9e9e';
        ctx.beginPath();
        ctx.moveTo(ax, ay);
        ctx.lineTo(bx, by);
        ctx.stroke();
        drawn++;
      }
      return drawn;
    }
    const box = Math.min(14, Math.max(5, 1.4 * view.s));
    let drawn = 0;
    for (let k = 0; k < ids.length; k++) {
      const c = net.centre.get(ids[k]);
      if (!c) continue;
      const st = states[k] || '';
      const [px, py] = toScreen(c[0], c[1]);
      const perRow = Math.min(st.length, 8) || 1;
      const rows = Math.ceil(st.length / perRow);
      const w = perRow * box, h = rows * box;
      if (px + w < 0 || px - w > cssW || py + h < 0 || py - h > cssH) continue;
      const x0 = px - w / 2, y0 = py - h / 2;
      ctx.fillStyle = 'rgba(0,0,0,0.75)';
      ctx.fillRect(x0 - 2, y0 - 2, w + 4, h + 4);
      for (let j = 0; j < st.length; j++) {
        ctx.fillStyle = TLS_COLOURS[st[j]] || '#9e9e9e';
        ctx.fillRect(x0 + (j % perRow) * box + 1, y0 + Math.floor(j / perRow) * box + 1, box - 2, box - 2);
      }
      drawn++;
    }
    return drawn;
  }

  function drawLabels() {
    ctx.font = '11px system-ui, sans-serif';
    ctx.fillStyle = '#ffffff';
    ctx.textAlign = 'center';
    ctx.textBaseline = 'middle';
    const n = Math.min(step.n, 2000);
    for (let i = 0; i < n; i++) {
      const a = step.angle[i] * DEG, half = step.length[i] / 2;
      const [px, py] = toScreen(step.x[i] - half * Math.sin(a), step.y[i] - half * Math.cos(a));
      if (px < -50 || py < -20 || px > cssW + 50 || py > cssH + 20) continue;
      ctx.fillText(step.id[i], px, py - 0.6 * step.width[i] * view.s - 6);
    }
  }

  // ------------------------------------------------------------------ hover
  let hover = null; // {kind, i, inst}

  function inside(wx, wy, fx, fy, heading, len, wid, pad) {
    const a = heading * DEG;
    const dx = Math.sin(a), dy = Math.cos(a);
    const vx = wx - fx, vy = wy - fy;
    const along = vx * dx + vy * dy; // 0 at the front bumper, -len at the rear
    const lat = -vx * dy + vy * dx;
    if (along > pad || along < -len - pad || Math.abs(lat) > wid / 2 + pad) return Infinity;
    return Math.abs(along + len / 2) + Math.abs(lat);
  }

  function findHover() {
    if (!mouse || drag) return null;
    const [wx, wy] = toWorld(mouse.x, mouse.y);
    const pad = 3 / view.s;
    let best = null, bestD = Infinity;
    if (step) {
      for (let i = 0; i < step.n; i++) {
        const d = inside(wx, wy, step.x[i], step.y[i], step.angle[i], Math.max(step.length[i], 4 / view.s),
          Math.max(step.width[i], 2.5 / view.s), pad);
        if (d < bestD) { bestD = d; best = { kind: 'sumo', i }; }
      }
    }
    for (const p of physics) {
      const m = p.msg;
      for (let i = 0; i < m.n; i++) {
        const [len, wid] = sizeOf(m.id[i], m.cls[i]);
        const d = inside(wx, wy, m.x[i], m.y[i], m.heading[i], Math.max(len, 4 / view.s), Math.max(wid, 2.5 / view.s), pad);
        if (d < bestD) { bestD = d; best = { kind: 'physics', i, inst: p.name }; }
      }
    }
    return best;
  }

  const f1 = (v) => (Number.isFinite(v) ? v.toFixed(1) : '–');
  const f2 = (v) => (Number.isFinite(v) ? v.toFixed(2) : '–');

  // [vType id, vClass] of agent i of the newest step, from the table of the step's static
  // version (the static data may have brought it after the step was decoded), else undefined.
  function vtypeOf(i) {
    const table = vtypeTable(step.sv) || step.vtypes;
    const vt = table[step.vtype[i]];
    return vt && vt[0] ? vt : undefined; // a dropped row is ["", ""]
  }

  function hoverText(h) {
    let id, cls;
    if (h.kind === 'sumo') { id = step.id[h.i]; cls = step.cls[h.i]; } else {
      const p = physics.find((q) => q.name === h.inst);
      id = p.msg.id[h.i]; cls = p.msg.cls[h.i];
    }
    const lines = [];
    const si = step ? (step.index || (step.index = new Map(step.id.map((k, i) => [k, i])))).get(id) : undefined;
    let type = CLASS_NAMES[cls] || 'other';
    if (si !== undefined) {
      const vt = vtypeOf(si);
      if (vt) type = `${vt[0]} (${vt[1]})`;
    }
    lines.push(`${id}`);
    lines.push(`type   ${type}`);
    if (si !== undefined) {
      const lane = step.lane[si];
      const laneName = lane >= 0 && net && net.laneIds[lane] !== undefined ? net.laneIds[lane] : lane >= 0 ? `#${lane}` : '–';
      const fl = step.flags[si];
      const flags = [fl & 1 ? 'inside-vehicle' : '', fl & 2 ? 'ego' : '', fl & 4 ? 'jumped' : '', fl & 8 ? 'new' : '']
        .filter(Boolean).join(' ');
      lines.push(`SUMO   x ${f1(step.x[si])}  y ${f1(step.y[si])}  ${f1(step.angle[si])}°`);
      lines.push(`       v ${f1(step.speed[si])} m/s  a ${f1(step.accel[si])} m/s²  ${step.length[si].toFixed(1)}×${step.width[si].toFixed(1)} m`);
      lines.push(`lane   ${laneName}${flags ? '  [' + flags + ']' : ''}`);
    }
    for (const p of physics) {
      const m = p.msg;
      const j = m.id.indexOf(id);
      if (j < 0) continue;
      lines.push(`${p.name.padEnd(6)} ${MODE_NAMES[m.mode[j]] || m.mode[j]}  v ${f1(m.speed[j])}  err lon ${f2(m.err_lon[j])} lat ${f2(m.err_lat[j])} m`);
    }
    return lines.join('\n');
  }

  function drawHover() {
    let fx, fy, hd, len, wid;
    if (hover.kind === 'sumo') {
      if (!step || hover.i >= step.n) return;
      const i = hover.i;
      [fx, fy, hd, len, wid] = [step.x[i], step.y[i], step.angle[i], step.length[i], step.width[i]];
    } else {
      const p = physics.find((q) => q.name === hover.inst);
      if (!p || hover.i >= p.msg.n) return;
      const m = p.msg, i = hover.i;
      [len, wid] = sizeOf(m.id[i], m.cls[i]);
      [fx, fy, hd] = [m.x[i], m.y[i], m.heading[i]];
    }
    const s = view.s;
    ctx.setTransform(dpr * s, 0, 0, -dpr * s, dpr * (cssW / 2 - view.cx * s), dpr * (cssH / 2 + view.cy * s));
    ctx.beginPath();
    footprint(ctx, fx, fy, hd, Math.max(len, 4 / s), Math.max(wid, 2.5 / s));
    ctx.strokeStyle = '#ffffff';
    ctx.lineWidth = 2.5 / s;
    ctx.stroke();
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  }

  function updateTooltip() {
    hover = findHover();
    if (!hover) { tooltip.hidden = true; return; }
    tooltip.textContent = hoverText(hover);
    tooltip.hidden = false;
    const x = Math.min(mouse.x + 14, cssW - tooltip.offsetWidth - 4);
    const y = Math.min(mouse.y + 14, cssH - tooltip.offsetHeight - 4);
    tooltip.style.left = x + 'px';
    tooltip.style.top = y + 'px';
  }

  // ------------------------------------------------------------------ HUD
  function hudConn() {
    const el = $('hud-conn');
    if (!stats.connected) { el.textContent = 'disconnected'; el.className = 'conn bad'; return; }
    if (stats.sumoAlive === false) { el.textContent = 'SUMO side gone'; el.className = 'conn bad'; return; }
    el.textContent = stats.staticLoaded ? 'live' : 'live, no static data yet';
    el.className = 'conn ok';
  }

  function esc(s) {
    return String(s).replace(/[&<>"]/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;' })[c]);
  }

  let lastHud = 0;
  function updateHud(now) {
    if (now - lastHud < 250) return;
    lastHud = now;
    stats.stepHz = rate(stepHist, now, 3000, true);
    stats.frameHz = rate(frameHist, now, 3000, false);
    hudConn();
    if (step) {
      stats.step = step.step;
      stats.simTime = step.t;
      $('hud-time').textContent = `${step.t.toFixed(1)} s`;
      $('hud-step').textContent = `${step.step}  (dt ${step.dt} s)`;
      let ego = 0;
      const perCls = new Array(CLASS_NAMES.length).fill(0);
      for (let i = 0; i < step.n; i++) {
        perCls[Math.min(step.cls[i], 5)]++;
        if (step.flags[i] & 2) ego++;
      }
      $('hud-agents').textContent = `${step.n}` + (ego ? `  (${ego} ego)` : '');
      $('hud-legend').innerHTML =
        CLASS_NAMES.map((c, k) => (perCls[k] ? `<span><i class="sw outline" style="border-color:${CLASS_COLOURS[k]}"></i>${c} ${perCls[k]}</span>` : ''))
          .join('') +
        physics.map((p) => `<span><i class="sw" style="background:${p.colour}"></i>${esc(p.name)}</span>`).join('') +
        `<span><i class="sw" style="background:#ff1744;border-radius:5px"></i>look-ahead</span>`;
      const ids = step.tls && step.tls.id ? step.tls.id : [];
      const shown = ids.slice(0, 10).map((id, k) => {
        const st = step.tls.state[k] || '';
        const letters = [...st].map((ch) => `<b style="color:${TLS_COLOURS[ch] || '#9e9e9e'}">${esc(ch)}</b>`).join('');
        return `<div>${esc(id)} ${letters}</div>`;
      });
      if (ids.length > 10) shown.push(`<div>+${ids.length - 10} more</div>`);
      $('hud-tls').innerHTML = shown.join('');
    }
    $('hud-rate').textContent = `${stats.stepHz.toFixed(1)} Hz`;
    $('hud-fps').textContent = `${stats.frameHz.toFixed(1)} Hz  (draw ${stats.drawMs.toFixed(1)} ms)`;
    $('hud-physics').textContent = physics.length
      ? physics.map((p) => `${p.name}: ${p.msg.n} (tick ${p.msg.tick}, coll ${p.msg.counters.collisions ?? 0})`).join(', ')
      : 'none';
  }

  // ------------------------------------------------------------------ input
  canvas.addEventListener('mousedown', (e) => {
    drag = { x: e.clientX, y: e.clientY, cx: view.cx, cy: view.cy };
    canvas.classList.add('dragging');
    tooltip.hidden = true;
  });
  window.addEventListener('mouseup', () => {
    drag = null;
    canvas.classList.remove('dragging');
  });
  canvas.addEventListener('mousemove', (e) => {
    const r = canvas.getBoundingClientRect();
    mouse = { x: e.clientX - r.left, y: e.clientY - r.top };
    if (drag) {
      view.cx = drag.cx - (e.clientX - drag.x) / view.s;
      view.cy = drag.cy + (e.clientY - drag.y) / view.s;
      view.user = true;
      dirty = true;
    }
    hoverDirty = true;
  });
  canvas.addEventListener('mouseleave', () => { mouse = null; hoverDirty = true; });
  canvas.addEventListener('wheel', (e) => {
    e.preventDefault();
    const r = canvas.getBoundingClientRect();
    const px = e.clientX - r.left, py = e.clientY - r.top;
    const [wx, wy] = toWorld(px, py);
    const k = Math.exp(-e.deltaY * (e.deltaMode === 1 ? 0.05 : 0.0015));
    view.s = Math.min(Math.max(view.s * k, 0.005), 500);
    // keep the world point under the cursor where it is
    view.cx = wx - (px - cssW / 2) / view.s;
    view.cy = wy + (py - cssH / 2) / view.s;
    view.user = true;
    dirty = true;
    hoverDirty = true;
  }, { passive: false });
  canvas.addEventListener('dblclick', () => { view.user = false; fit(); });
  window.addEventListener('keydown', (e) => {
    if (e.key === 'f') { view.user = false; fit(); }
    if (e.key === 'p') { showPaths = !showPaths; dirty = true; }
  });
  window.addEventListener('resize', resize);

  // ------------------------------------------------------------------ main loop
  function frame(now) {
    if (pendingFrame) consumeFrame(now);
    if (hoverDirty) {
      hoverDirty = false;
      const before = hover;
      updateTooltip();
      if (before || hover) dirty = true; // the highlight follows the pointer
    }
    if (dirty) {
      draw();
      dirty = false;
    }
    updateHud(now);
    requestAnimationFrame(frame);
  }

  // Exposed for tests and the console.
  stats.fit = () => { view.user = false; fit(); };
  stats.view = view;
  stats.decode = { unpack, readStep, readPhysics, buildNetwork };
  stats.vtypeOf = (id) => { // for tests: the vType row of agent `id` in the newest step, or null
    if (!step) return null;
    const i = step.id.indexOf(id);
    return i < 0 ? null : vtypeOf(i) || null;
  };
  // CSS-pixel position of an agent's body centre (front bumper minus length/2), or null.
  stats.screenOf = (id) => {
    const i = step ? step.id.indexOf(id) : -1;
    if (i < 0) return null;
    const a = step.angle[i] * DEG, half = step.length[i] / 2;
    return toScreen(step.x[i] - half * Math.sin(a), step.y[i] - half * Math.cos(a));
  };

  resize();
  connect();
  requestAnimationFrame(frame);
})();
