"""The golden vectors describe one consistent world, and UTM-sized positions survive the wire."""

from __future__ import annotations

import math

import numpy as np
import pytest

from protocol import VCLASS_TO_AGENT_CLASS, AgentClass, AgentFlag, decode, encode
from protocol.golden_vectors import GOLDEN_DIR, UTM_SHIFT, valid_messages


def _load(name):
    return decode((GOLDEN_DIR / f"{name}.msgpack").read_bytes())


@pytest.fixture(scope="module")
def world():
    return {name: _load(name) for name in ("step", "step_no_paths", "step_utm", "static", "physics", "ack", "ego")}


def _lane_shape(static, i):
    ln = static.lanes
    return ln.shape_xy[ln.shape_offsets[i]:ln.shape_offsets[i + 1]]


def _project(shape, p):
    """Distance of point p to polyline ``shape`` [m] and the heading there [deg cw from north]."""
    best = (math.inf, 0.0)
    for a, b in zip(shape[:-1], shape[1:]):
        d = b - a
        t = float(np.clip(np.dot(p - a, d) / np.dot(d, d), 0.0, 1.0))
        dist = float(np.hypot(*(a + t * d - p)))
        if dist < best[0]:
            best = (dist, math.degrees(math.atan2(d[0], d[1])) % 360.0)
    return best


def test_steps_refer_to_the_static_data_version(world):
    st = world["static"]
    for name in ("step", "step_no_paths", "step_utm"):
        assert world[name].static_version == st.version > 0, name
    assert world["step_no_paths"].vtypes is None  # the table travels only when it changes


def test_vtypes_of_the_step_are_the_static_rows(world):
    st, step = world["static"], world["step"]
    assert [(v.id, v.vclass) for v in step.vtypes] == [(v.id, v.vclass) for v in st.vtypes]
    a = step.agents
    for i, aid in enumerate(a.ids):
        k = int(a.vtype[i])
        assert k < len(st.vtypes), aid
        assert a.cls[i] == VCLASS_TO_AGENT_CLASS.get(st.vtypes[k].vclass, AgentClass.OTHER), aid
        assert a.length[i] == st.vtype_length[k] and a.width[i] == st.vtype_width[k], aid


def test_agents_on_lanes_lie_on_them_and_head_their_way(world):
    st, a = world["static"], world["step"].agents
    on_lane = [i for i in range(a.n) if a.lane[i] >= 0]
    assert on_lane, "the golden step has agents on lanes"
    for i in on_lane:
        dist, heading = _project(_lane_shape(st, int(a.lane[i])), np.array([a.x[i], a.y[i]]))
        assert dist <= 0.01, a.ids[i]
        assert abs((float(a.angle[i]) - heading + 180.0) % 360.0 - 180.0) < 1.0, a.ids[i]


def test_paths_start_at_the_bumper_and_run_on_lane_vertices(world):
    st, a = world["static"], world["step"].agents
    vertices = {tuple(p) for p in np.round(st.lanes.shape_xy, 6)}
    for i in range(a.n):
        path = a.path(i)
        if a.flags[i] & AgentFlag.INSIDE_VEHICLE:
            assert len(path) == 0, a.ids[i]
            continue
        assert len(path) >= 2, a.ids[i]
        np.testing.assert_allclose(path[0], [a.x[i], a.y[i]], atol=1e-3)
        for p in np.round(path[1:], 6):
            assert tuple(p) in vertices, (a.ids[i], p)


def _along(path, s):
    seg = np.hypot(*np.diff(path, axis=0).T)
    for (p, q), d in zip(zip(path[:-1], path[1:]), seg):
        if s <= d:
            return p + (q - p) * (s / d)
        s -= d
    return path[-1]


def test_look_ahead_points_follow_section_4(world):
    a = world["step"].agents
    lad_min, lad_max, k_lad = 7.0, 10.0, 1.0
    for i in range(a.n):
        la = np.array([a.la_x[i], a.la_y[i]])
        if a.flags[i] & AgentFlag.INSIDE_VEHICLE:
            np.testing.assert_allclose(la, [a.x[i], a.y[i]], atol=1e-3)  # riders: their own position
            continue
        v = float(a.speed[i])
        lad = lad_min if v < lad_min else min(v * k_lad, lad_max)
        np.testing.assert_allclose(la, _along(a.path(i), lad), atol=1e-3, err_msg=a.ids[i])


