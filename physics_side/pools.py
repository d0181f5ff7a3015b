"""``SlotPools``: which slots the physics world has and who holds them - pools, growth, allocation, parking.

One pool of pre-allocated slots per model family and size (``models.size_key``) in each
of ``shards`` simulations, compiled by ``layout.compile_layout``. Unused slots sit asleep
in a parking lot far from the network; ``take`` wakes a slot for a new agent (the caller
places it), ``park`` puts it back. A pool that runs low is regrown on a worker thread and
switched in later (``reserve`` / ``take``); one that runs out grows at once with one
recompile. Live agents keep their exact state through a switch, but every slot number
changes: ``generation`` increments and ``slot_of`` maps agent ids to current slots.

The per-tick world (``world.PhysicsWorld``) owns a ``SlotPools`` and reads its current
``layout``; nothing here runs per control tick.
"""

from __future__ import annotations

import atexit
import concurrent.futures
import threading
import logging
import math
import time
from dataclasses import dataclass
from itertools import repeat

import mujoco
import numpy as np

from physics_side import models as M
from physics_side.kinematics import concat_ranges
from physics_side.layout import SLOTS_PER_SIM, Layout, Pool, carry_over, compile_layout
from protocol.messages import AgentClass

log = logging.getLogger(__name__)

SLEEP_NEVER = int(mujoco.mjtSleepPolicy.mjSLEEP_NEVER)
SLEEP_ALLOWED = int(mujoco.mjtSleepPolicy.mjSLEEP_ALLOWED)
NEIGHBOUR_M = 40.0  # [m] a new agent joins the shard of a live agent this close
NEW_POOL_SLOTS = 4  # [slots per shard] first capacity of a pool for a newly seen size
LOW_WATER_PARTS = 4  # [1] a pool with less than 1/this of its slots free grows in the background
# expected agents -> slots (sized up front). Above 1 / (1 - 1/LOW_WATER_PARTS) = 1.33, so that a
# world holding the agents it was sized for is not below the low-water mark: at 1.25 it was,
# and every run sized by ``expect`` compiled a doubled model on a second thread as soon as its
# agents were there (measured: 0.3 s of CPU inside a 150-car shard process's first seconds).
HEADROOM = 1.4
# A new agent joins its neighbour's shard unless that shard holds more than its share:
# SHARD_SHARE_SLACK x the mean load, plus SHARD_SHARE_EXTRA agents
SHARD_SHARE_SLACK = 1.1  # [1]
SHARD_SHARE_EXTRA = 2  # [agents]
PARKED_BRAKE = 100.0  # [N*m] on each spin joint of a parked slot (brakes on: it does not roll)


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


_GROWTHS: set[threading.Thread] = set()  # background compiles still running
GROWTH_EXIT_WAIT_S = 5.0  # [s] how long interpreter exit waits for a running compile (``_wait_for_growths``)


def _wait_for_growths() -> None:
    """At interpreter exit, wait (at most GROWTH_EXIT_WAIT_S) for running compiles: one that
    returns into Python while the interpreter finalizes crashes the process (a script that
    ended right after a small pool growth exited with a segmentation fault, 6 runs of 6). A
    longer compile is left to end with the process."""
    deadline = time.monotonic() + GROWTH_EXIT_WAIT_S
    for t in list(_GROWTHS):
        t.join(max(0.0, deadline - time.monotonic()))


atexit.register(_wait_for_growths)


def _in_daemon_thread(fn, *args) -> concurrent.futures.Future:
    """``fn(*args)`` on a daemon thread of its own, as a Future (an executor's worker threads
    are joined at interpreter exit, so a process could not end during a compile)."""
    fut: concurrent.futures.Future = concurrent.futures.Future()

    def work() -> None:
        try:
            if not fut.set_running_or_notify_cancel():
                return
            try:
                fut.set_result(fn(*args))
            except BaseException as e:  # handed to whoever reads the result
                fut.set_exception(e)
        finally:
            _GROWTHS.discard(threading.current_thread())

    t = threading.Thread(target=work, name="physics-growth", daemon=True)
    _GROWTHS.add(t)
    t.start()
    return fut


