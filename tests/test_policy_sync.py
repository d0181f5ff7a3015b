"""Sync (``physics_side.policies.sync``): each agent's new SUMO sample against its previous one
(retype, stale, drift, hops) and the rules it feeds (spawn, jump, slide), on small arrays and
driven through a fleet."""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from physics_side import models
from physics_side.config import PhysicsConfig, ticks_to
from physics_side.policies.base import Cause, Previous, Verdict
from physics_side.policies.sync import (
    PED_HOP_M, STALE_MIN_S, STALE_STEPS, detect_jump, detect_slide, detect_spawn, hops, pedestrian_hops, retyped,
    side_drift, stale, yaw_rates,
)
from physics_side.reference import Reference
from protocol.messages import AgentClass, AgentFlag, AgentMode, VType
from synthetic.traffic import circle_traffic
from tests.test_physics_fleet import lane_change_step, line_step, make_fleet, run_step, turn_step, with_cols


def _ref(t: float, x, y, angle_deg, speed, lane_y=None) -> Reference:
    """Agents heading along their SUMO angle with a straight 100 m path each (its lane's centre
    line, at ``lane_y`` [m] when given, else through the agent)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    yaw = np.radians(90.0 - np.asarray(angle_deg, float))
    n = len(x)
    ly = y if lane_y is None else np.asarray(lane_y, float)
    pts = np.stack([np.c_[x, ly], np.c_[x + 100.0 * np.cos(yaw), ly + 100.0 * np.sin(yaw)]], 1).reshape(-1, 2)
    return Reference(t, x, y, angle_deg, speed, np.zeros(n), x, y, np.arange(n + 1) * 2, pts)


def test_a_changed_vtype_or_class_is_a_retype_and_stale_samples_are_none():
    prev = np.array([0, 1, -1])
    old_vtype, old_cls = np.array([3, 4], np.uint16), np.array([0, 0], np.uint8)
    assert list(retyped(prev, old_vtype, old_cls, 2, np.array([3, 5, 0]), np.array([0, 0, 0]))) == [1]
    assert list(retyped(prev, old_vtype, old_cls, 2, np.array([3, 4, 0]), np.array([1, 0, 0]))) == [0]
    assert len(retyped(np.array([-1]), old_vtype, old_cls, 2, np.array([9]), np.array([9]))) == 0
    assert not stale(10.0, 9.9, 0.1) and stale(10.0, 10.0, 0.1) and stale(10.0, 10.5, 0.1)  # same time, or back
    assert not stale(10.0, 10.0 - 0.99 * STALE_MIN_S, 0.1) and stale(10.0, 10.0 - STALE_MIN_S, 0.1)
    assert not stale(10.0, 10.0 - 0.99 * STALE_STEPS, 1.0) and stale(10.0, 10.0 - STALE_STEPS, 1.0)


def test_yaw_rates_drift_and_hops_on_a_two_agent_sample():
    old = _ref(0.0, [0.0, 0.0], [0.0, 10.0], [90.0, 90.0], [1.0, 10.0])
    prev = np.array([0, 1])
    yaw = np.radians([90.0 - 80.0, 0.0])  # agent 0 turned 10 deg left in 0.1 s
    assert np.allclose(yaw_rates(yaw, old, prev, 0.1), [math.radians(10.0) / 0.1, 0.0])
    assert not yaw_rates(yaw, None, prev, 0.1).any()
    cfg = SimpleNamespace(sideways_jump_m=1.0, sideways_jump_speed=5.0, max_side_speed=2.0)
    x, y = np.array([0.1, 1.0]), np.array([3.2, 13.2])  # both 3.2 m to the left
    slow, hop = hops(x, y, np.array([1.0, 10.0], np.float32), old, prev, 0.1, cfg)
    assert list(slow) == [True, False] and list(hop) == [True, False]  # the fast one changes lanes driving
    slow, hop = hops(x, np.array([0.9, 10.0]), np.array([1.0, 10.0], np.float32), old, prev, 0.1, cfg)
    assert list(hop) == [False, False]  # 0.9 m: within sideways_jump_m
    slow, hop = hops(x, y, np.array([1.0, 1.0], np.float32), old, prev, 2.0, cfg)
    assert not hop.any()  # 3.2 m over 2 s is within max_side_speed
    # agent 0 drifts 0.05 m off its lane's centre line in 0.1 s; agent 1 0.5 m (a hop: no drift)
    cur = _ref(0.1, [0.1, 1.0], [0.05, 10.5], [90.0, 90.0], [1.0, 10.0], lane_y=[0.0, 10.0])
    rate, drift = side_drift(cur, old, prev, 0.1, 2.0)
    assert np.allclose(rate, [0.5, 0.0]) and np.allclose(drift, rate)
    assert side_drift(cur, None, prev, 0.1, 2.0)[1] is None
    # back on the centre line: the drift ends there
    back = _ref(0.2, [0.2, 2.0], [0.0, 10.0], [90.0, 90.0], [1.0, 10.0])
    rate, drift = side_drift(back, cur, prev, 0.2, 2.0)
    assert rate[0] == pytest.approx(-0.5) and drift[0] == 0.0


def test_a_pedestrian_moved_further_than_it_walks_hops():
    old = _ref(0.0, [0.0, 0.0], [0.0, 5.0], [90.0, 90.0], [1.2, 1.2])
    kind = np.array([models.KIND_PED, models.KIND_CAR], np.int8)
    reach = 1.2 * 0.1 + PED_HOP_M
    x = np.array([reach + 0.01, reach + 0.01])
    hop = pedestrian_hops(x, np.array([0.0, 5.0]), np.array([1.2, 1.2], np.float32), old, np.array([0, 1]), 0.1, kind)
    assert list(hop) == [True, False]  # (a car moving as far is no pedestrian hop)
    x = np.array([reach - 0.01, 0.0])
    assert not pedestrian_hops(x, np.array([0.0, 5.0]), np.array([1.2, 1.2], np.float32), old, np.array([0, 1]), 0.1,
                               kind).any()


def _detect_step(n: int, **cols):
    """The part of a ``Step`` the spawn, jump and slide rules read (defaults: nothing moves)."""
    base = dict(
        n=n, is_new=np.zeros(n, bool), flags=np.zeros(n, np.uint8), ped_hop=np.zeros(n, bool),
        hop=np.zeros(n, bool), slow=np.zeros(n, bool), side_rate=np.zeros(n), e_lat=np.zeros(n),
        mode=np.full(n, AgentMode.PHYSICAL, np.uint8), kind=np.full(n, models.KIND_CAR, np.int8),
        cfg=SimpleNamespace(sideways_slide_m=0.5), prev=np.arange(n), gap=0.1, step_length=0.1,
        reach=np.full(n, 0.2), speed=np.zeros(n, np.float32),
        before=Previous(*(np.zeros(n, bool),) * 4, jump_t=np.full(n, -np.inf)),
    )
    base.update(cols)
    return SimpleNamespace(**base)


def test_spawn_jump_and_slide_claim_in_order():
    """0 new and flagged JUMPED (a spawn), 1 teleported, 2 hopped but kinematic (not placed),
    3 a pedestrian hop, 4 sliding 1 m off (placed), 5 standing, slid 0.2 m (a carry's start)."""
    n = 6
    old = _ref(0.0, np.zeros(n), np.arange(n) * 10.0, np.full(n, 90.0), np.zeros(n))
    x, y = np.zeros(n), np.arange(n) * 10.0
    y[5] += 0.2
    s = _detect_step(
        n, is_new=np.array([1, 0, 0, 0, 0, 0], bool), flags=np.array([AgentFlag.JUMPED, AgentFlag.JUMPED, 0, 0, 0, 0], np.uint8),
        hop=np.array([0, 0, 1, 0, 0, 0], bool), ped_hop=np.array([0, 0, 0, 1, 0, 0], bool),
        mode=np.array([AgentMode.PHYSICAL] * 2 + [AgentMode.KINEMATIC] + [AgentMode.PHYSICAL] * 3, np.uint8),
        slow=np.array([0, 0, 1, 0, 1, 1], bool), side_rate=np.array([0, 0, 0, 0, 1.0, 1.0]),
        e_lat=np.array([0, 0, 0, 0, 1.0, 0.2]), old=old, x=x, y=y, ref=SimpleNamespace(interpolated=None))
    v = Verdict.empty(s)
    for rule in (detect_spawn, detect_jump, detect_slide):
        rule(s, v)
    assert list(v.cause) == [Cause.SPAWN, Cause.JUMP, 0, Cause.JUMP, Cause.JUMP, Cause.JUMP]
    assert list(v.sliding) == [False] * 5 + [True]
    # the slide under way: carried on, no new placement; without SUMO moving it sideways, none starts
    s2 = replace_ns(s, is_new=np.zeros(n, bool), flags=np.zeros(n, np.uint8), hop=np.zeros(n, bool),
                    ped_hop=np.zeros(n, bool), e_lat=np.zeros(n),
                    before=Previous(*(np.zeros(n, bool),) * 2, sliding=v.sliding, ghost=np.zeros(n, bool),
                                    jump_t=np.full(n, -np.inf)))
    v2 = Verdict.empty(s2)
    detect_slide(s2, v2)
    assert not (v2.cause != 0).any() and list(v2.sliding) == [False] * 5 + [True]
    s3 = replace_ns(s2, side_rate=np.zeros(n), before=Previous(*(np.zeros(n, bool),) * 4, jump_t=np.full(n, -np.inf)))
    v3 = Verdict.empty(s3)
    detect_slide(s3, v3)
    assert not v3.sliding.any()


def replace_ns(ns: SimpleNamespace, **cols) -> SimpleNamespace:
    return SimpleNamespace(**{**vars(ns), **cols})


def test_spawn_leave_and_teleport_placements():
    f = make_fleet()
    run_step(f, circle_traffic(3, 0))
    assert f.world.counters["placements"] == 3 and f.counters["placements_spawn"] == 3
    snap = f.snapshot()
    assert snap.ids == ["veh0", "veh1", "veh2"] and np.all(snap.mode == AgentMode.PHYSICAL)
    # veh1 teleports (JUMPED): placed at its new pose, counted
    msg = circle_traffic(3, 1)
    x = msg.agents.x.copy()
    x[1] += 30.0
    flags = msg.agents.flags.copy()
    flags[1] = AgentFlag.JUMPED
    run_step(f, with_cols(msg, x=x, flags=flags))
    assert f.counters["placements_jump"] == 1 and f.world.counters["placements"] == 4
    snap = f.snapshot()
    moved = np.hypot(snap.x[1] - x[1], snap.y[1] - msg.agents.y[1])
    assert moved == pytest.approx(1.0, abs=0.05)  # placed there, then 0.1 s at 10 m/s
    # veh2 leaves: parked, its slot free again; ids follow the message order
    m = circle_traffic(3, 2)
    keep = [0, 1]
    a = m.agents
    run_step(f, with_cols(m, ids=a.ids[:2], **{k: getattr(a, k)[keep] for k in (
        "cls", "vtype", "x", "y", "angle", "speed", "accel", "signals", "la_x", "la_y", "length", "width", "lane",
        "flags")}, path_offsets=a.path_offsets[:3], path_xy=a.path_xy[: int(a.path_offsets[2])]))
    assert f.snapshot().ids == ["veh0", "veh1"] and f.world.counters["parked"] == 1
    assert "veh2" not in f.world.agent_slot


@pytest.mark.parametrize("reference, step_s", [("auto", 0.1), ("interpolate", 0.1), ("auto", 0.5)])
def test_a_pedestrian_sumo_moves_further_than_it_walks_is_placed_there(reference, step_s):
    """SUMO moves a pedestrian onto a walking area 1.3 m at once (one 0.1 s step at 1.2 m/s):
    it is placed there (a jump), not left running after it at twice its speed; ordinary
    walking is never placed. Interpolating, the jump is no motion to follow between the
    samples either (followed, a pedestrian of the demo ran 3.5 m past its crossing's entry;
    steps of 0.5 s are interpolated by default)."""
    f = make_fleet(reference=reference)
    ped = np.array([AgentClass.PEDESTRIAN], np.uint8)
    worst = 0.0
    for k in range(30):
        x = 100.0 + 1.2 * k * step_s + (1.3 if k >= 15 else 0.0)
        msg = line_step(k, [x], [1.2], step_s=step_s)
        run_step(f, with_cols(msg, cls=ped, length=np.array([0.3], np.float32), width=np.array([0.5], np.float32)))
        if k >= 15:
            worst = max(worst, float(np.hypot(f.err_lon, f.err_lat).max()))
    from physics_side import models as M

    assert f.kind[0] == M.KIND_PED
    assert f.counters["placements_jump"] == 1 and f.counters["placements_divergence"] == 0, f.counters
    assert worst < 0.3, worst


def test_sideways_jumps_slow_agents_are_placed_fast_ones_driven():
    """SUMO's instantaneous lane change: a queueing car cannot drive 3.2 m sideways, a
    fast one changes lanes physically over the next seconds."""
    f = make_fleet()
    slow = lambda k: circle_traffic(1, k, speed=2.0)  # noqa: E731
    for k in range(3):
        run_step(f, slow(k))
    m = slow(3)
    a = m.agents
    yaw = np.radians(90.0 - a.angle[0])
    left = np.array([-np.sin(yaw), np.cos(yaw)]) * 3.2  # one lane to the left
    run_step(f, with_cols(m, x=a.x + left[0], y=a.y + left[1], path_xy=a.path_xy + left.astype(np.float32)))
    assert f.counters["placements_jump"] == 1
    assert abs(f.snapshot().err_lat[0]) < 0.05

    f = make_fleet()
    for k in range(3):
        run_step(f, circle_traffic(1, k, speed=12.0))
    m = circle_traffic(1, 3, speed=12.0)
    a = m.agents
    yaw = np.radians(90.0 - a.angle[0])
    left = np.array([-np.sin(yaw), np.cos(yaw)]) * 3.2
    shifted = lambda m: with_cols(m, x=m.agents.x + left[0], y=m.agents.y + left[1],  # noqa: E731
                              path_xy=m.agents.path_xy + left.astype(np.float32))
    run_step(f, shifted(m))
    assert f.counters["placements_jump"] == 0
    first = f.snapshot().err_lat[0]
    assert first < -2.5  # 3.2 m right of the new lane, closing in
    lat = []
    for k in range(4, 40):  # the next 3.6 s: the physical car changes lanes
        run_step(f, shifted(circle_traffic(1, k, speed=12.0)))
        lat.append(f.snapshot().err_lat[0])
    assert abs(lat[-1]) < 0.1 and np.all(np.diff(lat[:10]) > 0)  # closes monotonically at first
    assert max(lat) < 0.3  # without a big overshoot into the next lane


@pytest.mark.parametrize("v", [3.0, 13.9])
def test_continuous_lane_change_is_driven_within_bounds(v):
    """SUMO's --lanechange.duration 3 s: 3.2 m sideways at 1.07 m/s. The reference drifts
    with it between steps and the car follows: small error, no placement, no tilt."""
    f = make_fleet()
    worst = 0.0
    for k in range(80):
        msg, off = lane_change_step(k, 0.1, v, 3.2 / 3.0, t0=2.0)
        f.apply_step(msg)
        for _ in range(f.rates.ticks_per_step):
            f.tick()
            worst = max(worst, float(np.hypot(f.err_lon, f.err_lat).max()))
    snap = f.snapshot()
    assert f.counters["placements_jump"] + f.counters["placements_divergence"] == 0
    assert abs(snap.y[0] - 103.2) < 0.15 and abs(snap.roll[0]) < 3.0
    assert worst < (0.3 if v > 10 else 0.5), worst


def test_a_lane_change_ends_on_the_new_lanes_centre_line():
    """SUMO stops a continuous lane change on the target lane's centre line: the sample that
    arrives there is not extrapolated a further step sideways past it (its offset is 0, whose
    sign is no direction), and the car does not run past the line."""
    f = make_fleet()
    end_k = 50  # 2.0 s + 3.2 m at 1.07 m/s
    over = 0.0
    for k in range(end_k + 15):
        msg, off = lane_change_step(k, 0.1, 13.9, 3.2 / 3.0, t0=2.0)
        f.apply_step(msg)
        if k == end_k:
            assert off == pytest.approx(3.2)
            # half a step on, the reference is still on the line (was 0.053 m past it)
            assert f.ref.at(0.05).y[0] == pytest.approx(103.2, abs=1e-3)
            assert f.ref.drift_angle(0.05) == pytest.approx(0.0)
        for _ in range(f.rates.ticks_per_step):
            f.tick()
            if k >= end_k:
                over = max(over, float(f.snapshot().y[0]) - 103.2)
    assert over < 0.08, over  # (0.15 m when the sample drifted on)


def test_a_standing_vehicle_slid_sideways_is_carried_along_the_slide():
    """SUMO's continuous lane change while standing in a queue: no vehicle drives that, so it
    follows SUMO's slide every tick (one placement for the slide), not lagging 0.5 m behind."""
    f = make_fleet()
    worst = 0.0
    for k in range(80):
        msg, off = lane_change_step(k, 0.1, 0.0, 3.2 / 3.0, t0=2.0)
        f.apply_step(msg)
        for _ in range(f.rates.ticks_per_step):
            f.tick()
            worst = max(worst, float(np.hypot(f.err_lon, f.err_lat).max()))
    snap = f.snapshot()
    assert f.counters["placements_jump"] == 1 and f.counters["placements_divergence"] == 0, f.counters
    assert abs(snap.y[0] - 103.2) < 0.1 and abs(snap.roll[0]) < 3.0
    assert worst < 0.1, worst


def test_a_standing_slide_before_a_bend_keeps_the_body_as_it_stands():
    """A car standing where its lane bends (radius 8 m from its bumper) that SUMO slides
    0.5 m sideways: it follows the slide as it stands, wheels straight, not in the
    steady-turn pose of the bend (that turned a stopped 6.5 m van 11 deg, its rear into the
    next lane) nor on SUMO's angle, which turns with the lane change."""
    f = make_fleet()
    s_arc = np.arange(0.0, 60.0, 2.0)
    bend = np.minimum(s_arc, 10.0) / 8.0  # [rad] heading along the path: 72 deg over 10 m, then straight
    hx = np.concatenate([[0.0], np.cumsum(2.0 * np.cos(bend[:-1]))])
    hy = np.concatenate([[0.0], np.cumsum(2.0 * np.sin(bend[:-1]))])
    worst_yaw = 0.0
    for k in range(40):
        t = k * 0.1
        off = float(np.clip((t - 1.0) * 0.5, 0.0, 0.5))
        m = circle_traffic(1, 0)
        f32 = lambda a: np.array([a], np.float32)  # noqa: E731
        pts = np.c_[100.0 + hx, 100.0 + hy].astype(np.float32)  # the lane's centre line
        # SUMO turns its angle with the lane change (38 deg in a standing one in the demo)
        a = replace(m.agents, x=np.array([100.0]), y=np.array([100.0 + off]), angle=f32(90.0 - 60.0 * off),
                    speed=f32(0.0),
                    accel=f32(0.0), la_x=pts[3:4, 0], la_y=pts[3:4, 1], flags=np.array([8 if k == 0 else 0], np.uint8),
                    path_offsets=np.array([0, 30], np.uint32), path_xy=pts)
        f.apply_step(replace(m, step=k, time=t, step_length=0.1, agents=a))
        for _ in range(f.rates.ticks_per_step):
            f.tick()
            worst_yaw = max(worst_yaw, abs(float(f.snapshot().heading[0]) - 90.0))
    snap = f.snapshot()
    assert f.counters["placements_jump"] == 1, f.counters  # the slide: one placement
    assert abs(snap.y[0] - 100.5) < 0.05 and abs(snap.x[0] - 100.0) < 0.05
    assert worst_yaw < 1.0, worst_yaw


def test_a_vtype_change_respawns_the_agent_in_the_model_of_its_new_size():
    """vehicle.setType mid-run (a car becomes a 12 m bus): the agent leaves its car slot and
    is spawned again in a pool whose model has the new type's length and width."""
    f = make_fleet()
    for k in range(3):
        run_step(f, circle_traffic(2, k))
    w = f.world
    car_pool = int(w.tables.pool[w.slot_of(["veh0"])[0]])
    assert w.pools[car_pool].spec.length == pytest.approx(5.0, rel=0.05)
    msg = circle_traffic(2, 3)
    a = msg.agents
    vtype, cls = a.vtype.copy(), a.cls.copy()
    length, width = a.length.copy(), a.width.copy()
    vtype[0], cls[0], length[0], width[0] = 1, int(AgentClass.BUS), 12.0, 2.5
    msg = replace(msg, vtypes=[VType("car", "passenger"), VType("city_bus", "bus")])
    spawns = f.counters["placements_spawn"]
    run_step(f, with_cols(msg, vtype=vtype, cls=cls, length=length, width=width))
    assert f.counters["retyped"] == 1 and f.counters["placements_spawn"] == spawns + 1
    pool = int(w.tables.pool[w.slot_of(["veh0"])[0]])
    assert pool != car_pool
    assert w.pools[pool].spec.length == pytest.approx(12.0, rel=0.05)
    assert w.pools[pool].spec.width == pytest.approx(2.5, rel=0.05)
    # veh1 kept its slot and type; the bus drives on from where SUMO has it
    assert int(w.tables.pool[w.slot_of(["veh1"])[0]]) == car_pool
    snap = f.snapshot()
    assert snap.cls[0] == AgentClass.BUS
    assert np.hypot(snap.x[0] - msg.agents.x[0], snap.y[0] - msg.agents.y[0]) < 1.5


def test_a_vehicle_pulling_away_into_a_turn_is_driven_not_carried():
    """A car waiting in a junction turn pulls away (SUMO's Euler update: 0.026 m in the first
    0.1 s step at 2.6 m/s^2): its bumper moves sideways of its old heading along the lane,
    which is no slide off the lane. It is driven from where it stands (before: carried, i.e.
    placed in the steady-turn pose of the lane's bend: in synth_lefthand_grid 60 deg off SUMO's
    angle, the car ran wide into a pedestrian and was placed for divergence)."""
    f = make_fleet()
    s, worst = 0.0, 0.0
    for k in range(40):
        v = max(0.0, 2.6 * (k - 10) * 0.1)  # stands for 1 s, then pulls away
        s += v * 0.1
        msg = turn_step(k, s, v)
        f.apply_step(msg)
        for _ in range(f.rates.ticks_per_step):
            f.tick()
            worst = max(worst, float(np.hypot(f.err_lon, f.err_lat).max()))
    # (before: placements_jump 1, the carry at the first step of the pull-away)
    assert f.counters["placements_jump"] == 0 and f.counters["placements_divergence"] == 0, f.counters
    assert worst < 0.75, worst  # measured 0.53 m: pulling away to 7.8 m/s on the 8 m radius


@pytest.mark.parametrize("side_speed", [0.8, 1.3])
def test_a_slow_vehicle_sumo_moves_sideways_within_a_long_step_is_carried_along(side_speed):
    """At 1 s steps SUMO moves a crawling vehicle (0.5 m/s) 0.8 m sideways per step (a lane
    change in a queue): no vehicle drives 0.8 m sideways over 0.5 m of travel, so it is
    carried along SUMO's motion (one placement for the slide) instead of standing still and
    being placed off its lane at the next sample (a bus in Bologna, 1.4 m). 1.3 m per 1 s step
    is such a slide too, no hop: a hop is beyond ``max_side_speed`` times the step (placed at
    the next sample's pose at the interval's start, a bus in Hamburg was 1.1 m off SUMO)."""
    from physics_side.config import ticks_to

    f = make_fleet()
    worst = 0.0
    for k in range(8):
        msg, off = lane_change_step(k, 1.0, 0.5, side_speed, t0=2.0)
        f.apply_step(msg)
        assert f.interpolating
        for _ in range(ticks_to(0.0, 1.0, f.dt)):
            f.tick()
            worst = max(worst, float(np.hypot(f.err_lon, f.err_lat).max()))
    snap = f.snapshot()
    assert f.counters["placements_jump"] == 1 and f.counters["placements_divergence"] == 0, f.counters
    assert abs(snap.y[0] - 103.2) < 0.1 and abs(snap.roll[0]) < 3.0, (snap.y, snap.roll)
    assert worst < 0.2, worst


def test_pool_keys_round_trip_to_the_millimetre_and_families_name_a_class_once(caplog):
    import logging

    from physics_side.policies.sync import families, pool_keys, unpack_pool_keys

    key = pool_keys(np.array([1, 5]), np.array([3, 65535]), np.array([4.9996, 12.0]), np.array([1.8, 2.55]))
    cls, vtype, length, width = unpack_pool_keys(key)
    assert list(cls) == [1, 5] and list(vtype) == [3, 65535]
    assert list(length) == [5.0, 12.0] and list(width) == [1.8, 2.55]
    assert len(np.unique(pool_keys(np.ones(2), np.zeros(2), np.array([5.0, 5.0004]), np.full(2, 1.8)))) == 1
    warned: set[str] = set()
    vtypes = [VType("car", "passenger"), VType("lorry", "truck")]
    with caplog.at_level(logging.INFO, logger="physics_side.fleet"):
        for _ in range(2):
            fam = families(np.array([int(AgentClass.PASSENGER), int(AgentClass.OTHER)]), np.array([0, 1]),
                           np.array([5.0, 12.0]), vtypes, warned)
    assert "truck" in fam[1] and warned == {"truck"}
    assert sum("truck" in r.getMessage() for r in caplog.records) == 1


def test_samples_keep_each_agents_previous_sample_and_its_turn_rate():
    from physics_side.policies.sync import Samples

    cfg = PhysicsConfig()
    samples = Samples()
    m0 = line_step(0, [100.0, 50.0], [10.0, 10.0])
    first = samples.advance(m0, np.arange(2), ["veh0", "veh1"], np.full(2, -1), None, cfg, False, np.zeros(0, np.int8))
    assert not first.yaw_rate.any() and samples.newest.t_k == 0.0 and not first.slow.any()
    m1 = with_cols(line_step(1, [101.0, 51.0], [10.0, 10.0]), angle=np.array([90.0, 80.0], np.float32))
    kind = np.zeros(2, np.int8)
    second = samples.advance(m1, np.arange(2), ["veh0", "veh1"], np.array([0, 1]), samples.newest, cfg, False, kind)
    assert second.yaw_rate == pytest.approx([0.0, math.radians(10.0) / 0.1])
    assert samples.yaw_rate is second.yaw_rate and samples.newest.t_k == pytest.approx(0.1)
    assert not samples.kin_rate.any()  # (no earlier rate that agrees: no turn carried on)
