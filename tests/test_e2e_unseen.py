"""A scenario the project has never seen, generated at test time, runs clean.

Left-hand traffic, UTM-sized coordinates (691 km / 5,335 km, not normalised), 0.05 s steps,
the sublane model, rerouting devices, and SUMO's default vehicle classes the bundled demo
never uses (trucks, trailers, motorcycles, coaches, with SUMO's default sizes), routed by SUMO
at insertion. ``sumoco demo --sumocfg`` must finish in lockstep with every daemon exiting 0,
at the scenario's own step length, nothing rejected.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from sumo_side.scenarios import find_sumo_binary
from tests.harness import ROOT

pytestmark = pytest.mark.integration

SIM_S = 6.0  # [s] simulated
STEP_S = 0.05  # [s] the scenario's step length

ROUTES = """<routes>
  <vType id="truck" vClass="truck"/>
  <vType id="trailer" vClass="trailer"/>
  <vType id="moto" vClass="motorcycle"/>
  <vType id="coach" vClass="coach"/>
  <vType id="car" vClass="passenger"/>
  <flow id="car" type="car" from="A0A1" to="C2C1" begin="0" end="60" period="2"/>
  <flow id="truck" type="truck" from="A1A0" to="C1C2" begin="0" end="60" period="6"/>
  <flow id="trailer" type="trailer" from="C0B0" to="A2B2" begin="0.5" end="60" period="7"/>
  <flow id="moto" type="moto" from="B0A0" to="B2C2" begin="1" end="60" period="3"/>
  <flow id="coach" type="coach" from="C2B2" to="A0B0" begin="1.5" end="60" period="8"/>
</routes>
"""

SUMOCFG = f"""<configuration>
  <input>
    <net-file value="net.net.xml"/>
    <route-files value="routes.rou.xml"/>
  </input>
  <time><begin value="0"/><end value="300"/><step-length value="{STEP_S}"/></time>
  <processing><lateral-resolution value="0.8"/></processing>
  <routing>
    <device.rerouting.probability value="1"/>
    <device.rerouting.period value="2"/>
  </routing>
  <random_number><seed value="3"/></random_number>
  <report><no-step-log value="true"/></report>
</configuration>
"""


@pytest.fixture(scope="module")
def scenario(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("unseen")
    subprocess.run(
        [find_sumo_binary("netgenerate"), "--grid", "--grid.number", "3", "--grid.length", "120",
         "--default.lanenumber", "2", "--tls.guess", "true", "--lefthand", "true",
         "--offset.x", "691000", "--offset.y", "5335000", "--offset.disable-normalization", "true",
         "--seed", "5", "-o", "net.net.xml"],
        cwd=d, check=True, capture_output=True, timeout=60,
    )
    (d / "routes.rou.xml").write_text(ROUTES)
    (d / "unseen.sumocfg").write_text(SUMOCFG)
    return d / "unseen.sumocfg"


def test_unseen_scenario_runs_clean(scenario, tmp_path):
    cfg = tmp_path / "run.toml"
    cfg.write_text("""
[run]
id = "unseen"
timing = "lockstep"
lockstep_timeout_s = 30.0
[physics]
preset = "default"
[demo]
presets = ["default"]
lad_sweep = false
""")
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "sumoco.app.cli", "demo", "--config", str(cfg), "--sumocfg",
                        str(scenario), "--out", str(out), "--duration", str(SIM_S), "--quiet"],
                       capture_output=True, text=True, timeout=240, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-3000:]
    s = json.loads((out / "summary.json").read_text())
    assert s["daemons"]["exit_codes"] == {"sumo": 0, "physics-default": 0}
    assert s["daemons"]["completed"] is True
    assert s["steps"] == round(SIM_S / STEP_S)
    p = s["presets"]["default"]
    assert p["rejected"] == 0 and p["counters"]["dropped_steps"] == 0
    assert sum(s["agents_seen_sumo"].values()) >= 5
    log = (out / "logs" / "sumo.log").read_text() + (out / "logs" / "physics-default.log").read_text()
    assert "Traceback" not in log
