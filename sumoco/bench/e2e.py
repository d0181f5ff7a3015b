"""End-to-end latency against raw Zenoh moving the same bytes between the same two processes.

One publisher process (this one) and one subscriber process (``python -m
sumoco.bench.e2e --sub``) exchange two interleaved streams in the same run, on two
keys with the SUMO daemon's publisher settings (``STEP_PUT``):

- ``raw``: the already-encoded step bytes. Sent stamp just before ``put``; received stamp
  in the subscriber callback once the payload is Python bytes (``to_bytes``, which any
  Python receiver needs). This is the limit: Zenoh alone.
- ``e2e``: the same step as the SUMO side sends it. Sent stamp just before ``encode``
  (the message built from numpy columns just before, as the bridge does); received stamp once the physics side's receive
  path has decoded it: callback -> ``to_bytes`` -> bounded ``DropOldest`` queue -> wake the
  main loop (``runtime.transport.Wake``) -> ``decode_as`` with the daemon's limits
  (``physics_side.daemon``). As in the daemon's loop, the previous step is released only
  after the next one is decoded (and stamped).

Per-phase columns (medians): ``encode`` on the publisher; ``handoff`` from the callback's
put to the main loop holding the bytes, of which ``wake`` is the wake-up alone (callback's
put to the main loop running again after its wait); ``decode``.

Each row names its ``codec``: ``c`` (the C fast path of ``protocol.codec``) or ``python``
(``SUMOCO_PURE_CODEC=1``: the publisher calls ``encode_python``, the subscriber process is
started with the variable set); ``run_e2e_bench`` measures both in one run when the C path
is built.

The ``busy_poll`` pair (rows with ``"pair": "busy_poll"``): the default receive path and,
right after it, the subscriber polling a ring of steps as a daemon with
``physics.busy_poll_ms`` does (``runtime.transport.RingPoll``, window ``BUSY_POLL_ROW_MS``:
it spins from one step to the next, a core busy; ``spins`` counts its passes).

Both processes run with the daemons' process settings (``runtime.hotpath``). CLOCK_MONOTONIC is shared by all processes of one host, so the difference of
two stamps is the one-way latency. Messages alternate raw / e2e half a period apart, so
machine load hits both streams alike; the row carries both and their ratio.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import subprocess
import sys
import threading
import time
from typing import NamedTuple

import numpy as np
import zenoh

from protocol.codec import FAST_CODEC, DecodeLimits, decode_as, encode, encode_python
from protocol.keys import Keys
from protocol.messages import StepMessage
from runtime.config import ZenohConfig
from runtime.hotpath import freeze_startup_objects, tune_allocator
from runtime.queues import DropOldest
from runtime.transport import RingPoll, Wake, free_tcp_port, open_session
from synthetic.traffic import synthetic_step

KEYS = Keys("sumocobench", "e2e")
RAW_KEY = f"{KEYS.base}/raw/step"
#: The SUMO daemon's step publisher settings (sumo_side.daemon): never dropped, not batched.
STEP_PUT = {"congestion_control": zenoh.CongestionControl.BLOCK, "express": True}
#: [ms] the busy-poll rows' window: longer than the 20 ms between two steps, so the subscriber
#: spins from one step to the next, as a lockstep daemon whose window covers SUMO's step
BUSY_POLL_ROW_MS = 25.0


def _percentiles(a: np.ndarray) -> tuple[float | None, float | None, float | None]:
    if not len(a):
        return None, None, None
    return (round(float(np.percentile(a, 50)), 4), round(float(np.percentile(a, 99)), 4),
            round(float(a.max()), 4))


def _median_ms(ns: list[int], skip: int) -> float | None:
    a = np.asarray(ns, float)[skip:]
    return round(float(np.median(a)) / 1e6, 4) if len(a) else None


def _subscriber(connect: str, shm: bool, count: int, timeout_s: float, max_agents: int,
                busy_poll_ms: float = 0.0) -> None:
    cfg = ZenohConfig(listen=(f"tcp/127.0.0.1:{free_tcp_port()}",), connect=(connect,), shared_memory=shm)
    raw_at: list[int] = []
    e2e_at: dict[int, int] = {}
    decode_ns: list[int] = []
    decode_cpu_ns: list[int] = []
    handoff_ns: list[int] = []
    wake_ns: list[int] = []  # part of the hand-off: until the main loop runs again after its wait
    woke = [0]
    steps: DropOldest[tuple[bytes, int]] = DropOldest(64, 256 << 20, size=lambda item: len(item[0]))
    wake = Wake()  # as PhysicsDaemon._wake
    stop = threading.Event()
    limits = DecodeLimits.for_agents(max_agents)

    def on_raw(sample: zenoh.Sample) -> None:
        sample.payload.to_bytes()
        raw_at.append(time.monotonic_ns())  # Zenoh keeps one publisher's order: index = arrival

    def on_step(sample: zenoh.Sample) -> None:  # as PhysicsDaemon._on_step
        data = sample.payload.to_bytes()
        steps.put((data, time.monotonic_ns()))
        wake.set()

    poll: list[RingPoll] = []  # busy_poll_ms > 0: the step subscriber's ring (PhysicsDaemon._poll)

    def main_loop() -> None:  # as PhysicsDaemon.run in lockstep: wait, take one step, decode
        held: list[StepMessage] = []
        while not stop.is_set():
            if poll:
                poll[0].pull()
            if not steps:
                if poll:  # as PhysicsDaemon._idle
                    poll[0].wait(stop, 0.05, wake)
                else:
                    wake.wait(0.05)
                woke[0] = time.monotonic_ns()
                wake.clear()
                continue
            data, landed = steps.get()
            t0 = time.monotonic_ns()
            handoff_ns.append(t0 - landed)
            if woke[0] >= landed:  # (it waited for this step)
                wake_ns.append(woke[0] - landed)
            c0 = time.thread_time_ns()
            msg = decode_as(data, StepMessage, limits)
            t1 = time.monotonic_ns()
            e2e_at[msg.step] = t1
            decode_ns.append(t1 - t0)
            decode_cpu_ns.append(time.thread_time_ns() - c0)
            # The daemon's loop holds the previous step until the next one is decoded and
            # applied (``msg = self.handle_step(...)``): it is released here, after the stamp.
            held[:] = [msg]
            if poll:
                poll[0].arm()  # as the daemon after its ack: the next step is due

    tune_allocator()
    freeze_startup_objects()
    with open_session(cfg) as s:
        if busy_poll_ms > 0:
            poll.append(RingPoll(s, KEYS.step, 64, busy_poll_ms / 1e3, on_step))
        worker = threading.Thread(target=main_loop, daemon=True)
        worker.start()
        subs = [s.declare_subscriber(RAW_KEY, on_raw), *poll] if poll else \
            [s.declare_subscriber(RAW_KEY, on_raw), s.declare_subscriber(KEYS.step, on_step)]
        tok = s.liveliness().declare_token(KEYS.physics_alive)
        deadline = time.monotonic() + timeout_s
        while (len(raw_at) < count or len(e2e_at) < count) and time.monotonic() < deadline:
            time.sleep(0.05)
        stop.set()
        worker.join(1.0)
        tok.undeclare()
        for sub in subs:
            sub.undeclare()
    json.dump({"raw": raw_at, "e2e": e2e_at, "decode_ns": decode_ns, "decode_cpu_ns": decode_cpu_ns,
               "handoff_ns": handoff_ns, "wake_ns": wake_ns, "codec": "c" if FAST_CODEC else "python",
               "spins": poll[0].spins if poll else 0}, sys.stdout)


class _Sent(NamedTuple):
    """The publisher's side of one row: send stamps [ns] and the encode cost of the e2e stream."""

    raw: list[int]
    e2e: list[int]
    encode_ns: list[int]
    encode_cpu_ns: list[int]


