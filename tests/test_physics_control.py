"""Controllers and references as pure functions over arrays (no MuJoCo)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from physics_side import control as C
from physics_side import kinematics as K
from physics_side.reference import PathSet, Reference, stopping_distance, tracking_error


# --------------------------------------------------------------------------- LAD


def test_lad_formula_matches_the_paper():
    v = np.array([0.0, 5.0, 6.99, 7.0, 8.5, 10.0, 30.0])
    got = C.lad(v, lad_min=7.0, lad_max=10.0, k_lad=1.0)
    # LAD_min below LAD_min, v * k in between, capped at LAD_max
    assert np.allclose(got, [7.0, 7.0, 7.0, 7.0, 8.5, 10.0, 10.0])
    assert np.allclose(C.lad(np.array([9.0]), 5.0, 20.0, 2.0), [18.0])


# --------------------------------------------------------------------------- pure pursuit


def test_pursuit_alpha_signs_and_geometry():
    # heading east; targets ahead-left, ahead-right, straight ahead, behind-left
    a = C.pursuit_alpha(np.zeros(4), np.zeros(4), np.zeros(4), np.array([10, 10, 10, -1.0]), np.array([10, -10, 0, 1.0]))
    assert np.allclose(a[:3], [math.pi / 4, -math.pi / 4, 0.0])
    assert a[3] == pytest.approx(math.pi - math.atan(1.0))
    # the same geometry rotated: heading north, target to the west is a left turn
    assert C.pursuit_alpha(0.0, 0.0, math.pi / 2, -5.0, 5.0) == pytest.approx(math.pi / 4)


def test_pure_pursuit_arc_passes_through_the_target():
    # target on a circle of radius R through the rear axle (tangent to the heading)
    L, R = 2.8, 15.0
    th = np.array([0.3, 0.6, 1.0])
    tx, ty = R * np.sin(th), R * (1 - np.cos(th))
    alpha = C.pursuit_alpha(0.0, 0.0, 0.0, tx, ty)
    delta = C.pure_pursuit_delta(alpha, np.hypot(tx, ty), np.full(3, L))
    assert np.allclose(delta, math.atan(L / R))


def test_paper_steer_percentage_and_clip():
    max_steer = np.full(4, math.radians(35))
    alpha = np.radians([0.0, 10.0, -10.0, 45.0])
    pct, ang = C.paper_steer(alpha, 0.05, max_steer)
    assert np.allclose(pct, [0.0, 0.5, -0.5, 1.0])  # 10 deg * 0.05 = 50 %; 45 deg clips to 100 %
    assert np.allclose(ang, pct * max_steer)


# --------------------------------------------------------------------------- longitudinal


def test_paper_pedal_terms():
    u, uc = C.paper_pedal(np.array([0.1, -0.1, 0.0, 2.0]), np.array([0.0, 0.0, 1.0, 0.0]), 15.0, 1.0)
    assert np.allclose(u, [0.75, -0.75, 0.5, 15.0])  # (K1 e + K2 de) / 2
    assert np.allclose(uc, [0.75, -0.75, 0.5, 1.0])
    drive, brake = C.pedal_to_torques(uc, np.full(4, 2000.0), np.full(4, 4000.0))
    assert np.allclose(drive, [1500, 0, 1000, 2000]) and np.allclose(brake, [0, 3000, 0, 0])


def test_accel_command_pd_ff_and_integral():
    a = C.accel_command(np.array([0.5, 0.0]), np.array([0.0, -1.0]), np.array([1.0, 0.0]), np.array([0.0, 2.0]),
                        omega=2.0, zeta=1.0, k_int=0.5)
    assert np.allclose(a, [1.0 + 4.0 * 0.5, -4.0 * 1.0 + 0.5 * 2.0])


def test_accel_to_torques_splits_drive_and_brake():
    d, b = C.accel_to_torques(np.array([2.0, -3.0, 100.0]), np.full(3, 1000.0), np.full(3, 0.3),
                              np.full(3, 2500.0), np.full(3, 5000.0))
    assert np.allclose(d, [600.0, 0.0, 2500.0]) and np.allclose(b, [0.0, 900.0, 0.0])


# --------------------------------------------------------------------------- lateral


def test_stanley_bumper_reduces_to_stanley_at_the_front_axle():
    he = np.array([0.1, -0.05, 0.0])
    e = np.array([0.0, 0.3, -0.4])
    v = np.array([10.0, 5.0, 2.0])
    L = np.full(3, 2.7)
    got = C.stanley_bumper(he, e, v, 2.0, 1.0, L, L)
    classic = -he - np.arctan2(2.0 * e, v + 1.0)
    assert np.allclose(got, classic)
    # guide point ahead of the front axle: same sign, smaller wheel angle for the same beta
    far = C.stanley_bumper(he, e, v, 2.0, 1.0, L + 1.0, L)
    assert np.all(np.sign(far) == np.sign(classic)) and np.all(np.abs(far) < np.abs(classic))
    # left of the path (e > 0) steers right
    assert C.stanley_bumper(np.zeros(1), np.ones(1), np.full(1, 5.0), 2.0, 1.0, np.full(1, 3.5), np.full(1, 2.7))[0] < 0


def test_steady_state_delta_keeps_the_bumper_on_the_circle():
    L, d, R = 2.8, 3.8, 12.0
    delta = K.steady_state_delta(np.array([1 / R, -1 / R, 0.0]), np.full(3, d), np.full(3, L))
    r_rear = L / np.tan(abs(delta[0]))
    assert math.hypot(r_rear, d) == pytest.approx(R)
    assert delta[1] == pytest.approx(-delta[0]) and delta[2] == 0.0


def test_ackermann_inner_wheel_turns_more_about_one_centre():
    L, T = np.full(2, 2.8), np.full(2, 1.6)
    left, right = K.ackermann(np.array([0.3, -0.3]), L, T)
    assert left[0] > 0.3 > right[0] > 0  # left turn: left wheel inner
    assert right[1] < -0.3 < left[1] < 0
    # both wheel axes meet the rear-axle line at the same point
    R = 2.8 / math.tan(0.3)
    assert 2.8 / math.tan(left[0]) == pytest.approx(R - 0.8)
    assert 2.8 / math.tan(right[0]) == pytest.approx(R + 0.8)


def test_roll_stabiliser_targets_the_lean_into_the_turn():
    # upright bicycle in a steady left turn: target lean is negative roll (left side down)
    t = C.roll_stabiliser(np.zeros(1), np.zeros(1), np.full(1, 6.0), np.full(1, 0.6), 1000.0, 100.0, np.full(1, 1e4))
    lean = math.atan(6.0 * 0.6 / 9.81)
    assert t[0] == pytest.approx(-1000.0 * lean)
    # at the target lean and not rolling: no torque; torque clipped to the limit
    assert C.roll_stabiliser(np.full(1, -lean), np.zeros(1), np.full(1, 6.0), np.full(1, 0.6), 1000.0, 100.0,
                             np.full(1, 1e4))[0] == pytest.approx(0.0, abs=1e-9)
    assert C.roll_stabiliser(np.full(1, 1.0), np.zeros(1), np.zeros(1), np.zeros(1), 1000.0, 100.0, np.full(1, 50.0))[0] == -50.0


def test_planar_force_is_bounded_in_norm():
    fx, fy = C.planar_force(np.array([10.0, 0.01]), np.array([10.0, 0.0]), np.zeros(2), np.zeros(2), np.zeros(2),
                            np.zeros(2), np.full(2, 70.0), 3.0, 1.0, np.full(2, 300.0))
    assert math.hypot(fx[0], fy[0]) == pytest.approx(300.0)
    assert fx[0] == pytest.approx(fy[0])  # direction kept
    assert fx[1] == pytest.approx(70.0 * 9.0 * 0.01)  # unclipped PD term


def test_control_state_take_realigns():
    s = C.ControlState(integ=np.array([1.0, 2.0, 3.0]))
    t = s.take(np.array([2, -1, 0]))
    assert np.allclose(t.integ, [3.0, 0.0, 1.0])


def test_control_state_sees_the_step_length_from_the_reference_age():
    s = C.ControlState.zeros(1)
    taus = [0.0, 0.02, 0.04, 0.06, 0.08, 0.0, 0.02]  # 0.1 s steps at 50 Hz
    got = [s.observe_tau(t, 0.02) for t in taus]
    assert got[:5] == [0.0] * 5 and got[5] == pytest.approx(0.1) and got[6] == pytest.approx(0.1)
    # 0.05 s steps: 3, 2, 3 ticks, each new step 0.01 s behind physics time
    s = C.ControlState.zeros(1)
    for t in (0.0, 0.02, 0.04, 0.01, 0.03):
        step = s.observe_tau(t, 0.02)
    assert step == pytest.approx(0.05)
    assert s.take(np.array([0])).step_s == pytest.approx(0.05)  # kept over a new SUMO step


def test_mean_speed_lead_follows_sumos_euler_positions():
    """SUMO's Euler update moves a vehicle at its new speed over the step: from a sample
    (v, a) the next sample is v' = v + a dt, s = v' dt. The extrapolation plus the lead
    of half a step reaches it exactly; without it, a dt^2 / 2 short and a dt / 2 too fast."""
    dt, v, a = 0.1, 12.0, -4.5
    line = np.c_[np.arange(0.0, 40.0, 1.0), np.zeros(40)]
    ref = Reference(0.0, np.zeros(1), np.zeros(1), np.array([90.0]), np.array([v]), np.array([a]), np.zeros(1),
                    np.zeros(1), np.array([0, 40]), line)
    s, vel = ref.profile(dt)
    ds, dv = ref.mean_speed_lead(dt, 0.5 * dt)
    assert s[0] + ds[0] == pytest.approx((v + a * dt) * dt)
    assert vel[0] + dv[0] == pytest.approx(v + a * dt + a * dt / 2)  # the smooth speed at the next sample
    assert ref.mean_speed_lead(dt, 0.0)[0][0] == 0.0
    # a stop within the lead never reverses
    ref = Reference(0.0, np.zeros(1), np.zeros(1), np.array([90.0]), np.array([0.1]), np.array([-4.5]),
                    np.zeros(1), np.zeros(1), np.array([0, 40]), line)
    ds, dv = ref.mean_speed_lead(0.01, 0.05)
    s, vel = ref.profile(0.01)
    assert vel[0] + dv[0] == pytest.approx(0.0) and s[0] + ds[0] >= 0.0


# --------------------------------------------------------------------------- references


def _arc(R: float, n: int, x0=0.0, y0=0.0):
    th = np.linspace(0, np.pi / 2, n)
    return np.c_[x0 + R * np.sin(th), y0 + R * (1 - np.cos(th))]


def test_pathset_evaluates_ragged_polylines_and_extrapolates():
    line = np.c_[np.linspace(0, 30, 4), np.full(4, 5.0)]
    arc = _arc(10.0, 41)
    ps = PathSet(np.array([0, 4, 45]), np.vstack([line, arc]))
    assert np.allclose(ps.total, [30.0, 10 * np.pi / 2], rtol=1e-3)
    p = ps.at(np.array([12.0, 10 * np.pi / 4]))
    assert (p.x[0], p.y[0], p.heading[0], p.curvature[0]) == pytest.approx((12.0, 5.0, 0.0, 0.0))
    assert math.hypot(p.x[1], p.y[1] - 10.0) == pytest.approx(10.0, abs=2e-3)  # on the circle
    assert p.heading[1] == pytest.approx(math.pi / 4, abs=1e-3) and p.curvature[1] == pytest.approx(0.1, rel=1e-2)
    # before the start / past the end: along the first / last segment
    q = ps.at(np.array([-2.0, 100.0]))
    assert (q.x[0], q.y[0]) == pytest.approx((-2.0, 5.0))
    end = arc[-1]
    assert math.hypot(q.x[1] - end[0], q.y[1] - end[1]) == pytest.approx(100.0 - ps.total[1])
    assert q.y[1] > 90.0 and abs(q.x[1] - end[0]) < 0.03 * (100.0 - ps.total[1])  # along the last chord


def test_pathset_synthesises_arcs_without_a_path():
    ps = PathSet.concat_fallback(np.zeros(0), np.zeros((0, 2)), np.array([0.0, 1.0]), np.array([0.0, 0.0]),
                                 np.array([0.0, np.pi / 2]), np.array([0.0, 0.1]))
    p = ps.at(np.array([10.0, 10 * np.pi / 2]))
    assert (p.x[0], p.y[0]) == pytest.approx((10.0, 0.0))
    assert (p.x[1], p.y[1]) == pytest.approx((-9.0, 10.0), abs=0.05)  # quarter circle of radius 10


def test_stopping_distance_never_reverses():
    s, v = stopping_distance(np.array([10.0, 10.0, 2.0]), np.array([2.0, -2.0, -4.0]), 1.0)
    assert np.allclose(s, [11.0, 9.0, 0.5]) and np.allclose(v, [12.0, 8.0, 0.0])


def test_reference_held_extrapolated_and_projection():
    arc = _arc(20.0, 200).astype(np.float32)
    ref = Reference(
        t_k=3.0, x=np.array([0.0]), y=np.array([0.0]), angle_deg=np.array([90.0]), speed=np.array([5.0]),
        accel=np.array([1.0]), la_x=np.array([7.0]), la_y=np.array([1.0]),
        path_offsets=np.array([0, 200]), path_xy=arc,
    )
    h = ref.held()
    assert (h.x[0], h.y[0], h.speed[0]) == (0.0, 0.0, 5.0)
    r = ref.at(0.1)
    s = 5.0 * 0.1 + 0.5 * 0.1**2
    assert r.s[0] == pytest.approx(s) and r.speed[0] == pytest.approx(5.1)
    assert math.hypot(r.x[0], r.y[0] - 20.0) == pytest.approx(20.0, abs=1e-3)
    assert r.yaw[0] == pytest.approx(s / 20.0, abs=2e-3)
    assert r.tangent[0] == pytest.approx(s / 20.0, abs=2e-3)  # same here: SUMO's angle is the tangent
    # a point 0.3 m left of the path at s = 2 m projects back to s = 2, lateral +0.3
    p = ref.point_at(np.array([2.0]))
    px, py = p.x - 0.3 * np.sin(p.heading), p.y + 0.3 * np.cos(p.heading)
    s_p, lat, _ = ref.project(px, py, np.array([1.9]))
    assert s_p[0] == pytest.approx(2.0, abs=5e-3) and lat[0] == pytest.approx(0.3, abs=5e-3)
    lon, lat2 = tracking_error(np.array([1.0]), np.array([0.0]), h)  # heading east at the sample
    assert lon[0] == pytest.approx(1.0) and lat2[0] == pytest.approx(0.0, abs=1e-6)


def test_pathset_drops_repeated_vertices_and_keeps_straight_headings():
    # SUMO repeats the junction point where one lane ends and the next begins
    xy = np.array([[0.0, 0.0], [-15.0, 0.0], [-15.0, 0.0], [-25.0, 0.0]])
    off, xy2 = PathSet.dedup(np.array([0, 4]), xy)
    assert list(off) == [0, 3] and len(xy2) == 3
    ps = PathSet.concat_fallback(np.array([0, 4]), xy, np.zeros(1), np.zeros(1), np.full(1, np.pi), np.zeros(1))
    for s in (0.0, 5.0, 14.0, 15.0, 20.0):
        p = ps.at(np.array([s]))
        assert abs(abs(p.heading[0]) - np.pi) < 1e-9 and p.curvature[0] == 0.0


def test_pathset_long_segments_turn_only_near_the_corner():
    # 20 m east, then 20 m north: the heading blends over BLEND_M around the corner only
    from physics_side.reference import BLEND_M

    ps = PathSet(np.array([0, 3]), np.array([[0.0, 0.0], [20.0, 0.0], [20.0, 20.0]]))
    h = lambda s: ps.at(np.array([s])).heading[0]  # noqa: E731
    assert h(20.0 - BLEND_M - 0.1) == 0.0 and h(20.0) == pytest.approx(np.pi / 4)
    assert h(20.0 + BLEND_M + 0.1) == pytest.approx(np.pi / 2)
    assert ps.at(np.array([19.0])).curvature[0] == pytest.approx(np.pi / 2 / (2 * BLEND_M))


def test_pathset_a_lanes_last_stretch_before_a_tight_curve_keeps_its_heading():
    """The last 3.4 m of a straight lane before a dead end's U-turn (1.44 m segments of radius
    1.6 m): the path heads along the lane at the bumper (it took 2.4 times the U-turn's first
    corner, 46 deg off, and a bicycle steered off its lane); a sampled curve's first segment,
    as long as its neighbours, still continues their turn."""
    u = np.array([[17.01, 301.6], [13.6, 301.6], [12.4, 300.8], [12.0, 300.0], [12.4, 299.2], [13.6, 298.4],
                  [30.0, 298.4]])
    ps = PathSet(np.array([0, len(u)]), u)
    assert ps.at(np.array([0.0])).heading[0] == pytest.approx(np.pi)
    th = np.radians(np.arange(0.0, 91.0, 10.0))  # a quarter circle sampled every 10 deg
    arc = np.c_[10.0 * np.sin(th), 10.0 * (1.0 - np.cos(th))]
    ps = PathSet(np.array([0, len(arc)]), arc)
    assert ps.at(np.array([0.0])).curvature[0] == pytest.approx(0.1, rel=0.05)


def test_sumo_body_angle_is_kept_apart_from_the_path_tangent():
    """In a junction SUMO's angle is the rear-to-front chord, not the lane tangent at the
    front bumper: controllers steer on the tangent, kinematic agents show SUMO's angle."""
    line = np.c_[np.linspace(0, 30, 4), np.zeros(4)].astype(np.float32)  # tangent east
    ref = Reference(
        t_k=0.0, x=np.array([0.0]), y=np.array([0.0]), angle_deg=np.array([110.0]), speed=np.array([5.0]),
        accel=np.array([0.0]), la_x=np.array([7.0]), la_y=np.array([0.0]),
        path_offsets=np.array([0, 4]), path_xy=line,
    )
    assert ref.point_at(np.array([3.0])).heading[0] == pytest.approx(0.0)
    assert ref.held().tangent[0] == pytest.approx(0.0)
    assert ref.at(0.1).yaw[0] == pytest.approx(np.radians(-20.0))  # SUMO's angle, turned with the path
    lon, lat = tracking_error(np.array([1.0]), np.array([0.5]), ref.held())
    assert (lon[0], lat[0]) == pytest.approx((1.0, 0.5))  # along / across the path


