"""Ego vehicle on a real libsumo scenario: poses move it, traffic reacts, drift is
measured, it is held when poses pause and removed after the timeout (fake clock)."""

from __future__ import annotations

import numpy as np
import pytest

from protocol.messages import AgentFlag, EgoPose
from sumo_side.config import SumoConfig
from sumo_side.ego import EgoManager
from sumo_side.simulation import SumoSim
from tests.sumo_testnet import make_testnet

LANE_Y = -1.6  # centre line of A0B0_2 (left lane eastbound) in the test net


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture()
def sim(tmp_path_factory):
    s = SumoSim(SumoConfig(sumocfg=make_testnet(tmp_path_factory.mktemp("egonet"))), seed=3)
    s.start()
    yield s
    s.close()


def step(sim, ego):
    ego.apply()
    sim.step()
    snap = sim.read()
    return snap, ego.after_step(snap.ids, snap.x, snap.y, snap.arrived)


def test_pose_moves_ego_and_traffic_reacts(sim):
    clock = FakeClock()
    ego = EgoManager(sim.api, SumoConfig(ego_hold_s=0.3, ego_timeout_s=30.0), clock)
    # The ego stands on v0's lane (v0 turns left at B0, so it keeps to this lane).
    ego.offer(EgoPose("ego", 60.0, LANE_Y, 90.0, 0.0))
    v0_x = []
    for k in range(150):
        snap, flags = step(sim, ego)
        i = snap.ids.index("ego")
        assert flags[i] & AgentFlag.EGO
        assert bool(flags[i] & AgentFlag.JUMPED) == (k == 0)  # placed: only in its first step
        assert (snap.x[i], snap.y[i]) == pytest.approx((60.0, LANE_Y), abs=1e-6)
        if "v0" in snap.ids:
            j = snap.ids.index("v0")
            v0_x.append((snap.x[j], snap.y[j], snap.speed[j]))
        clock.t += 0.1
        ego.offer(EgoPose("ego", 60.0, LANE_Y, 90.0, 0.0))
    # v0 came up behind the standing ego and stopped there instead of driving through it.
    x, y, v = np.array(v0_x).T
    behind = np.abs(y - LANE_Y) < 0.1
    assert behind.all(), "v0 left its lane"
    assert x.max() < 60.0 - 5.0 + 0.5  # ego length 5 m (DEFAULT_VEHTYPE), min gap kept
    assert v[-1] == pytest.approx(0.0, abs=0.01)
    assert ego.counters["ego_created"] == 1 and ego.counters["ego_errors"] == 0
    assert ego.drift_max_m < 1e-6


def test_ego_follows_moving_poses_counts_drift_and_jumps(sim):
    clock = FakeClock()
    ego = EgoManager(sim.api, SumoConfig(ego_jump_m=5.0), clock)
    x = 20.0
    for k in range(40):
        ego.offer(EgoPose("ego", x, LANE_Y, 90.0, 10.0, vtype="car"))
        snap, flags = step(sim, ego)
        i = snap.ids.index("ego")
        assert (snap.x[i], snap.y[i]) == pytest.approx((x, LANE_Y), abs=1e-6)
        assert snap.speed[i] == pytest.approx(10.0) or k == 0
        assert sim.api.vehicle.getTypeID("ego") == "car"
        assert not flags[i] & AgentFlag.JUMPED or k == 0
        x += 1.0
        clock.t += 0.1
    n_drift = ego.drift_samples
    assert n_drift == 40 and ego.drift_max_m < 1e-6 and ego.counters["ego_drift_events"] == 0
    # a 30 m jump of the pose: flagged JUMPED
    ego.offer(EgoPose("ego", x + 30.0, LANE_Y, 90.0, 10.0))
    snap, flags = step(sim, ego)
    assert flags[snap.ids.index("ego")] & AgentFlag.JUMPED
    # a pose SUMO cannot follow exactly (far off any road with keepRoute=1: mapped back to
    # the route) shows up as drift
    ego.cfg = SumoConfig(ego_keep_route=1)
    ego.offer(EgoPose("ego", x + 31.0, LANE_Y + 40.0, 90.0, 10.0))
    snap, flags = step(sim, ego)
    assert ego.drift_last_m > 10.0 and ego.counters["ego_drift_events"] == 1


