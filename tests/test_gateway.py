"""``sumoco gateway``: a run's keys over one WebSocket, with real clients in Python and Node."""

from __future__ import annotations

import asyncio
import base64
import json
import os
import shutil
import subprocess
import threading
import time

import pytest
import zenoh
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from protocol.codec import decode, encode
from protocol.errors import ProtocolError
from protocol.keys import Keys
from protocol.messages import CameraPose, EgoPose, StaticData, StepMessage
from sumoco.viewing.gateway import Gateway, GatewayConfig, pack_frame, unpack_frame
from runtime.config import ZenohConfig
from runtime.transport import open_session
from synthetic.feed import FakePublisher
from synthetic.traffic import FakeRun, synthetic_step
from tests.harness import ROOT, Daemon, endpoint, wait_until

KEYS = Keys("sumoco", "synth")
MAP_REPLY = b"\x81\xa4kind\xa3map"  # stands in for the SUMO side's map answer (SPEC 9)


def test_frame_round_trip_and_bad_frames():
    f = pack_frame("sumoco/x/sumo/step", b"\x81\xa1v\x01")
    assert f[:2] == (18).to_bytes(2, "little")
    assert unpack_frame(f) == ("sumoco/x/sumo/step", b"\x81\xa1v\x01")
    for bad in (b"", b"\x05", b"\x09\x00abc", b"\x02\x00\xff\xfe"):
        with pytest.raises(ProtocolError):
            unpack_frame(bad)


@pytest.fixture()
def run_and_gateway(tmp_path):
    """A synthetic run on Zenoh and a gateway process connected to it."""
    ep = endpoint()
    session = open_session(ZenohConfig(listen=(ep,)))
    pub = FakePublisher(session, FakeRun(grid=1, n=15, run="synth"), instances=("main",)).start()
    egos: list[bytes] = []
    session.declare_subscriber(KEYS.ego_all, lambda s: egos.append(s.payload.to_bytes()))
    session.declare_queryable(KEYS.sumo_map, lambda q: q.reply(KEYS.sumo_map, MAP_REPLY) if "sha256=" not in
                              str(q.parameters) else q.reply_err(b"map not ready"))
    gw = Daemon("gateway", ["gateway", "--run", "synth", "--connect", ep, "--listen", endpoint(),
                            "--port", "0", "--token-file", str(tmp_path / "token")], tmp_path)
    try:
        line = wait_until(lambda: next((ln for ln in gw.tail(50).splitlines() if ln.startswith('{"url"')), None),
                          20.0, "the gateway's URL", procs=[gw])
        url = json.loads(line)["url"]
        token = (tmp_path / "token").read_text().strip()
        assert url.endswith(f"?token={token}") and len(token) >= 16
        assert (tmp_path / "token").stat().st_mode & 0o077 == 0
        yield url, egos, gw
    finally:
        pub.stop()
        code = gw.terminate(5)
        session.close()
        assert code == 0, gw.tail()