def test_rear_axle_steer_puts_the_body_on_the_chord_of_a_circle():
    """On a circle of radius R with the body on the chord (SUMO's angle) both axles sit on the
    circle: the kinematic solution steers front and rear by the same angle, opposite ways, and
    keeps the bumper's direction the fixed-axle law asked for."""
    from physics_side.control import rear_axle_steer

    L, d, R, v = 6.0, 9.0, 12.0, 4.0
    # both axles on the circle: their velocities are its tangents, +a and -a off the chord,
    # a = asin(L / 2R); the body turns at V / R with its forward speed v = V cos(a)
    a = math.asin(L / (2 * R))
    beta = math.atan((1 - d / L) * math.tan(-a) + d / L * math.tan(a))
    steer = np.array([math.atan(L * math.tan(beta) / d)])
    front, rear = rear_axle_steer(steer, np.zeros(1), np.array([v]), np.zeros(1),
                                  np.array([v / (R * math.cos(a))]), np.array([L]), np.array([d]), np.array([0.9]),
                                  np.array([0.7]))
    assert front[0] == pytest.approx(a, abs=1e-9) and rear[0] == pytest.approx(-a, abs=1e-9)
    # a saturated front axle: the rear turns against it for the bumper's direction
    front, rear = rear_axle_steer(np.array([1.2]), np.zeros(1), np.array([v]), np.zeros(1), np.zeros(1),
                                  np.array([L]), np.array([d]), np.array([0.6]), np.array([0.7]))
    assert front[0] == pytest.approx(0.6) and rear[0] < 0.0


