"""Physics level of detail: full physics in interest zones, kinematic placement elsewhere."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from physics_side.config import PhysicsConfig, PhysicsSettings
from physics_side.daemon import build_fleet
from physics_side.lod import HYSTERESIS, DetailZones
from protocol.errors import ConfigError
from protocol.messages import AgentMode
from sumoco.testing.synthetic import circle_traffic


def test_zones_regions_egos_and_hysteresis():
    z = DetailZones.from_config(50.0, [[1000.0, 0.0, 10.0]])
    x = np.array([0.0, 30.0, 49.0, 200.0, 1005.0, 0.96 * 50.0])
    y = np.zeros(6)
    ego = np.array([True, False, False, False, False, False])
    full = z.full(x, y, ego)
    # the ego, inside 0.9 r of it, the region; 49 m and 48 m are in the hysteresis band
    assert full.tolist() == [True, True, False, False, True, False]
    kept = z.full(x, y, ego, was_full=np.ones(6, bool))
    assert kept.tolist() == [True, True, True, False, True, True]
    assert HYSTERESIS < 1.0
    assert DetailZones.from_config(0.0, []) is None


def test_lod_config_is_checked():
    with pytest.raises(ConfigError, match=r"lod_regions\[0\]"):
        PhysicsConfig(lod_regions=((1.0, 2.0),)).validate()
    with pytest.raises(ConfigError, match="lod_radius_m"):
        PhysicsConfig(lod_radius_m=-1.0).validate()


def test_fleet_runs_full_physics_only_in_the_zone_and_switches_smoothly():
    # circle traffic on a 300 m circle around (1000, 1000); a region on it that the
    # eighth car (at 0.51 rad, 10 m/s) reaches after about a second
    cx, cy = 1000.0 + 300.0 * np.cos(0.6), 1000.0 + 300.0 * np.sin(0.6)
    f = build_fleet(PhysicsSettings(physics=replace(
        PhysicsConfig(), shards=1, initial_slots={"passenger": 24}, lod_regions=((cx, cy, 12.0),))))
    n = 20
    seen_in = set()
    for k in range(30):
        msg = circle_traffic(n, k)
        f.apply_step(msg)
        for _ in range(f.rates.ticks_per_step):
            f.tick()
        snap = f.snapshot()
        a = msg.agents
        inside = np.hypot(a.x - cx, a.y - cy) < 12.0 * HYSTERESIS
        outside = np.hypot(a.x - cx, a.y - cy) > 12.0
        assert np.all(snap.mode[inside] == AgentMode.PHYSICAL)
        assert np.all(snap.mode[outside] == AgentMode.KINEMATIC)
        seen_in |= {snap.ids[i] for i in np.flatnonzero(inside)}
        # every agent stays on its SUMO trajectory whichever mode produced its state
        assert np.abs(snap.err_lat).max() < 0.3 and np.abs(snap.err_lon).max() < 0.6
    assert f.counters["placements_lod"] >= 1  # agents that drove into the zone
    assert len(seen_in) >= 1
    counts = f.mode_counts()
    assert counts["physical"] >= 1 and counts["kinematic"] >= n // 2
