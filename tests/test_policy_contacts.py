"""Contacts (``physics_side.policies.contacts``): the contact guard, ghosts and the collision
accounting, on small arrays and driven through a fleet."""

from __future__ import annotations

import logging
from types import SimpleNamespace

import numpy as np

from physics_side import models
from physics_side.policies.base import Previous, Verdict
from physics_side.policies.contacts import (
    GHOST_CLEAR_M, GUARD_HOLD_S, JUMP_EXCUSE_S, MAX_PENDING_COLLISIONS, CollisionBook, ContactGuard, excused, ghosts,
    sumo_overlaps,
)
from protocol.messages import AgentFlag, AgentMode
from tests.test_physics_fleet import line_step, make_fleet


def test_a_placed_body_overlapping_a_live_one_is_a_ghost_until_clear():
    """Three 4 x 2 m bodies in a row: 1 placed 3 m behind 0 (overlapping), 2 placed far off;
    then 1 is 0.2 m clear (still a ghost: within GHOST_CLEAR_M), then 1 m clear (joins)."""
    cy, yaw, L, W, ped = np.zeros(3), np.zeros(3), np.full(3, 4.0), np.full(3, 2.0), np.zeros(3, bool)
    placed = np.array([False, True, True])
    g, fresh = ghosts(np.array([0.0, -3.0, 50.0]), cy, yaw, L, W, ped, np.zeros(3, bool), placed)
    assert list(g) == [False, True, False] and list(fresh) == [False, True, False]
    g, fresh = ghosts(np.array([0.0, -4.0 - GHOST_CLEAR_M / 2, 50.0]), cy, yaw, L, W, ped, g, np.zeros(3, bool))
    assert list(g) == [False, True, False] and not fresh.any()
    g, _ = ghosts(np.array([0.0, -5.0, 50.0]), cy, yaw, L, W, ped, g, np.zeros(3, bool))
    assert not g.any()


def test_pedestrians_never_ghost_each_other_and_the_input_is_not_written():
    ped = np.ones(2, bool)
    before = np.zeros(2, bool)
    g, _ = ghosts(np.zeros(2), np.zeros(2), np.zeros(2), np.full(2, 0.3), np.full(2, 0.5), ped, before,
                  np.array([False, True]))
    assert not g.any() and not before.any()


def _ghosts_one_by_one(cx, cy, yaw, length, width, ped, ghost, placed):
    """The ghost rule as first written: each body against every other, in index order (the
    reference the pair search must equal)."""
    from physics_side.policies.footprints import overlaps_any

    ghost = ghost.copy()
    idx = np.arange(len(ghost))
    fresh = np.zeros(len(ghost), bool)
    for i in np.flatnonzero(placed):
        other = (idx != i) & (~placed | (idx < i)) & ~ghost & ~(ped & ped[i])
        if overlaps_any(i, cx, cy, yaw, length, width, other):
            ghost[i] = fresh[i] = True
    for i in np.flatnonzero(ghost & ~fresh):
        other = (idx != i) & ~ghost & ~(ped & ped[i])
        if not overlaps_any(i, cx, cy, yaw, length, width, other, GHOST_CLEAR_M):
            ghost[i] = False
    return ghost, fresh


def test_ghosts_equal_the_one_by_one_rule_on_crowded_scenes():
    """Dense random scenes (cars, buses, pedestrians; bodies touching edge to edge and corner
    to corner; stacked on one point; NaN poses), every mix of placed and old ghosts: the
    same ghosts and the same fresh ones as testing each body against every other."""
    rng = np.random.default_rng(7)
    cases = 0
    for trial in range(400):
        n = int(rng.integers(0, 40))
        spread = float(rng.choice([3.0, 10.0, 40.0]))
        cx, cy = rng.uniform(0, spread, n), rng.uniform(0, spread, n)
        yaw = rng.choice([0.0, np.pi / 2, np.pi / 4, -np.pi], n) if trial % 3 == 0 else rng.uniform(-np.pi, np.pi, n)
        ped = rng.random(n) < 0.3
        length = np.where(ped, 0.3, rng.choice([4.0, 4.5, 12.0], n))
        width = np.where(ped, 0.5, rng.choice([1.8, 2.0, 2.5], n))
        if n >= 4 and trial % 4 == 1:  # exact contacts: edge to edge, corner to corner, clear by the margin
            cx[1], cy[1], yaw[:4] = cx[0] + length[0] / 2 + length[1] / 2, cy[0], 0.0
            cx[2], cy[2] = cx[0] + (length[0] + length[2]) / 2, cy[0] + (width[0] + width[2]) / 2
            cx[3], cy[3] = cx[0] - (length[0] + length[3]) / 2 - GHOST_CLEAR_M, cy[0]
        if n >= 3 and trial % 5 == 2:
            cx[:3], cy[:3] = cx[0], cy[0]  # stacked on one spot (two vehicles inserted at one point)
        if n and trial % 17 == 3:
            cx[0] = np.nan
        placed = rng.random(n) < rng.choice([0.0, 0.3, 1.0])
        ghost = rng.random(n) < rng.choice([0.0, 0.3, 0.8])
        want = _ghosts_one_by_one(cx, cy, yaw, length, width, ped, ghost, placed)
        got = ghosts(cx, cy, yaw, length, width, ped, ghost, placed)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]), trial
        cases += int(want[0].any() or want[1].any())
    assert cases > 150  # most scenes had ghosts to decide