def test_a_saturated_front_axle_never_crabs_a_lagging_body_sideways():
    """Front at full lock while the body lags SUMO's angle (a 7.1 m truck in a junction turn):
    the rear axle does not turn in phase with the front (which crabs the bumper sideways at
    no yaw rate: the truck's body fell 23 deg behind); aligned, the bumper's direction wins."""
    from physics_side.control import rear_axle_steer

    L, d, v, lim_f, lim_r = 4.26, 5.5, 3.9, math.radians(50.0), math.radians(40.0)

    def steer(lag: float) -> tuple[float, float]:
        f, r = rear_axle_steer(np.array([0.852]), np.zeros(1), np.array([v]), np.array([lag]), np.array([0.487]),
                               np.array([L]), np.array([d]), np.array([lim_f]), np.array([lim_r]), a_lat=np.array([9.0]))
        return float(f[0]), float(r[0])

    f, r = steer(0.377)  # 21.6 deg behind
    assert f == pytest.approx(lim_f) and r * f <= 0.0
    f, r = steer(0.0)  # on SUMO's angle: the rear turns in phase for the bumper's direction
    assert f == pytest.approx(lim_f) and r > 0.0


def test_steer_limit_is_the_friction_circle_or_the_mechanical_limit():
    """``steer_limit`` is what ``friction_steer_limit`` clips to: atan(L a / v^2) at speed, the
    mechanical limit when slow (a car of 2.7 m at 11.7 m/s^2: 10.6 deg at 13 m/s, 35 deg at 3)."""
    from physics_side.control import friction_steer_limit, steer_limit

    v = np.array([3.0, 13.0, 20.0])
    L, a, mx = np.full(3, 2.7), np.full(3, 11.7), np.full(3, np.radians(35.0))
    lim = steer_limit(v, L, a, mx)
    assert np.degrees(lim[0]) == pytest.approx(35.0)
    assert np.degrees(lim[1]) == pytest.approx(np.degrees(np.arctan(2.7 * 11.7 / 169.0)))
    assert np.all(np.diff(lim) < 0)
    assert np.allclose(friction_steer_limit(np.full(3, 1.0), v, L, a, mx), lim)
    assert np.allclose(friction_steer_limit(np.full(3, -1.0), v, L, a, mx), -lim)