def _exchange(cfg: ZenohConfig, ep: str, build, agents: int, shm: bool, steps: int, period_s: float,
              codec: str = "c", busy_poll_ms: float = 0.0) -> tuple[_Sent, dict]:
    """Start the subscriber process, then send ``steps`` of both streams half a period apart;
    the subscriber's receive stamps and costs (its JSON) with our send stamps."""
    sent = _Sent([], [], [], [])
    enc = encode if codec == "c" else encode_python
    env = dict(os.environ, SUMOCO_PURE_CODEC="0" if codec == "c" else "1")
    with open_session(cfg) as s:
        pub_raw = s.declare_publisher(RAW_KEY, **STEP_PUT)
        pub = s.declare_publisher(KEYS.step, **STEP_PUT)
        alive = s.liveliness().declare_subscriber(KEYS.physics_alive, history=True)
        proc = subprocess.Popen(
            [sys.executable, "-m", "sumoco.bench.e2e", "--sub", ep, "--count", str(steps),
             "--timeout", str(steps * period_s + 30), "--max-agents", str(agents), "--busy-poll-ms", str(busy_poll_ms)]
            + (["--shm"] if shm else []),
            stdout=subprocess.PIPE, env=env,
        )
        try:
            if alive.recv() is None:  # blocks until the subscriber's token arrives
                raise RuntimeError("subscriber never came up")
            deadline = time.monotonic() + 10.0
            while not (pub.matching_status.matching and pub_raw.matching_status.matching):
                if time.monotonic() > deadline:
                    raise RuntimeError("subscriber's subscriptions never reached the publisher")
                time.sleep(0.01)
            half = period_s / 2
            nxt = time.monotonic()
            for i in range(steps):
                nxt += half
                wire = encode(build(i))
                sent.raw.append(time.monotonic_ns())
                pub_raw.put(wire)
                time.sleep(max(0.0, nxt - time.monotonic()))
                nxt += half
                msg = build(i)
                t0 = time.monotonic_ns()
                sent.e2e.append(t0)
                c0 = time.thread_time_ns()
                data = enc(msg)
                sent.encode_cpu_ns.append(time.thread_time_ns() - c0)
                sent.encode_ns.append(time.monotonic_ns() - t0)
                pub.put(data)
                time.sleep(max(0.0, nxt - time.monotonic()))
            out, _ = proc.communicate(timeout=steps * period_s + 60)
        finally:
            if proc.poll() is None:
                proc.kill()
            gc.unfreeze()
    return sent, json.loads(out or b"{}")


