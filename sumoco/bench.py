"""``sumoco bench {sumo,physics,e2e,codec} --json``: benchmark rows as JSON on stdout.

Benchmarks measure speed; tests check correctness. Each area owns its benchmark
function (``sumo_side.bench``, ``physics_side.bench``, ``sumoco.e2e_bench``); this module
only dispatches and prints.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from protocol.codec import decode, encode
from protocol.messages import AgentBatch, AgentClass, StepMessage, TrafficLights, VType


def synthetic_step(n: int, seed: int = 0, path_points: int = 0, step: int = 1) -> StepMessage:
    """A StepMessage of ``n`` plausible agents (ids like SUMO's randomTrips ids)."""
    rng = np.random.default_rng(seed)
    f32 = np.float32
    ids = [f"veh{i}" for i in range(n)]
    x = rng.uniform(0, 2000, n)
    y = rng.uniform(0, 2000, n)
    off = np.arange(n + 1, dtype=np.uint32) * path_points
    xy = (rng.uniform(0, 2000, (n * path_points, 2))).astype(f32)
    agents = AgentBatch(
        ids=ids,
        cls=rng.integers(0, len(AgentClass), n).astype(np.uint8),
        vtype=np.zeros(n, np.uint16),
        x=x, y=y,
        angle=rng.uniform(0, 360, n).astype(f32),
        speed=rng.uniform(0, 15, n).astype(f32),
        accel=rng.uniform(-3, 3, n).astype(f32),
        signals=rng.integers(0, 16, n).astype(np.uint16),
        la_x=(x + 7).astype(f32), la_y=(y + 1).astype(f32),
        length=np.full(n, 5.0, f32), width=np.full(n, 1.8, f32),
        lane=rng.integers(0, 500, n).astype(np.int32),
        flags=np.zeros(n, np.uint8),
        path_offsets=off if path_points else np.zeros(0, np.uint32),
        path_xy=xy if path_points else np.zeros((0, 2), f32),
    )
    return StepMessage("bench", step, step * 0.1, 0.1, agents, TrafficLights.empty(),
                       [VType("DEFAULT_VEHTYPE", "passenger")])


def _best_ms(fn, repeat: int) -> float:
    """Median wall time of ``fn`` over ``repeat`` calls [ms]."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def run_codec_bench(sizes=(250, 1000, 2500), repeat: int = 200) -> list[dict]:
    rows = []
    for n in sizes:
        for pts in (0, 12):
            msg = synthetic_step(n, path_points=pts)
            data = encode(msg)
            rows.append({
                "agents": n,
                "path_points_per_agent": pts,
                "bytes": len(data),
                "bytes_per_agent": round(len(data) / n, 2),
                "encode_ms": round(_best_ms(lambda: encode(msg), repeat), 4),
                "decode_ms": round(_best_ms(lambda: decode(data), repeat), 4),
            })
    return rows


def cli_main(args) -> int:
    quick = bool(getattr(args, "quick", False))
    if args.what == "codec":
        rows = run_codec_bench(repeat=20 if quick else 200)
    elif args.what == "sumo":
        from sumo_side.bench import run_sumo_bench

        rows = run_sumo_bench(quick=quick)
    elif args.what == "physics":
        from physics_side.bench import run_physics_bench

        rows = run_physics_bench(quick=quick)
    elif args.what == "e2e":
        from sumoco.e2e_bench import run_e2e_bench

        rows = run_e2e_bench(quick=quick)
    else:  # pragma: no cover
        raise ValueError(args.what)
    json.dump(rows, sys.stdout, indent=1)
    sys.stdout.write("\n")
    return 0
