"""Position jumps no motion explains are flagged JUMPED; lane changes are not."""

from __future__ import annotations

import numpy as np

from protocol.messages import AgentFlag
from sumo_side.config import SumoConfig
from sumo_side.simulation import JUMP_MARGIN_M, PERSON_JUMP_MARGIN_M, SumoSim
from tests.harness import PAPER_CFG


def test_person_reaching_its_stop_is_jumped_but_lane_changes_are_not():
    # SUMO's one-step lane change (a sideways hop) is the case the jump margin must not flag
    sim = SumoSim(SumoConfig(sumocfg=PAPER_CFG, lanechange_duration_s=0.0), seed=42)
    sim.start()
    try:
        prev = {}
        rider_jumps, ref_jumps, ref_lane_changes = [], [], 0
        for _ in range(200):  # 20 s: the rider starts waiting at ~10.4 s; ref changes lane twice
            sim.step()
            snap = sim.read()
            for name in ("rider", "ref"):
                if name not in snap.ids:
                    continue
                i = snap.ids.index(name)
                xy = np.array([snap.x[i], snap.y[i]])
                if name in prev:
                    step_m = float(np.hypot(*(xy - prev[name])))
                    jumped = bool(snap.flags[i] & AgentFlag.JUMPED)
                    (rider_jumps if name == "rider" else ref_jumps).append((snap.time, step_m, jumped))
                prev[name] = xy
    finally:
        sim.close()
    big = [(t, d) for t, d, j in rider_jumps if d > JUMP_MARGIN_M + 2.0]
    assert big, "the scenario's rider should move > 7 m in one step when it starts waiting"
    assert all(j for t, d, j in rider_jumps if d > JUMP_MARGIN_M + 2.0)
    assert not any(j for _, _, j in ref_jumps), "ref's lane changes must not count as jumps"
    assert max(d for _, d, _ in ref_jumps) > 1.5  # a lane change happened (lateral hop)


def test_a_walker_sumo_puts_onto_a_crossing_is_jumped_ordinary_walking_is_not():
    """SUMO's pedestrian model moves a person from a walking area onto a crossing about 1 m at
    once (the demo's ped_3 at 20.6 s, at 1.4 m/s in a 0.1 s step): flagged JUMPED, so every
    engine places it instead of sliding it across; walking steps never are."""
    sim = SumoSim(SumoConfig(sumocfg=PAPER_CFG), seed=42)
    sim.start()
    try:
        prev: dict[str, tuple[np.ndarray, float]] = {}
        hops, walks = [], []
        for _ in range(300):  # 30 s
            sim.step()
            snap = sim.read()
            for i, name in enumerate(snap.ids):
                if i < snap.n_vehicles or snap.flags[i] & AgentFlag.INSIDE_VEHICLE:  # (persons follow the vehicles)
                    prev.pop(name, None)
                    continue
                xy, v = np.array([snap.x[i], snap.y[i]]), float(snap.speed[i])
                if name in prev:
                    moved = float(np.hypot(*(xy - prev[name][0])))
                    walk = max(v, prev[name][1]) * 0.1
                    jumped = bool(snap.flags[i] & AgentFlag.JUMPED)
                    if moved > walk + PERSON_JUMP_MARGIN_M:
                        hops.append((name, snap.time, moved, jumped))
                    elif moved <= walk + 0.05:
                        walks.append(jumped)
                prev[name] = (xy, v)
    finally:
        sim.close()
    assert any(n == "ped_3" and abs(t - 20.6) < 0.05 for n, t, _, _ in hops), hops
    assert all(j for _, _, _, j in hops), hops
    assert len(walks) > 1000 and not any(walks)


def test_static_data_maps_every_signal_link_to_its_lanes():
    import libsumo  # noqa: F401  (SumoSim drives it)

    sim = SumoSim(SumoConfig(sumocfg=PAPER_CFG), seed=42)
    sim.start()
    try:
        st = sim.static
        api = sim.api
        tl = st.tls_ids[0]
        n_links = len(api.trafficlight.getRedYellowGreenState(tl))
        links = st.tls_links
        assert sorted(set(links.link[links.tls == 0].tolist())) == list(range(n_links))
        for row in range(len(links.tls)):
            frm, to, via = api.trafficlight.getControlledLinks(tl)[links.link[row]][0]
            assert st.lanes.ids[links.from_lane[row]] == frm
            assert st.lanes.ids[links.to_lane[row]] == to
    finally:
        sim.close()
