"""``sumoco bench scale --quick`` and ``sumoco bench e2e --quick`` as OS processes: they run,
and every row is JSON with the fields the READMEs and the issue name.

No speed limits here: speed is what the benchmarks print, not what the tests check.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

from protocol.codec import FAST_CODEC
from tests.harness import ROOT

pytestmark = pytest.mark.integration


def _no_constant(name: str):
    raise ValueError(f"{name} in a bench row")  # NaN / Infinity are not JSON


def _bench(what: str, timeout_s: float) -> list[dict]:
    out = subprocess.run([sys.executable, "-m", "sumoco.cli", "bench", what, "--quick", "--json"], cwd=ROOT,
                         capture_output=True, text=True, timeout=timeout_s, stdin=subprocess.DEVNULL)
    assert out.returncode == 0, out.stderr[-4000:]
    rows = json.loads(out.stdout, parse_constant=_no_constant)
    assert isinstance(rows, list) and rows, out.stdout[-2000:]
    for r in rows:
        assert isinstance(r, dict), r
        assert "error" not in r, r
    return rows


def _positive(row: dict, *fields: str) -> None:
    for f in fields:
        v = row.get(f)
        assert isinstance(v, (int, float)) and not isinstance(v, bool), (f, row)
        assert math.isfinite(v) and v > 0, (f, row)


def _count(row: dict, field: str, minimum: int = 1) -> int:
    v = row.get(field)
    assert isinstance(v, int) and not isinstance(v, bool) and v >= minimum, (field, row)
    return v


def test_scale_bench_quick_rows():
    rows = _bench("scale", 420)
    pools = [r for r in rows if "pool_slots" in r]
    cosim = [r for r in rows if "lod" in r]
    shards = [r for r in rows if "shards" in r]
    realtime = [r for r in rows if r.get("timing") == "realtime"]
    lockstep = [r for r in rows if r.get("timing") == "lockstep"]
    processes = [r for r in rows if r.get("bench") == "scale_processes"]
    assert pools and cosim and shards and realtime and lockstep and processes, rows
    assert len(pools) + len(cosim) + len(shards) + len(realtime) + len(lockstep) + len(processes) == len(rows), rows

    for r in pools:
        _count(r, "pool_slots")
        _positive(r, "build_s", "rss_mb")

    assert {r["lod"] for r in cosim} == {False, True}, cosim
    for r in cosim:
        n = _count(r, "agents")
        full = _count(r, "full_physics_agents")
        assert full <= n + 1, r  # both are means over the steps
        if r["lod"]:
            assert full < n, r  # LOD keeps the agents outside its region out of MuJoCo
        _positive(r, "sumo_alone_steps_per_s", "cosim_steps_per_s", "bridge_ms", "sumo_step_ms", "physics_tick_ms",
                  "rss_mb")
        _count(r, "bytes_per_step")

    for r in shards:
        _count(r, "shards")
        # from wall time: how much load the host has decides it, so only its type is checked;
        # the CPU-time figure does not depend on other load
        _count(r, "agents_realtime", 0)
        _count(r, "agents_realtime_cpu")

    # one command per count (`sumoco physics --processes p`): it ended 0 after the final step
    assert [r["processes"] for r in processes] == [1, 2], processes
    for r in processes:
        _count(r, "agents_realtime", 0)
        assert r["exit_code"] == 0 and r["restarts"] == 0, r
        assert isinstance(r["vs_linear"], float) and isinstance(r["load_avg_1min"], float), r

    for r in lockstep:
        n = _count(r, "agents")
        assert _count(r, "full_physics_agents") < n, r
        _count(r, "steps")
        _positive(r, "sumo_alone_ms", "sumo_alone_cpu_ms", "lockstep_ms", "lockstep_cpu_ms", "lockstep_to_sumo_ratio",
                  "lockstep_to_sumo_cpu_ratio")

    for r in realtime:
        _count(r, "agents")
        _count(r, "lag_resets", 0)
        _count(r, "steps")


def test_e2e_bench_quick_rows():
    rows = _bench("e2e", 180)
    assert {(r["shm"], r["path_points_per_agent"]) for r in rows} == {(False, 0), (False, 12), (True, 0), (True, 12)}
    # a pair in turn: woken by the callback, and busy-polling as physics.busy_poll_ms does
    pair = [r for r in rows if r.get("pair") == "busy_poll"]
    assert [r["busy_poll_ms"] for r in pair] == [0.0, 25.0] and pair[0]["spins"] == 0 and pair[1]["spins"] > 0, pair
    # both codecs in the same run when the C fast path is built, the Python one alone otherwise
    assert {r["codec"] for r in rows} == ({"c", "python"} if FAST_CODEC else {"python"})
    for r in rows:
        _count(r, "agents")
        _count(r, "bytes")
        sent = _count(r, "sent")
        # the publisher blocks rather than drop a step (the SUMO daemon's settings)
        assert r["received_raw"] == sent and r["received_e2e"] == sent, r
        # raw Zenoh and end-to-end from the same run, beside their ratios
        _positive(r, "raw_ms_p50", "raw_ms_p99", "latency_ms_p50", "latency_ms_p99", "ratio_p50", "ratio_p99")
        assert r["raw_ms_p50"] <= r["raw_ms_p99"] and r["latency_ms_p50"] <= r["latency_ms_p99"], r
        _positive(r, "encode_ms_p50", "decode_ms_p50")


def test_process_rows_are_set_beside_what_bare_workers_reach_on_the_host():
    from sumoco.bench.scale import _beside_bare_workers

    rows = [{"shards": 1, "agents_realtime": 300}, {"shards": 2, "agents_realtime": 540, "vs_one_shard": 1.8},
            {"bench": "scale_processes", "processes": 1, "vs_linear": 1.0},
            {"bench": "scale_processes", "processes": 2, "vs_linear": 0.8},
            {"bench": "scale_processes", "processes": 4, "vs_linear": 0.7}]
    _beside_bare_workers(rows)
    one, two, four = rows[2:]
    assert two["bare_vs_one"] == 1.8 and two["vs_bare"] == 0.89  # 1.6x of the host's 1.8x
    assert "vs_bare" not in one and "vs_bare" not in four  # no bare row to set them beside
