"""Carried bodies' poses (``physics_side.policies.carry_pose``): the rate and curvature a
kinematic body turns at, its chord, and a carry's glide onto SUMO's pose; on small arrays,
then driven through a fleet."""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from physics_side.policies.carry_pose import (
    KIN_BLEND_S, KIN_GLIDE_MAX_M, KIN_MIN_SPEED, chord, glide, short_step_curvature, start_glide, turn_rate,
)
from physics_side.reference import Reference, ReferencePoint
from protocol.messages import AgentMode
from synthetic.traffic import circle_traffic
from tests.test_physics_fleet import arcs_step, arcs_xy, line_step, make_fleet, run_step, with_cols


def _points(n: int, **cols) -> ReferencePoint:
    z = np.zeros(n)
    base = dict(x=z, y=z, yaw=z, speed=z, accel=z, curvature=z, s=z, tangent=z)
    base.update({k: np.asarray(v, float) for k, v in cols.items()})
    return ReferencePoint(**base)


def test_the_turn_rate_between_samples_is_the_slower_of_two_that_agree():
    before = np.array([0.2, 0.2, -0.2, 0.0])
    now = np.array([0.1, 0.3, 0.3, 0.3])
    assert list(turn_rate(before, now)) == [0.1, 0.2, 0.0, 0.0]


def test_short_step_curvature_follows_sumos_turn_within_the_grip():
    kappa = np.array([0.1, 0.1, -0.1, 0.1, 0.5])  # the path's, around the bumper [1/m]
    rate = np.array([0.5, 0.5, 0.5, 0.5, 0.0])  # SUMO's turn of the body [rad/s] at 10 m/s: 0.05 /m
    speed = np.full(5, 10.0)
    ped = np.array([False, False, False, True, False])
    carried = np.array([True, False, True, True, True])
    a_lat = np.array([8.0, 8.0, 8.0, 8.0, 2.0])
    k = short_step_curvature(kappa, rate, speed, ped, carried, a_lat)
    # carried: the slower of both; by preset: SUMO's; against: SUMO's; pedestrian: the path's;
    # at most the grip's a_lat / v^2 (0.02 /m)
    assert k == pytest.approx([0.05, 0.05, 0.05, 0.1, 0.0])
    k = short_step_curvature(np.array([0.5]), np.array([0.0]), np.array([0.0]), np.zeros(1, bool), np.zeros(1, bool),
                             np.array([2.0]))
    assert k[0] == 0.0  # standing, SUMO not turning it: none (rates taken at KIN_MIN_SPEED)
    assert KIN_MIN_SPEED > 0


def test_a_chord_on_a_straight_path_is_its_heading_and_does_not_turn():
    pts = np.array([[0.0, 0.0], [100.0, 100.0]])
    ref = Reference(0.0, [0.0], [0.0], [45.0], [10.0], [0.0], [5.0], [5.0], np.array([0, 2]), pts)
    at = ref.at(0.0)
    ahead = replace(at, s=np.array([20.0]), x=np.array([20 / math.sqrt(2)]), y=np.array([20 / math.sqrt(2)]))
    yaw, kappa = chord(ref, ahead, 0.0, np.array([5.0]))
    assert yaw[0] == pytest.approx(math.pi / 4) and kappa[0] == pytest.approx(0.0, abs=1e-9)
    # the back behind the path's start: straight back along SUMO's angle
    yaw, _ = chord(ref, at, 0.0, np.array([5.0]))
    assert yaw[0] == pytest.approx(math.pi / 4)


