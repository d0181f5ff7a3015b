"""``sumoco bench {sumo,physics,coupling,e2e,codec,fidelity,scenarios,generated,viewer,...} --json``: benchmark rows as JSON on stdout.

Benchmarks measure speed; tests check correctness. Each area owns its benchmark
function (``sumoco.bench.sumo``, ``sumoco.bench.physics``, ``sumoco.bench.e2e``); this module
only dispatches and prints.
"""

from __future__ import annotations

import json
import sys

import msgpack
import numpy as np

from protocol.codec import FAST_CODEC, decode, decode_python, encode, encode_python
from sumoco.bench.timing import median_ms
from synthetic.traffic import circle_traffic, synthetic_step


def run_codec_bench(sizes=(250, 1000, 2500), repeat: int = 200) -> list[dict]:
    """Hot-loop encode and decode of synthetic steps, with the C fast path (``codec`` ``c``,
    when built) and the Python codec (``python``)."""
    codecs = {"python": (encode_python, decode_python)}
    if FAST_CODEC:
        codecs = {"c": (encode, decode), **codecs}
    rows = []
    for n in sizes:
        for pts in (0, 12):
            msg = synthetic_step(n, path_points=pts)
            data = encode(msg)
            for name, (enc, dec) in codecs.items():
                rows.append({
                    "case": "synthetic",
                    "codec": name,
                    "agents": n,
                    "path_points_per_agent": pts,
                    "bytes": len(data),
                    "bytes_per_agent": round(len(data) / n, 2),
                    "encode_ms": round(median_ms(lambda: enc(msg), repeat), 4),
                    "decode_ms": round(median_ms(lambda: dec(data), repeat), 4),
                })
    return rows + run_position_encoding_bench(repeat=repeat)


def _absolute_f64(wire: dict, a) -> dict:
    """The step of ``wire`` with look-ahead points and paths as absolute float64 (the
    alternative to protocol 1.2's float32 offsets, for comparison only)."""
    ag = {k: v for k, v in wire["agents"].items() if k not in ("la_dx", "la_dy", "path")}
    ag["la_x"] = np.asarray(a.la_x, "<f8").tobytes()
    ag["la_y"] = np.asarray(a.la_y, "<f8").tobytes()
    ag["path"] = {"off": np.asarray(a.path_offsets, "<u4").tobytes(), "xy": np.asarray(a.path_xy, "<f8").tobytes()}
    return {**wire, "agents": ag}


