"""``PhysicsWorld``: the per-tick world over the current layout, and the one owner of MuJoCo indices.

Per control tick: ``observe`` -> (controllers, outside: ``control``) -> ``place`` /
``command_vehicles`` / ``command_pedestrians`` (actuate) -> ``step`` -> ``contacts``.
Nothing outside this module indexes ``qpos``/``qvel``/``ctrl``: callers get named,
vectorised reads and writes over arrays of *slot numbers*.

Which slots exist and who holds them is ``pools.SlotPools`` (pools per model family and
size, growth in the background, allocation, parking), over a layout built by ``layout``:
``shards`` MuJoCo simulations of one model (``mujoco.batch.Batch``, stepped on a thread
pool; persistent because sleeping needs it). The world delegates ``pool_for`` /
``reserve`` / ``allocate`` / ``park`` / ``slot_of`` to it and rebinds its views when the
layout changes: slot numbers change then, ``generation`` increments.

Agents in different shards do not touch each other (they are in different
simulations); a new agent goes to the shard of the nearest live agent within
``pools.NEIGHBOUR_M`` (vehicles that follow each other share a shard) unless that shard
is over its share, else to the least-loaded shard.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, fields
from functools import cached_property
from typing import NamedTuple

import numpy as np

from physics_side import models as M
from physics_side.control import G, MAX_LEAN_TAN
from physics_side.kinematics import MAX_KAPPA_D, ackermann, ackermann_4ws, concat_ranges, steady_state_delta
from physics_side.layout import FREE_NQ, FREE_NV, FREE_POS, FREE_QUAT, FREE_WZ, PED_NQ, Layout, SlotTables
from physics_side.pools import HEADROOM, SLEEP_NEVER, SlotPools
from protocol.frames import wrap_pi
from protocol.messages import AgentClass
from runtime.native import numpy_math_is_libm, optional_extension

MAX_PLACE_CURVATURE = 0.2  # [1/m] placements assume at most a 5 m radius turn
# [1] tan of the steepest lean a placed two-wheeler takes (31 deg): the bicycles' stabiliser
# target cap, one value
PLACE_LEAN_TAN = MAX_LEAN_TAN
CONTACT_N = 1.0  # [N] chassis contact force that counts as touching
# Collision bits of placed (kinematic, external) bodies (``set_ghost``); the models' own:
# ground 1, chassis and frames 2, pedestrians 4 (``models``)
PED_BIT = M.PED_BIT
PLACED_VEHICLE_BIT = 8
PLACED_PED_BIT = 16
TCS_SLIP = 1.5  # [1] a heavy vehicle's driven wheel turning faster than this share of its speed ...
TCS_MARGIN_MPS = 5.0  # [m/s] ... plus this is spinning: braked by up to its drive share over ...
TCS_BAND_MPS = 5.0  # [m/s] ... this much more spin
CONTACT_GAP_S = 1.0  # [s] apart this long before a new touch counts as a new collision
PLAN_CACHE = 8  # [slot arrays] plans kept (a fleet uses a few slot arrays per step)

# The C paths of ``observe`` and ``command_vehicles`` for vehicles (bit-identical;
# ``SUMOCO_PURE_PHYSICS=1`` or no compiler: the numpy bodies). ``FAST_OBSERVE`` says which run.
_kernel = optional_extension("physics_side._worldkernel", "SUMOCO_PURE_PHYSICS")
if _kernel is not None and not numpy_math_is_libm():  # (its libm calls would not be numpy's bits)
    _kernel = None
FAST_OBSERVE: bool = _kernel is not None


@dataclass(frozen=True)
class Observation:
    """Measured state of a set of slots (arrays of length n), SUMO/MuJoCo world frame."""

    cx: np.ndarray
    """Body origin x [m]."""
    cy: np.ndarray
    """Body origin y [m]."""
    z: np.ndarray
    """Body origin height [m]."""
    fx: np.ndarray
    """Front bumper x [m]."""
    fy: np.ndarray
    """Front bumper y [m]."""
    yaw: np.ndarray
    """Heading [rad ccw from east]."""
    roll: np.ndarray
    """[rad], + = right side down."""
    pitch: np.ndarray
    """[rad], + = nose up."""
    speed: np.ndarray
    """Forward speed [m/s]."""
    vx: np.ndarray
    """World velocity x [m/s]."""
    vy: np.ndarray
    """World velocity y [m/s]."""
    yaw_rate: np.ndarray
    """[rad/s]."""
    roll_rate: np.ndarray
    """[rad/s]."""
    steer: np.ndarray
    """Road-wheel steering angle [rad, + left] (mean of the steered wheels)."""
    fvx: np.ndarray
    """Front-bumper velocity x [m/s] (body velocity plus yaw rate x lever)."""
    fvy: np.ndarray
    """Front-bumper velocity y [m/s]."""


OBSERVATION_ROWS = tuple(f.name for f in fields(Observation))  # (the C path's output rows, in this order)
_OBS_ROW = {name: i for i, name in enumerate(OBSERVATION_ROWS)}


class _SlotPlan:
    """Index arrays derived from one array of slot numbers, built on first use.

    A fleet reads and writes the same slots every control tick until the next SUMO step,
    so the gathers of ``SlotTables`` rows are done once per step, not once per tick.
    """

    def __init__(self, t: SlotTables, slots: np.ndarray):
        self.t = t
        self.slots = slots
        kind = t.kind[slots]
        self.ped = kind == M.KIND_PED
        self.veh = ~self.ped
        self.all_veh = bool(self.veh.all())
        self.any_veh = bool(self.veh.any())
        self.any_ped = bool(self.ped.any())
        self.front = t.front[slots]

    @cached_property
    def veh_front(self) -> np.ndarray:
        return np.ascontiguousarray(self.front[self.veh])

    @cached_property
    def veh_state(self) -> np.ndarray:
        """(15, n_veh) flat state indices: freejoint qpos (7), qvel (6), left/right steer qpos."""
        sv = self.slots[self.veh]
        t = self.t
        return np.concatenate([
            t.qpos[sv][None, :] + np.arange(FREE_NQ)[:, None], t.qvel[sv][None, :] + np.arange(FREE_NV)[:, None],
            t.steer_q[sv].T,
        ])

    @cached_property
    def ped_state(self) -> np.ndarray:
        """(6, n_ped) flat state indices: slide x, slide y, yaw hinge qpos, then their qvel."""
        sp = self.slots[self.ped]
        t = self.t
        k = np.arange(PED_NQ)[:, None]
        return np.concatenate([t.qpos[sp][None, :] + k, t.qvel[sp][None, :] + k])

    @cached_property
    def ped_park(self) -> tuple[np.ndarray, np.ndarray]:
        sp = self.slots[self.ped]
        return self.t.park_x[sp], self.t.park_y[sp]

    @cached_property
    def command(self) -> tuple:
        """wheelbase, track, left/right steer ctrl, drive ctrl, spin frictionloss (n, 4), brake share (n, 4)."""
        t, s = self.t, self.slots
        su = t.steer_u[s]
        return (t.wheelbase[s], t.track[s], su[:, 0].copy(), su[:, 1].copy(), t.drive_u[s], t.spin_fl[s],
                t.brake_share[s])

    @cached_property
    def traction(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """Rows of the slots with traction control, their spin qvel indices (k, 4), wheel radii
        (k, 1) and drive shares (k, 4); None: none."""
        t = self.t
        ok = np.flatnonzero(t.traction_control[self.slots] > 0)
        if not len(ok):
            return None
        s = self.slots[ok]
        return ok, t.spin_v[s], t.r_wheel[s][:, None], t.drive_share[s]

    @cached_property
    def rear(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Rows of the slots that steer their rear axle and their (n, 2) rear steer ctrl; None: none."""
        ru = self.t.rsteer_u[self.slots]
        ok = np.flatnonzero(ru[:, 0] >= 0)
        return (ok, ru[ok]) if len(ok) else None

    @cached_property
    def stab(self) -> tuple[np.ndarray, np.ndarray]:
        """Stabiliser ctrl index of the slots that have one, and which of the slots they are."""
        au = self.t.aux_u[self.slots][:, 0]
        ok = au >= 0
        return au[ok], ok

    @cached_property
    def body_force(self) -> np.ndarray:
        """(3, n) flat cfrc_ext indices of each root body's force."""
        b = self.t.body[self.slots]
        return np.stack([b, b + 1, b + 2])