def test_a_carry_glides_from_its_driven_pose_unless_it_starts_far_off_or_new():
    """Agent 0 began 1 m off, 1 began 5 m off, 2 is new, 3 carried since the last step (row 0)."""
    prev = np.array([1, 2, -1, 0])
    was = np.array([False, False, False, True])
    began = np.array([True, True, True, False])
    obs = SimpleNamespace(fx=np.array([1.0, 5.0, 1.0, 0.0]), fy=np.zeros(4), yaw=np.array([0.1, 0.0, 0.0, 0.0]))
    held = _points(4)
    old_off, old_age = np.array([[0.5, 0.0, 0.0], [0.0] * 3, [0.0] * 3]), np.array([0.2, np.inf, np.inf])
    off, age = start_glide(prev, was, began, obs, held, np.zeros(4), old_off, old_age)
    assert np.allclose(off, [[1.0, 0.0, 0.1], [0.0] * 3, [0.0] * 3, [0.5, 0.0, 0.0]]) and 5.0 > KIN_GLIDE_MAX_M
    assert age.tolist() == [0.0, 0.0, 0.0, 0.2]
    at, yaw = glide(_points(4), np.zeros(4), off, np.array([0.0, 0.0, np.inf, KIN_BLEND_S]))
    assert at.x == pytest.approx([1.0, 0.0, 0.0, 0.5 / math.e]) and yaw == pytest.approx([0.1, 0.0, 0.0, 0.0])


def test_a_kinematic_body_does_not_carry_a_one_step_jump_of_sumos_angle_on():
    """SUMO's angle jumps 3.4 deg in one 0.05 s step (a sublane move's start) and then holds:
    a kinematic body turns onto the new angle, not 3.4 deg further over the next step (a
    carried 16.5 m trailer's rear swung 0.7 m sideways into a bicycle); a steady turn is
    still carried on between samples."""
    from protocol.frames import sumo_angle_to_yaw

    f = make_fleet(presets={"passenger": "kinematic"})
    dt, v = 0.05, 1.3
    angles = [90.0] * 10 + [86.6] * 6
    for k, ang in enumerate(angles):
        m = line_step(k, [10.0 + v * dt * k], [v], step_s=dt)
        run_step(f, with_cols(m, angle=np.array([ang], np.float32)))
        if k >= 10:
            yaw = float(f.world.observe(f.slots).yaw[0])
            assert abs(math.degrees(yaw - sumo_angle_to_yaw(ang))) < 0.5, (k, math.degrees(yaw))
    g = make_fleet(presets={"passenger": "kinematic"})
    for k in range(12):  # a steady 20 deg/s turn: the body keeps turning between samples
        ang = 90.0 - 20.0 * dt * k
        run_step(g, with_cols(line_step(k, [10.0 + v * dt * k], [v], step_s=dt), angle=np.array([ang], np.float32)))
    yaw = math.degrees(float(g.world.observe(g.slots).yaw[0]))
    assert abs(yaw - math.degrees(sumo_angle_to_yaw(90.0 - 20.0 * dt * 12))) < 0.3, yaw


def test_a_carried_long_body_never_turns_against_sumos_turn_of_it():
    """A 16.5 m trailer carried through an S (right round 12 m, then left) at 7 m/s in 0.05 s
    steps: where its bumper's path already turns left while its chord still turns right, the
    body turns with its chord (placed turning at its bumper's 0.3 rad/s against its chord, a
    trailer was handed back spinning and placed for divergence)."""
    f = make_fleet()
    m0 = circle_traffic(1, 0)
    arcs, size, v, s, dt = [(12.0, -25.0), (12.0, 45.0)], (16.5, 2.55), 7.0, -8.0, 0.05
    against, turning = [], 0
    for k in range(120):
        run_step(f, arcs_step(m0, k, s, v, 0.0, arcs, size, "trailer"))
        chord = [np.arctan2(*(arcs_xy(q, arcs)[0] - arcs_xy(q - size[0], arcs)[0])[::-1]) for q in (s, s + v * dt)]
        rate = (chord[1] - chord[0]) / dt
        if f.mode[0] == AgentMode.KINEMATIC and abs(rate) > 0.05:
            turning += 1
            against.append(-float(f.world.observe(f.slots).yaw_rate[0]) * np.sign(rate))
        s += v * dt
    assert f.counters["carries_infeasible"] > 0 and turning > 10
    assert max(against) < 0.02, max(against)  # [rad/s] against the chord's turn
    assert f.counters["placements_divergence"] == 0
