"""Full precision with real SUMO at UTM-sized coordinates (issue: float32 quantised to 0.5 m).

The pack's synth_utm_grid runs the same routes on the same grid twice: once near the
origin and once shifted by ~(691,000, 5,335,000) m without normalisation. Every position
that reaches a receiver (agent, look-ahead point, path ahead, lane shapes) must match the
local run, shifted back, to 1 mm.
"""

from __future__ import annotations

import numpy as np
import pytest

from protocol.codec import decode, encode
from sumo_side.bridge import Bridge
from sumo_side.config import SumoConfig
from sumo_side.simulation import SumoSim
from tests.harness import scenario_pack

PACK = scenario_pack()
pytestmark = pytest.mark.skipif(PACK is None, reason="scenario pack ../shared/scenarios not found")

STEPS = 150  # 15 s: cars depart, drive and turn through the grid's junctions


def _run(name: str):
    cfg = PACK / "synth_utm_grid" / name
    sim = SumoSim(SumoConfig(sumocfg=cfg), sumocfg=cfg, run_id="utm")
    sim.start()
    try:
        bridge = Bridge(sim, sim.cfg, "utm")
        static = decode(encode(sim.static_data()))
        steps = []
        for k in range(STEPS):
            sim.step()
            steps.append(decode(encode(bridge.build(k, sim.read()))))
        return static, steps
    finally:
        sim.close()


def test_utm_run_matches_the_local_run_to_1_mm():
    local_static, local = _run("grid_local.sumocfg")
    utm_static, utm = _run("grid_utm.sumocfg")
    assert utm_static.lanes.ids == local_static.lanes.ids
    shift = utm_static.lanes.shape_xy[0] - local_static.lanes.shape_xy[0]
    assert shift[0] > 600_000 and shift[1] > 5_000_000
    np.testing.assert_allclose(utm_static.lanes.shape_xy - shift, local_static.lanes.shape_xy, rtol=0, atol=1e-3)
    compared = points = 0
    for a, b in zip(local, utm):
        la, lb = a.agents, b.agents
        assert la.ids == lb.ids
        if not la.n:
            continue
        for name in ("x", "la_x"):
            np.testing.assert_allclose(getattr(lb, name) - shift[0], getattr(la, name), rtol=0, atol=1e-3)
        for name in ("y", "la_y"):
            np.testing.assert_allclose(getattr(lb, name) - shift[1], getattr(la, name), rtol=0, atol=1e-3)
        np.testing.assert_array_equal(lb.path_offsets, la.path_offsets)
        np.testing.assert_allclose(lb.path_xy - shift, la.path_xy, rtol=0, atol=1e-3)
        compared += la.n
        points += len(la.path_xy)
    assert compared > 200 and points > 1000, (compared, points)
    # what protocol 1.1's absolute float32 made of the same paths
    last = utm[-1].agents.path_xy
    assert np.abs(last.astype(np.float32).astype(np.float64) - last).max() > 0.05