def measure(agents: int, shm: bool, steps: int = 300, period_s: float = 0.02, warmup: int = 20,
            path_points: int = 12, codec: str = "c", busy_poll_ms: float = 0.0) -> dict:
    """One row: raw and end-to-end latency at ``agents``, measured in the same run, with the
    ``codec`` ``c`` or ``python`` on both sides; ``busy_poll_ms`` > 0: the subscriber polls
    its steps as the daemon does with ``physics.busy_poll_ms``."""
    if codec not in ("c", "python") or (codec == "c" and not FAST_CODEC):
        raise ValueError(f"codec {codec!r} not available (the C fast path is {'on' if FAST_CODEC else 'off'})")
    load_before = os.getloadavg()[0]
    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    cfg = ZenohConfig(listen=(ep,), shared_memory=shm)
    def build(i: int):
        # Built just before it is sent, as the SUMO side's bridge builds each step: the
        # arrays are fresh in cache for both streams (a few seeds: no repeat is cheaper).
        return synthetic_step(agents, seed=i % 4, step=i, path_points=path_points)

    nbytes = len(encode(build(0)))
    tune_allocator()
    freeze_startup_objects()
    sent, got = _exchange(cfg, ep, build, agents, shm, steps, period_s, codec, busy_poll_ms)
    if got.get("codec", codec) != codec:
        raise RuntimeError(f"subscriber decoded with {got['codec']}, not {codec}")
    raw_at = got.get("raw", [])
    e2e_at = {int(k): v for k, v in got.get("e2e", {}).items()}
    raw = np.array([(raw_at[i] - sent.raw[i]) / 1e6 for i in range(warmup, min(steps, len(raw_at)))])
    e2e = np.array([(e2e_at[i] - sent.e2e[i]) / 1e6 for i in range(warmup, steps) if i in e2e_at])
    r50, r99, rmax = _percentiles(raw)
    e50, e99, emax = _percentiles(e2e)
    dec = np.asarray(got.get("decode_ns", []), float)[warmup:] / 1e6
    enc = np.asarray(sent.encode_ns, float)[warmup:] / 1e6
    hand = np.asarray(got.get("handoff_ns", []), float)[warmup:] / 1e6
    woke = np.asarray(got.get("wake_ns", []), float)[warmup:] / 1e6
    return {
        "agents": agents,
        "path_points_per_agent": path_points,
        "codec": codec,
        "shm": shm,
        # the subscriber's busy-poll window after each step [ms] (0: woken by the callback);
        # ``spins``: its passes over an empty ring (it holds a core while it spins)
        "busy_poll_ms": busy_poll_ms,
        "spins": got.get("spins", 0),
        "bytes": nbytes,
        "sent": steps,
        "received_raw": len(raw_at),
        "received_e2e": len(e2e_at),
        "raw_ms_p50": r50, "raw_ms_p99": r99, "raw_ms_max": rmax,
        "latency_ms_p50": e50, "latency_ms_p99": e99, "latency_ms_max": emax,
        "ratio_p50": round(e50 / r50, 3) if e50 and r50 else None,
        "ratio_p99": round(e99 / r99, 3) if e99 and r99 else None,
        "encode_ms_p50": round(float(np.median(enc)), 4) if len(enc) else None,
        "decode_ms_p50": round(float(np.median(dec)), 4) if len(dec) else None,
        "handoff_ms_p50": round(float(np.median(hand)), 4) if len(hand) else None,
        # of the hand-off, the wake-up alone: callback's put to the main loop running again
        "wake_ms_p50": round(float(np.median(woke)), 4) if len(woke) else None,
        # CPU time of the same calls: wall minus CPU is time spent waiting for a core
        "encode_cpu_ms_p50": _median_ms(sent.encode_cpu_ns, warmup),
        "decode_cpu_ms_p50": _median_ms(got.get("decode_cpu_ns", []), warmup),
        # 1-minute load average before and after the row: other processes share the cores,
        # and every cost here after an idle wait is cold-cache cost, which load inflates
        "loadavg_1m": [round(load_before, 2), round(os.getloadavg()[0], 2)],
    }


