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
from itertools import repeat
from types import SimpleNamespace
from typing import NamedTuple

import numpy as np

from physics_side import models
from physics_side.policies.base import Cause, Step, Verdict, log, realign
from physics_side.policies.carry_pose import turn_rate
from physics_side.reference import Reference, tracking_error
from protocol.frames import sumo_angle_to_yaw, wrap_pi
from protocol.messages import AgentClass, AgentFlag, StepMessage

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
PROJECT_ITERATIONS = 3  # projections of the next sample onto the previous path (interpolation)
# a pool key (``pool_keys``): one int64 of wire class, vType, length and width in whole millimetres
SIZE_BITS = 20  # [bit] a length or width (up to 1,048 m)
VTYPE_BITS = 16  # [bit]
CLASS_BITS = 8  # [bit]
MM_PER_M = 1e3  # [mm/m]


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


def pool_keys(cls, vtype, length, width) -> np.ndarray:
    """One int64 per agent for its model and pool: wire class, vType index, length and width
    [m] to the millimetre (np.unique of a 1-D array: ~0.5 ms at 10,000 agents; of rows ~20 ms)."""
    size_max = (1 << SIZE_BITS) - 1
    mm = lambda v: np.clip(np.round(np.asarray(v, np.float64) * MM_PER_M), 0, size_max).astype(np.int64)  # noqa: E731
    return ((np.asarray(cls, np.int64) & ((1 << CLASS_BITS) - 1)) << (VTYPE_BITS + 2 * SIZE_BITS)
            | (np.asarray(vtype, np.int64) & ((1 << VTYPE_BITS) - 1)) << (2 * SIZE_BITS)
            | mm(length) << SIZE_BITS | mm(width))


