"""``run_physics_bench``: cost of one 20 ms control tick for many driving agents.

Synthetic SUMO traffic (``synthetic.traffic.circle_traffic``): cars on concentric circular lanes, spaced
along them, at lane speed, with the path ahead and look-ahead points a SUMO side would
send. Per SUMO step the bench encodes the step (the SUMO side's cost, not counted),
then - counted - decodes it and applies it to the fleet; per control tick it runs the
controllers and MuJoCo substeps, then encodes and publishes ``PhysicsState`` on a real
loopback Zenoh session. A row:

- ``agents``; ``tick_ms``: mean wall time of a control tick including the per-step work
  amortised over the step's ticks; ``tick_p95_ms``;
- ``mujoco_ms``: the MuJoCo substeps of a tick; ``overhead_ms`` = tick_ms - mujoco_ms;
  ``overhead_share`` = overhead_ms / tick_ms, and ``overhead_share_p50`` from medians (the
  median tick's overhead over the median tick): a preemption by another process on a shared
  host lands in either part of a tick at random and moves the means, rarely the medians;
- ``rtf``: 20 ms / tick_ms (real-time factor of the control loop); ``shards``, ``threads``;
- ``phases_ms``: the overhead by phase per tick (``Fleet.phase_s``: sync, policies, act per
  step, spread over its ticks; observe, control, actuate, measure per tick; the daemon's
  decode and publish), and ``load_avg_1min`` of the host.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import replace

import numpy as np

from physics_side.config import PhysicsSettings, check_rates
from physics_side.daemon import build_fleet
from physics_side.fleet import FLEET_PHASES
from protocol.codec import decode_as, encode
from protocol.messages import PhysicsState, StepMessage
from synthetic.traffic import circle_traffic

log = logging.getLogger(__name__)

def _settings(n: int, base: PhysicsSettings | None) -> PhysicsSettings:
    s = base or PhysicsSettings()
    per_shard = int(np.ceil(n / s.physics.shards)) + 8
    return replace(s, physics=replace(s.physics, initial_slots={"passenger": per_shard}, preset="default",
                                      presets={}))


def bench_one(n: int, seconds: float = 2.0, warmup_s: float = 0.4, settings: PhysicsSettings | None = None,
              session=None) -> dict:
    """One row (see module docstring) for ``n`` cars."""
    import zenoh

    from protocol.keys import Keys
    from runtime.config import ZenohConfig
    from runtime.transport import open_session

    settings = _settings(n, settings)
    cfg = settings.physics
    rates = check_rates(cfg.sumo_step_s, cfg.control_hz, cfg.timestep_s)
    fleet = build_fleet(settings)
    own = session is None
    if own:
        session = open_session(ZenohConfig(mode="peer", listen=("tcp/127.0.0.1:0",)))
    keys = Keys("sumoco", "bench", "bench")
    pub = session.declare_publisher(keys.physics_state, congestion_control=zenoh.CongestionControl.DROP)
    steps = int(round((warmup_s + seconds) / cfg.sumo_step_s))
    warm = int(round(warmup_s / cfg.sumo_step_s))
    tick_times: list[float] = []
    mj_times: list[float] = []
    step_cost = 0.0
    extra = {"decode": 0.0, "publish": 0.0}  # [s] the daemon's own phases around the fleet's
    phases0 = None
    try:
        for k in range(steps):
            if k == warm:
                phases0 = dict(fleet.phase_s)
                extra = dict.fromkeys(extra, 0.0)
            data = encode(circle_traffic(n, k, cfg.sumo_step_s))
            t0 = time.perf_counter()
            msg = decode_as(data, StepMessage)
            td = time.perf_counter()
            fleet.apply_step(msg)
            step_cost = time.perf_counter() - t0
            extra["decode"] += td - t0
            for j in range(rates.ticks_per_step):
                t1 = time.perf_counter()
                m0 = fleet.world.mujoco_s
                fleet.tick()
                if fleet.tick_count % cfg.state_every == 0:
                    tp = time.perf_counter()
                    state = PhysicsState("bench", fleet.tick_count, msg.time + (j + 1) * rates.control_dt, msg.step,
                                         fleet.snapshot(), dict(fleet.world.counters))
                    pub.put(encode(state))
                    extra["publish"] += time.perf_counter() - tp
                dt = time.perf_counter() - t1
                if k >= warm:
                    # the step's decode + sync is spread over its ticks
                    tick_times.append(dt + step_cost / rates.ticks_per_step)
                    mj_times.append(fleet.world.mujoco_s - m0)
    finally:
        pub.undeclare()
        if own:
            session.close()
    tick = np.asarray(tick_times) * 1e3
    mj = np.asarray(mj_times) * 1e3
    tick_ms = float(tick.mean())
    mujoco_ms = float(mj.mean())
    w = fleet.world
    n_ticks = max(len(tick_times), 1)
    phases = {p: (fleet.phase_s[p] - (phases0 or {}).get(p, 0.0)) for p in FLEET_PHASES if p != "mujoco"}
    phases.update(extra)
    return {
        "agents": n,
        "tick_ms": round(tick_ms, 3),
        "tick_p95_ms": round(float(np.percentile(tick, 95)), 3),
        "mujoco_ms": round(mujoco_ms, 3),
        "overhead_ms": round(tick_ms - mujoco_ms, 3),
        "overhead_share": round((tick_ms - mujoco_ms) / tick_ms, 3),
        "overhead_share_p50": round(float(np.median(tick - mj) / np.median(tick)), 3),
        # where the overhead goes, per tick [ms] (per-step phases spread over the step's ticks)
        "phases_ms": {p: round(v * 1e3 / n_ticks, 3) for p, v in phases.items()},
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "rtf": round(rates.control_dt * 1e3 / tick_ms, 2),
        "shards": w.shards,
        "threads": w.threads,
        "substeps": rates.substeps,
        "collisions": int(w.counters["collisions"]),
        "placements": int(w.counters["placements"]),
        "max_err_m": round(float(np.max(np.hypot(fleet.err_lon, fleet.err_lat))) if fleet.n else 0.0, 3),
    }


def run_physics_bench(sizes=(100, 500, 1000), quick: bool = False, settings: PhysicsSettings | None = None) -> list[dict]:
    """Rows for each size (``quick``: 50 and 100 agents, short runs)."""
    if quick:
        sizes = tuple(s for s in sizes if s <= 100) or (50,)
    seconds = 0.6 if quick else 2.0
    return [bench_one(n, seconds=seconds, warmup_s=0.2 if quick else 0.4, settings=settings) for n in sizes]


__all__ = ["bench_one", "run_physics_bench"]
