"""``Fleet``: the agents of the current SUMO step as aligned arrays; syncs them on each step, drives them each tick.

One object between the transport (``daemon``) and the world (``world``); the control
laws are ``control``'s, the rules that reconcile SUMO's motion with physics are
``policies``', the references ``reference``'s; none of them calls back here:

- ``apply_step(msg)``: sync (the agent set: spawn, park, retype; each agent's previous
  sample; the reference) -> detect (the policies of ``policies.POLICIES`` in table order:
  carry, roll back, jump, slide, flip, divergence) -> act (carries, placements, ghosts,
  each counted).
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
from dataclasses import dataclass, replace
from types import MappingProxyType
from typing import NamedTuple

import numpy as np

from physics_side import control as C
from physics_side import models as M
from physics_side import policies
from physics_side.config import PhysicsSettings, Rates
from physics_side.faults import Faults
from physics_side.policies import carry_pose, contacts, placement, sync
from physics_side.policies.base import Cause, Previous, Step, Verdict, realign, realign_mask
from physics_side.policies.footprints import centre
from physics_side.reference import Reference, ReferencePoint, tracking_error
from physics_side.world import PhysicsWorld
from protocol.frames import sumo_angle_to_yaw, yaw_to_sumo_angle
from protocol.messages import AgentBatch, AgentClass, AgentFlag, AgentMode, PhysicsAgents, PhysicsFeedback, StepMessage

log = logging.getLogger(__name__)

P_PAPER, P_DEFAULT, P_KINEMATIC = 0, 1, 2
_PRESET_CODE = {"paper": P_PAPER, "default": P_DEFAULT, "kinematic": P_KINEMATIC}
_TYPE_NAME = {
    AgentClass.PASSENGER: "passenger", AgentClass.TAXI: "taxi", AgentClass.BUS: "bus",
    AgentClass.BICYCLE: "bicycle", AgentClass.PEDESTRIAN: "pedestrian", AgentClass.OTHER: "other",
}
_BICYCLE_ROLL_STIFFNESS = M.default_spec(AgentClass.BICYCLE).roll_stiffness  # [N*m/rad] the stabiliser gains' reference
TIME_EPS_S = 1e-9  # [s] step lengths closer than this to interpolate_above_s are not above it
PROJECT_ITERATIONS = 3  # projections of the next sample onto the previous path (interpolation)
LOG_IDS = 10  # agents named in one log line
# pool keys (``reserve``): one int64 of class, vType, length and width in whole millimetres
SIZE_BITS = 20  # [bit] a length or width (up to 1,048 m)
VTYPE_BITS = 16  # [bit]
CLASS_BITS = 8  # [bit]
MM_PER_M = 1e3  # [mm/m]


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


class _Sample(NamedTuple):
    """This step's samples against each agent's previous one (``Fleet._sample``)."""

    x: np.ndarray
    y: np.ndarray
    speed: np.ndarray
    yaw_rate: np.ndarray
    ref: Reference
    side_rate: np.ndarray
    slow: np.ndarray
    hop: np.ndarray
    ped_hop: np.ndarray


class DebugState(NamedTuple):
    """A read-only look at the policies' state (``Fleet.debug_state``), for tests and tools."""

    guard_pairs: MappingProxyType
    """Pairs the contact guard carries: (id, id) -> SUMO time [s] last near."""
    carried: np.ndarray
    """Carried for a manoeuvre or a contact, bool per agent."""
    sliding: np.ndarray
    """Carried along SUMO's sideways slide, bool per agent."""
    rolls_back: np.ndarray
    """May roll back to a standing reference, bool per agent."""
    pending_collisions: tuple[str, ...]
    """Physics-only collisions re-checked at the next sample."""


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
            **{c: 0 for c in policies.COUNTERS},
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
        self.ids: list[str] = []
        self._index: dict[str, int] = {}
        self.slots = np.zeros(0, np.int64)
        self.wire_cls = np.zeros(0, np.uint8)
        self.preset = np.zeros(0, np.int8)
        self.mode = np.zeros(0, np.uint8)
        self.kind = np.zeros(0, np.int8)
        self.ref: Reference | None = None
        self._sample_ref: Reference | None = None
        self._prev_batch = None
        self._prev_rows: dict[str, int] = {}
        self._prev_time = 0.0
        self.sumo_len = self.sumo_wid = np.zeros(0)  # SUMO's length and width [m]
        # the policies' state per agent (``policies.base.Previous``)
        self.ghost = self.carried = self.guarded = self.sliding = np.zeros(0, bool)
        self.jump_t = np.zeros(0)
        self._guard = contacts.ContactGuard()
        self._collisions = contacts.CollisionBook()
        self.kin_off = np.zeros((0, 3))  # carried agents' offset from SUMO's pose at the start (x, y [m], yaw [rad])
        self.kin_age = np.zeros(0)  # [s] since the carry started
        self._sumo_yaw = self._sumo_yaw_rate = np.zeros(0)  # SUMO body angle [rad] and its rate [rad/s]
        self._kin_rate = np.zeros(0)  # [rad/s] kinematic bodies' turn rate between samples (``carry_pose.turn_rate``)
        self._rolls_back = np.zeros(0, bool)  # who may roll back to its standing reference (``carry.rolls_back``)
        self._chord_end: np.ndarray | None = None  # carried bodies' chord to SUMO's angle at the step's end [rad]
        self.tau = 0.0
        self.state = C.ControlState.zeros(0)
        self.s_act = self.drive = self.brake = self.aux = self.err_lon = self.err_lat = np.zeros(0)
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
        return mode == "interpolate" or (mode == "auto" and step_length > self.cfg.interpolate_above_s + TIME_EPS_S)

    @property
    def interpolating(self) -> bool:
        """``interpolates`` for the newest step."""
        return self.interpolates(self.step_length)

    @property
    def lag(self) -> float:
        """How far physics time runs behind the newest SUMO step [s]: a step length when
        interpolating (the interval between the previous and the newest sample), else 0."""
        return self.step_length if self.interpolating else 0.0

    @property
    def max_extrapolation(self) -> float:
        """How far past the newest SUMO sample the reference is extrapolated [s]: a number
        of SUMO steps, so a late step at any step length is bridged alike."""
        return self.cfg.max_extrapolation_steps * self.step_length

    def debug_state(self) -> DebugState:
        """The policies' state, read-only (copies)."""
        return DebugState(MappingProxyType(dict(self._guard.pairs)), self.carried.copy(), self.sliding.copy(),
                          self._rolls_back.copy(), tuple(self._collisions.pending))

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
        # one int64 per agent: np.unique of a 1-D array (~0.5 ms at 10,000 agents; of rows ~20 ms)
        size_max = (1 << SIZE_BITS) - 1
        mm = lambda v: np.clip(np.round(np.asarray(v, np.float64) * MM_PER_M), 0, size_max).astype(np.int64)  # noqa: E731
        key = ((np.asarray(agents.cls, np.int64) & ((1 << CLASS_BITS) - 1)) << (VTYPE_BITS + 2 * SIZE_BITS)
               | (np.asarray(agents.vtype, np.int64) & ((1 << VTYPE_BITS) - 1)) << (2 * SIZE_BITS)
               | mm(agents.length) << SIZE_BITS | mm(agents.width))
        todo = [k for k in np.unique(key).tolist() if k not in self._reserved]
        if not todo:
            return 0
        self._reserved.update(todo)
        u = np.asarray(todo, np.int64)
        length, width = ((u >> SIZE_BITS) & size_max) / MM_PER_M, (u & size_max) / MM_PER_M
        fam = self._families(u >> (VTYPE_BITS + 2 * SIZE_BITS), (u >> (2 * SIZE_BITS)) & ((1 << VTYPE_BITS) - 1), length)
        return self.world.reserve(zip(fam, length, width))

    def apply_step(self, msg: StepMessage, resync: bool = False, tau: float = 0.0) -> StepStats:
        """Sync with a SUMO step: the agent set, each agent's previous sample and the reference
        (``_sync``), then the policies' detect phase in table order (``policies.DETECT``), then
        act on their verdict (``_act``). ``resync`` after a SUMO restart; ``tau`` [s]: how far
        physics time is past the step's time (steps shorter than a control tick, realtime
        jitter): placements and errors use the reference then."""
        self._cache = None
        self._last_obs = None
        st = StepStats()
        s = self._sync(msg, resync, tau, st)
        v = Verdict.empty(s)
        for policy in policies.DETECT:
            policy.detect(s, v)
        self._act(s, v, st, msg.step)
        self.sumo_step = msg.step
        self.counters["steps"] += 1
        if resync:
            self.counters["resyncs"] += 1
        return st

    def _sync(self, msg: StepMessage, resync: bool, tau: float, st: StepStats) -> Step:
        """The agent set (parked, retyped, spawned), each agent's previous sample, the
        reference, the bodies before any placement: the ``Step`` the policies read."""
        a = msg.agents
        self.step_length = float(msg.step_length)
        rows = np.flatnonzero((a.flags & AgentFlag.INSIDE_VEHICLE) == 0)
        st.skipped = a.n - len(rows)
        self.counters["skipped_inside_vehicle"] += st.skipped
        ids = [a.ids[i] for i in rows]
        if msg.vtypes is not None:  # a step carries the table only when it changed (SPEC 3.1)
            self._vtypes = list(msg.vtypes)
        prev, old = self._membership(msg, rows, ids, resync, st)
        smp = self._sample(msg, rows, ids, prev, old)
        is_new = self._spawn(msg, rows, ids, st)
        self._adopt(msg, rows, ids, prev, smp.ref, tau)
        return self._step(msg, rows, prev, is_new, old, smp)

    def _membership(self, msg: StepMessage, rows: np.ndarray, ids: list[str], resync: bool,
                    st: StepStats) -> tuple[np.ndarray, Reference | None]:
        """Park agents that left or changed type; each agent's row in the previous step (-1:
        none) and the previous sample (None after a resync or a stale one: ``sync.stale``)."""
        w, a = self.world, msg.agents
        new_set = set(ids)
        gone = [aid for aid in self.ids if aid not in new_set]
        if gone:
            w.park(w.slot_of(gone))
            st.parked = len(gone)
        prev = np.fromiter((self._index.get(aid, -1) for aid in ids), np.int64, len(ids))
        retyped = sync.retyped(prev, self.wire_vtype, self.wire_cls, len(self._index), a.vtype[rows], a.cls[rows])
        if len(retyped):
            w.park(w.slot_of([ids[i] for i in retyped]))
            prev[retyped] = -1
            st.retyped = len(retyped)
            self.counters["retyped"] += len(retyped)
        old = self._sample_ref
        if resync or (old is not None and sync.stale(msg.time, old.t_k, msg.step_length)):
            old = None
            prev[:] = -1
        return prev, old

    def _sample(self, msg: StepMessage, rows: np.ndarray, ids: list[str], prev: np.ndarray,
                old: Reference | None) -> _Sample:
        """This step's samples against the previous ones (turn rates, drift, hops) and the
        reference over the step (between the samples when interpolating)."""
        a = msg.agents
        x, y, speed = a.x[rows], a.y[rows], a.speed[rows]
        yaw = sumo_angle_to_yaw(a.angle[rows])
        yaw_rate = sync.yaw_rates(yaw, old, prev, msg.time)
        ref = cur = Reference.from_batch(msg.time, a, rows if len(rows) < a.n else None, yaw_rate)
        before = np.zeros(len(ids))
        if old is not None and len(self._sumo_yaw_rate) and len(ids):
            before = realign(self._sumo_yaw_rate, prev, 0.0)
        self._kin_rate = carry_pose.turn_rate(before, yaw_rate)
        self._sumo_yaw, self._sumo_yaw_rate = yaw, yaw_rate
        self._chord_end = None
        side_rate, drift = sync.side_drift(ref, old, prev, msg.time, self.cfg.max_side_speed)
        if drift is not None:
            ref.set_side_rate(drift)
        slow, hop = sync.hops(x, y, speed, old, prev, msg.time, self.cfg)
        ped_hop = sync.pedestrian_hops(x, y, speed, old, prev, msg.time, self.kind)
        if self.interpolating:
            ref = self._interpolation(msg, rows, ids, a.flags[rows], cur, yaw_rate, old is not None, hop | ped_hop)
        self._sample_ref = cur
        self._prev_batch, self._prev_time = a, msg.time
        self._prev_rows = {aid: int(r) for aid, r in zip(ids, rows)}
        return _Sample(x, y, speed, yaw_rate, ref, side_rate, slow, hop, ped_hop)

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
        merged = sync.stack_batches(pb, msg.agents)
        sel = np.where(known, src, n_prev + np.asarray(rows, np.int64))
        ref = Reference.from_batch(self._prev_time if pb is not None else msg.time, merged, sel, yaw_rate)
        if known.any():
            guess = 0.5 * (ref.speed + cur.speed) * L
            s_end, lat_end, _ = ref.project_far(cur.x, cur.y, guess, iterations=PROJECT_ITERATIONS)
        else:
            s_end = lat_end = np.zeros(len(ids))
        ref.interpolate_to(L, known, s_end, cur.speed, cur.accel, lat_end)
        return ref

    def _spawn(self, msg: StepMessage, rows: np.ndarray, ids: list[str], st: StepStats) -> np.ndarray:
        """Slots for this step's agents, new ones allocated in their model's pool; returns the new (bool)."""
        w, a = self.world, msg.agents
        slots = w.slot_of(ids)
        new = np.flatnonzero(slots < 0)
        if len(new):
            fam = self._families(a.cls[rows[new]], a.vtype[rows[new]], a.length[rows[new]])
            pools = np.array([w.pool_for(f, float(a.length[rows[i]]), float(a.width[rows[i]]))
                              for f, i in zip(fam, new)])
            gen = w.generation
            new_slots = w.allocate([ids[i] for i in new], pools, a.x[rows[new]], a.y[rows[new]])
            if w.generation != gen:  # the model grew: every slot number changed
                slots = w.slot_of(ids)
            else:
                slots[new] = new_slots
            st.spawned = len(new)
        self.slots = slots
        is_new = np.zeros(len(ids), bool)
        is_new[new] = True
        return is_new

    def _adopt(self, msg: StepMessage, rows: np.ndarray, ids: list[str], prev: np.ndarray, ref: Reference,
               tau: float) -> None:
        """This step's agents become the fleet's: ids, classes, modes, reference, controller state."""
        a = msg.agents
        cls, flags = a.cls[rows], a.flags[rows]
        preset = self._preset_lut[cls]
        self.ids = ids
        self._index = {aid: i for i, aid in enumerate(ids)}
        self.wire_vtype = a.vtype[rows].astype(np.uint16)
        self.wire_cls = cls.astype(np.uint8)
        self.kind = self.world.tables.kind[self.slots].astype(np.int8)
        self.authoritative = ((flags & AgentFlag.PHYSICS_AUTHORITY) != 0) & self.two_way
        self.touching = np.zeros(len(ids), bool)
        self._stalled = self.faults.stalled(self._index, len(ids), msg.time)
        self._unbraked = self.faults.unbraked(self._index, len(ids), msg.time)
        self.preset = preset
        mode = np.where(preset == P_KINEMATIC, AgentMode.KINEMATIC, AgentMode.PHYSICAL)
        self.mode = np.where((flags & AgentFlag.EGO) != 0, AgentMode.EXTERNAL, mode).astype(np.uint8)
        self.ref = ref
        self.tau = max(0.0, float(tau))
        self.state = self.state.take(prev)
        self.stopping = False
        self._params()
        self.sumo_len = a.length[rows].astype(np.float64)
        self.sumo_wid = a.width[rows].astype(np.float64)

    def _step(self, msg: StepMessage, rows: np.ndarray, prev: np.ndarray, is_new: np.ndarray,
              old: Reference | None, smp: _Sample) -> Step:
        """The ``Step`` the policies read: the bodies before any placement against the reference."""
        ref = smp.ref
        obs = self.world.observe(self.slots)
        held = (ref.at(min(self.tau, self.max_extrapolation)) if self.tau > 0 or self.interpolating
                else ref.held())
        e_lon, e_lat = tracking_error(obs.fx, obs.fy, held)
        t = self.world.tables
        before = Previous(carried=realign_mask(self.carried, prev), guarded=realign_mask(self.guarded, prev),
                          sliding=realign_mask(self.sliding, prev), ghost=realign_mask(self.ghost, prev),
                          jump_t=realign(self.jump_t, prev, -np.inf))
        return Step(
            cfg=self.cfg, ctl=self.ctl, t=msg.time, gap=msg.time - old.t_k if old is not None else 0.0,
            step_length=self.step_length, interpolating=self.interpolating, tau=self.tau,
            horizon=min(self.tau, self.max_extrapolation), ids=self.ids, index=self._index, prev=prev,
            is_new=is_new, flags=msg.agents.flags[rows], kind=self.kind, mode=self.mode,
            authoritative=self.authoritative, x=smp.x, y=smp.y, speed=smp.speed, yaw_rate=smp.yaw_rate,
            kin_rate=self._kin_rate, old=old, ref=ref, held=held, obs=obs, e_lon=e_lon, e_lat=e_lat,
            dist=np.hypot(e_lon, e_lat), side_rate=smp.side_rate, slow=smp.slow, hop=smp.hop, ped_hop=smp.ped_hop,
            length=t.length[self.slots], width=t.width[self.slots], height=t.height[self.slots],
            sumo_len=self.sumo_len, sumo_wid=self.sumo_wid, limits=self.limits, reach=self._reach, before=before,
            guard=self._guard,
        )

    def _act(self, s: Step, v: Verdict, st: StepStats, step: int) -> None:
        """The verdict into the world and the fleet: carries, placements (each counted by
        cause), ghosts, the errors the first tick starts from."""
        self._carry(s, v)
        self.sliding, self._rolls_back = v.sliding, v.rolls_back
        place, held, e_lon = v.cause != Cause.NONE, s.held, s.e_lon
        if place.any():
            idx = np.flatnonzero(place)
            slide = v.sliding[idx]  # a slide's start: placed as it stands
            if slide.any():
                self._place_slide(idx[slide], held, s.obs.yaw, count=True)
            self._place(idx[~slide], held, count=True)
            self.state.integ[idx] = 0.0
            e_lon[idx] = 0.0
        jumped, diverged, flipped = v.placed(Cause.JUMP), v.placed(Cause.DIVERGENCE), v.placed(Cause.FLIP)
        st.jumped, st.diverged, st.flipped = int(jumped.sum()), int(diverged.sum()), int(flipped.sum())
        for cause, k in ((Cause.SPAWN, st.spawned), (Cause.JUMP, st.jumped), (Cause.DIVERGENCE, st.diverged),
                         (Cause.FLIP, st.flipped)):
            self.counters[f"placements_{cause.name.lower()}"] += k
        for name, k in v.counts.items():
            self.counters[name] += k
        if st.diverged or st.flipped:
            log.warning("step %d: placed %d diverged %s, %d flipped %s", step, st.diverged,
                        [self.ids[i] for i in np.flatnonzero(diverged)][:LOG_IDS], st.flipped,
                        [self.ids[i] for i in np.flatnonzero(flipped)][:LOG_IDS])
        placed_obs = self.world.observe(self.slots) if place.any() else s.obs  # (also the first tick's start state)
        self._update_ghosts(placed_obs, s.is_new, place, s.before.ghost)
        self.jump_t = s.before.jump_t
        self.jump_t[jumped | ((s.flags & AgentFlag.JUMPED) != 0)] = s.t
        if self._collisions.pending:
            self._recheck_collisions()
        # along-path position of each bumper on the new path (``obs`` predates the placements:
        # placed agents sit exactly at s = 0)
        self.s_act = (np.where(place, held.s, s.ref.project_far(s.obs.fx, s.obs.fy, held.s + e_lon, tau=self.tau)[0])
                      if s.n else e_lon.copy())
        self.drive, self.brake, self.aux = np.zeros(s.n), np.zeros(s.n), np.zeros(s.n)
        self.err_lon = np.where(place, 0.0, e_lon)
        self.err_lat = np.where(place, 0.0, s.e_lat)
        self._cache = (placed_obs, None)  # the first tick starts from the state after the placements

    def _carry(self, s: Step, v: Verdict) -> None:
        """Carries of this step (manoeuvre or contact, never agents physics owns): the modes,
        each carry's glide onto SUMO's pose (``carry_pose.start_glide``), counted."""
        was = s.before.carried
        now = (v.manoeuvre | v.guard) & ~s.authoritative
        self.carried = now
        began = now & ~was
        # a carry the guard started stays the guard's while the manoeuvre keeps it
        contact = now & (v.guard | (was & s.before.guarded))
        self.guarded = contact
        yaw0 = self._kin_pose(s.held, self.tau)[0] if began.any() else None
        self.kin_off, self.kin_age = carry_pose.start_glide(s.prev, was, began, s.obs, s.held, yaw0, self.kin_off,
                                                            self.kin_age)
        self.mode = v.mode
        policies.carry.count(v, s, now, began, contact)

    def _update_ghosts(self, obs, is_new: np.ndarray, placed: np.ndarray, ghost: np.ndarray) -> None:
        """Ghosts (``contacts.ghosts``) after this step's placements (``obs``: the state after
        them; ``ghost``: last step's ghosts)."""
        ghost = ghost & ~is_new
        if self.n == 0:
            self.ghost = ghost
            return
        t_ = self.world.tables
        L, W = t_.length[self.slots], t_.width[self.slots]
        cx, cy = centre(obs.fx, obs.fy, obs.yaw, L)
        self.ghost, fresh = contacts.ghosts(cx, cy, obs.yaw, L, W, self.kind == M.KIND_PED, ghost, placed)
        self._set_bits()  # every step: a recompile resets the bits, and the modes change
        self.counters["ghost_spawns"] += int((fresh & is_new).sum())
        self.counters["ghost_placements"] += int((fresh & ~is_new).sum())

    def _set_bits(self) -> None:
        """The world's collision bits of every agent: ghosts, and bodies placed every tick."""
        placed = (self.mode == AgentMode.KINEMATIC) | (self.mode == AgentMode.EXTERNAL)
        self.world.set_ghost(self.slots, self.ghost, placed)

    def _sumo_overlaps(self, idx: np.ndarray, ref: Reference) -> np.ndarray:
        return contacts.sumo_overlaps(idx, ref.held(), self.sumo_len, self.sumo_wid, self.kind == M.KIND_PED)

    def _split_collisions(self, began: np.ndarray) -> None:
        """Count collisions that began (``contacts.CollisionBook``): SUMO's where its footprints
        overlap at the interval's start or (interpolating) end sample, or after a jump."""
        t = self.ref.t_k
        idx = np.flatnonzero(began)
        sumo = contacts.excused(t, self.jump_t[idx]) | self._sumo_overlaps(idx, self.ref)
        final = self._sample_ref is not self.ref  # interpolating: the interval's end sample is known
        if final:
            sumo |= self._sumo_overlaps(idx, self._sample_ref)
        self._ghost_sumo_overlaps(self._collisions.began(idx, t, sumo, final, self.ids, self.counters))

    def _recheck_collisions(self) -> None:
        moved = self._collisions.recheck(self._index, self._sample_ref.t_k,
                                         lambda idx: self._sumo_overlaps(idx, self._sample_ref), self.ids, self.counters)
        self._ghost_sumo_overlaps(moved)

    def _ghost_sumo_overlaps(self, idx: np.ndarray) -> None:
        """Agents touching where SUMO has them overlap pass through each other as in SUMO (ghosts
        until clear): pushing them apart knocked them into third agents."""
        if len(idx):
            self.ghost = self.ghost.copy()
            self.ghost[idx] = True
            self._set_bits()
            self.counters["ghost_sumo_overlaps"] += len(idx)

    def _place_slide(self, idx: np.ndarray, at, yaw: np.ndarray, count: bool) -> None:
        """Place standing agents ``idx`` that SUMO slides sideways at ``at`` as they stand (body
        ``yaw``, full length), wheels straight: in the steady-turn pose of a bend at the bumper a
        stopped 6.5 m van turned 11 deg, its rear into passing traffic; on SUMO's angle (which
        turns with the lane change, 38 deg while standing) a car's rear swung into the next lane."""
        self._place(idx, replace(at, curvature=np.zeros_like(at.curvature)), count=count, steady_turn=False, yaw=yaw)

    def _place(self, idx: np.ndarray, at, count: bool, steady_turn: bool = True,
               yaw: np.ndarray | None = None) -> None:
        """Place agents ``idx`` at reference point ``at`` (full-length arrays); ``yaw``
        (full length) replaces ``at.yaw`` as the body angle of a kinematic placement.
        Physical placements: the steady-turn pose for the path tangent; kinematic ones:
        SUMO's own body angle (the direct representation)."""
        if yaw is None:
            yaw = at.tangent if steady_turn else at.yaw
        if steady_turn:
            # a standing vehicle stands on SUMO's angle, wheels straight: in the steady-turn pose of
            # a bend that starts at its bumper, a car inserted standing there stood 37 deg off
            still = at.speed[idx] < sync.CARRY_SPEED
            if still.any():
                s_ = idx[still]
                self.world.place(self.slots[s_], at.x[s_], at.y[s_], at.yaw[s_], at.speed[s_], None,
                                 steady_turn=False, count=count)
                idx = idx[~still]
        if steady_turn and len(self._rear_idx):
            # a vehicle that steers its rear axle is placed on SUMO's chord, as it drives
            rear = self.limits.max_rear[idx] > 0
            if rear.any():
                r = idx[rear]
                self.world.place(self.slots[r], at.x[r], at.y[r], at.yaw[r], at.speed[r], at.curvature[r],
                                 steady_turn=False, count=count)
                idx = idx[~rear]
        self.world.place(self.slots[idx], at.x[idx], at.y[idx], yaw[idx], at.speed[idx], at.curvature[idx],
                         steady_turn=steady_turn, count=count)

    def _params(self) -> None:
        """The agents' model parameters and vehicle limits from the world's slot tables."""
        t = self.world.tables
        s = self.slots
        ped = self.kind == M.KIND_PED
        self.params = p = C.VehicleParams(
            wheelbase=np.where(ped, 1.0, t.wheelbase[s]), d_bumper=np.where(ped, 1.0, t.front[s] - t.rear_axle[s]),
            rear_axle=t.rear_axle[s], front_offset=t.front[s], m_eff=t.m_eff[s],
            r_wheel=np.where(ped, 1.0, t.r_wheel[s]), max_steer=t.max_steer[s],
            max_drive=t.max_drive[s], max_brake=t.max_brake[s], max_rear=t.max_rsteer[s],
        )
        # the configured stabiliser gains are the default bicycle's: a heavier or lower
        # two-wheeler gets them in proportion to gravity's toppling stiffness (280 kg
        # motorcycles were hardly stiffer than gravity and fell out of turns)
        self.limits = C.vehicle_limits(t.tyre_mu[s], t.mass[s], self.kind == M.KIND_BIKE, t.drive_grip[s], t.r_wheel[s],
                                       t.max_rsteer[s], t.roll_stiffness[s] / _BICYCLE_ROLL_STIFFNESS, t.stab_max[s])
        self._rear_idx = np.flatnonzero(self.limits.max_rear > 0)
        self._gen = self.world.generation
        self._groups = None
        # tightest path curvature [1/m] each vehicle's bumper follows when driven: its front
        # steering's; a steered rear axle keeps a long body on SUMO's chord rather than turning
        # it tighter (a truck released at 75 % of its four-wheel-steered limit ran 6 m wide)
        self._reach = C.bumper_curvature_limit(p.wheelbase, p.d_bumper, p.max_steer, None)

    def _kin_pose(self, at: ReferencePoint, tau: float) -> tuple[np.ndarray, ReferencePoint]:
        """Body angle [rad] of kinematic agents placed at ``at`` (``tau`` [s] past the sample),
        and ``at`` with the curvature they are placed turning at (``carry_pose.kinematic_pose``)."""
        carried = self.carried if len(self.carried) == self.n else np.zeros(self.n, bool)
        fix = None
        if self.interpolating and carried.any():
            if self._chord_end is None:  # once per SUMO step
                self._chord_end = carry_pose.chord_fix(self.ref, self.step_length, self._sumo_yaw, self.sumo_len)
            fix = self._chord_end
        rate = self.ref.yaw_rate if self.interpolating else self._kin_rate  # (interpolating: the next sample's known)
        return carry_pose.kinematic_pose(self.ref, at, tau, rate, self.step_length, self.interpolating,
                                         self.kind == M.KIND_PED, carried, self.limits.a_lat, self.sumo_len, fix)

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
        the sample: the presets' controllers, the kinematic agents' poses, the rear axles,
        then the vehicle limits, the bicycle stabiliser and the pedestrians' force control
        (all in ``control``). Writes nothing into the world (the controllers' integrators are
        ``self.state``)."""
        n, ref, p = self.n, self.ref, self.params
        if self._groups is None:
            self._groups = self._build_groups()
        g = self._groups
        stop_speed = stopping = None
        if self.stopping:
            stopping = np.ones(n, bool)
            stop_speed = np.maximum(self.stop_v0 - self.cfg.stop_decel * self.stop_t, 0.0)
        vobs = C.VehicleObs(obs.fx, obs.fy, obs.cx, obs.cy, obs.yaw, obs.speed, obs.yaw_rate, obs.fvx, obs.fvy)
        cmds = []
        if g.any_default:
            cmds.append((g.all_default, g.use_default, C.control_default(
                vobs, p, ref, tau, self.dt, self.ctl.default, self.state, stopping, self.cfg.stop_decel,
                stop_speed, s_guess=self.s_act, proj=proj, rolls_back=self._rolls_back)))
        if g.any_paper:
            cmds.append((g.all_paper, g.use_paper, C.control_paper(vobs, p, ref, self.ctl.paper)))
        steer, drive, brake, aux = C.merge_commands(n, cmds)
        at = kin_yaw = None
        if len(g.kin_idx):  # placed at the reference (``_actuate``), steering shown for its path
            kin_yaw, at = self._kin_pose(ref.at(tau), tau)
            steer[g.kin_idx] = np.arctan(p.wheelbase[g.kin_idx] * at.curvature[g.kin_idx])
        carry = carry_yaw = None
        if not self.stopping and self.sliding.any():  # standing, slid sideways by SUMO: follow the slide
            carry = np.flatnonzero(self.sliding)
            at = ref.at(tau) if at is None else at  # (a carried slide is placed straight anyway)
            carry_yaw = obs.yaw  # (this tick's observation: not written)
            drive[carry] = 0.0
        rear = self._rear_axle(steer, obs, tau) if len(self._rear_idx) else None
        catch_up = (C.CatchUp(ref, self.s_act, tau, g.use_default, self.err_lat)
                    if g.any_default and not self.stopping else None)
        steer, drive, brake = C.limit_commands(steer, drive, brake, obs, p, self.limits, rear is not None, catch_up)
        stab = None
        if len(g.veh_idx) and self.limits.any_bike:  # only bicycles have a stabiliser (the world skips the rest)
            d = self.ctl.default
            stab = C.bike_stabiliser(obs, steer, p, self.limits, g.veh_idx, d.bike_roll_kp, d.bike_roll_kd)
        ped = None
        if len(g.ped_idx):
            paper = (self.preset[g.ped_idx] == P_PAPER) & (not self.stopping)
            fx, fy, tz, force = C.pedestrian_control(g.ped_idx, obs, ref.at(tau), ref.held(), paper, stop_speed,
                                                     self.limits.mass, p.max_drive, self.ctl.paper, self.ctl.default)
            ped = (fx, fy, tz)
            drive[g.ped_idx] = force
        return _Commands(steer, drive, brake, aux, stab, ped, at, kin_yaw, carry, rear, carry_yaw)

    def _rear_axle(self, steer: np.ndarray, obs, tau: float) -> np.ndarray:
        """Rear-axle angles [rad] of long vehicles under our preset, the body onto SUMO's chord
        (``C.rear_axle_steer``; the paper's car keeps a fixed rear axle); their front angles
        in ``steer`` are replaced. SUMO's body angle moves at its rate between the last two
        samples (the chord's own rate: the path's curvature at the front is not the body's)."""
        ri = self._rear_idx
        ri = ri[(self.mode[ri] == AgentMode.PHYSICAL) & (self.preset[ri] == P_DEFAULT)]
        rear = np.zeros(self.n)
        rate = self._sumo_yaw_rate[ri]
        if self.stopping:
            yaw_ref, rate = obs.yaw[ri], np.zeros(len(ri))
        else:
            yaw_ref = self._sumo_yaw[ri] + rate * (min(tau, self.max_extrapolation) - self.lag)
        p = self.params
        steer[ri], rear[ri] = C.rear_axle_steer(
            steer[ri], obs.yaw[ri], obs.speed[ri], yaw_ref, rate, p.wheelbase[ri], p.d_bumper[ri],
            p.max_steer[ri], self.limits.max_rear[ri], a_lat=self.limits.a_lat[ri],
        )
        return rear

    def _actuate(self, u: _Commands, obs) -> None:
        """Write the commands into the world: kinematic agents and SUMO's sideways slides
        placed at the reference (a carry gliding onto it), vehicles' steering / drive /
        brakes, pedestrians' forces."""
        w = self.world
        g = self._groups
        if len(g.kin_idx):
            at, yaw = u.at, u.kin_yaw
            if len(self.kin_age) == self.n and np.isfinite(self.kin_age).any():
                at, yaw = carry_pose.glide(at, yaw, self.kin_off, self.kin_age)
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
        obs2 = self.world.observe(self.slots)
        s_guess = self.s_act + np.maximum(obs.speed, 0.0) * self.dt
        r2, (s2, lat2, pp2) = self.ref.at_and_project(min(self.tau, self.max_extrapolation), obs2.fx, obs2.fy, s_guess)
        self.s_act = s2
        self.err_lon = s2 - r2.s
        self.err_lat = lat2
        self.drive = u.drive
        self.brake = u.brake
        self.aux = u.aux
        self.touching, began = self.world.contacts(self.slots, placement.upright(obs2.roll, obs2.pitch,
                                                                                 self.cfg.flip_deg))
        if began.any():
            self._split_collisions(began)
        self._last_obs = obs2
        self._cache = (obs2, (s2, lat2, pp2))

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


__all__ = ["DebugState", "Fleet", "StepStats", "P_DEFAULT", "P_KINEMATIC", "P_PAPER"]
