"""``sumoco bench fidelity``: real libsumo -> codec -> one fleet per preset, scored by the report's analysis."""

from __future__ import annotations

from sumoco.bench.fidelity import DEMO_SUMOCFG, run_one


def test_fidelity_rows_at_a_long_step_length():
    """The bundled demo at 0.5 s SUMO steps (no config to match; such long steps are
    interpolated between the last two samples, one step behind): rows per preset with
    error stats, agent types, collisions split and placements by cause."""
    rows = run_one(DEMO_SUMOCFG, presets=("default",), step_s=0.5, duration_s=8.0)
    (r,) = rows
    assert r["preset"] == "default" and r["step_s"] == 0.5 and r["sim_s"] >= 7.0
    assert r["agents"] and r["reference_car"] == "ref"
    e = r["error_m"]
    assert e["samples"] > 100 and e["p95"] < 0.3 and e["max"] < 1.0, e  # interpolated (one step behind)
    assert set(r["placements"]) == {"spawn", "jump", "divergence", "flip"}
    assert r["placements"]["divergence"] == 0 and r["placements"]["flip"] == 0
    assert r["collisions_physics_only"] == 0
