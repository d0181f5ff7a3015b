"""Closed-form tests of the look-ahead distance, point and path ahead (no SUMO needed)."""

from __future__ import annotations

import numpy as np
import pytest

from sumo_side.lanes import LaneGraph, Link
from sumo_side.lookahead import (
    MODE_LANES,
    MODE_NONE,
    MODE_STRAIGHT,
    PathPlanner,
    PolylineStore,
    look_ahead_distance,
)


def make_graph(lanes: dict[str, tuple[str, np.ndarray, float]], links: dict[str, list[tuple[str, str]]]):
    """LaneGraph from {lane id: (edge id, shape, sumo length)} and {lane: [(to, via)]}."""
    ids = list(lanes)
    idx = {k: i for i, k in enumerate(ids)}
    return LaneGraph(
        ids=ids,
        edges=[lanes[k][0] for k in ids],
        shapes=[np.asarray(lanes[k][1], float) for k in ids],
        widths=np.full(len(ids), 3.2),
        lengths=np.array([lanes[k][2] for k in ids]),
        allowed=[["passenger"] for _ in ids],
        links=[[Link(idx[t], idx[v] if v else -1) for t, v in links.get(k, [])] for k in ids],
    )


def run_one(planner, lane, pos, speed, route=("e",), ri=0, x=0.0, y=0.0, angle=90.0, mode=MODE_LANES):
    ids = ["a"]
    lane = np.array([lane])
    seq = planner.update_sequences(ids, lane, np.array([mode == MODE_LANES]), lambda _id: (route, ri))
    return planner.compute(seq, lane, np.array([pos], float), np.array([x]), np.array([y]),
                           np.array([angle]), np.array([speed], float), np.array([mode]))


# ----------------------------------------------------------------------------- LAD


@pytest.mark.parametrize(
    "v, expected",
    [
        (0.0, 7.0),  # standing: LAD_min
        (6.99, 7.0),  # below LAD_min
        (7.0, 7.0),  # v == LAD_min: v * k = 7
        (8.5, 8.5),  # between: v * k
        (10.0, 10.0),  # at LAD_max
        (25.0, 10.0),  # above: clamped to LAD_max
    ],
)
def test_lad_paper_defaults(v, expected):
    assert look_ahead_distance(v, 7.0, 10.0, 1.0) == pytest.approx(expected)


def test_lad_compares_speed_with_lad_min_as_the_paper_writes():
    # k = 2: v = 5 m/s is below LAD_min = 7 (the paper's condition), so LAD = 7, not 10.
    assert look_ahead_distance(5.0, 7.0, 10.0, 2.0) == pytest.approx(7.0)
    # v = 8 is not below LAD_min: min(16, 10) = 10.
    assert look_ahead_distance(8.0, 7.0, 10.0, 2.0) == pytest.approx(10.0)
    # vectorised: one array in, one out
    out = look_ahead_distance(np.array([0.0, 8.0, 9.5, 30.0]), 7.0, 10.0, 1.0)
    np.testing.assert_allclose(out, [7.0, 8.0, 9.5, 10.0])


# ----------------------------------------------------------------------------- geometry


def test_straight_lane_point_and_path():
    g = make_graph({"e_0": ("e", [(0, 0), (100, 0)], 100.0)}, {})
    p = PathPlanner(g, 7, 10, 1, path_length=25)
    r = run_one(p, 0, pos=20.0, speed=8.5)
    np.testing.assert_allclose(r.la_xy[0], [28.5, 0.0], atol=1e-9)
    path = r.path_xy[r.path_offsets[0] : r.path_offsets[1]]
    np.testing.assert_allclose(path, [[20, 0], [45, 0]], atol=1e-5)


def test_straight_lane_keeps_inner_vertices_of_the_path():
    g = make_graph({"e_0": ("e", [(0, 0), (10, 0), (20, 0), (30, 0), (100, 0)], 100.0)}, {})
    p = PathPlanner(g, 7, 10, 1, path_length=25)
    r = run_one(p, 0, pos=5.0, speed=0.0)
    path = r.path_xy[r.path_offsets[0] : r.path_offsets[1]]
    np.testing.assert_allclose(path, [[5, 0], [10, 0], [20, 0], [30, 0]], atol=1e-5)
    np.testing.assert_allclose(r.la_xy[0], [12.0, 0.0])  # standing: LAD_min = 7