def unpack_pool_keys(key: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(wire class, vType index, length [m], width [m]) of ``pool_keys``."""
    size_max = (1 << SIZE_BITS) - 1
    return (key >> (VTYPE_BITS + 2 * SIZE_BITS), (key >> (2 * SIZE_BITS)) & ((1 << VTYPE_BITS) - 1),
            ((key >> SIZE_BITS) & size_max) / MM_PER_M, (key & size_max) / MM_PER_M)


def families(cls: np.ndarray, vtype: np.ndarray, length: np.ndarray, vtypes: list, warned: set[str]) -> list[str]:
    """Model family of each agent from its vType's vClass (``vtypes``: the newest table SUMO
    sent); a vClass without a wire class of its own is named once (``warned``)."""
    out = []
    for c, t, L in zip(cls.tolist(), vtype.tolist(), length.tolist()):
        vclass = vtypes[t].vclass if t < len(vtypes) else ""
        out.append(models.family_for(c, vclass, L))
    if AgentClass.OTHER in cls:
        for c, t, f in zip(cls.tolist(), vtype.tolist(), out):
            vclass = vtypes[t].vclass if t < len(vtypes) else "?"
            if c == AgentClass.OTHER and vclass not in warned:
                warned.add(vclass)
                log.info("vClass %r has no wire class of its own: driven by the %s model", vclass, f)
    return out


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


class Sample(NamedTuple):
    """This step's samples against each agent's previous one (``Samples.advance``)."""

    x: np.ndarray
    """Front bumper x [m] (SUMO's)."""
    y: np.ndarray
    speed: np.ndarray
    """[m/s] as SUMO sent it."""
    yaw_rate: np.ndarray
    """SUMO's turn rate [rad/s] over its last two samples."""
    ref: Reference
    """The reference over this step (between the samples when interpolating)."""
    side_rate: np.ndarray
    slow: np.ndarray
    hop: np.ndarray
    ped_hop: np.ndarray


class Samples:
    """Each agent's previous SUMO sample, kept from step to step, and the reference built
    from it and the new one."""

    def __init__(self) -> None:
        self.newest: Reference | None = None
        """The newest sample as a reference from its time."""
        self.yaw = self.yaw_rate = np.zeros(0)
        """SUMO's body angle [rad] at the newest sample and its rate [rad/s] over the last two."""
        self.kin_rate = np.zeros(0)
        """[rad/s] the rate kinematic bodies turn at between samples (``carry_pose.turn_rate``)."""
        self._batch = None
        self._rows: dict[str, int] = {}  # agent id -> its row in ``_batch``
        self._ids: list[str] = []  # the agents and rows ``_rows`` maps
        self._row_of = np.zeros(0, np.int64)
        self._time = 0.0

    def advance(self, msg: StepMessage, rows: np.ndarray, ids: list[str], prev: np.ndarray, old: Reference | None,
                cfg, interpolating: bool, old_kind: np.ndarray) -> Sample:
        """The samples of ``msg`` (its ``rows``, agents ``ids``, rows ``prev`` in the previous
        step) against the previous ones (``old``, None: none usable): turn rates, drift, hops,
        and the reference over the step; they become the previous ones."""
        a = msg.agents
        x, y, speed = a.x[rows], a.y[rows], a.speed[rows]
        yaw = sumo_angle_to_yaw(a.angle[rows])
        yaw_rate = yaw_rates(yaw, old, prev, msg.time)
        ref = cur = Reference.from_batch(msg.time, a, rows if len(rows) < a.n else None, yaw_rate)
        before = np.zeros(len(ids))
        if old is not None and len(self.yaw_rate) and len(ids):
            before = realign(self.yaw_rate, prev, 0.0)
        self.kin_rate = turn_rate(before, yaw_rate)
        self.yaw, self.yaw_rate = yaw, yaw_rate
        side_rate, drift = side_drift(ref, old, prev, msg.time, cfg.max_side_speed)
        if drift is not None:
            ref.set_side_rate(drift)
        slow, hop = hops(x, y, speed, old, prev, msg.time, cfg)
        ped_hop = pedestrian_hops(x, y, speed, old, prev, msg.time, old_kind)
        if interpolating:
            ref = self._interpolation(msg, rows, ids, a.flags[rows], cur, yaw_rate, old is not None, hop | ped_hop)
        self.newest = cur
        self._batch, self._time = a, msg.time
        if ids != self._ids or not np.array_equal(rows, self._row_of):  # (else the same map)
            self._rows = dict(zip(ids, rows.tolist()))
            self._ids, self._row_of = ids, rows
        return Sample(x, y, speed, yaw_rate, ref, side_rate, slow, hop, ped_hop)

    def _interpolation(self, msg: StepMessage, rows: np.ndarray, ids: list[str], flags: np.ndarray, cur: Reference,
                       yaw_rate: np.ndarray, have_prev: bool, hop: np.ndarray) -> Reference:
        """The reference over (previous step, this step]: each known agent's previous sample and
        path, reaching this step's sample at its end (SUMO's own motion, no guess); new,
        teleported or sideways-hopping (``hop``) agents follow their own sample shifted one
        step back."""
        L = float(msg.step_length)
        pb = self._batch if have_prev else None
        src = np.fromiter(map(self._rows.get, ids, repeat(-1)), np.int64, len(ids)) if pb is not None \
            else np.full(len(ids), -1, np.int64)
        known = (src >= 0) & ((flags & AgentFlag.JUMPED) == 0) & ~hop
        n_prev = pb.n if pb is not None else 0
        merged = stack_batches(pb, msg.agents)
        sel = np.where(known, src, n_prev + np.asarray(rows, np.int64))
        ref = Reference.from_batch(self._time if pb is not None else msg.time, merged, sel, yaw_rate)
        if known.any():
            guess = 0.5 * (ref.speed + cur.speed) * L
            s_end, lat_end, _ = ref.project_far(cur.x, cur.y, guess, iterations=PROJECT_ITERATIONS)
        else:
            s_end = lat_end = np.zeros(len(ids))
        ref.interpolate_to(L, known, s_end, cur.speed, cur.accel, lat_end)
        return ref


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
    "Sample", "Samples", "detect_jump", "detect_slide", "detect_spawn", "families", "hops", "pedestrian_hops",
    "pool_keys", "retyped", "side_drift", "unpack_pool_keys",
    "stack_batches", "stale", "yaw_rates",
]
