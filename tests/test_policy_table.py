"""The policy table (``physics_side.policies``): one ordered list of the rules, the interface
they share (``Step`` -> ``Verdict``), and the fleet running them in that order."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from physics_side import policies
from physics_side.policies.base import Cause, Verdict, realign, realign_mask
from protocol.messages import AgentMode
from synthetic.traffic import circle_traffic
from tests.test_physics_fleet import make_fleet, run_step


def test_the_table_names_every_rule_once_in_order_with_its_phase():
    names = [p.name for p in policies.POLICIES]
    assert len(names) == len(set(names))
    assert [p.name for p in policies.DETECT] == [
        "spawn", "manoeuvre", "contact_guard", "roll_back", "jump", "slide", "flip", "divergence"]
    for p in policies.POLICIES:
        assert p.phase in ("sample", "detect", "tick")
        assert (p.detect is not None) == (p.phase == "detect"), p.name
        assert p.trigger and p.action and p.release


def test_every_counter_of_the_table_is_a_fleet_counter_and_every_cause_has_one():
    f = make_fleet()
    assert set(policies.COUNTERS) <= set(f.counters)
    for cause in Cause:
        if cause != Cause.NONE:
            assert f"placements_{cause.name.lower()}" in f.counters


def test_the_first_claim_wins_and_a_carry_makes_an_agent_kinematic():
    s = SimpleNamespace(n=3, mode=np.full(3, AgentMode.PHYSICAL, np.uint8))
    v = Verdict.empty(s)
    v.place(np.array([True, False, False]), Cause.SPAWN)
    v.place(np.array([True, True, False]), Cause.JUMP)
    v.carry(np.array([False, False, True]))
    assert list(v.cause) == [Cause.SPAWN, Cause.JUMP, Cause.NONE]
    assert list(v.mode) == [AgentMode.PHYSICAL, AgentMode.PHYSICAL, AgentMode.KINEMATIC]
    assert list(v.free()) == [False, False, False] and s.mode[2] == AgentMode.PHYSICAL  # (the step's mode stays)
    v.count("x", 2)
    v.count("x", np.int64(1))
    assert v.counts == {"x": 3}


def test_previous_state_is_realigned_to_the_new_agent_order():
    prev = np.array([2, -1, 0])
    assert list(realign_mask(np.array([True, False, True]), prev)) == [True, False, True]
    assert list(realign_mask(np.zeros(0, bool), prev)) == [False] * 3
    assert list(realign(np.array([1.0, 2.0, 3.0]), prev, -np.inf)) == [3.0, -np.inf, 1.0]
    assert list(realign(np.zeros(0), prev, -np.inf)) == [-np.inf] * 3


def test_the_fleet_runs_the_detect_rules_in_table_order(monkeypatch):
    seen = []

    def spy(p):
        def detect(s, v):
            seen.append(p.name)
            p.detect(s, v)
        return p._replace(detect=detect)

    monkeypatch.setattr(policies, "DETECT", tuple(spy(p) for p in policies.DETECT))
    f = make_fleet()
    run_step(f, circle_traffic(2, 0))
    assert seen == [p.name for p in policies.DETECT]
    assert f.counters["placements_spawn"] == 2
