"""Bundled and generated SUMO scenarios, checked by running them in libsumo.

The paper scenario must reproduce the reference manoeuvre of the Sumonity paper's
section 4 (two lane changes, then a right turn at a signalised junction) with all five
agent classes around it; generated grids must actually hold the requested number of
vehicles. libsumo runs one simulation per process, so each test closes its own.
"""

from __future__ import annotations

import os
import re
import sys
import xml.etree.ElementTree as ET
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import libsumo
import pytest

from protocol.errors import ConfigError
from sumo_side.scenarios import (
    PAPER_DIR,
    build_paper_net,
    find_sumo_binary,
    grid_size_for,
    make_grid_scenario,
    paper_sumocfg,
    sumo_home,
)

PAPER_STEPS = 1200  # 120 s at 0.1 s


@dataclass
class PaperRun:
    """What one 120 s run of the paper scenario showed."""

    ref_roads: list[str] = field(default_factory=list)  # distinct consecutive road ids
    ref_lane_by_step: list[tuple[str, int]] = field(default_factory=list)  # (road, lane index)
    ref_distance_at_turn: float | None = None  # [m] driven when entering the turn lane
    ref_arrived: bool = False
    teleported: set[str] = field(default_factory=set)
    vclasses: Counter = field(default_factory=Counter)  # one count per vehicle
    persons: set[str] = field(default_factory=set)
    persons_on_crossings: set[str] = field(default_factory=set)
    persons_in_vehicles: set[str] = field(default_factory=set)
    tls_states_at_turn: str = ""  # signal of ref's link when it entered the turn
    lane_changes: list[dict[str, str]] = field(default_factory=list)  # ref's, from SUMO


def _net_tls_ids() -> set[str]:
    """Traffic lights declared in the paper net (read from the file, no simulation)."""
    root = ET.parse(PAPER_DIR / "paper.net.xml").getroot()
    return {t.get("id") for t in root.iter("tlLogic")}


def _crossing_ids(net_file: Path) -> set[str]:
    root = ET.parse(net_file).getroot()
    return {e.get("id") for e in root.iter("edge") if e.get("function") == "crossing"}


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory) -> PaperRun:
    cfg = paper_sumocfg()
    out = tmp_path_factory.mktemp("paper") / "lanechanges.xml"
    crossings = _crossing_ids(cfg.parent / "paper.net.xml")
    assert crossings, "paper net has no pedestrian crossings"
    run = PaperRun()
    libsumo.start(["sumo", "-c", str(cfg), "--no-step-log", "true",
                   "--lanechange-output", str(out), "--seed", "42"])
    try:
        # ref's right-turn link: its internal (via) lane and signal index at C
        turn_via, turn_index = None, None
        for index, links in enumerate(libsumo.trafficlight.getControlledLinks("C")):
            for from_lane, to_lane, via in links:
                if from_lane == "w_in3_1" and to_lane == "s_out1_1":
                    turn_via, turn_index = via, index
        assert turn_via is not None, "no signalised link w_in3_1 -> s_out1_1 at C"
        seen_vehicles: set[str] = set()
        for _ in range(PAPER_STEPS):
            libsumo.simulationStep()
            run.teleported.update(libsumo.simulation.getStartingTeleportIDList())
            if "ref" in libsumo.simulation.getArrivedIDList():
                run.ref_arrived = True
            for veh in libsumo.simulation.getDepartedIDList():
                if veh not in seen_vehicles:
                    seen_vehicles.add(veh)
                    run.vclasses[libsumo.vehicle.getVehicleClass(veh)] += 1
            for person in libsumo.person.getIDList():
                run.persons.add(person)
                if libsumo.person.getRoadID(person) in crossings:
                    run.persons_on_crossings.add(person)
                if libsumo.person.getVehicle(person):
                    run.persons_in_vehicles.add(person)
            if "ref" in libsumo.vehicle.getIDList():
                road = libsumo.vehicle.getRoadID("ref")
                lane_id = libsumo.vehicle.getLaneID("ref")
                run.ref_lane_by_step.append((road, libsumo.vehicle.getLaneIndex("ref")))
                if not run.ref_roads or run.ref_roads[-1] != road:
                    run.ref_roads.append(road)
                if lane_id == turn_via and run.ref_distance_at_turn is None:
                    run.ref_distance_at_turn = libsumo.vehicle.getDistance("ref")
                    run.tls_states_at_turn = (
                        libsumo.trafficlight.getRedYellowGreenState("C")[turn_index])
    finally:
        libsumo.close()  # also flushes the lane-change output
    run.lane_changes = [c.attrib for c in ET.parse(out).getroot().iter("change")
                        if c.get("id") == "ref"]
    return run


def test_ref_changes_lanes_left_then_right(paper_run):
    changes = paper_run.lane_changes
    assert [(c["from"], c["to"]) for c in changes] == [
        ("w_in1_1", "w_in1_2"),  # left, around the bus lane on w_in2
        ("w_in3_2", "w_in3_1"),  # back right: the right turn leaves from lane 1 only
    ]
    assert [int(c["dir"]) for c in changes] == [1, -1]
    # the lane index seen from outside changes on the same edge, twice
    same_edge_changes = [
        (a, b) for a, b in zip(paper_run.ref_lane_by_step, paper_run.ref_lane_by_step[1:])
        if a[0] == b[0] and not a[0].startswith(":") and a[1] != b[1]
    ]
    assert same_edge_changes == [(("w_in1", 1), ("w_in1", 2)), (("w_in3", 2), ("w_in3", 1))]


