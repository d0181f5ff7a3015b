"""``sumoco bench scale``: how far one machine goes, each number beside its limit from the same run.

Rows (one JSON object each; field names stable across versions):

- pool rows: ``pool_slots``, ``build_s`` (world build: spec + compile + batch), ``rss_mb``
  (peak resident memory of a fresh process that only builds the world), with the goals
  ``goal_build_s`` / ``goal_rss_mb`` and ``template_build_s`` (one slot, the floor).
- co-simulation rows, per size and with LOD off / on: ``agents``, ``lod``,
  ``full_physics_agents``, ``sumo_alone_steps_per_s`` and ``cosim_steps_per_s`` (the
  same grid scenario: SUMO's own steps alone, then the whole lockstep chain per step in
  one process: SUMO step, bridge, encode, decode, apply, ``ticks_per_step`` physics
  ticks, state encode), ``bridge_ms``, ``sumo_step_ms``, ``bytes_per_step``,
  ``physics_tick_ms``, ``mujoco_ms`` (MuJoCo's own step of the same bodies),
  ``rss_mb``, ``cosim_to_sumo_ratio``; the same per step in CPU time
  (``sumo_alone_cpu_ms``, ``cosim_cpu_ms``, ``cosim_to_sumo_cpu_ratio``: all threads of
  the process, not inflated by other load) and ``load_avg_1min``. The transport between processes is not in
  these rows (``sumoco bench e2e`` measures it against raw Zenoh).

With LOD on, a region around the network centre holds about ``FULL_AGENTS`` agents in
full physics; the rest never enter MuJoCo (``physics_side.lod.DetailSplit``, as in the
daemon) and are published on their extrapolated SUMO pose.
"""

from __future__ import annotations

import json
import logging
import os
import resource
import subprocess
import sys
import time
import numpy as np

log = logging.getLogger(__name__)

FULL_AGENTS = 500  # agents in full physics with LOD on (the goal: >= 500)
GOAL_BUILD_S = 5.0  # [s] pool build for 4,096 slots
GOAL_RSS_MB = 2048.0  # [MB]

_POOL_CODE = """
import json, resource, time
t0 = time.perf_counter()
from physics_side.world import PhysicsWorld, HEADROOM
from protocol.messages import AgentClass
t1 = time.perf_counter()
w = PhysicsWorld(0.005, 4, shards=2, threads=2, initial={{}}, expect={{AgentClass.PASSENGER: int({slots} / HEADROOM)}})
t2 = time.perf_counter()
print(json.dumps({{"pool_slots": w.capacity, "simulations": w.shards, "build_s": round(t2 - t1, 3),
                  "rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}}))
"""


def pool_row(slots: int) -> dict:
    """Build a world of about ``slots`` passenger slots in a fresh process."""
    out = subprocess.run([sys.executable, "-c", _POOL_CODE.format(slots=slots)], capture_output=True, text=True,
                         timeout=600, check=True)
    row = json.loads(out.stdout.strip().splitlines()[-1])
    one = json.loads(subprocess.run([sys.executable, "-c", _POOL_CODE.format(slots=2)], capture_output=True,
                                    text=True, timeout=600, check=True).stdout.strip().splitlines()[-1])
    row.update(load_avg_1min=round(os.getloadavg()[0], 2), template_build_s=one["build_s"], template_rss_mb=one["rss_mb"], goal_build_s=GOAL_BUILD_S,
               goal_rss_mb=GOAL_RSS_MB)
    return row


def _lod_region(x: np.ndarray, y: np.ndarray, n_full: int) -> tuple[float, float, float]:
    """A circle around the agents' centre holding about ``n_full`` of them [m]."""
    cx, cy = float(np.median(x)), float(np.median(y))
    d = np.sort(np.hypot(x - cx, y - cy))
    r = float(d[min(n_full, len(d)) - 1]) if len(d) else 1.0
    return cx, cy, max(r, 1.0)


