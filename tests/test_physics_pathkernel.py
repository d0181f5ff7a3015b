"""The C fast path of ``PathSet.at`` (physics_side._pathkernel) against its Python body.

Every output bit for bit (the sign of a zero included; NaN at the same places) on recorded
SUMO paths, synthetic traffic and random ragged polylines (repeated vertices, one-segment
paths, sampled curves), at arc lengths before the start, past the end, on the vertices
(and one ulp either side), on the blend boundaries, NaN and infinite, in shapes (n,),
(k, n) and more, contiguous or not.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from physics_side import reference
from physics_side.reference import FAST_PATHS, MIN_SEG_M, PathSet, Reference
from synthetic.traffic import circle_traffic

needs_c = pytest.mark.skipif(not FAST_PATHS, reason="physics_side._pathkernel not built (or SUMOCO_PURE_PHYSICS set)")
FIELDS = ("x", "y", "heading", "curvature")


# --------------------------------------------------------------------------- helpers


def _bits_equal(a: np.ndarray, b: np.ndarray) -> bool:
    """Same shape, NaN at the same places, every other value with the same bits."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype != np.float64 or b.dtype != np.float64:
        return False
    na, nb = np.isnan(a), np.isnan(b)
    return bool(np.array_equal(na, nb) and np.array_equal(a[~na].view(np.uint64), b[~nb].view(np.uint64)))


def _same(ps: PathSet, s) -> None:
    """``at`` (the C path when built) and the Python body agree bit for bit on ``s``."""
    with np.errstate(invalid="ignore", over="ignore"):  # inf * 0 on purpose (the non-finite queries)
        c = ps.at(s)
        p = ps._at_python(np.asarray(s, np.float64))
    for f in FIELDS:
        assert _bits_equal(getattr(c, f), getattr(p, f)), f


def _queries(ps: PathSet, rng: np.random.Generator) -> list[np.ndarray]:
    """Arc lengths that probe every branch: random ones around [0, total], each agent's
    vertices (exactly and one ulp either side), its blend boundaries, the ends, and the
    non-finite values."""
    n = ps.n
    total = ps.total
    qs = [rng.uniform(-10.0, 1.2 * total + 10.0), np.zeros(n), -np.zeros(n), total.copy(),
          np.nextafter(total, np.inf), np.nextafter(total, -np.inf), np.full(n, -1e-300), total + 1e9]
    # every vertex's arc length and the blend boundaries of its segment, one vertex of each agent per row
    counts = np.diff(ps.offsets)
    for r in range(int(counts.max())):
        v = np.minimum(ps.offsets[:-1] + r, ps.offsets[1:] - 1)
        c = ps.cum[v]
        qs += [c, np.nextafter(c, np.inf), np.nextafter(c, -np.inf)]
        j = np.minimum(v, ps.last_seg)
        c0, L, bs, be = ps._seg[4, j], ps._seg[5, j], ps._seg[6, j], ps._seg[7, j]
        qs += [c0 + bs, c0 + L - be, np.nextafter(c0 + bs, -np.inf), np.nextafter(c0 + L - be, np.inf)]
    special = np.array([np.nan, np.inf, -np.inf, -0.0, 0.0, -1e308, 1e308, 5e-324])
    qs.append(np.resize(special, n))
    qs.append(np.resize(special[::-1], n))
    return qs


