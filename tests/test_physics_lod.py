"""Physics level of detail: full physics in interest zones, kinematic placement elsewhere."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from physics_side.config import PhysicsConfig, PhysicsSettings
from physics_side.daemon import build_fleet
from physics_side.lod import HYSTERESIS, DetailSplit, DetailZones
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


def test_far_agents_never_reach_the_fleet_and_follow_their_sumo_trajectory():
    # circle traffic on a 300 m circle around (1000, 1000); a region on it that the
    # eighth car (at 0.51 rad, 10 m/s) reaches after about a second
    cx, cy = 1000.0 + 300.0 * np.cos(0.6), 1000.0 + 300.0 * np.sin(0.6)
    split = DetailSplit(DetailZones.from_config(0.0, [[cx, cy, 12.0]]))
    f = build_fleet(PhysicsSettings(physics=replace(PhysicsConfig(), shards=1, initial_slots={"passenger": 4})))
    n = 20
    entered = set()
    for k in range(30):
        msg = circle_traffic(n, k)
        near = split.apply(msg)
        f.apply_step(near)
        for _ in range(f.rates.ticks_per_step):
            f.tick()
        a = msg.agents
        d = np.hypot(a.x - cx, a.y - cy)
        assert set(near.agents.ids) >= {a.ids[i] for i in np.flatnonzero(d < 12.0 * HYSTERESIS)}
        assert not set(near.agents.ids) & {a.ids[i] for i in np.flatnonzero(d > 12.0)}
        entered |= set(near.agents.ids)
        t = msg.time + 0.05
        snap = split.snapshot(f.snapshot(), t)
        assert sorted(snap.ids) == sorted(a.ids) and len(snap.ids) == n
        far = snap.mode == AgentMode.KINEMATIC
        assert far.sum() == n - near.agents.n and np.all(snap.mode[~far] == AgentMode.PHYSICAL)
        # far agents: on the circle, 0.5 m (10 m/s x 0.05 s) past their SUMO pose
        idx = [a.ids.index(i) for i in np.array(snap.ids)[far]]
        moved = np.hypot(snap.x[far] - a.x[idx], snap.y[far] - a.y[idx])
        assert np.allclose(moved, 0.5, atol=0.02)
        assert np.allclose(np.hypot(snap.x[far] - 1000.0, snap.y[far] - 1000.0), 300.0 + 4.0 * a.lane[idx], atol=0.05)
    assert entered and f.world.counters["spawned"] == len(entered) < n // 2  # only the zone's agents got a slot
    assert f.world.capacity < n


def test_daemon_publishes_far_agents_as_kinematic_without_simulating_them():
    from physics_side.daemon import PhysicsDaemon
    from protocol.codec import encode
    from protocol.keys import Keys
    from sumoco.common.config import RunConfig

    cx, cy = 1000.0 + 300.0 * np.cos(0.6), 1000.0 + 300.0 * np.sin(0.6)
    settings = PhysicsSettings(physics=replace(
        PhysicsConfig(), shards=1, initial_slots={"passenger": 4}, lod_regions=((cx, cy, 12.0),)))
    fleet = build_fleet(settings)
    d = PhysicsDaemon(None, Keys("sumoco", "lod"), fleet, settings, RunConfig(timing="lockstep"))
    for k in range(3):
        msg = d._decode(encode(circle_traffic(20, k)))  # as received
        assert d._apply(msg)
        for _ in range(fleet.rates.ticks_per_step):
            fleet.tick()
    snap = d._agents()
    c = d.all_counters()
    assert len(snap.ids) == 20 and fleet.n == c["physical"] < 20
    assert c["lod_far"] == 20 - fleet.n and c["kinematic"] == c["lod_far"]
    assert int((snap.mode == AgentMode.KINEMATIC).sum()) == c["lod_far"]