class PhysicsWorld:
    """Pooled multi-agent MuJoCo world, per tick (see module docstring)."""

    def __init__(
        self, timestep: float = 0.005, substeps: int = 4, shards: int = 1, threads: int = 0,
        initial: dict[AgentClass, int] | None = None, pool_chunk: int = 32,
        awd: frozenset[AgentClass] = frozenset(), expect: dict[AgentClass, int] | None = None,
        adopt_early: bool = False,
    ):
        """``initial``, ``pool_chunk``, ``awd``, ``expect``, ``adopt_early``: the slot pools
        (``pools.SlotPools``); ``substeps`` MuJoCo steps of ``timestep`` [s] per control tick,
        on ``threads`` threads (default: one per shard)."""
        self.timestep = float(timestep)
        self.substeps = int(substeps)
        self.threads = int(threads) or int(shards)
        self.counters = {
            "placements": 0, "spawned": 0, "parked": 0, "collisions": 0, "pool_grows": 0, "growth_waits": 0,
        }
        self.mujoco_s = 0.0  # [s] wall time spent in MuJoCo steps (cumulative)
        self.mujoco_cpu_s = 0.0  # [s] CPU time of the process (all threads) in MuJoCo steps (cumulative)
        # Reading the process's CPU clock right after a threaded MuJoCo step costs 0.2-4 ms
        # (the kernel sums the pool's still-running threads): only benchmarks that report
        # MuJoCo's CPU time switch it on.
        self.measure_cpu = False
        self.time = 0.0  # [s] simulated time
        self.bits_version = 0  # counts ``set_ghost`` calls: collision bits written by anyone
        self.pools = SlotPools(
            self.timestep, shards, self.threads, initial, pool_chunk=pool_chunk, awd=awd, expect=expect,
            adopt_early=adopt_early, counters=self.counters,
        )
        self._layout: Layout | None = None
        self._bind()

    def _bind(self) -> None:
        """Views of the pools' current layout (after a switch: slot numbers changed; the
        contact memory starts afresh)."""
        layout = self.pools.layout
        if layout is self._layout:
            return
        self._layout = layout
        self.model = layout.model
        self._batch = layout.batch
        self._state = layout.state
        self._fl = layout.frictionloss
        self._policy = layout.sleep_policy
        self._cfrc = layout.cfrc_ext
        self._contype = layout.contype
        self._conaff = layout.conaffinity
        self._tables = layout.tables
        self._plans: dict[bytes, _SlotPlan] = {}
        G = layout.slots
        self.in_contact = np.zeros(G, bool)
        self.last_touch = np.full(G, -np.inf)

    # ------------------------------------------------------------------ slots (``SlotPools``)

    @property
    def generation(self) -> int:
        """Increments whenever slot numbers change (the layout was switched)."""
        return self.pools.generation

    @property
    def shards(self) -> int:
        return self.pools.shards

    @property
    def capacity(self) -> int:
        """Total slots over all pools and shards."""
        return self.pools.capacity

    @property
    def live(self) -> np.ndarray:
        """Which slots hold an agent (bool per slot)."""
        return self.pools.live

    @property
    def agent_slot(self) -> dict[str, int]:
        return self.pools.agent_slot

    @property
    def build_s(self) -> float:
        """[s] wall time spent compiling on the stepping thread (cumulative)."""
        return self.pools.build_s

    @property
    def wait_s(self) -> float:
        """[s] wall time spent waiting for a background growth (cumulative)."""
        return self.pools.wait_s

    @property
    def growing(self) -> bool:
        return self.pools.growing

    @property
    def growth_ready(self) -> bool:
        return self.pools.growth_ready

    def close(self) -> None:
        """Stop a background growth (its result is dropped)."""
        self.pools.close()

    def pool_for(self, family: str, length: float, width: float) -> int:
        """Pool index for an agent of a model family (``models.FAMILIES``) and size [m]."""
        return self.pools.pool_for(family, length, width)

    def slot_of(self, ids: list[str]) -> np.ndarray:
        """Current slot of each agent id, -1 when not in the world."""
        return self.pools.slot_of(ids)

    def reserve(self, sizes) -> int:
        """``SlotPools.reserve``: pools for sizes that may come, compiled in the background."""
        added = self.pools.reserve(sizes)
        self._bind()
        return added

    def allocate(self, ids: list[str], pools: np.ndarray, near_x: np.ndarray, near_y: np.ndarray) -> np.ndarray:
        """Take a slot for each new agent (growing pools if needed), in the shard of the
        live agent nearest to (``near_x``, ``near_y``) [m]; returns slot numbers.

        The slot is woken but not placed: call ``place`` next.
        """
        self.pools.make_room(pools)
        self._bind()
        live = np.flatnonzero(self.pools.live)
        obs = self.observe(live) if len(live) else None
        return self.pools.take(
            ids, pools, near_x, near_y, live, None if obs is None else obs.fx, None if obs is None else obs.fy,
        )

    def park(self, slots: np.ndarray) -> None:
        """Send slots back to the parking lot (zero velocity, brakes on) and let them sleep."""
        slots = np.asarray(slots, np.int64)
        if len(slots) == 0:
            return
        self.pools.park(slots)
        self.set_ghost(slots, False)
        self.in_contact[slots] = False
        self.last_touch[slots] = -np.inf

    def _plan(self, slots: np.ndarray) -> _SlotPlan:
        """The (cached) ``_SlotPlan`` of an int64 slot array; keyed by content, so callers
        may pass fresh arrays; dropped on recompile (slot numbers change)."""
        key = slots.tobytes()
        plan = self._plans.get(key)
        if plan is None:
            if len(self._plans) >= PLAN_CACHE:
                self._plans.clear()
            plan = self._plans[key] = _SlotPlan(self._tables, slots.copy())
        return plan

    # ------------------------------------------------------------------ reads

    def observe(self, slots: np.ndarray) -> Observation:
        """Vectorised state of ``slots`` (any mix of kinds)."""
        slots = np.asarray(slots, np.int64)
        plan = self._plan(slots)
        st = self._state
        if plan.all_veh and _kernel is not None:  # the usual case, in one C pass
            out = np.empty((len(OBSERVATION_ROWS), len(slots)))
            _kernel.observe(st, plan.veh_state, plan.front, out)
            return Observation(*out)
        if _kernel is not None:
            return self._observe_mixed(plan)
        if plan.all_veh:  # the usual case: one gather, no scatter
            cx, cy, z, yaw, roll, pitch, vx, vy, wz, wx, steer = _vehicle_state(st[plan.veh_state])
        else:
            n = len(slots)
            veh, ped = plan.veh, plan.ped
            # (what pedestrians have not - height, roll, pitch, roll rate, steering - stays 0)
            out = tuple(np.zeros(n) for _ in _VEHICLE_STATE)
            cx, cy, z, yaw, roll, pitch, vx, vy, wz, wx, steer = out
            if plan.any_veh:
                for arr, val in zip(out, _vehicle_state(st[plan.veh_state])):
                    arr[veh] = val
            if plan.any_ped:
                g = st[plan.ped_state]
                px, py = plan.ped_park
                cx[ped] = px + g[0]
                cy[ped] = py + g[1]
                yaw[ped] = wrap_pi(g[2])
                vx[ped], vy[ped], wz[ped] = g[3], g[4], g[5]
        c, s = np.cos(yaw), np.sin(yaw)
        front = plan.front
        wf = wz * front
        return Observation(
            cx=cx, cy=cy, z=z, fx=cx + front * c, fy=cy + front * s, yaw=yaw, roll=roll, pitch=pitch,
            speed=vx * c + vy * s, vx=vx, vy=vy, yaw_rate=wz, roll_rate=wx, steer=steer,
            fvx=vx - wf * s, fvy=vy + wf * c,
        )

    def _observe_mixed(self, plan: "_SlotPlan") -> Observation:
        """``observe`` of vehicles and pedestrians: the vehicles' rows in C, the pedestrians'
        in numpy (elementwise, the same values as the numpy body over all of them)."""
        st = self._state
        n = len(plan.slots)
        out = np.zeros((len(OBSERVATION_ROWS), n))  # (what pedestrians have not stays 0)
        if plan.any_veh:
            vout = np.empty((len(OBSERVATION_ROWS), int(plan.veh.sum())))
            _kernel.observe(st, plan.veh_state, plan.veh_front, vout)
            out[:, plan.veh] = vout
        if plan.any_ped:
            g = st[plan.ped_state]
            px, py = plan.ped_park
            cx, cy, yaw, vx, vy, wz = px + g[0], py + g[1], wrap_pi(g[2]), g[3], g[4], g[5]
            c, s = np.cos(yaw), np.sin(yaw)
            front = plan.front[plan.ped]
            wf = wz * front
            rows = {"cx": cx, "cy": cy, "fx": cx + front * c, "fy": cy + front * s, "yaw": yaw,
                    "speed": vx * c + vy * s, "vx": vx, "vy": vy, "yaw_rate": wz, "fvx": vx - wf * s,
                    "fvy": vy + wf * c}
            for name, val in rows.items():
                out[_OBS_ROW[name], plan.ped] = val
        return Observation(*out)

    def vehicle_pose(self, slots: np.ndarray) -> np.ndarray:
        """(n, 7) freejoint coordinates of vehicles: body origin x, y, z [m] and orientation as
        a unit quaternion (w, x, y, z), world frame."""
        return self._state[self._tables.qpos[self._vehicles(slots)][:, None] + np.arange(FREE_NQ)]

    def wheel_spin(self, slots: np.ndarray) -> np.ndarray:
        """(n, 4) angular velocity [rad/s] of the wheel of each brake column fl, fr, rl, rr of
        vehicles (a two-wheeler's wheels twice each)."""
        return self._state[self._tables.spin_v[self._vehicles(slots)]]

    def awake_trees(self, shard: int = 0) -> int:
        """Kinematic trees awake in one shard's simulation (every parked slot sleeps)."""
        return int(self._batch.get_data(shard).ntree_awake)

    def _vehicles(self, slots: np.ndarray) -> np.ndarray:
        """``slots`` as an int64 array, checked to hold vehicles only (freejoint, wheels)."""
        slots = np.asarray(slots, np.int64)
        if (self._tables.kind[slots] == M.KIND_PED).any():
            raise ValueError("pedestrians have no freejoint and no wheels (their pose: observe)")
        return slots

    # ------------------------------------------------------------------ writes

    def place(
        self, slots: np.ndarray, fx: np.ndarray, fy: np.ndarray, yaw: np.ndarray, speed: np.ndarray,
        curvature: np.ndarray | None = None, steady_turn: bool = True, count: bool = True,
    ) -> None:
        """Put agents with their *front bumper* at (fx, fy), moving along a path of heading
        ``yaw`` [rad] and ``curvature`` [1/m] at ``speed`` [m/s], wheels rolling.

        ``steady_turn``: the body takes the pose of a vehicle in a steady turn whose bumper
        follows the path (yaw lags the path heading by asin(kappa * d), rear axle without
        side slip, steering at the matching angle) - a spawn without a transient. Else the
        body yaw is the path heading (the SUMO angle: kinematic/external agents), still
        moving so that the bumper follows the path. Counted as placements unless ``count``
        is False (kinematic and external agents are placed every tick, counted apart).
        """
        slots = np.asarray(slots, np.int64)
        n = len(slots)
        if n == 0:
            return
        yaw = np.asarray(yaw, np.float64) * np.ones(n)
        speed = np.asarray(speed, np.float64) * np.ones(n)
        kappa = np.zeros(n) if curvature is None else np.asarray(curvature, np.float64) * np.ones(n)
        kappa = np.clip(kappa, -MAX_PLACE_CURVATURE, MAX_PLACE_CURVATURE)
        p = _placement(self._tables, slots, fx, fy, yaw, speed, kappa, steady_turn)
        if p.veh.any():
            self._place_vehicles(slots[p.veh], p, speed[p.veh], steady_turn)
        if p.ped.any():
            self._place_pedestrians(slots[p.ped], p)
        self._policy[self._tables.tree[slots]] = SLEEP_NEVER
        if count:
            self.counters["placements"] += n

    def _place_vehicles(self, sv: np.ndarray, p: "_Placement", speed: np.ndarray, steady_turn: bool) -> None:
        """Write the pose of the vehicles ``sv`` (rows ``p.veh`` of the placement ``p``)."""
        t = self._tables
        st = self._state
        veh = p.veh
        st[concat_ranges(t.qvel[sv], t.nv[sv])] = 0.0
        qb = t.qpos[sv]
        # bicycles lean into the turn at the steady-turn angle (roll about +x, left side
        # down in a left turn); cars stand level. Placed as SUMO has them (kinematic),
        # two-wheelers stay upright like its footprints: a carried motorcycle leaning
        # 31 deg swept its rider 0.5 m sideways into a pedestrian SUMO passed 0.45 m off.
        bike = (t.kind[sv] == M.KIND_BIKE) & steady_turn
        roll = np.where(bike, -np.arctan(np.clip(speed * p.omega[veh] / G, -PLACE_LEAN_TAN, PLACE_LEAN_TAN)), 0.0)
        quat = _quat_zyx(p.body_yaw[veh], t.rest_pitch[sv], roll)
        h = np.where(bike, t.rest_z[sv] * np.cos(roll), t.rest_z[sv])
        st[qb] = p.cx[veh]
        st[qb + 1] = p.cy[veh]
        st[qb + 2] = h
        for k in range(FREE_QUAT):
            st[qb + FREE_POS + k] = quat[:, k]
        vb = t.qvel[sv]
        st[vb] = p.vcx[veh]
        st[vb + 1] = p.vcy[veh]
        st[vb + FREE_WZ] = p.omega[veh]
        left, right = ackermann(p.steer[veh], t.wheelbase[sv], t.track[sv])
        sq = t.steer_q[sv]
        st[sq[:, 0]] = left
        st[sq[:, 1]] = right
        su = t.steer_u[sv]
        st[su[:, 0]] = left
        st[su[:, 1]] = right
        rq, ru = t.rsteer_q[sv], t.rsteer_u[sv]
        has = rq[:, 0] >= 0
        if has.any():  # a steered rear axle starts straight (fixed-axle pose above)
            st[rq[has].reshape(-1)] = 0.0
            st[ru[has].reshape(-1)] = 0.0
        # wheels rolling at the forward speed of the axle they are on (rear axle speed)
        v_r = p.vcx[veh] * p.c[veh] + p.vcy[veh] * p.s[veh]
        st[t.spin_v[sv]] = (v_r / t.r_wheel[sv])[:, None]

    def _place_pedestrians(self, sp: np.ndarray, p: "_Placement") -> None:
        """Write the pose of the pedestrians ``sp`` (rows ``p.ped`` of the placement ``p``):
        their slide joints are relative to their parking spot."""
        t = self._tables
        st = self._state
        ped = p.ped
        qb = t.qpos[sp]
        st[qb] = p.cx[ped] - t.park_x[sp]
        st[qb + 1] = p.cy[ped] - t.park_y[sp]
        st[qb + 2] = p.body_yaw[ped]
        vb = t.qvel[sp]
        st[vb] = p.vcx[ped]
        st[vb + 1] = p.vcy[ped]
        st[vb + 2] = p.omega[ped]

    def set_orientation(self, slots: np.ndarray, quat: np.ndarray) -> None:
        """Turn vehicles in place to the orientation ``quat``, a unit quaternion (w, x, y, z) in
        the world frame, (4,) or (n, 4); position, velocities and wheels stay (e.g. a car put
        on its roof: (0, 1, 0, 0))."""
        self._state[self._tables.qpos[self._vehicles(slots)][:, None] + FREE_POS + np.arange(FREE_QUAT)] = quat

    def command_vehicles(
        self, slots: np.ndarray, steer: np.ndarray, drive: np.ndarray, brake: np.ndarray,
        stab: np.ndarray | None = None, rear: np.ndarray | None = None, speed: np.ndarray | None = None,
    ) -> None:
        """Steer (bicycle-model angle [rad], split by Ackermann), drive and brake torques [N*m];
        ``rear``: rear-axle bicycle-model angles [rad] of the slots that steer it (else unused).
        With the vehicles' forward ``speed`` [m/s] heavy vehicles' wheel brakes also act as
        their traction control (``traction_control``)."""
        slots = np.asarray(slots, np.int64)
        if len(slots) == 0:
            return
        plan = self._plan(slots)
        if _kernel is not None and all(getattr(a, "dtype", None) == np.float64 for a in (steer, drive, brake)):
            self._command_fast(plan, steer, drive, brake, stab, rear, speed)
            return
        wheelbase, track, steer_l, steer_r, drive_u, spin_fl, brake_share = plan.command
        st = self._state
        left, right = ackermann(steer, wheelbase, track)
        r4 = plan.rear
        if r4 is not None:
            ok, ru = r4
            rr = np.zeros(len(ok)) if rear is None else np.asarray(rear)[ok]
            left[ok], right[ok], st[ru[:, 0]], st[ru[:, 1]] = ackermann_4ws(steer[ok], rr, wheelbase[ok], track[ok])
        st[steer_l] = left
        st[steer_r] = right
        st[drive_u] = drive
        fl = brake[:, None] * brake_share
        tc = plan.traction
        if speed is not None and tc is not None:
            rows, spin_v, r, share = tc
            fl[rows] = traction_control(fl[rows], np.asarray(drive)[rows, None] * share, st[spin_v] * r,
                                        np.asarray(speed)[rows, None])
        self._fl[spin_fl] = fl
        if stab is not None:
            au, ok = plan.stab
            st[au] = np.asarray(stab)[ok]

    def _command_fast(self, plan: _SlotPlan, steer, drive, brake, stab, rear, speed) -> None:
        """``command_vehicles`` of float64 commands (the numpy body computes float32 ones in
        float32) with every vehicle's columns written in C, then what only some have (rear
        steering, traction control, stabiliser) written over them as the numpy body does: the
        same values land."""
        wheelbase, track, steer_l, steer_r, drive_u, spin_fl, brake_share = plan.command
        st = self._state
        steer, drive, brake = (np.ascontiguousarray(a) for a in (steer, drive, brake))
        _kernel.command(st, self._fl, steer_l, steer_r, drive_u, spin_fl, wheelbase, track, brake_share,
                        steer, drive, brake)
        r4 = plan.rear
        if r4 is not None:
            ok, ru = r4
            rr = np.zeros(len(ok)) if rear is None else np.asarray(rear)[ok]
            st[steer_l[ok]], st[steer_r[ok]], st[ru[:, 0]], st[ru[:, 1]] = ackermann_4ws(
                steer[ok], rr, wheelbase[ok], track[ok])
        tc = plan.traction
        if speed is not None and tc is not None:
            rows, spin_v, r, share = tc
            self._fl[spin_fl[rows]] = traction_control(brake[rows, None] * brake_share[rows], drive[rows, None] * share,
                                                       st[spin_v] * r, np.asarray(speed)[rows, None])
        if stab is not None:
            au, ok = plan.stab
            st[au] = np.asarray(stab)[ok]

    def command_pedestrians(self, slots: np.ndarray, fx: np.ndarray, fy: np.ndarray, tz: np.ndarray) -> None:
        """Planar force [N] and yaw torque [N*m] of pedestrians."""
        slots = np.asarray(slots, np.int64)
        if len(slots) == 0:
            return
        t = self._tables
        st = self._state
        st[t.drive_u[slots]] = fx
        au = t.aux_u[slots]
        st[au[:, 0]] = fy
        st[au[:, 1]] = tz

    def step(self) -> None:
        """Advance every shard by one control tick (``substeps`` MuJoCo steps)."""
        if self.measure_cpu:
            c0 = time.process_time()
        t0 = time.perf_counter()
        self._batch.step(nstep=self.substeps)
        self.mujoco_s += time.perf_counter() - t0
        if self.measure_cpu:
            self.mujoco_cpu_s += time.process_time() - c0
        self.time += self.substeps * self.timestep

    def set_ghost(self, slots: np.ndarray, ghost: bool | np.ndarray, placed: np.ndarray | None = None) -> None:
        """Switch the body geom of ``slots`` off for other agents (``ghost``: it then touches
        the ground only, like a wheel) or back to its model's collision bits. A spawn into an
        occupied spot stays a ghost until it is clear, so bodies never stack.

        ``placed``: agents put at their pose every tick (kinematic, external) touch every
        driven body but not each other: neither answers a contact (both are placed again at
        the next tick), so a touch between them is no physics; seen between two bodies
        carried through a lane shape's corner between the samples of 1 s steps."""
        slots = np.asarray(slots, np.int64)
        if len(slots) == 0:
            return
        self.bits_version += 1  # (callers that keep what they set see that it changed)
        t = self._tables
        ghost = np.broadcast_to(np.asarray(ghost, bool), slots.shape)
        g, gm = t.geom[slots], t.geom_model[slots]
        m = self.model
        # ground-only: contype 0, conaffinity 1 for bodies on the ground; pedestrians (no
        # ground contact) switch off entirely
        ped = t.kind[slots] == M.KIND_PED
        ct, ca = m.geom_contype[gm], m.geom_conaffinity[gm]
        if placed is not None:
            on = np.asarray(placed, bool) & ~ghost
            ct = np.where(on, np.where(ped, PLACED_PED_BIT, PLACED_VEHICLE_BIT), ct)
            ca = np.where(on & ~ped, ca | PED_BIT, ca)  # (driven chassis and pedestrians: as before)
        self._contype[g] = np.where(ghost, 0, ct)
        self._conaff[g] = np.where(ghost, np.where(ped, 0, 1), ca)

    def contacts(self, slots: np.ndarray, upright: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Agents of ``slots`` touching another agent now, and which of them began a collision.

        From cfrc_ext of each agent's root body (chassis, bicycle frame or pedestrian):
        wheels are separate bodies, so ground contact only shows when an agent is not
        ``upright`` (then it is excluded). Parked slots sleep and never touch. A collision
        begins when an agent touches after ``CONTACT_GAP_S`` without touching, so one
        crash with bounces counts once per agent involved.
        """
        slots = np.asarray(slots, np.int64)
        force = np.abs(self._cfrc.reshape(-1)[self._plan(slots).body_force])
        mag = force[0] + force[1] + force[2]
        touching = (mag > CONTACT_N) & upright
        if not touching.any():  # the usual tick
            self.in_contact[slots] = False
            return touching, touching
        began_mask = touching & ((self.time - self.last_touch[slots]) > CONTACT_GAP_S)
        self.last_touch[slots[touching]] = self.time
        self.in_contact[slots] = touching
        self.counters["collisions"] += int(began_mask.sum())
        return touching, began_mask

    @property
    def tables(self) -> SlotTables:
        return self._tables


class _Placement(NamedTuple):
    """Pose and motion of placed agents (arrays over all of them, ``place``)."""

    veh: np.ndarray
    """Which are vehicles."""
    ped: np.ndarray
    """Which are pedestrians."""
    body_yaw: np.ndarray
    """[rad]."""
    cx: np.ndarray
    """Body origin x [m]."""
    cy: np.ndarray
    """Body origin y [m]."""
    c: np.ndarray
    """cos(body yaw)."""
    s: np.ndarray
    """sin(body yaw)."""
    vcx: np.ndarray
    """Body origin velocity x [m/s]."""
    vcy: np.ndarray
    """Body origin velocity y [m/s]."""
    omega: np.ndarray
    """Yaw rate [rad/s]."""
    steer: np.ndarray
    """Bicycle-model steering angle [rad] (pedestrians: 0)."""


def _placement(
    t: SlotTables, slots: np.ndarray, fx: np.ndarray, fy: np.ndarray, yaw: np.ndarray, speed: np.ndarray,
    kappa: np.ndarray, steady_turn: bool,
) -> _Placement:
    """Body pose and velocity of agents whose front bumper is at (fx, fy) [m] on a path of
    heading ``yaw`` [rad] and curvature ``kappa`` [1/m] at ``speed`` [m/s] (``PhysicsWorld.place``)."""
    n = len(slots)
    ped = t.kind[slots] == M.KIND_PED
    veh = ~ped
    front = t.front[slots]
    rear = t.rear_axle[slots]
    d = np.where(veh, front - rear, 1.0)
    omega = speed * kappa  # bumper on a circle of radius 1/kappa at speed v
    if steady_turn:
        beta = np.where(veh, np.arcsin(np.clip(kappa * d, -MAX_KAPPA_D, MAX_KAPPA_D)), 0.0)
        steer = np.where(veh, steady_state_delta(kappa, d, np.where(veh, t.wheelbase[slots], 1.0)), 0.0)
    else:
        beta = np.zeros(n)
        steer = np.where(veh, np.arctan(t.wheelbase[slots] * kappa), 0.0)
    body_yaw = yaw - beta
    c, s = np.cos(body_yaw), np.sin(body_yaw)
    cx, cy = fx - front * c, fy - front * s
    # centre velocity = bumper velocity - omega x (bumper - centre)
    vbx, vby = speed * np.cos(yaw), speed * np.sin(yaw)
    vcx = vbx + omega * front * s
    vcy = vby - omega * front * c
    return _Placement(veh, ped, body_yaw, cx, cy, c, s, vcx, vcy, omega, steer)


def traction_control(brake: np.ndarray, drive: np.ndarray, surface: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """Per-wheel brake torques [N*m] (n, 4) of a heavy vehicle's traction control (ASR): each
    wheel's share of the ``brake`` torque, or, for a driven wheel spinning faster than
    ``TCS_SLIP`` of the vehicle's forward ``speed`` [m/s] (n, 1) plus ``TCS_MARGIN_MPS``
    (``surface``: its surface speed [m/s]), up to its own share of the ``drive`` [N*m] over
    ``TCS_BAND_MPS`` more spin (the other driven wheels keep theirs).

    A sliding tyre's friction points along its slip: a truck's inner rear wheel, unloaded
    in a junction turn under full drive, spun up to 700 m/s of surface speed and the truck
    slid 3.6 m out of the turn into a pedestrian. Cars, buses and bicycles are left without:
    braked at their spinning wheel they fell behind SUMO pulling away (spider network p95
    0.16 -> 0.18-0.22 m), and an anti-lock (tried too) stopped them late."""
    over = surface - (TCS_SLIP * np.maximum(speed, 0.0) + TCS_MARGIN_MPS)
    return np.maximum(brake, np.maximum(drive, 0.0) * np.clip(over / TCS_BAND_MPS, 0.0, 1.0))


_VEHICLE_STATE = ("cx", "cy", "z", "yaw", "roll", "pitch", "vx", "vy", "wz", "wx", "steer")  # ``_vehicle_state``


def _vehicle_state(g: np.ndarray) -> tuple[np.ndarray, ...]:
    """cx, cy, z, yaw, roll, pitch, vx, vy, yaw rate, roll rate, steer from the rows of
    ``_SlotPlan.veh_state`` (freejoint qpos, qvel, steer qpos)."""
    qw, qx, qy, qz = g[3], g[4], g[5], g[6]
    xx_yy = qx * qx + qy * qy
    yaw = np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
    roll = np.arctan2(2 * (qw * qx + qy * qz), 1 - 2 * xx_yy)
    pitch = -np.arcsin(np.minimum(np.maximum(2 * (qw * qy - qz * qx), -1.0), 1.0))
    # freejoint angular velocity is in the body frame: world z = third row of R
    wz = 2 * (qx * qz - qw * qy) * g[10] + 2 * (qy * qz + qw * qx) * g[11] + (1 - 2 * xx_yy) * g[12]
    steer = 0.5 * (g[13] + g[14])  # mean of the steered wheels
    return g[0], g[1], g[2], yaw, roll, pitch, g[7], g[8], wz, g[10], steer


def _quat_zyx(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z) of yaw about z, then pitch about y, then roll about x (n, 4)."""
    cy, sy = np.cos(0.5 * yaw), np.sin(0.5 * yaw)
    cp, sp = np.cos(0.5 * pitch), np.sin(0.5 * pitch)
    cr, sr = np.cos(0.5 * roll), np.sin(0.5 * roll)
    return np.stack([
        cy * cp * cr + sy * sp * sr,
        cy * cp * sr - sy * sp * cr,
        cy * sp * cr + sy * cp * sr,
        sy * cp * cr - cy * sp * sr,
    ], axis=-1)


__all__ = ["HEADROOM", "Observation", "PhysicsWorld"]  # HEADROOM: re-exported (``pools``)