def _check_everything(ps: PathSet, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    qs = _queries(ps, rng)
    for q in qs:
        _same(ps, q)
    _same(ps, np.stack(qs))  # (k, n) in one call
    _same(ps, np.stack(qs[:6]).reshape(2, 3, ps.n))  # more leading dimensions


def _random_paths(rng: np.random.Generator, n: int, max_vertices: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """n ragged random-walk polylines with every kind of segment: long and short, sampled
    curves, exactly repeated vertices (zero length, floored at MIN_SEG_M), 1-segment paths."""
    counts = rng.integers(2, max_vertices + 1, n)
    counts[rng.random(n) < 0.2] = 2  # one segment
    off = np.concatenate(([0], np.cumsum(counts)))
    parts = []
    for c in counts:
        kind = rng.integers(4)
        if kind == 0:  # a random walk, steps from mm to 100 m
            steps = rng.normal(size=(c - 1, 2)) * 10.0 ** rng.uniform(-3, 2, (c - 1, 1))
        elif kind == 1:  # a sampled arc (SUMO's internal junction lanes)
            th = np.cumsum(np.full(c - 1, rng.uniform(-0.6, 0.6)))
            steps = rng.uniform(0.5, 3.0) * np.c_[np.cos(th), np.sin(th)]
        elif kind == 2:  # straight lane segments with sharp corners
            th = rng.choice([0.0, np.pi / 2, -np.pi / 2, np.pi], c - 1)
            steps = rng.uniform(5.0, 80.0, (c - 1, 1)) * np.c_[np.cos(th), np.sin(th)]
        else:  # a walk around the +-pi seam of the heading
            th = np.pi + rng.normal(0, 0.3, c - 1)
            steps = rng.uniform(0.1, 10.0, (c - 1, 1)) * np.c_[np.cos(th), np.sin(th)]
        steps[rng.random(c - 1) < 0.15] = 0.0  # a repeated vertex
        start = rng.uniform(-3000.0, 3000.0, 2)
        parts.append(np.vstack([start, start + np.cumsum(steps, axis=0)]))
    return off, np.vstack(parts)


# --------------------------------------------------------------------------- equality


@needs_c
def test_recorded_sumo_paths():
    """240 steps' paths of a bicycle in a SUMO grid scenario (tests/data), as 240 agents, both
    as they come (repeated junction points) and deduplicated like a step's paths."""
    d = np.load(Path(__file__).parent / "data" / "bicycle_waiting_beside_a_zigzag_lane.npz")
    off = np.asarray(d["path_offsets"], np.int64)
    xy = np.asarray(d["path_xy"], np.float64)
    keep = np.flatnonzero(np.diff(off) >= 2)
    counts = np.diff(off)[keep]
    src = np.concatenate([np.arange(off[k], off[k + 1]) for k in keep])
    off2 = np.concatenate(([0], np.cumsum(counts)))
    _check_everything(PathSet(off2, xy[src]))
    n = len(off) - 1
    ps = PathSet.concat_fallback(off, xy, np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n))
    _check_everything(ps, seed=1)


@needs_c
@pytest.mark.parametrize("n", [1, 30, 1000])
def test_synthetic_traffic_paths(n):
    msg = circle_traffic(n, 7)
    ps = Reference.from_batch(msg.time, msg.agents).path
    assert ps.n == n
    _check_everything(ps, seed=n)


@needs_c
@pytest.mark.parametrize("seed", range(12))
def test_random_ragged_polylines(seed):
    rng = np.random.default_rng(seed)
    off, xy = _random_paths(rng, int(rng.integers(1, 80)))
    ps = PathSet(off, xy)
    assert (ps.seglen >= MIN_SEG_M).all()
    _check_everything(ps, seed)


@needs_c
def test_synthesised_arcs_and_a_single_segment():
    n = 5
    ps = PathSet.concat_fallback(np.zeros(0), np.zeros((0, 2)), np.arange(n, dtype=float), np.zeros(n),
                                 np.linspace(-3, 3, n), np.array([0.0, 0.1, -0.5, 1e-9, 2.0]))
    _check_everything(ps)
    ps = PathSet(np.array([0, 2]), np.array([[1.0, 2.0], [1.0, 2.0]]))  # one zero-length segment
    _check_everything(ps)
    ps = PathSet(np.array([0, 3]), np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]))  # only repeats
    _check_everything(ps)


@needs_c
def test_shapes_layouts_and_empty():
    rng = np.random.default_rng(3)
    off, xy = _random_paths(rng, 17)
    ps = PathSet(off, xy)
    s = rng.uniform(-5, 100, (4, 17))
    _same(ps, np.asfortranarray(s))  # not C-contiguous
    _same(ps, s[:, ::-1][:, ::-1][::2])  # strided rows
    _same(ps, np.broadcast_to(np.linspace(0, 50, 6)[:, None], (6, 17)))  # zero strides (policies/carry.py)
    _same(ps, s[0].astype(np.float32))  # converted to float64 first
    _same(ps, list(s[1]))
    _same(ps, np.zeros((0, 17)))
    _same(ps, 3.0)  # a scalar: broadcast by the Python body
    p = ps.at(s)
    assert all(getattr(p, f).shape == (4, 17) and getattr(p, f).dtype == np.float64 for f in FIELDS)
    empty = PathSet(np.zeros(1, np.int64), np.zeros((0, 2)))
    for shape in [(0,), (3, 0)]:
        p = empty.at(np.zeros(shape))
        assert all(getattr(p, f).shape == shape for f in FIELDS)