def test_arc_lookahead_matches_closed_form():
    # Quarter circle of radius 20 m centred at (0, 20), starting at the origin heading east.
    R = 20.0
    th = np.linspace(0.0, np.pi / 2, 4001)
    shape = np.column_stack([R * np.sin(th), R - R * np.cos(th)])
    arc_len = R * np.pi / 2
    g = make_graph({"arc_0": ("arc", shape, arc_len)}, {})
    p = PathPlanner(g, 7, 10, 1, path_length=25)
    for s0, v in [(0.0, 0.0), (5.0, 9.0), (12.0, 30.0)]:
        r = run_one(p, 0, pos=s0, speed=v)
        lad = look_ahead_distance(v, 7, 10, 1)
        phi = (s0 + lad) / R
        expected = [R * np.sin(phi), R - R * np.cos(phi)]
        np.testing.assert_allclose(r.la_xy[0], expected, atol=2e-4)
        # every path vertex lies on the circle
        path = r.path_xy[r.path_offsets[0] : r.path_offsets[1]].astype(float)
        radius = np.hypot(path[:, 0], path[:, 1] - R)
        np.testing.assert_allclose(radius, R, atol=1e-3)


def test_path_shorter_than_lad_clamps_at_the_end():
    g = make_graph({"e_0": ("e", [(0, 0), (5, 0)], 5.0)}, {})
    p = PathPlanner(g, 7, 10, 1, path_length=25)
    r = run_one(p, 0, pos=3.0, speed=9.0)
    np.testing.assert_allclose(r.la_xy[0], [5.0, 0.0])
    path = r.path_xy[r.path_offsets[0] : r.path_offsets[1]]
    np.testing.assert_allclose(path, [[3, 0], [5, 0]], atol=1e-6)


def test_sumo_lane_length_differs_from_geometry():
    # SUMO length 50 m for a 100 m polyline: lane position 10 is 20 m along the shape.
    g = make_graph({"e_0": ("e", [(0, 0), (100, 0)], 50.0)}, {})
    p = PathPlanner(g, 7, 10, 1, path_length=25)
    r = run_one(p, 0, pos=10.0, speed=0.0)
    np.testing.assert_allclose(r.la_xy[0], [27.0, 0.0])


def two_edges_with_junction():
    lanes = {
        "a_0": ("a", [(0, 0), (50, 0)], 50.0),
        ":j_0_0": (":j_0", [(50, 0), (60, 0)], 10.0),
        "b_0": ("b", [(60, 0), (60, 100)], 100.0),  # junction leaves (60,0) north
        "c_0": ("c", [(60, 0), (160, 0)], 100.0),  # other branch, straight on
        ":j_1_0": (":j_1", [(50, 0), (60, 0)], 10.0),
    }
    links = {
        "a_0": [("c_0", ":j_1_0"), ("b_0", ":j_0_0")],
        ":j_0_0": [("b_0", "")],
        ":j_1_0": [("c_0", "")],
    }
    return make_graph(lanes, links)


def test_path_follows_route_through_internal_lane():
    g = two_edges_with_junction()
    p = PathPlanner(g, 7, 10, 1, path_length=25)
    a, b = g.index["a_0"], g.index["b_0"]
    assert p.walk(a, ("a", "b"), 0) == (a, g.index[":j_0_0"], b)
    assert p.walk(a, ("a", "c"), 0) == (a, g.index[":j_1_0"], g.index["c_0"])
    # 45 m along a_0 at 9 m/s: LAD = 9 m = the last 5 m of a_0 + 4 m into the junction
    r = run_one(p, a, pos=45.0, speed=9.0, route=("a", "b"))
    np.testing.assert_allclose(r.la_xy[0], [54.0, 0.0], atol=1e-9)
    path = r.path_xy[r.path_offsets[0] : r.path_offsets[1]]
    np.testing.assert_allclose(path[0], [45, 0], atol=1e-5)
    np.testing.assert_allclose(path[-1], [60, 10], atol=1e-4)  # 25 m: 5 + 10 + 10 north
    # route to c goes straight on
    p2 = PathPlanner(g, 7, 10, 1, path_length=25)
    r = run_one(p2, a, pos=45.0, speed=30.0, route=("a", "c"))
    np.testing.assert_allclose(r.la_xy[0], [55.0, 0.0], atol=1e-9)


def test_vehicle_inside_the_junction_continues_to_next_route_edge():
    g = two_edges_with_junction()
    p = PathPlanner(g, 7, 10, 1, path_length=25)
    j0 = g.index[":j_0_0"]
    # On the internal lane SUMO keeps the route index of the edge before the junction.
    r = run_one(p, j0, pos=8.0, speed=0.0, route=("a", "b"), ri=0)
    np.testing.assert_allclose(r.la_xy[0], [60.0, 5.0], atol=1e-9)


