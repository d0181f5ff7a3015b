"""Carry (``physics_side.policies.carry``): manoeuvres no vehicle of the agent's size can
drive are shown as SUMO has them, and who may roll back to its stop; the rules on small
arrays, then driven through a fleet."""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from physics_side import control, models
from physics_side.config import ticks_to
from physics_side.policies.base import Verdict
from physics_side.policies.carry import (
    CAR_GRIP_BRAKE, CAR_GRIP_SHARE, HEAVY_GRIP_SHARE, INFEASIBLE_MARGIN, MOTORCYCLE_GRIP_SHARE, SPAWN_OFF_DEG, grip_shares,
    path_tightness, rolls_back, starts,
)
from physics_side.reference import Reference
from protocol.messages import AgentClass, AgentMode, VType
from synthetic.traffic import circle_traffic
from tests.test_physics_fleet import (
    arcs_step, arcs_xy, bend_xy, line_step, make_fleet, one_agent, run_step, turn_step, with_cols,
)


def test_grip_shares_by_kind():
    kind = np.array([models.KIND_CAR, models.KIND_CAR, models.KIND_BIKE, models.KIND_BIKE, models.KIND_PED], np.int8)
    max_rear = np.array([0.0, 0.2, 0.0, 0.0, 0.0])  # (a car model that steers its rear axle: a heavy vehicle)
    mass = np.array([1300.0, 9000.0, 90.0, 2 * control.MOTORCYCLE_MASS_KG, 80.0])
    share, brake = grip_shares(kind, max_rear, mass)
    assert list(share) == [CAR_GRIP_SHARE, HEAVY_GRIP_SHARE, 1.0, MOTORCYCLE_GRIP_SHARE, 0.0]
    assert list(brake) == [CAR_GRIP_BRAKE, 0.0, 0.0, 0.0, 0.0]


def _arc_ref(R: float, v: float, angle_off_deg: float = 0.0) -> Reference:
    """One agent at the start of a left arc of radius ``R`` [m] (a straight path when R is
    inf), speed ``v``, SUMO's angle ``angle_off_deg`` off the path's heading."""
    s = np.arange(0.0, 60.0, 0.5)
    pts = np.c_[s, np.zeros_like(s)] if math.isinf(R) else np.c_[R * np.sin(s / R), R * (1.0 - np.cos(s / R))]
    return Reference(0.0, [0.0], [0.0], [90.0 - angle_off_deg], [v], [0.0], [pts[14, 0]], [pts[14, 1]],
                     np.array([0, len(pts)]), pts)


def test_path_tightness_is_the_curvature_ahead_over_the_reach_and_the_lateral_demand():
    reach, a_lat = np.array([0.2]), np.array([8.0])
    kind, share, brake = np.array([models.KIND_CAR], np.int8), np.zeros(1), np.zeros(1)
    tight, sustained = path_tightness(_arc_ref(math.inf, 10.0), False, reach, a_lat, kind, share, brake)
    assert tight[0] == pytest.approx(0.0, abs=1e-9) and sustained[0] == pytest.approx(0.0, abs=1e-9)
    tight, sustained = path_tightness(_arc_ref(20.0, 10.0), False, reach, a_lat, kind, share, brake)
    assert tight[0] == pytest.approx((1.0 / 20.0) / 0.2, rel=0.05)  # a 20 m radius: 1/4 of a 5 m reach
    assert sustained[0] == pytest.approx(10.0 ** 2 / 20.0, rel=0.05)  # v^2 / R
    # at long steps the lateral demand counts against the grip: 5 m/s^2 of 8
    tight, _ = path_tightness(_arc_ref(20.0, 10.0), True, np.array([1.0]), a_lat, kind, share, brake)
    assert tight[0] == pytest.approx(5.0 / 8.0, rel=0.05)
    # at short steps at the share: a car braked at CAR_GRIP_BRAKE counts its sustained demand
    share, brake = grip_shares(kind, np.zeros(1), np.array([1300.0]))
    tight, sustained = path_tightness(_arc_ref(20.0, 10.0), False, np.array([1.0]), a_lat, kind, share, brake)
    assert tight[0] == pytest.approx(max(0.05, sustained[0] / (8.0 * CAR_GRIP_SHARE)), rel=0.05)