def cosim_rows(size: int, steps: int, lod_modes=(False, True), seed: int = 42) -> list[dict]:
    """SUMO alone, then the lockstep chain with LOD off / on, on one grid scenario."""
    from physics_side.config import PhysicsConfig, PhysicsSettings, check_rates
    from physics_side.daemon import build_fleet
    from physics_side.lod import DetailSplit, DetailZones
    from protocol.codec import decode_as, encode
    from protocol.messages import AgentMode, PhysicsState, StepMessage
    from sumo_side.bench import _cache_dir
    from sumo_side.bridge import Bridge
    from sumo_side.config import SumoConfig
    from sumo_side.scenarios import make_grid_scenario
    from sumo_side.simulation import SumoSim

    cfg_path = make_grid_scenario(_cache_dir(), size, seed=seed)
    cfg = SumoConfig(sumocfg=cfg_path)
    rows = []
    for lod in lod_modes:
        sim = SumoSim(cfg, seed=seed, run_id="bench")
        sim.start()
        try:
            bridge = Bridge(sim, cfg, "bench")
            k = 0
            snap = None
            for k in range(6000):  # fill the network to the target size
                sim.step()
                snap = sim.read()
                bridge.build(k, snap)
                if snap.n >= 0.97 * size:
                    break
            perf = time.perf_counter
            cpu = time.process_time
            alone, alone_cpu = [], []
            for _ in range(steps):  # SUMO alone: its own step, nothing else
                k += 1
                t0, c0 = perf(), cpu()
                sim.step()
                alone.append(perf() - t0)
                alone_cpu.append(cpu() - c0)
                snap = sim.read()
                bridge.build(k, snap)
            split = None
            expect = snap.n * 1.1
            if lod:  # as the daemon does: agents outside the zone never reach the fleet
                region = _lod_region(np.asarray(snap.x), np.asarray(snap.y), FULL_AGENTS)
                split = DetailSplit(DetailZones.from_config(0.0, [region]))
                expect = FULL_AGENTS * 1.3
            phys = PhysicsConfig(shards=2, threads=2, initial_slots={}, expect={"passenger": int(expect)},
                                 preset="default")
            settings = PhysicsSettings(physics=phys)
            rates = check_rates(phys.sumo_step_s, phys.control_hz, phys.timestep_s)
            fleet = build_fleet(settings)
            sumo_t, bridge_t, total_t, tick_t, mj_t, nbytes, agents_n, full, total_cpu = ([] for _ in range(9))
            for i in range(steps + 5):
                k += 1
                t0, c0 = perf(), cpu()
                sim.step()
                t1 = perf()
                snap = sim.read()
                data = encode(bridge.build(k, snap))
                t2 = perf()
                msg = decode_as(data, StepMessage)
                near = msg if split is None else split.apply(msg)
                fleet.apply_step(near)
                m0 = fleet.world.mujoco_s
                ticks = []
                for _ in range(rates.ticks_per_step):
                    tt = perf()
                    fleet.tick()
                    ticks.append(perf() - tt)
                agents = fleet.snapshot() if split is None else split.snapshot(fleet.snapshot(), msg.time)
                encode(PhysicsState(run="bench", tick=fleet.tick_count, time=msg.time, sumo_step=msg.step,
                                    agents=agents, counters={}))
                t3, c3 = perf(), cpu()
                if i < 5:  # the first steps spawn the whole network
                    continue
                sumo_t.append(t1 - t0)
                bridge_t.append(t2 - t1)
                total_t.append(t3 - t0)
                total_cpu.append(c3 - c0)
                tick_t.append(float(np.mean(ticks)))
                mj_t.append((fleet.world.mujoco_s - m0) / rates.ticks_per_step)
                nbytes.append(len(data))
                agents_n.append(msg.agents.n)
                full.append(int((fleet.mode == AgentMode.PHYSICAL).sum()))
            fleet.world.close()
        finally:
            sim.close()
        ms = lambda xs: round(float(np.mean(xs)) * 1e3, 3)  # noqa: E731
        rows.append({
            "agents": int(round(float(np.mean(agents_n)))), "lod": lod, "full_physics_agents": int(np.mean(full)),
            "sumo_alone_steps_per_s": round(1.0 / float(np.mean(alone)), 2),
            "cosim_steps_per_s": round(1.0 / float(np.mean(total_t)), 2),
            "cosim_to_sumo_ratio": round(float(np.mean(alone)) / float(np.mean(total_t)), 3),
            "bridge_ms": ms(bridge_t), "sumo_step_ms": ms(sumo_t),
            "bridge_to_sumo_ratio": round(float(np.mean(bridge_t)) / float(np.mean(sumo_t)), 3),
            "bytes_per_step": int(np.mean(nbytes)), "physics_tick_ms": ms(tick_t), "mujoco_ms": ms(mj_t),
            "ticks_per_step": rates.ticks_per_step, "simulations": fleet.world.shards,
            "rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1), "steps": steps,
            # CPU time (all threads of this process): robust to other load on the machine
            "sumo_alone_cpu_ms": ms(alone_cpu), "cosim_cpu_ms": ms(total_cpu),
            "cosim_to_sumo_cpu_ratio": round(float(np.mean(alone_cpu)) / float(np.mean(total_cpu)), 3),
            "load_avg_1min": round(os.getloadavg()[0], 2),
        })
        log.info("bench scale: %s", rows[-1])
    return rows


def run_scale_bench(sizes=(1000, 2500, 5000, 10000), pool_sizes=(1024, 2048, 4096), steps: int = 30,
                    quick: bool = False) -> list[dict]:
    """Pool rows, then co-simulation rows per size (quick: 1,024 slots and 1,000 agents)."""
    if quick:
        sizes, pool_sizes, steps = (1000,), (1024,), 10
    rows = [pool_row(n) for n in pool_sizes]
    for size in sizes:
        rows.extend(cosim_rows(size, steps))
    return rows


__all__ = ["cosim_rows", "pool_row", "run_scale_bench"]
