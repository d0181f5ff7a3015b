"""SUMO side on a real libsumo scenario: what we read equals libsumo's own getters,
look-ahead points lie on the lane shapes at the paper's distance, persons walk and ride,
departures/arrivals/teleports are flagged, traffic lights match.

One SUMO run (module fixture) checks every step and records mismatches; the tests then
assert on the record. libsumo allows one simulation per process, so the ego tests live
in their own module.
"""

from __future__ import annotations


import numpy as np
import pytest

from protocol.tables import StaticTracker
from protocol.codec import decode, encode
from protocol.messages import AgentClass, AgentFlag, StaticData, StepMessage
from sumo_side.bridge import Bridge
from sumo_side.config import SumoConfig
from sumo_side.lookahead import look_ahead_distance
from sumo_side.simulation import SumoSim
from tests.sumo_testnet import EXPECTED_IDS, make_testnet

STEPS = 700  # 70 s: every agent departs, the bus ride ends, the jumper teleports


def dist_to_polyline(p: np.ndarray, poly: np.ndarray) -> float:
    a, b = poly[:-1], poly[1:]
    ab = b - a
    L2 = np.maximum((ab * ab).sum(1), 1e-12)
    t = np.clip(((p - a) * ab).sum(1) / L2, 0, 1)
    return float(np.min(np.hypot(*(a + t[:, None] * ab - p).T)))


