"""How a carried (kinematic) body is posed between SUMO's samples: its angle, the curvature
it is placed turning at, and its glide from the pose it drove to onto SUMO's.

Used every tick for agents kinematic by preset or carried by a policy (``carry``,
``contacts``), and once when a carry starts (the glide's offset).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from physics_side.reference import Reference, ReferencePoint
from protocol.frames import wrap_pi

KIN_CURVATURE_M = 4.0  # [m] window of the path curvature carried bodies are placed turning at
KIN_GLIDE_MAX_M = 3.0  # [m] a carry starting further off SUMO's pose starts on it (no glide)
KIN_BLEND_S = 0.4  # [s] time constant of a carried body's glide from its driven pose onto SUMO's
CHORD_FIX_MAX_DEG = 30.0  # [deg] a carried body's chord is turned onto SUMO's angle at the step's end within this
KIN_MIN_SPEED = 1.0  # [m/s] curvatures from turn rates and the tyres' grip are taken at least at this speed
ON_PATH_MAX_RAD = 0.5 * math.pi  # [rad] SUMO's angle this far off its path's start: turned on the spot
CHORD_MIN_M2 = 1e-6  # [m^2] floor of a chord's squared length where it divides
POSE_DIMS = 3  # a glide's offset: x [m], y [m], yaw [rad]


def turn_rate(before: np.ndarray, now: np.ndarray) -> np.ndarray:
    """Rate [rad/s] kinematic bodies turn at between samples from SUMO's rates over its last
    two steps (``before``, ``now``): the slower of both where they agree, else 0. A one-step
    jump of its angle (a sublane move's start: 3.4 deg in 0.05 s at 1.3 m/s) carried on for a
    step swung a carried 16.5 m trailer's rear 0.7 m sideways."""
    return np.where(before * now > 0.0, np.sign(now) * np.minimum(np.abs(before), np.abs(now)), 0.0)


def chord(ref: Reference, at: ReferencePoint, tau: float, sumo_len: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angle [rad] and turning curvature [1/m] of each body's chord (SUMO's length
    ``sumo_len`` [m]) on the interpolated path with its bumper at ``at``: back to front,
    straight back along SUMO's angle at the step's start where the back is behind the path's
    start; curvature cross(d, u_front - u_back) / |d|^2 for the chord d and the path's unit
    tangents at both ends."""
    back = at.s - sumo_len
    p = ref.point_at(np.maximum(back, 0.0), tau)
    # (SUMO's angle unless it is far off the path's start: a vehicle it turned on the spot)
    h0 = np.where(np.abs(wrap_pi(ref.yaw - ref.start_heading)) < ON_PATH_MAX_RAD, ref.yaw, ref.start_heading)
    short = np.minimum(back, 0.0)
    dx, dy = at.x - p.x - short * np.cos(h0), at.y - p.y - short * np.sin(h0)
    hb = np.where(back > 0.0, p.heading, h0)
    ux, uy = np.cos(at.tangent) - np.cos(hb), np.sin(at.tangent) - np.sin(hb)
    kappa = (dx * uy - dy * ux) / np.maximum(dx * dx + dy * dy, CHORD_MIN_M2)
    return np.arctan2(dy, dx), kappa


def chord_fix(ref: Reference, step_length: float, sumo_yaw: np.ndarray, sumo_len: np.ndarray) -> np.ndarray:
    """The chord's difference [rad] from SUMO's angle ``sumo_yaw`` at the step's end sample,
    for agents with a known next sample (0 beyond CHORD_FIX_MAX_DEG): the chord's straight
    back is not SUMO's back on its lanes (a carried bus's chord was 7 deg off SUMO's angle
    there, its rear 1.4 m into the next lane)."""
    fix = wrap_pi(sumo_yaw - chord(ref, ref.at(step_length), step_length, sumo_len)[0])
    known = ref.interpolated if ref.interpolated is not None else np.zeros(ref.n, bool)
    return np.where(known & (np.abs(fix) < math.radians(CHORD_FIX_MAX_DEG)), fix, 0.0)


def short_step_curvature(kappa: np.ndarray, rate: np.ndarray, speed: np.ndarray, ped: np.ndarray,
                         carried: np.ndarray, a_lat: np.ndarray) -> np.ndarray:
    """Curvature [1/m] a kinematic body is placed turning at between short steps, from the
    path's ``kappa`` [1/m] around its bumper: no tighter than its tyres carry (``a_lat``
    [m/s^2]) at its ``speed`` [m/s] (vans and trailers handed back at a lane shape's corner at
    14 m/s spun round), and neither against nor faster than SUMO's own turn of the body
    (``rate`` [rad/s]): in an S the bumper's path turns one way while a long body's chord
    still turns the other (handed back spinning), and a van placed turning faster than SUMO
    turned it was handed back over-rotating. Bodies kinematic by preset turn at SUMO's rate;
    ``carried`` ones at the slower of both where they agree; pedestrians at their path's."""
    lim = np.where(ped, np.inf, a_lat / np.maximum(speed, KIN_MIN_SPEED) ** 2)
    k_sumo = rate / np.maximum(speed, KIN_MIN_SPEED)
    both = kappa * k_sumo
    slower = np.where(both > 0.0, np.sign(kappa) * np.minimum(np.abs(kappa), np.abs(k_sumo)),
                      np.where(both < 0.0, k_sumo, 0.0))
    kappa = np.where(ped, kappa, np.where(carried, slower, k_sumo))
    return np.clip(kappa, -lim, lim)