def test_default_loop_brakes_faster_when_ahead_and_catches_up_as_before():
    """The along-path loop brakes at ``brake_omega`` where that asks for more braking (the
    car ahead of SUMO or faster: it learns a sample late that SUMO brakes) and keeps
    ``pos_omega`` where it catches up."""
    from dataclasses import replace

    from physics_side.config import DefaultControl

    n = 2
    xs = np.r_[np.arange(0.0, 60.0, 2.0), np.arange(0.0, 60.0, 2.0)]
    path = np.c_[xs, np.zeros_like(xs)]
    ref = Reference(0.0, np.zeros(n), np.zeros(n), np.full(n, 90.0), np.full(n, 10.0), np.zeros(n),
                    np.full(n, 7.0), np.zeros(n), np.array([0, 30, 60]), path)
    # agent 0 is 0.2 m ahead and 0.5 m/s faster than its reference, agent 1 as much behind and slower
    fx, v = np.array([0.2, -0.2]), np.array([10.5, 9.5])
    one = np.ones(n)
    obs = C.VehicleObs(fx, np.zeros(n), fx - 4.0, np.zeros(n), np.zeros(n), v, np.zeros(n), v, np.zeros(n))
    p = C.VehicleParams(2.7 * one, 3.6 * one, -1.3 * one, 2.3 * one, 1400.0 * one, 0.3 * one,
                        np.radians(35.0) * one, 2500.0 * one, 5000.0 * one)
    cfg = DefaultControl()
    assert cfg.brake_omega > cfg.pos_omega
    cmds = {}
    for w in (cfg.brake_omega, cfg.pos_omega):  # (brake_omega <= pos_omega: one loop)
        st = C.ControlState.zeros(n)
        cmds[w] = C.control_default(obs, p, ref, 0.0, 0.02, replace(cfg, brake_omega=w), st).aux
        integ = st.integ
    e_s, e_v = np.array([-0.2, 0.2]), np.array([-0.5, 0.5])
    slow = C.accel_command(e_s, e_v, 0.0, integ, cfg.pos_omega, cfg.pos_zeta, cfg.k_int)
    fast = C.accel_command(e_s, e_v, 0.0, integ, cfg.brake_omega, cfg.pos_zeta, cfg.k_int)
    np.testing.assert_allclose(cmds[cfg.pos_omega], slow, atol=1e-6)
    np.testing.assert_allclose(cmds[cfg.brake_omega], [fast[0], slow[1]], atol=1e-6)
    assert cmds[cfg.brake_omega][0] < cmds[cfg.pos_omega][0] - 2.0  # -7.2 instead of -3.75 m/s^2
    # a reference interpolated to the next sample (long steps) brings no late news: one loop
    for w in (cfg.brake_omega, cfg.pos_omega):
        ref.interpolate_to(0.5, np.ones(n, bool), np.full(n, 5.0), np.full(n, 10.0), np.zeros(n), np.zeros(n))
        assert ref.interpolated is not None
        cmds[w] = C.control_default(obs, p, ref, 0.0, 0.02, replace(cfg, brake_omega=w), C.ControlState.zeros(n)).aux
    np.testing.assert_allclose(cmds[cfg.brake_omega], cmds[cfg.pos_omega], atol=1e-9)


