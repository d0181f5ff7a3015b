"""Lane changes a vehicle can drive: the SUMO side makes them continuous unless the scenario chose."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sumo_side.simulation import lane_change_args

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "configs" / "scenarios" / "paper" / "paper.sumocfg"


def _cfg(tmp_path, body: str) -> Path:
    p = tmp_path / "x.sumocfg"
    p.write_text(f'<configuration><processing>{body}</processing></configuration>')
    return p


def test_continuous_lane_changes_only_where_the_scenario_did_not_choose(tmp_path):
    plain = _cfg(tmp_path, "")
    assert lane_change_args(plain, (), 3.0) == ["--lanechange.duration", "3"]
    assert lane_change_args(plain, (), 0.0) == []
    assert lane_change_args(plain, ("--lateral-resolution", "0.8"), 3.0) == []
    assert lane_change_args(plain, ("--lanechange.duration=0",), 3.0) == []
    assert lane_change_args(_cfg(tmp_path, '<lanechange.duration value="0"/>'), (), 3.0) == []
    assert lane_change_args(_cfg(tmp_path, '<lateral-resolution value="0.8"/>'), (), 3.0) == []


def test_bundled_demo_changes_lanes_continuously():
    """Real libsumo on the bundled demo: no moving vehicle hops sideways by a lane width."""
    import libsumo as t

    t.start(["sumo", "-c", str(PAPER), "--no-step-log", "true", "--no-warnings", "true",
             *lane_change_args(PAPER, (), 3.0)])
    try:
        prev: dict[str, tuple[float, float]] = {}
        worst = 0.0
        changes = 0
        lanes: dict[str, str] = {}
        for _ in range(300):
            t.simulationStep()
            for v in t.vehicle.getIDList():
                x, y = t.vehicle.getPosition(v)
                a = math.radians(90.0 - t.vehicle.getAngle(v))
                lane = t.vehicle.getLaneID(v)
                if v in prev and not lane.startswith(":") and not lanes[v].startswith(":"):
                    dx, dy = x - prev[v][0], y - prev[v][1]
                    worst = max(worst, abs(-dx * math.sin(a) + dy * math.cos(a)))
                    changes += lane != lanes[v] and lane.rsplit("_", 1)[0] == lanes[v].rsplit("_", 1)[0]
                prev[v] = (x, y)
                lanes[v] = lane
        assert changes >= 2  # the demo's reference car changes lanes twice
        # 3.2 m over 3 s = 0.11 m per 0.1 s step, plus curved lanes (a hop would be 3.2 m)
        assert worst < 0.5, worst
    finally:
        t.close()
    assert np.isfinite(worst)
