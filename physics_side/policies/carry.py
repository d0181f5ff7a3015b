"""Carry: a manoeuvre no vehicle of the agent's size can drive is shown as SUMO has it.

A U-turn on a turnaround lane, a coach through a tight junction corner, a junction turn
beyond the tyres' grip or a two-wheeler's lean: driven, the vehicle ran metres wide into
its neighbours and was placed back. Such a physical vehicle is carried (kinematic on SUMO's
poses, ``carry_pose``) until the manoeuvre is over; counted apart (``carries_infeasible``,
``carried_infeasible_ms``). Seen on the path ahead (``path_tightness``), in SUMO's turn rate,
or at its insertion far off its path's heading (``starts``); over when ``keeps`` no longer
holds. Also here: who may roll back to a standing reference it came to rest past
(``rolls_back``).
"""

from __future__ import annotations

import math

import numpy as np

from physics_side import control, models
from physics_side.policies.base import LOG_IDS, Step, Verdict, log
from physics_side.policies.footprints import footprints_overlap
from physics_side.reference import Reference
from protocol.frames import wrap_pi
from protocol.messages import AgentMode
from runtime.native import numpy_math_is_libm, optional_extension

# The C path of ``path_tightness`` after its path evaluation (bit-identical;
# ``SUMOCO_PURE_PHYSICS=1`` or no compiler: the numpy body). ``FAST_TIGHTNESS`` says which runs.
_kernel = optional_extension("physics_side.policies._policykernel", "SUMOCO_PURE_PHYSICS")
if _kernel is not None and not numpy_math_is_libm():  # (its libm calls would not be numpy's bits)
    _kernel = None
FAST_TIGHTNESS: bool = _kernel is not None

# Seen on the path ahead: the heading change over INFEASIBLE_WINDOW_M (shorter windows take
# the corners of coarse lane shapes for curves no car can follow), for windows starting up to
# 1 s of travel ahead (within INFEASIBLE_AHEAD_M)
INFEASIBLE_WINDOW_M = 8.0  # [m]
INFEASIBLE_GRID_M = 2.0  # [m] spacing of the windows' starts
INFEASIBLE_AHEAD_M = (2.0, 20.0)  # [m]
GRID_END_M = 1e-9  # [m] (the last window's end is on the grid)
INFEASIBLE_MARGIN = 0.9  # [1] a path this much tighter than the vehicle's reach starts a carry ...
INFEASIBLE_RELEASE = 0.75  # [1] ... which ends once the path ahead is within this share of it
INFEASIBLE_STRAIGHT_DEG = 10.0  # [deg] ... and SUMO's body angle is this close to the path's heading
# [deg] a vehicle SUMO inserts moving with its body angle this far off its path's heading is
# carried from its first step (its chord back to front where a curved lane meets a straight
# one: a truck inserted at 13 m/s 33 deg off the lane it drove along ran 3.8 m wide)
SPAWN_OFF_DEG = 20.0
# [1] ... and the path ahead (8 m windows) asks less than this share of the tyres' lateral acceleration
INFEASIBLE_GRIP_KEEP = 0.5
# Or seen in SUMO's turn rate: faster than INFEASIBLE_RATE_MARGIN x full lock at its speed
# (SUMO's angle is the chord back to front, which turns faster than the bumper's path
# entering a bend), moving faster than INFEASIBLE_MIN_SPEED, INFEASIBLE_OFF_M off
INFEASIBLE_RATE_MARGIN = 1.5  # [1]
INFEASIBLE_MIN_SPEED = 1.0  # [m/s]
INFEASIBLE_OFF_M = 0.5  # [m]
# Between the samples of long (interpolated) steps a carry also starts for a turn beyond the
# tyres' grip at the step's speed: at 1 s steps SUMO takes junction corners at 13 m/s through
# 45-75 deg within one step (15-25 m/s^2); driven, cars ran up to 9 m wide. The demand v^2 *
# kappa of GRIP_WINDOW_K windows counts as a share of the tyres' lateral acceleration.
# [grid steps] 4 m windows: over 8 m a bus's 26 deg corner of its lane's shape at 10.5 m/s
# looked like 0.7 of its grip; driven, it crabbed 20 deg off its lane into a bus
GRIP_WINDOW_K = 2
# At short steps the grip check covers heavy vehicles (those that steer their rear axle) at
# this share of their tyres' grip: a 7.1 m truck SUMO took through a 12 m junction turn at 8.5
# m/s steered to full lock, fell 17 deg behind SUMO's angle and its rear swung into a car.
# Two-wheelers are carried (upright) beyond the lean their tyres and riders hold (motorcycles
# at MOTORCYCLE_GRIP_SHARE): driven through SUMO's 7-9 m/s^2 junction turns they fell over.
HEAVY_GRIP_SHARE = 0.6  # [1]
# Cars beyond their tyres' friction itself (INFEASIBLE_MARGIN x this share of the steering's
# A_LAT_SHARE of it) over the 8 m windows: a taxi SUMO took through 90 deg in 1.5 s at 13.4
# m/s (15 m/s^2) ran 6 m wide. Below it cars stay driven (the demo's turns ask 4-7 m/s^2)
CAR_GRIP_SHARE = 1.2  # [1]
# [m/s^2] ... at the least speed SUMO can brake them to before each window (its emergency
# deceleration; at their own speed cars were carried on their approach to the demo's turns)
CAR_GRIP_BRAKE = 9.0
# [1] motorcycles and mopeds drive SUMO's 9-10 m/s^2 junction turns leaning at their limit
MOTORCYCLE_GRIP_SHARE = 1.4
# [m/s^2] a carried two-wheeler (any carry) is handed back (upright) only below this of SUMO's
# turn (upright mid-arc, a motorcycle rolled to 54 deg)
GUARD_BIKE_RELEASE_ALAT = 2.0
SHARE_FLOOR = 1e-9  # [1] floor of a grip share where it divides (0: not checked)
LEAN_READ_MAX_RAD = 1.0  # [rad] a roll read for the lean's swing is taken at most this far
RIDER_BACK_CLEAR_M = 0.3  # [m] a two-wheeler's way back must be this clear of every body (``rolls_back``)
MS_PER_S = 1e3  # [ms/s]


