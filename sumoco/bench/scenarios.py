"""``sumoco bench scenarios --json``: every scenario of a pack through ``sumoco demo``.

Each scenario runs as a user runs it (``sumoco demo --sumocfg X``, lockstep, both control
presets side by side) for ``duration`` simulated seconds; one JSON row per scenario: agents
by type, wall time, error p50/p95/max and collisions per preset, rejected messages, every
daemon's exit code. The pack is ``../shared/scenarios`` beside the repository unless
``--pack`` names another folder (one sub-folder per scenario, see its MANIFEST.md).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from sumoco.bench.scenario import REPO_ROOT, demo_config

#: Scenario of each pack folder (the .sumocfg the pack's MANIFEST names to run) and its --begin.
PACK_RUNS: tuple[tuple[str, str, float | None], ...] = (
    ("bologna_acosta", "sumoco_60s.sumocfg", None),
    ("doerpfeldstr", "sumoco_begin50300_60s.sumocfg", None),
    ("doerpfeldstr", "sumoco_trams_60s.sumocfg", None),
    ("tavf_hamburg", "sumoco_60s.sumocfg", None),
    ("synth_lefthand_grid", "lefthand.sumocfg", None),
    ("synth_utm_grid", "grid_local.sumocfg", None),
    ("synth_utm_grid", "grid_utm.sumocfg", None),
    ("synth_features_grid", "features.sumocfg", None),
)

def default_pack() -> Path:
    """``shared/scenarios`` beside the repository (or beside a parent folder)."""
    for base in (REPO_ROOT.parent, *REPO_ROOT.parent.parents):
        if (base / "shared" / "scenarios" / "MANIFEST.md").is_file():
            return base / "shared" / "scenarios"
    return REPO_ROOT.parent / "shared" / "scenarios"


def run_one(cfg: Path, sumocfg: Path, out: Path, duration: float, begin: float | None,
            authority: str | None = None) -> dict:
    argv = [sys.executable, "-m", "sumoco.cli", "demo", "--config", str(cfg), "--out", str(out),
            "--sumocfg", str(sumocfg), "--duration", str(duration), "--quiet"]
    if begin is not None:
        argv += ["--begin", str(begin)]
    if authority:
        argv += ["--authority", authority]
    t0 = time.monotonic()
    r = subprocess.run(argv, capture_output=True, text=True)
    wall = time.monotonic() - t0
    row: dict = {"scenario": f"{sumocfg.parent.name}/{sumocfg.name}", "demo_exit_code": r.returncode,
                 "wall_s": round(wall, 1)}
    try:
        s = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        row["error"] = (r.stderr.strip().splitlines() or ["no summary"])[-1]
        return row
    row.update({
        "steps": s.get("steps"),
        "sim_time_s": s.get("sim_time_s"),
        "rtf": s.get("wall", {}).get("rtf"),
        "agents_by_type": s.get("agents_seen_sumo"),
        "exit_codes": s.get("daemons", {}).get("exit_codes"),
        "completed": s.get("daemons", {}).get("completed"),
        "sumo_rejected": (s.get("sumo_side") or {}).get("rejected"),
        "authority": authority or "sumo",
    })
    side = s.get("sumo_side") or {}
    # SUMO's own trip account, in both modes: what its traffic did, and no vehicle lost
    row["trips"] = {k: side.get(k) for k in (
        "vehicles_inserted", "trips_arrived", "vehicles_running_end", "vanished", "travel_time_mean_s",
        "time_loss_mean_s")}
    if "feedback_steps_applied" in side:  # two-way coupling: what SUMO did with the physical states
        row["coupling"] = {k: side.get(k) for k in (
            "intent_gap_p50_m", "intent_gap_p95_m", "intent_gap_max_m", "feedback_ms", "feedback_late",
            "feedback_clamped", "feedback_internal", "feedback_unknown", "teleports", "arrived", "departed")}
    for inst, p in s.get("presets", {}).items():
        e = p["error_m"]["overall"]
        at = p["error_m"].get("at_samples", {}).get("overall", {})
        row[inst] = {"p50_m": e.get("p50"), "p95_m": e.get("p95"), "max_m": e.get("max"),
                     "at_samples_p95_m": at.get("p95"),
                     "collisions": p.get("collisions"), "collisions_physics_only": p.get("collisions_physics_only"),
                     "placements": p.get("placements"), "placements_by_cause": p.get("placements_by_cause"),
                     "carries_infeasible": p.get("carries_infeasible"),
                     "carries_contact": p.get("carries_contact"), "rejected": p.get("rejected"),
                     "physical_share": p.get("physical_share"),
                     "physical_share_pedestrians": p.get("physical_share_pedestrians")}
    return row


def run_scenario_bench(pack: Path | None = None, duration: float = 60.0, quick: bool = False,
                       out_root: Path | None = None, authority: str | None = None) -> list[dict]:
    """One row per pack scenario (``quick``: 10 s each)."""
    pack = Path(pack) if pack else default_pack()
    duration = 10.0 if quick else duration
    root = Path(out_root) if out_root else Path(tempfile.mkdtemp(prefix="sumoco-scenarios-"))
    cfg = demo_config(root, "bench", ("paper", "default"), duration)
    rows = []
    for folder, name, begin in PACK_RUNS:
        sumocfg = pack / folder / name
        if not sumocfg.is_file():
            rows.append({"scenario": f"{folder}/{name}", "error": f"not found: {sumocfg}"})
            continue
        rows.append(run_one(cfg, sumocfg, root / folder / Path(name).stem, duration, begin, authority))
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    return rows