@pytest.mark.integration
def test_python_client_subscribes_gets_static_and_sends_ego(run_and_gateway):
    url, egos, _ = run_and_gateway
    with connect(url, max_size=None, open_timeout=10) as ws:
        hello = json.loads(ws.recv(timeout=5))
        assert hello["op"] == "hello" and hello["base"] == KEYS.base
        ws.send(json.dumps({"op": "subscribe", "key": "sumo/step"}))
        ws.send(json.dumps({"op": "static"}))
        ego = EgoPose(id="py", x=1.0, y=2.0, angle=90.0, speed=3.0)
        ws.send(pack_frame("ego/py", encode(ego)))
        steps, static, texts = [], None, []
        while len(steps) < 5 or static is None:
            m = ws.recv(timeout=10)
            if isinstance(m, str):
                texts.append(json.loads(m))
                continue
            key, payload = unpack_frame(m)
            if key == KEYS.static:
                static = decode(payload)
            else:
                assert key == KEYS.step
                steps.append(decode(payload))
        assert {"op": "subscribed", "key": KEYS.step} in texts
        assert isinstance(static, StaticData) and len(static.lanes.ids) > 0
        assert all(isinstance(s, StepMessage) for s in steps)
        assert [s.step for s in steps] == sorted(s.step for s in steps)
        wait_until(lambda: egos, 5.0, "the ego pose on Zenoh")
        assert decode(egos[0]) == ego
        # Bad input gets an error naming the problem; the connection stays usable.
        ws.send(pack_frame("sumo/step", encode(ego)))
        ws.send("{not json")
        ws.send(json.dumps({"op": "subscribe", "key": "sumo/**/x/**/bad?"}))
        errors = []
        while len(errors) < 3:
            m = ws.recv(timeout=10)
            if isinstance(m, str) and json.loads(m)["op"] == "error":
                errors.append(json.loads(m)["error"])
        assert "ego/<id>" in errors[0] and "JSON" in errors[1]
        ws.send(json.dumps({"op": "unsubscribe", "key": "sumo/step"}))
        # Any queryable of the run through "get"; an error answer is passed on with its text.
        ws.send(json.dumps({"op": "get", "key": "sumo/map"}))
        ws.send(json.dumps({"op": "get", "key": "sumo/map", "parameters": "sha256=ab"}))
        answers = []
        while len(answers) < 2:
            m = ws.recv(timeout=10)
            if isinstance(m, bytes) and unpack_frame(m)[0] == KEYS.sumo_map:
                answers.append(unpack_frame(m)[1])
            elif isinstance(m, str) and json.loads(m)["op"] == "error":
                answers.append(json.loads(m)["error"])
        assert MAP_REPLY in answers and any(isinstance(a, str) and "map not ready" in a for a in answers)


@pytest.mark.integration
def test_client_camera_goes_to_zenoh_with_a_token_that_leaves_with_the_client(run_and_gateway):
    url, _, gw = run_and_gateway
    args = list(gw.proc.args)
    run_ep = args[args.index("--connect") + 1]  # the run's session, which the gateway joined
    s = open_session(ZenohConfig(listen=(endpoint(),), connect=(run_ep,)))
    cams: list[tuple[str, bytes]] = []
    alive: dict[str, bool] = {}
    lock = threading.Lock()

    def on_cam(x):
        with lock:
            cams.append((str(x.key_expr), x.payload.to_bytes()))

    def on_alive(x):
        with lock:
            alive[str(x.key_expr)] = x.kind == zenoh.SampleKind.PUT

    subs = [s.declare_subscriber(KEYS.viewer_camera_all, on_cam),
            s.liveliness().declare_subscriber(KEYS.viewer_alive_all, on_alive, history=True)]
    try:
        with connect(url, max_size=None, open_timeout=10) as ws:
            json.loads(ws.recv(timeout=5))

            def sent_and_seen():
                ws.send(pack_frame("viewer/camera", encode(CameraPose("anything", 12.5, -3.0))))
                with lock:
                    return cams[-1] if cams else None
            key, payload = wait_until(sent_and_seen, 10.0, "the client's camera on Zenoh", poll_s=0.1)
            who = Keys.viewer_of(key)
            assert who.startswith("viewer/gw-") and key == f"{KEYS.base}/viewer/{who}/camera"
            cam = decode(payload)
            assert (cam.id, cam.x, cam.y) == (who.split("/")[1], 12.5, -3.0)  # the gateway's id
            token = f"{KEYS.base}/viewer/{who}/alive"
            wait_until(lambda: alive.get(token), 10.0, "the camera's liveliness token")
            ws.send(pack_frame("viewer/camera", encode(EgoPose("e", 1, 2, 3, 4))))
            err = json.loads(ws.recv(timeout=10))
            assert err["op"] == "error" and "camera" in err["error"]
        wait_until(lambda: alive.get(token) is False, 10.0, "the token gone with the client")
    finally:
        for sub in subs:
            sub.undeclare()
        s.close()


