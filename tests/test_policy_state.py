"""The policies' state from step to step (``physics_side.policies.state.PolicyState``):
realigned to each new agent order, carries settled and counted, ghosts and jumps kept."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from physics_side.policies.base import Previous, Verdict
from physics_side.policies.state import PolicyState
from protocol.messages import AgentMode


def test_previous_state_follows_the_agents_into_the_new_order():
    ps = PolicyState()
    ps.carried, ps.guarded = np.array([True, False, True]), np.array([True, False, False])
    ps.sliding, ps.ghost = np.array([False, True, False]), np.array([False, False, True])
    ps.jump_t = np.array([1.0, 2.0, 3.0])
    ps.chord_end = np.zeros(3)
    b = ps.previous(np.array([2, -1, 0, 1]))
    assert list(b.carried) == [True, False, True, False] and list(b.guarded) == [False, False, True, False]
    assert list(b.sliding) == [False, False, False, True] and list(b.ghost) == [True, False, False, False]
    assert list(b.jump_t) == [3.0, -np.inf, 1.0, 2.0] and ps.chord_end is None  # (recomputed once per step)
    empty = PolicyState().previous(np.array([-1, -1]))
    assert not empty.carried.any() and list(empty.jump_t) == [-np.inf, -np.inf]


def _step(n: int, before: Previous, prev, authoritative=None):
    z = np.zeros(n)
    return SimpleNamespace(
        n=n, prev=np.asarray(prev), before=before, step_length=0.1, ids=[f"a{i}" for i in range(n)],
        authoritative=np.zeros(n, bool) if authoritative is None else np.asarray(authoritative, bool),
        obs=SimpleNamespace(fx=z, fy=z, yaw=z), held=SimpleNamespace(x=z, y=z), ref=SimpleNamespace(t_k=0.0),
        mode=np.full(n, AgentMode.PHYSICAL, np.uint8), is_new=np.zeros(n, bool), t=5.0,
    )


def test_carries_settle_with_their_cause_and_are_counted_in_episodes_and_time():
    """0 starts a manoeuvre carry, 1 a contact carry, 2 goes on with a contact carry the
    manoeuvre now keeps (still the guard's), 3 is owned by physics (never carried)."""
    n = 4
    off = np.zeros(n, bool)
    before = Previous(carried=np.array([False, False, True, False]), guarded=np.array([False, False, True, False]),
                      sliding=off, ghost=off, jump_t=np.full(n, -np.inf))
    s = _step(n, before, [0, 1, 2, 3], authoritative=[False, False, False, True])
    v = Verdict.empty(s)
    v.manoeuvre = np.array([True, False, True, False])
    v.guard = np.array([False, True, False, True])
    ps = PolicyState()
    ps.kin_off, ps.kin_age = np.zeros((n, 3)), np.array([np.inf, np.inf, 0.3, np.inf])
    ps.settle_carries(s, v, lambda: np.zeros(n))
    assert list(ps.carried) == [True, True, True, False] and list(ps.guarded) == [False, True, True, False]
    assert list(ps.kin_age) == [0.0, 0.0, 0.3, np.inf]
    assert v.counts == {"carries_infeasible": 1, "carried_infeasible_ms": 100, "carries_contact": 1,
                        "carried_contact_ms": 200}


def test_ghosts_after_placements_and_jump_times():
    n = 2
    before = Previous(carried=np.zeros(n, bool), guarded=np.zeros(n, bool), sliding=np.zeros(n, bool),
                      ghost=np.array([True, False]), jump_t=np.array([1.0, -np.inf]))
    s = _step(n, before, [0, 1])
    ps = PolicyState()
    # two 4 m bodies 10 m apart: the old ghost is clear and joins; nobody new
    fresh = ps.settle_ghosts(s, np.array([0.0, 10.0]), np.zeros(n), np.zeros(n), np.full(n, 4.0), np.full(n, 2.0),
                             np.zeros(n, bool), np.zeros(n, bool))
    assert not fresh.any() and not ps.ghost.any()
    ps.make_ghosts(np.array([1]))
    assert list(ps.ghost) == [False, True]
    ps.settle_jumps(s, np.array([False, True]))
    assert list(ps.jump_t) == [1.0, 5.0]
