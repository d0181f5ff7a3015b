"""Placement (``physics_side.policies.placement``): flipped or diverged physical bodies are
put back on SUMO's pose, checked last, on agents no earlier rule claimed."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from physics_side.policies.base import Cause, Verdict
from physics_side.policies.placement import detect_divergence, detect_flip, diverged, flipped, upright
from protocol.messages import AgentMode
from synthetic.traffic import circle_traffic
from tests.test_physics_fleet import make_fleet, run_step, with_cols


def _step(roll, pitch, dist, mode=None):
    """The part of a ``Step`` the placement rules read."""
    n = len(roll)
    return SimpleNamespace(n=n, obs=SimpleNamespace(roll=np.radians(roll), pitch=np.radians(pitch)),
                           dist=np.asarray(dist, float), cfg=SimpleNamespace(flip_deg=60.0, divergence_m=3.0),
                           mode=np.full(n, AgentMode.PHYSICAL, np.uint8) if mode is None else np.asarray(mode, np.uint8))


def test_flip_and_divergence_thresholds():
    r = np.radians([59.0, 61.0, -61.0, 0.0])
    p = np.radians([0.0, 0.0, 0.0, 61.0])
    assert list(flipped(r, p, 60.0)) == [False, True, True, True]
    assert list(upright(r, p, 60.0)) == [True, False, False, False]
    assert list(diverged(np.array([2.9, 3.0, 3.1]), 3.0)) == [False, False, True]
    # exactly at the threshold: neither flipped nor upright (strict on both sides)
    edge = np.array([math.radians(60.0)])
    assert not flipped(edge, np.zeros(1), 60.0)[0] and not upright(edge, np.zeros(1), 60.0)[0]


def test_the_first_rule_that_claims_an_agent_names_the_cause():
    """Agent 0 is new, 1 was placed for a jump, 2 is carried along a slide, 3 is kinematic,
    4 flipped and diverged (a flip), 5 diverged only, 6 neither."""
    s = _step([0, 80, 80, 80, 80, 0, 0], [0] * 7, [9, 9, 9, 9, 9, 9, 0],
              mode=[AgentMode.PHYSICAL] * 3 + [AgentMode.KINEMATIC] + [AgentMode.PHYSICAL] * 3)
    v = Verdict.empty(s)
    v.place(np.array([1, 0, 0, 0, 0, 0, 0], bool), Cause.SPAWN)
    v.place(np.array([1, 1, 0, 0, 0, 0, 0], bool), Cause.JUMP)
    v.sliding = np.array([0, 0, 1, 0, 0, 0, 0], bool)
    detect_flip(s, v)
    detect_divergence(s, v)
    assert list(v.cause) == [Cause.SPAWN, Cause.JUMP, 0, 0, Cause.FLIP, Cause.DIVERGENCE, 0]


def test_divergence_and_flip_are_placed_and_counted():
    f = make_fleet(divergence_m=3.0)
    run_step(f, circle_traffic(2, 0))
    # SUMO moves veh0 5 m sideways without a JUMPED flag: divergence -> placement
    msg = circle_traffic(2, 1)
    y = msg.agents.y.copy()
    y[0] += 5.0
    run_step(f, with_cols(msg, y=y))
    assert f.counters["placements_divergence"] == 1
    # now 2 m beside where it was placed: within divergence_m, tracked, not placed
    msg = circle_traffic(2, 2)
    y = msg.agents.y.copy()
    y[0] += 7.0
    f.apply_step(with_cols(msg, y=y))
    assert f.counters["placements_divergence"] == 1
    # a car on its roof is placed upright again
    slot = f.slots[1:2]
    w = f.world
    o = w.observe(slot)
    w.place(slot, o.fx, o.fy, o.yaw, o.speed, count=False)
    w.set_orientation(slot, np.array([0.0, 1.0, 0.0, 0.0]))  # rolled 180 deg
    f.apply_step(with_cols(circle_traffic(2, 3), y=circle_traffic(2, 3).agents.y + np.array([7.0, 0.0])))
    assert f.counters["placements_flip"] == 1
    assert abs(np.degrees(w.observe(slot).roll[0])) < 1.0


class _World:
    """Records ``place`` calls (slots, yaw, steady_turn)."""

    def __init__(self):
        self.calls = []

    def place(self, slots, x, y, yaw, speed, curvature, steady_turn=True, count=True):
        self.calls.append((list(slots), list(np.round(yaw, 6)), steady_turn, count))


def test_act_places_each_claimed_agent_once_as_it_should_stand_and_counts_by_cause(caplog):
    """0 spawned moving, 1 diverged standing (on SUMO's angle), 2 a slide's start (as it
    stands: its own yaw), 3 flipped, a rear-steered bus (on SUMO's chord), 4 untouched."""
    import logging

    from physics_side.policies.placement import act
    from physics_side.reference import ReferencePoint

    n = 5
    held = ReferencePoint(x=np.zeros(n), y=np.zeros(n), yaw=np.full(n, 0.1), speed=np.array([5.0, 0.0, 0.0, 5.0, 5.0]),
                          accel=np.zeros(n), curvature=np.zeros(n), s=np.zeros(n), tangent=np.full(n, 0.2))
    s = SimpleNamespace(n=n, held=held, obs=SimpleNamespace(yaw=np.full(n, 0.3)), ids=[f"a{i}" for i in range(n)],
                        mode=np.full(n, AgentMode.PHYSICAL, np.uint8))
    v = Verdict.empty(s)
    v.cause[:] = [Cause.SPAWN, Cause.DIVERGENCE, Cause.JUMP, Cause.FLIP, Cause.NONE]
    v.sliding = np.array([False, False, True, False, False])
    w = _World()
    with caplog.at_level(logging.WARNING, logger="physics_side.fleet"):
        placed = act(w, np.arange(10, 15), s, v, np.array([0.0, 0.0, 0.0, 0.2, 0.0]), step=7)
    assert list(placed) == [True, True, True, True, False]
    assert sorted(w.calls) == sorted([
        ([12], [0.3], False, True),  # the slide's start, as it stands
        ([11], [0.1], False, True),  # standing: SUMO's angle, wheels straight
        ([13], [0.1], False, True),  # steers its rear axle: SUMO's chord
        ([10], [0.2], True, True),  # moving: the steady turn along the tangent
    ])
    assert v.counts == {"placements_spawn": 1, "placements_jump": 1, "placements_divergence": 1, "placements_flip": 1}
    assert any("step 7: placed 1 diverged ['a1'], 1 flipped ['a3']" in r.getMessage() for r in caplog.records)