def arc_length_to(path: np.ndarray, p: np.ndarray) -> float:
    """Distance along ``path`` from its start to the point of ``path`` nearest ``p``."""
    a, b = path[:-1], path[1:]
    ab = b - a
    seg = np.hypot(*ab.T)
    L2 = np.maximum(seg**2, 1e-12)
    t = np.clip(((p - a) * ab).sum(1) / L2, 0, 1)
    d = np.hypot(*(a + t[:, None] * ab - p).T)
    k = int(np.argmin(d))
    return float(seg[:k].sum() + t[k] * seg[k])


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    cfg_path = make_testnet(tmp_path_factory.mktemp("testnet"))
    cfg = SumoConfig(sumocfg=cfg_path)
    sim = SumoSim(cfg, seed=7, run_id="t")
    sim.start()
    api = sim.api
    bridge = Bridge(sim, cfg, "t")
    # All lane segments at once, so "distance to the route's lanes" is one numpy op.
    seg_a = np.concatenate([sh[:-1] for sh in sim.graph.shapes if len(sh) > 1])
    seg_b = np.concatenate([sh[1:] for sh in sim.graph.shapes if len(sh) > 1])
    seg_lane = np.concatenate([np.full(len(sh) - 1, j) for j, sh in enumerate(sim.graph.shapes) if len(sh) > 1])
    seg_edge = np.array(sim.graph.edges)[seg_lane]
    route_masks: dict[tuple, np.ndarray] = {}

    def dist_to_route_lanes(p, route):
        m = route_masks.get(route)
        if m is None:
            m = route_masks[route] = np.isin(seg_edge, list(route)) | np.char.startswith(seg_edge, ":")
        a, b = seg_a[m], seg_b[m]
        ab = b - a
        t = np.clip(((p - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-12), 0, 1)
        return float(np.min(np.hypot(*(a + t[:, None] * ab - p).T)))
    rec = {
        "mismatch": [], "seen": set(), "new_flags": [], "riding_steps": 0, "walking_steps": 0,
        "la_checked": 0, "jumped": [], "arrived": set(), "tls_checked": 0, "paths_full": 0,
        "classes": {},
    }
    mism = rec["mismatch"]
    prev_ids: set[str] = set()
    tracker = StaticTracker()  # the vType table travels only when it changes
    try:
        for k in range(STEPS):
            sim.step()
            snap = sim.read()
            msg = tracker.resolve(bridge.build(k, snap))
            assert msg.vtypes is not None, k
            again = decode(encode(msg))
            assert isinstance(again, StepMessage) and again.agents.ids == msg.agents.ids
            a = msg.agents
            ids = a.ids
            rec["seen"].update(ids)
            rec["arrived"].update(snap.arrived)
            for i, aid in enumerate(ids):
                rec["classes"][aid] = AgentClass(int(a.cls[i]))
                is_new = bool(a.flags[i] & AgentFlag.NEW)
                if is_new != (aid not in prev_ids):
                    mism.append((k, aid, "NEW flag", is_new))
                if i < snap.n_vehicles:
                    dom = api.vehicle
                    if abs(a.accel[i] - dom.getAcceleration(aid)) > 1e-3 and not is_new:
                        mism.append((k, aid, "accel", a.accel[i], dom.getAcceleration(aid)))
                    if a.signals[i] != dom.getSignals(aid):
                        mism.append((k, aid, "signals"))
                    if abs(snap.lane_pos[i] - dom.getLanePosition(aid)) > 1e-9:
                        mism.append((k, aid, "lanepos"))
                else:
                    dom = api.person
                    riding = dom.getVehicle(aid) != ""
                    if riding != bool(a.flags[i] & AgentFlag.INSIDE_VEHICLE):
                        mism.append((k, aid, "riding flag"))
                    if riding:
                        rec["riding_steps"] += 1
                        vx, vy = api.vehicle.getPosition(dom.getVehicle(aid))
                        if np.hypot(a.x[i] - vx, a.y[i] - vy) > 1e-9:
                            mism.append((k, aid, "rider pose != vehicle pose"))
                        if a.path_offsets[i + 1] != a.path_offsets[i] or (a.la_x[i], a.la_y[i]) != pytest.approx((a.x[i], a.y[i]), abs=1e-3):
                            mism.append((k, aid, "rider path/look-ahead"))
                    else:
                        rec["walking_steps"] += 1
                x, y = dom.getPosition(aid)
                if (a.x[i], a.y[i]) != (x, y):
                    mism.append((k, aid, "position", (a.x[i], a.y[i]), (x, y)))
                if abs(a.angle[i] - dom.getAngle(aid)) > 1e-3 or abs(a.speed[i] - dom.getSpeed(aid)) > 1e-4:
                    mism.append((k, aid, "angle/speed"))
                lane_id = dom.getLaneID(aid)
                if (sim.graph.ids[a.lane[i]] if a.lane[i] >= 0 else "") != lane_id:
                    mism.append((k, aid, "lane", a.lane[i], lane_id))
                if msg.vtypes[a.vtype[i]].id != dom.getTypeID(aid):
                    mism.append((k, aid, "vtype"))
                if a.flags[i] & AgentFlag.JUMPED:
                    rec["jumped"].append((k, aid))

                # look-ahead of vehicles on lanes: on the lane shapes, LAD along the path
                if i < snap.n_vehicles and a.lane[i] >= 0 and api.vehicle.getLateralLanePosition(aid) == 0:
                    path = a.path(i).astype(float)
                    la = np.array([a.la_x[i], a.la_y[i]], float)
                    lad = float(look_ahead_distance(a.speed[i], 7.0, 10.0, 1.0))
                    if np.hypot(path[0, 0] - a.x[i], path[0, 1] - a.y[i]) > 0.01:
                        mism.append((k, aid, "path start != front bumper", path[0], (a.x[i], a.y[i])))
                    path_len = float(np.hypot(*np.diff(path, axis=0).T).sum())
                    s_la = arc_length_to(path, la)
                    on_path = min(dist_to_polyline(la, path), 1.0)
                    expected = min(lad, path_len)
                    if on_path > 1e-3 or abs(s_la - expected) > 2e-3:
                        mism.append((k, aid, "look-ahead distance", s_la, expected, on_path))
                    # LAD_max + margin, plus one step's travel (the physics follows it until the next step)
                    full = 25.0 + float(a.speed[i]) * 0.1
                    if path_len > full + 1e-3:
                        mism.append((k, aid, "path too long", path_len))
                    if path_len > full - 1e-3:
                        rec["paths_full"] += 1
                    route = api.vehicle.getRoute(aid)
                    for pt in (path[0], la, path[-1]):
                        d = dist_to_route_lanes(pt, route)
                        if d > 1e-3:
                            mism.append((k, aid, "look-ahead/path point off the route's lanes", d))
                    rec["la_checked"] += 1
            for j, tid in enumerate(msg.tls.ids):
                if msg.tls.state[j] != api.trafficlight.getRedYellowGreenState(tid):
                    mism.append((k, tid, "tls state"))
                if msg.tls.phase[j] != api.trafficlight.getPhase(tid):
                    mism.append((k, tid, "tls phase"))
                if abs(msg.tls.next_switch[j] - (api.trafficlight.getNextSwitch(tid) - api.simulation.getTime())) > 1e-3:
                    mism.append((k, tid, "tls next switch"))
                rec["tls_checked"] += 1
            prev_ids = set(ids)
        rec["sim"] = sim
        rec["static"] = sim.static
        rec["lanes"] = list(api.lane.getIDList())
        rec["shape0"] = (rec["lanes"][0], api.lane.getShape(rec["lanes"][0]))
        rec["bounds"] = api.simulation.getNetBoundary()
        rec["junctions"] = list(api.junction.getIDList())
        rec["counters"] = dict(sim.counters)
        yield rec
    finally:
        sim.close()


def test_agents_equal_libsumo_getters(record):
    assert record["mismatch"] == []
    assert record["seen"] == EXPECTED_IDS


def test_look_ahead_points_on_lane_shapes_at_lad(record):
    assert record["la_checked"] > 1000  # many vehicle-steps were checked...
    assert record["paths_full"] > 500  # ...most with the full LAD_max + margin path


def test_persons_walk_and_ride(record):
    assert record["riding_steps"] > 100  # p1 rides bus0
    assert record["walking_steps"] > 100  # p0 walks
    assert record["classes"]["p0"] == AgentClass.PEDESTRIAN
    assert record["classes"]["bus0"] == AgentClass.BUS
    assert record["classes"]["bike0"] == AgentClass.BICYCLE
    assert record["classes"]["v0"] == AgentClass.PASSENGER


def test_departures_arrivals_teleports(record):
    c = record["counters"]
    assert c["departed"] == 11 and c["persons_departed"] == 2
    assert {"v0", "v1", "bus0", "jumper"} <= record["arrived"]
    assert c["teleports"] == 1
    assert [aid for _, aid in record["jumped"]] == ["jumper"]


def test_traffic_lights_match_libsumo(record):
    assert record["tls_checked"] == 5 * STEPS


def test_static_data(record):
    st: StaticData = record["static"]
    assert st.lanes.ids == record["lanes"]
    assert any(i.startswith(":") for i in st.lanes.ids)  # junction-internal lanes included
    assert any("_w" in i for i in st.lanes.ids) and any("_c" in i for i in st.lanes.ids)  # walking areas, crossings
    lane0, shape0 = record["shape0"]
    i = st.lanes.ids.index(lane0)
    np.testing.assert_allclose(st.lanes.shape_xy[st.lanes.shape_offsets[i] : st.lanes.shape_offsets[i + 1]], shape0, atol=1e-4)
    assert st.junctions.ids == record["junctions"]
    (x0, y0), (x1, y1) = record["bounds"]
    assert st.bounds == pytest.approx((x0, y0, x1, y1))
    assert st.net_offset == (0.0, 0.0) and st.projection == "!"  # netgenerate's <location>
    assert len(st.tls_ids) == 5
    assert {"car", "bus", "bike"} <= {v.id for v in st.vtypes}
    again = decode(encode(st))
    assert again.lanes.ids == st.lanes.ids and again.lanes.allow == st.lanes.allow
