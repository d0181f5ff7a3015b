"""``Fleet``: the agents of the current SUMO step as aligned arrays; syncs them on each step, drives them each tick.

One object between the transport (``daemon``) and the world (``world``); the control
laws are ``control``'s, the references ``reference``'s, neither calls back here:

- ``apply_step(msg)``: sync the agent set with a ``StepMessage`` - spawn new agents at
  their SUMO pose and speed, park agents that left, place agents that SUMO teleported
  (JUMPED) or that diverged/flipped (each placement counted), rebuild the references.
- ``tick()``: observe (the world's state) -> control (controllers and vehicle limits for
  every agent at once, pure numpy) -> actuate (commands, kinematic placements) -> step
  (``substeps`` MuJoCo steps) -> tracking errors and contacts.
- ``snapshot()``: the ``PhysicsAgents`` columns for ``PhysicsState``.
- ``begin_stop()``: SUMO is gone: every agent brakes to rest along its last path.

Tracking errors (``err_lon``/``err_lat``) are measured for every mode against the same
reference: the front bumper of the SUMO trajectory extrapolated to the physics time
(``Reference.at``), so presets are comparable.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np

from physics_side import control as C
from physics_side import models as M
from physics_side.config import PhysicsSettings, Rates
from physics_side.faults import Faults
from physics_side.reference import Reference, ReferencePoint, tracking_error
from physics_side.world import PhysicsWorld
from protocol.frames import sumo_angle_to_yaw, wrap_pi, yaw_to_sumo_angle
from protocol.messages import AgentBatch, AgentClass, AgentFlag, AgentMode, PhysicsAgents, PhysicsFeedback, StepMessage

log = logging.getLogger(__name__)

P_PAPER, P_DEFAULT, P_KINEMATIC = 0, 1, 2
_PRESET_CODE = {"paper": P_PAPER, "default": P_DEFAULT, "kinematic": P_KINEMATIC}
_TYPE_NAME = {
    AgentClass.PASSENGER: "passenger", AgentClass.TAXI: "taxi", AgentClass.BUS: "bus",
    AgentClass.BICYCLE: "bicycle", AgentClass.PEDESTRIAN: "pedestrian", AgentClass.OTHER: "other",
}
GHOST_CLEAR_M = 0.3  # [m] a ghost spawn joins once its body is this far from every other body
JUMP_EXCUSE_S = 2.0  # [s] a collision this soon after SUMO teleported / jumped the agent is SUMO's
CARRY_SPEED = 0.5  # [m/s] below this SUMO speed a sideways slide is carried, not driven
BIKE_MAX_LEAN_DEG = 35.0  # [deg] bicycles (a rider's lean)
BIKE_LEAN_TARGET_TAN = 0.6  # [1] bicycles' stabiliser leans for at most tan(phi) = this (31 deg)
MOTORCYCLE_MAX_LEAN_DEG = 42.0  # [deg] motorcycles and mopeds: at their tyres' ~48 deg a lean transient reached 60
MAX_PENDING_COLLISIONS = 256  # physics-only collisions re-checked at the next sample (bounded)
MOTORCYCLE_MASS_KG = 150.0  # [kg] single-track models at least this heavy are motorcycles
PED_HOP_M = 0.5  # [m] a pedestrian's sample this much further than its speed takes it is a jump
RIDER_BACK_CLEAR_M = 0.3  # [m] a two-wheeler's way back must be this clear of every body (``_may_roll_back``)
SUMO_OVERLAP_M = 0.05  # [m] SUMO footprints this close count as SUMO's own collision
_BICYCLE_ROLL_STIFFNESS = M.default_spec(AgentClass.BICYCLE).roll_stiffness  # [N*m/rad] the stabiliser gains' reference
# A manoeuvre no vehicle of the agent's size can drive (a U-turn on a turnaround lane, a
# coach through a tight junction corner) is shown as SUMO has it, kinematic, until it is
# over: driven, the vehicle ran metres wide into its neighbours and was placed back
# (counted apart: ``carries_infeasible``). Seen on the path ahead: the heading change over
# INFEASIBLE_WINDOW_M (shorter windows take the corners of coarse lane shapes for curves no
# car can follow), for windows starting up to 1 s of travel ahead (within INFEASIBLE_AHEAD_M)
INFEASIBLE_WINDOW_M = 8.0  # [m]
INFEASIBLE_GRID_M = 2.0  # [m] spacing of the windows' starts
INFEASIBLE_AHEAD_M = (2.0, 20.0)  # [m]
INFEASIBLE_MARGIN = 0.9  # [1] a path this much tighter than the vehicle's reach starts a carry ...
INFEASIBLE_RELEASE = 0.75  # [1] ... which ends once the path ahead is within this share of it
INFEASIBLE_STRAIGHT_DEG = 10.0  # [deg] ... and SUMO's body angle is this close to the path's heading
# [deg] a vehicle SUMO inserts moving with its body angle this far off its path's heading is
# carried from its first step (its chord back to front where a curved lane meets a straight
# one: a truck inserted at 13 m/s 33 deg off the lane it drove along, placed on that angle,
# ran 3.8 m wide before it had turned onto its lane)
SPAWN_OFF_DEG = 20.0
# [1] ... and the path ahead (8 m windows) asks less than this share of the tyres' lateral acceleration
INFEASIBLE_GRIP_KEEP = 0.5
# Or seen in SUMO's turn rate: faster than INFEASIBLE_RATE_MARGIN x full lock at its speed
# (SUMO's angle is the chord back to front, which turns faster than the bumper's path
# entering a bend), moving faster than INFEASIBLE_MIN_SPEED [m/s], INFEASIBLE_OFF_M [m] off
INFEASIBLE_RATE_MARGIN = 1.5
INFEASIBLE_MIN_SPEED = 1.0
INFEASIBLE_OFF_M = 0.5
KIN_CURVATURE_M = 4.0  # [m] window of the path curvature carried bodies are placed turning at (``_kin_pose``)
KIN_GLIDE_MAX_M = 3.0  # [m] a carry starting further off SUMO's pose starts on it (no glide)
KIN_BLEND_S = 0.4  # [s] time constant of a carried body's glide from its driven pose onto SUMO's
# Between the samples of long (interpolated) steps a carry also starts for a turn beyond the
# tyres' grip at the step's speed: at 1 s steps SUMO takes junction corners at 13 m/s through
# 45-75 deg within one step (15-25 m/s^2 of lateral acceleration); driven, cars ran up to 9 m
# wide and were placed back. The demand v^2 * kappa of GRIP_WINDOW_K windows counts as a share
# of the lateral acceleration the tyres carry (``_a_lat``), against INFEASIBLE_MARGIN / _RELEASE.
# [grid steps] the grip check's windows are 4 m: over 8 m a bus's 26 deg corner of its lane's
# shape at 10.5 m/s looked like 0.7 of its grip; driven, it crabbed 20 deg off its lane into a bus
GRIP_WINDOW_K = 2
# At short steps the grip check covers heavy vehicles (those that steer their rear axle) at
# this share of their tyres' grip: a 7.1 m truck SUMO took through a 12 m junction turn at
# 8.5 m/s (5-9 m/s^2) steered to full lock, its body fell 17 deg behind SUMO's angle and
# its rear swung into a car. Cars at this share were carried on their approach to the
# demo's turns (its reference car tracked worse): they are carried only beyond CAR_GRIP_SHARE.
# Two-wheelers are carried (upright) beyond the lean their tyres and riders hold (``_a_lat``;
# motorcycles at MOTORCYCLE_GRIP_SHARE): SUMO takes bicycles through junction turns at
# 7-9 m/s^2 and its angle jumps there; driven, they fell over and were placed back. They are
# handed back only once SUMO turns them at less than GUARD_BIKE_RELEASE_ALAT (upright mid-arc,
# a motorcycle rolled to 54 deg).
HEAVY_GRIP_SHARE = 0.6
# Cars beyond their tyres' friction itself (INFEASIBLE_MARGIN x this share of the steering's
# A_LAT_SHARE of it: 12.6 of 12.75 m/s^2) over the 8 m windows: SUMO takes a curved lane (not
# a junction) at 13.4 m/s through 90 deg in 1.5 s (15 m/s^2); driven, a taxi steered at its
# grip's 11 deg, ran 6 m wide and was placed back. Below it cars stay driven (the demo's
# turns ask 4-7 m/s^2)
CAR_GRIP_SHARE = 1.2
# [m/s^2] ... at the least speed SUMO can brake them to before each window (its emergency
# deceleration; at their own speed cars were carried on their approach to the demo's turns)
CAR_GRIP_BRAKE = 9.0
# Motorcycles and mopeds drive SUMO's 9-10 m/s^2 junction turns leaning at their limit (within
# a metre of SUMO's track): they are carried only beyond this share of their lean's acceleration
MOTORCYCLE_GRIP_SHARE = 1.4
CHORD_FIX_MAX_DEG = 30.0  # [deg] a carried body's chord is turned onto SUMO's angle at the step's end within this
GRIP_SAT_LAT_M = 0.3  # [m] sideways off the path beyond which a vehicle at its tyres' limit gets no drive to catch up
# Contact guard: SUMO packs agents closer than any driven body keeps to its reference (a
# bicycle 0.2 m beside a car in the sublane model, a pedestrian 0.15 m from a passing
# motorcycle) and a two-wheeler leans its rider beyond SUMO's upright footprint. A pair of
# agents whose physics footprints come within GUARD_GAP_M (now, or GUARD_HORIZON_S ahead with
# their errors kept) where SUMO's footprints have a gap is carried (shown kinematic, gliding
# onto SUMO's poses; placed bodies do not touch each other) for at least GUARD_HOLD_S and
# until SUMO has them GUARD_KEEP_M apart; counted apart (``carries_contact``).
GUARD_GAP_M = 0.1  # [m]
GUARD_HORIZON_S = (0.3, 1.0)  # [s] look-ahead: at least the first, at least a step, at most the second
GUARD_HOLD_S = 1.0  # [s]
GUARD_KEEP_M = 0.3  # [m]
GUARD_BIKE_RELEASE_ALAT = 2.0  # [m/s^2] a carried two-wheeler (any carry) is handed back (upright) only below this of SUMO's turn
MAX_GUARD_PAIRS = 4096  # active guard pairs (bounded; more are not guarded, logged)


def _stack_batches(a, b):
    """The columns ``Reference.from_batch`` reads of batch ``a`` (or nothing) followed by ``b``."""
    from types import SimpleNamespace

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


def footprints_overlap(ax, ay, ah, al, aw, bx, by, bh, bl, bw, margin: float = 0.0) -> np.ndarray:
    """Do rectangles a and b (centre x, y [m], heading [rad], length, width [m]) overlap,
    each grown by ``margin`` [m]? Separating-axis test (``footprint_gap``), vectorised."""
    g = 2.0 * margin
    return footprint_gap(ax, ay, ah, np.asarray(al) + g, np.asarray(aw) + g,
                         bx, by, bh, np.asarray(bl) + g, np.asarray(bw) + g) <= 0.0


def footprint_gap(ax, ay, ah, al, aw, bx, by, bh, bl, bw) -> np.ndarray:
    """Separation [m] of rectangles a and b (centre x, y [m], heading [rad], length, width
    [m]) along the separating axis that parts them most: their distance where an edge faces the
    other (a lower bound corner to corner), negative where they overlap. Vectorised."""
    ca, sa, cb, sb = np.cos(ah), np.sin(ah), np.cos(bh), np.sin(bh)
    dx, dy = np.asarray(bx) - ax, np.asarray(by) - ay
    hal, haw, hbl, hbw = 0.5 * np.asarray(al), 0.5 * np.asarray(aw), 0.5 * np.asarray(bl), 0.5 * np.asarray(bw)
    gap = np.full(np.broadcast(dx, dy, ca, cb).shape, -np.inf)
    for ux, uy in ((ca, sa), (-sa, ca), (cb, sb), (-sb, cb)):
        ra = hal * np.abs(ca * ux + sa * uy) + haw * np.abs(-sa * ux + ca * uy)
        rb = hbl * np.abs(cb * ux + sb * uy) + hbw * np.abs(-sb * ux + cb * uy)
        gap = np.maximum(gap, np.abs(dx * ux + dy * uy) - ra - rb)
    return gap


def near_pairs(x: np.ndarray, y: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i < j) of discs (centre x, y, radius r [m]) that overlap. A grid of cells
    as wide as the largest disc: every disc against the discs of its own cell and of four of
    its eight neighbours (the other four see it), O(n log n + candidates); a sweep along x
    alone took every car of a north-south street as a candidate of every other."""
    n = len(x)
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    cell = max(2.0 * float(r.max()), 1e-3)
    gx, gy = np.floor(x / cell).astype(np.int64), np.floor(y / cell).astype(np.int64)
    gx -= gx.min()
    gy -= gy.min() - 1  # (a row below the lowest: the (1, -1) neighbour's key stays apart)
    rows = int(gy.max()) + 2
    key = gx * rows + gy
    order = np.argsort(key, kind="stable")
    ks = key[order]
    pos = np.arange(n)
    ii, jj = [], []
    for dx, dy in ((0, 0), (0, 1), (1, -1), (1, 0), (1, 1)):
        want = ks + dx * rows + dy
        lo = np.searchsorted(ks, want, side="left")
        hi = np.searchsorted(ks, want, side="right")
        if dx == 0 and dy == 0:
            lo = np.maximum(lo, pos + 1)  # (its own cell: the discs after it)
        cnt = np.maximum(hi - lo, 0)
        a = np.repeat(pos, cnt)
        b = np.repeat(lo, cnt) + np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        ii.append(order[a])
        jj.append(order[b])
    i, j = np.concatenate(ii), np.concatenate(jj)
    keep = np.hypot(x[i] - x[j], y[i] - y[j]) < r[i] + r[j]
    i, j = i[keep], j[keep]
    return np.minimum(i, j), np.maximum(i, j)