def _ghosts_counting_tests(monkeypatch, *args):
    """``ghosts(*args)`` and the number of pairs in each exact footprint test it ran."""
    from physics_side.policies import contacts as contacts_mod

    calls, real = [], contacts_mod.footprints_overlap

    def counting(*a, **kw):
        calls.append(len(a[0]))
        return real(*a, **kw)

    monkeypatch.setattr(contacts_mod, "footprints_overlap", counting)
    return ghosts(*args), calls


def test_a_thousand_bodies_spawned_at_once_are_sorted_in_one_pass(monkeypatch):
    """1,000 bodies placed in one step, 3 of them onto occupied spots: the same answer as one
    by one, with the exact tests done in a handful of array calls (counted)."""
    n = 1000
    cx, cy = np.arange(n) * 10.0, np.zeros(n)
    cx[[10, 500, 999]] = cx[[9, 499, 998]] + 3.0
    yaw, ped = np.zeros(n), np.zeros(n, bool)
    length, width = np.full(n, 4.5), np.full(n, 1.8)
    placed = np.ones(n, bool)
    got, calls = _ghosts_counting_tests(monkeypatch, cx, cy, yaw, length, width, ped, np.zeros(n, bool), placed)
    assert list(np.flatnonzero(got[0])) == [10, 500, 999] and list(np.flatnonzero(got[1])) == [10, 500, 999]
    assert len(calls) == 2 and max(calls) < 50  # two exact tests, over the near pairs only


def test_a_later_step_tests_only_the_pairs_of_the_placed_and_the_ghosts(monkeypatch):
    """1,000 cars in a queue 0.5 m apart (every neighbour a candidate pair), one placed, one an
    old ghost: the exact tests cover their pairs only."""
    n = 1000
    cx, cy = np.arange(n) * 5.0, np.zeros(n)
    yaw, ped = np.zeros(n), np.zeros(n, bool)
    length, width = np.full(n, 4.5), np.full(n, 1.8)
    placed, ghost = np.zeros(n, bool), np.zeros(n, bool)
    placed[300], ghost[700] = True, True
    got, calls = _ghosts_counting_tests(monkeypatch, cx, cy, yaw, length, width, ped, ghost, placed)
    want = _ghosts_one_by_one(cx, cy, yaw, length, width, ped, ghost, placed)
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    assert list(np.flatnonzero(got[0])) == [700]  # (0.5 m from its neighbours: not GHOST_CLEAR_M clear)
    assert len(calls) == 2 and max(calls) <= 4  # bodies 300 and 700, each with its two neighbours


def test_sumo_overlaps_and_the_teleport_excuse():
    h = SimpleNamespace(x=np.array([10.0, 6.0, 30.0]), y=np.zeros(3), yaw=np.zeros(3))  # bumpers
    L, W = np.full(3, 5.0), np.full(3, 1.8)
    # agent 1's body (1-6 m) reaches into agent 0's (5-10 m); agent 2 is far off
    assert list(sumo_overlaps(np.array([0, 1, 2]), h, L, W, np.zeros(3, bool))) == [True, True, False]
    assert list(excused(10.0, np.array([-np.inf, 10.0 - JUMP_EXCUSE_S, 9.0]))) == [False, True, True]


def test_the_collision_book_counts_and_rechecks_at_the_next_sample(caplog):
    c = {"collisions_sumo_reported": 0, "collisions_physics_only": 0}
    book = CollisionBook()
    ids = ["a", "b", "c"]
    sumo = book.began(np.array([0, 2]), 1.0, np.array([True, False]), False, ids, c)
    assert list(sumo) == [0] and book.pending == ["c"] and c == {"collisions_sumo_reported": 1, "collisions_physics_only": 1}
    # at the next sample SUMO has "c" overlapping: it was SUMO's
    moved = book.recheck({"a": 0, "c": 1}, 1.1, lambda idx: np.ones(len(idx), bool), ids, c)
    assert list(moved) == [1] and book.pending == [] and c == {"collisions_sumo_reported": 2, "collisions_physics_only": 0}
    # the interval's end known (interpolating): told at once; a full list is told at once too
    with caplog.at_level(logging.WARNING, logger="physics_side.fleet"):
        book.began(np.array([1]), 2.0, np.array([False]), True, ids, c)
        book.pending = ["x"] * MAX_PENDING_COLLISIONS
        book.began(np.array([2]), 2.0, np.array([False]), False, ids, c)
    assert len(book.pending) == MAX_PENDING_COLLISIONS and c["collisions_physics_only"] == 2
    assert sum("collided in physics only" in r.getMessage() for r in caplog.records) == 2