def grip_shares(kind: np.ndarray, max_rear: np.ndarray, mass: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Share of the tyres' grip (or the lean's) beyond which a turn is carried at short steps
    (heavy vehicles, two-wheelers, cars; 0 = not checked) and the deceleration [m/s^2] SUMO
    may brake a car at before each window (0: at its own speed)."""
    bike = kind == models.KIND_BIKE
    car = (kind == models.KIND_CAR) & (max_rear <= 0)
    share = np.where(max_rear > 0, HEAVY_GRIP_SHARE,
                     np.where(bike, np.where(mass < control.MOTORCYCLE_MASS_KG, 1.0, MOTORCYCLE_GRIP_SHARE),
                              np.where(car, CAR_GRIP_SHARE, 0.0)))
    return share, np.where(car, CAR_GRIP_BRAKE, 0.0)


def path_tightness(ref: Reference, interpolating: bool, reach: np.ndarray, a_lat: np.ndarray, kind: np.ndarray,
                   share: np.ndarray, brake: np.ndarray,
                   roll: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each vehicle's tightest path ahead as a share of its ``reach`` [1/m], and the largest
    lateral acceleration [m/s^2] its path's 8 m windows ahead ask at its speed (cars at short
    steps: at the least speed SUMO can brake them to at ``brake`` [m/s^2]). The reach's share
    is the mean curvature of 8 m windows starting up to 1 s of travel ahead. Between the
    samples of long steps also as a share of the tyres' grip ``a_lat`` [m/s^2] at the step's
    speed; at short steps as a share of ``share`` of it (``grip_shares``), a two-wheeler's
    swing from its lean (``roll`` [rad]) into the turn ahead included. One path evaluation
    per SUMO step: headings every INFEASIBLE_GRID_M, windows by index offset."""
    k = int(round(INFEASIBLE_WINDOW_M / INFEASIBLE_GRID_M))
    grid = np.arange(0.0, INFEASIBLE_AHEAD_M[1] + INFEASIBLE_WINDOW_M + GRID_END_M, INFEASIBLE_GRID_M)[:, None]
    h = ref.path.at(np.broadcast_to(grid, (len(grid), ref.n))).heading
    v = np.maximum(ref.speed, 0.0)
    if interpolating:
        v = np.maximum(v, ref.step_speed)
    ahead = np.clip(v, *INFEASIBLE_AHEAD_M)
    with_grip = interpolating or bool(np.any(share > 0))
    bike = kind == models.KIND_BIKE
    with_lean = with_grip and not interpolating and roll is not None and bool(np.any(bike))
    if _kernel is not None and ref.n:
        f8 = np.float64
        tight, sustained = np.empty(ref.n), np.empty(ref.n)
        _kernel.tightness(
            np.ascontiguousarray(h, f8), np.ascontiguousarray(grid[:, 0]), *(np.ascontiguousarray(a, f8) for a in (
                v, ahead, np.broadcast_to(reach, v.shape), np.broadcast_to(a_lat, v.shape), share, brake)),
            np.ascontiguousarray(roll, f8) if with_lean else None, np.ascontiguousarray(bike), tight, sustained,
            (float(interpolating), float(with_grip), float(with_lean), k, GRIP_WINDOW_K, INFEASIBLE_WINDOW_M,
             GRIP_WINDOW_K * INFEASIBLE_GRID_M, control.G, LEAN_READ_MAX_RAD, CAR_GRIP_SHARE, SHARE_FLOOR))
        return tight, sustained
    return _tightness_numpy(h, grid, k, v, ahead, interpolating, with_grip, with_lean, reach, a_lat, bike, share, brake,
                            roll)