@needs_c
def test_reference_evaluations_go_through_the_kernel(monkeypatch):
    """The control tick's calls (Reference.at / at_and_project / point_at) reach the C path
    and give what the Python body gives (with Reference's own C path off, as where numpy's
    cos / sin are not libm's; tests/test_physics_referencekernel.py tests that one)."""
    monkeypatch.setattr(reference, "FAST_REFERENCE", False)
    monkeypatch.setattr(reference, "FAST_PATHSET", False)
    msg = circle_traffic(40, 3)
    ref = Reference.from_batch(msg.time, msg.agents)
    calls = []
    kernel = reference._kernel

    class Spy:
        @staticmethod
        def at(*args):
            calls.append(args[4].shape)
            return kernel.at(*args)

    monkeypatch.setattr(reference, "_kernel", Spy)
    r, (s, lat, g) = ref.at_and_project(0.1, msg.agents.x + 0.2, msg.agents.y, np.zeros(40))
    assert calls == [(2, 40)]
    monkeypatch.setattr(reference, "_kernel", None)
    ref2 = Reference.from_batch(msg.time, msg.agents)
    r2, (s2, lat2, g2) = ref2.at_and_project(0.1, msg.agents.x + 0.2, msg.agents.y, np.zeros(40))
    for a, b in [(r.x, r2.x), (r.y, r2.y), (r.yaw, r2.yaw), (r.curvature, r2.curvature), (s, s2), (lat, lat2),
                 (g.x, g2.x), (g.heading, g2.heading)]:
        assert _bits_equal(a, b)


# --------------------------------------------------------------------------- errors


@needs_c
def test_kernel_rejects_what_it_cannot_read():
    """Wrong dtypes, shapes, layouts and segment ranges raise a clear error (never a wrong
    answer or a crash)."""
    ps = PathSet(np.array([0, 3, 5]), np.array([[0.0, 0], [1, 0], [2, 1], [5, 5], [6, 6]]))
    k = reference._kernel
    s = np.array([0.5, 0.5])
    out = np.empty((4, 2))
    args = [ps._seg, ps.key, ps._agents_f, ps._agents_i, s, out]
    k.at(*args)
    assert _bits_equal(out[0], ps._at_python(s).x)

    def fails(i, value, exc, match):
        a = list(args)
        a[i] = value
        with pytest.raises(exc, match=match):
            k.at(*a)

    fails(0, ps._seg.astype(np.float32), TypeError, "seg: needs float64")
    fails(0, np.asfortranarray(ps._seg), TypeError, "seg: needs a C-contiguous")
    fails(0, ps._seg[:14], ValueError, r"seg: needs shape \(15, 4\)")
    fails(1, ps.key[:-1], ValueError, r"key: needs shape \(5,\)")
    fails(2, ps._agents_f[:, :1], TypeError, "agents_f: needs a C-contiguous")
    fails(3, ps._agents_i.astype(np.int32), TypeError, "agents_i: needs int64")
    fails(3, np.array([[0, 3], [1, 4]]), ValueError, "outside seg")  # last_seg 4 of 4 segments
    fails(3, np.array([[0, 3], [1, 2]]), ValueError, "outside seg")  # last_seg < first
    fails(4, s.astype(np.int64), TypeError, "s: needs float64")
    fails(4, np.float64(1.0), ValueError, "s: needs 1 to 8 dimensions")
    fails(5, np.empty((4, 3)), ValueError, r"out: needs shape \(4, \*s.shape\)")
    fails(5, np.empty((2, 4)).T, TypeError, "out: needs a writable C-contiguous")
    ro = np.empty((4, 2))
    ro.flags.writeable = False
    fails(5, ro, TypeError, "out: needs a writable")
    fails(5, b"x" * 64, TypeError, "out: needs a writable")
    with pytest.raises(TypeError, match="takes 6 arguments"):
        k.at(*args[:5])


# --------------------------------------------------------------------------- construction

needs_c_build = pytest.mark.skipif(not reference.FAST_PATHSET, reason="physics_side._pathkernel not built, "
                                   "SUMOCO_PURE_PHYSICS set, or numpy's hypot / arctan2 are not libm's")