def test_lane_change_feed_forward_uses_the_cars_own_speed():
    """SUMO drifts the sample sideways at 1 m/s while its speed along the lane is 2 m/s;
    a car catching up at 4 m/s moves sideways at SUMO's 1 m/s with its bumper at
    atan(1 / 4) to the lane, not atan(1 / 2) (pulling away from a stop mid-lane-change, the
    reference car ran 0.15 m past its new lane's centre line)."""
    from physics_side.config import DefaultControl

    xs = np.arange(0.0, 60.0, 2.0)
    ref = Reference(0.0, np.zeros(1), np.zeros(1), np.full(1, 90.0), np.full(1, 2.0), np.zeros(1),
                    np.full(1, 7.0), np.zeros(1), np.array([0, 30]), np.c_[xs, np.zeros_like(xs)])
    ref.set_side_rate(np.array([1.0]))
    assert ref.drift_angle(0.0) == pytest.approx(math.atan(0.5))
    yaw, v = math.atan(0.25), 4.0
    one = np.ones(1)
    obs = C.VehicleObs(np.zeros(1), np.zeros(1), -4.0 * math.cos(yaw) * one, -4.0 * math.sin(yaw) * one,
                       yaw * one, v * one, np.zeros(1), v * math.cos(yaw) * one, v * math.sin(yaw) * one)
    p = C.VehicleParams(2.7 * one, 3.6 * one, -1.3 * one, 2.3 * one, 1400.0 * one, 0.3 * one,
                        np.radians(35.0) * one, 2500.0 * one, 5000.0 * one)
    cmd = C.control_default(obs, p, ref, 0.0, 0.02, DefaultControl(), C.ControlState.zeros(1))
    assert abs(float(cmd.steer[0])) < 1e-3, cmd.steer  # (0.17 rad with SUMO's speed)