class SlotPools:
    """Pools of slots over a compiled layout, grown as agents come (see module docstring)."""

    def __init__(
        self, timestep: float, shards: int, threads: int, initial: dict[AgentClass, int] | None = None,
        pool_chunk: int = 32, awd: frozenset[AgentClass] = frozenset(),
        expect: dict[AgentClass, int] | None = None, adopt_early: bool = False,
        counters: dict[str, int] | None = None,
    ):
        """``initial``: slots per simulation per class (its default size bucket); ``expect``:
        agents per class expected at once over the whole world (sized up front with
        ``HEADROOM``). ``shards`` simulations at least, more when the slots would exceed
        ``layout.SLOTS_PER_SIM`` per simulation. ``adopt_early``: switch to a model grown in
        the background as soon as it is ready (realtime); else only when a pool runs out,
        so that a lockstep run does not depend on compile times. ``counters``: the dict
        that counts spawned, parked, pool_grows, growth_waits (shared with the world)."""
        self.timestep = float(timestep)
        self.threads = int(threads)
        self.pool_chunk = int(pool_chunk)
        self.awd = frozenset(awd)
        self.adopt_early = bool(adopt_early)
        self.counters = counters if counters is not None else {
            "spawned": 0, "parked": 0, "pool_grows": 0, "growth_waits": 0,
        }
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
                # the demand spread over the simulations there are: with more simulations than
                # ``shards`` (SLOTS_PER_SIM) ``initial`` per simulation would multiply it (measured:
                # 508 per simulation for 2 shards became 4 x 508 slots for 1,016)
                self._add_pool(M.default_key(cls), math.ceil(demand[cls] / self.shards))
        self.generation = 0
        self.agent_slot: dict[str, int] = {}
        self.slot_agent: list[str | None] = []
        self.build_s = 0.0  # [s] wall time spent compiling on the stepping thread (cumulative)
        self.wait_s = 0.0  # [s] wall time spent waiting for a background growth (cumulative)
        self.live = np.zeros(0, bool)
        self.layout: Layout | None = None
        self._growth: _Growth | None = None
        self._install(compile_layout(self._pools, self.timestep, self.shards, self.threads))

    def __getitem__(self, p: int) -> Pool:
        """Pool ``p`` of the current layout (or added since, not compiled yet)."""
        return self._pools[p]

    def __len__(self) -> int:
        return len(self._pools)

    @property
    def capacity(self) -> int:
        """Total slots over all pools and shards."""
        return self.shards * sum(p.capacity for p in self._pools)

    def slot_of(self, ids: list[str]) -> np.ndarray:
        """Current slot of each agent id, -1 when not in the world."""
        return np.fromiter(map(self.agent_slot.get, ids, repeat(-1)), np.int64, len(ids))

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

    def _install(self, layout: Layout) -> None:
        """Switch to a compiled layout; live agents of the previous one keep their exact
        qpos/qvel/ctrl/brakes (slot numbers change: ``generation`` increments)."""
        old = self.layout
        self.layout = layout
        self._pools = list(layout.pools)
        self.shards = layout.shards
        G = layout.slots
        old_live = self.live if old is not None else None
        old_agents = self.slot_agent
        self.live = np.zeros(G, bool)
        self.slot_agent = [None] * G
        self.agent_slot = {}
        t = layout.tables
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
        lay = self.layout
        new, ot = lay.tables, old.tables
        news = carry_over(old, lay, olds)
        for a, n in (("qpos", "nq"), ("qvel", "nv"), ("ctrl", "nu")):
            src = concat_ranges(getattr(ot, a)[olds], getattr(ot, n)[olds])
            dst = concat_ranges(getattr(new, a)[news], getattr(new, n)[news])
            lay.state[dst] = old.state[src]
        ok = ot.spin_fl[olds] >= 0
        lay.frictionloss[new.spin_fl[news][ok]] = old.frictionloss[ot.spin_fl[olds][ok]]
        lay.contype[new.geom[news]] = old.contype[ot.geom[olds]]  # ghosts stay ghosts
        lay.conaffinity[new.geom[news]] = old.conaffinity[ot.geom[olds]]
        lay.sleep_policy[new.tree[news]] = SLEEP_NEVER
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
        log.info(
            "physics world: pools running low (%s), compiling %d slots in the background",
            ", ".join(f"{self._pools[p].spec.name} +{e}" for p, e in extra.items()), sims * sum(p.capacity for p in pools),
        )
        fut = _in_daemon_thread(compile_layout, pools, self.timestep, sims, self.threads)
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
        of new pools. May switch to a grown layout (``generation``)."""
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
            if LOW_WATER_PARTS * free < p.capacity * self.shards:
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
        """Drop a background growth without waiting for it: a MuJoCo compile cannot be
        interrupted, and one of thousands of slots on a loaded machine takes seconds, which
        a daemon asked to stop must not spend (its thread is a daemon thread)."""
        if self._growth is not None:
            self._growth.future.cancel()  # no effect once it runs; its result is never read
        self._growth = None

    # ------------------------------------------------------------------ agent set

    def make_room(self, pools: np.ndarray) -> None:
        """Enough free slots for one new agent per entry of ``pools`` (pool indexes): switch
        to the background growth (at once with ``adopt_early``, else when it covers what is
        missing), else recompile now. May switch layouts (``generation``)."""
        pools = np.asarray(pools, np.int64)
        if self.adopt_early:
            self._adopt(wait=False)
        needs = self._needs(pools)
        if needs and self._growth is not None and self._growth.covers(needs, self._pools, self.shards):
            self._adopt(wait=True)
            needs = self._needs(pools)
        if needs:
            self._grow(needs)

    def take(
        self, ids: list[str], pools: np.ndarray, near_x: np.ndarray, near_y: np.ndarray,
        live: np.ndarray, live_x: np.ndarray | None, live_y: np.ndarray | None,
    ) -> np.ndarray:
        """Wake a free slot for each new agent (after ``make_room``); returns slot numbers.

        Each goes to the shard of the live agent (slots ``live``, front bumpers at
        ``live_x``, ``live_y`` [m], or None) nearest to (``near_x``, ``near_y``) [m] within
        ``NEIGHBOUR_M``, unless that shard is over its share; else to the least-loaded shard
        with a free slot. The slot is woken but not placed."""
        pools = np.asarray(pools, np.int64)
        t = self.layout.tables
        load = np.bincount(t.shard[self.live], minlength=self.shards).astype(np.float64)
        out = np.empty(len(ids), np.int64)
        for k, (aid, p) in enumerate(zip(ids, pools)):
            shard = -1
            share = (load.sum() + 1) / self.shards * SHARD_SHARE_SLACK + SHARD_SHARE_EXTRA
            if live_x is not None and len(live):
                d2 = (live_x - near_x[k]) ** 2 + (live_y - near_y[k]) ** 2
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
        self.layout.sleep_policy[t.tree[out]] = SLEEP_NEVER
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
        """Send slots back to the parking lot (rest pose, zero velocity and controls, brakes
        on), let them sleep and free them. (Their collision bits are the world's.)"""
        slots = np.asarray(slots, np.int64)
        if len(slots) == 0:
            return
        lay = self.layout
        t = lay.tables
        st = lay.state
        q0 = lay.model.qpos0
        src = concat_ranges(t.qpos0[slots], t.nq[slots])
        st[concat_ranges(t.qpos[slots], t.nq[slots])] = q0[src]
        st[concat_ranges(t.qvel[slots], t.nv[slots])] = 0.0
        st[concat_ranges(t.ctrl[slots], t.nu[slots])] = 0.0
        fl = t.spin_fl[slots]
        lay.frictionloss[fl[fl >= 0]] = PARKED_BRAKE
        lay.sleep_policy[t.tree[slots]] = SLEEP_ALLOWED
        for g in slots:
            aid = self.slot_agent[g]
            if aid is not None:
                self.agent_slot.pop(aid, None)
            self.slot_agent[g] = None
            self._free[(int(t.pool[g]), int(t.shard[g]))].append(int(g))
        self.live[slots] = False
        self.counters["parked"] += len(slots)


__all__ = ["HEADROOM", "NEIGHBOUR_M", "SLEEP_ALLOWED", "SLEEP_NEVER", "SlotPools"]
