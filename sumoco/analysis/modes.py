"""Shadow against two-way coupling on the same scenario: ``modes.md`` and ``modes.json``.

Reads the ``summary.json`` of finished runs (``sumoco demo --compare-authority`` makes two:
``sumo-authority/`` and ``physics-authority/``; ``sumoco compare`` takes any) and sets side
by side what the mode changes: how much of the vehicles' time physics drives, how close
physics tracks SUMO, and what SUMO's traffic did (trips ended, their travel time and time
loss from SUMO's tripinfo device, throughput, vehicles lost, teleports).
"""

from __future__ import annotations

import json
from pathlib import Path

#: the preset whose numbers stand for a run (the instance SUMO follows in two-way mode)
FOLLOWED_PRESET = "default"
SECONDS_PER_HOUR = 3600.0


def _preset(summary: dict) -> tuple[str, dict]:
    presets = summary.get("presets") or {}
    if FOLLOWED_PRESET in presets:
        return FOLLOWED_PRESET, presets[FOLLOWED_PRESET]
    name = next(iter(presets), "")
    return name, presets.get(name, {})


def mode_row(run_dir: Path) -> dict:
    """One run's row (``run_dir``: a demo output folder with ``summary.json``)."""
    s = json.loads((Path(run_dir) / "summary.json").read_text())
    name, p = _preset(s)
    side = s.get("sumo_side") or {}
    sim_s = float(s.get("sim_time_s") or 0.0)
    arrived = side.get("trips_arrived")
    err = (p.get("error_m") or {}).get("overall") or {}
    return {
        "run": Path(run_dir).name,
        "authority": s.get("authority", "sumo"),
        "preset": name,
        "sim_time_s": sim_s,
        "physical_share": p.get("physical_share"),
        "error_p50_m": err.get("p50"),
        "error_p95_m": err.get("p95"),
        "error_max_m": err.get("max"),
        "collisions_physics": p.get("collisions"),
        "intent_gap_p95_m": side.get("intent_gap_p95_m"),
        "feedback_ms": side.get("feedback_ms"),
        "feedback_late": side.get("feedback_late"),
        "trips_arrived": arrived,
        "travel_time_mean_s": side.get("travel_time_mean_s"),
        "time_loss_mean_s": side.get("time_loss_mean_s"),
        "throughput_veh_h": round(arrived / sim_s * SECONDS_PER_HOUR, 1) if arrived is not None and sim_s else None,
        "vehicles_inserted": side.get("vehicles_inserted"),
        "vanished": side.get("vanished"),
        "teleports": side.get("teleports"),
        "exit_codes": (s.get("daemons") or {}).get("exit_codes"),
    }


def _cell(v) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.3f}" if abs(v) < 100 else f"{v:.1f}"
    return str(v)


COLUMNS = (
    ("run", "run"), ("authority", "authority"), ("physical_share", "physical share"),
    ("error_p95_m", "tracking p95 [m]"), ("error_max_m", "tracking max [m]"),
    ("intent_gap_p95_m", "intent gap p95 [m]"), ("feedback_ms", "write-back [ms/step]"),
    ("trips_arrived", "trips ended"), ("travel_time_mean_s", "travel time mean [s]"),
    ("time_loss_mean_s", "time loss mean [s]"), ("throughput_veh_h", "throughput [veh/h]"),
    ("vanished", "vanished"), ("teleports", "teleports"),
)


def render_modes(rows: list[dict]) -> str:
    lines = [
        "# Shadow and two-way coupling side by side",
        "",
        "Physical share: vehicle agent-time driven by physics (not carried), preset "
        f"`{FOLLOWED_PRESET}`. Tracking: front-bumper error against SUMO. Trips: SUMO's tripinfo "
        "device (vehicles that ended their route in the run). Vanished: inserted vehicles that "
        "neither arrived nor are still running at the end.",
        "",
        "| " + " | ".join(h for _, h in COLUMNS) + " |",
        "|" + "---|" * len(COLUMNS),
    ]
    for r in rows:
        lines.append("| " + " | ".join(_cell(r.get(k)) for k, _ in COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def write_modes(run_dirs: list[Path], out: Path) -> list[dict]:
    """``modes.json`` and ``modes.md`` for ``run_dirs`` in ``out``; returns the rows."""
    rows = [mode_row(d) for d in run_dirs]
    out.mkdir(parents=True, exist_ok=True)
    (out / "modes.json").write_text(json.dumps(rows, indent=1, sort_keys=True) + "\n")
    (out / "modes.md").write_text(render_modes(rows))
    return rows


def cli_main(args) -> int:
    """``sumoco compare RUN_DIR... --out DIR``."""
    from protocol.errors import ConfigError

    dirs = [Path(d) for d in args.runs]
    for d in dirs:
        if not (d / "summary.json").is_file():
            raise ConfigError(f"{d}: expected a run folder with summary.json (a `sumoco demo` output)")
    out = Path(args.out) if args.out else dirs[0].parent
    write_modes(dirs, out)
    print(f"comparison: {out / 'modes.md'}")
    return 0


__all__ = ["COLUMNS", "FOLLOWED_PRESET", "cli_main", "mode_row", "render_modes", "write_modes"]
