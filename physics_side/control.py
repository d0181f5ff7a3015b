"""Controllers as pure functions over arrays: every function takes all agents at once.

Building blocks (unit-tested on their own):

- ``lad``: the paper's adaptive look-ahead distance.
- ``pursuit_alpha`` / ``pure_pursuit_delta``: pure-pursuit geometry (Coulter 1992).
- ``paper_steer``: P_steer = delta_ref[deg] * k_steer, clipped to +-100 % of max steer.
- ``paper_pedal``: u_in = (K1 * e_pos + K2 * e_v) / 2, clipped to [-1, 1].
- ``stanley_bumper``: Stanley's law with the guide point at the front bumper.
- ``accel_command``: damped along-path position loop with feed-forward and integral.
- ``accel_to_torques`` / ``pedal_to_torques``: wheel torques and brakes.
- ``roll_stabiliser`` / ``steered_roll_stabiliser``: bicycle roll PD towards the steady-turn lean.
- ``planar_force`` / ``pedestrian_force``: pedestrian force with a bounded norm, heading servo.

Vehicle limits every preset gets after its controller (tyres and drivetrain, not tuning):

- ``friction_steer_limit``: no steering beyond what the tyres carry at the current speed.
- ``traction_limit``: no drive torque beyond the driven wheels' grip the turn leaves.
- ``curve_speed_cut``: no drive while faster than the bend ahead allows (default preset).

``control_paper`` / ``control_default`` compose them for one preset. Integrator state
lives in ``ControlState`` (arrays aligned with the agents), nothing else is kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from physics_side.config import DefaultControl, PaperControl
from physics_side.reference import Reference, ReferencePoint, tracking_error
from protocol.frames import wrap_pi
from protocol.messages import AgentMode
from runtime.native import numpy_math_is_libm, optional_extension

G = 9.81  # [m/s^2]
P_PAPER, P_DEFAULT, P_KINEMATIC = 0, 1, 2  # controller presets: the paper's, ours, placed at SUMO's pose
PRESET_CODE = {"paper": P_PAPER, "default": P_DEFAULT, "kinematic": P_KINEMATIC}
A_LAT_SHARE = 0.92  # [1] share of the tyres' grip (mu g) the steering limit allows in lateral acceleration
GRIP_LATERAL = 1.0  # [1] weight of the turn's lateral acceleration in the drive's friction circle
CURVE_PREVIEW_S = np.array([0.0, 0.5, 1.0])  # [s] path curvature taken this far ahead at the current speed
DRIVE_GRIP_USE = 0.9  # [1] share of the driven wheels' grip the drive may use (traction control)
CREEP_ACCEL = 1.5  # [m/s^2] acceleration bound of a roll back to a standing reference
CREEP_FROM_REST = 0.05  # [m/s] a roll back starts below this forward speed
CREEP_DONE_M = 0.03  # [m] a roll back ends this close to the standing reference
MAX_LEAD_STEP_S = 0.2  # [s] longest step taken for the mean-speed lead (a late or coalesced step is no step length)
PED_YAW_KP = 60.0  # [N*m/rad] pedestrian heading servo
PED_YAW_KD = 15.0  # [N*m*s/rad]
PED_YAW_MAX = 150.0  # [N*m] pedestrian heading servo torque limit
REAR_STEER_K_YAW = 0.3  # [1/s] rear-axle steering: body angle error -> yaw rate
REAR_STEER_LAG = math.radians(3.0)  # [rad] a body this far behind SUMO's angle is lagging (``rear_axle_steer``)
REAR_STEER_V_MIN = 1.0  # [m/s] below this the rear-axle law acts as at this speed
STEER_SAT_SHARE = 0.97  # [1] steering at this share of its limit counts as saturated
STEER_SAT_DECEL = 2.0  # [m/s^2] braking per m/s over the reference while saturated (at most this)
GRIP_SAT_LAT_M = 0.3  # [m] sideways off the path beyond which a vehicle at its tyres' limit gets no drive to catch up
MAX_GRIP_USE = 0.95  # [1] largest share of the tyres' grip a turn or a lean is taken to use (friction circles)
# [1] tan of the steepest lean the bicycles' stabiliser leans for (31 deg): leaning up to their
# 35 deg limit flipped a bicycle in the 1 s-step tram scenario
MAX_LEAN_TAN = 0.6
BIKE_MAX_LEAN_DEG = 35.0  # [deg] bicycles (a rider's lean)
MOTORCYCLE_MAX_LEAN_DEG = 42.0  # [deg] motorcycles and mopeds: at their tyres' ~48 deg a lean transient reached 60
MOTORCYCLE_MASS_KG = 150.0  # [kg] single-track models at least this heavy are motorcycles
PURSUIT_MIN_DIST_M = 1e-3  # [m] floor of the pursuit distance where it divides
STANLEY_BETA_MAX = 1.2  # [rad] largest bumper direction off the body Stanley's law asks for
FORCE_FLOOR_N = 1e-9  # [N] floor of a force norm where it divides
CURVATURE_FLOOR = 1e-6  # [1/m] (or tan sum [1]) floor where a curvature divides
STEER_LIMIT_V_MIN = 0.1  # [m/s] the friction circle's steering limit is taken at least at this speed
A_LAT_FLOOR = 1e-6  # [m/s^2] floor of a lateral acceleration limit where it divides
SPEED2_FLOOR = 0.01  # [m^2/s^2] floor of a squared speed where it divides
TAU_EPS_S = 1e-9  # [s] reference ages closer than this are the same
GAIN_FLOOR = 1e-9  # [1] floor of an integral gain where it divides
STOP_DECEL = 3.0  # [m/s^2] default braking to rest when SUMO is gone
HOLD_ACCEL_MAX = 0.5  # [m/s^2] a standing reference holds the brakes unless more than this is asked
ROLLING_BACK_SPEED = 0.01  # [m/s] rolling backwards faster than this continues a roll back
CREEP_GAIN = 2.0  # [1/s] roll back: speed error -> acceleration
REAR_STEERED_DEMAND_MAX = 1.5  # [rad] steering demand kept whole for vehicles that steer their rear axle


def _arctan_is_libm() -> bool:
    """Does numpy's float64 arctan give libm's bits (the control kernel's atan)? (Not checked
    by ``numpy_math_is_libm``; numpy builds with their own SIMD arctan would differ.)"""
    x = np.concatenate([np.linspace(-50.0, 50.0, 2001), np.random.default_rng(0).uniform(-1e4, 1e4, 500)])
    return bool(np.array_equal(np.arctan(x), [math.atan(v) for v in x.tolist()]))


# The C path of ``control_default``'s per-agent arithmetic (bit-identical; no compiler,
# ``SUMOCO_PURE_PHYSICS=1`` or numpy math that is not libm's: the numpy body). Its tanh stays
# numpy's (numpy's own SIMD tanh is not libm's). ``FAST_CONTROL`` says which runs.
_kernel = optional_extension("physics_side._controlkernel", "SUMOCO_PURE_PHYSICS")
if _kernel is not None and not (numpy_math_is_libm() and _arctan_is_libm()):  # (its libm calls)
    _kernel = None
FAST_CONTROL: bool = _kernel is not None


def _clip(x, lo, hi):
    """``np.clip`` (same values) without its dispatch layer, which costs a few
    microseconds per call on arrays of a few hundred agents (several calls per tick)."""
    return np.minimum(np.maximum(x, lo), hi)


# --------------------------------------------------------------------------- building blocks


def lad(v_ref: np.ndarray, lad_min: float, lad_max: float, k_lad: float) -> np.ndarray:
    """Paper eq. for the look-ahead distance [m] from the reference speed [m/s].

    LAD = LAD_min if v_ref < LAD_min else min(v_ref * k_LAD, LAD_max). (The paper compares
    a speed with a distance; with k_LAD = 1 s the two branches meet at v = LAD_min.)
    """
    v = np.asarray(v_ref, np.float64)
    return np.where(v < lad_min, lad_min, np.minimum(v * k_lad, lad_max))


def pursuit_alpha(bx, by, yaw, tx, ty) -> np.ndarray:
    """Angle [rad, + left] between the heading and the line from base (bx, by) to target (tx, ty)."""
    return wrap_pi(np.arctan2(np.asarray(ty) - by, np.asarray(tx) - bx) - yaw)


def pure_pursuit_delta(alpha: np.ndarray, dist: np.ndarray, wheelbase: np.ndarray) -> np.ndarray:
    """Classic pure pursuit: road-wheel angle [rad] of the arc from the rear axle through the target."""
    return np.arctan2(2.0 * wheelbase * np.sin(alpha), np.maximum(dist, PURSUIT_MIN_DIST_M))


def paper_steer(alpha: np.ndarray, k_steer: float, max_steer: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Paper eq. (1): P_steer = delta_ref[deg] * k_steer in [-1, 1]; angle = P_steer * max_steer.

    ``alpha`` is delta_ref, the pure-pursuit angle [rad]; returns (P_steer [1], angle [rad]).
    """
    pct = _clip(np.rad2deg(alpha) * k_steer, -1.0, 1.0)
    return pct, pct * max_steer