def _log_physics_only(t: float, agent: str) -> None:
    log.warning("t=%.2f s: %s collided in physics only (SUMO had a gap there)", t, agent)


@dataclass(frozen=True)
class _Pose:
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray


@dataclass(frozen=True)
class _Groups:
    """Which agents each part of a control tick handles; changes only with the agent set,
    the modes or the world's slot numbers, so it is built once per SUMO step, not per tick."""

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
    """Vehicles (commanded through ``command_vehicles``)."""
    veh_slots: np.ndarray
    all_veh: bool
    ped_idx: np.ndarray
    """Pedestrians under force control."""


@dataclass(frozen=True)
class _Commands:
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
    """Bicycle stabiliser torque [N*m] per vehicle (``_Groups.veh_idx``), None without bicycles."""
    ped: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    """Force x, y [N] and yaw torque [N*m] per pedestrian (``_Groups.ped_idx``)."""
    at: ReferencePoint | None
    """Reference point where kinematic agents and ``carry`` are placed (``Reference.at``), or None."""
    kin_yaw: np.ndarray | None
    """Body angle [rad] of kinematic agents (``Fleet._kin_pose``), or None."""
    carry: np.ndarray | None
    """Standing agents carried along SUMO's sideways slide (placed), or None."""
    rear: np.ndarray | None
    """Rear-axle angle [rad] per agent (vehicles that steer it), None when nobody does."""
    carry_yaw: np.ndarray | None = None
    """Body yaw [rad] per agent that ``carry`` keeps (its own at the tick's start)."""


@dataclass
class StepStats:
    """What ``apply_step`` did."""

    spawned: int = 0
    parked: int = 0
    jumped: int = 0
    diverged: int = 0
    flipped: int = 0
    skipped: int = 0
    retyped: int = 0


