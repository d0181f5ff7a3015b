// A sumoco gateway client in plain JavaScript (Node >= 22, or Node 20 with
// --experimental-websocket; the same code runs in a browser page). Written from
// protocol/SPEC.md, section "WebSocket gateway", alone.
//
//   node --experimental-websocket client.mjs 'ws://127.0.0.1:8766/ws?token=...' [frames] [egoB64]
//
// Subscribes to the SUMO steps, asks for the static data, prints one JSON line per
// binary frame ({key, bytes, b64}) and, when an ego pose (msgpack, base64) is given,
// sends it upstream on ego/<id>. Decoding the msgpack payload is up to the engine
// (any msgpack library; SPEC.md sections 3.x give the maps).

const [url, framesArg = "5", egoB64 = ""] = process.argv.slice(2);
const want = Number(framesArg);
if (typeof WebSocket === "undefined") {
  console.error("no WebSocket in this Node: use Node >= 22 or --experimental-websocket");
  process.exit(2);
}

// Binary frame: u16 little-endian key length, the key (UTF-8), the msgpack payload.
function unpackFrame(buf) {
  const view = new DataView(buf);
  const n = view.getUint16(0, true);
  const key = new TextDecoder().decode(new Uint8Array(buf, 2, n));
  return { key, payload: new Uint8Array(buf, 2 + n) };
}

function packFrame(key, payload) {
  const k = new TextEncoder().encode(key);
  const out = new Uint8Array(2 + k.length + payload.length);
  new DataView(out.buffer).setUint16(0, k.length, true);
  out.set(k, 2);
  out.set(payload, 2 + k.length);
  return out;
}

const ws = new WebSocket(url);
ws.binaryType = "arraybuffer";
let got = 0;
let sawStatic = false;
const timer = setTimeout(() => { console.error("timed out"); process.exit(1); }, 20000);

ws.onopen = () => {
  ws.send(JSON.stringify({ op: "subscribe", key: "sumo/step" }));
  ws.send(JSON.stringify({ op: "static" }));
  if (egoB64) ws.send(packFrame("ego/js", Uint8Array.from(Buffer.from(egoB64, "base64"))));
};

ws.onmessage = (ev) => {
  if (typeof ev.data === "string") {
    const msg = JSON.parse(ev.data);
    console.log(JSON.stringify({ text: msg }));
    if (msg.op === "error") process.exitCode = 3;
    return;
  }
  const { key, payload } = unpackFrame(ev.data);
  if (key.endsWith("/sumo/static")) sawStatic = true;
  else got += 1;
  console.log(JSON.stringify({ key, bytes: payload.length, b64: Buffer.from(payload).toString("base64") }));
  if (got >= want && sawStatic) {
    clearTimeout(timer);
    ws.close();
  }
};

ws.onerror = (ev) => { console.error("websocket error", ev.message ?? ""); process.exit(1); };
ws.onclose = () => clearTimeout(timer);
