"""``sumoco bench coupling``: the SUMO side's cost of two-way coupling beside SUMO's own step.

A grid scenario fills to about ``agents`` vehicles in libsumo; then, per step, every vehicle
is physics-authoritative and the write-back of its physical state (``SumoCoupling``'s
``FeedbackWriter``: ``moveTo`` on its lane at an along-path offset, ``setPreviousSpeed``) runs
before SUMO's step, with states made from SUMO's own (each vehicle 0.05 m behind its sample,
its speed 1 % lower: a vehicle that tracks well). Rows: ``sumo_step_ms`` (SUMO's own step,
which also pays for the moved vehicles), ``feedback_ms`` (the write-back), their ratio
(goal: at most 0.3 at 1,000 vehicles), and SUMO's step without any write-back measured in
the same run before it (``sumo_alone_ms``) as the limit.
"""

from __future__ import annotations

import os
import time

import numpy as np

from protocol.messages import PhysicsFeedback
from sumo_side.bridge import Bridge
from sumo_side.config import SumoConfig
from sumo_side.coupling import FeedbackWriter
from sumo_side.simulation import SumoSim
from sumoco.bench.scenario import fill, grid_scenario

BEHIND_M = 0.05  # [m] the synthetic physical body's lag behind SUMO's sample
SLOWER = 0.99  # [1] its speed against SUMO's


def _states(snap, step: int) -> tuple[PhysicsFeedback, np.ndarray]:
    nv = snap.n_vehicles
    f32 = np.float32
    fb = PhysicsFeedback(
        run="bench", step=step, time=snap.time, ids=list(snap.ids[:nv]), x=snap.x[:nv], y=snap.y[:nv],
        heading=snap.angle[:nv].astype(f32), speed=(snap.speed[:nv] * SLOWER).astype(f32),
        d_lon=np.full(nv, -BEHIND_M, f32), d_lat=np.zeros(nv, f32), contact=np.zeros(nv, np.uint8))
    return fb, np.arange(nv)


def bench_one(agents: int, steps: int) -> dict:
    sim = SumoSim(SumoConfig(sumocfg=grid_scenario(agents)), seed=42, run_id="bench")
    sim.start()
    try:
        bridge = Bridge(sim, sim.cfg, "bench")
        k, snap = fill(sim, bridge, agents)
        perf = time.perf_counter
        alone = []
        for _ in range(steps):  # the limit: SUMO's own step, nothing written back
            t0 = perf()
            sim.step()
            alone.append(perf() - t0)
            snap = sim.read()
        g = sim.graph
        writer = FeedbackWriter(sim.api, g.ids, g.lengths, g.pos_factor, g.internal)
        t_fb, t_step, n = [], [], []
        for _ in range(steps):
            fb, rows = _states(snap, k)
            t0 = perf()
            writer.apply(fb, rows, snap.lane, snap.lane_pos)
            t1 = perf()
            sim.step()
            t2 = perf()
            snap = sim.read()
            k += 1
            t_fb.append(t1 - t0)
            t_step.append(t2 - t1)
            n.append(fb.n)
        med = lambda v: round(float(np.median(v)) * 1e3, 3)  # noqa: E731
        return {
            "bench": "coupling", "agents": int(np.mean(n)), "steps": steps,
            "sumo_alone_ms": med(alone), "sumo_step_ms": med(t_step), "feedback_ms": med(t_fb),
            "feedback_vs_sumo_step": round(float(np.median(t_fb) / np.median(t_step)), 3),
            "feedback_vs_sumo_alone": round(float(np.median(t_fb) / np.median(alone)), 3),
            "feedback_us_per_vehicle": round(float(np.median(t_fb)) * 1e6 / max(np.mean(n), 1), 2),
            "clamped": writer.stats.clamped, "internal": writer.stats.internal, "unknown": writer.stats.unknown,
            "teleports": sim.counters["teleports"],
            "load_avg_1m": round(os.getloadavg()[0], 2),
        }
    finally:
        sim.close()


def run_coupling_bench(quick: bool = False) -> list[dict]:
    sizes = (250,) if quick else (250, 1000)
    return [bench_one(n, 30 if quick else 100) for n in sizes]


__all__ = ["run_coupling_bench", "bench_one"]