def test_riders_share_a_vehicle_pose(world):
    a = world["step"].agents
    riders = [i for i in range(a.n) if a.flags[i] & AgentFlag.INSIDE_VEHICLE]
    assert riders
    vehicles = {(a.x[i], a.y[i]) for i in range(a.n) if not a.flags[i] & AgentFlag.INSIDE_VEHICLE}
    for i in riders:
        assert (a.x[i], a.y[i]) in vehicles, a.ids[i]


def test_tls_rows_match_signal_letters(world):
    st, tls = world["static"], world["step"].tls
    assert tls.ids == st.tls_ids
    links = st.tls_links
    for t, tid in enumerate(st.tls_ids):
        idx = sorted(set(links.link[links.tls == t].tolist()))
        assert idx == list(range(len(tls.state[tls.ids.index(tid)]))), tid
    for k in ("from_lane", "to_lane", "via_lane"):
        col = getattr(links, k)
        assert ((col >= -1) & (col < len(st.lanes.ids))).all(), k
    # a link's via lane leaves its from lane's end and reaches its to lane's start
    for r in range(len(links.tls)):
        f, to, via = (int(getattr(links, k)[r]) for k in ("from_lane", "to_lane", "via_lane"))
        if via >= 0:
            np.testing.assert_allclose(_lane_shape(st, via)[0], _lane_shape(st, f)[-1], atol=0.01)
            np.testing.assert_allclose(_lane_shape(st, via)[-1], _lane_shape(st, to)[0], atol=0.01)
    assert tls.program == ["0"]


def test_physics_rows_join_step_rows_by_id(world):
    step, ph = world["step"], world["physics"]
    assert ph.sumo_step == step.step == world["ack"].step
    assert ph.time == pytest.approx(step.time)
    a = step.agents
    for j, pid in enumerate(ph.agents.ids):
        i = a.ids.index(pid)
        assert not a.flags[i] & AgentFlag.INSIDE_VEHICLE
        assert ph.agents.cls[j] == a.cls[i]
        assert math.hypot(ph.agents.x[j] - a.x[i], ph.agents.y[j] - a.y[i]) < 1.0, pid


def test_time_is_after_the_step(world):
    s = world["step"]
    assert s.time == pytest.approx((s.step + 1) * s.step_length)  # begin 0


def test_ego_pose_is_on_a_lane(world):
    st, e = world["static"], world["ego"]
    dist = min(_project(_lane_shape(st, i), np.array([e.x, e.y]))[0] for i in range(len(st.lanes.ids)))
    assert dist < 0.01


def test_static_shapes_are_float64_and_match_their_float32_copy():
    import msgpack

    wire = msgpack.unpackb((GOLDEN_DIR / "static.msgpack").read_bytes(), raw=False)
    shape = wire["lanes"]["shape"]
    xy64 = np.frombuffer(shape["xy64"], "<f8")
    xy32 = np.frombuffer(shape["xy"], "<f4")
    np.testing.assert_array_equal(xy64.astype(np.float32), xy32)


# ------------------------------------------------------------------ UTM-sized positions


def test_utm_golden_vector_decodes_to_1_mm(world):
    """step_utm is step moved by UTM_SHIFT: every position must come back within 1 mm."""
    ref = valid_messages()["step_utm"].agents
    a = world["step_utm"].agents
    assert a.x.min() > 690_000 and a.y.min() > 5_334_000
    for name in ("x", "y", "la_x", "la_y"):
        got = getattr(a, name)
        assert got.dtype == np.float64
        assert np.abs(got - getattr(ref, name)).max() <= 1e-3, name
    assert np.abs(a.path_xy - ref.path_xy).max() <= 1e-3
    # the same world as the local golden step, translated
    local = world["step"].agents
    np.testing.assert_allclose(a.path_xy - UTM_SHIFT, local.path_xy, rtol=0, atol=1e-3)
    np.testing.assert_allclose(a.la_x - UTM_SHIFT[0], local.la_x, rtol=0, atol=1e-3)


