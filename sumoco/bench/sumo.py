"""``sumoco bench sumo``: per-step cost of the SUMO side at ~250, ~2,500 and ~10,000 agents.

For each size a grid scenario (``sumo_side.scenarios.make_grid_scenario``) runs in
libsumo until the network holds about that many vehicles; then, per step, it measures

- ``sumo_step_ms``: SUMO's own ``simulationStep``;
- ``bridge_ms``: everything else the daemon does per step (``read`` of the subscriptions,
  look-ahead and paths, building and encoding the message, publishing it on a real
  loopback Zenoh session with a subscriber attached, and the garbage-collector tick),
  with the daemon's code (``Bridge``, ``HotLoopGC``);
- ``encode_ms`` / ``decode_ms`` of the published message, and its size per agent with
  and without path polylines.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from pathlib import Path

import numpy as np

from protocol.codec import decode, encode
from sumo_side.bridge import Bridge
from sumo_side.config import SumoConfig
from sumo_side.daemon import HotLoopGC
from sumo_side.simulation import SumoSim
from sumoco.bench.timing import median_ms
from sumoco.bench.scenario import fill, grid_scenario

log = logging.getLogger(__name__)


class _Sink:
    """A subscriber in a second Zenoh session: counts what arrives."""

    def __init__(self) -> None:
        self.count = 0
        self.bytes = 0
        self._lock = threading.Lock()

    def __call__(self, sample) -> None:
        n = len(sample.payload)
        with self._lock:
            self.count += 1
            self.bytes += n


def _sessions():
    from runtime.config import ZenohConfig
    from runtime.transport import free_tcp_port, open_session

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    pub_s = open_session(ZenohConfig(listen=(ep,)))
    sub_s = open_session(ZenohConfig(connect=(ep,), listen=()))
    return pub_s, sub_s


def _timed_steps(sim, bridge, publisher, k: int, steps: int) -> tuple[dict[str, list], object]:
    """The daemon's per-step work for ``steps`` steps after step ``k``, each part timed [s];
    the last message too (for the codec figures)."""
    t = {name: [] for name in ("sumo", "read", "build", "encode", "publish", "gc", "agents", "bytes")}
    msg = None
    perf = time.perf_counter
    with HotLoopGC() as hot_gc:
        for i in range(steps):
            k += 1
            t0 = perf()
            sim.step()
            t1 = perf()
            snap = sim.read()
            t2 = perf()
            msg = bridge.build(k, snap)
            t3 = perf()
            data = encode(msg)
            t4 = perf()
            publisher.put(data)
            t5 = perf()
            # the daemon collects once per status period (1 s); here once per 10 steps
            # (1 s of simulated time at 0.1 s steps), its time counted as bridge time
            if i % 10 == 9:
                hot_gc.tick()
            t6 = perf()
            for name, v in (("sumo", t1 - t0), ("read", t2 - t1), ("build", t3 - t2), ("encode", t4 - t3),
                            ("publish", t5 - t4), ("gc", t6 - t5), ("agents", snap.n), ("bytes", len(data))):
                t[name].append(v)
    return t, msg


def _codec_figures(msg) -> dict:
    """Size per agent and decode/encode time of ``msg``, with and without its paths."""
    a = msg.agents
    no_paths = dataclasses.replace(
        msg, agents=dataclasses.replace(a, path_offsets=np.zeros(0, np.uint32), path_xy=np.zeros((0, 2), np.float32))
    )
    data_np = encode(no_paths)
    data_wp = encode(msg)
    n = max(a.n, 1)
    return {
        "decode_ms": round(median_ms(lambda: decode(data_wp), 30), 4),
        "bytes_per_agent": round(len(data_np) / n, 2),
        "bytes_per_agent_with_paths": round(len(data_wp) / n, 2),
        "path_points_per_agent": round(len(a.path_xy) / n, 2),
        "encode_ms_no_paths": round(median_ms(lambda: encode(no_paths), 30), 4),
        "decode_ms_no_paths": round(median_ms(lambda: decode(data_np), 30), 4),
    }


def bench_one(sumocfg: Path, target: int, steps: int, warmup_max: int = 3000, seed: int = 42) -> dict:
    import zenoh

    from protocol.keys import Keys

    cfg = SumoConfig(sumocfg=sumocfg)
    sim = SumoSim(cfg, seed=seed, run_id="bench")
    sim.start()
    pub_s, sub_s = _sessions()
    keys = Keys("sumoco", "bench")
    sink = _Sink()
    sub = sub_s.declare_subscriber(keys.step, sink)
    publisher = pub_s.declare_publisher(
        keys.step, congestion_control=zenoh.CongestionControl.BLOCK, express=True
    )
    deadline = time.monotonic() + 10.0
    while not publisher.matching_status and time.monotonic() < deadline:
        time.sleep(0.01)
    try:
        bridge = Bridge(sim, cfg, "bench")
        # Warm up: let the network fill to the target size (and the path cache with it).
        k, _ = fill(sim, bridge, target, warmup_max)
        walks0 = bridge.planner.resolved
        t, msg = _timed_steps(sim, bridge, publisher, k, steps)
        codec = _codec_figures(msg)
        ms = lambda xs: round(float(np.mean(xs)) * 1e3, 3)  # noqa: E731
        bridge_each = sum(np.array(t[name]) for name in ("read", "build", "encode", "publish", "gc"))
        wait_end = time.monotonic() + 5.0
        while sink.count < steps and time.monotonic() < wait_end:
            time.sleep(0.01)
        agents = t["agents"]
        return {
            "scenario": sumocfg.parent.name,
            "agents": int(round(float(np.mean(agents)))),
            "agents_min": int(min(agents)),
            "agents_max": int(max(agents)),
            "steps": steps,
            "warmup_steps": k + 1,
            "sumo_step_ms": ms(t["sumo"]),
            "bridge_ms": round(float(np.mean(bridge_each)) * 1e3, 3),
            "bridge_ms_p95": round(float(np.percentile(bridge_each, 95)) * 1e3, 3),
            "bridge_to_sumo_ratio": round(float(np.mean(bridge_each) / max(np.mean(t["sumo"]), 1e-12)), 3),
            "read_ms": ms(t["read"]),
            "lookahead_build_ms": ms(t["build"]),
            "encode_ms": ms(t["encode"]),
            "publish_ms": ms(t["publish"]),
            "gc_ms": ms(t["gc"]),
            **codec,
            "lane_walks_per_step": round((bridge.planner.resolved - walks0) / steps, 2),
            "received": sink.count,
        }
    finally:
        for obj in (sub, publisher):
            try:
                obj.undeclare()
            except Exception:
                pass
        pub_s.close()
        sub_s.close()
        sim.close()


#: [agents] from this size on a row measures fewer steps (SUMO alone takes ~150 ms per step)
LARGE_AGENTS = 10_000
LARGE_STEPS = 100
QUICK_MAX_AGENTS = 2_500  # ``--quick`` leaves the largest size out


def run_sumo_bench(sizes=(250, 2500, 10_000), steps: int | None = None, quick: bool = False,
                   seed: int = 42) -> list[dict]:
    """One row per scenario size (about ``size`` vehicles in the network), with the host's
    load average (other processes share the cores the row measures)."""
    import os

    steps = steps or (30 if quick else 300)
    rows = []
    for size in sizes:
        if quick and size > QUICK_MAX_AGENTS:
            continue
        cfg = grid_scenario(size, seed=seed)
        log.info("bench sumo: %d agents target, scenario %s", size, cfg)
        n = min(steps, LARGE_STEPS) if size >= LARGE_AGENTS else steps
        rows.append({"target_agents": size, **bench_one(Path(cfg), size, n, seed=seed),
                     "load_avg_1min": round(os.getloadavg()[0], 2)})
    return rows