def kinematic_pose(ref: Reference, at: ReferencePoint, tau: float, rate: np.ndarray, step_length: float,
                   interpolating: bool, ped: np.ndarray, carried: np.ndarray, a_lat: np.ndarray,
                   sumo_len: np.ndarray, fix: np.ndarray | None) -> tuple[np.ndarray, ReferencePoint]:
    """Body angle [rad] of kinematic agents placed at ``at`` (``tau`` [s] past the sample),
    and ``at`` with the curvature they are placed turning at.

    At short steps: SUMO's own angle turning at ``rate`` [rad/s] between its samples (not the
    path's heading at the bumper: a corner of a coarse lane shape right at the bumper swung a
    carried car's body 19 deg off SUMO's angle, into its neighbours). Between the samples of
    long steps SUMO's angle at either sample may be far off the interpolated path (a 65 deg
    corner taken within one step): ``carried`` bodies take the ``chord`` on the interpolated
    path, turning at its own rate, plus its difference ``fix`` [rad] (``chord_fix``) in
    proportion to the time (placed turning at the curvature of a lane shape's corner at the
    bumper, a released car kept spinning). Placed turning at the path's mean curvature over
    KIN_CURVATURE_M around the bumper: at a lane shape's corner the curvature right there is a
    spike (a carried van handed back steering 36 deg against its turn spun and was placed)."""
    sumo = wrap_pi(ref.yaw + rate * min(tau, step_length))
    h = ref.path.at(at.s + np.array([[-0.5], [0.5]]) * KIN_CURVATURE_M).heading
    kappa = wrap_pi(h[1] - h[0]) / KIN_CURVATURE_M
    if not interpolating:
        kappa = short_step_curvature(kappa, rate, at.speed, ped, carried, a_lat)
    at = replace(at, curvature=kappa)
    if not interpolating or not carried.any():  # (agents kinematic by preset: SUMO's)
        return sumo, at
    u = min(max(tau, 0.0) / step_length, 1.0)
    yaw, kappa = chord(ref, at, tau, sumo_len)
    kappa = kappa + fix / (step_length * np.maximum(at.speed, KIN_MIN_SPEED))
    return (np.where(carried, wrap_pi(yaw + u * fix), sumo),
            replace(at, curvature=np.where(carried, kappa, at.curvature)))


def start_glide(prev: np.ndarray, was: np.ndarray, began: np.ndarray, obs, held: ReferencePoint,
                yaw0: np.ndarray | None, old_off: np.ndarray, old_age: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each carried body's offset from SUMO's pose (x, y [m], yaw [rad]) at its carry's start
    and the carry's age [s] (inf: not carried): carries under way keep theirs (``was``, rows
    ``prev``); one that ``began`` glides from the pose it drove to (``obs``; ``yaw0``: the
    carried angle there), switched at once a long body's yaw jumped to SUMO's chord, its rear
    ~1 m sideways. A body spawned (at its parking spot) or teleported this step, or further
    than KIN_GLIDE_MAX_M off, starts on SUMO's pose (a van carried from its spawn glided in
    from the parking spot 70 km away)."""
    n = len(prev)
    off, age = np.zeros((n, POSE_DIMS)), np.full(n, np.inf)
    if was.any():
        off[was], age[was] = old_off[prev[was]], old_age[prev[was]]
    if began.any():
        o = np.c_[obs.fx - held.x, obs.fy - held.y, wrap_pi(obs.yaw - yaw0)]
        far = (prev < 0) | (np.hypot(o[:, 0], o[:, 1]) > KIN_GLIDE_MAX_M)
        off[began] = np.where(far[:, None], 0.0, o)[began]
        age[began] = 0.0
    return off, age


def glide(at: ReferencePoint, yaw: np.ndarray, off: np.ndarray, age: np.ndarray) -> tuple[ReferencePoint, np.ndarray]:
    """``at`` and body angle ``yaw`` [rad] moved by what is left of each carry's starting
    offset ``off`` after ``age`` [s] (none for agents kinematic by preset, age inf)."""
    f = np.exp(-age / KIN_BLEND_S)
    return replace(at, x=at.x + f * off[:, 0], y=at.y + f * off[:, 1]), yaw + f * off[:, 2]


__all__ = ["chord", "chord_fix", "glide", "kinematic_pose", "short_step_curvature", "start_glide", "turn_rate"]
