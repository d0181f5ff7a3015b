"""The physics benchmark produces sane rows (speed targets are for `sumoco bench physics`)."""

from __future__ import annotations

from sumoco.bench.physics import run_physics_bench
from synthetic.traffic import circle_traffic


def test_circle_traffic_keeps_cars_apart():
    import numpy as np

    a = circle_traffic(300, 7).agents
    d = np.hypot(a.x[:, None] - a.x[None, :], a.y[:, None] - a.y[None, :])
    np.fill_diagonal(d, np.inf)
    assert d.min() > 3.9  # lanes 4 m apart, cars 22 m apart along a lane
    assert len(a.path_offsets) == 301 and a.path_xy.shape == (300 * 12, 2)


def test_bench_rows_have_the_fields_and_drive_well():
    rows = run_physics_bench(sizes=(30,), quick=True)
    assert len(rows) == 1
    r = rows[0]
    for k in ("agents", "tick_ms", "mujoco_ms", "overhead_ms", "rtf"):
        assert k in r
    assert r["agents"] == 30 and r["tick_ms"] > 0 and 0 < r["mujoco_ms"] < r["tick_ms"]
    assert abs(r["overhead_ms"] - (r["tick_ms"] - r["mujoco_ms"])) < 1e-2
    assert 0 < r["overhead_share_p50"] < 1 and abs(r["overhead_share"] - r["overhead_ms"] / r["tick_ms"]) < 1e-2
    assert abs(r["rtf"] - 20.0 / r["tick_ms"]) < 0.05 * r["rtf"]
    assert r["max_err_m"] < 0.1 and r["collisions"] == 0 and r["placements"] == 30