def run_position_encoding_bench(sizes=(1000, 2500), repeat: int = 200) -> list[dict]:
    """Float32 offsets from each agent's float64 position (protocol 1.2) against absolute
    float64, at UTM-sized coordinates with 12 path points per agent (SPEC.md 6). Encode and
    decode time the look-ahead points and paths only: packing them and building the
    absolute float64 arrays a receiver needs; ``codec_*`` is the whole message."""
    rows = []
    for n in sizes:
        msg = circle_traffic(n, 5, centre=(691_000.0, 5_335_000.0))
        a = msg.agents
        wire = encode(msg)
        doc = msgpack.unpackb(wire, raw=False)
        w64 = msgpack.packb(_absolute_f64(doc, a), use_bin_type=True)
        off = np.asarray(a.path_offsets, np.int64)
        counts = np.diff(off)

        def enc_offsets():
            dxy = np.empty(a.path_xy.shape, np.float32)
            dxy[:, 0] = a.path_xy[:, 0] - np.repeat(a.x, counts)
            dxy[:, 1] = a.path_xy[:, 1] - np.repeat(a.y, counts)
            return msgpack.packb([(a.la_x - a.x).astype("<f4").tobytes(), (a.la_y - a.y).astype("<f4").tobytes(),
                                  dxy.tobytes()])

        def enc_f64():
            return msgpack.packb([np.asarray(a.la_x, "<f8").tobytes(), np.asarray(a.la_y, "<f8").tobytes(),
                                  np.asarray(a.path_xy, "<f8").tobytes()])

        def dec_offsets():
            ag = msgpack.unpackb(wire, raw=False)["agents"]
            x, y = np.frombuffer(ag["x"], "<f8"), np.frombuffer(ag["y"], "<f8")
            lx, ly = x + np.frombuffer(ag["la_dx"], "<f4"), y + np.frombuffer(ag["la_dy"], "<f4")
            c = np.diff(np.frombuffer(ag["path"]["off"], "<u4").astype(np.int64))
            xy = np.frombuffer(ag["path"]["dxy"], "<f4").reshape(-1, 2).astype(np.float64)
            xy[:, 0] += np.repeat(x, c)
            xy[:, 1] += np.repeat(y, c)
            return lx, ly, xy

        def dec_f64():
            ag = msgpack.unpackb(w64, raw=False)["agents"]
            return (np.frombuffer(ag["la_x"], "<f8"), np.frombuffer(ag["la_y"], "<f8"),
                    np.frombuffer(ag["path"]["xy"], "<f8").reshape(-1, 2))

        out = decode(wire).agents
        err = max(np.abs(out.path_xy - a.path_xy).max(), np.abs(out.la_x - a.la_x).max(), np.abs(out.la_y - a.la_y).max())
        rows.append({
            "case": "positions_utm",
            "agents": n,
            "path_points_per_agent": int(len(a.path_xy) // n),
            "f64_bytes_per_agent": round(len(w64) / n, 1),
            "offsets_bytes_per_agent": round(len(wire) / n, 1),
            "f64_encode_ms": round(median_ms(enc_f64, repeat), 4),
            "offsets_encode_ms": round(median_ms(enc_offsets, repeat), 4),
            "f64_decode_ms": round(median_ms(dec_f64, repeat), 4),
            "offsets_decode_ms": round(median_ms(dec_offsets, repeat), 4),
            "codec_encode_ms": round(median_ms(lambda: encode(msg), repeat), 4),
            "codec_decode_ms": round(median_ms(lambda: decode(wire), repeat), 4),
            "offsets_max_error_mm": round(float(err) * 1e3, 4),
        })
    return rows


def cli_main(args) -> int:
    quick = bool(getattr(args, "quick", False))
    if args.what == "soak":  # streams one row per minute instead of one list at the end
        from sumoco.bench.soak import cli_main as soak_main

        return soak_main(args)
    if args.what == "codec":
        rows = run_codec_bench(repeat=20 if quick else 200)
    elif args.what == "sumo":
        from sumoco.bench.coupling import run_coupling_bench
        from sumoco.bench.sumo import run_sumo_bench

        # with the two-way write-back's cost (feedback_ms against SUMO's own step) beside it
        rows = run_sumo_bench(quick=quick) + run_coupling_bench(quick=quick)
    elif args.what == "physics":
        from sumoco.bench.physics import run_physics_bench

        rows = run_physics_bench(quick=quick)
    elif args.what == "fidelity":
        from sumoco.bench.fidelity import run_fidelity_bench

        rows = run_fidelity_bench(quick=quick)
    elif args.what == "record":
        from sumoco.bench.record import run_record_bench

        rows = run_record_bench(quick=quick)
    elif args.what == "gateway":
        from sumoco.bench.record import run_gateway_bench

        rows = run_gateway_bench(quick=quick)
    elif args.what == "scenarios":
        from sumoco.bench.scenarios import run_scenario_bench

        rows = run_scenario_bench(getattr(args, "pack", None), getattr(args, "duration", None) or 60.0,
                                  quick=quick, out_root=getattr(args, "out", None),
                                  authority=getattr(args, "authority", None))
    elif args.what == "generated":
        from sumoco.bench.generated import run_generated_bench

        rows = run_generated_bench(getattr(args, "duration", None) or 60.0, quick=quick,
                                   out_root=getattr(args, "out", None), pack=getattr(args, "pack", None),
                                   nets=tuple(getattr(args, "net", None) or ()))
    elif args.what == "scale":
        from sumoco.bench.scale import run_scale_bench

        rows = run_scale_bench(quick=quick)
    elif args.what == "takeover":
        from sumoco.bench.scale import takeover_bench

        rows = takeover_bench(getattr(args, "runs", None) or 20)
    elif args.what == "viewer":
        from sumoco.bench.viewer import run_viewer_bench

        counts = getattr(args, "agents", None)
        rows = run_viewer_bench(tuple(int(x) for x in counts.split(",")) if counts else None,
                                getattr(args, "duration", None), quick=quick)
    elif args.what == "coupling":
        from sumoco.bench.coupling import run_coupling_bench

        rows = run_coupling_bench(quick=quick)
    elif args.what == "e2e":
        from sumoco.bench.e2e import run_e2e_bench

        rows = run_e2e_bench(quick=quick)
    else:  # pragma: no cover
        raise ValueError(args.what)
    json.dump(rows, sys.stdout, indent=1)
    sys.stdout.write("\n")
    return 0