TABLES = ("cum", "key", "total", "_base", "seglen", "dir", "h", "turn_s", "b_s", "turn_e", "b_e", "_seg", "_agents_f")


def _python_pathset(fn):
    saved = reference.FAST_PATHSET
    reference.FAST_PATHSET = False
    try:
        return fn()
    finally:
        reference.FAST_PATHSET = saved


def _same_build(off, xy) -> PathSet:
    """PathSet(off, xy) in C and in Python: every table bit for bit; and dedup's results."""
    with np.errstate(all="ignore"):  # (the non-finite vertices)
        c = PathSet(off, xy)
        p = _python_pathset(lambda: PathSet(off, xy))
    for name in TABLES:
        assert _bits_equal(np.ascontiguousarray(getattr(c, name)), np.ascontiguousarray(getattr(p, name))), name
    for name in ("first", "last_seg", "_agents_i"):
        assert np.array_equal(getattr(c, name), getattr(p, name)) and getattr(c, name).dtype == np.int64, name
    return c


def _same_dedup(off, xy, tol: float = 0.01) -> None:
    with np.errstate(all="ignore"):
        o1, x1 = PathSet.dedup(off, xy, tol)
        o2, x2 = _python_pathset(lambda: PathSet.dedup(off, xy, tol))
    assert np.array_equal(o1, o2) and o1.dtype == o2.dtype == np.int64
    assert _bits_equal(x1, x2)


@needs_c_build
@pytest.mark.parametrize("seed", range(16))
def test_build_and_dedup_of_random_ragged_polylines(seed):
    """Random paths (sampled curves near the sampling ratio, repeated vertices, one-segment
    paths, vertices within the dedup tolerance), then deduplicated and built again."""
    rng = np.random.default_rng(seed)
    off, xy = _random_paths(rng, int(rng.integers(1, 120)))
    ps = _same_build(off, xy)
    _check_everything(ps, seed)
    near = xy.copy()
    near[1:] += rng.choice([0.0, 0.004, 0.01, -0.01, 0.02], (len(xy) - 1, 1))  # around the tolerance
    _same_dedup(off, xy)
    _same_dedup(off, near)
    _same_dedup(off, near, 0.0)
    _same_dedup(off, xy, 0.0)  # (repeated vertices exactly 0 apart)
    o, x = PathSet.dedup(off, near)
    if np.diff(o).min() >= 2:  # (a dedup may leave a path one vertex)
        _same_build(o, x)


@needs_c_build
def test_build_of_recorded_and_synthetic_paths():
    d = np.load(Path(__file__).parent / "data" / "bicycle_waiting_beside_a_zigzag_lane.npz")
    off = np.asarray(d["path_offsets"], np.int64)
    xy = np.asarray(d["path_xy"], np.float64)
    _same_dedup(off, xy)  # (with empty and one-vertex paths)
    n = len(off) - 1
    ps = PathSet.concat_fallback(off, xy, np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n))
    p2 = _python_pathset(lambda: PathSet.concat_fallback(off, xy, np.zeros(n), np.zeros(n), np.zeros(n),
                                                         np.zeros(n)))
    for name in TABLES:
        assert _bits_equal(np.ascontiguousarray(getattr(ps, name)), np.ascontiguousarray(getattr(p2, name))), name
    for n in (1, 30, 1000):
        a = circle_traffic(n, 7).agents
        _same_build(np.asarray(a.path_offsets, np.int64), np.asarray(a.path_xy, np.float64))


