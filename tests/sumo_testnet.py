"""A tiny SUMO scenario for the SUMO-side tests, generated with netgenerate (< 1 s).

3x3 grid, 100 m edges, 2 lanes + sidewalk per direction, crossings, traffic lights.
Traffic: cars on a route with two turns, a car flow, a bus carrying a person from its
departure (``depart="triggered"``), a walking person, a bicycle, and a car whose route has
a gap (A0A1 -> C1C2): SUMO teleports it across 1 s after it stops at the gap.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

from sumo_side.scenarios import find_sumo_binary

ROUTES = """<routes>
  <vType id="car" vClass="passenger" length="4.5" width="1.8"/>
  <vType id="bus" vClass="bus" length="12" width="2.5"/>
  <vType id="bike" vClass="bicycle" length="1.6" width="0.65"/>
  <route id="r0" edges="A0B0 B0B1 B1C1 C1C2"/>
  <route id="rb" edges="A1B1 B1C1"/>
  <route id="rgap" edges="A0A1 C1C2"/>
  <vehicle id="v0" type="car" route="r0" depart="0"/>
  <vehicle id="jumper" type="car" route="rgap" depart="0"/>
  <flow id="f0" type="car" from="A0A1" to="C2C1" begin="0" end="30" period="5"/>
  <person id="p0" depart="0">
    <walk edges="A0B0 B0B1"/>
  </person>
  <vehicle id="bus0" type="bus" route="rb" depart="1"/>
  <person id="p1" depart="triggered">
    <ride from="A1B1" to="B1C1" lines="bus0"/>
  </person>
  <vehicle id="bike0" type="bike" route="r0" depart="1"/>
  <vehicle id="v1" type="car" route="r0" depart="2"/>
</routes>
"""

SUMOCFG = """<configuration>
  <input>
    <net-file value="net.net.xml"/>
    <route-files value="routes.rou.xml"/>
  </input>
  <time>
    <begin value="0"/>
    <step-length value="0.1"/>
  </time>
  <processing>
    <ignore-route-errors value="true"/>
    <time-to-teleport.disconnected value="1"/>
  </processing>
  <report>
    <no-step-log value="true"/>
    <no-warnings value="true"/>
  </report>
</configuration>
"""

#: Vehicle and person ids the scenario has in its first 30 s.
EXPECTED_IDS = {"v0", "v1", "jumper", "bus0", "bike0", "p0", "p1",
                *(f"f0.{i}" for i in range(6))}


def make_testnet(folder: Path) -> Path:
    """Write the scenario into ``folder`` (if not there yet) and return its .sumocfg."""
    folder.mkdir(parents=True, exist_ok=True)
    cfg = folder / "test.sumocfg"
    if cfg.is_file():
        return cfg
    subprocess.run(
        [find_sumo_binary("netgenerate"), "--grid", "--grid.number", "3", "--grid.length", "100",
         "--default.lanenumber", "2", "--tls.guess", "true", "--sidewalks.guess", "true",
         "--crossings.guess", "true", "--seed", "1", "-o", "net.net.xml"],
        cwd=folder, check=True, capture_output=True, timeout=60,
    )
    (folder / "routes.rou.xml").write_text(ROUTES)
    cfg.write_text(SUMOCFG)
    return cfg
