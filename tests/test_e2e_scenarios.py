"""Real SUMO scenarios through ``sumoco demo --sumocfg``: a short slice of each, in lockstep.

The scenario pack lives beside the repository (``../shared/scenarios``, see its MANIFEST.md;
the files are not part of this repository). Each slice must end with every daemon exiting
0 on the same final step, at the scenario's own step length, with nothing rejected, SUMO's
own outputs in the run folder (the pack's folders are read-only) and a report written.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.harness import ROOT, scenario_pack

pytestmark = pytest.mark.integration

PACK = scenario_pack()

if PACK is None:
    if os.environ.get("CI"):
        raise RuntimeError("scenario pack missing: CI must have shared/scenarios beside the clone")
    pytest.skip(f"scenario pack not found (expected shared/scenarios beside {ROOT} or a parent)",
                allow_module_level=True)

#: (case, .sumocfg in the pack, --begin or None, simulated seconds, step length the scenario sets [s])
CASES = [
    # upstream config: tripinfos, detector output and SUMO's log must land in the run folder
    ("bologna", "bologna_acosta/run.sumocfg", 30.0, 8.0, 1.0),
    # upstream config, begin 50300 (HH:MM:SS departures), edgeData outputs in additional files
    ("doerpfeldstr", "doerpfeldstr/all_modes.sumocfg", None, 8.0, 1.0),
    ("doerpfeldstr_trams", "doerpfeldstr/sumoco_trams_60s.sumocfg", 50520.0, 8.0, 1.0),
    ("hamburg", "tavf_hamburg/sumoco_60s.sumocfg", 20.0, 6.0, 1.0),
    ("lefthand", "synth_lefthand_grid/lefthand.sumocfg", 20.0, 6.0, 0.1),
    ("grid_local", "synth_utm_grid/grid_local.sumocfg", 20.0, 6.0, 0.1),
    ("grid_utm", "synth_utm_grid/grid_utm.sumocfg", 20.0, 6.0, 0.1),
    # begin 100 in the scenario, 0.5 s steps, sublane model, rerouting devices
    ("features", "synth_features_grid/features.sumocfg", None, 10.0, 0.5),
]


def _config(tmp: Path) -> Path:
    p = tmp / "pack.toml"
    p.write_text("""
[run]
id = "pack"
timing = "lockstep"
lockstep_timeout_s = 30.0
[physics]
preset = "default"
[record]
physics_hz = 10.0
[demo]
presets = ["default"]
lad_sweep = false
wall_limit_s = 150.0
""")
    return p


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict:
    tmp = tmp_path_factory.mktemp("pack")
    cfg = _config(tmp)
    done = {"t0": time.time()}
    for case, sumocfg, begin, duration, _ in CASES:
        out = tmp / case
        argv = [sys.executable, "-m", "sumoco.cli", "demo", "--config", str(cfg), "--out", str(out),
                "--sumocfg", str(PACK / sumocfg), "--duration", str(duration), "--quiet"]
        if begin is not None:
            argv += ["--begin", str(begin)]
        done[case] = (subprocess.run(argv, capture_output=True, text=True, timeout=240, cwd=ROOT), out)
    return done


@pytest.mark.parametrize("case, sumocfg, begin, duration, dt", CASES, ids=[c[0] for c in CASES])
def test_slice_runs_clean(runs, case, sumocfg, begin, duration, dt):
    r, out = runs[case]
    assert r.returncode == 0, r.stderr[-3000:]
    s = json.loads((out / "summary.json").read_text())
    assert s["daemons"]["exit_codes"] == {"sumo": 0, "physics-default": 0}
    assert s["daemons"]["completed"] is True
    # the scenario's own step length, and the duration counted from its begin
    assert s["steps"] == round(duration / dt), s["steps"]
    assert s["sim_time_s"] == pytest.approx(duration - dt)
    p = s["presets"]["default"]
    assert p["rejected"] == 0 and p["counters"]["dropped_steps"] == 0
    assert s["sumo_side"]["rejected"] == 0 and s["sumo_side"]["steps"] == s["steps"]
    assert sum(s["agents_seen_sumo"].values()) > 0
    assert (out / "report.md").stat().st_size > 200
    log = (out / "logs" / "sumo.log").read_text()
    assert "Traceback" not in log


def test_scenario_outputs_go_to_the_run_folder(runs):
    _, out = runs["bologna"]
    assert (out / "sumo" / "tripinfos.xml").is_file()
    assert (out / "sumo" / "e1_output.xml").is_file()
    assert (out / "sumo" / "sumo_log.txt").is_file()
    # nothing written next to the scenario by this run (other tools may have left files there)
    for name in ("tripinfos.xml", "e1_output.xml", "sumo_log.txt"):
        f = PACK / "bologna_acosta" / name
        assert not f.exists() or f.stat().st_mtime < runs["t0"], f


def test_sumo_warnings_reach_the_log(runs):
    _, out = runs["doerpfeldstr"]
    assert "Warning: Unequal lengths of bidi lane" in (out / "logs" / "sumo.log").read_text()


def test_utm_offsets_track_like_local_coordinates(runs):
    """Same net and routes, shifted by 691 km / 5,335 km: tracking must not depend on it."""
    local = json.loads((runs["grid_local"][1] / "summary.json").read_text())
    utm = json.loads((runs["grid_utm"][1] / "summary.json").read_text())
    assert local["agents_seen_sumo"] == utm["agents_seen_sumo"]
    e_local = local["presets"]["default"]["error_m"]["overall"]
    e_utm = utm["presets"]["default"]["error_m"]["overall"]
    assert e_utm["p95"] == pytest.approx(e_local["p95"], abs=0.02)
    assert e_utm["max"] == pytest.approx(e_local["max"], abs=0.1)