def _start_step(ref: Reference, prev: int, reach: float, yaw_rate: float = 0.0, dist: float = 0.0):
    return SimpleNamespace(ref=ref, interpolating=False, dist=np.array([dist]), yaw_rate=np.array([yaw_rate]),
                           reach=np.array([reach]), prev=np.array([prev]))


def test_a_carry_starts_beyond_the_reach_on_a_fast_turn_or_an_insertion_off_the_path():
    ref = _arc_ref(math.inf, 10.0)
    assert not starts(_start_step(ref, 0, 0.2), np.array([INFEASIBLE_MARGIN]))[0]
    assert starts(_start_step(ref, 0, 0.2), np.array([1.01 * INFEASIBLE_MARGIN]))[0]
    # SUMO turns it at twice full lock (0.2 / m at 10 m/s: 2 rad/s) once it is 1 m off
    assert starts(_start_step(ref, 0, 0.2, yaw_rate=4.0, dist=1.0), np.zeros(1))[0]
    assert not starts(_start_step(ref, 0, 0.2, yaw_rate=4.0, dist=0.1), np.zeros(1))[0]
    # inserted (no previous sample) moving with its angle far off its path
    off = _arc_ref(math.inf, 10.0, angle_off_deg=1.5 * SPAWN_OFF_DEG)
    assert starts(_start_step(off, -1, 0.2), np.zeros(1))[0]
    assert not starts(_start_step(off, 0, 0.2), np.zeros(1))[0]


def test_a_two_wheeler_rolls_back_only_with_a_clear_way():
    """A bicycle standing 2 m past its stop with a car 1 m behind it; a car 2 m past its stop."""
    n = 3
    obs = SimpleNamespace(cx=np.array([0.0, -3.8, 20.0]), cy=np.zeros(n), yaw=np.zeros(n))
    s = SimpleNamespace(
        n=n, kind=np.array([models.KIND_BIKE, models.KIND_CAR, models.KIND_CAR], np.int8),
        held=SimpleNamespace(speed=np.zeros(n)), e_lon=np.array([2.0, 0.0, 2.0]), obs=obs,
        length=np.array([1.6, 5.0, 5.0]), width=np.array([0.65, 1.8, 1.8]),
        ctl=SimpleNamespace(default=SimpleNamespace(hold_speed=0.1, creep_back_m=0.5)),
        mode=np.full(n, AgentMode.PHYSICAL, np.uint8),
    )
    v = Verdict.empty(s)
    assert list(rolls_back(s, v)) == [False, True, True]
    obs.cx[1] = -20.0
    assert list(rolls_back(s, v)) == [True, True, True]


@pytest.mark.parametrize("R, turn_deg, v, s0", [(10.0, 70.0, 13.0, -40.0), (1.0, 45.0, 14.0, -38.0)])
def test_a_turn_beyond_the_tyres_at_one_second_steps_is_carried_not_driven_wide(R, turn_deg, v, s0):
    """SUMO at 1 s steps takes a 70 deg bend of 10 m radius at 13 m/s (17 m/s^2, beyond the
    tyres' 11.7), or a 45 deg corner of its lane's shape at 14 m/s: between the interpolated
    samples the car is carried through it (kinematic, counted) and handed back on the
    straight, on its path and not turning (Hamburg: cars ran up to 9 m wide of such turns and
    were placed back). The second one is handed back 1 s after the corner: placed turning at
    the curvature of the lane's corner, or released while its chord still turned, it spun
    round (0.7 m off; 6.3 m and rolling backwards)."""
    f = make_fleet()
    m0 = circle_traffic(1, 0)
    L = 1.0
    worst, slowest, modes = 0.0, np.inf, []
    for k in range(9):
        s = s0 + v * k * L
        front, back = bend_xy(s, R, turn_deg)[0], bend_xy(s - 4.5, R, turn_deg)[0]
        chord = np.arctan2(front[1] - back[1], front[0] - back[0])
        pts = bend_xy(s + np.arange(0.0, 60.0, 1.0), R, turn_deg).astype(np.float32)
        a = one_agent(m0, k, front[0], front[1], 90.0 - np.degrees(chord), v, 0.0, pts)
        f.apply_step(replace(m0, step=k, time=k * L, step_length=L, agents=a))
        assert f.interpolating
        for _ in range(ticks_to(0.0, L, f.dt)):
            f.tick()
            snap = f.snapshot()
            modes.append(int(snap.mode[0]))
            if snap.mode[0] == AgentMode.PHYSICAL:
                worst = max(worst, float(np.hypot(snap.err_lon[0], snap.err_lat[0])))
                slowest = min(slowest, float(snap.speed[0]))
    assert f.counters["carries_infeasible"] == 1, f.counters
    assert f.counters["placements_divergence"] == 0 and f.counters["placements_flip"] == 0, f.counters
    assert modes[-1] == AgentMode.PHYSICAL  # handed back after the bend
    assert worst < 0.3, worst  # driven within 0.3 m before and after the carry
    assert slowest > v - 2.0, slowest  # no spin after the hand-back
    snap = f.snapshot()
    assert abs(((snap.heading[0] - 90.0 + turn_deg) + 180.0) % 360.0 - 180.0) < 3.0, snap.heading  # on the last leg