def test_a_leaning_two_wheeler_gets_only_the_drive_its_tyres_carry_beside_the_lean():
    """Upright: the drive asked for; leaning at the lean limit's lateral acceleration (a
    motorcycle's 42 deg): 0.31 of the maximum (the 0.95 cap); half of it: sqrt(0.75) of it;
    braking (negative drive) and smaller requests pass unchanged."""
    a_lat = np.full(4, C.G * math.tan(math.radians(42.0)))
    max_drive = np.full(4, 500.0)
    half = math.atan(0.5 * math.tan(math.radians(42.0)))
    roll = np.array([0.0, math.radians(42.0), -half, math.radians(42.0)])
    out = C.lean_traction_limit(np.array([500.0, 500.0, 500.0, -80.0]), roll, a_lat, max_drive)
    assert out[0] == pytest.approx(500.0)
    assert out[1] == pytest.approx(500.0 * math.sqrt(1.0 - 0.95 ** 2))
    assert out[2] == pytest.approx(500.0 * math.sqrt(0.75))
    assert out[3] == pytest.approx(-80.0)


# --------------------------------------------------------------------------- vehicle limits, composed


def _limits(n: int, a_lat: float = 8.0, bike=None, max_rear=None, grip=np.inf, mass: float = 1300.0):
    """``VehicleLimits`` of ``n`` agents alike."""
    bike = np.zeros(n, bool) if bike is None else np.asarray(bike, bool)
    grip = np.full(n, grip)
    return C.VehicleLimits(a_lat=np.full(n, a_lat), grip_torque=grip,
                           max_rear=np.zeros(n) if max_rear is None else np.asarray(max_rear, float),
                           stab_gain=np.ones(n), stab_max=np.full(n, 200.0), mass=np.full(n, mass), bike=bike,
                           any_grip=bool(np.isfinite(grip).any()), any_bike=bool(bike.any()))