class Fleet:
    """Agents of the newest SUMO step, aligned arrays (see module docstring)."""

    def __init__(self, world: PhysicsWorld, settings: PhysicsSettings, rates: Rates):
        self.world = world
        self.cfg = settings.physics
        self.ctl = settings.control
        self.rates = rates
        self.dt = rates.control_dt
        self._warned_vclass: set[str] = set()
        self._vtypes: list = []
        self._reserved: set[int] = set()  # keys (class, vType, length, width) with a pool (``reserve``)
        # preset code per wire class (the config names presets per agent type)
        self._preset_lut = np.array(
            [_PRESET_CODE[self.cfg.preset_for(_TYPE_NAME[c])] for c in AgentClass], np.int8)
        self.counters: dict[str, int] = {
            "steps": 0, "placements_spawn": 0, "placements_jump": 0, "placements_divergence": 0,
            "placements_flip": 0, "resyncs": 0, "skipped_inside_vehicle": 0,
            "collisions_sumo_reported": 0, "collisions_physics_only": 0, "ghost_spawns": 0, "ghost_placements": 0, "ghost_sumo_overlaps": 0,
            "retyped": 0, "carries_infeasible": 0, "carried_infeasible_ms": 0,
            "carries_contact": 0, "carried_contact_ms": 0, "guard_pairs_dropped": 0,
        }
        self.wire_vtype = np.zeros(0, np.uint16)  # vType index per agent of the newest step
        self._empty()
        self.sumo_step = -1
        self.step_length = rates.ticks_per_step * rates.control_dt  # [s] of the newest SUMO step
        self.tick_count = 0
        self.stopping = False
        # two-way coupling: True in the one instance SUMO follows (the daemon sets it); there
        # agents flagged PHYSICS_AUTHORITY are never carried: physics drives them, SUMO follows
        self.two_way = False
        self.authoritative = np.zeros(0, bool)
        self.touching = np.zeros(0, bool)  # agents touching another agent's body at the last tick
        self.faults = Faults(self.cfg.stall, self.cfg.brake_failure)
        self._stalled: np.ndarray | None = None
        self._unbraked: np.ndarray | None = None

    def _empty(self) -> None:
        n = 0
        self.ids: list[str] = []
        self._index: dict[str, int] = {}
        self.slots = np.zeros(n, np.int64)
        self.wire_cls = np.zeros(n, np.uint8)
        self.preset = np.zeros(n, np.int8)
        self.mode = np.zeros(n, np.uint8)
        self.kind = np.zeros(n, np.int8)
        self.ref: Reference | None = None
        self._sample_ref: Reference | None = None
        self._prev_batch = None
        self._prev_rows: dict[str, int] = {}
        self._prev_time = 0.0
        self.ghost = np.zeros(0, bool)
        self.sumo_len = np.zeros(0)
        self.sumo_wid = np.zeros(0)
        self.jump_t = np.zeros(0)
        self.carry = np.zeros(0, bool)
        self.infeasible = np.zeros(0, bool)
        self.guarded = np.zeros(0, bool)  # carried, the carry started by the contact guard (``_contact_guard``)
        self._guard_pairs: dict[tuple[str, str], float] = {}  # guarded pair -> time [s] it was last near
        self.kin_off = np.zeros((0, 3))  # carried agents' offset from SUMO's pose at the start (x, y [m], yaw [rad])
        self.kin_age = np.zeros(0)  # [s] since the carry started
        self._sumo_yaw = self._sumo_yaw_rate = np.zeros(0)  # SUMO body angle [rad] and its rate [rad/s]
        self._kin_rate = np.zeros(0)  # [rad/s] kinematic bodies' turn rate between samples (``_kin_pose``)
        self._rolls_back = np.zeros(0, bool)  # who may roll back to its standing reference (``_may_roll_back``)
        self._chord_end: np.ndarray | None = None  # carried bodies' chord to SUMO's angle at the step's end [rad]
        self._pending_collisions: list[str] = []
        self.tau = 0.0
        self.state = C.ControlState.zeros(0)
        self.s_act = np.zeros(0)
        self.drive = np.zeros(0)
        self.brake = np.zeros(0)
        self.aux = np.zeros(0)
        self.err_lon = np.zeros(0)
        self.err_lat = np.zeros(0)
        self.stop_v0 = np.zeros(0)
        self.stop_t = 0.0
        self._gen = -1
        self._groups: _Groups | None = None
        self._cache = None
        self._last_obs = None

    @property
    def n(self) -> int:
        return len(self.ids)

    def interpolates(self, step_length: float) -> bool:
        """Does physics run one SUMO step behind, between the last two samples, for steps of
        ``step_length`` [s]? Extrapolating past the newest sample misses what SUMO decides
        within the step (a stop: (a_new - a_old) * step^2, 1.5 m at 0.5 s); interpolating
        costs one step of latency, which is small for short steps."""
        mode = self.cfg.reference
        return mode == "interpolate" or (mode == "auto" and step_length > self.cfg.interpolate_above_s + 1e-9)

    @property
    def interpolating(self) -> bool:
        """``interpolates`` for the newest step."""
        return self.interpolates(self.step_length)

    @property
    def lag(self) -> float:
        """How far physics time runs behind the newest SUMO step [s]: a step length when
        interpolating (the interval between the previous and the newest sample), else 0."""
        return self.step_length if self.interpolating else 0.0

    def _interpolation(self, msg: StepMessage, rows, ids, flags, cur: Reference, yaw_rate, have_prev: bool,
                       hop: np.ndarray):
        """The reference over (previous step, this step]: each known agent's previous sample and
        path, reaching this step's sample at its end (SUMO's own motion, no guess); new,
        teleported or sideways-hopping (``hop``) agents follow their own sample shifted one
        step back."""
        L = float(msg.step_length)
        pb = self._prev_batch if have_prev else None
        src = np.fromiter((self._prev_rows.get(i, -1) for i in ids), np.int64, len(ids)) if pb is not None \
            else np.full(len(ids), -1, np.int64)
        known = (src >= 0) & ((flags & AgentFlag.JUMPED) == 0) & ~hop
        n_prev = pb.n if pb is not None else 0
        merged = _stack_batches(pb, msg.agents)
        sel = np.where(known, src, n_prev + np.asarray(rows, np.int64))
        ref = Reference.from_batch(self._prev_time if pb is not None else msg.time, merged, sel, yaw_rate)
        if known.any():
            guess = 0.5 * (ref.speed + cur.speed) * L
            s_end, lat_end, _ = ref.project_far(cur.x, cur.y, guess, iterations=3)
        else:
            s_end = lat_end = np.zeros(len(ids))
        ref.interpolate_to(L, known, s_end, cur.speed, cur.accel, lat_end)
        return ref

    @property
    def max_extrapolation(self) -> float:
        """How far past the newest SUMO sample the reference is extrapolated [s]: a number
        of SUMO steps, so a late step at any step length is bridged alike."""
        return self.cfg.max_extrapolation_steps * self.step_length

    # ------------------------------------------------------------------ step sync

    def _families(self, cls: np.ndarray, vtype: np.ndarray, length: np.ndarray) -> list[str]:
        """Model family of each agent from its vType's vClass (the newest table SUMO sent)."""
        vt = self._vtypes
        out = []
        for c, t, L in zip(cls.tolist(), vtype.tolist(), length.tolist()):
            vclass = vt[t].vclass if t < len(vt) else ""
            out.append(M.family_for(c, vclass, L))
        if AgentClass.OTHER in cls:
            for c, t, f in zip(cls.tolist(), vtype.tolist(), out):
                vclass = vt[t].vclass if t < len(vt) else "?"
                if c == AgentClass.OTHER and vclass not in self._warned_vclass:
                    self._warned_vclass.add(vclass)
                    log.info("vClass %r has no wire class of its own: driven by the %s model", vclass, f)
        return out

    def reserve(self, agents: AgentBatch, vtypes: list | None = None) -> int:
        """Pools for every size in ``agents`` (e.g. a whole step, other shards' agents too),
        compiled in the background (``PhysicsWorld.reserve``); returns the new pools."""
        if vtypes is not None and list(vtypes) != self._vtypes:
            self._vtypes = list(vtypes)
            self._reserved.clear()  # vType indexes may mean other types now
        if agents.n == 0:
            return 0
        # one int64 per (class 8 bits, vType 16, length 20 and width 20 bits in mm): np.unique
        # of a 1-D array (~0.5 ms at 10,000 agents; of rows it was ~20 ms)
        mm = lambda v: np.clip(np.round(np.asarray(v, np.float64) * 1e3), 0, (1 << 20) - 1).astype(np.int64)  # noqa: E731
        key = ((np.asarray(agents.cls, np.int64) & 0xFF) << 56 | (np.asarray(agents.vtype, np.int64) & 0xFFFF) << 40
               | mm(agents.length) << 20 | mm(agents.width))
        todo = [k for k in np.unique(key).tolist() if k not in self._reserved]
        if not todo:
            return 0
        self._reserved.update(todo)
        u = np.asarray(todo, np.int64)
        length, width = ((u >> 20) & 0xFFFFF) / 1e3, (u & 0xFFFFF) / 1e3
        fam = self._families(u >> 56, (u >> 40) & 0xFFFF, length)
        return self.world.reserve(zip(fam, length, width))

    def apply_step(self, msg: StepMessage, resync: bool = False, tau: float = 0.0) -> StepStats:
        """Sync with a SUMO step (see module docstring). ``resync`` after a SUMO restart;
        ``tau`` [s]: how far physics time is past the step's time (steps shorter than a
        control tick, realtime jitter): placements and errors use the reference then."""
        self._cache = None
        self._last_obs = None
        old_ref = self._sample_ref
        w = self.world
        a = msg.agents
        st = StepStats()
        self.step_length = float(msg.step_length)
        rows = np.flatnonzero((a.flags & AgentFlag.INSIDE_VEHICLE) == 0)
        st.skipped = a.n - len(rows)
        self.counters["skipped_inside_vehicle"] += st.skipped
        ids = [a.ids[i] for i in rows]
        cls = a.cls[rows]
        flags = a.flags[rows]
        if msg.vtypes is not None:  # a step carries the table only when it changed (SPEC 3.1)
            self._vtypes = list(msg.vtypes)
        preset = self._preset_lut[cls]
        ego = (flags & AgentFlag.EGO) != 0

        # leave: agents of the previous step missing now
        new_set = set(ids)
        gone = [aid for aid in self.ids if aid not in new_set]
        if gone:
            w.park(w.slot_of(gone))
            st.parked = len(gone)
        # previous sample of each agent (yaw rate, sideways jumps, controller state); a
        # resync or a clock that went back (a new SUMO run) has no usable previous sample
        prev = np.fromiter((self._index.get(aid, -1) for aid in ids), np.int64, len(ids))
        # a vType change (vehicle.setType, a size of its own): leave and spawn anew in the
        # model and pool of the new type (indexes of unchanged types never change)
        had = prev >= 0
        vtype = a.vtype[rows]
        if had.any() and len(self.wire_vtype) == len(self._index) == len(self.wire_cls):
            p0 = np.maximum(prev, 0)
            retyped = np.flatnonzero(had & ((self.wire_vtype[p0] != vtype) | (self.wire_cls[p0] != cls)))
            if len(retyped):
                w.park(w.slot_of([ids[i] for i in retyped]))
                prev[retyped] = -1
                st.retyped = len(retyped)
                self.counters["retyped"] += len(retyped)
        gap_max = max(1.0, 2.5 * msg.step_length)  # [s] beyond this the previous sample is stale
        if resync or (old_ref is not None and not 0.0 < msg.time - old_ref.t_k < gap_max):
            old_ref = None
            prev[:] = -1
        x, y = a.x[rows], a.y[rows]
        yaw = sumo_angle_to_yaw(a.angle[rows])
        yaw_rate = np.zeros(len(ids))
        if old_ref is not None and len(ids):
            had = prev >= 0
            yaw_rate[had] = wrap_pi(yaw[had] - old_ref.yaw[prev[had]]) / (msg.time - old_ref.t_k)
        ref = cur = Reference.from_batch(msg.time, a, rows if st.skipped else None, yaw_rate)
        # kinematic bodies turn on between samples at the rate SUMO kept over its last two
        # steps: a one-step jump of its angle (a sublane move's start: 3.4 deg in 0.05 s at
        # 1.3 m/s) carried on for a step swung a carried 16.5 m trailer's rear 0.7 m sideways
        before = np.zeros(len(ids))
        if old_ref is not None and len(self._sumo_yaw_rate) and len(ids):
            had = prev >= 0
            before[had] = self._sumo_yaw_rate[prev[had]]
        self._kin_rate = np.where(before * yaw_rate > 0.0, np.sign(yaw_rate) * np.minimum(np.abs(before), np.abs(yaw_rate)), 0.0)
        self._sumo_yaw, self._sumo_yaw_rate = yaw, yaw_rate
        self._chord_end = None
        side_rate = np.zeros(len(ids))
        if old_ref is not None and bool((prev >= 0).any()):  # (the previous step may have had no agents)
            had = prev >= 0
            p0 = np.maximum(prev, 0)
            gap = msg.time - old_ref.t_k
            # SUMO's sideways motion off its lane's centre line (continuous lane change); a
            # hop, or the step where the lane switches (the offset flips sides), is no drift
            side = (ref.side_offset - old_ref.side_offset[p0]) / gap
            side_rate = np.where(had & (np.abs(side) < self.cfg.max_side_speed), side, 0.0)
            # a sample that came back onto its lane's centre line has ended its lane change
            # there (SUMO stops it on the line; its offset's sign is rounding): no drift past
            # it (a car ran a whole step's drift, 0.18 m, beyond its new lane's centre)
            arrived = np.abs(ref.side_offset) < 0.25 * np.abs(side_rate) * gap
            ref.set_side_rate(np.where(arrived, 0.0, side_rate))
        # SUMO moves a slow vehicle sideways at once when it changes lanes without a
        # lane-change duration (queues at junctions) or parks off the lane (a bus bay): no
        # vehicle can drive that without hitting its neighbours, so it is placed like a
        # teleport (counted as a jump), at its new pose also when interpolating. At long steps a
        # hop is beyond max_side_speed over the step: 1.3 m in a 1 s step is a slow lane change
        # (carried along it below); placed as a hop, a bus in Hamburg was 1.1 m off SUMO
        slow = hop = np.zeros(len(ids), bool)
        if self.cfg.sideways_jump_m > 0 and old_ref is not None and old_ref.n and len(ids):
            p0 = np.maximum(prev, 0)
            vmax = self.cfg.sideways_jump_speed
            slow = (prev >= 0) & (old_ref.speed[p0] < vmax) & (a.speed[rows] < vmax)
            if slow.any():
                _, side = tracking_error(x, y, _Pose(old_ref.x[p0], old_ref.y[p0], old_ref.yaw[p0]))
                reach = max(self.cfg.sideways_jump_m, self.cfg.max_side_speed * (msg.time - old_ref.t_k))
                hop = slow & (np.abs(side) > reach)
        # a pedestrian SUMO moves further than it walks (onto a walking area or crossing: 1.3 m
        # in one 0.1 s step) is placed there: running after it, one ran into a bus; followed
        # between samples as motion, one ran 3.5 m past its crossing's entry
        ped_hop = np.zeros(len(ids), bool)
        if old_ref is not None and old_ref.n and len(ids) and len(self.kind):
            p0 = np.maximum(prev, 0)
            moved = np.hypot(x - old_ref.x[p0], y - old_ref.y[p0])
            reach = np.maximum(old_ref.speed[p0], a.speed[rows]) * (msg.time - old_ref.t_k) + PED_HOP_M
            ped_hop = (prev >= 0) & (self.kind[p0] == M.KIND_PED) & (moved > reach)
        if self.interpolating:
            ref = self._interpolation(msg, rows, ids, flags, cur, yaw_rate, old_ref is not None, hop | ped_hop)
        self._sample_ref = cur
        self._prev_batch, self._prev_time = a, msg.time
        self._prev_rows = {aid: int(r) for aid, r in zip(ids, rows)}

        slots = w.slot_of(ids)
        new = np.flatnonzero(slots < 0)
        if len(new):
            fam = self._families(cls[new], a.vtype[rows[new]], a.length[rows[new]])
            pools = np.array([w.pool_for(f, float(a.length[rows[i]]), float(a.width[rows[i]]))
                              for f, i in zip(fam, new)])
            gen = w.generation
            new_slots = w.allocate([ids[i] for i in new], pools, x[new], y[new])
            if w.generation != gen:  # the model grew: every slot number changed
                slots = w.slot_of(ids)
            else:
                slots[new] = new_slots
            st.spawned = len(new)
        self.ids = ids
        self._index = {aid: i for i, aid in enumerate(ids)}
        self.wire_vtype = vtype.astype(np.uint16)
        self.slots = slots
        self.wire_cls = cls.astype(np.uint8)
        self.kind = w.tables.kind[slots].astype(np.int8)
        self.authoritative = ((flags & AgentFlag.PHYSICS_AUTHORITY) != 0) & self.two_way
        self.touching = np.zeros(len(ids), bool)
        self._stalled = self.faults.stalled(self._index, len(ids), msg.time)
        self._unbraked = self.faults.unbraked(self._index, len(ids), msg.time)
        self.preset = preset
        mode = np.where(preset == P_KINEMATIC, AgentMode.KINEMATIC, AgentMode.PHYSICAL)
        self.mode = np.where(ego, AgentMode.EXTERNAL, mode).astype(np.uint8)
        self.ref = ref
        self.tau = max(0.0, float(tau))
        self.state = self.state.take(prev)
        self.stopping = False
        self._params()

        # placements: new agents, teleported agents, diverged or flipped physical agents
        obs = w.observe(slots)
        held = (ref.at(min(self.tau, self.max_extrapolation)) if self.tau > 0 or self.interpolating
                else ref.held())
        e_lon, e_lat = tracking_error(obs.fx, obs.fy, held)
        dist = np.hypot(e_lon, e_lat)
        self.sumo_len = a.length[rows].astype(np.float64)
        self.sumo_wid = a.width[rows].astype(np.float64)
        self._carry_infeasible(ref, prev, yaw_rate, dist, obs, held)
        self._rolls_back = self._may_roll_back(obs, held, e_lon)
        physical = self.mode == AgentMode.PHYSICAL
        is_new = np.zeros(len(ids), bool)
        is_new[new] = True
        jumped = ((flags & AgentFlag.JUMPED) != 0) & ~is_new & physical
        jumped |= ped_hop & ~is_new & physical
        # A slow vehicle's sideways hop (above) is placed like a teleport (counted as a jump);
        # faster lane changes are driven (the paper's error peaks at lane changes) ...
        carry = np.zeros(len(ids), bool)
        if slow.any():
            # ... or slides sideways while (nearly) standing (a continuous lane change in a
            # queue): once it is further off than a car can make up by driving, placed too
            sliding = slow & (np.abs(side_rate) > 0.05) & (np.abs(e_lat) > self.cfg.sideways_slide_m)
            jumped |= (hop | sliding) & ~is_new & physical
            # a standing vehicle that SUMO slides sideways cannot drive it at all: it is carried
            # along SUMO's slide every tick (one placement per slide, counted as a jump) instead
            # of lagging up to sideways_slide_m behind and being placed then
            _, shift = tracking_error(x, y, _Pose(old_ref.x[p0], old_ref.y[p0], old_ref.yaw[p0]))
            gap = max(msg.time - old_ref.t_k, 1e-9)
            carry = (slow & (old_ref.speed[p0] < CARRY_SPEED) & (a.speed[rows] < CARRY_SPEED)
                     & (np.abs(shift) > 0.05 * gap) & ~jumped & ~is_new & physical & (self.kind != M.KIND_PED))
        was_carried = np.zeros(len(ids), bool)
        if len(self.carry) and (prev >= 0).any():
            was_carried = (prev >= 0) & self.carry[np.maximum(prev, 0)]
        if slow.any():
            # a slide starts only when the sample moves off its lane's centre line: a vehicle
            # pulling away into a junction turn moves its bumper sideways of its old heading
            # along the lane (0.008 m at 0.26 m/s in the first 0.1 s step) and was carried, i.e.
            # placed in the steady-turn pose of the lane's sharpest bend, 60 deg off SUMO's
            # angle; a slide under way continues through the step where the lane switches
            carry &= was_carried | (np.abs(side_rate) > 0.05)
            if ref.interpolated is not None:
                # between the samples of long steps also a slow vehicle that SUMO moves sideways off
                # its path further than it can drive over its travel in the step (a lane change's
                # S of curvature at its reach covers reach * travel^2 / 4): a bus stopping from
                # 1.3 m/s that SUMO moved 0.9 m sideways stood still, 1.4 m off at the next sample
                lat = np.abs(ref.side_rate) * self.step_length
                travel = ref.step_speed * self.step_length
                carry |= (slow & ref.interpolated & (lat > self.cfg.sideways_slide_m)
                          & (lat > 0.25 * self._reach() * travel * travel)
                          & ~jumped & ~is_new & physical & (self.kind != M.KIND_PED))
        jumped |= carry & ~was_carried
        self.carry = carry
        flip = math.radians(self.cfg.flip_deg)
        flipped = ~is_new & ~jumped & ~carry & physical & ((np.abs(obs.roll) > flip) | (np.abs(obs.pitch) > flip))
        diverged = ~is_new & ~jumped & ~carry & ~flipped & physical & (dist > self.cfg.divergence_m)
        place = is_new | jumped | flipped | diverged
        if place.any():
            idx = np.flatnonzero(place)
            slide = carry[idx]  # a slide's start: placed as it stands
            if slide.any():
                self._place_slide(idx[slide], held, obs.yaw, count=True)
            self._place(idx[~slide], held, count=True)
            self.state.integ[idx] = 0.0
            e_lon[idx] = 0.0
        st.jumped, st.diverged, st.flipped = int(jumped.sum()), int(diverged.sum()), int(flipped.sum())
        self.counters["placements_spawn"] += len(new)
        self.counters["placements_jump"] += st.jumped
        self.counters["placements_divergence"] += st.diverged
        self.counters["placements_flip"] += st.flipped
        if st.diverged or st.flipped:
            log.warning("step %d: placed %d diverged %s, %d flipped %s", msg.step, st.diverged,
                        [self.ids[i] for i in np.flatnonzero(diverged)][:10], st.flipped,
                        [self.ids[i] for i in np.flatnonzero(flipped)][:10])
        # along-path position of each bumper on the new path (guess for the projection)
        # (``obs`` predates the placements: placed agents sit exactly at s = 0)
        placed_obs = w.observe(slots) if place.any() else obs  # (also the first tick's start state)
        self._update_ghosts(placed_obs, is_new, place, prev)
        self.jump_t = np.where(prev >= 0, self.jump_t[np.maximum(prev, 0)] if len(self.jump_t) else -np.inf, -np.inf)
        self.jump_t[jumped | ((flags & AgentFlag.JUMPED) != 0)] = msg.time
        if self._pending_collisions:
            self._recheck_collisions()
        self.s_act = (np.where(place, held.s, ref.project_far(obs.fx, obs.fy, held.s + e_lon, tau=self.tau)[0]) if len(ids)
                      else e_lon.copy())
        n = len(ids)
        self.drive = np.zeros(n)
        self.brake = np.zeros(n)
        self.aux = np.zeros(n)
        self.err_lon = np.where(place, 0.0, e_lon)
        self.err_lat = np.where(place, 0.0, e_lat)
        self.sumo_step = msg.step
        # the first tick starts from the state after the placements
        self._cache = (placed_obs, None)
        self.counters["steps"] += 1
        if resync:
            self.counters["resyncs"] += 1
        return st

    def _update_ghosts(self, obs, is_new: np.ndarray, placed: np.ndarray, prev: np.ndarray) -> None:
        """Bodies placed into an occupied spot stay ghosts (no agent contact) until they are clear.

        An agent placed this step (``placed``: spawned, or put on SUMO's pose after a jump,
        a divergence, a flip or a slide's start; ``obs`` is the state after the placements)
        whose footprint overlaps a live body (or one placed before it this step) becomes a
        ghost: a motorcycle standing 2.1 m past its stop and 19 deg off was put on SUMO's
        pose as it stood, its rear into a bicycle queued beside it. A ghost whose footprint
        is ``GHOST_CLEAR_M`` clear of every other body joins again. Pedestrian pairs are
        never checked (their bodies do not touch each other)."""
        n = self.n
        old = self.ghost[np.maximum(prev, 0)] if len(self.ghost) else np.zeros(n, bool)
        ghost = np.where(prev >= 0, old, False) & ~is_new
        if n == 0:
            self.ghost = ghost
            return
        t_ = self.world.tables
        L, W = t_.length[self.slots], t_.width[self.slots]
        yaw = obs.yaw
        cx, cy = obs.fx - 0.5 * L * np.cos(yaw), obs.fy - 0.5 * L * np.sin(yaw)
        ped = self.kind == M.KIND_PED
        idx = np.arange(n)
        fresh = np.zeros(n, bool)
        for i in np.flatnonzero(placed):
            other = (idx != i) & (~placed | (idx < i)) & ~ghost & ~(ped & ped[i])
            if other.any() and footprints_overlap(cx[i], cy[i], yaw[i], L[i], W[i], cx[other], cy[other],
                                                  yaw[other], L[other], W[other]).any():
                ghost[i] = fresh[i] = True
        for i in np.flatnonzero(ghost & ~fresh):
            other = (idx != i) & ~ghost & ~(ped & ped[i])
            if not (other.any() and footprints_overlap(cx[i], cy[i], yaw[i], L[i], W[i], cx[other], cy[other],
                                                       yaw[other], L[other], W[other], GHOST_CLEAR_M).any()):
                ghost[i] = False
        self.ghost = ghost
        self._set_bits()  # every step: a recompile resets the bits, and the modes change
        self.counters["ghost_spawns"] += int((fresh & is_new).sum())
        self.counters["ghost_placements"] += int((fresh & ~is_new).sum())

    def _set_bits(self) -> None:
        """The world's collision bits of every agent: ghosts, and bodies placed every tick."""
        placed = (self.mode == AgentMode.KINEMATIC) | (self.mode == AgentMode.EXTERNAL)
        self.world.set_ghost(self.slots, self.ghost, placed)

    def _sumo_overlaps(self, idx: np.ndarray, h) -> np.ndarray:
        """Whether each agent of ``idx`` overlaps another agent in SUMO's footprints of sample ``h``."""
        cx = h.x - 0.5 * self.sumo_len * np.cos(h.yaw)
        cy = h.y - 0.5 * self.sumo_len * np.sin(h.yaw)
        ped = self.kind == M.KIND_PED
        every = np.arange(self.n)
        out = np.zeros(len(idx), bool)
        for k, i in enumerate(idx):  # (only agents that touched: a handful per step)
            other = (every != i) & ~(ped & ped[i])
            out[k] = bool(other.any() and footprints_overlap(
                cx[i], cy[i], h.yaw[i], self.sumo_len[i], self.sumo_wid[i], cx[other], cy[other], h.yaw[other],
                self.sumo_len[other], self.sumo_wid[other], SUMO_OVERLAP_M).any())
        return out

    def _split_collisions(self, began: np.ndarray) -> None:
        """Count collisions that began: SUMO also had them (its footprints overlap there,
        or the agent was teleported / jumped in the last ``JUMP_EXCUSE_S``) or physics only.
        A contact between two samples is SUMO's when its footprints overlap at either: one
        counted physics-only now moves over if they overlap at the next sample
        (``_recheck_collisions``)."""
        t = self.ref.t_k
        idx = np.flatnonzero(began)
        sumo = ((t - self.jump_t[idx]) <= JUMP_EXCUSE_S) | self._sumo_overlaps(idx, self.ref.held())
        later = self._sample_ref is not self.ref  # interpolating: the interval's end sample is known
        if later:
            sumo |= self._sumo_overlaps(idx, self._sample_ref.held())
        self.counters["collisions_sumo_reported"] += int(sumo.sum())
        self.counters["collisions_physics_only"] += int((~sumo).sum())
        self._ghost_sumo_overlaps(idx[sumo])
        for i in idx[~sumo]:
            if not later and len(self._pending_collisions) < MAX_PENDING_COLLISIONS:
                self._pending_collisions.append(self.ids[i])  # told at the next sample (_recheck_collisions)
            else:
                _log_physics_only(t, self.ids[i])

    def _ghost_sumo_overlaps(self, idx: np.ndarray) -> None:
        """Agents touching where SUMO has them overlap pass through each other as in SUMO (ghosts
        until clear, ``_update_ghosts``): pushing them apart knocked them into third agents."""
        if len(idx):
            self.ghost = self.ghost.copy()
            self.ghost[idx] = True
            self._set_bits()
            self.counters["ghost_sumo_overlaps"] += len(idx)

    def _recheck_collisions(self) -> None:
        """At a new sample: physics-only collisions of the last interval whose agents overlap in
        SUMO's footprints now were SUMO's (it moved them into each other between its samples)."""
        pending, self._pending_collisions = self._pending_collisions, []
        idx = np.array([self._index[a] for a in pending if a in self._index], np.int64)
        for a in pending:
            if a not in self._index:  # left SUMO at this sample: stays physics only
                _log_physics_only(self._sample_ref.t_k, a)
        if not len(idx):
            return
        overlap = self._sumo_overlaps(idx, self._sample_ref.held())
        moved = int(overlap.sum())
        self._ghost_sumo_overlaps(idx[overlap])
        if moved:
            self.counters["collisions_physics_only"] -= moved
            self.counters["collisions_sumo_reported"] += moved
            log.info("%d collision(s) of the last interval were SUMO's: its footprints overlap at t=%.2f s",
                     moved, self._sample_ref.t_k)
        for i in idx[~overlap]:
            _log_physics_only(self._sample_ref.t_k, self.ids[i])

    def _place_slide(self, idx: np.ndarray, at, yaw: np.ndarray, count: bool) -> None:
        """Place standing agents ``idx`` that SUMO slides sideways at ``at`` as they stand (body
        ``yaw``, full length), wheels straight: in the steady-turn pose of a bend at the bumper a
        stopped 6.5 m van turned 11 deg, its rear into passing traffic; on SUMO's angle (which
        turns with the lane change, 38 deg while standing) a car's rear swung into the next lane."""
        self._place(idx, replace(at, curvature=np.zeros_like(at.curvature)), count=count, steady_turn=False, yaw=yaw)

    def _place(self, idx: np.ndarray, at, count: bool, steady_turn: bool = True,
               yaw: np.ndarray | None = None) -> None:
        """Place agents ``idx`` at reference point ``at`` (full-length arrays); ``yaw``
        (full length) replaces ``at.yaw`` as the body angle of a kinematic placement."""
        # physical placements: the steady-turn pose for the path tangent; kinematic ones:
        # SUMO's own body angle (the direct representation)
        if yaw is None:
            yaw = at.tangent if steady_turn else at.yaw
        if steady_turn:
            # a standing vehicle stands on SUMO's angle, wheels straight: in the steady-turn pose of
            # a bend that starts at its bumper, a car inserted standing there stood 37 deg off
            still = at.speed[idx] < CARRY_SPEED
            if still.any():
                s_ = idx[still]
                self.world.place(self.slots[s_], at.x[s_], at.y[s_], at.yaw[s_], at.speed[s_], None,
                                 steady_turn=False, count=count)
                idx = idx[~still]
        if steady_turn and len(self._rear_idx):
            # a vehicle that steers its rear axle is placed on SUMO's chord, as it drives
            rear = self._max_rear[idx] > 0
            if rear.any():
                r = idx[rear]
                self.world.place(self.slots[r], at.x[r], at.y[r], at.yaw[r], at.speed[r], at.curvature[r],
                                 steady_turn=False, count=count)
                idx = idx[~rear]
        self.world.place(
            self.slots[idx], at.x[idx], at.y[idx], yaw[idx], at.speed[idx], at.curvature[idx],
            steady_turn=steady_turn, count=count,
        )

    def _params(self) -> None:
        t = self.world.tables
        s = self.slots
        ped = self.kind == M.KIND_PED
        wb = np.where(ped, 1.0, t.wheelbase[s])
        self.params = C.VehicleParams(
            wheelbase=wb, d_bumper=np.where(ped, 1.0, t.front[s] - t.rear_axle[s]),
            rear_axle=t.rear_axle[s], front_offset=t.front[s], m_eff=t.m_eff[s],
            r_wheel=np.where(ped, 1.0, t.r_wheel[s]), max_steer=t.max_steer[s],
            max_drive=t.max_drive[s], max_brake=t.max_brake[s], max_rear=t.max_rsteer[s],
        )
        self.mass = t.mass[s]
        self.stab_max = t.stab_max[s]
        # the configured stabiliser gains are the default bicycle's: a heavier or lower
        # two-wheeler gets them in proportion to gravity's toppling stiffness (280 kg
        # motorcycles were hardly stiffer than gravity and fell out of turns)
        self._stab_gain = t.roll_stiffness[s] / _BICYCLE_ROLL_STIFFNESS
        self._max_rear = t.max_rsteer[s]
        self._rear_idx = np.flatnonzero(self._max_rear > 0)
        # [m/s^2] lateral acceleration the tyres carry; two-wheelers also lean no further than
        # BIKE_MAX_LEAN_DEG / MOTORCYCLE_MAX_LEAN_DEG (SUMO's bicycles take junction turns at
        # 5-6 m/s: at the tyres' limit the stabiliser asked for 50-65 deg of lean and they fell)
        a_lat = C.lateral_accel_limit(t.tyre_mu[s])
        lean = np.radians(np.where(t.mass[s] < MOTORCYCLE_MASS_KG, BIKE_MAX_LEAN_DEG, MOTORCYCLE_MAX_LEAN_DEG))
        self._a_lat = np.where(self.kind == M.KIND_BIKE, np.minimum(a_lat, C.G * np.tan(lean)), a_lat)
        # drive torque the driven wheels carry (four-wheeled vehicles; inf for the others)
        self._grip_torque = C.drive_grip_torque(t.drive_grip[s], t.r_wheel[s])
        self._any_grip = bool(np.isfinite(self._grip_torque).any())
        self._any_bike = bool(np.any(self.kind == M.KIND_BIKE))
        # share of the tyres' grip (or the lean's) beyond which a turn is carried at short steps
        # (``_path_tightness``): heavy vehicles, two-wheelers; 0 = not checked
        bike = self.kind == M.KIND_BIKE
        car = (self.kind == M.KIND_CAR) & (t.max_rsteer[s] <= 0)
        self._short_grip_share = np.where(
            t.max_rsteer[s] > 0, HEAVY_GRIP_SHARE,
            np.where(bike, np.where(t.mass[s] < MOTORCYCLE_MASS_KG, 1.0, MOTORCYCLE_GRIP_SHARE),
                     np.where(car, CAR_GRIP_SHARE, 0.0)))
        self._any_short_grip = bool(np.any(self._short_grip_share > 0))
        self._grip_brake = np.where(car, CAR_GRIP_BRAKE, 0.0)
        self._gen = self.world.generation
        self._groups = None
        p = self.params
        self._reach_c = C.bumper_curvature_limit(p.wheelbase, p.d_bumper, p.max_steer, None)

    def _reach(self) -> np.ndarray:
        """Tightest path curvature [1/m] each vehicle's bumper follows when driven: its front
        steering's (``bumper_curvature_limit``); a steered rear axle keeps a long body on
        SUMO's chord rather than turning it tighter (a truck released at 75 % of its
        four-wheel-steered limit ran 6 m wide). Computed with the agents' parameters (``_params``)."""
        return self._reach_c

    def _path_tightness(self, ref: Reference, roll: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Each vehicle's tightest path ahead as a share of its reach (``_reach``), and the
        largest lateral acceleration [m/s^2] its path's 8 m windows ahead ask at its speed
        (cars at short steps: at the least speed SUMO can brake them to). The reach's share is the mean
        curvature of 8 m windows starting up to 1 s of travel ahead. Between the samples of
        long steps also as a share of its tyres' grip at the step's speed (see above); at
        short steps as a share of ``_short_grip_share`` of it (heavy vehicles, two-wheelers,
        cars beyond their tyres' friction). One path evaluation per SUMO step: headings every
        INFEASIBLE_GRID_M, windows by index offset."""
        k = int(round(INFEASIBLE_WINDOW_M / INFEASIBLE_GRID_M))
        grid = np.arange(0.0, INFEASIBLE_AHEAD_M[1] + INFEASIBLE_WINDOW_M + 1e-9, INFEASIBLE_GRID_M)[:, None]
        h = ref.path.at(np.broadcast_to(grid, (len(grid), self.n))).heading
        kappa = np.abs(wrap_pi(h[k:] - h[:-k])) / INFEASIBLE_WINDOW_M
        v = np.maximum(ref.speed, 0.0)
        if self.interpolating:
            v = np.maximum(v, ref.step_speed)
        ahead = np.clip(v, *INFEASIBLE_AHEAD_M)
        tight = np.where(grid[:-k] <= ahead, kappa, 0.0).max(axis=0) / self._reach()
        # over the 8 m windows, at short steps at the least speed SUMO can brake a car to by
        # each window (a lane shape's 15 deg corner within 4 m asked 12.6 m/s^2 at 14 m/s:
        # carried for 0.3 s, a van was handed back steering into it and spun)
        v2 = v * v - (0.0 if self.interpolating else 2.0 * self._grip_brake * grid[:-k])
        sustained = np.where(grid[:-k] <= ahead, kappa * np.maximum(v2, 0.0), 0.0).max(axis=0)
        if self.interpolating or self._any_short_grip:
            kg = GRIP_WINDOW_K
            kap = wrap_pi(h[kg:] - h[:-kg]) / (kg * INFEASIBLE_GRID_M)  # (+ left)
            demand = np.where(grid[:-kg] <= ahead, kap, 0.0) * v * v  # [m/s^2] + left
            grip = np.abs(demand).max(axis=0) / self._a_lat
            if not self.interpolating and roll is not None and self._any_bike:
                # a two-wheeler leaning one way into a turn the other way swings its lean across
                # both: SUMO's S through a junction (left at 4 m/s, then right at 8-9 m/s^2 at 8
                # m/s) flipped a motorcycle still leaning 28 deg into the left part
                lean = -C.G * np.tan(np.clip(roll, -1.0, 1.0))  # [m/s^2] + left (roll < 0: leaning left)
                swing = np.abs(demand - lean).max(axis=0) / self._a_lat
                grip = np.where(self.kind == M.KIND_BIKE, np.maximum(grip, swing), grip)
            if not self.interpolating:  # short steps: at each vehicle's share
                share = self._short_grip_share
                grip = np.where(share > 0, grip / np.maximum(share, 1e-9), 0.0)
                grip = np.where(self._grip_brake > 0, sustained / (self._a_lat * CAR_GRIP_SHARE), grip)
            tight = np.maximum(tight, grip)
        return tight, sustained

    def _kin_pose(self, at: ReferencePoint, tau: float) -> tuple[np.ndarray, ReferencePoint]:
        """Body angle [rad] of kinematic agents placed at ``at`` (``tau`` [s] past the sample),
        and ``at`` with the curvature they are placed turning at.

        At short steps: SUMO's own angle turning at its rate between its samples (not the
        path's heading at the bumper: a corner of a coarse lane shape right at the bumper swung
        a carried car's body 19 deg off SUMO's angle for one step, into its neighbours). Between
        the samples of long steps SUMO's angle at either sample may be far off the interpolated
        path (a 65 deg corner taken within one step): the chord from the body's back to its
        bumper on the interpolated path, SUMO's own definition of the angle, straight back
        along SUMO's angle at the step's start where the back is behind the path's start. It
        turns at the chord's own rate (curvature cross(d, u_front - u_back) / |d|^2 for the
        chord d and the path's unit tangents at both ends): placed turning at the curvature of
        a lane shape's corner at the bumper, a released car kept spinning (90 deg off, rolling
        backwards). The straight back is not SUMO's back on its lanes: the chord's difference
        from SUMO's angle at the step's end sample is added in proportion to the time (a
        carried bus's chord was 7 deg off SUMO's angle there, its rear 1.4 m into the next lane)."""
        ref = self.ref
        rate = ref.yaw_rate if self.interpolating else self._kin_rate  # (interpolating: the next sample's known)
        sumo = wrap_pi(ref.yaw + rate * min(tau, self.step_length))
        # placed turning at the path's mean curvature over KIN_CURVATURE_M around the bumper:
        # at a lane shape's corner the curvature right there is a spike (a carried van was
        # handed back steering 36 deg against its turn at 7 m/s, spun 30 deg off and was
        # placed back 5.9 m behind)
        h = ref.path.at(at.s + np.array([[-0.5], [0.5]]) * KIN_CURVATURE_M).heading
        kappa = wrap_pi(h[1] - h[0]) / KIN_CURVATURE_M
        if not self.interpolating:
            # ... and no tighter than its tyres carry at its speed: placed turning at a lane
            # shape's corner at 14 m/s (a trailer's wheels at 37 deg), vans and trailers handed
            # back there spun round and were placed back 6 m behind
            lim = np.where(self.kind == M.KIND_PED, np.inf, self._a_lat / np.maximum(at.speed, 1.0) ** 2)
            # ... and neither against nor faster than SUMO's own turn of the body: in an S the
            # bumper's path turns one way while a long body's chord still turns the other (a
            # trailer placed turning right at its bumper's 1 rad/s while its chord turned left
            # was handed back spinning and placed), and a van placed turning at its bumper's
            # path in a junction turn, faster than SUMO turned it, was handed back over-rotating
            # and fell 4 m behind. Bodies kinematic by preset (never handed back) turn at SUMO's
            # rate; carried ones where it turns the same way as their bumper's path at the slower
            # of both (at SUMO's rate everywhere, buses handed back after a turn with their
            # chord still turning lagged up to 0.7 m)
            k_sumo = rate / np.maximum(at.speed, 1.0)
            carried = self.infeasible if len(self.infeasible) == self.n else np.zeros(self.n, bool)
            both = kappa * k_sumo
            slower = np.where(both > 0.0, np.sign(kappa) * np.minimum(np.abs(kappa), np.abs(k_sumo)),
                              np.where(both < 0.0, k_sumo, 0.0))
            kappa = np.where(self.kind == M.KIND_PED, kappa, np.where(carried, slower, k_sumo))
            kappa = np.clip(kappa, -lim, lim)
        at = replace(at, curvature=kappa)
        if not self.interpolating or not self.infeasible.any():  # (agents kinematic by preset: SUMO's)
            return sumo, at
        if self._chord_end is None:  # once per SUMO step
            L = self.step_length
            fix = wrap_pi(self._sumo_yaw - self._chord(ref.at(L), L)[0])
            known = ref.interpolated if ref.interpolated is not None else np.zeros(self.n, bool)
            self._chord_end = np.where(known & (np.abs(fix) < math.radians(CHORD_FIX_MAX_DEG)), fix, 0.0)
        u = min(max(tau, 0.0) / self.step_length, 1.0)
        yaw, kappa = self._chord(at, tau)
        kappa = kappa + self._chord_end / (self.step_length * np.maximum(at.speed, 1.0))
        return (np.where(self.infeasible, wrap_pi(yaw + u * self._chord_end), sumo),
                replace(at, curvature=np.where(self.infeasible, kappa, at.curvature)))

    def _chord(self, at: ReferencePoint, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """Angle [rad] and turning curvature [1/m] of each body's chord on the interpolated path
        with its bumper at ``at`` (``_kin_pose``)."""
        ref = self.ref
        back = at.s - self.sumo_len
        p = ref.point_at(np.maximum(back, 0.0), tau)
        # (SUMO's angle unless it is far off the path's start: a vehicle it turned on the spot)
        h0 = np.where(np.abs(wrap_pi(ref.yaw - ref.start_heading)) < 0.5 * np.pi, ref.yaw, ref.start_heading)
        short = np.minimum(back, 0.0)
        dx, dy = at.x - p.x - short * np.cos(h0), at.y - p.y - short * np.sin(h0)
        hb = np.where(back > 0.0, p.heading, h0)
        ux, uy = np.cos(at.tangent) - np.cos(hb), np.sin(at.tangent) - np.sin(hb)
        kappa = (dx * uy - dy * ux) / np.maximum(dx * dx + dy * dy, 1e-6)
        return np.arctan2(dy, dx), kappa

    def _may_roll_back(self, obs, held, e_lon: np.ndarray) -> np.ndarray:
        """Who may roll back to a standing reference it came to rest past (``control_default``):
        four-wheeled vehicles, and two-wheelers whose way back is clear of every other body
        (``RIDER_BACK_CLEAR_M``). A motorcycle rolled back into the bicycle queued beside and
        behind it under the sublane model; never rolled back, a motorcycle stopped 2.7 m past
        SUMO's stop (SUMO brakes it at 10 m/s^2 and more) stood on a crossing in the way of a
        pedestrian."""
        out = self.kind != M.KIND_BIKE
        cand = np.flatnonzero(~out & (held.speed <= self.ctl.default.hold_speed)
                              & (e_lon > self.ctl.default.creep_back_m) & (self.mode == AgentMode.PHYSICAL))
        if not len(cand):
            return out
        t_ = self.world.tables
        L, W = t_.length[self.slots], t_.width[self.slots]
        every = np.arange(self.n)
        for i in cand:  # (two-wheelers standing past their stop: a handful)
            back = e_lon[i]  # the way back: the body stretched back to its reference
            c, s_ = np.cos(obs.yaw[i]), np.sin(obs.yaw[i])
            other = every != i
            out[i] = not footprints_overlap(
                obs.cx[i] - 0.5 * back * c, obs.cy[i] - 0.5 * back * s_, obs.yaw[i], L[i] + back, W[i],
                obs.cx[other], obs.cy[other], obs.yaw[other], L[other], W[other], RIDER_BACK_CLEAR_M).any()
        return out

    def _carry_infeasible(self, ref: Reference, prev: np.ndarray, yaw_rate: np.ndarray, dist: np.ndarray,
                          obs, held) -> None:
        """Agents (physical vehicles) on a manoeuvre they cannot drive become kinematic until
        it is over (see INFEASIBLE_*); counted in episodes and agent-seconds. Seen on the path
        ahead, or in SUMO's own turn rate (``yaw_rate`` [rad/s] between its last samples; a
        turnaround at a dead end is not on the path until the vehicle is on it) once the
        vehicle is ``dist`` > INFEASIBLE_OFF_M off its reference (SUMO's angle also jumps
        where a lane meets a junction: a one-step rate of 3 rad/s in an ordinary turn)."""
        was = np.zeros(self.n, bool)
        if len(self.infeasible) and (prev >= 0).any():
            was = (prev >= 0) & self.infeasible[np.maximum(prev, 0)]
        cand = (self.mode == AgentMode.PHYSICAL) & (self.kind != M.KIND_PED)
        now = np.zeros(self.n, bool)
        if self.cfg.carry_infeasible and cand.any():
            tight, sustained = self._path_tightness(ref, obs.roll)
            start = tight > INFEASIBLE_MARGIN
            if not self.interpolating:  # (between the samples of long steps SUMO's rate is a chord's)
                start |= ((ref.speed > INFEASIBLE_MIN_SPEED) & (dist > INFEASIBLE_OFF_M)
                          & (np.abs(yaw_rate) > INFEASIBLE_RATE_MARGIN * ref.speed * self._reach()))
            start |= ((prev < 0) & (ref.speed > INFEASIBLE_MIN_SPEED)
                      & (np.abs(wrap_pi(ref.yaw - ref.start_heading)) > math.radians(SPAWN_OFF_DEG)))
            # over once the path ahead is in reach and the body is straight on it (a long
            # vehicle's rear is still in the turn when its bumper is out: SUMO's chord angle)
            # and the carried body itself has turned onto SUMO's angle (SUMO's angle jumps where a
            # junction meets the lane: released in that step, a car was handed back 20 deg off
            # the lane and fell 1.8 m behind)
            straight = math.radians(INFEASIBLE_STRAIGHT_DEG)
            keep = ((tight > INFEASIBLE_RELEASE) | (np.abs(wrap_pi(ref.yaw - ref.start_heading)) > straight)
                    | (np.abs(wrap_pi(obs.yaw - ref.yaw)) > straight)
                    # ... and SUMO no longer turns it tighter than its steering holds (handed back
                    # while SUMO still turned it at 100 deg/s, a car lagged 0.6 m, a van spun round)
                    | (np.abs(yaw_rate) > INFEASIBLE_RELEASE * np.maximum(ref.speed, INFEASIBLE_MIN_SPEED)
                       * self._reach()))
            # ... and the path ahead asks little of the tyres (a carry started on SUMO's turn
            # rate ended where the path's curvature was within the steering: a taxi handed back
            # in a 75 deg junction turn at 8 m/s, 8.7 m/s^2, ran 2.6 m wide at full lock)
            keep |= sustained > INFEASIBLE_GRIP_KEEP * self._a_lat
            # ... and once the carried body no longer turns faster than its tyres carry (between
            # long steps' samples the chord of a body whose back is still in the corner turns at
            # up to 1.2 rad/s at 14 m/s: released then, cars spun round; at short steps a bus
            # carried through a lane shape's S at 11 m/s, handed back turning at 0.8 rad/s
            # where the S turned the other way, spun 40 deg off)
            keep |= np.abs(obs.yaw_rate * obs.speed) > INFEASIBLE_RELEASE * self._a_lat
            # ... and a two-wheeler (placed upright) not in a turn it would have to lean into, now
            # in SUMO's turn rate or ahead on its path's 8 m windows (over 4 m a lane shape's
            # 2 deg corners held a motorcycle at 14 m/s; SUMO holds a motorcycle's angle for a few
            # steps in a junction turn, then jumps it: handed back upright when the rate read 0
            # with 30 deg of a 10 m arc still ahead at 8.6 m/s, it over-turned 20 deg and fell)
            # ... nor while SUMO brakes it so hard that, with the turn ahead, its tyres are past
            # the share of their grip a carry ends at (handed back upright at 13 m/s while SUMO
            # braked it at 10 m/s^2 into a 5.6 m/s^2 bend, a motorcycle fell to the outside)
            keep |= (self.kind == M.KIND_BIKE) & ((np.abs(yaw_rate * ref.speed) > GUARD_BIKE_RELEASE_ALAT)
                                                  | (sustained > GUARD_BIKE_RELEASE_ALAT)
                                                  | (np.hypot(sustained, np.maximum(-ref.accel, 0.0))
                                                     > INFEASIBLE_RELEASE * self._a_lat))
            now = cand & (start | (was & keep))
        guard = self._contact_guard(ref, prev, obs, held, was)
        now |= guard
        now &= ~self.authoritative  # coupling: physics owns these; SUMO follows what they do
        self.infeasible = now
        # a carry glides from the body's pose onto SUMO's (KIN_BLEND_S): switched at once, a
        # long body's yaw jumped from its driven pose to SUMO's chord, its rear ~1 m sideways
        off, age = np.zeros((self.n, 3)), np.full(self.n, np.inf)
        if was.any():
            off[was], age[was] = self.kin_off[prev[was]], self.kin_age[prev[was]]
        began = now & ~was
        # a carry the guard started stays the guard's while the manoeuvre keeps it (above)
        had_guard = (prev >= 0) & self.guarded[np.maximum(prev, 0)] if len(self.guarded) else np.zeros(self.n, bool)
        contact = now & (guard | (was & had_guard))
        self.guarded = contact
        if began.any():
            yaw0 = self._kin_pose(held, self.tau)[0]
            o = np.c_[obs.fx - held.x, obs.fy - held.y, wrap_pi(obs.yaw - yaw0)]
            # ... from a pose it drove to; a body spawned (at its parking spot) or teleported
            # this step starts on SUMO's pose (a van carried from its spawn glided in from the
            # parking spot 70 km away, 5.6 km off a second later)
            far = (prev < 0) | (np.hypot(o[:, 0], o[:, 1]) > KIN_GLIDE_MAX_M)
            off[began] = np.where(far[:, None], 0.0, o)[began]
            age[began] = 0.0
        self.kin_off, self.kin_age = off, age
        if now.any():
            self.mode = np.where(now, AgentMode.KINEMATIC, self.mode).astype(np.uint8)
            ms = 1e3 * self.step_length
            self.counters["carries_infeasible"] += int((began & ~guard).sum())
            self.counters["carried_infeasible_ms"] += int(round(ms * (now & ~contact).sum()))
            self.counters["carries_contact"] += int((began & guard).sum())
            self.counters["carried_contact_ms"] += int(round(ms * contact.sum()))
            if (began & ~guard).any():
                log.info("t=%.2f s: %s on a manoeuvre beyond their steering: shown kinematic until it is over",
                         ref.t_k, [self.ids[i] for i in np.flatnonzero(began & ~guard)][:10])

    def _contact_guard(self, ref: Reference, prev: np.ndarray, obs, held, was: np.ndarray) -> np.ndarray:
        """Agents carried so that a contact SUMO does not have cannot happen (GUARD_*): pairs
        whose physics footprints (a two-wheeler's widened by its rider's lean) come within
        GUARD_GAP_M now or GUARD_HORIZON_S ahead (their errors kept, or moving on at their
        velocity) while SUMO's footprints now have a gap; a pair stays guarded
        for GUARD_HOLD_S after it was last near and while SUMO has it within GUARD_KEEP_M.
        Pedestrian pairs never touch; a pair of bodies both placed every tick neither."""
        n = self.n
        out = np.zeros(n, bool)
        if not self.cfg.contact_guard or n < 2:
            self._guard_pairs = {}
            return out
        t = ref.t_k
        t_ = self.world.tables
        L, W = t_.length[self.slots], t_.width[self.slots]
        had = prev >= 0
        ghost = had & self.ghost[np.maximum(prev, 0)] if len(self.ghost) else np.zeros(n, bool)
        ped = self.kind == M.KIND_PED
        placed = (self.mode != AgentMode.PHYSICAL) | was
        H = float(np.clip(self.step_length, *GUARD_HORIZON_S))
        # SUMO's footprints now and H ahead (its angle turning at its rate)
        sx = held.x - 0.5 * self.sumo_len * np.cos(held.yaw)
        sy = held.y - 0.5 * self.sumo_len * np.sin(held.yaw)
        ah = ref.at(min(self.tau, self.max_extrapolation) + H)
        syaw2 = held.yaw + self._kin_rate * H
        sx2 = ah.x - 0.5 * self.sumo_len * np.cos(syaw2)
        sy2 = ah.y - 0.5 * self.sumo_len * np.sin(syaw2)
        # the bodies' footprints: a two-wheeler's body (its rider) leaning over reaches
        # height x sin(roll) sideways, less what its half-width comes in
        lean = np.abs(obs.roll)
        extra = np.where(self.kind == M.KIND_BIKE,
                         np.maximum(t_.height[self.slots] * np.sin(lean) - 0.5 * W * (1.0 - np.cos(lean)), 0.0), 0.0)
        side = 0.5 * extra * np.sign(obs.roll)  # (+ roll: right side down)
        px = np.where(had, obs.fx - 0.5 * L * np.cos(obs.yaw) + side * np.sin(obs.yaw), sx)
        py = np.where(had, obs.fy - 0.5 * L * np.sin(obs.yaw) - side * np.cos(obs.yaw), sy)
        pyaw = np.where(had, obs.yaw, held.yaw)
        pw = W + extra
        v = np.maximum(np.hypot(obs.vx, obs.vy), np.abs(held.speed))
        r = 0.5 * np.hypot(np.maximum(L, self.sumo_len), np.maximum(pw, self.sumo_wid)) + v * H + GUARD_GAP_M
        i, j = near_pairs(px, py, r)
        ok = ~(ped[i] & ped[j]) & ~ghost[i] & ~ghost[j] & ~(placed[i] & placed[j])
        i, j = i[ok], j[ok]
        if len(i):
            def gaps(ax, ay, ah_, bx, by, bh, al, aw, bl, bw):
                return footprint_gap(ax[i], ay[i], ah_[i], al[i], aw[i], bx[j], by[j], bh[j], bl[j], bw[j])
            sumo_now = gaps(sx, sy, held.yaw, sx, sy, held.yaw, self.sumo_len, self.sumo_wid, self.sumo_len, self.sumo_wid)
            # the bodies now and ahead: with their errors kept, or moving on at their velocity
            kx, ky, kyaw = sx2 + px - sx, sy2 + py - sy, syaw2 + wrap_pi(pyaw - held.yaw)
            lx, ly, lyaw = px + obs.vx * H, py + obs.vy * H, pyaw + obs.yaw_rate * H
            pg = np.minimum(gaps(px, py, pyaw, px, py, pyaw, L, pw, L, pw),
                            np.minimum(gaps(kx, ky, kyaw, kx, ky, kyaw, L, pw, L, pw),
                                       gaps(lx, ly, lyaw, lx, ly, lyaw, L, pw, L, pw)))
            # SUMO's footprints this close are its own collision; only now counts (ahead they are
            # our extrapolation: a motorcycle SUMO stops within a step from 15 m/s runs on into
            # its leader there, SUMO's next sample does not)
            near = (pg < GUARD_GAP_M) & (sumo_now > 2.0 * SUMO_OVERLAP_M)
            ids = self.ids
            sg = sumo_now
            told = []
            for a, b, g_p, g_s in zip(i[near], j[near], pg[near], sg[near]):
                key = (ids[a], ids[b]) if ids[a] < ids[b] else (ids[b], ids[a])
                if key not in self._guard_pairs:
                    if len(self._guard_pairs) >= MAX_GUARD_PAIRS:
                        self.counters["guard_pairs_dropped"] += 1
                        continue
                    told.append(f"{key[0]} and {key[1]} ({g_p:.2f} m apart, SUMO's {g_s:.2f} m)")
                self._guard_pairs[key] = t
            if told:
                log.info("t=%.2f s: %d pair(s) carried to keep clear: %s", t, len(told), "; ".join(told[:5]))
        pairs = [(self._index.get(a, -1), self._index.get(b, -1), t0) for (a, b), t0 in self._guard_pairs.items()]
        pairs = [p for p in pairs if p[0] >= 0 and p[1] >= 0]
        if pairs:
            a, b, t0 = (np.array(c) for c in zip(*pairs))
            sumo_now = footprint_gap(sx[a], sy[a], held.yaw[a], self.sumo_len[a], self.sumo_wid[a],
                                     sx[b], sy[b], held.yaw[b], self.sumo_len[b], self.sumo_wid[b])
            stay = ((t - t0) < GUARD_HOLD_S) | (sumo_now < GUARD_KEEP_M)
            a, b, t0 = a[stay], b[stay], t0[stay]
            self._guard_pairs = {(self.ids[x], self.ids[y]) if self.ids[x] < self.ids[y] else (self.ids[y], self.ids[x]):
                                 float(z) for x, y, z in zip(a, b, t0)}
            out[a] = True
            out[b] = True
        else:
            self._guard_pairs = {}
        out &= self.mode == AgentMode.PHYSICAL
        return out

    def _build_groups(self) -> _Groups:
        veh = self.kind != M.KIND_PED
        if self.stopping:  # every vehicle brakes along its path with the default controller
            kin = np.zeros(self.n, bool)
            use_default, use_paper = veh.copy(), np.zeros(self.n, bool)
        else:
            kin = (self.mode == AgentMode.KINEMATIC) | (self.mode == AgentMode.EXTERNAL)
            use_default = veh & ~kin & (self.preset == P_DEFAULT)
            use_paper = veh & ~kin & (self.preset == P_PAPER)
        veh_idx = np.flatnonzero(veh)
        return _Groups(
            kin_idx=np.flatnonzero(kin), use_default=use_default, use_paper=use_paper,
            any_default=bool(use_default.any()), all_default=bool(use_default.all()), any_paper=bool(use_paper.any()),
            all_paper=bool(use_paper.all()), veh_idx=veh_idx,
            veh_slots=self.slots[veh_idx], all_veh=len(veh_idx) == self.n, ped_idx=np.flatnonzero(~veh & ~kin),
        )

    # ------------------------------------------------------------------ control tick

    def begin_stop(self) -> None:
        """SUMO side gone: every agent brakes to rest (mode STOPPING) along its last path."""
        if self.stopping or self.n == 0:
            self.stopping = True
            return
        self._cache = None
        obs = self.world.observe(self.slots)
        self.stop_v0 = np.maximum(obs.speed, 0.0)
        self.stop_t = 0.0
        self.mode = np.full(self.n, AgentMode.STOPPING, np.uint8)
        self.stopping = True
        self._groups = None

    def tick(self) -> None:
        """One control tick: observe -> control (pure numpy, laws in ``control``) -> actuate
        -> ``substeps`` MuJoCo steps -> tracking errors and contacts."""
        w = self.world
        if self.n == 0 or self.ref is None:
            w.step()
            self.tick_count += 1
            return
        obs, proj = self._observe()
        tau = min(self.tau, self.max_extrapolation)
        u = self._control(obs, proj, tau)
        if self._stalled is not None:  # faults: a stalled vehicle brakes fully, no drive
            u.drive[self._stalled] = 0.0
            u.brake[self._stalled] = self.world.tables.max_brake[self.slots[self._stalled]]
        if self._unbraked is not None:  # faults: no drive, no brakes: it coasts
            u.drive[self._unbraked] = 0.0
            u.brake[self._unbraked] = 0.0
        self._actuate(u, obs)
        w.step()
        self.tick_count += 1
        self.tau += self.dt
        if self.stopping:
            self.stop_t += self.dt
        self._measure(obs, u)

    def _observe(self):
        """This tick's start state: (observation, bumper projection or None); after the model
        grew, the agents' new slot numbers first (and their ghost bits again)."""
        w = self.world
        if self._gen != w.generation:  # the model grew: every slot number changed
            self.slots = w.slot_of(self.ids)
            self._params()
            self._cache = None
            self._set_bits()
        # the previous tick's end state (or the one ``apply_step`` read) is this tick's start
        # state unless a placement happened in between (then the cache was dropped)
        if self._cache is not None:
            return self._cache
        return w.observe(self.slots), None

    def _control(self, obs, proj, tau: float) -> _Commands:
        """Commands for every agent from the observation and the reference ``tau`` [s] past
        the sample: the presets' controllers, then the vehicle limits, the bicycle
        stabiliser and the pedestrians' force control (all in ``control``). Writes nothing into
        the world (the controllers' integrators are ``self.state``)."""
        n = self.n
        ref = self.ref
        p = self.params
        if self._groups is None:
            self._groups = self._build_groups()
        g = self._groups
        stop_speed = None
        stopping = None
        if self.stopping:
            stopping = np.ones(n, bool)
            stop_speed = np.maximum(self.stop_v0 - self.cfg.stop_decel * self.stop_t, 0.0)
        vobs = C.VehicleObs(obs.fx, obs.fy, obs.cx, obs.cy, obs.yaw, obs.speed, obs.yaw_rate, obs.fvx, obs.fvy)
        cmds = []
        if g.any_default:
            cmd = C.control_default(
                vobs, p, ref, tau, self.dt, self.ctl.default, self.state, stopping, self.cfg.stop_decel,
                stop_speed, s_guess=self.s_act, proj=proj, rolls_back=self._rolls_back,
            )
            cmds.append((g.all_default, g.use_default, cmd))
        if g.any_paper:
            cmds.append((g.all_paper, g.use_paper, C.control_paper(vobs, p, ref, self.ctl.paper)))
        if len(cmds) == 1 and cmds[0][0]:  # one controller for everybody (the usual case)
            cmd = cmds[0][2]
            steer, drive, brake, aux = cmd.steer, cmd.drive, cmd.brake, cmd.aux
        else:
            steer, drive, brake, aux = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
            for _, use, cmd in cmds:
                steer = np.where(use, cmd.steer, steer)
                drive = np.where(use, cmd.drive, drive)
                brake = np.where(use, cmd.brake, brake)
                aux = np.where(use, cmd.aux, aux)
        at = kin_yaw = None
        if len(g.kin_idx):  # placed at the reference (``_actuate``), steering shown for its path
            idx = g.kin_idx
            kin_yaw, at = self._kin_pose(ref.at(tau), tau)
            steer[idx] = np.arctan(p.wheelbase[idx] * at.curvature[idx])
        carry = carry_yaw = None
        if not self.stopping and self.carry.any():  # standing, slid sideways by SUMO: follow the slide
            carry = np.flatnonzero(self.carry)
            at = ref.at(tau) if at is None else at  # (a carried slide is placed straight anyway)
            carry_yaw = obs.yaw  # (this tick's observation: not written)
            drive[carry] = 0.0
        rear = None
        if len(self._rear_idx):  # long vehicles: the body onto SUMO's chord (``C.rear_axle_steer``)
            ri = self._rear_idx  # (under our preset: the paper's car keeps a fixed rear axle)
            ri = ri[(self.mode[ri] == AgentMode.PHYSICAL) & (self.preset[ri] == P_DEFAULT)]
            rear = np.zeros(n)
            # SUMO's body angle moving at its rate between the last two samples (the chord's own
            # rate: the path's curvature at the front is not the body's in an S or a turn's entry)
            rate = self._sumo_yaw_rate[ri]
            if self.stopping:
                yaw_ref, rate = obs.yaw[ri], np.zeros(len(ri))
            else:
                yaw_ref = self._sumo_yaw[ri] + rate * (min(tau, self.max_extrapolation) - self.lag)
            steer[ri], rear[ri] = C.rear_axle_steer(
                steer[ri], obs.yaw[ri], obs.speed[ri], yaw_ref, rate, p.wheelbase[ri], p.d_bumper[ri],
                p.max_steer[ri], self._max_rear[ri], a_lat=self._a_lat[ri],
            )
        # vehicle properties, whatever the controller asked for
        lim_f = C.steer_limit(obs.speed, p.wheelbase, self._a_lat, p.max_steer)
        if rear is None:
            steer = np.clip(steer, -lim_f, lim_f)
        else:  # (both axles steered: MuJoCo's tyres and the curve speed cut keep the grip)
            fixed = self._max_rear <= 0
            steer = np.where(fixed, np.clip(steer, -lim_f, lim_f), steer)
        if self._any_grip:
            drive = C.traction_limit(drive, obs.speed, obs.yaw_rate, self._grip_torque)
        if g.any_default and not self.stopping:
            v = np.maximum(obs.speed, 0.0)
            kap = np.abs(ref.path.at(self.s_act + v * C.CURVE_PREVIEW_S[:, None]).curvature).max(axis=0)
            v_ref = ref.at(tau).speed
            drive = C.curve_speed_cut(drive, obs.speed, kap, v_ref, self._a_lat, g.use_default)
            # steering at its mechanical limit and faster than the reference: no drive, brakes ...
            vr = np.where(g.use_default, v_ref, np.inf)
            drive, brake = C.saturation_speed_cut(drive, brake, steer, p.max_steer, obs.speed, vr, p.m_eff, p.r_wheel)
            # ... and no drive at the tyres' limit (fixed rear axle) while faster than the reference
            # and off the path: at 1 s steps SUMO turns cars through 45-65 deg within a step; running
            # wide, they fell behind along the path and sped up to catch up (16.5 m/s behind SUMO's
            # 13.9), which widened the turn further until they were placed 6 m off
            grip_sat = np.abs(steer) >= C.STEER_SAT_SHARE * lim_f
            if rear is not None:
                grip_sat &= fixed
            drive = np.where(grip_sat & (obs.speed > vr) & (np.abs(self.err_lat) > GRIP_SAT_LAT_M), 0.0, drive)
        if self._any_bike:  # a leaning two-wheeler's tyres carry less drive and braking
            bike = self.kind == M.KIND_BIKE
            drive = np.where(bike, C.lean_traction_limit(drive, obs.roll, self._a_lat, p.max_drive), drive)
            brake = np.where(bike, C.lean_traction_limit(brake, obs.roll, self._a_lat, p.max_brake), brake)
        vi = g.veh_idx
        stab = None
        if len(vi) and self._any_bike:  # only bicycles have a stabiliser (the world skips the rest)
            gain = self._stab_gain[vi]  # (leaning up to the steering limit's lateral acceleration)
            stab = C.steered_roll_stabiliser(
                obs.roll[vi], obs.roll_rate[vi], obs.speed[vi], steer[vi], p.wheelbase[vi],
                self.ctl.default.bike_roll_kp * gain, self.ctl.default.bike_roll_kd * gain, self.stab_max[vi],
                # bicycles keep their old target cap (tan 0.6, 31 deg): leaning up to their 35 deg
                # limit flipped a bicycle in the 1 s-step tram scenario
                np.where(self.mass[vi] < MOTORCYCLE_MASS_KG, BIKE_LEAN_TARGET_TAN, self._a_lat[vi] / C.G),
            )
        ped = None
        if len(g.ped_idx):
            fx, fy, tz, force = self._pedestrians(g.ped_idx, obs, tau, stopping, stop_speed)
            ped = (fx, fy, tz)
            drive[g.ped_idx] = force
        return _Commands(steer, drive, brake, aux, stab, ped, at, kin_yaw, carry, rear, carry_yaw)

    def _actuate(self, u: _Commands, obs) -> None:
        """Write the commands into the world: kinematic agents and SUMO's sideways slides
        placed at the reference, vehicles' steering / drive / brakes, pedestrians' forces."""
        w = self.world
        g = self._groups
        if len(g.kin_idx):
            at, yaw = u.at, u.kin_yaw
            if len(self.kin_age) == self.n and np.isfinite(self.kin_age).any():
                f = np.exp(-self.kin_age / KIN_BLEND_S)  # 0 for agents kinematic by preset (age inf)
                at = replace(at, x=at.x + f * self.kin_off[:, 0], y=at.y + f * self.kin_off[:, 1])
                yaw = yaw + f * self.kin_off[:, 2]
                self.kin_age = self.kin_age + self.dt
            self._place(g.kin_idx, at, count=False, steady_turn=False, yaw=yaw)
        if u.carry is not None:
            self._place_slide(u.carry, u.at, u.carry_yaw, count=False)
        vi = g.veh_idx
        if len(vi):
            if g.all_veh:
                w.command_vehicles(g.veh_slots, u.steer, u.drive, u.brake, u.stab, u.rear, obs.speed)
            else:
                w.command_vehicles(g.veh_slots, u.steer[vi], u.drive[vi], u.brake[vi], u.stab,
                                   None if u.rear is None else u.rear[vi], obs.speed[vi])
        if u.ped is not None:
            w.command_pedestrians(self.slots[g.ped_idx], *u.ped)

    def _measure(self, obs, u: _Commands) -> None:
        """After the step: tracking errors against the extrapolated reference, contacts and
        collisions; the end state is the next tick's start state."""
        w = self.world
        ref = self.ref
        obs2 = w.observe(self.slots)
        s_guess = self.s_act + np.maximum(obs.speed, 0.0) * self.dt
        r2, (s2, lat2, pp2) = ref.at_and_project(min(self.tau, self.max_extrapolation), obs2.fx, obs2.fy, s_guess)
        self.s_act = s2
        self.err_lon = s2 - r2.s
        self.err_lat = lat2
        self.drive = u.drive
        self.brake = u.brake
        self.aux = u.aux
        flip = math.radians(self.cfg.flip_deg)
        upright = (np.abs(obs2.roll) < flip) & (np.abs(obs2.pitch) < flip)
        self.touching, began = w.contacts(self.slots, upright)
        if began.any():
            self._split_collisions(began)
        self._last_obs = obs2
        self._cache = (obs2, (s2, lat2, pp2))

    def _pedestrians(self, pi: np.ndarray, obs, tau: float, stopping, stop_speed) -> tuple:
        """Force control of pedestrians ``pi`` (``control.pedestrian_force``) towards the held
        sample (paper preset) or the extrapolated reference (default), or to a stop where
        they are; returns (force x, force y [N], yaw torque [N*m], force norm [N])."""
        ref = self.ref
        paper = (self.preset[pi] == P_PAPER) & (not self.stopping)
        r = ref.at(tau)
        h = ref.held()
        tx = np.where(paper, h.x[pi], r.x[pi])
        ty = np.where(paper, h.y[pi], r.y[pi])
        tyaw = np.where(paper, h.tangent[pi], r.tangent[pi])
        v = np.where(paper, h.speed[pi], r.speed[pi])
        if stopping is not None:
            v = stop_speed[pi]
            tx, ty = obs.fx[pi], obs.fy[pi]
        # feed-forward (along-path acceleration, centripetal) for the extrapolated reference only
        return C.pedestrian_force(
            obs.fx[pi], obs.fy[pi], obs.vx[pi], obs.vy[pi], obs.yaw[pi], obs.yaw_rate[pi], tx, ty, tyaw, v,
            np.where(paper, 0.0, r.accel[pi]), np.where(paper, 0.0, r.curvature[pi]), self.mass[pi],
            np.where(paper, self.ctl.paper.ped_omega, self.ctl.default.ped_omega),
            np.where(paper, self.ctl.paper.ped_zeta, self.ctl.default.ped_zeta), self.params.max_drive[pi],
        )

    # ------------------------------------------------------------------ output

    def snapshot(self) -> PhysicsAgents:
        """Per-agent actual state for ``PhysicsState``."""
        obs = self._last_obs
        if obs is None or len(obs.fx) != self.n or self._gen != self.world.generation:
            if self._gen != self.world.generation:
                self.slots = self.world.slot_of(self.ids)
                self._params()
            obs = self.world.observe(self.slots)
        f32 = np.float32
        return PhysicsAgents(
            ids=list(self.ids), cls=self.wire_cls.astype(np.uint8), mode=self.mode.astype(np.uint8),
            x=obs.fx.astype(np.float64), y=obs.fy.astype(np.float64), z=obs.z.astype(f32),
            heading=yaw_to_sumo_angle(obs.yaw).astype(f32), roll=np.rad2deg(obs.roll).astype(f32),
            pitch=np.rad2deg(obs.pitch).astype(f32), speed=obs.speed.astype(f32),
            steer=np.rad2deg(obs.steer).astype(f32), drive=np.asarray(self.drive, f32),
            brake=np.asarray(self.brake, f32), err_lon=np.asarray(self.err_lon, f32),
            err_lat=np.asarray(self.err_lat, f32),
        )

    def feedback(self, run: str, step: int, time: float) -> PhysicsFeedback:
        """Two-way coupling: the physical state of the physics-authoritative agents (SPEC 3.8)."""
        a = self.snapshot()
        rows = np.flatnonzero(self.authoritative) if len(self.authoritative) == a.n else np.zeros(0, np.int64)
        f32 = np.float32
        touching = self.touching[rows] if len(self.touching) == a.n else np.zeros(len(rows), bool)
        return PhysicsFeedback(
            run=run, step=int(step), time=float(time), ids=[a.ids[i] for i in rows], x=a.x[rows], y=a.y[rows],
            heading=a.heading[rows], speed=a.speed[rows], d_lon=a.err_lon[rows].astype(f32),
            d_lat=a.err_lat[rows].astype(f32), contact=touching.astype(np.uint8))

    def mode_counts(self) -> dict[str, int]:
        m = self.mode
        return {
            "physical": int((m == AgentMode.PHYSICAL).sum()), "kinematic": int((m == AgentMode.KINEMATIC).sum()),
            "external": int((m == AgentMode.EXTERNAL).sum()), "stopping": int((m == AgentMode.STOPPING).sum()),
        }


__all__ = ["Fleet", "StepStats", "P_DEFAULT", "P_KINEMATIC", "P_PAPER"]