@pytest.mark.parametrize("cls, length, width, carried", [(AgentClass.BUS, 12.0, 2.5, True),
                                                         (AgentClass.PASSENGER, 5.0, 1.8, False)])
def test_a_heavy_vehicle_in_a_turn_beyond_its_grip_is_carried_at_short_steps(cls, length, width, carried):
    """SUMO takes a 12 m radius turn at 8.5 m/s (6 m/s^2) in 0.05 s steps: a bus (a heavy vehicle,
    HEAVY_GRIP_SHARE of its tyres' grip) is carried through it, a car drives it."""
    f = make_fleet()
    dt, v, s = 0.05, 8.5, 0.0
    for k in range(30):
        msg = turn_step(k, s, v, R=12.0, step_s=dt, length=length)
        a = msg.agents
        msg = replace(msg, agents=replace(a, cls=np.array([int(cls)], a.cls.dtype),
                                          length=np.array([length], a.length.dtype), width=np.array([width], a.width.dtype)))
        run_step(f, msg)
        s += v * dt
    assert (f.counters["carries_infeasible"] > 0) == carried, f.counters
    assert f.counters["placements_divergence"] == 0


@pytest.mark.parametrize("v, carried", [(13.4, True), (10.0, False)])
def test_a_car_on_a_bend_beyond_its_tyres_friction_is_carried(v, carried):
    """SUMO takes a car round a 12 m radius at 13.4 m/s (15 m/s^2, beyond its tyres' mu g of
    12.75) in 0.1 s steps, as it does on curved lanes that are no junction: the car is carried
    (driven, it steered at its grip's 11 deg and ran metres wide); at 10 m/s (8.3 m/s^2) it
    drives the bend."""
    f = make_fleet()
    dt, s, wide = 0.1, 0.0, 0.0
    for k in range(20):
        run_step(f, turn_step(k, s, v, R=12.0, step_s=dt))
        if f.mode[0] == AgentMode.PHYSICAL:
            wide = max(wide, abs(float(f.err_lat[0])))
        s += v * dt
    assert (f.counters["carries_infeasible"] > 0) == carried, f.counters
    assert (f.mode[0] == AgentMode.KINEMATIC) == carried  # (still in the bend: not handed back)
    assert f.counters["placements_divergence"] == 0
    assert wide < 0.5, wide


def test_an_agent_carried_from_its_first_step_starts_on_sumos_pose():
    """A bus SUMO inserts inside a turn beyond its grip is carried from its first step: its
    body starts on SUMO's pose, not gliding in from its parking spot (kilometres away)."""
    f = make_fleet()
    dt, v = 0.05, 8.5
    for k in range(4):
        msg = turn_step(k, 10.0 + v * dt * k, v, R=12.0, step_s=dt, length=12.0)
        a = msg.agents
        msg = replace(msg, agents=replace(a, cls=np.array([int(AgentClass.BUS)], a.cls.dtype),
                                          length=np.array([12.0], a.length.dtype), width=np.array([2.5], a.width.dtype)))
        run_step(f, msg)
        assert f.mode[0] == AgentMode.KINEMATIC
        s = f.snapshot()
        assert math.hypot(s.x[0] - a.x[0], s.y[0] - a.y[0]) < 1.0, (k, s.x[0], a.x[0])