def _params(n: int, wheelbase: float = 2.7, max_steer_deg: float = 35.0):
    one = np.ones(n)
    return C.VehicleParams(wheelbase * one, 3.6 * one, -1.3 * one, 2.3 * one, 1400.0 * one, 0.3 * one,
                           np.radians(max_steer_deg) * one, 2500.0 * one, 5000.0 * one)


def test_vehicle_limits_cap_a_riders_lean_and_find_the_grip_limited_drives():
    mu = np.full(3, 1.0)
    mass = np.array([1300.0, 90.0, 2 * C.MOTORCYCLE_MASS_KG])
    bike = np.array([False, True, True])
    lim = C.vehicle_limits(mu, mass, bike, np.array([np.inf, np.inf, 3000.0]), np.full(3, 0.3), np.zeros(3),
                           np.ones(3), np.full(3, 200.0))
    tyres = C.A_LAT_SHARE * C.G
    assert lim.a_lat == pytest.approx([tyres, C.G * math.tan(math.radians(C.BIKE_MAX_LEAN_DEG)),
                                       min(tyres, C.G * math.tan(math.radians(C.MOTORCYCLE_MAX_LEAN_DEG)))])
    assert lim.any_grip and lim.any_bike
    assert list(np.isfinite(lim.grip_torque)) == [False, False, True]


def test_merge_commands_keeps_one_controllers_arrays_and_merges_two_by_mask():
    n = 3
    a = C.VehicleCommand(np.full(n, 0.1), np.full(n, 10.0), np.zeros(n), np.zeros(n))
    b = C.VehicleCommand(np.full(n, -0.2), np.zeros(n), np.full(n, 50.0), np.ones(n))
    steer, drive, brake, aux = C.merge_commands(n, [(True, np.ones(n, bool), a)])
    assert steer is a.steer and drive is a.drive
    use_a = np.array([True, False, False])
    steer, drive, brake, aux = C.merge_commands(n, [(False, use_a, a), (False, np.array([False, True, False]), b)])
    assert list(steer) == [0.1, -0.2, 0.0] and list(brake) == [0.0, 50.0, 0.0] and list(aux) == [0.0, 1.0, 0.0]


def test_groups_split_the_agents_by_what_a_tick_does_with_them():
    from protocol.messages import AgentMode

    ped = np.array([False, False, False, True, False])
    mode = np.array([AgentMode.PHYSICAL, AgentMode.PHYSICAL, AgentMode.KINEMATIC, AgentMode.PHYSICAL,
                     AgentMode.EXTERNAL], np.uint8)
    preset = np.array([C.P_DEFAULT, C.P_PAPER, C.P_DEFAULT, C.P_DEFAULT, C.P_DEFAULT], np.int8)
    g = C.groups(ped, mode, preset, False, np.arange(10, 15))
    assert list(g.kin_idx) == [2, 4] and list(g.ped_idx) == [3] and list(g.veh_idx) == [0, 1, 2, 4]
    assert list(g.use_default) == [True, False, False, False, False] and list(g.use_paper) == [False, True, False,
                                                                                                 False, False]
    assert list(g.veh_slots) == [10, 11, 12, 14] and not g.all_veh and g.any_paper and not g.all_default
    g = C.groups(ped, mode, preset, True, np.arange(5))  # stopping: every vehicle brakes with ours
    assert len(g.kin_idx) == 0 and list(g.use_default) == [True, True, True, False, True] and not g.any_paper


def test_limit_commands_clip_the_steering_to_the_friction_circle_and_cut_drive_in_grip():
    """At 10 m/s on 8 m/s^2 of grip a 2.7 m car steers at most atan(2.7 * 8 / 100); a car that
    steers its rear axle keeps its demand; the grip-limited drive loses what the turn uses."""
    from types import SimpleNamespace

    n = 2
    obs = SimpleNamespace(speed=np.full(n, 10.0), yaw_rate=np.array([0.0, 0.8]), roll=np.zeros(n))
    steer, drive, brake = C.limit_commands(np.full(n, 0.5), np.full(n, 1000.0), np.zeros(n), obs, _params(n),
                                           _limits(n, grip=600.0), False, None)
    assert steer == pytest.approx(np.full(n, math.atan(2.7 * 8.0 / 100.0)))
    use = min(10.0 * 0.8 / C.G, C.MAX_GRIP_USE) * C.GRIP_LATERAL
    assert drive == pytest.approx([600.0, 600.0 * math.sqrt(1.0 - use * use)]) and not brake.any()
    steer, _, _ = C.limit_commands(np.full(n, 0.5), np.zeros(n), np.zeros(n), obs, _params(n),
                                   _limits(n, max_rear=[0.0, 0.2]), True, None)
    assert steer[0] == pytest.approx(math.atan(0.216)) and steer[1] == 0.5