def _tightness_numpy(h, grid, k, v, ahead, interpolating, with_grip, with_lean, reach, a_lat, bike, share, brake, roll):
    """``path_tightness`` after the path evaluation, in numpy (the C path's reference)."""
    kappa = np.abs(wrap_pi(h[k:] - h[:-k])) / INFEASIBLE_WINDOW_M
    tight = np.where(grid[:-k] <= ahead, kappa, 0.0).max(axis=0) / reach
    # over the 8 m windows, at short steps at the least speed SUMO can brake a car to by
    # each window (a lane shape's 15 deg corner within 4 m asked 12.6 m/s^2 at 14 m/s:
    # carried for 0.3 s, a van was handed back steering into it and spun)
    v2 = v * v - (0.0 if interpolating else 2.0 * brake * grid[:-k])
    sustained = np.where(grid[:-k] <= ahead, kappa * np.maximum(v2, 0.0), 0.0).max(axis=0)
    if not with_grip:
        return tight, sustained
    kg = GRIP_WINDOW_K
    kap = wrap_pi(h[kg:] - h[:-kg]) / (kg * INFEASIBLE_GRID_M)  # (+ left)
    demand = np.where(grid[:-kg] <= ahead, kap, 0.0) * v * v  # [m/s^2] + left
    grip = np.abs(demand).max(axis=0) / a_lat
    if with_lean:
        # a two-wheeler leaning one way into a turn the other way swings its lean across both:
        # SUMO's S through a junction (left at 4 m/s, then right at 8-9 m/s^2 at 8 m/s)
        # flipped a motorcycle still leaning 28 deg into the left part
        lean = -control.G * np.tan(np.clip(roll, -LEAN_READ_MAX_RAD, LEAN_READ_MAX_RAD))  # [m/s^2] + left
        swing = np.abs(demand - lean).max(axis=0) / a_lat
        grip = np.where(bike, np.maximum(grip, swing), grip)
    if not interpolating:  # short steps: at each vehicle's share
        grip = np.where(share > 0, grip / np.maximum(share, SHARE_FLOOR), 0.0)
        grip = np.where(brake > 0, sustained / (a_lat * CAR_GRIP_SHARE), grip)
    return np.maximum(tight, grip), sustained


def starts(s: Step, tight: np.ndarray) -> np.ndarray:
    """Carries that start: the path ahead beyond INFEASIBLE_MARGIN of the reach or grip; at
    short steps SUMO's turn rate beyond its steering once the body is INFEASIBLE_OFF_M off
    (between long steps' samples SUMO's rate is a chord's); an insertion moving far off its
    path's heading."""
    ref = s.ref
    start = tight > INFEASIBLE_MARGIN
    if not s.interpolating:
        start |= ((ref.speed > INFEASIBLE_MIN_SPEED) & (s.dist > INFEASIBLE_OFF_M)
                  & (np.abs(s.yaw_rate) > INFEASIBLE_RATE_MARGIN * ref.speed * s.reach))
    start |= ((s.prev < 0) & (ref.speed > INFEASIBLE_MIN_SPEED)
              & (np.abs(wrap_pi(ref.yaw - ref.start_heading)) > math.radians(SPAWN_OFF_DEG)))
    return start


def keeps(s: Step, tight: np.ndarray, sustained: np.ndarray) -> np.ndarray:
    """Carries under way that go on; one ends only once all of these are over."""
    ref, obs, a_lat = s.ref, s.obs, s.limits.a_lat
    straight = math.radians(INFEASIBLE_STRAIGHT_DEG)
    # the path ahead in reach, the body straight on it (a long vehicle's rear is still in the
    # turn when its bumper is out: SUMO's chord angle) and the carried body itself turned onto
    # SUMO's angle (released where SUMO's angle jumps at a junction's end, a car fell 1.8 m behind)
    keep = ((tight > INFEASIBLE_RELEASE) | (np.abs(wrap_pi(ref.yaw - ref.start_heading)) > straight)
            | (np.abs(wrap_pi(obs.yaw - ref.yaw)) > straight)
            # ... SUMO no longer turning it tighter than its steering holds (handed back at 100
            # deg/s, a car lagged 0.6 m, a van spun round)
            | (np.abs(s.yaw_rate) > INFEASIBLE_RELEASE * np.maximum(ref.speed, INFEASIBLE_MIN_SPEED) * s.reach))
    # ... the path ahead asking little of the tyres (a taxi handed back in a 75 deg junction
    # turn at 8 m/s, 8.7 m/s^2, ran 2.6 m wide at full lock)
    keep |= sustained > INFEASIBLE_GRIP_KEEP * a_lat
    # ... the carried body no longer turning faster than its tyres carry (a chord whose back is
    # still in the corner turns at up to 1.2 rad/s at 14 m/s: released then, cars spun round)
    keep |= np.abs(obs.yaw_rate * obs.speed) > INFEASIBLE_RELEASE * a_lat
    # ... a two-wheeler (placed upright) not in a turn it would have to lean into, in SUMO's
    # turn rate or ahead (SUMO holds a motorcycle's angle for a few steps in a junction turn,
    # then jumps it: handed back when the rate read 0 mid-arc, it over-turned and fell), nor
    # braked so hard that with the turn ahead its tyres are past the release share (a
    # motorcycle handed back while SUMO braked it at 10 m/s^2 into a bend fell to the outside)
    keep |= (s.kind == models.KIND_BIKE) & ((np.abs(s.yaw_rate * ref.speed) > GUARD_BIKE_RELEASE_ALAT)
                                            | (sustained > GUARD_BIKE_RELEASE_ALAT)
                                            | (np.hypot(sustained, np.maximum(-ref.accel, 0.0))
                                               > INFEASIBLE_RELEASE * a_lat))
    return keep