def paper_pedal(e_pos: np.ndarray, e_v: np.ndarray, k1: float, k2: float) -> tuple[np.ndarray, np.ndarray]:
    """u1 = K1 * e_pos, u2 = K2 * e_v, u_in = (u1 + u2) / 2; returns (u_in, u_in clipped to [-1, 1])."""
    u = 0.5 * (k1 * np.asarray(e_pos) + k2 * np.asarray(e_v))
    return u, _clip(u, -1.0, 1.0)


def pedal_to_torques(u: np.ndarray, max_drive: np.ndarray, max_brake: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pedal in [-1, 1] -> (drive torque, brake torque) [N*m]: + throttle, - brake."""
    return np.maximum(u, 0.0) * max_drive, np.maximum(-u, 0.0) * max_brake


def stanley_bumper(
    heading_err: np.ndarray, e_lat: np.ndarray, v: np.ndarray, k: float, v_soft: float,
    d_bumper: np.ndarray, wheelbase: np.ndarray, max_correction: float | None = None,
) -> np.ndarray:
    """Stanley's law for a guide point ``d_bumper`` ahead of the rear axle (the front bumper).

    The guide point's velocity direction relative to the body is
    beta = atan(d * tan(delta) / L). Stanley asks for beta = -heading_err - atan(k e / v),
    with heading_err = vehicle yaw - path heading and e the lateral offset (+ left); so
    tan(delta) = L * tan(beta) / d. With d = L it is the classic front-axle Stanley.
    ``max_correction`` [rad] saturates the cross-track term smoothly (tanh): a large
    offset (SUMO's instantaneous lane change, a standing start beside the path) is
    closed at a bounded angle to the path instead of at full lock.
    Returns the road-wheel angle [rad] (unclipped).
    """
    corr = np.arctan2(k * e_lat, np.abs(v) + v_soft)
    if max_correction:
        corr = max_correction * np.tanh(corr / max_correction)
    beta = -heading_err - corr
    beta = _clip(beta, -STANLEY_BETA_MAX, STANLEY_BETA_MAX)
    return np.arctan(wheelbase * np.tan(beta) / d_bumper)


def accel_command(
    e_s: np.ndarray, e_v: np.ndarray, a_ref: np.ndarray, integ: np.ndarray, omega: float, zeta: float,
    k_int: float,
) -> np.ndarray:
    """Damped position loop with feed-forward: a = a_ref + w^2 e_s + 2 zeta w e_v + k_i * integral [m/s^2]."""
    return a_ref + omega * omega * e_s + 2.0 * zeta * omega * e_v + k_int * integ


def accel_to_torques(
    a_cmd: np.ndarray, m_eff: np.ndarray, r_wheel: np.ndarray, max_drive: np.ndarray, max_brake: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Wheel torque for an acceleration: + on the drive motor, - as brake torque [N*m]."""
    t = a_cmd * m_eff * r_wheel
    return _clip(t, 0.0, max_drive), _clip(-t, 0.0, max_brake)


def roll_stabiliser(
    roll: np.ndarray, roll_rate: np.ndarray, speed: np.ndarray, yaw_rate: np.ndarray, kp, kd,
    limit: np.ndarray, max_lean_tan=MAX_LEAN_TAN,
) -> np.ndarray:
    """Bicycle stabiliser torque about the frame's forward axis [N*m].

    Target lean: the steady-turn equilibrium tan(phi) = v * r / g, into the turn (a left
    turn, r > 0, needs the left side down, i.e. negative roll about +x), up to
    ``max_lean_tan`` [1]. ``kp`` [N*m/rad], ``kd`` [N*m*s/rad] and ``max_lean_tan`` may be
    per agent.
    """
    target = -np.arctan(_clip(speed * yaw_rate / G, -max_lean_tan, max_lean_tan))
    return _clip(-kp * (roll - target) - kd * roll_rate, -limit, limit)


def steered_roll_stabiliser(
    roll: np.ndarray, roll_rate: np.ndarray, speed: np.ndarray, steer: np.ndarray, wheelbase: np.ndarray,
    kp, kd, limit: np.ndarray, max_lean_tan=MAX_LEAN_TAN,
) -> np.ndarray:
    """``roll_stabiliser`` [N*m] leaning for the turn the steering asks for: yaw rate
    r = v tan(delta) / L of a kinematic bicycle (speed [m/s], steer [rad], wheelbase [m]),
    not the measured one, which feeds lean transients back into the target."""
    r_cmd = speed * np.tan(steer) / wheelbase
    return roll_stabiliser(roll, roll_rate, speed, r_cmd, kp, kd, limit, max_lean_tan)


def planar_force(
    ex: np.ndarray, ey: np.ndarray, evx: np.ndarray, evy: np.ndarray, ax: np.ndarray, ay: np.ndarray,
    mass: np.ndarray, omega: float, zeta: float, fmax: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Pedestrian PD + feed-forward force (x, y) [N], its norm clipped to ``fmax``."""
    fx, fy, _, scale = _bounded_force(ex, ey, evx, evy, ax, ay, mass, omega, zeta, fmax)
    return fx * scale, fy * scale


def _bounded_force(ex, ey, evx, evy, ax, ay, mass, omega, zeta, fmax):
    """``planar_force`` before scaling: (fx, fy, norm [N], scale [1] that bounds it to ``fmax``)."""
    k, c = omega * omega, 2.0 * zeta * omega
    fx = mass * (ax + k * ex + c * evx)
    fy = mass * (ay + k * ey + c * evy)
    norm = np.hypot(fx, fy)
    scale = np.where(norm > fmax, fmax / np.maximum(norm, FORCE_FLOOR_N), 1.0)
    return fx, fy, norm, scale


def pedestrian_force(
    px: np.ndarray, py: np.ndarray, vx: np.ndarray, vy: np.ndarray, yaw: np.ndarray, yaw_rate: np.ndarray,
    tx: np.ndarray, ty: np.ndarray, theading: np.ndarray, v: np.ndarray, accel: np.ndarray, curvature: np.ndarray,
    mass: np.ndarray, omega: np.ndarray, zeta: np.ndarray, fmax: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Planar force control of pedestrians towards a moving target.

    Position (``px``, ``py``) [m], velocity (``vx``, ``vy``) [m/s], ``yaw`` [rad] and
    ``yaw_rate`` [rad/s] of each pedestrian; target (``tx``, ``ty``) [m] moving along
    ``theading`` [rad] at ``v`` [m/s] with along-path ``accel`` [m/s^2] on a path of
    ``curvature`` [1/m] (feed-forward: along-path plus centripetal v^2 * kappa); loop
    ``omega`` [rad/s] and ``zeta`` [1] per pedestrian, ``mass`` [kg], force norm bounded
    by ``fmax`` [N]. Returns (force x [N], force y [N], yaw torque [N*m] of a heading
    servo towards ``theading``, force norm [N]).
    """
    c, s = np.cos(theading), np.sin(theading)
    cen = v * v * curvature
    ax = accel * c - cen * s
    ay = accel * s + cen * c
    fx, fy, norm, scale = _bounded_force(tx - px, ty - py, v * c - vx, v * s - vy, ax, ay, mass, omega, zeta, fmax)
    tz = np.clip(PED_YAW_KP * wrap_pi(theading - yaw) - PED_YAW_KD * yaw_rate, -PED_YAW_MAX, PED_YAW_MAX)
    return fx * scale, fy * scale, tz, norm * scale


# --------------------------------------------------------------------------- vehicle limits


def lateral_accel_limit(tyre_mu: np.ndarray) -> np.ndarray:
    """Lateral acceleration [m/s^2] the steering limit allows on tyres of friction ``tyre_mu`` [1]."""
    return A_LAT_SHARE * G * tyre_mu


def drive_grip_torque(drive_grip: np.ndarray, r_wheel: np.ndarray) -> np.ndarray:
    """Drive torque [N*m] the driven wheels may use: ``DRIVE_GRIP_USE`` of the force they
    carry (``drive_grip`` [N], inf where unlimited) at wheel radius ``r_wheel`` [m]."""
    finite = np.isfinite(drive_grip)
    return np.where(finite, DRIVE_GRIP_USE * np.where(finite, drive_grip, 0.0) * r_wheel, np.inf)


def bumper_curvature_limit(
    wheelbase: np.ndarray, d_bumper: np.ndarray, max_steer: np.ndarray, max_rear: np.ndarray | None,
) -> np.ndarray:
    """Largest curvature [1/m] of the path a vehicle's front bumper can follow (at walking
    pace, full lock): the turning centre lies wheelbase / (tan f + tan r) to the side, at
    wheelbase tan r / (tan f + tan r) ahead of the rear axle (r: a steered rear axle's
    limit, else 0); the bumper, ``d_bumper`` ahead of the rear axle, circles it."""
    tf = np.tan(max_steer)
    tr = np.zeros_like(tf) if max_rear is None else np.tan(np.maximum(max_rear, 0.0))
    k = np.maximum(tf + tr, CURVATURE_FLOOR)
    return 1.0 / np.hypot(wheelbase / k, d_bumper - wheelbase * tr / k)


def steer_limit(speed: np.ndarray, wheelbase: np.ndarray, a_lat: np.ndarray, max_steer: np.ndarray) -> np.ndarray:
    """Largest steering angle [rad] at ``speed`` [m/s]: the friction circle's atan(L * a_lat / v^2)
    (v at least 0.1 m/s) or ``max_steer`` [rad], whichever is smaller (``friction_steer_limit``)."""
    return np.minimum(max_steer, np.arctan(wheelbase * a_lat / np.maximum(speed, STEER_LIMIT_V_MIN) ** 2))


def friction_steer_limit(
    steer: np.ndarray, speed: np.ndarray, wheelbase: np.ndarray, a_lat: np.ndarray, max_steer: np.ndarray,
) -> np.ndarray:
    """Steering angle [rad] clipped to the friction circle at the current ``speed`` [m/s]:
    |delta| <= atan(L * a_lat / v^2) (wheelbase L [m], lateral acceleration ``a_lat``
    [m/s^2]; v at least 0.1 m/s), and to ``max_steer`` [rad] (like the Unity car
    controller's speed-dependent steering limit)."""
    lim = steer_limit(speed, wheelbase, a_lat, max_steer)
    return np.minimum(np.maximum(steer, -lim), lim)


def traction_limit(drive: np.ndarray, speed: np.ndarray, yaw_rate: np.ndarray, grip_torque: np.ndarray) -> np.ndarray:
    """Drive torque [N*m] bounded by the driven wheels' grip ``grip_torque`` [N*m] less what
    the turn uses (friction circle with the lateral acceleration v * r, speed [m/s], yaw
    rate [rad/s], at most MAX_GRIP_USE g): a spinning rear axle carries no side force, and a
    rear-driven car pulling away in a bend spun round."""
    use = np.minimum(np.abs(speed * yaw_rate) / G, MAX_GRIP_USE) * GRIP_LATERAL
    return np.minimum(drive, grip_torque * np.sqrt(1.0 - use * use))


def lean_traction_limit(torque: np.ndarray, roll: np.ndarray, a_lat: np.ndarray, max_torque: np.ndarray) -> np.ndarray:
    """Drive or brake ``torque`` [N*m] of a two-wheeler leaning at ``roll`` [rad]: its tyres
    carry the lean's lateral acceleration g tan(roll) as a share of what its lean limit allows
    (``a_lat`` [m/s^2], at most MAX_GRIP_USE), and of ``max_torque`` [N*m] only the rest of the friction
    circle: at full throttle out of a turn a motorcycle's roll swung +-35 deg and past 50; braked
    at SUMO's 10 m/s^2 while leaning 40 deg, one fell."""
    use = np.minimum(np.abs(np.tan(roll)) * G / np.maximum(a_lat, A_LAT_FLOOR), MAX_GRIP_USE)
    return np.minimum(torque, max_torque * np.sqrt(1.0 - use * use))


def curve_speed_cut(
    drive: np.ndarray, speed: np.ndarray, curvature_ahead: np.ndarray, v_ref: np.ndarray, a_lat: np.ndarray,
    mask: np.ndarray,
) -> np.ndarray:
    """Drive torque [N*m], zero for agents of ``mask`` faster (``speed`` [m/s]) than both
    their reference speed ``v_ref`` [m/s] and the speed sqrt(a_lat / kappa) that the
    largest ``curvature_ahead`` |kappa| [1/m] allows at lateral acceleration ``a_lat``
    [m/s^2]: catching up into a tight turn ran cars metres wide."""
    v_curve = np.sqrt(a_lat / np.maximum(curvature_ahead, CURVATURE_FLOOR))
    over = mask & (speed > np.maximum(v_curve, v_ref))
    return np.where(over, 0.0, drive)


def rear_axle_steer(
    steer: np.ndarray, yaw: np.ndarray, speed: np.ndarray, yaw_ref: np.ndarray, yaw_rate_ref: np.ndarray,
    wheelbase: np.ndarray, d_bumper: np.ndarray, max_front: np.ndarray, max_rear: np.ndarray,
    k_yaw: float = REAR_STEER_K_YAW, v_min: float = REAR_STEER_V_MIN, a_lat: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(front, rear) bicycle-model angles [rad] of an all-wheel-steered vehicle from the front
    angle ``steer`` a law asked for a fixed rear axle.

    The law's angle fixes the bumper's direction relative to the body (``stanley_bumper``):
    tan(beta) = d tan(delta) / L. The rear axle then turns the body towards SUMO's body angle
    ``yaw_ref`` (the chord from its back to its front on the lane) at the yaw rate
    r = ``yaw_rate_ref`` + k_yaw * (yaw_ref - yaw); with both axles steered (kinematic
    bicycle, bumper ``d_bumper`` ahead of the rear axle) tan(beta) = tan(rear) + d r / v and
    r = v (tan(front) - tan(rear)) / L, so tan(rear) = tan(beta) - d r / v and
    tan(front) = tan(beta) + (L - d) r / v. A saturated rear axle leaves the bumper's direction
    to the front one. ``v_min`` [m/s] bounds the angles when standing; ``a_lat`` [m/s^2]: the
    rear axle never turns the vehicle tighter than its tyres carry at this speed."""
    b = d_bumper / wheelbase
    tb = b * np.tan(steer)
    r = yaw_rate_ref + k_yaw * wrap_pi(yaw_ref - yaw)
    v = np.where(speed < 0, np.minimum(speed, -v_min), np.maximum(speed, v_min))
    t_r, t_f = np.tan(max_rear), np.tan(max_front)
    tr = _clip(tb - d_bumper * r / v, -t_r, t_r)
    tf = (tb - (1.0 - b) * tr) / b  # a saturated rear axle: the bumper's direction first
    # a saturated front axle: the rear one turns against it for the bumper's direction (the
    # tightest turn a long vehicle has), the body angle goes second
    # ... unless the body has already turned further than SUMO's (it would spin about its middle)
    ahead = wrap_pi(yaw - yaw_ref) * np.sign(tb) > 0.0
    sat = (np.abs(tf) > t_f) & ~ahead
    tf = _clip(tf, -t_f, t_f)
    tr_b = _clip((tb - b * tf) / (1.0 - b), -t_r, t_r)
    # ... but never in phase with the front while the body lags SUMO's angle: crabbing the
    # bumper sideways, a truck's body fell 23 deg behind in a junction turn and ran 1.7 m wide
    lag = wrap_pi(yaw_ref - yaw) * np.sign(tf) > REAR_STEER_LAG
    tr_b = np.where(lag & (tr_b * tf > 0.0), np.where(tr * tf < 0.0, tr, 0.0), tr_b)
    tr = np.where(sat, tr_b, tr)
    if a_lat is not None:  # the turn's curvature (tan f - tan r) / L within the tyres' grip at this speed
        q_max = wheelbase * a_lat / np.maximum(speed * speed, SPEED2_FLOOR)
        tr = _clip(tr, tf - q_max, tf + q_max)
    return np.arctan(tf), np.arctan(tr)


def saturation_speed_cut(
    drive: np.ndarray, brake: np.ndarray, steer: np.ndarray, max_steer: np.ndarray, speed: np.ndarray,
    v_ref: np.ndarray, m_eff: np.ndarray, r_wheel: np.ndarray, share: float = STEER_SAT_SHARE,
    decel: float = STEER_SAT_DECEL,
) -> tuple[np.ndarray, np.ndarray]:
    """(drive, brake) [N*m]: a vehicle steering at its limit (``share`` of ``max_steer``) and
    faster than its reference (``v_ref`` [m/s]) does not drive and brakes at ``decel``
    [m/s^2] per m/s over: a catch-up in a turn it cannot make ran trucks, buses and cars
    metres wide of SUMO's junction lanes (and into the neighbours); the lag is made up on
    the straight after."""
    over = (np.abs(steer) >= share * max_steer) & (speed > v_ref)
    want = np.minimum((speed - v_ref) * decel, decel) * m_eff * r_wheel
    return np.where(over, 0.0, drive), np.where(over, np.maximum(brake, want), brake)


# --------------------------------------------------------------------------- composed laws


@dataclass
class ControlState:
    """Per-agent controller memory (arrays aligned with the agents of the current step)."""

    integ: np.ndarray
    """Integral of the along-path position error [m*s]."""
    tau_last: float = -1.0
    """``tau`` of the previous tick [s] (it drops when a new SUMO sample arrives)."""
    step_s: float = 0.0
    """SUMO step length [s] seen by the controller: time between two samples (0 = unknown)."""

    @classmethod
    def zeros(cls, n: int) -> "ControlState":
        return cls(integ=np.zeros(n))

    def take(self, index: np.ndarray) -> "ControlState":
        """State re-aligned to a new agent order; index -1 = new agent (zeros)."""
        index = np.asarray(index, np.int64)
        integ = np.where(index >= 0, self.integ[np.maximum(index, 0)] if len(self.integ) else 0.0, 0.0)
        return ControlState(integ=np.asarray(integ, np.float64), tau_last=self.tau_last, step_s=self.step_s)

    def observe_tau(self, tau: float, dt: float) -> float:
        """Track the SUMO step length from the reference's age ``tau`` [s] at each tick of
        ``dt`` [s]: when it drops, a sample arrived ``tau_last + dt - tau`` after the previous
        one. Returns the step length [s] (0 until two samples were seen)."""
        if tau + TAU_EPS_S < self.tau_last:
            self.step_s = self.tau_last + dt - tau
        self.tau_last = tau
        return self.step_s


@dataclass(frozen=True)
class VehicleParams:
    """Per-agent model parameters the controllers need (arrays of length n)."""

    wheelbase: np.ndarray
    """[m]."""
    d_bumper: np.ndarray
    """Rear axle -> front bumper [m]."""
    rear_axle: np.ndarray
    """Body origin -> rear axle along the heading [m] (negative)."""
    front_offset: np.ndarray
    """Body origin -> front bumper [m]."""
    m_eff: np.ndarray
    """[kg]."""
    r_wheel: np.ndarray
    """[m]."""
    max_steer: np.ndarray
    """[rad]."""
    max_drive: np.ndarray
    """[N*m]."""
    max_brake: np.ndarray
    """[N*m]."""
    max_rear: np.ndarray | None = None
    """Rear-axle steering limit [rad] (0 or None: a fixed rear axle)."""


@dataclass(frozen=True)
class VehicleObs:
    """Measured vehicle state (arrays of length n)."""

    fx: np.ndarray
    """Front bumper x [m]."""
    fy: np.ndarray
    """Front bumper y [m]."""
    cx: np.ndarray
    """Body origin x [m]."""
    cy: np.ndarray
    """Body origin y [m]."""
    yaw: np.ndarray
    """[rad]."""
    speed: np.ndarray
    """Forward speed [m/s]."""
    yaw_rate: np.ndarray
    """[rad/s]."""
    fvx: np.ndarray
    """Front-bumper velocity x [m/s]."""
    fvy: np.ndarray
    """Front-bumper velocity y [m/s]."""

    def bumper_speed_along(self, heading: np.ndarray) -> np.ndarray:
        """Front-bumper speed along a direction [m/s] (the path's, for the speed error)."""
        return self.fvx * np.cos(heading) + self.fvy * np.sin(heading)


@dataclass(frozen=True)
class VehicleCommand:
    steer: np.ndarray
    """Bicycle-model road-wheel angle [rad, + left]."""
    drive: np.ndarray
    """Total drive torque [N*m]."""
    brake: np.ndarray
    """Total brake torque [N*m]."""
    aux: np.ndarray
    """Diagnostics: u_in (paper) or commanded acceleration [m/s^2] (default)."""


def control_paper(
    obs: VehicleObs, p: VehicleParams, ref: Reference, cfg: PaperControl,
) -> VehicleCommand:
    """The seed's controller: held sample, P+P pedal, pure pursuit on the SUMO look-ahead point."""
    held = ref.held()
    # position error along the path: reference minus actual, on the reference heading
    e_lon, _ = tracking_error(obs.fx, obs.fy, held)
    e_pos = -e_lon
    u_raw, u = paper_pedal(e_pos, held.speed - obs.speed, cfg.k1, cfg.k2)
    drive, brake = pedal_to_torques(u, p.max_drive, p.max_brake)
    if cfg.lookahead == "message":
        tx, ty = ref.la_x, ref.la_y
    else:
        la = ref.point_at(lad(held.speed / cfg.lad_speed_divisor, cfg.lad_min, cfg.lad_max, cfg.k_lad))
        tx, ty = la.x, la.y
    # base of the pursuit: the rear axle of the actual vehicle
    c, s = np.cos(obs.yaw), np.sin(obs.yaw)
    bx, by = obs.cx + p.rear_axle * c, obs.cy + p.rear_axle * s
    alpha = pursuit_alpha(bx, by, obs.yaw, tx, ty)
    _, steer = paper_steer(alpha, cfg.k_steer, p.max_steer)
    return VehicleCommand(steer, drive, brake, u_raw)


def _roll_back(obs: VehicleObs, p: VehicleParams, cfg: DefaultControl, v_ref: np.ndarray, e_s: np.ndarray,
               rolls_back: np.ndarray | None, drive: np.ndarray, brake: np.ndarray) -> tuple:
    """(who rolls back or None, drive, brake [N*m]) of ``control_default``. SUMO's Euler steps
    stop a vehicle within one step from any speed (1 s steps: 3.3 m/s to rest in 0.2 m), which
    no brake can follow: a vehicle that came to rest past its standing reference (``e_s`` [m]
    < 0, ``v_ref`` [m/s] standing) rolls back to it, wheels straight, instead of standing there
    for the whole wait (0.8 m for 20 s behind a bus's stop). Only from rest: a vehicle still
    rolling forwards brakes as usual; one already rolling back goes on until it is within
    CREEP_DONE_M. ``rolls_back``: who may (None: all)."""
    back = ((v_ref <= cfg.hold_speed)
            & (((e_s < -cfg.creep_back_m) & (obs.speed < CREEP_FROM_REST))
               | ((e_s < -CREEP_DONE_M) & (obs.speed < -ROLLING_BACK_SPEED)))
            if cfg.creep_back_m > 0 else None)
    if back is not None and rolls_back is not None:
        back &= rolls_back
    if back is not None and back.any():
        v_back = -np.minimum(cfg.creep_speed, 0.5 * -e_s)
        t_back = _clip(CREEP_GAIN * (v_back - obs.speed), -CREEP_ACCEL, CREEP_ACCEL) * p.m_eff * p.r_wheel
        drive = np.where(back, _clip(t_back, -p.max_drive, p.max_drive), drive)
        brake = np.where(back, 0.0, brake)
    return back, drive, brake


def _default_steer(obs: VehicleObs, p: VehicleParams, ref: Reference, tau: float, cfg: DefaultControl,
                   s_act: np.ndarray, e_lat: np.ndarray, pp) -> np.ndarray:
    """Road-wheel angle [rad] of ``control_default``'s lateral law (Stanley at the front
    bumper, or front-axle pure pursuit) for bumpers at ``s_act`` [m] along their paths,
    ``e_lat`` [m] off them at path point ``pp``; clipped to the steering (vehicles that steer
    their rear axle keep the whole demand: ``rear_axle_steer`` splits it)."""
    if cfg.lateral == "stanley":
        # heading of the path where the bumper will be after the steering lag
        ahead = ref.point_at(s_act + np.maximum(obs.speed, 0.0) * cfg.preview_s, tau) if cfg.preview_s else pp
        # the vehicle yaw that keeps the bumper moving along the path: the bumper velocity
        # leads the body by beta_ss = asin(kappa * d) in a steady turn
        # ... turned by the drift's angle for SUMO's lateral speed at the car's own speed (at
        # SUMO's, a car catching up from a stop mid lane change went 0.15 m further sideways)
        heading_err = wrap_pi(obs.yaw - ahead.heading - ref.drift_angle(tau, np.maximum(obs.speed, 0.0)))
        steer = stanley_bumper(heading_err, e_lat, obs.speed, cfg.k_cross, cfg.v_soft, p.d_bumper, p.wheelbase,
                               math.radians(cfg.max_correction_deg))
        if cfg.k_yaw:
            r_ref = obs.speed * ahead.curvature
            steer = steer - cfg.k_yaw * (obs.yaw_rate - r_ref)
    else:
        # front-axle pure pursuit: target LAD ahead of the bumper's projection on the path
        L = lad(obs.speed, cfg.lad_min, cfg.lad_max, cfg.k_lad)
        tgt = ref.point_at(s_act + L, tau)
        c, s = np.cos(obs.yaw), np.sin(obs.yaw)
        ax_x = obs.cx + (p.rear_axle + p.wheelbase) * c
        ax_y = obs.cy + (p.rear_axle + p.wheelbase) * s
        alpha = pursuit_alpha(ax_x, ax_y, obs.yaw, tgt.x, tgt.y)
        # arc from the front axle: steer the front wheels towards the target point
        steer = alpha
    lim = p.max_steer if p.max_rear is None else np.where(p.max_rear > 0, REAR_STEERED_DEMAND_MAX, p.max_steer)
    steer = _clip(steer, -lim, lim)
    return steer


def control_default(
    obs: VehicleObs, p: VehicleParams, ref: Reference, tau: float, dt: float, cfg: DefaultControl,
    state: ControlState, stopping: np.ndarray | None = None, stop_decel: float = STOP_DECEL,
    stop_speed: np.ndarray | None = None, s_guess: np.ndarray | None = None, proj=None,
    rolls_back: np.ndarray | None = None,
) -> VehicleCommand:
    """Ours: extrapolated reference, front-bumper lateral law, damped longitudinal loop.

    ``stopping`` (bool mask) switches agents to a braking-to-rest speed profile
    (``stop_speed`` [m/s] is their target speed now) while still following the path.
    ``s_guess`` is where the bumper was along the path [m] (for the projection);
    ``proj`` = (s, lateral offset, path point) of the bumper when already known.
    ``rolls_back`` (bool mask, default all): who may roll back to a standing reference it
    came to rest past (not riders: a motorcycle rolled back into the bicycle queued beside
    and behind it under the sublane model).

    The per-agent arithmetic runs in C when it is built (``FAST_CONTROL``), bit-identical to
    ``_control_default_numpy``, which runs otherwise and for inputs the C path does not read.
    """
    if proj is None and s_guess is not None:  # one path evaluation for both
        r, proj = ref.at_and_project(tau, obs.fx, obs.fy, s_guess)
    else:
        r = ref.at(tau)
        if proj is None:
            proj = ref.project(obs.fx, obs.fy, r.s, tau)
    step = state.observe_tau(tau, dt)
    if FAST_CONTROL:
        cmd = _control_default_c(obs, p, ref, tau, dt, cfg, state, r, proj, step, stopping, stop_decel, stop_speed,
                                 rolls_back)
        if cmd is not None:
            return cmd
    return _control_default_numpy(obs, p, ref, tau, dt, cfg, state, r, proj, step, stopping, stop_decel, stop_speed,
                                  rolls_back)


def _control_default_numpy(
    obs: VehicleObs, p: VehicleParams, ref: Reference, tau: float, dt: float, cfg: DefaultControl,
    state: ControlState, r: ReferencePoint, proj: tuple, step: float, stopping: np.ndarray | None,
    stop_decel: float, stop_speed: np.ndarray | None, rolls_back: np.ndarray | None,
) -> VehicleCommand:
    """``control_default`` in numpy once the reference ``r`` at ``tau``, the bumper's projection
    ``proj`` and the SUMO step length ``step`` [s] (``ControlState.observe_tau``) are known
    (the reference for the C path, which computes the same bits)."""
    s_act, e_lat, pp = proj
    e_s = r.s - s_act  # + = behind the reference
    v_ref, a_ref = r.speed, r.accel
    # a standing reference is SUMO's pose itself: the error along SUMO's own heading (the
    # projection on the path fails where an agent stands beside a centre line that turns
    # tighter than its offset: a bicycle waiting 1.3 m beside a junction lane's 0.8 m zigzag
    # was projected behind its reference, drove on to 3 m/s and was placed 6 m ahead)
    still = v_ref <= cfg.hold_speed
    if still.any():
        e_s = np.where(still, (r.x - obs.fx) * np.cos(r.yaw) + (r.y - obs.fy) * np.sin(r.yaw), e_s)
    if cfg.mean_speed_lead and step > 0.0:
        # SUMO's speed is the mean over the step before its sample: follow the smooth motion
        # through its positions, half a step further on in the speed profile (reference.py)
        ds, dv = ref.mean_speed_lead(tau, cfg.mean_speed_lead * min(step, MAX_LEAD_STEP_S))
        e_s = e_s + ds
        v_ref = v_ref + dv
    if stopping is not None and np.any(stopping):
        v_ref = np.where(stopping, stop_speed, v_ref)
        a_ref = np.where(stopping, np.where(stop_speed > 0, -stop_decel, 0.0), a_ref)
        e_s = np.where(stopping, 0.0, e_s)
    # the bumper's speed along the path: in a turn it exceeds the body's forward speed
    e_v = v_ref - obs.bumper_speed_along(pp.heading)
    # integral only while tracking (not while stopping or standing)
    live = (v_ref > cfg.hold_speed) if stopping is None else (v_ref > cfg.hold_speed) & ~stopping
    int_max = cfg.int_limit / max(cfg.k_int, GAIN_FLOOR)
    state.integ = np.where(live, _clip(state.integ + e_s * dt, -int_max, int_max), 0.0)
    a_cmd = accel_command(e_s, e_v, a_ref, state.integ, cfg.pos_omega, cfg.pos_zeta, cfg.k_int)
    if cfg.brake_omega > cfg.pos_omega and ref.interpolated is None:
        # ahead of SUMO or faster, a faster loop brakes: extrapolating, the car learns that
        # SUMO brakes one sample late (0.5 m/s too fast at 0.1 s steps), and ahead is where
        # SUMO's leader or stop line is; catching up keeps the slower loop (an interpolated
        # reference knows the next sample: at 1 s steps the faster loop placed more cars)
        a_cmd = np.minimum(a_cmd, accel_command(e_s, e_v, a_ref, state.integ, cfg.brake_omega, cfg.pos_zeta, cfg.k_int))
    a_cmd = _clip(a_cmd, -cfg.decel_max, cfg.accel_max)
    drive, brake = accel_to_torques(a_cmd, p.m_eff, p.r_wheel, p.max_drive, p.max_brake)
    hold = (v_ref <= cfg.hold_speed) & (a_cmd <= HOLD_ACCEL_MAX)
    brake = np.where(hold, np.maximum(brake, cfg.hold_brake * p.max_brake), brake)
    drive = np.where(hold, 0.0, drive)
    back, drive, brake = _roll_back(obs, p, cfg, v_ref, e_s, rolls_back, drive, brake)
    steer = _default_steer(obs, p, ref, tau, cfg, s_act, e_lat, pp)
    if back is not None and back.any():
        steer = np.where(back, 0.0, steer)
    return VehicleCommand(steer, drive, brake, a_cmd)



def _default_constants(cfg: DefaultControl) -> tuple[tuple, tuple]:
    """The scalars of ``_control_default_numpy`` for the C path, computed as the numpy body
    computes them: (prepare's, control's without the per-call ones); kept per ``cfg``."""
    global _CONSTANTS
    if _CONSTANTS is not None and _CONSTANTS[0] is cfg:
        return _CONSTANTS[1]
    stanley = cfg.lateral == "stanley"
    mc = math.radians(cfg.max_correction_deg)
    omega, zeta, w_b = cfg.pos_omega, cfg.pos_zeta, cfg.brake_omega
    int_max = cfg.int_limit / max(cfg.k_int, GAIN_FLOOR)
    prepare = (float(stanley), cfg.preview_s, cfg.k_cross, cfg.v_soft, float(bool(mc)), mc, cfg.lad_min, cfg.lad_max,
               cfg.k_lad)
    control = (
        float(stanley), cfg.hold_speed, -int_max, int_max, omega * omega, 2.0 * zeta * omega, cfg.k_int,
        w_b * w_b, 2.0 * zeta * w_b, -cfg.decel_max, cfg.accel_max, HOLD_ACCEL_MAX, cfg.hold_brake,
        float(cfg.creep_back_m > 0), -cfg.creep_back_m, CREEP_FROM_REST, -CREEP_DONE_M, -ROLLING_BACK_SPEED,
        cfg.creep_speed, CREEP_GAIN, CREEP_ACCEL, float(bool(mc)), mc, STANLEY_BETA_MAX, float(bool(cfg.k_yaw)),
        cfg.k_yaw, REAR_STEERED_DEMAND_MAX,
    )
    _CONSTANTS = (cfg, (prepare, control))
    return _CONSTANTS[1]


_CONSTANTS: tuple | None = None  # (the DefaultControl, its ``_default_constants``)


def _control_default_c(
    obs: VehicleObs, p: VehicleParams, ref: Reference, tau: float, dt: float, cfg: DefaultControl,
    state: ControlState, r: ReferencePoint, proj: tuple, step: float, stopping: np.ndarray | None,
    stop_decel: float, stop_speed: np.ndarray | None, rolls_back: np.ndarray | None,
) -> VehicleCommand | None:
    """``_control_default_numpy`` in C (physics_side._controlkernel): the reference's own
    methods for the preview point and the drift and numpy's tanh between its two calls; the
    kernel computes ``Reference.mean_speed_lead``'s correction itself (from the sample's
    speed and acceleration). None for inputs it does not read (not float64 (n,)
    C-contiguous, masks not bool, a reference of another type): the numpy body then runs,
    nothing changed."""
    speed = obs.speed
    if type(speed) is not np.ndarray or speed.ndim != 1 or not len(speed) or type(ref) is not Reference:
        return None
    if (stopping is not None and (stop_speed is None or getattr(stopping, "dtype", None) != np.bool_)) or \
            (rolls_back is not None and getattr(rolls_back, "dtype", None) != np.bool_):
        return None
    n = len(speed)
    s_act, e_lat, pp = proj
    c_prep, c_ctl = _default_constants(cfg)
    pre = np.empty((3, n))
    try:
        _kernel.prepare(speed, s_act, e_lat, pre, c_prep)
    except (TypeError, ValueError):
        return None
    v_pos, s_ahead, corr = pre
    drift = None
    if cfg.lateral == "stanley":
        ahead = ref.point_at(s_ahead, tau) if cfg.preview_s else pp
        lat1, lat2 = ahead.heading, ahead.curvature
        d = ref.drift_angle(tau, v_pos)
        drift = d if isinstance(d, np.ndarray) else None  # (0.0: no drift)
        if c_prep[4]:  # max_correction: stanley_bumper's tanh
            corr = np.tanh(corr)
    else:
        tgt = ref.point_at(s_ahead, tau)
        lat1, lat2 = tgt.x, tgt.y
        corr = None
    # Reference.mean_speed_lead's arithmetic in the kernel: none, its zeros, or its profile
    lead_mode, lead = 0.0, 0.0
    if cfg.mean_speed_lead and step > 0.0:
        lead = cfg.mean_speed_lead * min(step, MAX_LEAD_STEP_S)
        lead_mode = 1.0 if lead <= 0.0 or ref.interpolated is not None else 2.0
    brake_on = float(cfg.brake_omega > cfg.pos_omega and ref.interpolated is None)
    consts = (c_ctl[0], c_ctl[1], -stop_decel, dt, *c_ctl[2:7], brake_on, *c_ctl[7:], lead_mode, tau, lead, tau + lead)
    out = np.empty((5, n))
    try:
        _kernel.control(obs.fx, obs.fy, obs.cx, obs.cy, obs.yaw, speed, obs.yaw_rate, obs.fvx, obs.fvy,
                        r.x, r.y, r.yaw, r.s, r.speed, r.accel, s_act, pp.heading, ref.speed, ref.accel,
                        stopping, stop_speed, state.integ, p.wheelbase, p.d_bumper, p.rear_axle, p.m_eff, p.r_wheel,
                        p.max_steer, p.max_drive, p.max_brake, p.max_rear, rolls_back, lat1, lat2, drift, corr, out,
                        consts)
    except (TypeError, ValueError):
        return None
    state.integ = out[4]
    return VehicleCommand(out[0], out[1], out[2], out[3])


# --------------------------------------------------------------------------- vehicle limits, composed


@dataclass(frozen=True)
class VehicleLimits:
    """Per-agent limits of tyres, drivetrain and riders (arrays of length n, ``vehicle_limits``)."""

    a_lat: np.ndarray
    """Lateral acceleration the tyres carry [m/s^2]; two-wheelers: no more than their lean's."""
    grip_torque: np.ndarray
    """Drive torque the driven wheels carry [N*m] (inf: unlimited)."""
    max_rear: np.ndarray
    """Rear-axle steering limit [rad] (0: a fixed rear axle)."""
    stab_gain: np.ndarray
    """[1] scale of the configured (the default bicycle's) stabiliser gains."""
    stab_max: np.ndarray
    """Stabiliser torque limit [N*m]."""
    mass: np.ndarray
    """[kg]."""
    bike: np.ndarray
    """Two-wheelers, bool."""
    any_grip: bool
    """Some agent's drive is grip-limited."""
    any_bike: bool


def vehicle_limits(tyre_mu: np.ndarray, mass: np.ndarray, bike: np.ndarray, drive_grip: np.ndarray,
                   r_wheel: np.ndarray, max_rear: np.ndarray, stab_gain: np.ndarray,
                   stab_max: np.ndarray) -> VehicleLimits:
    """The agents' ``VehicleLimits`` from their models' tyre friction ``tyre_mu`` [1], ``mass``
    [kg], driven wheels' grip ``drive_grip`` [N] at radius ``r_wheel`` [m], rear-axle limit
    ``max_rear`` [rad] and stabiliser (``stab_gain`` [1], ``stab_max`` [N*m]). Two-wheelers
    lean no further than BIKE_MAX_LEAN_DEG / MOTORCYCLE_MAX_LEAN_DEG (SUMO's bicycles take
    junction turns at 5-6 m/s: at the tyres' limit the stabiliser asked for 50-65 deg of lean
    and they fell)."""
    a_lat = lateral_accel_limit(tyre_mu)
    lean = np.radians(np.where(mass < MOTORCYCLE_MASS_KG, BIKE_MAX_LEAN_DEG, MOTORCYCLE_MAX_LEAN_DEG))
    grip = drive_grip_torque(drive_grip, r_wheel)
    return VehicleLimits(
        a_lat=np.where(bike, np.minimum(a_lat, G * np.tan(lean)), a_lat), grip_torque=grip, max_rear=max_rear,
        stab_gain=stab_gain, stab_max=stab_max, mass=mass, bike=bike, any_grip=bool(np.isfinite(grip).any()),
        any_bike=bool(np.any(bike)),
    )


def merge_commands(n: int, cmds: list[tuple[bool, np.ndarray, VehicleCommand]]) -> tuple[np.ndarray, ...]:
    """(steer, drive, brake, aux) of ``n`` agents from the presets' commands ``(all, mask,
    command)``: each command where its mask holds, zeros elsewhere."""
    if len(cmds) == 1 and cmds[0][0]:  # one controller for everybody (the usual case)
        cmd = cmds[0][2]
        return cmd.steer, cmd.drive, cmd.brake, cmd.aux
    steer, drive, brake, aux = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    for _, use, cmd in cmds:
        steer = np.where(use, cmd.steer, steer)
        drive = np.where(use, cmd.drive, drive)
        brake = np.where(use, cmd.brake, brake)
        aux = np.where(use, cmd.aux, aux)
    return steer, drive, brake, aux


@dataclass(frozen=True)
class CatchUp:
    """What the default preset's catch-up limits read (``limit_commands``)."""

    ref: Reference
    s_act: np.ndarray
    """Each bumper's arc length along its path [m]."""
    tau: float
    """[s] past the sample."""
    mask: np.ndarray
    """Agents under the default controller, bool."""
    err_lat: np.ndarray
    """Sideways offset from the path at the last tick [m]."""


@dataclass(frozen=True)
class Groups:
    """Which agents each part of a control tick handles (``groups``); changes only with the
    agent set, the modes or the world's slot numbers, so it is built once per SUMO step."""

    kin_idx: np.ndarray
    """Placed at the reference each tick (kinematic / external)."""
    use_default: np.ndarray
    """Vehicles under the default controller (all of them while stopping), bool."""
    use_paper: np.ndarray
    any_default: bool
    all_default: bool
    any_paper: bool
    all_paper: bool
    veh_idx: np.ndarray
    """Vehicles (commanded through the world's ``command_vehicles``)."""
    veh_slots: np.ndarray
    all_veh: bool
    ped_idx: np.ndarray
    """Pedestrians under force control."""


def groups(ped: np.ndarray, mode: np.ndarray, preset: np.ndarray, stopping: bool, slots: np.ndarray) -> Groups:
    """``Groups`` of agents (pedestrians ``ped``, ``AgentMode`` ``mode``, preset codes
    ``preset``, world ``slots``); ``stopping``: every vehicle brakes along its path with the
    default controller."""
    veh = ~ped
    n = len(ped)
    if stopping:
        kin = np.zeros(n, bool)
        use_default, use_paper = veh.copy(), np.zeros(n, bool)
    else:
        kin = (mode == AgentMode.KINEMATIC) | (mode == AgentMode.EXTERNAL)
        use_default = veh & ~kin & (preset == P_DEFAULT)
        use_paper = veh & ~kin & (preset == P_PAPER)
    veh_idx = np.flatnonzero(veh)
    return Groups(
        kin_idx=np.flatnonzero(kin), use_default=use_default, use_paper=use_paper,
        any_default=bool(use_default.any()), all_default=bool(use_default.all()), any_paper=bool(use_paper.any()),
        all_paper=bool(use_paper.all()), veh_idx=veh_idx, veh_slots=slots[veh_idx], all_veh=len(veh_idx) == n,
        ped_idx=np.flatnonzero(~veh & ~kin),
    )


@dataclass(frozen=True)
class Commands:
    """What one control tick writes into the world (arrays over the agents unless noted)."""

    steer: np.ndarray
    """Bicycle-model road-wheel angle [rad]."""
    drive: np.ndarray
    """Drive torque [N*m] (pedestrians: force norm [N])."""
    brake: np.ndarray
    """Brake torque [N*m]."""
    aux: np.ndarray
    """Controller diagnostics (``VehicleCommand.aux``)."""
    stab: np.ndarray | None
    """Bicycle stabiliser torque [N*m] per vehicle (``Groups.veh_idx``), None without bicycles."""
    ped: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    """Force x, y [N] and yaw torque [N*m] per pedestrian (``Groups.ped_idx``)."""
    at: ReferencePoint | None
    """Reference point where kinematic agents and ``carry`` are placed (``Reference.at``), or None."""
    kin_yaw: np.ndarray | None
    """Body angle [rad] of kinematic agents (``carry_pose.kinematic_pose``), or None."""
    carry: np.ndarray | None
    """Standing agents carried along SUMO's sideways slide (placed), or None."""
    rear: np.ndarray | None
    """Rear-axle angle [rad] per agent (vehicles that steer it), None when nobody does."""
    carry_yaw: np.ndarray | None = None
    """Body yaw [rad] per agent that ``carry`` keeps (its own at the tick's start)."""


def limit_commands(steer: np.ndarray, drive: np.ndarray, brake: np.ndarray, obs, p: VehicleParams,
                   lim: VehicleLimits, rear_steered: bool, catch_up: CatchUp | None) -> tuple[np.ndarray, ...]:
    """(steer [rad], drive, brake [N*m]) within the vehicles' limits, whatever the controller
    asked for: the friction circle's steering (not where both axles steer: MuJoCo's tyres and
    the curve speed cut keep the grip), the driven wheels' grip, and for ``catch_up`` (the
    default preset, not stopping) no drive faster than the bend ahead allows, none with the
    steering saturated while faster than the reference, and none at the tyres' limit (fixed
    rear axle) while faster than the reference and GRIP_SAT_LAT_M off the path: at 1 s steps
    SUMO turns cars through 45-65 deg within a step; running wide, they fell behind and sped up
    to catch up (16.5 m/s behind SUMO's 13.9), which widened the turn until they were placed.
    A leaning two-wheeler's tyres carry less drive and braking. ``obs``: speed [m/s], yaw_rate
    [rad/s], roll [rad] per agent.

    The elementwise arithmetic runs in C when it is built (``FAST_CONTROL``), bit-identical to
    ``_limit_commands_numpy``, which runs otherwise and for inputs the C path does not read;
    the bend ahead's curvature and the reference speed are looked up here for both."""
    kap = v_ref = None
    if catch_up is not None:
        c = catch_up
        v = np.maximum(obs.speed, 0.0)
        kap = np.abs(c.ref.path.at(c.s_act + v * CURVE_PREVIEW_S[:, None]).curvature).max(axis=0)
        v_ref = c.ref.at(c.tau).speed
    if FAST_CONTROL:
        out = _limit_commands_c(steer, drive, brake, obs, p, lim, rear_steered, catch_up, kap, v_ref)
        if out is not None:
            return out
    return _limit_commands_numpy(steer, drive, brake, obs, p, lim, rear_steered, catch_up, kap, v_ref)


def _limit_commands_numpy(steer: np.ndarray, drive: np.ndarray, brake: np.ndarray, obs, p: VehicleParams,
                          lim: VehicleLimits, rear_steered: bool, catch_up: CatchUp | None, kap: np.ndarray | None,
                          v_ref: np.ndarray | None) -> tuple[np.ndarray, ...]:
    """``limit_commands`` in numpy once the largest path curvature ahead ``kap`` [1/m] and
    the reference speed ``v_ref`` [m/s] are known (``catch_up`` only; the reference for the
    C path, which computes the same bits)."""
    lim_f = steer_limit(obs.speed, p.wheelbase, lim.a_lat, p.max_steer)
    fixed = lim.max_rear <= 0
    steer = np.where(fixed, np.clip(steer, -lim_f, lim_f), steer) if rear_steered else np.clip(steer, -lim_f, lim_f)
    if lim.any_grip:
        drive = traction_limit(drive, obs.speed, obs.yaw_rate, lim.grip_torque)
    if catch_up is not None:
        c = catch_up
        drive = curve_speed_cut(drive, obs.speed, kap, v_ref, lim.a_lat, c.mask)
        vr = np.where(c.mask, v_ref, np.inf)
        drive, brake = saturation_speed_cut(drive, brake, steer, p.max_steer, obs.speed, vr, p.m_eff, p.r_wheel)
        grip_sat = np.abs(steer) >= STEER_SAT_SHARE * lim_f
        if rear_steered:
            grip_sat &= fixed
        drive = np.where(grip_sat & (obs.speed > vr) & (np.abs(c.err_lat) > GRIP_SAT_LAT_M), 0.0, drive)
    if lim.any_bike:
        drive = np.where(lim.bike, lean_traction_limit(drive, obs.roll, lim.a_lat, p.max_drive), drive)
        brake = np.where(lim.bike, lean_traction_limit(brake, obs.roll, lim.a_lat, p.max_brake), brake)
    return steer, drive, brake


def _limit_commands_c(steer: np.ndarray, drive: np.ndarray, brake: np.ndarray, obs, p: VehicleParams,
                      lim: VehicleLimits, rear_steered: bool, catch_up: CatchUp | None, kap: np.ndarray | None,
                      v_ref: np.ndarray | None) -> tuple[np.ndarray, ...] | None:
    """``_limit_commands_numpy`` in C (physics_side._controlkernel.limit), reading the attributes
    the numpy body reads under the same flags. None for inputs it does not read (not float64
    (n,) C-contiguous, a catch-up mask not bool: ``mask & ...`` of other integers is bitwise):
    the numpy body then runs."""
    if type(steer) is not np.ndarray or steer.ndim != 1:
        return None
    grip = (obs.yaw_rate, lim.grip_torque) if lim.any_grip else (None, None)
    cut = (None,) * 6
    if catch_up is not None:
        if getattr(catch_up.mask, "dtype", None) != np.bool_:
            return None
        cut = (kap, v_ref, catch_up.mask, catch_up.err_lat, p.m_eff, p.r_wheel)
    bike = (obs.roll, lim.bike, p.max_drive, p.max_brake) if lim.any_bike else (None,) * 4
    # the module's constants at call time (none copied into C)
    consts = (float(bool(rear_steered)), STEER_LIMIT_V_MIN, G, MAX_GRIP_USE, GRIP_LATERAL, CURVATURE_FLOOR,
              STEER_SAT_SHARE, STEER_SAT_DECEL, GRIP_SAT_LAT_M, A_LAT_FLOOR)
    out = np.empty((3, len(steer)))
    try:
        _kernel.limit(steer, drive, brake, obs.speed, p.wheelbase, lim.a_lat, p.max_steer, lim.max_rear, *grip, *cut,
                      *bike, out, consts)
    except (TypeError, ValueError):
        return None
    return out[0], out[1], out[2]


def rear_axle_commands(steer: np.ndarray, obs, p: VehicleParams, lim: VehicleLimits, idx: np.ndarray,
                       sumo_yaw: np.ndarray, sumo_rate: np.ndarray, ahead: float | None) -> np.ndarray:
    """Rear-axle angles [rad] of all agents, those of ``idx`` turning their bodies towards
    SUMO's body angle ``sumo_yaw`` [rad] moving at its rate ``sumo_rate`` [rad/s] for
    ``ahead`` [s] (``rear_axle_steer``; None: stopping, the body's own angle), 0 elsewhere;
    their front angles in ``steer`` are replaced. ``obs``: yaw [rad], speed [m/s] per agent."""
    rate = sumo_rate[idx]
    if ahead is None:
        yaw_ref, rate = obs.yaw[idx], np.zeros(len(idx))
    else:
        yaw_ref = sumo_yaw[idx] + rate * ahead
    rear = np.zeros(len(steer))
    steer[idx], rear[idx] = rear_axle_steer(
        steer[idx], obs.yaw[idx], obs.speed[idx], yaw_ref, rate, p.wheelbase[idx], p.d_bumper[idx],
        p.max_steer[idx], lim.max_rear[idx], a_lat=lim.a_lat[idx],
    )
    return rear


def bike_stabiliser(obs, steer: np.ndarray, p: VehicleParams, lim: VehicleLimits, idx: np.ndarray, kp: float,
                    kd: float) -> np.ndarray:
    """Stabiliser torque [N*m] of vehicles ``idx`` (``steered_roll_stabiliser``; gains ``kp``
    [N*m/rad], ``kd`` [N*m*s/rad] scaled per model), leaning up to the steering limit's
    lateral acceleration; bicycles keep MAX_LEAN_TAN. ``obs``: roll [rad], roll_rate [rad/s],
    speed [m/s] per agent."""
    gain = lim.stab_gain[idx]
    return steered_roll_stabiliser(
        obs.roll[idx], obs.roll_rate[idx], obs.speed[idx], steer[idx], p.wheelbase[idx], kp * gain, kd * gain,
        lim.stab_max[idx], np.where(lim.mass[idx] < MOTORCYCLE_MASS_KG, MAX_LEAN_TAN, lim.a_lat[idx] / G),
    )


def pedestrian_control(idx: np.ndarray, obs, at, held, paper: np.ndarray, stop_speed: np.ndarray | None,
                       mass: np.ndarray, max_force: np.ndarray, paper_cfg: PaperControl,
                       default_cfg: DefaultControl) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``pedestrian_force`` of pedestrians ``idx`` towards the held sample ``held`` (``paper``,
    per pedestrian) or the extrapolated reference ``at``, or to a stop where they are at
    ``stop_speed`` [m/s] (SUMO gone); feed-forward (along-path acceleration, centripetal) for
    the extrapolated reference only. ``obs``: fx, fy [m], vx, vy [m/s], yaw [rad], yaw_rate
    [rad/s] per agent. Returns (force x, force y [N], yaw torque [N*m], force norm [N])."""
    tx = np.where(paper, held.x[idx], at.x[idx])
    ty = np.where(paper, held.y[idx], at.y[idx])
    tyaw = np.where(paper, held.tangent[idx], at.tangent[idx])
    v = np.where(paper, held.speed[idx], at.speed[idx])
    if stop_speed is not None:
        v = stop_speed[idx]
        tx, ty = obs.fx[idx], obs.fy[idx]
    return pedestrian_force(
        obs.fx[idx], obs.fy[idx], obs.vx[idx], obs.vy[idx], obs.yaw[idx], obs.yaw_rate[idx], tx, ty, tyaw, v,
        np.where(paper, 0.0, at.accel[idx]), np.where(paper, 0.0, at.curvature[idx]), mass[idx],
        np.where(paper, paper_cfg.ped_omega, default_cfg.ped_omega),
        np.where(paper, paper_cfg.ped_zeta, default_cfg.ped_zeta), max_force[idx],
    )


__all__ = [
    "ControlState", "VehicleCommand", "VehicleObs", "VehicleParams", "accel_command", "accel_to_torques",
    "FAST_CONTROL", "control_default", "control_paper", "lad", "paper_pedal", "paper_steer", "pedal_to_torques",
    "planar_force", "pure_pursuit_delta", "pursuit_alpha", "roll_stabiliser", "stanley_bumper",
    "bumper_curvature_limit", "curve_speed_cut", "drive_grip_torque", "friction_steer_limit", "lateral_accel_limit",
    "pedestrian_force",
    "steer_limit",
    "rear_axle_steer", "saturation_speed_cut", "steered_roll_stabiliser", "traction_limit",
    "CatchUp", "Commands", "Groups", "VehicleLimits", "bike_stabiliser", "groups", "limit_commands", "merge_commands",
    "pedestrian_control", "rear_axle_commands", "vehicle_limits", "PRESET_CODE", "P_DEFAULT", "P_KINEMATIC", "P_PAPER",
]
