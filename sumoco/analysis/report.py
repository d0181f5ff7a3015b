"""Tracking report from a recording: ``summary.json``, the paper's figures, ``report.md``.

Everything here is computed from the recorded messages alone, so ``sumoco report
run.mcap`` rebuilds exactly what the live demo wrote. The metric is in ``analysis``.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from sumoco.analysis import figures as figs
from sumoco.analysis.summary import LANE_CHANGE_AFTER_S, LANE_CHANGE_BEFORE_S, analyse_recording
from sumoco.recording.record import open_recording

log = logging.getLogger(__name__)


def write_report(recording: str | Path, out_dir: str | Path, lad_sweep: bool = True) -> dict:
    """Rebuild summary.json, the figures and report.md from a recording."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    res = open_recording(recording)  # streamed: memory does not grow with the file
    summary, fig_data = analyse_recording(res)
    figures: list[str] = []
    ref_id = summary["reference_car"]
    if ref_id and fig_data is not None:
        figures = figs.make_figures(fig_data, ref_id, out, lad_sweep=lad_sweep, summary=summary)
    summary["figures"] = figures
    (out / "summary.json").write_text(json.dumps(summary, indent=1, sort_keys=True) + "\n")
    (out / "report.md").write_text(render_markdown(summary, recording))
    return summary


def _fmt(s: dict | None) -> str:
    if not s or s.get("mean") is None:
        return "n/a"
    return f"{s['mean']:.3f} / {s['p95']:.3f} / {s['max']:.3f}"


def _fmt_lc(lc: dict | None) -> str:
    if not lc or not lc.get("count") or lc.get("max_error_m") is None:
        return "0" if lc else "n/a"
    return f"{lc['count']}, {lc['p95_error_m']:.3f} / {lc['max_error_m']:.3f}"


_SHARE_TYPES = ("passenger", "taxi", "bus", "bicycle", "other")


def _share(v) -> str:
    return "n/a" if v is None else f"{100.0 * v:.1f} %"


def render_markdown(summary: dict, recording) -> str:
    lines = [
        "# sumoco run report",
        "",
        f"Recording: `{Path(recording).name}`; {summary['steps']} SUMO steps, "
        f"{summary['sim_time_s']} s simulated"
        + (f", real-time factor {summary['wall']['rtf']}" if summary["wall"].get("rtf") else "")
        + ".",
        f"Reference car: `{summary['reference_car']}`. Agents SUMO reported: "
        + ", ".join(f"{k} {v}" for k, v in summary["agents_seen_sumo"].items()) + ".",
        "",
        "Front-bumper position error against SUMO at the same time [m], mean / p95 / max:",
        "",
        "| preset | all agents | reference car | ref straight | ref turn | lane changes: count, p95 / max "
        "| collisions (physics only) | placements (spawn / jump / divergence / flip) "
        "| kinematic through a manoeuvre beyond steering or lean: count, agent-s "
        "| kinematic to keep clear of a contact SUMO does not have: count, agent-s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for inst, p in summary["presets"].items():
        rc = p.get("reference_car", {})
        pc = p.get("placements_by_cause", {})
        ci = p.get("carries_infeasible", {})
        cc = p.get("carries_contact", {})
        causes = " / ".join(str(pc.get(c, 0)) for c in ("spawn", "jump", "divergence", "flip"))
        lines.append(
            f"| {inst} | {_fmt(p['error_m']['overall'])} | {_fmt(rc.get('overall'))} | "
            f"{_fmt(rc.get('straight'))} | {_fmt(rc.get('turn'))} | {_fmt_lc(p.get('lane_changes'))} | "
            f"{p['collisions']} "
            f"({p.get('collisions_physics_only', 0)}) | {p['placements']} ({causes}) | "
            f"{ci.get('count', 0)}, {ci.get('agent_s', 0):g} | {cc.get('count', 0)}, {cc.get('agent_s', 0):g} |"
        )
    lines += [
        "",
        "Lane changes: every lane change SUMO reports (lane index to another lane of the same",
        f"edge), the error of the agent's samples from {LANE_CHANGE_BEFORE_S:g} s before to "
        f"{LANE_CHANGE_AFTER_S:g} s after it, outside junctions.",
        "",
        "Collisions count physics contacts between agents; \"physics only\" are those where SUMO",
        "had no collision or teleport of its own (its footprints apart). Placements put an",
        "agent at its SUMO pose: at spawn, after a SUMO teleport or a sideways slide in a queue",
        "(jump), when it diverged too far, or when it flipped.",
        "",
        "Per agent type (mean / p95 / max) [m]:", "",
    ]
    types = sorted({t for p in summary["presets"].values() for t in p["error_m"]["per_type"]})
    lines.append("| preset | " + " | ".join(types) + " |")
    lines.append("|---" * (len(types) + 1) + "|")
    for inst, p in summary["presets"].items():
        lines.append(f"| {inst} | " + " | ".join(_fmt(p["error_m"]["per_type"].get(t)) for t in types) + " |")
    shares = {inst: p.get("physical_share") for inst, p in summary["presets"].items()}
    if any(v is not None for v in shares.values()):
        lines += ["", f"Physical share (vehicle agent-time driven by physics, not carried or placed; "
                      f"authority: {summary.get('authority', 'sumo')}):", "",
                  "| preset | all vehicles | " + " | ".join(_SHARE_TYPES) + " | pedestrians |",
                  "|---" * (len(_SHARE_TYPES) + 3) + "|"]
        for inst, p in summary["presets"].items():
            by = p.get("physical_share_by_type") or {}
            lines.append(f"| {inst} | {_share(p.get('physical_share'))} | "
                         + " | ".join(_share(by.get(t)) for t in _SHARE_TYPES)
                         + f" | {_share(p.get('physical_share_pedestrians'))} |")
    if summary.get("figures"):
        lines += ["", "## Figures (reference car, presets side by side)", ""]
        for f in summary["figures"]:
            lines.append(f"![{f}]({f})")
            lines.append("")
    if summary.get("lad_sweep"):
        lines += ["", "LAD_min sweep through the right turn (paper preset, reference car replayed alone):", "",
                  "| LAD_min [m] | max lateral error in turn [m] | max error [m] | placements divergence / flip |",
                  "|---|---|---|---|"]
        for row in summary["lad_sweep"]:
            lines.append(f"| {row['lad_min_m']} | {row['turn_lat_max_m']:.3f} | {row['err_max_m']:.3f} | "
                         f"{row.get('placements_divergence', 0)} / {row.get('placements_flip', 0)} |")
    if summary.get("truncated_recording"):
        lines += ["", "**The recording is truncated**: numbers cover what it holds."]
    return "\n".join(lines) + "\n"


def cli_main(args) -> int:
    out = Path(args.out) if getattr(args, "out", None) else Path(args.recording).parent
    summary = write_report(args.recording, out, lad_sweep=not getattr(args, "no_sweep", False))
    print(json.dumps({k: summary[k] for k in ("steps", "reference_car")} | {
        "presets": {k: v["error_m"]["overall"] for k, v in summary["presets"].items()}}, indent=1))
    return 0