def test_end_of_route_clamps():
    g = two_edges_with_junction()
    p = PathPlanner(g, 7, 10, 1, path_length=25)
    # route ends on a: no continuation although the lane has links
    r = run_one(p, g.index["a_0"], pos=48.0, speed=9.0, route=("a",))
    np.testing.assert_allclose(r.la_xy[0], [50.0, 0.0])


def test_straight_and_none_modes():
    g = make_graph({"e_0": ("e", [(0, 0), (100, 0)], 100.0)}, {})
    p = PathPlanner(g, 7, 10, 1, path_length=25)
    ids = ["walker", "rider", "noroad"]
    lane = np.array([-1, 0, -1])
    seq = p.update_sequences(ids, lane, np.array([False, False, True]), lambda _: (("e",), 0))
    assert (seq == -1).all()
    r = p.compute(seq, lane, np.zeros(3), np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 3.0]),
                  np.array([90.0, 0.0, 0.0]), np.array([1.0, 5.0, 20.0]),
                  np.array([MODE_STRAIGHT, MODE_NONE, MODE_LANES]))
    np.testing.assert_allclose(r.la_xy, [[8.0, 1.0], [2.0, 2.0], [3.0, 13.0]], atol=1e-9)
    assert list(np.diff(r.path_offsets)) == [2, 0, 2]
    np.testing.assert_allclose(r.path_xy[1], [26.0, 1.0], atol=1e-5)  # 25 m east


def test_sequences_are_cached_and_only_changed_agents_resolved():
    g = two_edges_with_junction()
    p = PathPlanner(g, 7, 10, 1, path_length=25)
    calls = []

    def route(aid):
        calls.append(aid)
        return ("a", "b"), 0

    a = g.index["a_0"]
    ids = ["v1", "v2"]
    lane = np.array([a, a])
    use = np.ones(2, bool)
    s1 = p.update_sequences(ids, lane, use, route)
    assert sorted(calls) == ["v1", "v2"] and s1[0] == s1[1] and p.store.n == 1
    calls.clear()
    s2 = p.update_sequences(ids, lane, use, route)
    assert calls == [] and (s2 == s1).all()
    # v0 departs (ids shift), v1 moves into the junction
    j0 = g.index[":j_0_0"]
    s3 = p.update_sequences(["v0", "v1", "v2"], np.array([a, j0, a]), np.ones(3, bool), route)
    assert sorted(calls) == ["v0", "v1"]
    assert s3[2] == s1[1] and s3[0] == s1[0] and s3[1] != s1[0]


def test_polyline_store_many_sequences_vectorised():
    store = PolylineStore(capacity=4)  # forces growth
    ids = [store.add(np.array([[0, k], [10, k], [10, k + 10]], float)) for k in range(50)]
    seq = np.array(ids)
    pts = store.point_at(seq, np.full(50, 15.0))
    np.testing.assert_allclose(pts[:, 0], 10.0)
    np.testing.assert_allclose(pts[:, 1], np.arange(50) + 5.0)
    # beyond the end: clamped to the last vertex
    pts = store.point_at(seq, np.full(50, 1e3))
    np.testing.assert_allclose(pts[:, 1], np.arange(50) + 10.0)
    counts, xy = store.pieces(seq[:2], np.array([5.0, 0.0]), np.array([12.0, 20.0]))
    assert list(counts) == [3, 3]
    np.testing.assert_allclose(xy, [[5, 0], [10, 0], [10, 2], [0, 1], [10, 1], [10, 11]])


def test_polyline_store_grows_past_its_polyline_capacity_between_queries():
    """The per-polyline arrays grow by doubling (from 1,024): queries between adds see every
    polyline added so far, before and after each growth."""
    store = PolylineStore()
    for k in range(2_100):
        store.add(np.array([[0.0, k], [10.0, k], [10.0, k + 10.0]]))
        if k in (0, 1_023, 1_024, 2_047, 2_048, 2_099):
            seq = np.arange(k + 1)
            pts = store.point_at(seq, np.full(k + 1, 15.0))
            np.testing.assert_allclose(pts[:, 0], 10.0)
            np.testing.assert_allclose(pts[:, 1], np.arange(k + 1) + 5.0)
    assert store.n == 2_100 and len(store.base) == len(store.first) == 2_100
    np.testing.assert_array_equal(store.first, np.arange(2_100) * 3)
    np.testing.assert_array_equal(store.last, np.arange(2_100) * 3 + 2)
    np.testing.assert_allclose(store.length, 20.0)