def manoeuvres(s: Step) -> np.ndarray:
    """Physical vehicles on a manoeuvre they cannot drive: starting one, or still on one."""
    # (physics-authoritative vehicles are never carried: with every vehicle so, nothing to test)
    cand = (s.mode == AgentMode.PHYSICAL) & (s.kind != models.KIND_PED) & ~s.authoritative
    if not (s.cfg.carry_infeasible and cand.any()):
        return np.zeros(s.n, bool)
    share, brake = grip_shares(s.kind, s.limits.max_rear, s.limits.mass)
    tight, sustained = path_tightness(s.ref, s.interpolating, s.reach, s.limits.a_lat, s.kind, share, brake,
                                      s.obs.roll)
    return cand & (starts(s, tight) | (s.before.carried & keeps(s, tight, sustained)))


def detect_manoeuvre(s: Step, v: Verdict) -> None:
    """Carry physical vehicles through manoeuvres they cannot drive (never the agents physics
    owns under two-way coupling)."""
    v.manoeuvre = manoeuvres(s) & ~s.authoritative
    v.carry(v.manoeuvre)


def rolls_back(s: Step, v: Verdict) -> np.ndarray:
    """Who may roll back to a standing reference it came to rest past (``control_default``):
    four-wheeled vehicles, and two-wheelers whose way back is clear of every other body
    (RIDER_BACK_CLEAR_M). A motorcycle rolled back into the bicycle queued beside and behind
    it under the sublane model; never rolled back, a motorcycle stopped 2.7 m past SUMO's
    stop stood on a crossing in the way of a pedestrian."""
    out = s.kind != models.KIND_BIKE
    d = s.ctl.default
    cand = np.flatnonzero(~out & (s.held.speed <= d.hold_speed) & (s.e_lon > d.creep_back_m) & v.physical)
    obs, L, W = s.obs, s.length, s.width
    every = np.arange(s.n)
    for i in cand:  # (two-wheelers standing past their stop: a handful)
        back = s.e_lon[i]  # the way back: the body stretched back to its reference
        c, s_ = np.cos(obs.yaw[i]), np.sin(obs.yaw[i])
        other = every != i
        out[i] = not footprints_overlap(
            obs.cx[i] - 0.5 * back * c, obs.cy[i] - 0.5 * back * s_, obs.yaw[i], L[i] + back, W[i],
            obs.cx[other], obs.cy[other], obs.yaw[other], L[other], W[other], RIDER_BACK_CLEAR_M).any()
    return out


def detect_roll_back(s: Step, v: Verdict) -> None:
    v.rolls_back = rolls_back(s, v)


def count(v: Verdict, s: Step, carried: np.ndarray, began: np.ndarray, contact: np.ndarray) -> None:
    """Episodes and agent-milliseconds of the carries (manoeuvre and contact apart)."""
    if not carried.any():
        return
    ms = MS_PER_S * s.step_length
    v.count("carries_infeasible", (began & ~v.guard).sum())
    v.count("carried_infeasible_ms", round(ms * (carried & ~contact).sum()))
    v.count("carries_contact", (began & v.guard).sum())
    v.count("carried_contact_ms", round(ms * contact.sum()))
    if (began & ~v.guard).any():
        log.info("t=%.2f s: %s on a manoeuvre beyond their steering: shown kinematic until it is over",
                 s.ref.t_k, [s.ids[i] for i in np.flatnonzero(began & ~v.guard)][:LOG_IDS])


__all__ = [
    "count", "detect_manoeuvre", "detect_roll_back", "grip_shares", "keeps", "manoeuvres", "path_tightness",
    "rolls_back", "starts",
]
