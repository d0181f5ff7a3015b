"""``sumoco bench generated --json``: scenarios nobody has seen, generated the way a new user
makes one, through ``sumoco demo``.

Four networks from ``netgenerate`` (a spider, a random network, a 3-lane grid, a left-hand
grid; sidewalks and crossings), ``randomTrips.py`` trips of every SUMO default vClass and
persons, 0.05 s steps, the sublane model (lateral resolution 0.8 m). The same demand also runs
on the scenario pack's real networks (when the pack is there), each with other SUMO settings
(``REAL_NETWORKS``: ballistic update, lateral resolution 0.4 m, random or free departure
lanes), and on any network file passed with ``--net``. Each runs for ``duration`` simulated
seconds with the default preset in lockstep; one JSON row per network (the scenario bench's
row: errors, collisions and their split, placements by cause, carries). The seeds are fixed,
so the traffic is the same from run to run.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from sumo_side.scenarios import find_sumo_binary, sumo_home
from sumoco.bench.scenario import demo_config
from sumoco.bench.scenarios import default_pack, run_one

STEP_S = 0.05  # [s]
#: network name -> netgenerate arguments (after the common ones)
NETWORKS: dict[str, tuple[str, ...]] = {
    "spider": ("--spider", "--spider.arm-number", "6", "--spider.circle-number", "3",
               "--spider.space-radius", "60", "--spider.omit-center", "--default.lanenumber", "2"),
    "random": ("--rand", "--rand.iterations", "60", "--default.lanenumber", "2"),
    "grid": ("--grid", "--grid.number", "4", "--grid.length", "150", "--default.lanenumber", "3"),
    "lefthand_grid": ("--grid", "--grid.number", "4", "--grid.length", "100", "--default.lanenumber", "2",
                      "--lefthand", "true"),
}
#: SUMO default vClass -> mean seconds between departures (randomTrips --period)
VCLASS_PERIOD_S: dict[str, float] = {
    "passenger": 2.0, "truck": 6.0, "trailer": 9.0, "motorcycle": 5.0, "coach": 9.0, "delivery": 7.0,
    "bicycle": 4.0, "moped": 8.0, "emergency": 20.0, "taxi": 10.0, "bus": 12.0, "evehicle": 15.0,
}
PERSON_PERIOD_S = 1.5
DEMAND_END_S = 60.0  # [s] trips depart until then
#: the scenario pack's real networks: name -> (file in the pack, seed, SUMO settings of ``generate``)
REAL_NETWORKS: dict[str, tuple[str, int, dict]] = {
    "bologna": ("bologna_acosta/acosta_buslanes.net.xml", 51, {}),
    "hamburg": ("tavf_hamburg/network.net.xml.gz", 52, {"lateral_resolution": 0.4, "ballistic": True,
                                                      "depart_lane": "random"}),
    "doerpfeldstr": ("doerpfeldstr/net.net.xml.gz", 53, {"depart_lane": "free"}),
}

def generate(name: str, folder: Path, seed: int = 11, net: Path | None = None, lateral_resolution: float = 0.8,
             ballistic: bool = False, depart_lane: str = "best") -> Path:
    """Network ``name`` of NETWORKS (or the network file ``net``) with its demand in ``folder``;
    returns its .sumocfg. ``lateral_resolution`` [m] (the sublane model), ``ballistic`` (SUMO's
    ballistic position update instead of Euler) and ``depart_lane`` (randomTrips' departLane)
    are the SUMO settings that differ between the rows."""
    folder.mkdir(parents=True, exist_ok=True)
    if net is None:
        net_file = "net.net.xml"
        subprocess.run([find_sumo_binary("netgenerate"), *NETWORKS[name], "--sidewalks.guess", "true",
                        "--crossings.guess", "true", "--tls.guess", "true", "--seed", str(seed), "-o", net_file],
                       cwd=folder, check=True, capture_output=True, timeout=120)
    else:
        net = Path(net)
        net_file = "net.net.xml.gz" if net.name.endswith(".gz") else "net.net.xml"
        shutil.copyfile(net, folder / net_file)
    tools = sumo_home() / "tools" / "randomTrips.py"
    env = dict(os.environ, SUMO_HOME=str(sumo_home()))
    files = []
    for i, (vclass, period) in enumerate(VCLASS_PERIOD_S.items()):
        out = f"{vclass}.trips.xml"
        r = subprocess.run([sys.executable, str(tools), "-n", net_file, "-o", out, "-e", str(DEMAND_END_S),
                            "-p", str(period), "--seed", str(seed + i), "--prefix", f"{vclass}_",
                            "--vehicle-class", vclass, "--vclass", vclass, "--fringe-factor", "5",
                            "--min-distance", "100",
                            "--trip-attributes", f'departLane="{depart_lane}" departSpeed="max"'],
                           cwd=folder, capture_output=True, text=True, timeout=300, env=env)
        # a class without a usable edge on this network (randomTrips fails or writes no trip) is left out
        if r.returncode == 0 and "<trip " in (folder / out).read_text(errors="replace"):
            files.append(out)
    r = subprocess.run([sys.executable, str(tools), "-n", net_file, "-o", "persons.trips.xml", "-e",
                        str(DEMAND_END_S), "-p", str(PERSON_PERIOD_S), "--seed", str(seed), "--pedestrians",
                        "--prefix", "ped_", "--max-distance", "300"],
                       cwd=folder, capture_output=True, text=True, timeout=300, env=env)
    if r.returncode == 0 and "<person " in (folder / "persons.trips.xml").read_text(errors="replace"):
        files.append("persons.trips.xml")  # (a network without sidewalks may have no walks)
    if not files:
        raise RuntimeError(f"{net or name}: randomTrips found no route for any vClass on this network")
    cfg = folder / f"{name}.sumocfg"
    cfg.write_text(f"""<configuration>
  <input><net-file value="{net_file}"/><route-files value="{','.join(files)}"/></input>
  <time><begin value="0"/><end value="400"/><step-length value="{STEP_S}"/></time>
  <processing><lateral-resolution value="{lateral_resolution}"/><ignore-route-errors value="true"/>
    <step-method.ballistic value="{str(bool(ballistic)).lower()}"/></processing>
  <random_number><seed value="{seed}"/></random_number>
  <report><no-step-log value="true"/></report>
</configuration>
""")
    return cfg


def run_generated_bench(duration: float = 60.0, quick: bool = False, out_root: Path | None = None,
                        pack: Path | None = None, nets: tuple[str, ...] = ()) -> list[dict]:
    """One row per generated network, per real network of the pack (``pack``, default
    ``default_pack()``; left out with a note when it is not there) and per network file in
    ``nets`` (``quick``: 10 s each, the generated networks only)."""
    duration = 10.0 if quick else duration
    root = Path(out_root) if out_root else Path(tempfile.mkdtemp(prefix="sumoco-generated-"))
    cfg = demo_config(root, "generated", ("default",), duration, preset="default")
    todo: list[tuple[str, dict]] = [(name, {}) for name in NETWORKS]
    if not quick:
        pack = Path(pack) if pack else default_pack()
        for name, (rel, seed, settings) in REAL_NETWORKS.items():
            if (pack / rel).is_file():
                todo.append((name, dict(settings, net=pack / rel, seed=seed)))
            else:
                print(f"generated: {pack / rel} not found, row {name!r} left out", file=sys.stderr, flush=True)
    for i, path in enumerate(nets):
        todo.append((f"net{i}_{Path(path).name.split('.')[0]}", {"net": Path(path)}))
    rows = []
    for name, kw in todo:
        sumocfg = generate(name, root / name, **kw)
        row = run_one(cfg, sumocfg, root / name / "run", duration, None)
        row["network"] = name
        print(row, file=sys.stderr, flush=True)  # progress: a run takes a minute or more
        rows.append(row)
    return rows


__all__ = ["NETWORKS", "REAL_NETWORKS", "VCLASS_PERIOD_S", "generate", "run_generated_bench"]
