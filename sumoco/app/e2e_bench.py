"""End-to-end latency: SUMO-side publish to physics-side decoded, two OS processes.

The publisher (this process) stamps each step index with ``time.monotonic_ns()`` just
before ``put``; a subscriber process (``python -m sumoco.app.e2e_bench --sub``) stamps the
same index when ``decode`` returns. CLOCK_MONOTONIC is shared by all processes of one
host, so the difference is the one-way latency including encode-free transport and decode.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time

import numpy as np
import zenoh

from protocol.codec import decode, encode
from protocol.keys import Keys
from sumoco.testing.synthetic import synthetic_step
from sumoco.common.config import ZenohConfig
from sumoco.common.transport import free_tcp_port, open_session

KEYS = Keys("sumocobench", "e2e")


def _subscriber(connect: str, shm: bool, count: int, timeout_s: float) -> None:
    cfg = ZenohConfig(listen=(f"tcp/127.0.0.1:{free_tcp_port()}",), connect=(connect,), shared_memory=shm)
    stamps: dict[int, int] = {}
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        # Decode right where the sample lands (as the physics side's receive path does).
        msg = decode(sample.payload.to_bytes())
        stamps[msg.step] = time.monotonic_ns()
        if len(stamps) >= count:
            done.set()

    with open_session(cfg) as s:
        sub = s.declare_subscriber(KEYS.step, on_sample)
        tok = s.liveliness().declare_token(KEYS.physics_alive)
        done.wait(timeout_s)
        tok.undeclare()
        sub.undeclare()
    json.dump(stamps, sys.stdout)


def measure(agents: int, shm: bool, steps: int = 300, period_s: float = 0.02, warmup: int = 20) -> dict:
    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    cfg = ZenohConfig(listen=(ep,), shared_memory=shm)
    msgs = [encode(synthetic_step(agents, seed=i % 4, step=i)) for i in range(steps)]
    sent: dict[int, int] = {}
    with open_session(cfg) as s:
        pub = s.declare_publisher(KEYS.step, congestion_control=zenoh.CongestionControl.BLOCK)
        alive = s.liveliness().declare_subscriber(KEYS.physics_alive, history=True)
        proc = subprocess.Popen(
            [sys.executable, "-m", "sumoco.app.e2e_bench", "--sub", ep, "--count", str(steps),
             "--timeout", str(steps * period_s + 30)] + (["--shm"] if shm else []),
            stdout=subprocess.PIPE,
        )
        try:
            if alive.recv() is None:  # blocks until the subscriber's token arrives
                raise RuntimeError("subscriber never came up")
            time.sleep(0.3)  # let the subscription declaration reach this session
            nxt = time.monotonic()
            for i, data in enumerate(msgs):
                nxt += period_s
                sent[i] = time.monotonic_ns()
                pub.put(data)
                time.sleep(max(0.0, nxt - time.monotonic()))
            out, _ = proc.communicate(timeout=steps * period_s + 60)
        finally:
            if proc.poll() is None:
                proc.kill()
    got = {int(k): v for k, v in json.loads(out or b"{}").items()}
    lat = np.array([(got[i] - sent[i]) / 1e6 for i in range(warmup, steps) if i in got])
    return {
        "agents": agents,
        "shm": shm,
        "bytes": len(msgs[0]),
        "received": len(got),
        "sent": steps,
        "latency_ms_p50": round(float(np.percentile(lat, 50)), 4) if len(lat) else None,
        "latency_ms_p99": round(float(np.percentile(lat, 99)), 4) if len(lat) else None,
        "latency_ms_max": round(float(lat.max()), 4) if len(lat) else None,
    }


def run_e2e_bench(sizes=(100, 1000), quick: bool = False) -> list[dict]:
    steps = 60 if quick else 300
    return [measure(n, shm, steps=steps) for n in sizes for shm in (False, True)]


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--sub")
    ap.add_argument("--count", type=int, default=100)
    ap.add_argument("--timeout", type=float, default=60)
    ap.add_argument("--shm", action="store_true")
    a = ap.parse_args()
    if a.sub:
        _subscriber(a.sub, a.shm, a.count, a.timeout)
    else:
        print(json.dumps(run_e2e_bench(), indent=1))
