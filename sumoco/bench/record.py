"""``sumoco bench record|gateway --json``: recording size and cost, report memory, replay and gateway.

Rows (one JSON object each):

- ``record``: a synthetic run (``FakeRun``) published on loopback Zenoh in real time the way
  the daemons publish it (steps at 10 Hz, two physics instances at 50 Hz) and recorded with
  the defaults (compact encoding), raw payloads (``raw``), without scene or with everything:
  ``gb_per_hour`` of simulated time (with the goal on the defaults rows), messages
  ``dropped`` and ``thinned``;
- ``report_rss``: peak RSS of a process that summarises a recording for the report,
  streamed (``analyse_recording``, what ``sumoco report`` does) and fully in memory
  (``read_recording`` + ``load_run`` tables), for a short and a long recording of the same
  traffic (``rss_ratio_long_short`` on the long rows: the goal is a flat 1.0);
- ``replay``: a recording replayed to a subscriber: byte-exact payloads, and the error of
  the replayed step intervals against the recorded ones;
- ``gateway``: one-way latency of the same step messages to a direct Zenoh subscriber and
  to a WebSocket client of ``sumoco gateway`` (a separate process), measured in one run.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from protocol.codec import encode
from protocol.keys import Keys
from sumoco.recording.record import LiveRecorder, McapRecorder, RecordConfig, read_recording
from sumoco.recording.codec import CompactEncoder
from runtime.config import ZenohConfig
from runtime.transport import free_tcp_port, open_session
from synthetic.feed import FakePublisher
from synthetic.traffic import FakeRun


GOAL_GB_PER_HOUR = 1.0  # recording size with the defaults (issue "scale")


def _ep() -> str:
    return f"tcp/127.0.0.1:{free_tcp_port()}"


def _grid(n: int) -> int:
    return max(1, int(np.ceil(np.sqrt(n / 40))))


def record_size(agents: int, seconds: float, out: Path, config: RecordConfig | None = None) -> dict:
    """Record ``seconds`` of a synthetic run published live; size per simulated minute."""
    fake = FakeRun(grid=_grid(agents), n=agents, run="bench")
    rec = McapRecorder(out)
    with open_session(ZenohConfig(listen=(_ep(),))) as s:
        pub = FakePublisher(s, fake, step_hz=10.0, physics_hz=50.0)
        live = LiveRecorder(s, Keys("sumoco", "bench"), rec, config=config or RecordConfig())
        live.start()
        pub.start()
        live.fetch_static(5.0)
        t0 = time.monotonic()
        time.sleep(seconds)
        pub.stop()
        steps = pub.steps_sent
        live.stop()
        rec.close()
        wall = time.monotonic() - t0
    sim_s = steps * fake.dt
    size = out.stat().st_size
    return {"bench": "record", "agents": agents, "scene": live.config.scene,
            "physics_hz": live.config.physics_hz, "scene_hz": live.config.scene_hz,
            "sim_s": round(sim_s, 2), "wall_s": round(wall, 2), "bytes": size,
            "mb_per_min": round(size / sim_s * 60 / 1e6, 2), "gb_per_hour": round(size / sim_s * 3600 / 1e9, 3),
            **live.stats()}


def synthetic_recording(path: Path, agents: int, seconds: float, physics_hz: float = 10.0,
                        encoding: str = "compact") -> None:
    """A recording written straight from a FakeRun (no transport): for reader memory tests."""
    fake = FakeRun(grid=_grid(agents), n=agents, run="bench")
    keys = Keys("sumoco", "bench")
    rec = McapRecorder(path)
    enc = CompactEncoder() if encoding == "compact" else None

    def write(topic: str, msg, stamp: int) -> None:
        if enc is None:
            rec.write(topic, encode(msg), stamp)
        else:
            schema, data = enc.encode(topic, msg)
            rec.write(topic, data, stamp, schema=schema)

    t_ns = 1_000_000_000
    rec.write(keys.static, encode(fake.static()), t_ns, schema="static")
    per_step = max(1, int(round(physics_hz * fake.dt)))
    for k in range(int(seconds / fake.dt)):
        t = k * fake.dt
        stamp = t_ns + int(t * 1e9)
        write(keys.step, fake.step(k), stamp)
        for j, inst in enumerate(("paper", "default")):
            for i in range(per_step):
                write(Keys("sumoco", "bench", inst).physics_state,
                      fake.physics(k * per_step + i, t + i / physics_hz, k, gain=1.0 + j), stamp)
    rec.close()


_RSS_CHILD = r'''
import json, resource, sys, time
from sumoco.analysis.summary import analyse_recording, load_run, summarise
from sumoco.recording.record import open_recording, read_recording
t0 = time.perf_counter()
if sys.argv[2] == "stream":  # what `sumoco report` does
    steps = analyse_recording(open_recording(sys.argv[1]))[0]["steps"]
else:  # everything in memory: messages, then tables
    steps = summarise(load_run(read_recording(sys.argv[1])))["steps"]
print(json.dumps({"steps": steps, "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "load_s": time.perf_counter() - t0}))
'''


def report_rss(agents: int, seconds: tuple[float, ...], tmp: Path) -> list[dict]:
    rows = []
    for sec in seconds:
        path = tmp / f"rss_{agents}_{int(sec)}.mcap"
        synthetic_recording(path, agents, sec)
        for how in ("stream", "in_memory"):
            r = subprocess.run([sys.executable, "-c", _RSS_CHILD, str(path), how], capture_output=True,
                               text=True, timeout=600, check=True)
            d = json.loads(r.stdout)
            rows.append({"bench": "report_rss", "agents": agents, "sim_s": sec, "file_mb": round(path.stat().st_size / 1e6, 2),
                         "read": how, "steps": d["steps"], "rss_mb": round(d["rss_mb"], 1),
                         "load_s": round(d["load_s"], 2)})
    for r in rows[2:]:  # longest vs shortest of the same reading
        first = next(f for f in rows if f["read"] == r["read"])
        r["rss_ratio_long_short"] = round(r["rss_mb"] / first["rss_mb"], 2)
    return rows


def replay_fidelity(path: Path, speed: float = 1.0) -> dict:
    """Replay ``path`` once to a subscriber; compare bytes and step intervals with the recording."""
    rec = read_recording(path)
    keys = Keys("sumoco", "bench")
    recorded = [(m.data, m.log_time_ns / 1e9) for m in rec.messages if m.topic == keys.step]
    ep = _ep()
    got: list[tuple[bytes, float]] = []
    with open_session(ZenohConfig(listen=(_ep(),), connect=(ep,))) as s:
        s.declare_subscriber(keys.step, lambda smp: got.append((smp.payload.to_bytes(), time.monotonic())))
        proc = subprocess.run([sys.executable, "-m", "sumoco.cli", "replay", str(path), "--speed", str(speed),
                               "--listen", ep, "--wait-subscriber", "10", "--quiet"], capture_output=True, text=True, timeout=600)
        time.sleep(0.2)
    stats = json.loads(proc.stdout.strip().splitlines()[-1])
    index = {d: i for i, (d, _) in enumerate(recorded)}
    matched = [index.get(d, -1) for d, _ in got]
    rec_t = np.array([recorded[i][1] for i in matched if i >= 0])
    rep_t = np.array([t for (d, t), i in zip(got, matched) if i >= 0])
    err_ms = np.abs(np.diff(rep_t) * speed - np.diff(rec_t)) * 1e3 if len(rep_t) > 2 else np.zeros(1)
    return {"bench": "replay", "speed": speed, "recorded_steps": len(recorded), "received_steps": len(got),
            "byte_exact": int(sum(i >= 0 for i in matched)), "in_order": bool(matched == sorted(matched)),
            "interval_err_ms_p50": round(float(np.percentile(err_ms, 50)), 3),
            "interval_err_ms_p99": round(float(np.percentile(err_ms, 99)), 3),
            "duration_ratio": round(float((rep_t[-1] - rep_t[0]) * speed / (rec_t[-1] - rec_t[0])), 4)
            if len(rep_t) > 1 else None,
            "static_queries": stats.get("static_queries"), "replay_late_ms_max": round(stats["late_ms_max"], 2)}


def gateway_latency(agents: int, messages: int = 200, rate_hz: float = 20.0) -> dict:
    """Send time -> receive time of the same step payloads: direct Zenoh vs through the gateway."""
    from websockets.sync.client import connect

    from sumoco.viewing.gateway import unpack_frame

    keys = Keys("sumoco", "bench")
    fake = FakeRun(grid=_grid(agents), n=agents, run="bench")
    payloads = [encode(fake.step(k)) for k in range(messages)]
    ep = _ep()
    sent: dict[int, float] = {}
    direct: dict[int, float] = {}
    via_ws: dict[int, float] = {}
    index = {p: i for i, p in enumerate(payloads)}
    with tempfile.TemporaryDirectory() as tmp, open_session(ZenohConfig(listen=(ep,))) as pub_s, \
            open_session(ZenohConfig(listen=(_ep(),), connect=(ep,))) as sub_s:
        sub_s.declare_subscriber(keys.step, lambda smp: direct.setdefault(
            index.get(smp.payload.to_bytes(), -1), time.perf_counter()))
        tok = Path(tmp) / "token"
        gw = subprocess.Popen([sys.executable, "-m", "sumoco.cli", "gateway", "--run", "bench", "--connect", ep,
                               "--listen", _ep(), "--port", "0", "--token-file", str(tok), "--quiet"],
                              stdout=subprocess.PIPE, text=True)
        try:
            url = json.loads(gw.stdout.readline())["url"]
            with connect(url, max_size=None) as ws:
                ws.recv(timeout=10)  # hello
                ws.send(json.dumps({"op": "subscribe", "key": "sumo/step"}))
                ws.recv(timeout=10)  # subscribed

                def reader() -> None:
                    try:
                        while len(via_ws) < messages:
                            m = ws.recv(timeout=5)
                            if isinstance(m, bytes):
                                via_ws.setdefault(index.get(unpack_frame(m)[1], -1), time.perf_counter())
                    except Exception:
                        pass

                th = threading.Thread(target=reader, daemon=True)
                th.start()
                pub = pub_s.declare_publisher(keys.step)
                time.sleep(0.5)  # routes settle
                for i, p in enumerate(payloads):
                    sent[i] = time.perf_counter()
                    pub.put(p)
                    time.sleep(1.0 / rate_hz)
                th.join(10)
        finally:
            gw.terminate()
            gw.wait(10)
    d = np.array([direct[i] - sent[i] for i in sent if i in direct]) * 1e3
    w = np.array([via_ws[i] - sent[i] for i in sent if i in via_ws]) * 1e3
    row = {"bench": "gateway", "agents": agents, "bytes": len(payloads[0]), "messages": messages,
           "direct_received": len(d), "gateway_received": len(w)}
    for name, a in (("direct", d), ("gateway", w)):
        row[f"{name}_ms_p50"] = round(float(np.percentile(a, 50)), 3) if len(a) else None
        row[f"{name}_ms_p99"] = round(float(np.percentile(a, 99)), 3) if len(a) else None
    if len(d) and len(w):
        row["ratio_p50"] = round(row["gateway_ms_p50"] / row["direct_ms_p50"], 2)
        row["ratio_p99"] = round(row["gateway_ms_p99"] / row["direct_ms_p99"], 2)
    return row


def run_record_bench(quick: bool = False) -> list[dict]:
    rows = []
    secs = 5.0 if quick else 15.0
    variants = {"defaults": RecordConfig(), "no_scene": RecordConfig(scene=False), "raw": RecordConfig(encoding="raw"),
                "everything": RecordConfig(physics_hz=0.0, scene_hz=0.0)}
    plan = [(377, "defaults")] if quick else [(377, "defaults"), (377, "raw"), (377, "no_scene"), (377, "everything"),
                                               (2500, "defaults"), (2500, "raw"), (2500, "no_scene")]
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        for n, name in plan:
            path = t / f"rec_{n}_{name}.mcap"
            row = {**record_size(n, secs, path, variants[name]), "variant": name}
            if name == "defaults":  # issue goal: <= 1 GB per hour at 2,500 agents with the defaults
                row["goal_gb_per_hour"] = GOAL_GB_PER_HOUR
                row["meets_goal"] = row["gb_per_hour"] <= GOAL_GB_PER_HOUR
            rows.append(row)
            if n == 377 and name == "defaults":
                rows.append(replay_fidelity(path))
            os.remove(path)
        rows += report_rss(377, (10.0, 40.0) if quick else (30.0, 240.0), t)
    return rows


def run_gateway_bench(quick: bool = False) -> list[dict]:
    return [gateway_latency(n, messages=50 if quick else 200) for n in ((377,) if quick else (377, 2500))]