def test_utm_round_trip_of_random_traffic_to_1_mm():
    """Paths 100 m long around agents spread over a UTM zone survive encode/decode to 1 mm."""
    from synthetic.traffic import synthetic_step

    rng = np.random.default_rng(7)
    msg = synthetic_step(300, seed=7, path_points=8)
    a = msg.agents
    x = 691_000.0 + rng.uniform(-5_000, 5_000, a.n)
    y = 5_335_000.0 + rng.uniform(-5_000, 5_000, a.n)
    path = np.repeat(np.column_stack([x, y]), 8, axis=0) + rng.uniform(-100, 100, (8 * a.n, 2))
    la = np.column_stack([x, y]) + rng.uniform(-10, 10, (a.n, 2))
    from dataclasses import replace

    msg = replace(msg, agents=replace(a, x=x, y=y, la_x=la[:, 0], la_y=la[:, 1], path_xy=path))
    out = decode(encode(msg)).agents
    assert np.abs(out.path_xy - path).max() <= 1e-3
    assert np.abs(out.la_x - la[:, 0]).max() <= 1e-3 and np.abs(out.la_y - la[:, 1]).max() <= 1e-3
    # float32 absolute (protocol 1.1) could not: 0.5 m spacing at y ~ 5.3e6
    assert np.abs(path.astype(np.float32).astype(np.float64) - path).max() > 0.05


def test_reader_still_decodes_protocol_1_1_steps():
    """A 1.1 step (absolute float32 la_x/la_y and path.xy, vtypes every step) decodes."""
    import msgpack

    wire = msgpack.unpackb(encode(valid_messages()["step"]), raw=False)
    a = wire["agents"]
    x, y = np.frombuffer(a["x"], "<f8"), np.frombuffer(a["y"], "<f8")
    a["la_x"] = (x + np.frombuffer(a.pop("la_dx"), "<f4")).astype("<f4").tobytes()
    a["la_y"] = (y + np.frombuffer(a.pop("la_dy"), "<f4")).astype("<f4").tobytes()
    off = np.frombuffer(a["path"]["off"], "<u4").astype(np.int64)
    rel = np.frombuffer(a["path"].pop("dxy"), "<f4").reshape(-1, 2).astype(np.float64)
    rel += np.repeat(np.column_stack([x, y]), np.diff(off), axis=0)
    a["path"]["xy"] = rel.astype("<f4").tobytes()
    wire["v"] = [1, 1]
    del wire["sv"], wire["tls"]["program"]
    out = decode(msgpack.packb(wire, use_bin_type=True))
    ref = valid_messages()["step"].agents
    np.testing.assert_allclose(out.agents.path_xy, ref.path_xy, atol=1e-4)
    np.testing.assert_allclose(out.agents.la_y, ref.la_y, atol=1e-4)
    assert out.static_version == 0 and out.tls.program is None and len(out.vtypes) == 3


def test_spec_only_client_decodes_golden_vectors_like_the_codec():
    """The SPEC-only example client reads 1.2 steps and static data to the same numbers."""
    import importlib.util

    path = GOLDEN_DIR.parents[1] / "examples" / "python_client" / "client.py"
    spec = importlib.util.spec_from_file_location("spec_only_client", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    client_decode = mod.decode

    for name in ("step", "step_utm"):
        doc = client_decode((GOLDEN_DIR / f"{name}.msgpack").read_bytes())
        ref = _load(name).agents
        a = doc["agents"]
        np.testing.assert_allclose(a["la_x"], ref.la_x, rtol=0, atol=1e-3)
        np.testing.assert_allclose(a["la_y"], ref.la_y, rtol=0, atol=1e-3)
        flat = [p for poly in a["path"] for p in poly]
        np.testing.assert_allclose(np.array(flat), ref.path_xy, rtol=0, atol=1e-3)
    doc = client_decode((GOLDEN_DIR / "static.msgpack").read_bytes())
    st = _load("static")
    flat = [p for poly in doc["lanes"]["shape"] for p in poly]
    np.testing.assert_array_equal(np.array(flat), st.lanes.shape_xy)


def test_position_encoding_bench_compares_both_encodings():
    """The numbers behind SPEC.md 6: offsets are smaller than float64 and just as precise."""
    from sumoco.bench.cli import run_position_encoding_bench

    (row,) = run_position_encoding_bench(sizes=(200,), repeat=2)
    assert row["offsets_bytes_per_agent"] < 0.7 * row["f64_bytes_per_agent"]
    assert row["offsets_max_error_mm"] <= 1.0 and row["path_points_per_agent"] == 12