def test_ref_turns_right_at_the_traffic_light(paper_run):
    normal_roads = [r for r in paper_run.ref_roads if not r.startswith(":")]
    assert normal_roads == ["w_in1", "w_in2", "w_in3", "s_out1"]
    assert "C" in _net_tls_ids()
    # about 150 m of approach before the turn (the paper turns at ~128 m)
    assert paper_run.ref_distance_at_turn is not None
    assert 120.0 <= paper_run.ref_distance_at_turn <= 170.0
    # ref meets green (it yields to crossing pedestrians: lower-case g)
    assert paper_run.tls_states_at_turn in ("G", "g")
    assert paper_run.ref_arrived and "ref" not in paper_run.teleported


def test_right_turn_link_is_a_right_turn_from_lane_1_only():
    root = ET.parse(PAPER_DIR / "paper.net.xml").getroot()
    to_south = [c for c in root.iter("connection")
                if c.get("from") == "w_in3" and c.get("to") == "s_out1"]
    assert [(c.get("fromLane"), c.get("dir"), c.get("tl")) for c in to_south] == [("1", "r", "C")]


def test_all_five_classes_appear_and_pedestrians_cross(paper_run):
    classes = paper_run.vclasses
    for vclass in ("passenger", "taxi", "bus", "bicycle"):
        assert classes[vclass] >= 1, f"no {vclass} in {dict(classes)}"
    assert len(paper_run.persons) >= 5
    assert len(paper_run.persons_on_crossings) >= 3
    assert "rider" in paper_run.persons_in_vehicles  # rides the bus: "inside vehicle"
    total = sum(classes.values()) + len(paper_run.persons)
    assert 30 <= total <= 80
    assert not paper_run.teleported


def test_committed_paper_net_matches_its_sources(tmp_path):
    """paper.net.xml was regenerated after the last change of its plain-XML sources."""
    rebuilt = build_paper_net(PAPER_DIR, tmp_path / "paper.net.xml")

    def body(path: Path) -> str:  # skip netconvert's header comment (date, output path)
        text = path.read_text()
        return text[text.index("<net "):]

    assert body(rebuilt) == body(PAPER_DIR / "paper.net.xml"), (
        "paper.net.xml is stale: run `python configs/scenarios/build_paper.py`")


def test_grid_scenario_reaches_target_and_is_cached(tmp_path):
    target = 100
    cfg = make_grid_scenario(tmp_path, target, seed=7)
    assert cfg.is_file() and cfg.suffix == ".sumocfg"
    counts = []
    libsumo.start(["sumo", "-c", str(cfg), "--no-step-log", "true"])
    try:
        for step in range(1, 301):  # 30 s
            libsumo.simulationStep()
            if step % 50 == 0:
                counts.append(libsumo.vehicle.getIDCount())
    finally:
        libsumo.close()
    assert counts[-1] >= 0.8 * target, counts
    assert max(counts) <= 1.2 * target, counts
    mtime = cfg.stat().st_mtime_ns
    assert make_grid_scenario(tmp_path, target, seed=7) == cfg
    assert cfg.stat().st_mtime_ns == mtime  # cached: not regenerated
    assert make_grid_scenario(tmp_path, target, seed=8) != cfg


def test_grid_size_grows_with_vehicles():
    assert grid_size_for(100) == 5
    assert grid_size_for(250) == 5
    assert grid_size_for(2500) >= 9


def test_grid_rejects_bad_parameters(tmp_path):
    with pytest.raises(ConfigError, match="vehicles"):
        make_grid_scenario(tmp_path, 0)
    with pytest.raises(ConfigError, match="grid"):
        make_grid_scenario(tmp_path, 10, grid=1)


@pytest.mark.parametrize("name", ["sumo", "sumo-gui", "netconvert", "netgenerate"])
def test_find_sumo_binary(name):
    path = Path(find_sumo_binary(name))
    assert path.name == name and os.access(path, os.X_OK)
    assert (sumo_home() / "tools" / "randomTrips.py").is_file()


def test_missing_binary_names_the_tool():
    with pytest.raises(ConfigError, match="no-such-sumo-tool"):
        find_sumo_binary("no-such-sumo-tool")


def test_missing_sumo_home_is_a_config_error(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "sumo", None)  # `import sumo` raises ImportError
    monkeypatch.setenv("SUMO_HOME", str(tmp_path / "nowhere"))
    with pytest.raises(ConfigError, match="SUMO_HOME"):
        sumo_home()


def test_missing_paper_files_name_the_file(tmp_path):
    with pytest.raises(ConfigError, match=re.escape(str(tmp_path / "paper.sumocfg"))):
        paper_sumocfg(tmp_path)
    with pytest.raises(ConfigError, match="paper.nod.xml"):
        build_paper_net(tmp_path, tmp_path / "x.net.xml")
