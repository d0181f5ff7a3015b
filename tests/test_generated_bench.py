"""``sumoco bench generated`` builds scenarios nobody has seen as a new user would: a network
from netgenerate and randomTrips demand of every SUMO default vClass plus persons, at 0.05 s
steps with the sublane model (real SUMO tools; the runs themselves are the benchmark's)."""

from __future__ import annotations

import re

from pathlib import Path

from sumoco.bench.generated import NETWORKS, REAL_NETWORKS, STEP_S, VCLASS_PERIOD_S, generate
from sumoco.bench.scenarios import default_pack

DEMO_NET = Path(__file__).resolve().parents[1] / "configs" / "scenarios" / "paper" / "paper.net.xml"


def test_a_generated_scenario_has_every_default_vclass_and_persons(tmp_path):
    cfg = generate("lefthand_grid", tmp_path / "g")
    text = cfg.read_text()
    assert f'<step-length value="{STEP_S}"/>' in text and '<lateral-resolution value="0.8"/>' in text
    files = re.search(r'route-files value="([^"]+)"', text).group(1).split(",")
    demand = {f.split(".")[0]: (cfg.parent / f).read_text() for f in files}
    # every default class found edges it may use on this network (sidewalks and bike lanes too)
    assert set(VCLASS_PERIOD_S) <= set(demand), sorted(demand)
    for vclass in VCLASS_PERIOD_S:
        assert f'vClass="{vclass}"' in demand[vclass] and demand[vclass].count("<trip ") >= 3, vclass
    assert demand["persons"].count("<person ") >= 20
    assert 'lefthand="true"' in (cfg.parent / "net.net.xml").read_text()[:5000]
    assert set(NETWORKS) == {"spider", "random", "grid", "lefthand_grid"}


def test_a_network_of_ones_own_gets_the_same_demand_with_other_sumo_settings(tmp_path):
    """``--net FILE``: the bundled demo's network as a user's own; ballistic update, lateral
    resolution 0.4 m and random departure lanes reach the .sumocfg and the trips."""
    cfg = generate("own", tmp_path / "own", net=DEMO_NET, lateral_resolution=0.4, ballistic=True,
                   depart_lane="random")
    text = cfg.read_text()
    assert '<lateral-resolution value="0.4"/>' in text and '<step-method.ballistic value="true"/>' in text
    assert (cfg.parent / "net.net.xml").read_bytes() == DEMO_NET.read_bytes()
    files = re.search(r'route-files value="([^"]+)"', text).group(1).split(",")
    passenger = (cfg.parent / "passenger.trips.xml").read_text()
    assert "passenger.trips.xml" in files and 'departLane="random"' in passenger and passenger.count("<trip ") >= 3


def test_the_real_networks_of_the_generated_rows_are_in_the_pack():
    pack = default_pack()
    for name, (rel, _, _) in REAL_NETWORKS.items():
        assert (pack / rel).is_file(), (name, pack / rel)