def test_a_truck_inserted_moving_far_off_its_lanes_heading_is_carried_until_it_is_on_it():
    """SUMO inserts a truck at 13 m/s with its angle (the chord back to front) 33 deg off the
    lane its bumper drives along, and turns the angle onto the lane over 0.45 s (a curved lane
    meeting a straight one, A10 motorway network). A truck steers its rear axle and is placed on
    SUMO's chord: driven from there it ran 3.7 m wide. It is carried from its first step until
    its angle is on the lane, then driven."""
    f = make_fleet()
    dt, v = 0.05, 13.25
    worst, modes = 0.0, []
    for k in range(40):
        off = max(0.0, 33.0 * (1.0 - k / 9))
        msg = line_step(k, [100.0 + v * dt * k], [v], step_s=dt)
        msg = with_cols(msg, angle=np.array([90.0 - off], np.float32), cls=np.array([int(AgentClass.OTHER)], np.uint8),
                    length=np.array([7.1], np.float32), width=np.array([2.4], np.float32),
                    vtype=np.zeros(1, msg.agents.vtype.dtype))
        run_step(f, replace(msg, vtypes=[VType("lorry", "truck")]))
        modes.append(int(f.mode[0]))
        if f.mode[0] == AgentMode.PHYSICAL:
            worst = max(worst, float(np.hypot(f.err_lon, f.err_lat).max()))
    assert f.params.max_rear[0] > 0  # (a rear-steered model)
    assert modes[0] == AgentMode.KINEMATIC and modes[-1] == AgentMode.PHYSICAL, modes
    assert f.counters["carries_infeasible"] == 1 and f.counters["placements_divergence"] == 0, f.counters
    assert worst < 0.4, worst  # measured 0.28 m (before: 3.74 m)


@pytest.mark.parametrize("v, carried", [(8.0, True), (4.0, False)])
def test_a_two_wheeler_in_a_turn_beyond_its_lean_is_carried_upright_at_short_steps(v, carried):
    """SUMO takes a bicycle round an 8 m radius at 8 m/s (8 m/s^2: 39 deg of lean, beyond a
    rider's 35) in 0.05 s steps: carried upright (bicycles had fallen over in such junction
    turns and were placed back), and kept carried while SUMO still turns it harder than
    2 m/s^2; at 4 m/s (2 m/s^2) it is driven, leaning."""
    f = make_fleet()
    dt, s, roll_max = 0.05, 0.0, 0.0
    for k in range(40):
        msg = turn_step(k, s, v, R=8.0, step_s=dt, length=1.6)
        a = msg.agents
        msg = replace(msg, agents=replace(a, cls=np.array([int(AgentClass.BICYCLE)], a.cls.dtype),
                                          length=np.array([1.6], a.length.dtype), width=np.array([0.65], a.width.dtype)))
        run_step(f, msg)
        roll_max = max(roll_max, abs(float(f.world.observe(f.slots).roll[0])))
        s += v * dt
    assert (f.counters["carries_infeasible"] > 0) == carried, f.counters
    assert (f.mode[0] == AgentMode.KINEMATIC) == carried  # (still in the turn: not handed back)
    assert f.counters["placements_flip"] == 0 and f.counters["placements_divergence"] == 0
    assert (roll_max < 0.05) if carried else (0.1 < roll_max < math.radians(35.0)), math.degrees(roll_max)