@pytest.mark.integration
def test_handshake_checks_token_origin_and_host(run_and_gateway):
    url, _, _ = run_and_gateway
    base, token = url.split("?token=")
    for u, headers, status in (
        (base + "?token=wrong" + "x" * 20, None, 401),
        (base, None, 401),
        (url, {"Origin": "http://evil.example"}, 403),
        (url.replace("127.0.0.1", "localhost"), {"Origin": "http://localhost:5173"}, None),
    ):
        if status is None:
            with connect(u, additional_headers=headers, open_timeout=10) as ws:
                assert json.loads(ws.recv(timeout=5))["op"] == "hello"
            continue
        with pytest.raises(InvalidStatus) as e:
            connect(u, additional_headers=headers, open_timeout=10)
        assert e.value.response.status_code == status
    # DNS rebinding: a page from another name resolving to 127.0.0.1 sends its own Host.
    import socket

    port = int(base.rsplit(":", 1)[1].split("/")[0])
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall((f"GET /ws?token={token} HTTP/1.1\r\nHost: evil.example:{port}\r\nUpgrade: websocket\r\n"
                   "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                   "Sec-WebSocket-Version: 13\r\n\r\n").encode())
        assert s.recv(100).startswith(b"HTTP/1.1 403")


NODE = shutil.which("node")


@pytest.mark.integration
def test_node_client_from_the_examples(run_and_gateway):
    assert NODE, "node is needed for the gateway's JavaScript client test (apt install nodejs)"
    url, egos, _ = run_and_gateway
    ego = EgoPose(id="js", x=5.0, y=6.0, angle=180.0, speed=1.5)
    # Node >= 22 has WebSocket built in; Node 20 and 21 need the flag (newer ones may not know it).
    builtin = subprocess.run([NODE, "-e", "process.exit(typeof WebSocket === 'function' ? 0 : 1)"],
                             capture_output=True, timeout=30).returncode == 0
    flags = [] if builtin else ["--experimental-websocket"]
    r = subprocess.run([NODE, *flags, str(ROOT / "examples" / "gateway_client" / "client.mjs"),
                        url, "4", base64.b64encode(encode(ego)).decode()],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    lines = [json.loads(ln) for ln in r.stdout.splitlines() if ln.startswith("{")]
    frames = [ln for ln in lines if "key" in ln]
    steps = [decode(base64.b64decode(f["b64"])) for f in frames if f["key"] == KEYS.step]
    static = [decode(base64.b64decode(f["b64"])) for f in frames if f["key"] == KEYS.static]
    assert len(steps) >= 4 and all(isinstance(s, StepMessage) for s in steps)
    assert len(static) == 1 and isinstance(static[0], StaticData)
    assert all(f["bytes"] == len(base64.b64decode(f["b64"])) for f in frames)
    wait_until(lambda: egos, 5.0, "the Node client's ego pose on Zenoh")
    assert decode(egos[-1]) == ego


@pytest.mark.integration
def test_gateway_bounds_ego_ids_per_client_and_in_total():
    """A client gets at most ego_per_client ego ids, all clients at most ego_total: a pose for
    one more is refused with an error to that client, counted, and never reaches Zenoh."""
    ep = endpoint()
    victim = open_session(ZenohConfig(listen=(ep,)))  # stands in for the SUMO side
    got: list[str] = []
    lock = threading.Lock()

    def on_ego(s):
        with lock:
            got.append(decode(s.payload.to_bytes()).id)
    sub = victim.declare_subscriber(KEYS.ego_all, on_ego)
    gw_session = open_session(ZenohConfig(connect=(ep,), listen=()))
    gw = Gateway(gw_session, KEYS, GatewayConfig(port=0, ego_per_client=2, ego_total=3))
    ready, loop_of = threading.Event(), {}

    async def serve_until_stopped():
        loop_of["stop"], loop_of["loop"] = asyncio.Event(), asyncio.get_running_loop()
        await gw.run(loop_of["stop"], lambda _: ready.set())
    server = threading.Thread(target=asyncio.run, args=(serve_until_stopped(),), daemon=True)
    server.start()

    def seen(ego_id: str) -> int:
        with lock:
            return got.count(ego_id)

    def send(ws, ego_id: str) -> None:
        ws.send(pack_frame(f"ego/{ego_id}", encode(EgoPose(ego_id, 1.0, 2.0, 90.0, 0.0))))

    def next_error(ws) -> str:
        while True:
            m = ws.recv(timeout=10)
            if isinstance(m, str) and json.loads(m)["op"] == "error":
                return json.loads(m)["error"]

    try:
        assert ready.wait(20), "the gateway did not start"
        wait_until(lambda: list(gw_session.info.peers_zid()), 10, "the gateway's session to reach the run")
        with connect(gw.url(), open_timeout=10) as a, connect(gw.url(), open_timeout=10) as b:
            for ws in (a, b):
                assert json.loads(ws.recv(timeout=5))["op"] == "hello"
            for ego_id in ("a0", "a1"):
                wait_until(lambda i=ego_id: send(a, i) or seen(i), 10, f"{ego_id} on Zenoh", poll_s=0.1)
            send(a, "a2")  # a third id from the same client
            err = next_error(a)
            assert err.startswith("ego/a2: refused") and "per client (2)" in err, err
            wait_until(lambda: send(b, "b0") or seen("b0"), 10, "another client's ego on Zenoh", poll_s=0.1)
            send(b, "b1")  # within b's own bound, but the gateway holds 3 ids in all
            err = next_error(b)
            assert err.startswith("ego/b1: refused") and "the most it allows (3)" in err, err
            n0 = seen("a0")  # ids already driven still go through, after the refused ones
            wait_until(lambda: send(a, "a0") or seen("a0") > n0 + 1, 10, "a0 again", poll_s=0.1)
            time.sleep(0.3)
            assert seen("a2") == 0 and seen("b1") == 0, got
            st = gw.status()
            assert st["egos"] == 3 and st["ego_refused"] == 2 and st["rejected"] == 2, st
            a.close()  # a leaves: its two ids are freed
            wait_until(lambda: gw.status()["clients"] == 1, 10, "the gateway to see the client go")
            wait_until(lambda: send(b, "b1") or seen("b1"), 10, "b1 once a's ids are free", poll_s=0.1)
            assert gw.status()["egos"] == 2
    finally:
        if "loop" in loop_of:
            loop_of["loop"].call_soon_threadsafe(loop_of["stop"].set)
        server.join(10)
        sub.undeclare()
        gw_session.close()
        victim.close()


def _gateway_in_thread(ep: str, cfg: GatewayConfig):
    """A Gateway on a thread of its own, connected to ``ep``; returns (gw, session, stop)."""
    gw_session = open_session(ZenohConfig(connect=(ep,), listen=()))
    gw = Gateway(gw_session, KEYS, cfg)
    ready, loop_of = threading.Event(), {}

    async def serve_until_stopped():
        loop_of["stop"], loop_of["loop"] = asyncio.Event(), asyncio.get_running_loop()
        await gw.run(loop_of["stop"], lambda _: ready.set())
    server = threading.Thread(target=asyncio.run, args=(serve_until_stopped(),), daemon=True)
    server.start()
    assert ready.wait(20), "the gateway did not start"
    wait_until(lambda: list(gw_session.info.peers_zid()), 10, "the gateway's session to reach the run")

    def stop():
        loop_of["loop"].call_soon_threadsafe(loop_of["stop"].set)
        server.join(10)
        gw_session.close()
    return gw, gw_session, stop


def _texts(ws, op: str, n: int, timeout_s: float = 10.0) -> list[dict]:
    out, t_end = [], time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < t_end:
        m = ws.recv(timeout=max(0.1, t_end - time.monotonic()))
        if isinstance(m, str) and json.loads(m)["op"] == op:
            out.append(json.loads(m))
    return out


def test_gateway_relays_liveliness_dedups_overlaps_and_tells_ego_errors():
    """What an outside client found: liveliness reaches WebSocket clients, a sample matching two
    subscriptions comes once, ego ids that SUMO would drop are refused at the gateway (no slot
    used), /status needs the token and counts over clients that left, and a get with no
    queryable says so at once."""
    ep = endpoint()
    run = open_session(ZenohConfig(listen=(ep,)))  # stands in for the SUMO side
    egos: list[str] = []
    sub = run.declare_subscriber(KEYS.ego_all, lambda s: egos.append(decode(s.payload.to_bytes()).id))
    gw, _, stop = _gateway_in_thread(ep, GatewayConfig(port=0, ego_ids=("ego",), subscriptions_per_client=3))
    token = run.liveliness().declare_token(KEYS.sumo_alive)
    pub = run.declare_publisher(KEYS.step)
    try:
        with connect(gw.url(), open_timeout=10) as ws:
            assert json.loads(ws.recv(timeout=5))["op"] == "hello"
            ws.send(json.dumps({"op": "subscribe", "key": "sumo/alive"}))
            assert _texts(ws, "alive", 1) == [{"op": "alive", "key": KEYS.sumo_alive, "alive": True}]
            token.undeclare()  # the SUMO side leaves ...
            assert _texts(ws, "alive", 1) == [{"op": "alive", "key": KEYS.sumo_alive, "alive": False}]
            token = run.liveliness().declare_token(KEYS.sumo_alive)  # ... and comes back
            assert _texts(ws, "alive", 1)[0]["alive"] is True
            # overlapping subscriptions: every step once
            ws.send(json.dumps({"op": "subscribe", "key": "sumo/step"}))
            ws.send(json.dumps({"op": "subscribe", "key": "**"}))
            assert len(_texts(ws, "subscribed", 2)) == 2
            time.sleep(0.3)
            for k in range(20):
                pub.put(encode(synthetic_step(3, step=k)))
            seen = []
            t_end = time.monotonic() + 10
            while len(seen) < 20 and time.monotonic() < t_end:
                m = ws.recv(timeout=10)
                if isinstance(m, bytes) and unpack_frame(m)[0] == KEYS.step:
                    seen.append(decode(unpack_frame(m)[1]).step)
            time.sleep(0.3)
            while True:  # nothing more may be waiting
                try:
                    m = ws.recv(timeout=0.2)
                except TimeoutError:
                    break
                if isinstance(m, bytes) and unpack_frame(m)[0] == KEYS.step:
                    seen.append(decode(unpack_frame(m)[1]).step)
            assert sorted(seen) == list(range(20)), seen
            # a fourth subscription is over this gateway's bound of 3
            ws.send(json.dumps({"op": "subscribe", "key": "physics/**"}))
            assert "most the gateway allows per client (3)" in _texts(ws, "error", 1)[0]["error"]
            # ego errors reach the client, and use no slot
            ws.send(pack_frame("ego/ego", encode(EgoPose("other", 1.0, 2.0, 90.0, 0.0))))
            assert "differs from its key" in _texts(ws, "error", 1)[0]["error"]
            ws.send(pack_frame("ego/car9", encode(EgoPose("car9", 1.0, 2.0, 90.0, 0.0))))
            assert "takes ego ids 'ego' only" in _texts(ws, "error", 1)[0]["error"]
            assert gw.status()["egos"] == 0
            wait_until(lambda: ws.send(pack_frame("ego/ego", encode(EgoPose("ego", 1.0, 2.0, 90.0, 0.0)))) or egos,
                       10, "the right ego on Zenoh", poll_s=0.1)
            assert set(egos) == {"ego"}
            # a get with nothing to answer it says so without waiting out the timeout
            t0 = time.monotonic()
            ws.send(json.dumps({"op": "get", "key": "sumo/nothing"}))
            err = _texts(ws, "error", 1)[0]["error"]
            assert "nothing answers this key" in err and time.monotonic() - t0 < 4.0, err
        wait_until(lambda: gw.status()["clients"] == 0, 10, "the client to leave")
        base = gw.url().split("/ws?token=")[0].replace("ws://", "http://")
        import urllib.error
        import urllib.request
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(f"{base}/status", timeout=5)
        assert e.value.code == 401
        # the right token under a foreign Host (DNS rebinding): refused as the WebSocket is
        req = urllib.request.Request(f"{base}/status?token={gw.token}", headers={"Host": f"evil.example:{gw.port}"})
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(req, timeout=5)
        assert e.value.code == 403
        with urllib.request.urlopen(f"{base}/status?token={gw.token}", timeout=5) as r:
            st = json.loads(r.read())
        assert st["rejected"] == 3 and st["duplicates"] >= 20, st  # counted after the client left
        assert st["oversized"] == 0
    finally:
        stop()
        sub.undeclare()
        run.close()
