// sumoco wire decoding for the browser pages (2D and 3D): a msgpack reader for the subset
// the protocol uses and column readers that turn bins into typed arrays (SPEC.md 3).
// Exposed as window.sumocoDecode = {unpack, column, polyline, readStep, readPhysics, setStatic,
// vtypeTable, staticSv}.
(() => {
  'use strict';
  // ------------------------------------------------------------------ msgpack subset
  // map, array, str, bin, int, float, nil, bool: all the wire protocol uses (SPEC.md 3).
  const utf8 = new TextDecoder('utf-8');

  class Reader {
    constructor(u8) {
      this.u8 = u8;
      this.dv = new DataView(u8.buffer, u8.byteOffset, u8.byteLength);
      this.pos = 0;
    }
    take(len) {
      const s = this.pos;
      const e = s + len;
      if (e > this.u8.length) throw new Error('msgpack: truncated input');
      this.pos = e;
      return s;
    }
    str(len) {
      const s = this.take(len);
      const u8 = this.u8;
      if (len < 48) { // ids are short ASCII: skip TextDecoder's call overhead
        let out = '';
        for (let i = s; i < s + len; i++) {
          const c = u8[i];
          if (c > 0x7f) return utf8.decode(u8.subarray(s, s + len));
          out += String.fromCharCode(c);
        }
        return out;
      }
      return utf8.decode(u8.subarray(s, s + len));
    }
    bin(len) {
      const s = this.take(len);
      return this.u8.subarray(s, s + len); // a view: no copy
    }
    arr(len) {
      const a = new Array(len);
      for (let i = 0; i < len; i++) a[i] = this.read();
      return a;
    }
    map(len) {
      const m = Object.create(null); // keys come from the wire: no prototype to pollute
      for (let i = 0; i < len; i++) {
        const k = this.read();
        m[k] = this.read();
      }
      return m;
    }
    read() {
      if (this.pos >= this.u8.length) throw new Error('msgpack: truncated input');
      const b = this.u8[this.pos++];
      if (b < 0x80) return b;
      if (b < 0x90) return this.map(b & 0x0f);
      if (b < 0xa0) return this.arr(b & 0x0f);
      if (b < 0xc0) return this.str(b & 0x1f);
      if (b >= 0xe0) return b - 0x100;
      const dv = this.dv;
      switch (b) {
        case 0xc0: return null;
        case 0xc2: return false;
        case 0xc3: return true;
        case 0xc4: return this.bin(dv.getUint8(this.take(1)));
        case 0xc5: return this.bin(dv.getUint16(this.take(2)));
        case 0xc6: return this.bin(dv.getUint32(this.take(4)));
        case 0xca: return dv.getFloat32(this.take(4));
        case 0xcb: return dv.getFloat64(this.take(8));
        case 0xcc: return dv.getUint8(this.take(1));
        case 0xcd: return dv.getUint16(this.take(2));
        case 0xce: return dv.getUint32(this.take(4));
        case 0xcf: return Number(dv.getBigUint64(this.take(8)));
        case 0xd0: return dv.getInt8(this.take(1));
        case 0xd1: return dv.getInt16(this.take(2));
        case 0xd2: return dv.getInt32(this.take(4));
        case 0xd3: return Number(dv.getBigInt64(this.take(8)));
        case 0xd9: return this.str(dv.getUint8(this.take(1)));
        case 0xda: return this.str(dv.getUint16(this.take(2)));
        case 0xdb: return this.str(dv.getUint32(this.take(4)));
        case 0xdc: return this.arr(dv.getUint16(this.take(2)));
        case 0xdd: return this.arr(dv.getUint32(this.take(4)));
        case 0xde: return this.map(dv.getUint16(this.take(2)));
        case 0xdf: return this.map(dv.getUint32(this.take(4)));
        default: throw new Error('msgpack: unsupported type byte 0x' + b.toString(16));
      }
    }
  }

  function unpack(u8) {
    const r = new Reader(u8);
    const v = r.read();
    if (r.pos !== u8.length) throw new Error('msgpack: trailing bytes');
    return v;
  }

  // ------------------------------------------------------------------ columns (SPEC 3)
  const LITTLE = new Uint8Array(new Uint16Array([1]).buffer)[0] === 1;
  const GETTER = new Map([
    [Uint8Array, 'getUint8'], [Uint16Array, 'getUint16'], [Uint32Array, 'getUint32'],
    [Int32Array, 'getInt32'], [Float32Array, 'getFloat32'], [Float64Array, 'getFloat64'],
  ]);

  // A little-endian column of n values; n < 0 means "as many as the bytes hold".
  function column(bin, T, n, name) {
    if (!(bin instanceof Uint8Array)) throw new Error(name + ': expected a bin column');
    const size = T.BYTES_PER_ELEMENT;
    if (n < 0) n = Math.floor(bin.byteLength / size);
    if (bin.byteLength !== n * size) {
      throw new Error(`${name}: ${bin.byteLength} bytes, expected ${n} x ${size}`);
    }
    if (LITTLE) {
      // msgpack bins are not aligned: view in place when they happen to be, else copy.
      if (bin.byteOffset % size === 0) return new T(bin.buffer, bin.byteOffset, n);
      return new T(bin.slice().buffer);
    }
    const dv = new DataView(bin.buffer, bin.byteOffset, bin.byteLength);
    const get = GETTER.get(T);
    const out = new T(n);
    for (let i = 0; i < n; i++) out[i] = dv[get](i * size, true);
    return out;
  }

  // Static shapes: float64 xy64 (protocol 1.2) or float32 xy (1.1). Paths (anchors given):
  // float32 dxy offsets from each agent's float64 (x, y) (1.2) or absolute float32 xy (1.1).
  function polyline(p, n, name, anchors) {
    const off = column(p.off, Uint32Array, n + 1, name + '.off');
    if (p.xy64) return { off, xy: column(p.xy64, Float64Array, -1, name + '.xy64') };
    if (anchors && p.dxy) {
      const d = column(p.dxy, Float32Array, -1, name + '.dxy');
      const xy = new Float64Array(d.length);
      for (let i = 0; i < n; i++) {
        for (let j = off[i]; j < off[i + 1]; j++) {
          xy[2 * j] = anchors.x[i] + d[2 * j];
          xy[2 * j + 1] = anchors.y[i] + d[2 * j + 1];
        }
      }
      return { off, xy };
    }
    return { off, xy: column(p.xy, Float32Array, -1, name + '.xy') };
  }

  // vType tables by static version sv (SPEC 3.1, 3.2). Since protocol 1.2 a step carries its
  // table only when sv changes: a page that joined later takes it from the static data
  // (setStatic), which the server sends on connect and again for every new version.
  const vtypeTables = new Map(); // sv -> [[vType id, vClass], ...]
  const MAX_TABLES = 16; // a few versions are in flight at once; forget the oldest
  function remember(sv, table) {
    vtypeTables.delete(sv);
    vtypeTables.set(sv, table);
    while (vtypeTables.size > MAX_TABLES) vtypeTables.delete(vtypeTables.keys().next().value);
  }
  let staticSv = null;
  // The static data's vType table (a map of id / vclass arrays) under its sv.
  function setStatic(d) {
    if (d.kind !== 'static') throw new Error('expected static data, got ' + d.kind);
    const V = d.vtypes;
    const sv = d.sv | 0; // absent: a 1.1 sender, version 0
    if (V && Array.isArray(V.id)) {
      const vc = Array.isArray(V.vclass) ? V.vclass : [];
      remember(sv, V.id.map((id, i) => [id, vc[i] || '']));
    }
    staticSv = sv;
    return sv;
  }
  // The table of version sv, or null while it is unknown (the step's own cls, length and
  // width still draw the agents).
  function vtypeTable(sv) {
    return vtypeTables.get(sv | 0) || null;
  }

  // Look-ahead point: x + la_dx (1.2) or the absolute float32 la_x (1.1).
  function lookAhead(a, n, base, key, c) {
    const d = 'la_d' + key;
    if (!a[d]) return c('la_' + key, Float32Array);
    const off = c(d, Float32Array);
    const out = new Float64Array(n);
    for (let i = 0; i < n; i++) out[i] = base[i] + off[i];
    return out;
  }

  function readStep(d) {
    if (d.kind !== 'step') throw new Error('expected a step message, got ' + d.kind);
    const a = d.agents;
    const n = a.n | 0;
    const c = (k, T) => column(a[k], T, n, 'agents.' + k);
    const sv = d.sv | 0;
    if (Array.isArray(d.vtypes)) remember(sv, d.vtypes);
    const x = c('x', Float64Array), y = c('y', Float64Array);
    const s = {
      step: d.step, t: d.t, dt: d.dt, sv, vtypes: vtypeTable(sv) || [], n, id: a.id,
      cls: c('cls', Uint8Array), vtype: c('vtype', Uint16Array),
      x, y, angle: c('angle', Float32Array),
      speed: c('speed', Float32Array), accel: c('accel', Float32Array),
      signals: c('signals', Uint16Array), la_x: lookAhead(a, n, x, 'x', c), la_y: lookAhead(a, n, y, 'y', c),
      length: c('length', Float32Array), width: c('width', Float32Array),
      lane: c('lane', Int32Array), flags: c('flags', Uint8Array),
      path: a.path ? polyline(a.path, n, 'agents.path', { x, y }) : null,
      tls: d.tls || { id: [], state: [] },
      index: null,
    };
    return s;
  }

  function readPhysics(d) {
    if (d.kind !== 'physics') throw new Error('expected a physics message, got ' + d.kind);
    const a = d.agents;
    const n = a.n | 0;
    const c = (k, T) => column(a[k], T, n, 'agents.' + k);
    return {
      tick: d.tick, t: d.t, sumo_step: d.sumo_step, counters: d.counters || {}, n, id: a.id,
      cls: c('cls', Uint8Array), mode: c('mode', Uint8Array),
      x: c('x', Float64Array), y: c('y', Float64Array), heading: c('heading', Float32Array),
      z: c('z', Float32Array), roll: c('roll', Float32Array), pitch: c('pitch', Float32Array),
      brake: c('brake', Float32Array),
      speed: c('speed', Float32Array), steer: c('steer', Float32Array),
      err_lon: c('err_lon', Float32Array), err_lat: c('err_lat', Float32Array),
    };
  }

  window.sumocoDecode = {
    unpack, column, polyline, readStep, readPhysics, setStatic, vtypeTable,
    get staticSv() { return staticSv; },
  };
})();
