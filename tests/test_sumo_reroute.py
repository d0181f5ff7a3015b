"""Route changes reach the path ahead on the step they happen (real libsumo).

Three ways SUMO changes a vehicle's route while it stays on its lane: TraCI
``changeTarget``, a rerouting device, and a rerouter closing an edge. The check in every
step: each vehicle's lane sequence (look-ahead point and path ahead) equals the one walked
afresh from SUMO's current route and route index; and each scenario must show at least one
reroute that happened without a lane change, or the check would prove nothing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sumo_side.bridge import Bridge
from sumo_side.config import SumoConfig
from sumo_side.lookahead import MODE_LANES
from sumo_side.simulation import SumoSim
from tests.sumo_testnet import make_testnet

RUN_STEPS = 120  # 12 s at 0.1 s

CLOSING_REROUTER = """<additional>
  <rerouter id="close_B1C1" edges="A0B0 B0B1">
    <interval begin="3" end="1000"><closingReroute id="B1C1"/></interval>
  </rerouter>
</additional>
"""


@pytest.fixture(scope="module")
def net(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("reroute")
    cfg = make_testnet(folder)
    (folder / "close.add.xml").write_text(CLOSING_REROUTER)
    return cfg


def _run(cfg: Path, extra: tuple[str, ...] = (), hook=None) -> dict:
    """Step the scenario; returns what the per-step check found."""
    scfg = SumoConfig(sumocfg=cfg, extra_args=extra)
    sim = SumoSim(scfg, seed=1, run_id="t")
    sim.start()
    bridge = Bridge(sim, scfg, "t")
    planner = bridge.planner
    found = {"reroutes": [], "reroutes_on_same_lane": [], "mismatches": [], "checked": 0, "steps": [],
             "planner": planner}
    prev_lane: dict[str, int] = {}
    try:
        for k in range(RUN_STEPS):
            if hook is not None:
                hook(k, sim.api)
            sim.step()
            snap = sim.read()
            look = bridge.look_ahead(snap, with_paths=True)
            found["steps"].append((snap, look))
            for i in np.flatnonzero((snap.mode == MODE_LANES) & (look.seq >= 0)).tolist():
                vid = snap.ids[i]
                route, index = sim.route_of(vid)
                fresh = planner.sequence_for(planner.walk(int(snap.lane[i]), route, index))
                found["checked"] += 1
                if fresh != look.seq[i]:
                    found["mismatches"].append((k, vid))
                if snap.route_changed[i]:
                    found["reroutes"].append((k, vid))
                    if prev_lane.get(vid) == snap.lane[i]:
                        found["reroutes_on_same_lane"].append((k, vid))
            prev_lane = dict(zip(snap.ids, snap.lane.tolist()))
    finally:
        sim.close()
    return found


def test_change_target_rebuilds_the_path_ahead_on_that_step(net):
    changed_at = {}

    def hook(k, api):
        # v0 drives A0B0 -> B0B1 -> B1C1; once on B0B1, send it straight on at B1 instead
        # (no lane change needed, so only the route change can trigger the new path).
        if not changed_at and "v0" in api.vehicle.getIDList() and api.vehicle.getRoadID("v0") == "B0B1":
            api.vehicle.changeTarget("v0", "B1B2")
            changed_at["k"] = k

    found = _run(net, hook=hook)
    assert changed_at, "v0 never reached B0B1"
    assert found["checked"] > 500
    assert found["mismatches"] == []
    k = changed_at["k"]
    assert (k, "v0") in found["reroutes"], found["reroutes"]
    snap, look = found["steps"][k]
    i = snap.ids.index("v0")
    # The path ahead of the step the route changed already goes on into B1B2, not B1C1.
    planner = found["planner"]
    edges = {planner.graph.edges[ln] for ln in planner.lanes_of(int(look.seq[i]))}
    assert "B1B2" in edges and "B1C1" not in edges, edges


def test_rerouting_device_rebuilds_the_path_ahead(net):
    def hook(k, api):
        if k == 20:  # make B1C1 slow: the devices (every 1 s) route around it
            api.edge.setMaxSpeed("B1C1", 0.3)

    found = _run(net, ("--device.rerouting.probability", "1", "--device.rerouting.period", "1",
                       "--device.rerouting.adaptation-steps", "1",
                       "--device.rerouting.adaptation-interval", "1"), hook)
    assert found["reroutes_on_same_lane"], "no vehicle was rerouted by its device while on one lane"
    assert found["checked"] > 500
    assert found["mismatches"] == []


def test_closing_rerouter_rebuilds_the_path_ahead(net):
    found = _run(net, ("--additional-files", str(net.parent / "close.add.xml")))
    assert found["reroutes_on_same_lane"], "the rerouter rerouted nobody already on its edges"
    assert found["checked"] > 500
    assert found["mismatches"] == []