@needs_c_build
def test_build_of_hostile_paths():
    """Sampled ends exactly at the sampling ratio and the fine length, only repeated
    vertices, non-finite and huge vertices, a single one-segment path."""
    # first / last segments exactly SAMPLING_RATIO (1.5) times their neighbour, exactly FINE_SEG_M (4 m) long,
    # one ulp longer; then only repeated vertices
    pts = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 2.0], [3.0, 4.0], [6.0, 4.0],
                    [0.0, 0.0], [4.0, 0.0], [4.0, 3.0], [7.0, 3.0], [7.0, 7.0],
                    [0.0, 0.0], [np.nextafter(4.0, 9.0), 0.0], [np.nextafter(4.0, 9.0), 3.0], [9.0, 9.0],
                    [9.0, 9.0], [9.0, 9.0], [9.0, 9.0]])
    _same_build(np.array([0, 5, 10, 14, 17]), pts)
    exact = np.array([[0.0, 0.0], [0.01, 0.0], [0.01, 0.01], [0.0, 0.0], [0.0, 0.01]])  # 0.01 apart: all stay
    _same_dedup(np.array([0, 3, 5]), exact)
    _same_dedup(np.array([0, 4, 6]), np.insert(exact, 2, exact[1], axis=0))  # one goes, the others stay
    _same_build(np.array([0, 2]), np.array([[1.0, 2.0], [1.0, 2.0]]))
    _same_build(np.array([0, 2]), np.array([[1.0, 2.0], [-3.0, 2.0]]))
    bad = np.array([[0.0, 0.0], [np.nan, 1.0], [2.0, 2.0], [np.inf, 0.0], [1e308, -1e308], [-1e308, 1e308],
                    [0.0, 0.0], [-0.0, -0.0], [5e-324, 0.0]])
    _same_build(np.array([0, 3, 6, 9]), bad)
    _same_dedup(np.array([0, 3, 6, 9]), bad)
    _same_dedup(np.array([0, 0, 3, 3, 6, 9, 9]), bad)  # empty paths between


@needs_c_build
def test_build_and_dedup_leave_what_the_kernel_cannot_read_to_python():
    """Offsets that do not span xy or too few vertices: the Python body runs (and raises as before)."""
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    for off in (np.array([0, 2]), np.array([1, 3])):
        with pytest.raises(ValueError):
            PathSet(off, xy)
    with pytest.raises(ValueError, match="at least 2 vertices"):
        PathSet(np.array([0, 1, 3]), xy)
    k = reference._kernel
    seg, cum, key, turn, af = np.empty((15, 2)), np.empty(3), np.empty(3), np.empty(2), np.empty((2, 1))
    assert k.build(np.array([0, 3]), xy, seg, cum, key, turn, af) is True
    assert k.build(np.array([0, 2]), xy, seg, cum, key, turn, af) is False
    assert k.dedup(np.array([0, 2]), xy, 0.01, np.empty(2, np.int64), np.empty((3, 2))) == -1
    assert k.dedup(np.zeros(0, np.int64), xy, 0.01, np.zeros(0, np.int64), np.empty((3, 2))) == -1  # no paths
    assert k.dedup(np.zeros(1, np.int64), xy[:0], 0.01, np.zeros(1, np.int64), np.empty((0, 2))) == -1
    with pytest.raises(ValueError, match=r"seg: needs shape \(15, 2\)"):
        k.build(np.array([0, 3]), xy, np.empty((15, 1)), cum, key, turn, af)
    _same_dedup(np.array([0, 2, 3]), xy[:, ::-1].copy())
    _same_dedup(np.array([0, 2, 3]), np.asfortranarray(xy))


@needs_c_build
@pytest.mark.parametrize("tol", [0.01, 0.3, 0.0, 1e-200, 1e200, float("nan")])
def test_dedup_decides_near_ties_as_hypot_does(tol):
    """Vertices at distances within a few ulps of the tolerance in every direction (where the
    kernel's squared-distance shortcut hands over to hypot), tiny and huge steps."""
    rng = np.random.default_rng(7)
    k = 4000
    th = rng.uniform(-np.pi, np.pi, k)
    r = (0.01 if np.isnan(tol) or tol == 0.0 else tol) * (1.0 + rng.integers(-8, 9, k) * 2.0 ** -52)
    r[::7] *= 1.0 + rng.normal(0.0, 1e-6, len(r[::7]))
    steps = np.c_[r * np.cos(th), r * np.sin(th)]
    steps[::11] = rng.choice([0.0, 1e-170, 1e170, np.inf], (len(steps[::11]), 1))
    xy = np.cumsum(np.vstack([[0.0, 0.0], steps]), axis=0)
    xy[1::2] = xy[0::2][: len(xy[1::2])] + steps[0::2][: len(xy[1::2])]  # (each step from an exact vertex)
    counts = rng.integers(1, 6, len(xy))
    off = np.concatenate(([0], np.cumsum(counts)))
    off = off[off < len(xy)]
    off = np.append(off, len(xy))
    _same_dedup(off, xy, tol)
