"""``PhysicsWorld``: the per-tick world and the one owner of MuJoCo indices.

The world is ``shards`` MuJoCo simulations of one model (``mujoco.batch.Batch``, stepped
on a thread pool; persistent because sleeping needs it), built by ``layout``: *pools* of
pre-allocated slots, one pool per model family and size (``models.size_key``). Unused slots sit
asleep in a parking lot far from the network; spawning wakes a slot and places it,
parking puts it back. A pool that runs out grows by at least ``pool_chunk`` slots per
shard with one recompile (off the hot path); live agents keep their exact state.

Per control tick: ``observe`` -> (controllers, outside) -> ``command_vehicles`` /
``command_pedestrians`` / ``place`` -> ``step``. Nothing outside this module indexes
``qpos``/``qvel``/``ctrl``: callers get named, vectorised reads and writes over arrays
of *slot numbers*. Slot numbers change when the model grows; ``generation`` increments
then, and ``slot_of`` maps agent ids to current slots.

Agents in different shards do not touch each other (they are in different
simulations); a new agent goes to the shard of the nearest live agent within
``NEIGHBOUR_M`` (vehicles that follow each other share a shard) unless that shard is
over its share, else to the least-loaded shard.
"""
from __future__ import annotations

import concurrent.futures
import logging
import math
import time
from dataclasses import dataclass
from functools import cached_property

import mujoco
import numpy as np

from physics_side import models as M
from physics_side.kinematics import ackermann, concat_ranges, steady_state_delta
from physics_side.layout import SLOTS_PER_SIM, Layout, Pool, SlotTables, carry_over, compile_layout
from protocol.frames import wrap_pi
from protocol.messages import AgentClass

log = logging.getLogger(__name__)

SLEEP_NEVER = int(mujoco.mjtSleepPolicy.mjSLEEP_NEVER)
SLEEP_ALLOWED = int(mujoco.mjtSleepPolicy.mjSLEEP_ALLOWED)
NEIGHBOUR_M = 40.0  # [m] a new agent joins the shard of a live agent this close
MAX_PLACE_CURVATURE = 0.2  # [1/m] placements assume at most a 5 m radius turn
NEW_POOL_SLOTS = 4  # [slots per shard] first capacity of a pool for a newly seen size
CONTACT_N = 1.0  # [N] chassis contact force that counts as touching
CONTACT_GAP_S = 1.0  # [s] apart this long before a new touch counts as a new collision
HEADROOM = 1.25  # expected agents -> slots (sized up front)