def _pair_step(t: float, gap_physics: float, gap_sumo: float, kind=models.KIND_CAR, ids=("a", "b")):
    """Two standing 5 x 1.8 m cars heading east, b behind a: SUMO has b ``gap_sumo`` [m] behind
    a, physics ``gap_physics`` [m] (the ``Step`` fields the guard reads)."""
    n = 2
    fx = np.array([100.0, 95.0 - gap_physics])
    sx = np.array([100.0, 95.0 - gap_sumo])
    held = SimpleNamespace(x=sx, y=np.zeros(n), yaw=np.zeros(n), speed=np.zeros(n))
    ref = SimpleNamespace(t_k=t, at=lambda tau: held)
    obs = SimpleNamespace(fx=fx, fy=np.zeros(n), yaw=np.zeros(n), roll=np.zeros(n), vx=np.zeros(n), vy=np.zeros(n),
                          yaw_rate=np.zeros(n))
    off = np.zeros(n, bool)
    return SimpleNamespace(
        n=n, ids=list(ids), index={a: i for i, a in enumerate(ids)}, cfg=SimpleNamespace(contact_guard=True), ref=ref,
        held=held, obs=obs, prev=np.arange(n), kind=np.full(n, kind, np.int8), mode=np.full(n, AgentMode.PHYSICAL, np.uint8),
        length=np.full(n, 5.0), width=np.full(n, 1.8), height=np.full(n, 1.5), sumo_len=np.full(n, 5.0),
        sumo_wid=np.full(n, 1.8), step_length=0.1, horizon=0.0, kin_rate=np.zeros(n),
        before=Previous(carried=off, guarded=off, sliding=off, ghost=off, jump_t=np.full(n, -np.inf)),
    )


def test_the_guard_carries_a_pair_about_to_touch_where_sumo_keeps_a_gap_and_holds_it():
    guard = ContactGuard()
    s = _pair_step(0.0, 0.05, 1.0)
    v = Verdict.empty(s)
    assert guard.detect(s, v).all() and guard.pairs == {("a", "b"): 0.0}
    # apart in both within GUARD_HOLD_S of the last near: held
    assert guard.detect(_pair_step(0.9 * GUARD_HOLD_S, 2.0, 1.0), v).all()
    # after it, SUMO still within GUARD_KEEP_M: held; SUMO apart: released
    assert guard.detect(_pair_step(1.5 * GUARD_HOLD_S, 2.0, 0.2), v).all()
    assert not guard.detect(_pair_step(1.6 * GUARD_HOLD_S, 2.0, 1.0), v).any() and guard.pairs == {}


def test_the_guard_leaves_sumos_own_collisions_pedestrian_pairs_and_agents_physics_does_not_drive():
    guard = ContactGuard()
    s = _pair_step(0.0, 0.05, 0.05)  # SUMO's own: its footprints this close
    assert not guard.detect(s, Verdict.empty(s)).any()
    s = _pair_step(0.0, 0.05, 1.0, kind=models.KIND_PED)
    assert not guard.detect(s, Verdict.empty(s)).any()
    s = _pair_step(0.0, 0.05, 1.0)
    s.mode[:] = AgentMode.KINEMATIC  # both placed every tick: they never touch
    assert not guard.detect(s, Verdict.empty(s)).any()
    s = _pair_step(0.0, 0.05, 1.0)
    s.cfg.contact_guard = False
    guard.pairs = {("a", "b"): 0.0}
    assert not guard.detect(s, Verdict.empty(s)).any() and guard.pairs == {}


def test_two_vehicles_inserted_at_one_point_never_stack():
    """SUMO inserts a second car where the first one is: it spawns as a ghost (no contact
    with other agents), both stay on the ground, and it joins once the first one drove off."""
    f = make_fleet()
    z_max, ghost_seen = 0.0, False
    for k in range(60):
        x0 = 100.0 + 8.0 * k * 0.1  # veh0 drives off at 8 m/s; veh1 waits at the insertion point
        f.apply_step(line_step(k, [x0, 100.0], [8.0, 0.0]))
        ghost_seen |= bool(f.ghost[1])
        for _ in range(f.rates.ticks_per_step):
            f.tick()
            z_max = max(z_max, float(f.snapshot().z.max()))
    rest = float(f.world.tables.rest_z[f.slots].max())
    assert ghost_seen and f.counters["ghost_spawns"] == 1
    assert not f.ghost.any()  # clear again: a normal body
    assert z_max < rest + 0.05, (z_max, rest)  # nobody climbed on anybody
    assert f.world.counters["collisions"] == 0
    assert np.hypot(f.err_lon, f.err_lat).max() < 0.3