def test_a_carried_two_wheeler_is_not_handed_back_while_its_path_still_turns():
    """SUMO takes a bicycle at 6 m/s into a junction's 4 m corner (9 m/s^2, beyond its lean:
    carried) that opens into a 10 m arc (3.6 m/s^2), holding its angle for 4 steps at a time
    and then jumping it, as it does with two-wheelers in the sublane model. The bicycle stays
    carried (upright) while its path ahead still turns (until the arc's last 5 m, where its 8 m
    windows ask less than 2 m/s^2), though SUMO's turn rate reads 0 on three steps of four
    (handed back then, a motorcycle over-turned 20 deg and fell), and drives on after it."""
    f = make_fleet()
    m0 = circle_traffic(1, 0)
    arcs = [(4.0, 30.0), (10.0, 90.0)]
    arc_end = sum(R * np.radians(t) for R, t in arcs)
    dt, v, s, angle = 0.05, 6.0, -6.0, 90.0
    in_arc_modes, roll_max = [], 0.0
    for k in range(int((arc_end + 18.0) / (v * dt))):
        front, back = arcs_xy(s, arcs)[0], arcs_xy(s - 1.6, arcs)[0]
        if k % 4 == 0:
            angle = 90.0 - np.degrees(np.arctan2(front[1] - back[1], front[0] - back[0]))
        pts = arcs_xy(s + np.arange(0.0, 40.0, 1.0), arcs).astype(np.float32)
        a = one_agent(m0, k, front[0], front[1], angle, v, 0.0, pts, cls=AgentClass.BICYCLE, size=(1.6, 0.65))
        run_step(f, replace(m0, step=k, time=k * dt, step_length=dt, agents=a))
        if 4.0 < s < arc_end - 5.0:
            in_arc_modes.append((round(s, 1), int(f.mode[0])))
        roll_max = max(roll_max, abs(float(f.world.observe(f.slots).roll[0])))
        s += v * dt
    assert f.counters["carries_infeasible"] > 0, f.counters
    assert in_arc_modes and all(m == AgentMode.KINEMATIC for _, m in in_arc_modes), [x for x in in_arc_modes if x[1] != 1]
    assert f.mode[0] == AgentMode.PHYSICAL  # handed back on the straight
    assert f.counters["placements_flip"] == 0 and f.counters["placements_divergence"] == 0, f.counters
    assert roll_max < math.radians(35.0), math.degrees(roll_max)


def test_a_carried_two_wheeler_is_not_handed_back_while_sumo_brakes_it_beyond_its_grip():
    """SUMO takes a bicycle at 9 m/s into a junction's 4 m corner (carried, upright) and
    brakes it at 6.5 m/s^2 from within it onto the straight: it stays carried while SUMO brakes it
    beyond 0.75 of what its tyres and lean carry (handed back upright while SUMO braked it
    hard into a bend, a motorcycle fell to the outside), then rides on."""
    f = make_fleet()
    m0 = circle_traffic(1, 0)
    arcs = [(4.0, 45.0)]
    arc_end = sum(R * np.radians(t) for R, t in arcs)
    dt, v, s, accel = 0.05, 9.0, -9.0, 0.0
    braking_modes = []
    for k in range(120):
        accel = -6.5 if (s > 1.0 and v > 1.2) else 0.0
        front, back = arcs_xy(s, arcs)[0], arcs_xy(s - 1.6, arcs)[0]
        pts = arcs_xy(s + np.arange(0.0, 40.0, 1.0), arcs).astype(np.float32)
        angle = 90.0 - np.degrees(np.arctan2(front[1] - back[1], front[0] - back[0]))
        a = one_agent(m0, k, front[0], front[1], angle, v, accel, pts, cls=AgentClass.BICYCLE, size=(1.6, 0.65))
        run_step(f, replace(m0, step=k, time=k * dt, step_length=dt, agents=a))
        if accel < 0.0 and s > arc_end + 2.0:  # braking, past the corner
            braking_modes.append(int(f.mode[0]))
        v = max(v + accel * dt, 0.0)
        s += v * dt
    assert f.counters["carries_infeasible"] > 0, f.counters
    assert braking_modes and all(m == AgentMode.KINEMATIC for m in braking_modes), braking_modes
    assert f.mode[0] == AgentMode.PHYSICAL  # rides on once SUMO no longer brakes it
    assert f.counters["placements_flip"] == 0 and f.counters["placements_divergence"] == 0, f.counters