def run_e2e_bench(sizes=(100, 1000), quick: bool = False) -> list[dict]:
    """Rows for steps without paths and with the SUMO side's 12 path points per agent,
    over TCP and shared memory, with the C codec and the Python one (when the C one is built);
    then with 12 path points over TCP, the subscriber busy-polling (``BUSY_POLL_ROW_MS``)
    and the default rows again beside them (the two in turn, as the host's load drifts)."""
    steps = 60 if quick else 300
    codecs = ("c", "python") if FAST_CODEC else ("python",)
    rows = [measure(n, shm, steps=steps, path_points=pts, codec=c)
            for n in sizes for pts in (0, 12) for shm in (False, True) for c in codecs]
    for n in sizes[:1] if quick else sizes:
        for window in (0.0, BUSY_POLL_ROW_MS):
            rows.append({**measure(n, False, steps=steps, path_points=12, codec=codecs[0], busy_poll_ms=window),
                         "pair": "busy_poll"})
    return rows


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--sub")
    ap.add_argument("--count", type=int, default=100)
    ap.add_argument("--timeout", type=float, default=60)
    ap.add_argument("--max-agents", type=int, default=10_000)
    ap.add_argument("--busy-poll-ms", type=float, default=0.0)
    ap.add_argument("--shm", action="store_true")
    a = ap.parse_args()
    if a.sub:
        _subscriber(a.sub, a.shm, a.count, a.timeout, a.max_agents, a.busy_poll_ms)
    else:
        print(json.dumps(run_e2e_bench(), indent=1))