def test_a_vehicle_placed_onto_an_occupied_spot_passes_through_until_clear():
    """SUMO moves a car (a teleport) to where its bumper is inside a standing car's body:
    placed there, it is a ghost (no contact, no push) until it has driven clear, then an
    ordinary body again; nobody is pushed or stacked."""
    f = make_fleet()
    ghost_seen = False
    for k in range(50):
        if k < 10:
            xs, v, flags = [100.0, 60.0 + 5.0 * k * 0.1], [0.0, 5.0], None
        else:  # teleported at k = 10 to 103 m (body 98-103 m, the standing car's 95-100 m)
            xs, v = [100.0, 103.0 + 6.0 * (k - 10) * 0.1], [0.0, 6.0]
            flags = [0, int(AgentFlag.JUMPED) if k == 10 else 0]
        f.apply_step(line_step(k, xs, v, flags=flags))
        ghost_seen |= bool(f.ghost[1])
        for _ in range(f.rates.ticks_per_step):
            f.tick()
    assert ghost_seen and f.counters["ghost_placements"] == 1, f.counters
    assert not f.ghost.any()  # clear again
    assert f.world.counters["collisions"] == 0 and f.counters["collisions_physics_only"] == 0
    s = f.snapshot()
    assert abs(s.x[0] - 100.0) < 0.05 and float(s.z.max()) < float(f.world.tables.rest_z[f.slots].max()) + 0.05


def test_collisions_split_into_sumo_reported_and_physics_only():
    """A rear-end collision that SUMO has too (its footprints overlap) vs one only physics
    has (SUMO stops the follower 1 m short at a deceleration no car can brake); without the
    contact guard, which keeps the latter from happening (next test)."""
    f = make_fleet(contact_guard=False)
    for k in range(30):  # SUMO's own crash: veh1 runs into the standing veh0
        x1 = min(80.0 + 6.0 * k * 0.1, 97.0)  # bumper ends 2 m inside veh0's 5 m body
        f.apply_step(line_step(k, [100.0, x1], [0.0, 6.0 if x1 < 97.0 else 0.0]))
        for _ in range(f.rates.ticks_per_step):
            f.tick()
    assert f.counters["collisions_sumo_reported"] >= 1 and f.counters["collisions_physics_only"] == 0
    g = make_fleet(contact_guard=False)
    for k in range(40):  # physics only: SUMO stops veh1 1 m short of veh0 within 0.3 s from 15 m/s
        x1 = 60.0 + 15.0 * k * 0.1 if k < 24 else 94.0
        g.apply_step(line_step(k, [100.0, min(x1, 94.0)], [0.0, 15.0 if k < 24 else 0.0]))
        for _ in range(g.rates.ticks_per_step):
            g.tick()
    assert g.counters["collisions_physics_only"] >= 1 and g.counters["collisions_sumo_reported"] == 0


def test_a_contact_sumo_does_not_have_is_kept_off_by_carrying_the_pair():
    """SUMO stops a car from 15 m/s 1 m short of a standing one within 0.3 s: no car brakes
    that, so the pair is carried (shown on SUMO's poses) before the bodies touch, counted,
    and handed back once SUMO has them apart; both then stand where SUMO has them."""
    f = make_fleet()
    modes = []
    for k in range(60):
        x1 = 60.0 + 15.0 * k * 0.1 if k < 24 else 94.0
        f.apply_step(line_step(k, [100.0, min(x1, 94.0)], [0.0, 15.0 if k < 24 else 0.0]))
        modes.append(f.mode.copy())
        for _ in range(f.rates.ticks_per_step):
            f.tick()
    c = f.counters
    assert c["collisions_physics_only"] == 0 and f.world.counters["collisions"] == 0, c
    assert c["carries_contact"] == 2 and 1.0 <= c["carried_contact_ms"] / 1e3 / 2 <= 3.0, c
    assert any((m == AgentMode.KINEMATIC).all() for m in modes)  # both carried at once
    assert (f.mode == AgentMode.PHYSICAL).all() and not f.debug_state().guard_pairs  # handed back
    s = f.snapshot()
    assert np.abs(s.speed).max() < 0.3 and np.hypot(s.err_lon, s.err_lat).max() < 0.3, (s.speed, s.err_lon)