def test_ego_held_when_poses_pause_then_removed_and_recreated(sim):
    clock = FakeClock()
    ego = EgoManager(sim.api, SumoConfig(ego_hold_s=0.3, ego_timeout_s=5.0), clock)
    ego.offer(EgoPose("ego", 30.0, LANE_Y, 90.0, 8.0))
    snap, _ = step(sim, ego)
    clock.t += 0.1
    snap, _ = step(sim, ego)  # within ego_hold_s: last pose, last speed
    assert snap.speed[snap.ids.index("ego")] == pytest.approx(8.0)
    clock.t += 1.0
    for _ in range(3):  # paused beyond ego_hold_s: held in place, standing
        snap, flags = step(sim, ego)
        i = snap.ids.index("ego")
        assert snap.speed[i] == pytest.approx(0.0) and snap.x[i] == pytest.approx(30.0)
    clock.t += 5.0  # beyond ego_timeout_s: removed
    snap, _ = step(sim, ego)
    assert "ego" not in snap.ids and "ego" not in sim.api.vehicle.getIDList()
    assert ego.counters["ego_removed"] == 1 and ego.active_ids() == []
    ego.offer(EgoPose("ego", 50.0, LANE_Y, 90.0, 5.0))  # poses resume: re-created
    snap, flags = step(sim, ego)
    i = snap.ids.index("ego")
    assert flags[i] & AgentFlag.EGO and flags[i] & AgentFlag.JUMPED
    assert ego.counters["ego_created"] == 2


def test_bad_ego_vtype_is_counted_not_fatal(sim):
    ego = EgoManager(sim.api, SumoConfig(), FakeClock())
    ego.offer(EgoPose("ego", 30.0, LANE_Y, 90.0, 0.0, vtype="no-such-type"))
    snap, _ = step(sim, ego)
    assert "ego" not in snap.ids and ego.counters["ego_errors"] == 1


def test_egos_capped_per_client_and_in_total(sim):
    clock = FakeClock()
    ego = EgoManager(sim.api, SumoConfig(ego_id="*", ego_max=4, ego_max_per_client=2, ego_timeout_s=5.0), clock)

    slots = {"a.0": 20.0, "a.1": 32.0, "b.0": 44.0, "b.1": 56.0}  # 12 m apart on one lane

    def offer_all(ids):
        taken = []
        for i in ids:
            if not ego.admit(i):  # what the daemon does before offering a pose
                ego.offer(EgoPose(i, slots.get(i, 68.0), LANE_Y, 90.0, 0.0))
                taken.append(i)
        return taken

    # one client, many ids: two of them get in, the rest never reach SUMO
    assert offer_all([f"a.{k}" for k in range(6)]) == ["a.0", "a.1"]
    assert EgoManager.client_of("a.7") == "a" and EgoManager.client_of("solo") == "solo"
    assert "ego_max_per_client" in ego.admit("a.9")
    # another client still gets its egos in; the total cap then holds for everyone
    assert offer_all(["b.0", "b.1", "b.2"]) == ["b.0", "b.1"]
    assert "[sumo] ego_max allows" in ego.admit("c.0") and "[sumo] ego_max allows" in ego.admit("solo")
    assert offer_all(["a.0", "b.1"]) == ["a.0", "b.1"]  # egos already in keep being driven
    snap, flags = step(sim, ego)
    in_sumo = {i for i, f in zip(snap.ids, flags) if f & AgentFlag.EGO}
    assert in_sumo == {"a.0", "a.1", "b.0", "b.1"} == set(sim.api.vehicle.getIDList()) & in_sumo
    assert not {"a.2", "a.9", "b.2", "c.0", "solo"} & set(sim.api.vehicle.getIDList())
    assert ego.counters["ego_created"] == 4
    # a.2-a.5 and a.9 over their client's cap; b.2, c.0 and solo over the total
    assert ego.counters["ego_refused_client"] == 5 and ego.counters["ego_refused"] == 3
    # a removed ego frees its place for its client
    clock.t += 10.0
    ego.offer(EgoPose("b.0", 44.0, LANE_Y, 90.0, 0.0))
    ego.offer(EgoPose("b.1", 56.0, LANE_Y, 90.0, 0.0))
    snap, _ = step(sim, ego)  # a.0 and a.1 time out
    assert {"a.0", "a.1"}.isdisjoint(snap.ids) and ego.counters["ego_removed"] == 2
    assert offer_all(["a.5"]) == ["a.5"]
    snap, _ = step(sim, ego)
    assert "a.5" in snap.ids