def test_limit_commands_catch_up_gets_no_drive_into_a_bend_it_cannot_take():
    """A car at 12 m/s, its reference at 10 m/s, a 20 m bend ahead (8 m/s^2 allows 12.6 m/s):
    drive kept; the same at 14 m/s: no drive. Off the mask (the paper's car): kept."""
    from types import SimpleNamespace

    from physics_side.reference import Reference

    s = np.arange(0.0, 80.0, 0.5)
    pts = np.c_[20.0 * np.sin(s / 20.0), 20.0 * (1.0 - np.cos(s / 20.0))]
    ref = Reference(0.0, [0.0, 0.0], [0.0, 0.0], [90.0, 90.0], [10.0, 10.0], [0.0, 0.0], [5.0, 5.0], [0.0, 0.0],
                    np.array([0, len(pts), 2 * len(pts)]), np.r_[pts, pts])
    for v, mask, kept in ((12.0, True, True), (14.0, True, False), (14.0, False, True)):
        obs = SimpleNamespace(speed=np.full(2, v), yaw_rate=np.zeros(2), roll=np.zeros(2))
        catch_up = C.CatchUp(ref, np.zeros(2), 0.0, np.full(2, mask), np.zeros(2))
        _, drive, _ = C.limit_commands(np.zeros(2), np.full(2, 100.0), np.zeros(2), obs, _params(2), _limits(2),
                                       False, catch_up)
        assert (drive[0] == 100.0) == kept, (v, mask)


def test_the_bicycles_stabiliser_leans_at_most_max_lean_tan_and_motorcycles_to_their_grip():
    from types import SimpleNamespace

    n = 2
    obs = SimpleNamespace(roll=np.zeros(n), roll_rate=np.zeros(n), speed=np.full(n, 8.0))
    lim = _limits(n, a_lat=9.0, bike=[True, True])
    lim = C.VehicleLimits(**{**lim.__dict__, "mass": np.array([90.0, 2 * C.MOTORCYCLE_MASS_KG])})
    steer = np.full(n, 0.3)
    p = _params(n, wheelbase=1.1)
    out = C.bike_stabiliser(obs, steer, p, lim, np.arange(n), 40.0, 5.0)
    want = [C.steered_roll_stabiliser(obs.roll[i:i + 1], obs.roll_rate[i:i + 1], obs.speed[i:i + 1], steer[i:i + 1],
                                      p.wheelbase[i:i + 1], 40.0, 5.0, lim.stab_max[i:i + 1], cap)[0]
            for i, cap in ((0, C.MAX_LEAN_TAN), (1, 9.0 / C.G))]
    assert out == pytest.approx(want) and abs(out[1]) > abs(out[0])


def test_pedestrian_control_targets_the_held_sample_the_reference_or_a_stop():
    from types import SimpleNamespace

    n = 3
    z = np.zeros(n)
    obs = SimpleNamespace(fx=np.array([0.0, 0.0, 5.0]), fy=z, vx=z, vy=z, yaw=z, yaw_rate=z)
    held = SimpleNamespace(x=np.full(n, 1.0), y=z, tangent=z, speed=np.full(n, 1.0))
    at = SimpleNamespace(x=np.full(n, 2.0), y=z, tangent=z, speed=np.full(n, 1.0), accel=z, curvature=z)
    from physics_side.config import DefaultControl, PaperControl

    idx = np.arange(n)
    fx, fy, tz, norm = C.pedestrian_control(idx, obs, at, held, np.array([True, False, False]), None, np.full(n, 70.0),
                                            np.full(n, 1e4), PaperControl(), DefaultControl())
    assert 0.0 < fx[0] < fx[1]  # 1 m to the held sample, 2 m to the reference
    fx, _, _, _ = C.pedestrian_control(idx, obs, at, held, np.zeros(n, bool), np.zeros(n), np.full(n, 70.0),
                                       np.full(n, 1e4), PaperControl(), DefaultControl())
    assert fx == pytest.approx(np.zeros(n))  # stopping where they are: no force


def test_rear_axle_commands_steer_only_the_agents_given():
    from types import SimpleNamespace

    n = 3
    obs = SimpleNamespace(yaw=np.array([0.0, 0.0, 0.1]), speed=np.full(n, 5.0))
    steer = np.full(n, 0.2)
    rear = C.rear_axle_commands(steer, obs, _params(n), _limits(n, max_rear=[0.0, 0.1, 0.1]), np.array([1, 2]),
                                np.array([0.0, 0.3, 0.1]), np.zeros(n), None)
    assert rear[0] == 0.0 and steer[0] == 0.2  # not given: untouched
    # stopping (no time ahead): the body holds its own angle
    want_f, want_r = C.rear_axle_steer(np.full(2, 0.2), obs.yaw[1:], obs.speed[1:], obs.yaw[1:], np.zeros(2),
                                       np.full(2, 2.7), np.full(2, 3.6), np.radians(np.full(2, 35.0)), np.full(2, 0.1),
                                       a_lat=np.full(2, 8.0))
    assert rear[1:] == pytest.approx(want_r) and steer[1:] == pytest.approx(want_f)
