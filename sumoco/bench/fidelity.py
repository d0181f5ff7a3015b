"""``sumoco bench fidelity``: tracking error per preset, agent type, SUMO step length and scenario.

One process, no transport: SUMO (libsumo, the SUMO side's ``SumoSim`` + ``Bridge``) steps
the scenario; every step message goes through the codec (``encode`` / ``decode_as``, as
on the wire) into one ``Fleet`` per preset, which simulates up to the step's end time
exactly like the lockstep daemon (``ticks_to``). The states are scored with the report's
own analysis (``analysis.summarise``): front-bumper error against SUMO interpolated to
the physics time, PHYSICAL agents only, jumps and rides left out.

Rows (JSON): scenario, step_s, preset, agents by type, overall / reference-car / per-type
error stats [m], the error around lane changes (count, max, p95 [m]), collisions
(physics only / SUMO also reported), placements by cause, wall time. Runs are short
(``--duration``) so the whole sweep fits a few minutes.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

from protocol.codec import decode_as, encode
from protocol.messages import PhysicsState, StepMessage
from sumoco.bench.scenario import PAPER_SUMOCFG

log = logging.getLogger(__name__)

DEMO_SUMOCFG = PAPER_SUMOCFG  # the step-length sweep runs on the demo's scenario
STEP_LENGTHS = (0.05, 0.1, 0.2, 0.5, 1.0)
PRESETS = ("paper", "default")


def pack_scenarios() -> list[Path]:
    """The pack's scenarios (the list ``sumoco bench scenarios`` runs) where the pack is."""
    from sumoco.bench.scenarios import PACK_RUNS, default_pack

    d = default_pack()
    return [d / folder / name for folder, name, _ in PACK_RUNS if (d / folder / name).is_file()]


def run_one(
    sumocfg: Path, presets=PRESETS, step_s: float | None = None, duration_s: float = 30.0, seed: int = 42,
    settings=None,
) -> list[dict]:
    """One SUMO run of ``sumocfg`` driving one fleet per preset; a summary row per preset."""
    from physics_side.config import PhysicsSettings, ticks_to
    from physics_side.daemon import build_fleet
    from sumo_side.bridge import Bridge
    from sumo_side.config import SumoConfig
    from sumo_side.simulation import SumoSim
    from sumoco.analysis.summary import summarise

    settings = settings or PhysicsSettings()
    cfg = SumoConfig(sumocfg=Path(sumocfg))
    if step_s is not None:
        cfg = replace(cfg, step_length_s=float(step_s))
    sim = SumoSim(cfg, seed=seed, run_id="fidelity")
    sim.start()
    fleets = {}
    for p in presets:
        phys = replace(settings.physics, preset=p, presets={}, instance=p)
        fleets[p] = build_fleet(replace(settings, physics=phys))
    clock = {p: None for p in presets}
    rec = _Recorder(presets)
    wall = {p: 0.0 for p in presets}
    t0 = time.perf_counter()
    try:
        bridge = Bridge(sim, cfg, "fidelity")
        rec.static = sim.static
        k = 0
        while not sim.finished(duration_s):
            sim.step()
            msg = bridge.build(k, sim.read())
            data = encode(msg)
            msg = decode_as(data, StepMessage)
            rec.step(msg)
            for p, fleet in fleets.items():
                w0 = time.perf_counter()
                # the daemon's lockstep clock: interpolating, physics covers (previous step, this step]
                start = msg.time - (msg.step_length if fleet.interpolates(msg.step_length) else 0.0)
                t = start if clock[p] is None else clock[p]
                if t < start - fleet.dt:
                    t = start
                fleet.apply_step(msg, tau=t - start)
                for _ in range(ticks_to(t, start + msg.step_length, fleet.dt)):
                    fleet.tick()
                    t += fleet.dt
                    rec.state(p, t, fleet)
                clock[p] = t
                wall[p] += time.perf_counter() - w0
            k += 1
    finally:
        sim.close()
    summary = summarise(rec.run_data(time.perf_counter() - t0))
    rows = []
    for p in presets:
        e = summary["presets"].get(p, {})
        rows.append({
            "scenario": Path(sumocfg).parent.name + "/" + Path(sumocfg).name,
            "step_s": round(float(rec.step_length or 0.0), 4), "preset": p,
            "sim_s": summary["sim_time_s"], "agents": summary["agents_seen_sumo"],
            "error_m": e.get("error_m", {}).get("overall"),
            # the same at SUMO's sample times only (no assumption about SUMO between samples)
            "error_at_samples_m": e.get("error_m", {}).get("at_samples"),
            "reference_car": summary.get("reference_car"),
            "reference_car_error_m": e.get("reference_car"),
            "per_type_error_m": e.get("error_m", {}).get("per_type"),
            # the error around each lane change SUMO reports (count, max, p95 [m])
            "lane_changes": e.get("lane_changes"),
            "collisions": e.get("collisions"),
            "collisions_physics_only": e.get("collisions_physics_only"),
            "collisions_sumo_reported": e.get("collisions_sumo_reported"),
            "placements": e.get("placements_by_cause"),
            "carries_infeasible": e.get("carries_infeasible"),
            "carries_contact": e.get("carries_contact"),
            "physics_wall_s": round(wall[p], 3),
        })
    return rows


class _Recorder:
    """SUMO steps and physics states in memory, shaped like a recording for ``analysis``."""

    def __init__(self, presets) -> None:
        self.static = None
        self.steps: list[StepMessage] = []
        self.states: dict[str, list[PhysicsState]] = {p: [] for p in presets}
        self.step_length: float | None = None

    def step(self, msg: StepMessage) -> None:
        self.steps.append(msg)
        self.step_length = msg.step_length

    def state(self, preset: str, t: float, fleet) -> None:
        counters = dict(fleet.world.counters)
        counters.update(fleet.counters)
        self.states[preset].append(PhysicsState(
            run="fidelity", tick=fleet.tick_count, time=t, sumo_step=fleet.sumo_step, agents=fleet.snapshot(),
            counters=counters,
        ))

    def run_data(self, wall_s: float):
        from sumoco.analysis.summary import build_run_data

        return build_run_data(self.static, self.steps, self.states, wall_s)


def run_fidelity_bench(quick: bool = False, duration_s: float | None = None) -> list[dict]:
    """Step-length sweep on the bundled demo, then every pack scenario at its own step length."""
    rows = []
    dur = duration_s or (20.0 if quick else 60.0)
    steps = (0.1, 1.0) if quick else STEP_LENGTHS
    for st in steps:
        rows += run_one(DEMO_SUMOCFG, step_s=st, duration_s=dur)
    for cfg in pack_scenarios()[: 2 if quick else None]:
        try:
            rows += run_one(cfg, duration_s=min(dur, 30.0))
        except Exception as e:  # one broken scenario must not hide the others' rows
            log.warning("%s: %s", cfg, e)
            rows.append({"scenario": str(cfg), "error": str(e)})
    return rows


__all__ = ["pack_scenarios", "run_fidelity_bench", "run_one"]
