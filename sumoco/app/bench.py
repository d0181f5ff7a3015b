"""``sumoco bench {sumo,physics,e2e,codec,fidelity,scenarios,...} --json``: benchmark rows as JSON on stdout.

Benchmarks measure speed; tests check correctness. Each area owns its benchmark
function (``sumo_side.bench``, ``physics_side.bench``, ``sumoco.app.e2e_bench``); this module
only dispatches and prints.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from protocol.codec import decode, encode
from sumoco.testing.synthetic import synthetic_step


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
    if args.what == "soak":  # streams one row per minute instead of one list at the end
        from sumoco.app.soak import cli_main as soak_main

        return soak_main(args)
    if args.what == "codec":
        rows = run_codec_bench(repeat=20 if quick else 200)
    elif args.what == "sumo":
        from sumo_side.bench import run_sumo_bench

        rows = run_sumo_bench(quick=quick)
    elif args.what == "physics":
        from physics_side.bench import run_physics_bench

        rows = run_physics_bench(quick=quick)
    elif args.what == "fidelity":
        from sumoco.app.fidelity_bench import run_fidelity_bench

        rows = run_fidelity_bench(quick=quick)
    elif args.what == "record":
        from sumoco.app.record_bench import run_record_bench

        rows = run_record_bench(quick=quick)
    elif args.what == "gateway":
        from sumoco.app.record_bench import run_gateway_bench

        rows = run_gateway_bench(quick=quick)
    elif args.what == "scenarios":
        from sumoco.app.scenario_bench import run_scenario_bench

        rows = run_scenario_bench(getattr(args, "pack", None), getattr(args, "duration", None) or 60.0,
                                  quick=quick, out_root=getattr(args, "out", None))
    elif args.what == "e2e":
        from sumoco.app.e2e_bench import run_e2e_bench

        rows = run_e2e_bench(quick=quick)
    else:  # pragma: no cover
        raise ValueError(args.what)
    json.dump(rows, sys.stdout, indent=1)
    sys.stdout.write("\n")
    return 0
