"""``Fleet``: the agents of the current SUMO step as aligned arrays; syncs them on each step, drives them each tick.

One object between the transport (``daemon``) and the world (``world``); the control
laws are ``control``'s, the rules that reconcile SUMO's motion with physics are
``policies``', the references ``reference``'s; none of them calls back here:

- ``apply_step(msg)``: sync (the agent set: spawn, park, retype; each agent's previous
  sample; the reference) -> detect (the rules of ``policies.POLICIES`` in table order:
  spawn, manoeuvre and contact carries, roll back, jump, slide, flip, divergence) -> act
  (carries, placements, ghosts, each counted).
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

import time
from dataclasses import dataclass
from itertools import repeat
from types import MappingProxyType
from typing import NamedTuple

import numpy as np

from physics_side import control as C
from physics_side import models as M
from physics_side import policies
from physics_side.config import PhysicsSettings, Rates
from physics_side.control import P_DEFAULT, P_KINEMATIC, P_PAPER, PRESET_CODE
from physics_side.faults import Faults
from physics_side.policies import carry_pose, placement, sync
from physics_side.policies.base import Cause, Step, Verdict
from physics_side.policies.footprints import centre
from physics_side.policies.state import PolicyState
from physics_side.reference import Reference, ReferencePoint, tracking_error
from physics_side.world import PhysicsWorld
from protocol.frames import yaw_to_sumo_angle
from protocol.messages import AgentBatch, AgentClass, AgentFlag, AgentMode, PhysicsAgents, PhysicsFeedback, StepMessage

_TYPE_NAME = {
    AgentClass.PASSENGER: "passenger", AgentClass.TAXI: "taxi", AgentClass.BUS: "bus",
    AgentClass.BICYCLE: "bicycle", AgentClass.PEDESTRIAN: "pedestrian", AgentClass.OTHER: "other",
}
_BICYCLE_ROLL_STIFFNESS = M.default_spec(AgentClass.BICYCLE).roll_stiffness  # [N*m/rad] the stabiliser gains' reference
TIME_EPS_S = 1e-9  # [s] step lengths closer than this to interpolate_above_s are not above it
#: phases of ``Fleet.phase_s``: per SUMO step (sync, the policies' detect, act on the verdict)
#: and per control tick (observe, control, actuate, MuJoCo's step with its call, measure)
FLEET_PHASES = ("sync", "policies", "act", "observe", "control", "actuate", "mujoco", "measure")


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


_N_MODES = max(AgentMode) + 1


class DebugState(NamedTuple):
    """A read-only look at the policies' state (``Fleet.debug_state``), for tests and tools."""

    guard_pairs: MappingProxyType  # pairs the contact guard carries: (id, id) -> SUMO time [s] last near
    carried: np.ndarray  # carried for a manoeuvre or a contact, bool per agent
    sliding: np.ndarray  # carried along SUMO's sideways slide, bool per agent
    rolls_back: np.ndarray  # may roll back to a standing reference, bool per agent
    pending_collisions: tuple[str, ...]  # physics-only collisions re-checked at the next sample


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
        self._preset_lut = np.array([PRESET_CODE[self.cfg.preset_for(_TYPE_NAME[c])] for c in AgentClass], np.int8)
        self.counters: dict[str, int] = {
            "steps": 0, "placements_spawn": 0, "placements_jump": 0, "placements_divergence": 0,
            "placements_flip": 0, "resyncs": 0, "skipped_inside_vehicle": 0,
            **{c: 0 for c in policies.COUNTERS},
        }
        self.wire_vtype = np.zeros(0, np.uint16)  # vType index per agent of the newest step
        self.sumo_step = -1
        self.step_length = rates.ticks_per_step * rates.control_dt  # [s] of the newest SUMO step
        self.tick_count = 0
        # [s] wall time per phase of the Python part (cumulative; ``bench physics`` rows):
        # what the fleet adds to MuJoCo's own step, where it goes
        self.phase_s = dict.fromkeys(FLEET_PHASES, 0.0)
        self.stopping = False
        # two-way coupling: True in the one instance SUMO follows (the daemon sets it); there
        # agents flagged PHYSICS_AUTHORITY are never carried: physics drives them, SUMO follows
        self.two_way = False
        self.authoritative = np.zeros(0, bool)
        self.touching = np.zeros(0, bool)  # agents touching another agent's body at the last tick
        self.faults = Faults(self.cfg.stall, self.cfg.brake_failure)
        self._stalled: np.ndarray | None = None
        self._unbraked: np.ndarray | None = None
        self.ids: list[str] = []
        self._index: dict[str, int] = {}
        self.slots = np.zeros(0, np.int64)
        self.wire_cls = np.zeros(0, np.uint8)
        self.preset = np.zeros(0, np.int8)
        self.mode = np.zeros(0, np.uint8)
        self.kind = np.zeros(0, np.int8)
        self.ref: Reference | None = None
        self._samples = sync.Samples()  # each agent's previous SUMO sample
        self.sumo_len = self.sumo_wid = np.zeros(0)  # SUMO's length and width [m]
        self._policy = PolicyState()  # the policies' state from step to step
        self.tau = 0.0
        self.state = C.ControlState.zeros(0)
        self.s_act = self.drive = self.brake = self.aux = self.err_lon = self.err_lat = np.zeros(0)
        self.stop_v0 = np.zeros(0)
        self.stop_t = 0.0
        self._gen = -1
        self._params_slots = np.zeros(0, np.int64)
        self._bits = None  # what ``_set_bits`` set last: ((generation, bits version), slots, ghost, placed)
        self._groups: C.Groups | None = None
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

    @property
    def ghost(self) -> np.ndarray:
        """Agents without agent contact until clear (``policies.contacts``), bool."""
        return self._policy.ghost

    def debug_state(self) -> DebugState:
        """The policies' state, read-only (copies)."""
        ps = self._policy
        return DebugState(MappingProxyType(dict(ps.guard.pairs)), ps.carried.copy(), ps.sliding.copy(),
                          ps.rolls_back.copy(), tuple(ps.collisions.pending))

    # ------------------------------------------------------------------ step sync

    def reserve(self, agents: AgentBatch, vtypes: list | None = None) -> int:
        """Pools for every size in ``agents`` (e.g. a whole step, other shards' agents too),
        compiled in the background (``PhysicsWorld.reserve``); returns the new pools."""
        if vtypes is not None and list(vtypes) != self._vtypes:
            self._vtypes = list(vtypes)
            self._reserved.clear()  # vType indexes may mean other types now
        if agents.n == 0:
            return 0
        key = sync.pool_keys(agents.cls, agents.vtype, agents.length, agents.width)
        todo = [k for k in np.unique(key).tolist() if k not in self._reserved]
        if not todo:
            return 0
        self._reserved.update(todo)
        cls, vtype, length, width = sync.unpack_pool_keys(np.asarray(todo, np.int64))
        fam = sync.families(cls, vtype, length, self._vtypes, self._warned_vclass)
        return self.world.reserve(zip(fam, length, width))

    def apply_step(self, msg: StepMessage, resync: bool = False, tau: float = 0.0, restart: bool = False) -> StepStats:
        """Sync with a SUMO step: the agent set, each agent's previous sample and the reference
        (``_sync``), then the policies' detect phase in table order (``policies.DETECT``), then
        act on their verdict (``_act``). ``resync`` after a SUMO restart; ``tau`` [s]: how far
        physics time is past the step's time (steps shorter than a control tick, realtime
        jitter): placements and errors use the reference then. ``restart``: a new incarnation of
        the run (another epoch, SPEC 3.1.1): every agent of the old one leaves (parked), so an
        id that comes again is a new agent, spawned and placed."""
        self._cache = self._last_obs = None
        st = StepStats()
        ph, clock = self.phase_s, time.perf_counter
        t0 = clock()
        if restart:
            self._forget()
        s = self._sync(msg, resync or restart, tau, st)
        t1 = clock()
        v = Verdict.empty(s)
        for policy in policies.DETECT:
            policy.detect(s, v)
        t2 = clock()
        self._act(s, v, st, msg.step)
        t3 = clock()
        ph["sync"] += t1 - t0
        ph["policies"] += t2 - t1
        ph["act"] += t3 - t2
        self.sumo_step = msg.step
        self.counters["steps"] += 1
        if resync:
            self.counters["resyncs"] += 1
        return st

    def _forget(self) -> None:
        """Park every agent and drop what the fleet kept of them (a new incarnation of the run)."""
        if self.ids:
            self.world.park(self.world.slot_of(self.ids))
        self.ids, self._index = [], {}
        self.wire_vtype = np.zeros(0, np.uint16)
        self.wire_cls = np.zeros(0, np.uint8)
        self._samples = sync.Samples()
        self.counters["restarts"] = self.counters.get("restarts", 0) + 1

    def _sync(self, msg: StepMessage, resync: bool, tau: float, st: StepStats) -> Step:
        """The agent set (parked, retyped, spawned), each agent's previous sample, the
        reference, the bodies before any placement: the ``Step`` the policies read."""
        a = msg.agents
        self.step_length = float(msg.step_length)
        rows = np.flatnonzero((a.flags & AgentFlag.INSIDE_VEHICLE) == 0)
        st.skipped = a.n - len(rows)
        self.counters["skipped_inside_vehicle"] += st.skipped
        ids = list(a.ids) if len(rows) == a.n else [a.ids[i] for i in rows]  # (usually nobody rides)
        if msg.vtypes is not None:  # a step carries the table only when it changed (SPEC 3.1)
            self._vtypes = list(msg.vtypes)
        prev, old = self._membership(msg, rows, ids, resync, st)
        smp = self._samples.advance(msg, rows, ids, prev, old, self.cfg, self.interpolating, self.kind)
        is_new = self._spawn(msg, rows, ids, st)
        self._adopt(msg, rows, ids, prev, smp.ref, tau)
        return self._step(msg, rows, prev, is_new, old, smp)

    def _membership(self, msg: StepMessage, rows: np.ndarray, ids: list[str], resync: bool,
                    st: StepStats) -> tuple[np.ndarray, Reference | None]:
        """Park agents that left or changed type; each agent's row in the previous step (-1:
        none) and the previous sample (None after a resync or a stale one: ``sync.stale``)."""
        w, a = self.world, msg.agents
        if ids == self.ids:  # the same agents in the same order (a C-level compare): nothing to look up
            prev = np.arange(len(ids))
        else:
            new_set = set(ids)
            gone = [aid for aid in self.ids if aid not in new_set]
            if gone:
                w.park(w.slot_of(gone))
                st.parked = len(gone)
            prev = np.fromiter(map(self._index.get, ids, repeat(-1)), np.int64, len(ids))
        retyped = sync.retyped(prev, self.wire_vtype, self.wire_cls, len(self._index), a.vtype[rows], a.cls[rows])
        if len(retyped):
            w.park(w.slot_of([ids[i] for i in retyped]))
            prev[retyped] = -1
            st.retyped = len(retyped)
            self.counters["retyped"] += len(retyped)
        old = self._samples.newest
        if resync or (old is not None and sync.stale(msg.time, old.t_k, msg.step_length)):
            old = None
            prev[:] = -1
        return prev, old

    def _spawn(self, msg: StepMessage, rows: np.ndarray, ids: list[str], st: StepStats) -> np.ndarray:
        """Slots for this step's agents, new ones allocated in their model's pool; returns the new (bool)."""
        w, a = self.world, msg.agents
        slots = w.slot_of(ids)
        new = np.flatnonzero(slots < 0)
        if len(new):
            fam = sync.families(a.cls[rows[new]], a.vtype[rows[new]], a.length[rows[new]], self._vtypes,
                                self._warned_vclass)
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
        self.preset = preset = self._preset_lut[cls]
        if ids != self.ids:  # (the same agents in the same order: the index stands)
            self._index = dict(zip(ids, range(len(ids))))
        self.ids = ids
        self.wire_vtype = a.vtype[rows].astype(np.uint16)
        self.wire_cls = cls.astype(np.uint8)
        self.kind = self.world.tables.kind[self.slots].astype(np.int8)
        self.authoritative = ((flags & AgentFlag.PHYSICS_AUTHORITY) != 0) & self.two_way
        self.touching = np.zeros(len(ids), bool)
        self._stalled = self.faults.stalled(self._index, len(ids), msg.time)
        self._unbraked = self.faults.unbraked(self._index, len(ids), msg.time)
        mode = np.where(preset == P_KINEMATIC, AgentMode.KINEMATIC, AgentMode.PHYSICAL)
        self.mode = np.where((flags & AgentFlag.EGO) != 0, AgentMode.EXTERNAL, mode).astype(np.uint8)
        self.ref = ref
        self.tau = max(0.0, float(tau))
        self.state = self.state.take(prev)
        self.stopping = False
        if self._gen != self.world.generation or not np.array_equal(self.slots, self._params_slots):
            self._params()
        self._groups = None  # (the modes changed)
        self.sumo_len, self.sumo_wid = a.length[rows].astype(np.float64), a.width[rows].astype(np.float64)

    def _step(self, msg: StepMessage, rows: np.ndarray, prev: np.ndarray, is_new: np.ndarray,
              old: Reference | None, smp: sync.Sample) -> Step:
        """The ``Step`` the policies read: the bodies before any placement against the reference."""
        ref = smp.ref
        obs = self.world.observe(self.slots)
        held = (ref.at(min(self.tau, self.max_extrapolation)) if self.tau > 0 or self.interpolating
                else ref.held())
        e_lon, e_lat = tracking_error(obs.fx, obs.fy, held)
        t = self.world.tables
        return Step(
            cfg=self.cfg, ctl=self.ctl, t=msg.time, gap=msg.time - old.t_k if old is not None else 0.0,
            step_length=self.step_length, interpolating=self.interpolating, tau=self.tau,
            horizon=min(self.tau, self.max_extrapolation), ids=self.ids, index=self._index, prev=prev,
            is_new=is_new, flags=msg.agents.flags[rows], kind=self.kind, mode=self.mode,
            authoritative=self.authoritative, x=smp.x, y=smp.y, speed=smp.speed, yaw_rate=smp.yaw_rate,
            kin_rate=self._samples.kin_rate, old=old, ref=ref, held=held, obs=obs, e_lon=e_lon, e_lat=e_lat,
            dist=np.hypot(e_lon, e_lat), side_rate=smp.side_rate, slow=smp.slow, hop=smp.hop, ped_hop=smp.ped_hop,
            length=t.length[self.slots], width=t.width[self.slots], height=t.height[self.slots],
            sumo_len=self.sumo_len, sumo_wid=self.sumo_wid, limits=self.limits, reach=self._reach,
            before=self._policy.previous(prev), guard=self._policy.guard,
        )

    def _act(self, s: Step, v: Verdict, st: StepStats, step: int) -> None:
        """The verdict into the world and the fleet: carries, placements (each counted by
        cause), ghosts, the errors the first tick starts from."""
        ps = self._policy
        ps.settle_carries(s, v, lambda: self._kin_pose(s.held, self.tau)[0])
        self.mode = v.mode
        place = placement.act(self.world, self.slots, s, v, self.limits.max_rear, step)
        self.state.integ[place] = 0.0
        st.jumped, st.diverged, st.flipped = (int(v.placed(c).sum()) for c in placement.COUNTED)
        for name, k in v.counts.items():
            self.counters[name] += k
        placed_obs = self.world.observe(self.slots) if place.any() else s.obs  # (also the first tick's start state)
        cx, cy = centre(placed_obs.fx, placed_obs.fy, placed_obs.yaw, s.length)
        fresh = ps.settle_ghosts(s, cx, cy, placed_obs.yaw, s.length, s.width, s.kind == M.KIND_PED, place)
        if s.n:
            self._set_bits()  # every step: a recompile resets the bits, and the modes change
        self.counters["ghost_spawns"] += int((fresh & s.is_new).sum())
        self.counters["ghost_placements"] += int((fresh & ~s.is_new).sum())
        ps.settle_jumps(s, v.placed(Cause.JUMP) | ((s.flags & AgentFlag.JUMPED) != 0))
        if ps.collisions.pending:
            self._ghost_sumo_overlaps(ps.recheck_collisions(self._samples.newest, s.sumo_len, s.sumo_wid,
                                                            s.kind == M.KIND_PED, s.index, s.ids, self.counters))
        # along-path position of each bumper on the new path (``obs`` predates the placements:
        # placed agents sit exactly at s = 0)
        held, e_lon = s.held, np.where(place, 0.0, s.e_lon)  # (placed agents are on their reference)
        self.s_act = (np.where(place, held.s, s.ref.project_far(s.obs.fx, s.obs.fy, held.s + e_lon, tau=self.tau)[0])
                      if s.n else e_lon.copy())
        self.drive, self.brake, self.aux = np.zeros(s.n), np.zeros(s.n), np.zeros(s.n)
        self.err_lon = np.where(place, 0.0, e_lon)
        self.err_lat = np.where(place, 0.0, s.e_lat)
        self._cache = (placed_obs, None)  # the first tick starts from the state after the placements

    def _set_bits(self) -> None:
        """The world's collision bits of every agent: ghosts, and bodies placed every tick.
        Skipped when they would be the bits already set: the same slots, ghosts and placed
        bodies, and no other change of bits since (a park, a recompile)."""
        placed = (self.mode == AgentMode.KINEMATIC) | (self.mode == AgentMode.EXTERNAL)
        ghost = self._policy.ghost
        w, last = self.world, self._bits
        if (last is not None and last[0] == (w.generation, w.bits_version) and np.array_equal(last[1], self.slots)
                and np.array_equal(last[2], ghost) and np.array_equal(last[3], placed)):
            return
        w.set_ghost(self.slots, ghost, placed)
        self._bits = ((w.generation, w.bits_version), self.slots.copy(), np.array(ghost, bool), placed)

    def _split_collisions(self, began: np.ndarray) -> None:
        self._ghost_sumo_overlaps(self._policy.collisions_began(began, self.ref, self._samples.newest, self.sumo_len,
                                                                self.sumo_wid, self.kind == M.KIND_PED, self.ids,
                                                                self.counters))

    def _ghost_sumo_overlaps(self, idx: np.ndarray) -> None:
        """Agents touching where SUMO has them overlap pass through each other as in SUMO (ghosts
        until clear): pushing them apart knocked them into third agents."""
        if len(idx):
            self._policy.make_ghosts(idx)
            self._set_bits()
            self.counters["ghost_sumo_overlaps"] += len(idx)

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
        self._params_slots = self.slots.copy()  # the slots these are of (tables change only with the generation)
        self._groups = None
        # tightest path curvature [1/m] each vehicle's bumper follows when driven: its front
        # steering's; a steered rear axle keeps a long body on SUMO's chord rather than turning
        # it tighter (a truck released at 75 % of its four-wheel-steered limit ran 6 m wide)
        self._reach = C.bumper_curvature_limit(p.wheelbase, p.d_bumper, p.max_steer, None)

    def _kin_pose(self, at: ReferencePoint, tau: float) -> tuple[np.ndarray, ReferencePoint]:
        """Body angle [rad] of kinematic agents placed at ``at`` (``tau`` [s] past the sample),
        and ``at`` with the curvature they are placed turning at (``carry_pose.kinematic_pose``)."""
        ps = self._policy
        carried = ps.carried if len(ps.carried) == self.n else np.zeros(self.n, bool)
        fix = None
        if self.interpolating and carried.any():
            if ps.chord_end is None:  # once per SUMO step
                ps.chord_end = carry_pose.chord_fix(self.ref, self.step_length, self._samples.yaw, self.sumo_len)
            fix = ps.chord_end
        rate = self.ref.yaw_rate if self.interpolating else self._samples.kin_rate  # (interpolating: the next's known)
        return carry_pose.kinematic_pose(self.ref, at, tau, rate, self.step_length, self.interpolating,
                                         self.kind == M.KIND_PED, carried, self.limits.a_lat, self.sumo_len, fix)

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
        ph, clock = self.phase_s, time.perf_counter
        t0 = clock()
        obs, proj = self._observe()
        tau = min(self.tau, self.max_extrapolation)
        t1 = clock()
        u = self._control(obs, proj, tau)
        if self._stalled is not None:  # faults: a stalled vehicle brakes fully, no drive
            u.drive[self._stalled] = 0.0
            u.brake[self._stalled] = self.world.tables.max_brake[self.slots[self._stalled]]
        if self._unbraked is not None:  # faults: no drive, no brakes: it coasts
            u.drive[self._unbraked] = 0.0
            u.brake[self._unbraked] = 0.0
        t2 = clock()
        self._actuate(u, obs)
        t3 = clock()
        w.step()
        t4 = clock()
        self.tick_count += 1
        self.tau += self.dt
        if self.stopping:
            self.stop_t += self.dt
        self._measure(obs, u)
        ph["observe"] += t1 - t0
        ph["control"] += t2 - t1
        ph["actuate"] += t3 - t2
        ph["mujoco"] += t4 - t3
        ph["measure"] += clock() - t4

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

    def _control(self, obs, proj, tau: float) -> C.Commands:
        """Commands for every agent from the observation and the reference ``tau`` [s] past
        the sample: the presets' controllers, the kinematic agents' poses, the rear axles,
        then the vehicle limits, the bicycle stabiliser and the pedestrians' force control
        (all in ``control``). Writes nothing into the world (the controllers' integrators are
        ``self.state``)."""
        n, ref, p = self.n, self.ref, self.params
        if self._groups is None:
            self._groups = C.groups(self.kind == M.KIND_PED, self.mode, self.preset, self.stopping, self.slots)
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
                stop_speed, s_guess=self.s_act, proj=proj, rolls_back=self._policy.rolls_back)))
        if g.any_paper:
            cmds.append((g.all_paper, g.use_paper, C.control_paper(vobs, p, ref, self.ctl.paper)))
        steer, drive, brake, aux = C.merge_commands(n, cmds)
        at = kin_yaw = None
        if len(g.kin_idx):  # placed at the reference (``_actuate``), steering shown for its path
            kin_yaw, at = self._kin_pose(ref.at(tau), tau)
            steer[g.kin_idx] = np.arctan(p.wheelbase[g.kin_idx] * at.curvature[g.kin_idx])
        carry = carry_yaw = None
        if not self.stopping and self._policy.sliding.any():  # standing, slid sideways by SUMO: follow the slide
            carry = np.flatnonzero(self._policy.sliding)
            at = ref.at(tau) if at is None else at  # (a carried slide is placed straight anyway)
            carry_yaw = obs.yaw  # (this tick's observation: not written)
            drive[carry] = 0.0
        rear = None
        if len(self._rear_idx):  # long vehicles under our preset: the body onto SUMO's chord
            ri = self._rear_idx
            ri = ri[(self.mode[ri] == AgentMode.PHYSICAL) & (self.preset[ri] == P_DEFAULT)]
            ahead = None if self.stopping else min(tau, self.max_extrapolation) - self.lag
            sm = self._samples
            rear = C.rear_axle_commands(steer, obs, p, self.limits, ri, sm.yaw, sm.yaw_rate, ahead)
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
        return C.Commands(steer, drive, brake, aux, stab, ped, at, kin_yaw, carry, rear, carry_yaw)

    def _actuate(self, u: C.Commands, obs) -> None:
        """Write the commands into the world: kinematic agents and SUMO's sideways slides
        placed at the reference (a carry gliding onto it), vehicles' steering / drive /
        brakes, pedestrians' forces."""
        w = self.world
        g = self._groups
        if len(g.kin_idx):
            at, yaw = u.at, u.kin_yaw
            ps = self._policy
            if len(ps.kin_age) == self.n and np.isfinite(ps.kin_age).any():
                at, yaw = carry_pose.glide(at, yaw, ps.kin_off, ps.kin_age)
                ps.kin_age = ps.kin_age + self.dt
            placement.place(w, self.slots, g.kin_idx, at, None, count=False, steady_turn=False, yaw=yaw)
        if u.carry is not None:
            placement.place_slide(w, self.slots, u.carry, u.at, u.carry_yaw, count=False)
        vi = g.veh_idx
        if len(vi):
            if g.all_veh:
                w.command_vehicles(g.veh_slots, u.steer, u.drive, u.brake, u.stab, u.rear, obs.speed)
            else:
                w.command_vehicles(g.veh_slots, u.steer[vi], u.drive[vi], u.brake[vi], u.stab,
                                   None if u.rear is None else u.rear[vi], obs.speed[vi])
        if u.ped is not None:
            w.command_pedestrians(self.slots[g.ped_idx], *u.ped)

    def _measure(self, obs, u: C.Commands) -> None:
        """After the step: tracking errors against the extrapolated reference, contacts and
        collisions; the end state is the next tick's start state."""
        obs2 = self.world.observe(self.slots)
        s_guess = self.s_act + np.maximum(obs.speed, 0.0) * self.dt
        r2, (s2, lat2, pp2) = self.ref.at_and_project(min(self.tau, self.max_extrapolation), obs2.fx, obs2.fy, s_guess)
        self.s_act, self.err_lon, self.err_lat = s2, s2 - r2.s, lat2
        self.drive, self.brake, self.aux = u.drive, u.brake, u.aux
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
        # one bincount, not a comparison and a sum per mode: this runs with every state message
        c = np.bincount(np.asarray(self.mode, np.int64), minlength=_N_MODES).tolist()
        return {"physical": c[AgentMode.PHYSICAL], "kinematic": c[AgentMode.KINEMATIC],
                "external": c[AgentMode.EXTERNAL], "stopping": c[AgentMode.STOPPING]}


__all__ = ["DebugState", "FLEET_PHASES", "Fleet", "StepStats", "P_DEFAULT", "P_KINEMATIC", "P_PAPER"]
