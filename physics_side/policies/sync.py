"""Sync: how each agent's new SUMO sample relates to its previous one.

Sample phase (``Fleet`` builds the reference with them): a vType change respawns the agent
(``retyped``), a previous sample too old or a resync is no previous sample (``stale``),
SUMO's sideways drift off its lane's centre line (``side_drift``), a slow vehicle moved
sideways at once (``hops``) and a pedestrian moved further than it walks
(``pedestrian_hops``) are no motion to follow.

Detect phase (``detect_*``, table order): a new agent is placed at its SUMO pose (spawn);
a teleported (``AgentFlag.JUMPED``), hopping or pedestrian-hopping physical agent is placed
at its new pose (jump); a slow vehicle SUMO slides sideways further than it can drive is
placed, and a standing one SUMO slides sideways is carried along the slide (slide).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from physics_side import models
from physics_side.policies.base import Cause, Step, Verdict
from physics_side.reference import Reference, tracking_error
from protocol.frames import wrap_pi
from protocol.messages import AgentFlag

STALE_MIN_S = 1.0  # [s] a previous sample this recent is usable whatever the step length ...
STALE_STEPS = 2.5  # [steps] ... and one this many step lengths old
PED_HOP_M = 0.5  # [m] a pedestrian's sample this much further than its speed takes it is a jump
CARRY_SPEED = 0.5  # [m/s] below this SUMO speed a sideways slide is carried, not driven
SLIDE_MIN_SPEED = 0.05  # [m/s] SUMO's sideways motion at least this fast is a slide (not rounding)
# [1] a sample closer to its lane's centre line than this share of a step's drift has ended its
# lane change there (SUMO stops it on the line; its offset's sign is rounding)
ARRIVE_SHARE = 0.25
# [1] an S of curvature k (a lane change at the vehicle's reach) moves k * travel^2 * this sideways
S_CURVE_SHARE = 0.25
MIN_GAP_S = 1e-9  # [s] floor of the time between two samples where it divides


@dataclass(frozen=True)
class _Pose:
    """A pose ``tracking_error`` measures against: front bumper x, y [m], heading [rad]."""

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray


def stack_batches(a, b):
    """The columns ``Reference.from_batch`` reads of batch ``a`` (or nothing) followed by ``b``."""
    parts = [x for x in (a, b) if x is not None]
    cols = {k: np.concatenate([np.asarray(getattr(x, k), np.float64) for x in parts])
            for k in ("x", "y", "angle", "speed", "accel", "la_x", "la_y")}
    offs, xys, base = [np.zeros(1, np.int64)], [], 0
    for x in parts:
        o = np.asarray(x.path_offsets, np.int64) if len(x.path_offsets) else np.zeros(x.n + 1, np.int64)
        offs.append(o[1:] - o[0] + base)
        xys.append(np.asarray(x.path_xy[o[0]:o[-1]], np.float64).reshape(-1, 2))
        base += int(o[-1] - o[0])
    return SimpleNamespace(n=sum(x.n for x in parts), path_offsets=np.concatenate(offs),
                           path_xy=np.concatenate(xys) if xys else np.zeros((0, 2)), **cols)


# --------------------------------------------------------------------------- sample phase


def retyped(prev: np.ndarray, old_vtype: np.ndarray, old_cls: np.ndarray, n_old: int, vtype: np.ndarray,
            cls: np.ndarray) -> np.ndarray:
    """Rows whose vType or wire class changed since the previous step (``vehicle.setType``):
    they leave and spawn anew in the model and pool of the new type."""
    had = prev >= 0
    if not (had.any() and len(old_vtype) == n_old == len(old_cls)):
        return np.zeros(0, np.int64)
    p0 = np.maximum(prev, 0)
    return np.flatnonzero(had & ((old_vtype[p0] != vtype) | (old_cls[p0] != cls)))


def stale(t: float, old_t: float, step_length: float) -> bool:
    """Is the previous sample at ``old_t`` [s] no previous sample for one at ``t`` [s] (too old,
    or a clock that went back: a new SUMO run)?"""
    return not 0.0 < t - old_t < max(STALE_MIN_S, STALE_STEPS * step_length)


def yaw_rates(yaw: np.ndarray, old: Reference | None, prev: np.ndarray, t: float) -> np.ndarray:
    """SUMO's turn rate [rad/s] between each agent's previous sample and ``yaw`` [rad] at ``t``."""
    out = np.zeros(len(prev))
    if old is not None and len(prev):
        had = prev >= 0
        out[had] = wrap_pi(yaw[had] - old.yaw[prev[had]]) / (t - old.t_k)
    return out


def side_drift(ref: Reference, old: Reference | None, prev: np.ndarray, t: float,
               max_side_speed: float) -> tuple[np.ndarray, np.ndarray | None]:
    """SUMO's sideways speed [m/s] off its lane's centre line (a continuous lane change; a hop,
    or the step where the lane switches and the offset flips sides, is no drift), and the
    drift the reference carries on (None without a previous sample): none past a sample that
    came back onto the centre line (a car ran a whole step's drift, 0.18 m, beyond its new
    lane's centre)."""
    side_rate = np.zeros(len(prev))
    if old is None or not bool((prev >= 0).any()):  # (the previous step may have had no agents)
        return side_rate, None
    had = prev >= 0
    gap = t - old.t_k
    side = (ref.side_offset - old.side_offset[np.maximum(prev, 0)]) / gap
    side_rate = np.where(had & (np.abs(side) < max_side_speed), side, 0.0)
    arrived = np.abs(ref.side_offset) < ARRIVE_SHARE * np.abs(side_rate) * gap
    return side_rate, np.where(arrived, 0.0, side_rate)


def hops(x: np.ndarray, y: np.ndarray, speed: np.ndarray, old: Reference | None, prev: np.ndarray, t: float,
         cfg) -> tuple[np.ndarray, np.ndarray]:
    """(slow, hop): slow at both samples (below ``sideways_jump_speed``), and moved sideways
    further than ``sideways_jump_m`` or ``max_side_speed`` over the step. SUMO moves a slow
    vehicle sideways at once when it changes lanes without a lane-change duration (queues at
    junctions) or parks off the lane (a bus bay): no vehicle can drive that without hitting
    its neighbours. At long steps 1.3 m in a 1 s step is a slow lane change (a slide);
    placed as a hop, a bus in Hamburg was 1.1 m off SUMO."""
    slow = hop = np.zeros(len(prev), bool)
    if cfg.sideways_jump_m > 0 and old is not None and old.n and len(prev):
        p0 = np.maximum(prev, 0)
        vmax = cfg.sideways_jump_speed
        slow = (prev >= 0) & (old.speed[p0] < vmax) & (speed < vmax)
        if slow.any():
            _, side = tracking_error(x, y, _Pose(old.x[p0], old.y[p0], old.yaw[p0]))
            reach = max(cfg.sideways_jump_m, cfg.max_side_speed * (t - old.t_k))
            hop = slow & (np.abs(side) > reach)
    return slow, hop


def pedestrian_hops(x: np.ndarray, y: np.ndarray, speed: np.ndarray, old: Reference | None, prev: np.ndarray,
                    t: float, old_kind: np.ndarray) -> np.ndarray:
    """Pedestrians SUMO moved further than they walk (onto a walking area or crossing: 1.3 m
    in one 0.1 s step): running after it, one ran into a bus; followed between samples as
    motion, one ran 3.5 m past its crossing's entry. ``old_kind``: the previous step's kinds."""
    if not (old is not None and old.n and len(prev) and len(old_kind)):
        return np.zeros(len(prev), bool)
    p0 = np.maximum(prev, 0)
    moved = np.hypot(x - old.x[p0], y - old.y[p0])
    reach = np.maximum(old.speed[p0], speed) * (t - old.t_k) + PED_HOP_M
    return (prev >= 0) & (old_kind[p0] == models.KIND_PED) & (moved > reach)


# --------------------------------------------------------------------------- detect phase


def detect_spawn(s: Step, v: Verdict) -> None:
    """New agents are placed at their SUMO pose."""
    v.place(s.is_new, Cause.SPAWN)


def detect_jump(s: Step, v: Verdict) -> None:
    """Physical agents SUMO teleported, hopped sideways or moved further than a pedestrian
    walks are placed at their new pose (counted as jumps)."""
    v.place((((s.flags & AgentFlag.JUMPED) != 0) | s.ped_hop | s.hop) & v.physical, Cause.JUMP)


def detect_slide(s: Step, v: Verdict) -> None:
    """A slow vehicle SUMO slides sideways (a continuous lane change in a queue) is placed
    once it is further off than driving makes up (``sideways_slide_m``); a standing one is
    carried along SUMO's slide every tick (one placement per slide, counted as a jump)
    instead of lagging behind and being placed then. A slide starts only when the sample
    moves off its lane's centre line: a vehicle pulling away into a junction turn moves its
    bumper sideways of its old heading along the lane (0.008 m at 0.26 m/s in the first 0.1 s
    step) and was carried, 60 deg off SUMO's angle; a slide under way continues through the
    step where the lane switches."""
    if not s.slow.any():
        return
    physical = v.physical
    drifting = np.abs(s.side_rate) > SLIDE_MIN_SPEED
    v.place(s.slow & drifting & (np.abs(s.e_lat) > s.cfg.sideways_slide_m) & physical, Cause.JUMP)
    old, p0 = s.old, np.maximum(s.prev, 0)
    _, shift = tracking_error(s.x, s.y, _Pose(old.x[p0], old.y[p0], old.yaw[p0]))
    gap = max(s.gap, MIN_GAP_S)
    free = (v.cause == Cause.NONE) & physical & (s.kind != models.KIND_PED)
    carry = (s.slow & (old.speed[p0] < CARRY_SPEED) & (s.speed < CARRY_SPEED)
             & (np.abs(shift) > SLIDE_MIN_SPEED * gap) & free)
    was = s.before.sliding
    carry &= was | drifting
    ref = s.ref
    if ref.interpolated is not None:
        # between the samples of long steps also a slow vehicle that SUMO moves sideways off
        # its path further than it can drive over its travel in the step (a lane change's S at
        # its reach): a bus stopping from 1.3 m/s that SUMO moved 0.9 m sideways stood still,
        # 1.4 m off at the next sample
        lat = np.abs(ref.side_rate) * s.step_length
        travel = ref.step_speed * s.step_length
        carry |= (s.slow & ref.interpolated & (lat > s.cfg.sideways_slide_m)
                  & (lat > S_CURVE_SHARE * s.reach * travel * travel) & free)
    v.place(carry & ~was, Cause.JUMP)
    v.sliding = carry


__all__ = [
    "detect_jump", "detect_slide", "detect_spawn", "hops", "pedestrian_hops", "retyped", "side_drift",
    "stack_batches", "stale", "yaw_rates",
]