@dataclass(frozen=True)
class _Growth:
    """A bigger model being compiled on the worker thread."""

    future: concurrent.futures.Future
    capacity: dict[int, int]
    """Slots per simulation of each pool in it."""
    sims: int

    def covers(self, needs: dict[int, int], pools: list[Pool], sims: int) -> bool:
        """Whether it adds ``needs`` (pool -> slots per simulation of ``sims``) to ``pools``."""
        return all(
            p in self.capacity and self.capacity[p] * self.sims - pools[p].capacity * sims >= e * sims
            for p, e in needs.items()
        )


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
    def veh_state(self) -> np.ndarray:
        """(15, n_veh) flat state indices: freejoint qpos (7), qvel (6), left/right steer qpos."""
        sv = self.slots[self.veh]
        t = self.t
        return np.concatenate([
            t.qpos[sv][None, :] + np.arange(7)[:, None], t.qvel[sv][None, :] + np.arange(6)[:, None], t.steer_q[sv].T,
        ])

    @cached_property
    def ped_state(self) -> np.ndarray:
        """(6, n_ped) flat state indices: slide x, slide y, yaw hinge qpos, then their qvel."""
        sp = self.slots[self.ped]
        t = self.t
        k = np.arange(3)[:, None]
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
    """Pooled multi-agent MuJoCo world (see module docstring)."""

    def __init__(
        self, timestep: float = 0.005, substeps: int = 4, shards: int = 1, threads: int = 0,
        initial: dict[AgentClass, int] | None = None, pool_chunk: int = 32,
        awd: frozenset[AgentClass] = frozenset(), expect: dict[AgentClass, int] | None = None,
        adopt_early: bool = False,
    ):
        """``initial``: slots per simulation per class (its default size bucket); ``expect``:
        agents per class expected at once over the whole world (sized up front with
        ``HEADROOM``). ``shards`` simulations at least, more when the slots would exceed
        ``layout.SLOTS_PER_SIM`` per simulation. ``adopt_early``: switch to a model grown in
        the background as soon as it is ready (realtime); else only when a pool runs out,
        so that a lockstep run does not depend on compile times."""
        self.timestep = float(timestep)
        self.substeps = int(substeps)
        self.threads = int(threads) or int(shards)
        self.pool_chunk = int(pool_chunk)
        self.awd = frozenset(awd)
        self.adopt_early = bool(adopt_early)
        self._pools: list[Pool] = []
        self._pool_key: dict[tuple[str, int, int], int] = {}
        initial = {AgentClass(c): int(n) for c, n in (initial or {}).items()}
        expect = {AgentClass(c): int(n) for c, n in (expect or {}).items()}
        demand = {  # pools numbered in the order the config lists the types
            c: max(initial.get(c, 0) * int(shards), math.ceil(expect.get(c, 0) * HEADROOM))
            for c in [*initial, *(c for c in expect if c not in initial)]
        }
        self.shards = max(int(shards), math.ceil(sum(demand.values()) / SLOTS_PER_SIM))
        for cls in demand:
            if demand[cls] > 0:
                self._add_pool(M.default_key(cls), max(initial.get(cls, 0), math.ceil(demand[cls] / self.shards)))
        self.generation = 0
        self.agent_slot: dict[str, int] = {}
        self.slot_agent: list[str | None] = []
        self.counters = {
            "placements": 0, "spawned": 0, "parked": 0, "collisions": 0, "pool_grows": 0, "growth_waits": 0,
        }
        self.mujoco_s = 0.0  # [s] wall time spent in MuJoCo steps (cumulative)
        self.mujoco_cpu_s = 0.0  # [s] CPU time of the process (all threads) in MuJoCo steps (cumulative)
        self.build_s = 0.0  # [s] wall time spent compiling on the stepping thread (cumulative)
        self.wait_s = 0.0  # [s] wall time spent waiting for a background growth (cumulative)
        self.time = 0.0  # [s] simulated time
        self.live = np.zeros(0, bool)
        self._growth: _Growth | None = None
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._install(compile_layout(self._pools, self.timestep, self.shards, self.threads))

    # ------------------------------------------------------------------ pools / compile

    def _spec_of(self, key: tuple[str, int, int]) -> M.AgentSpec:
        spec = M.spec_for_key(key)
        return M.with_awd(spec, spec.cls in self.awd and spec.kind == M.KIND_CAR)

    def _add_pool(self, key: tuple[str, int, int], capacity: int) -> int:
        if key in self._pool_key:
            p = self._pool_key[key]
            old = self._pools[p]
            self._pools[p] = Pool(old.index, old.spec, old.capacity + capacity)
            return p
        p = len(self._pools)
        self._pools.append(Pool(p, self._spec_of(key), capacity))
        self._pool_key[key] = p
        return p

    @property
    def capacity(self) -> int:
        """Total slots over all pools and shards."""
        return self.shards * sum(p.capacity for p in self._pools)

    def _install(self, layout: Layout) -> None:
        """Switch to a compiled layout; live agents of the previous one keep their exact
        qpos/qvel/ctrl/brakes (slot numbers change: ``generation`` increments)."""
        old = getattr(self, "_layout", None)
        self._layout = layout
        self._pools = list(layout.pools)
        self.shards = layout.shards
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
        old_live = self.live if old is not None else None
        old_agents = self.slot_agent
        self.live = np.zeros(G, bool)
        self.in_contact = np.zeros(G, bool)
        self.last_touch = np.full(G, -np.inf)
        self.slot_agent = [None] * G
        self.agent_slot = {}
        t = self._tables
        self._free: dict[tuple[int, int], list[int]] = {}
        key = t.pool * self.shards + t.shard
        order = np.argsort(key, kind="stable")
        bounds = np.flatnonzero(np.diff(key[order])) + 1
        for group in np.split(order, bounds) if len(order) else ():
            g = int(group[0])
            # popped from the end: lowest slot number first
            self._free[(int(t.pool[g]), int(t.shard[g]))] = group[::-1].tolist()
        if old is not None:
            self._restore(old, old_live, old_agents)
        self.generation += 1

    def _restore(self, old: Layout, live: np.ndarray, agents: list) -> None:
        """Copy live agents from the previous layout (same pool/shard/index) into this one."""
        olds = np.flatnonzero(live)
        if len(olds) == 0:
            return
        new, ot = self._tables, old.tables
        news = carry_over(old, self._layout, olds)
        for a, n in (("qpos", "nq"), ("qvel", "nv"), ("ctrl", "nu")):
            src = concat_ranges(getattr(ot, a)[olds], getattr(ot, n)[olds])
            dst = concat_ranges(getattr(new, a)[news], getattr(new, n)[news])
            self._state[dst] = old.state[src]
        ok = ot.spin_fl[olds] >= 0
        self._fl[new.spin_fl[news][ok]] = old.frictionloss[ot.spin_fl[olds][ok]]
        self._contype[new.geom[news]] = old.contype[ot.geom[olds]]  # ghosts stay ghosts
        self._conaff[new.geom[news]] = old.conaffinity[ot.geom[olds]]
        self._policy[new.tree[news]] = SLEEP_NEVER
        self.live[news] = True
        for g_old, g_new in zip(olds, news):
            aid = agents[g_old]
            self.slot_agent[g_new] = aid
            self.agent_slot[aid] = int(g_new)
        taken = set(news.tolist())
        for k in {(int(new.pool[g]), int(new.shard[g])) for g in news}:
            self._free[k] = [g for g in self._free[k] if g not in taken]

    def _grown_pools(self, extra: dict[int, int]) -> tuple[list[Pool], int]:
        """Pools and simulation count with ``extra`` more slots per simulation for some pools:
        more slots per simulation up to ``SLOTS_PER_SIM``, more simulations beyond."""
        pools = [Pool(p.index, p.spec, p.capacity + extra.get(p.index, 0)) for p in self._pools]
        per_sim = sum(p.capacity for p in pools)
        sims = self.shards
        if per_sim > SLOTS_PER_SIM:
            total = {p.index: p.capacity * self.shards for p in pools}
            sims = max(self.shards, math.ceil(sum(total.values()) / SLOTS_PER_SIM))
            old = {p.index: p.capacity for p in self._pools}
            pools = [Pool(p.index, p.spec, max(old[p.index], math.ceil(total[p.index] / sims))) for p in pools]
        return pools, sims

    def _grow(self, needs: dict[int, int]) -> None:
        """Grow pools (pool index -> extra slots per simulation) now, with one recompile:
        a pool the background growth does not cover (e.g. a size seen for the first time)."""
        # a pool's first slots (a size seen for the first time) start small: sizes are many,
        # and every slot of every pool is rebuilt by the recompile
        extra = {p: max(e, self.pool_chunk if self._pools[p].capacity else NEW_POOL_SLOTS) for p, e in needs.items()}
        log.warning(
            "physics world: pools exhausted (%s), recompiling with more slots",
            ", ".join(f"{self._pools[p].spec.name} +{e}" for p, e in extra.items()),
        )
        pools, sims = self._grown_pools(extra)
        t0 = time.perf_counter()
        layout = compile_layout(pools, self.timestep, sims, self.threads)
        self.build_s += time.perf_counter() - t0
        self._install(layout)
        self.counters["pool_grows"] += 1

    def _grow_in_background(self, extra: dict[int, int]) -> None:
        """Compile a bigger model on a worker thread (MuJoCo's compile releases the GIL);
        ``_adopt`` switches to it later."""
        if self._growth is not None:
            return
        pools, sims = self._grown_pools(extra)
        if self._executor is None:
            self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="physics-growth")
        log.info(
            "physics world: pools running low (%s), compiling %d slots in the background",
            ", ".join(f"{self._pools[p].spec.name} +{e}" for p, e in extra.items()), sims * sum(p.capacity for p in pools),
        )
        fut = self._executor.submit(compile_layout, pools, self.timestep, sims, self.threads)
        self._growth = _Growth(fut, {p.index: p.capacity for p in pools}, sims)

    def _adopt(self, wait: bool) -> bool:
        """Switch to the background-grown model if it is ready (or ``wait`` for it)."""
        g = self._growth
        if g is None or (not wait and not g.future.done()):
            return False
        if not g.future.done():
            t0 = time.perf_counter()
            concurrent.futures.wait([g.future])
            self.wait_s += time.perf_counter() - t0
            self.counters["growth_waits"] += 1
        self._growth = None
        layout = g.future.result()
        if len(layout.pools) < len(self._pools) or any(
            p.capacity > q.capacity for p, q in zip(self._pools, layout.pools)
        ):
            return False  # pools were added meanwhile: that growth is stale
        self._install(layout)
        self.counters["pool_grows"] += 1
        return True

    def reserve(self, sizes) -> int:
        """Make pools for agents that may come, given as (family, length, width) [m] (e.g.
        every size of a step, also those of other shards' agents): a size seen for the first
        time gets its pool compiled in the background, so that taking over an agent of that
        size later spawns it without a compile on the stepping thread. Returns the number
        of new pools."""
        n = len(self._pools)
        for fam, length, width in sizes:
            self.pool_for(fam, float(length), float(width))
        added = len(self._pools) - n
        if self._growth is not None and self._growth.future.done() and any(
            p.capacity == 0 for p in self._pools
        ):
            self._adopt(wait=False)  # (dropped if stale: pools were added meanwhile)
        self._low_water()
        return added

    def _low_water(self) -> None:
        """Start a background growth for pools with less than a quarter of their slots free
        (each grows by half its size, at least ``pool_chunk`` per simulation), and for pools
        reserved without slots yet."""
        if self._growth is not None:
            return
        extra = {}
        for p in self._pools:
            if p.capacity == 0:
                extra[p.index] = NEW_POOL_SLOTS
                continue
            free = sum(len(self._free.get((p.index, s), ())) for s in range(self.shards))
            if 4 * free < p.capacity * self.shards:
                extra[p.index] = max(self.pool_chunk, p.capacity // 2)
        if extra:
            self._grow_in_background(extra)

    @property
    def growing(self) -> bool:
        """A bigger model is being compiled, or waits to be switched in."""
        return self._growth is not None

    @property
    def growth_ready(self) -> bool:
        """The bigger model is compiled (switched in when a pool runs out, or at once with
        ``adopt_early``)."""
        return self._growth is not None and self._growth.future.done()

    def close(self) -> None:
        """Stop a background growth (its result is dropped)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
        self._growth = None

    # ------------------------------------------------------------------ agent set

    def pool_for(self, family: str, length: float, width: float) -> int:
        """Pool index for an agent of a model family (``models.FAMILIES``) and size [m]."""
        key = M.size_key(family, length, width)
        p = self._pool_key.get(key)
        if p is None:  # a pool of the family within SIZE_TOLERANCE of this size does as well
            for k, q in self._pool_key.items():
                spec = self._pools[q].spec
                if (k[0] == family and abs(spec.length / length - 1) <= M.SIZE_TOLERANCE
                        and abs(spec.width / width - 1) <= M.SIZE_TOLERANCE):
                    return q
        if p is None:
            p = self._add_pool(key, 0)
        return p

    def allocate(self, ids: list[str], pools: np.ndarray, near_x: np.ndarray, near_y: np.ndarray) -> np.ndarray:
        """Take a slot for each new agent (growing pools if needed); returns slot numbers.

        The slot is woken but not placed: call ``place`` next.
        """
        pools = np.asarray(pools, np.int64)
        if self.adopt_early:
            self._adopt(wait=False)
        needs = self._needs(pools)
        if needs and self._growth is not None and self._growth.covers(needs, self._pools, self.shards):
            self._adopt(wait=True)
            needs = self._needs(pools)
        if needs:
            self._grow(needs)
        t = self._tables
        load = np.bincount(t.shard[self.live], minlength=self.shards).astype(np.float64)
        live = np.flatnonzero(self.live)
        obs = self.observe(live) if len(live) else None
        out = np.empty(len(ids), np.int64)
        for k, (aid, p) in enumerate(zip(ids, pools)):
            shard = -1
            share = (load.sum() + 1) / self.shards * 1.1 + 2
            if obs is not None and len(live):
                d2 = (obs.fx - near_x[k]) ** 2 + (obs.fy - near_y[k]) ** 2
                j = int(np.argmin(d2))
                if d2[j] < NEIGHBOUR_M**2:
                    s = int(t.shard[live[j]])
                    if load[s] < share and self._free.get((int(p), s)):
                        shard = s
            if shard < 0:
                order = np.argsort(load, kind="stable")
                shard = next(int(s) for s in order if self._free.get((int(p), int(s))))
            g = self._free[(int(p), shard)].pop()
            load[shard] += 1
            out[k] = g
            self.live[g] = True
            self.slot_agent[g] = aid
            self.agent_slot[aid] = g
        self._policy[t.tree[out]] = SLEEP_NEVER
        self.counters["spawned"] += len(ids)
        self._low_water()
        return out

    def _needs(self, pools: np.ndarray) -> dict[int, int]:
        """Extra slots per simulation each pool needs for ``pools`` (one entry per new agent)."""
        needs: dict[int, int] = {}
        for p in np.unique(pools):
            want = int((pools == p).sum())
            have = sum(len(self._free.get((int(p), s), [])) for s in range(self.shards))
            if self._pools[int(p)].capacity == 0 or have < want:
                needs[int(p)] = -(-(want - have) // self.shards) + 1
        return needs

    def park(self, slots: np.ndarray) -> None:
        """Send slots back to the parking lot (zero velocity, brakes on) and let them sleep."""
        slots = np.asarray(slots, np.int64)
        if len(slots) == 0:
            return
        t = self._tables
        q0 = self.model.qpos0
        src = concat_ranges(t.qpos0[slots], t.nq[slots])
        self._state[concat_ranges(t.qpos[slots], t.nq[slots])] = q0[src]
        self._state[concat_ranges(t.qvel[slots], t.nv[slots])] = 0.0
        self._state[concat_ranges(t.ctrl[slots], t.nu[slots])] = 0.0
        fl = t.spin_fl[slots]
        self._fl[fl[fl >= 0]] = 100.0
        self._policy[t.tree[slots]] = SLEEP_ALLOWED
        for g in slots:
            aid = self.slot_agent[g]
            if aid is not None:
                self.agent_slot.pop(aid, None)
            self.slot_agent[g] = None
            self._free[(int(t.pool[g]), int(t.shard[g]))].append(int(g))
        self.live[slots] = False
        self.set_ghost(slots, False)
        self.in_contact[slots] = False
        self.last_touch[slots] = -np.inf
        self.counters["parked"] += len(slots)

    def slot_of(self, ids: list[str]) -> np.ndarray:
        """Current slot of each agent id, -1 when not in the world."""
        get = self.agent_slot.get
        return np.fromiter((get(a, -1) for a in ids), np.int64, len(ids))

    def _plan(self, slots: np.ndarray) -> _SlotPlan:
        """The (cached) ``_SlotPlan`` of an int64 slot array; keyed by content, so callers
        may pass fresh arrays; dropped on recompile (slot numbers change)."""
        key = slots.tobytes()
        plan = self._plans.get(key)
        if plan is None:
            if len(self._plans) >= 8:  # a fleet uses a few slot arrays per step
                self._plans.clear()
            plan = self._plans[key] = _SlotPlan(self._tables, slots.copy())
        return plan

    # ------------------------------------------------------------------ reads

    def observe(self, slots: np.ndarray) -> Observation:
        """Vectorised state of ``slots`` (any mix of kinds)."""
        slots = np.asarray(slots, np.int64)
        plan = self._plan(slots)
        st = self._state
        if plan.all_veh:  # the usual case: one gather, no scatter
            cx, cy, z, yaw, roll, pitch, vx, vy, wz, wx, steer = _vehicle_state(st[plan.veh_state])
        else:
            n = len(slots)
            veh, ped = plan.veh, plan.ped
            cx, cy, yaw, vx, vy, wz = (np.empty(n) for _ in range(6))
            z, roll, pitch, wx, steer = (np.zeros(n) for _ in range(5))
            if plan.any_veh:
                out = (cx, cy, z, yaw, roll, pitch, vx, vy, wz, wx, steer)
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
        t = self._tables
        st = self._state
        yaw = np.asarray(yaw, np.float64) * np.ones(n)
        speed = np.asarray(speed, np.float64) * np.ones(n)
        kappa = np.zeros(n) if curvature is None else np.asarray(curvature, np.float64) * np.ones(n)
        kappa = np.clip(kappa, -MAX_PLACE_CURVATURE, MAX_PLACE_CURVATURE)
        kind = t.kind[slots]
        ped = kind == M.KIND_PED
        veh = ~ped
        front = t.front[slots]
        rear = t.rear_axle[slots]
        d = np.where(veh, front - rear, 1.0)
        omega = speed * kappa  # bumper on a circle of radius 1/kappa at speed v
        if steady_turn:
            beta = np.where(veh, np.arcsin(np.clip(kappa * d, -0.95, 0.95)), 0.0)
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
        if veh.any():
            sv = slots[veh]
            self._state[concat_ranges(t.qvel[sv], t.nv[sv])] = 0.0
            qb = t.qpos[sv]
            # bicycles lean into the turn at the steady-turn angle (roll about +x, left side
            # down in a left turn); cars stand level
            bike = t.kind[sv] == M.KIND_BIKE
            roll = np.where(bike, -np.arctan(np.clip(speed[veh] * omega[veh] / 9.81, -0.6, 0.6)), 0.0)
            quat = _quat_zyx(body_yaw[veh], t.rest_pitch[sv], roll)
            h = np.where(bike, t.rest_z[sv] * np.cos(roll), t.rest_z[sv])
            st[qb] = cx[veh]
            st[qb + 1] = cy[veh]
            st[qb + 2] = h
            for k in range(4):
                st[qb + 3 + k] = quat[:, k]
            vb = t.qvel[sv]
            st[vb] = vcx[veh]
            st[vb + 1] = vcy[veh]
            st[vb + 5] = omega[veh]
            left, right = ackermann(steer[veh], t.wheelbase[sv], t.track[sv])
            sq = t.steer_q[sv]
            st[sq[:, 0]] = left
            st[sq[:, 1]] = right
            su = t.steer_u[sv]
            st[su[:, 0]] = left
            st[su[:, 1]] = right
            # wheels rolling at the forward speed of the axle they are on (rear axle speed)
            v_r = vcx[veh] * c[veh] + vcy[veh] * s[veh]
            st[t.spin_v[sv]] = (v_r / t.r_wheel[sv])[:, None]
        if ped.any():
            sp = slots[ped]
            qb = t.qpos[sp]
            st[qb] = cx[ped] - t.park_x[sp]
            st[qb + 1] = cy[ped] - t.park_y[sp]
            st[qb + 2] = body_yaw[ped]
            vb = t.qvel[sp]
            st[vb] = vcx[ped]
            st[vb + 1] = vcy[ped]
            st[vb + 2] = omega[ped]
        self._policy[t.tree[slots]] = SLEEP_NEVER
        if count:
            self.counters["placements"] += n

    def command_vehicles(
        self, slots: np.ndarray, steer: np.ndarray, drive: np.ndarray, brake: np.ndarray,
        stab: np.ndarray | None = None,
    ) -> None:
        """Steer (bicycle-model angle [rad], split by Ackermann), drive and brake torques [N*m]."""
        slots = np.asarray(slots, np.int64)
        if len(slots) == 0:
            return
        plan = self._plan(slots)
        wheelbase, track, steer_l, steer_r, drive_u, spin_fl, brake_share = plan.command
        st = self._state
        left, right = ackermann(steer, wheelbase, track)
        st[steer_l] = left
        st[steer_r] = right
        st[drive_u] = drive
        self._fl[spin_fl] = brake[:, None] * brake_share
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
        t0, c0 = time.perf_counter(), time.process_time()
        self._batch.step(nstep=self.substeps)
        self.mujoco_s += time.perf_counter() - t0
        self.mujoco_cpu_s += time.process_time() - c0
        self.time += self.substeps * self.timestep

    def set_ghost(self, slots: np.ndarray, ghost: bool | np.ndarray) -> None:
        """Switch the body geom of ``slots`` off for other agents (``ghost``: it then touches
        the ground only, like a wheel) or back to its model's collision bits. A spawn into an
        occupied spot stays a ghost until it is clear, so bodies never stack."""
        slots = np.asarray(slots, np.int64)
        if len(slots) == 0:
            return
        t = self._tables
        ghost = np.broadcast_to(np.asarray(ghost, bool), slots.shape)
        g, gm = t.geom[slots], t.geom_model[slots]
        m = self.model
        # ground-only: contype 0, conaffinity 1 for bodies on the ground; pedestrians (no
        # ground contact) switch off entirely
        ped = t.kind[slots] == M.KIND_PED
        self._contype[g] = np.where(ghost, 0, m.geom_contype[gm])
        self._conaff[g] = np.where(ghost, np.where(ped, 0, 1), m.geom_conaffinity[gm])

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


__all__ = ["Observation", "PhysicsWorld"]