@pytest.mark.parametrize("first_turn_deg, carried", [(40.0, True), (0.0, False)])
def test_a_two_wheeler_leaning_into_one_turn_with_the_other_way_ahead_is_carried(first_turn_deg, carried):
    """SUMO takes a motorcycle at 8 m/s through a junction's S, left round 10 m (6.4 m/s^2,
    leaning 33 deg) straight into right round 8 m (8 m/s^2): its lean would swing across both
    (on such an S a motorcycle still leaning into the left part flipped), so it is carried; the
    same right turn from a straight approach is within its lean and driven."""
    f = make_fleet()
    m0 = circle_traffic(1, 0)
    arcs = [(10.0, first_turn_deg), (8.0, -60.0)] if first_turn_deg else [(8.0, -60.0)]
    v, s = 8.0, -8.0
    for k in range(80):
        run_step(f, arcs_step(m0, k, s, v, 0.0, arcs, (2.2, 0.9), "motorcycle"))
        s += v * 0.05
    assert (f.counters["carries_infeasible"] > 0) == carried, f.counters
    assert f.counters["placements_flip"] == 0 and f.counters["placements_divergence"] == 0, f.counters


def test_a_car_carried_through_a_bend_beyond_its_tyres_is_handed_back_driving_straight_on():
    """SUMO takes a car through a 90 deg bend of 12 m radius at 13.4 m/s (15 m/s^2) in 0.1 s
    steps, with a lane shape's 20 deg corner where the bend meets the straight: carried, then
    handed back past the corner, from where it drives on within 0.3 m of SUMO."""
    f = make_fleet()
    m0 = circle_traffic(1, 0)
    arcs = [(12.0, 70.0), (0.5, 20.0)]  # (the corner: 20 deg within 0.17 m)
    arc_end = sum(R * np.radians(t) for R, t in arcs)
    dt, v, s = 0.1, 13.4, -10.0
    after = []
    for k in range(int((arc_end + 45.0) / (v * dt))):
        front, back = arcs_xy(s, arcs)[0], arcs_xy(s - 4.5, arcs)[0]
        chord = np.arctan2(front[1] - back[1], front[0] - back[0])
        pts = arcs_xy(s + np.arange(0.0, 40.0, 1.0), arcs).astype(np.float32)
        a = one_agent(m0, k, front[0], front[1], 90.0 - np.degrees(chord), v, 0.0, pts)
        run_step(f, replace(m0, step=k, time=k * dt, step_length=dt, agents=a))
        if s > arc_end and f.mode[0] == AgentMode.PHYSICAL:
            after.append(math.hypot(float(f.err_lon[0]), float(f.err_lat[0])))
        s += v * dt
    assert f.counters["carries_infeasible"] > 0, f.counters
    assert f.counters["placements_divergence"] == 0 and f.counters["placements_flip"] == 0, f.counters
    assert len(after) > 10 and max(after) < 0.3, max(after)


@pytest.mark.parametrize("blocked", [False, True])
def test_a_two_wheeler_stopped_past_its_stop_rolls_back_only_if_the_way_is_clear(blocked):
    """SUMO stops a bicycle from 6 m/s at 8 m/s^2 (it brakes at ~4.5): it comes to rest 2.8 m
    past SUMO's stop and rolls back to it, unless a body stands in its way back (a car that
    stops 0.2 m behind SUMO's bicycle): then it stays where it stopped."""
    f = make_fleet()
    dt = 0.1
    for k in range(110):
        t = k * dt
        u = min(max(t - 1.0, 0.0), 0.75)
        xb, vb = 6.0 * min(t, 1.0) + 6.0 * u - 4.0 * u * u, 6.0 - 8.0 * u
        w = min(max(t - 1.0, 0.0), 1.5)
        xc, vc = 1.95 - 6.0 * max(1.0 - t, 0.0) + 6.0 * w - 2.0 * w * w, 6.0 - 4.0 * w
        if not blocked:
            xc -= 30.0
        m = line_step(k, [xb, xc], [vb, vc], ids=["bike", "car"], step_s=dt)
        a = m.agents
        m = replace(m, agents=replace(a, cls=np.array([int(AgentClass.BICYCLE), int(AgentClass.PASSENGER)], a.cls.dtype),
                                      length=np.array([1.6, 5.0], a.length.dtype), width=np.array([0.65, 1.8], a.width.dtype)))
        run_step(f, m)
    ahead = float(f.err_lon[f.ids.index("bike")])
    assert f.counters["placements_divergence"] == 0 and f.counters["collisions_physics_only"] == 0, f.counters
    if blocked:
        assert ahead > 2.0, ahead  # stayed where it stopped
    else:
        assert abs(ahead) < 0.3, ahead  # (never rolled back: 2.84 m)
