"""The C fast paths of the contact guard's footprint geometry (physics_side.policies.
_footprintkernel) against their numpy bodies: ``footprint_gap`` and ``gap_floor`` bit for bit
(NaN at the same places, signed zeros kept), ``near_pairs`` the same pairs in the same order,
on random, clustered, touching, coincident and hostile footprints and discs; and the guard's
candidate pairs of a real fleet's step the same either way."""

from __future__ import annotations

import numpy as np
import pytest

from physics_side.policies import contacts, footprints
from physics_side.policies.footprints import (
    FAST_FOOTPRINTS, _footprint_gap_numpy, _gap_floor_numpy, _near_pairs_numpy, footprint_gap, gap_floor, near_pairs,
)

needs_c = pytest.mark.skipif(not FAST_FOOTPRINTS, reason="physics_side.policies._footprintkernel not built "
                                                         "(or SUMOCO_PURE_PHYSICS set)")


def _bits_equal(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    if a.dtype != np.float64:
        return bool(np.array_equal(a, b))
    na, nb = np.isnan(a), np.isnan(b)
    return bool(np.array_equal(na, nb) and np.array_equal(a[~na].view(np.uint64), b[~nb].view(np.uint64)))


def _footprints(rng: np.random.Generator, m: int, hostile: bool) -> list[np.ndarray]:
    """(ax, ay, ah, al, aw, bx, by, bh, bl, bw) of m pairs: overlapping, touching, apart."""
    ax, ay = rng.uniform(-50, 50, m), rng.uniform(-50, 50, m)
    d = rng.choice([0.0, 1.0, 3.0, 10.0], m) * rng.random(m)
    t = rng.uniform(-np.pi, np.pi, m)
    cols = [ax, ay, rng.uniform(-4, 4, m), rng.uniform(0.2, 18, m), rng.uniform(0.3, 2.6, m),
            ax + d * np.cos(t), ay + d * np.sin(t), rng.uniform(-4, 4, m), rng.uniform(0.2, 18, m),
            rng.uniform(0.3, 2.6, m)]
    cols[2][: m // 10] = 0.0
    cols[7][: m // 10] = -0.0
    if hostile:
        for c in cols:
            pick = rng.random(m) < 0.05
            c[pick] = rng.choice([np.nan, np.inf, -np.inf, 0.0, -0.0, 1e300, -1e-300], int(pick.sum()))
    return cols


@needs_c
@pytest.mark.parametrize("hostile", [False, True])
def test_footprint_gap_bit_for_bit(hostile):
    rng = np.random.default_rng(1 + hostile)
    for m in (0, 1, 2, 5, 1000):
        cols = _footprints(rng, m, hostile)
        with np.errstate(all="ignore"):
            assert _bits_equal(footprint_gap(*cols), _footprint_gap_numpy(*cols)), m
    # identical rectangles: the gap is minus their overlap, not 0
    one = [np.array([v]) for v in (0.0, 0.0, 0.3, 4.0, 2.0, 0.0, 0.0, 0.3, 4.0, 2.0)]
    assert footprint_gap(*one)[0] < -1.9
    # broadcasting (a scalar against arrays) goes to numpy and agrees
    cols = _footprints(rng, 10, False)
    assert _bits_equal(footprint_gap(1.0, *cols[1:]), _footprint_gap_numpy(1.0, *cols[1:]))


@needs_c
@pytest.mark.parametrize("hostile", [False, True])
def test_gap_floor_bit_for_bit(hostile):
    rng = np.random.default_rng(3 + hostile)
    n = 300
    x, y = rng.uniform(-100, 100, n), rng.uniform(-100, 100, n)
    hl, hd = rng.uniform(0.1, 9, n), rng.uniform(0.2, 10, n)
    if hostile:
        for c in (x, y, hl, hd):
            pick = rng.random(n) < 0.05
            c[pick] = rng.choice([np.nan, np.inf, -np.inf, -0.0], int(pick.sum()))
    i, j = rng.integers(0, n, 2000), rng.integers(0, n, 2000)
    with np.errstate(all="ignore"):
        assert _bits_equal(gap_floor(x, y, i, j, hl, hd), _gap_floor_numpy(x, y, i, j, hl, hd))
        e = np.zeros(0, np.int64)
        assert _bits_equal(gap_floor(x, y, e, e, hl, hd), _gap_floor_numpy(x, y, e, e, hl, hd))
    with pytest.raises(IndexError):  # an index out of range is numpy's error, as before
        gap_floor(x, y, np.array([n]), np.array([0]), hl, hd)


def _discs(rng: np.random.Generator, n: int, kind: str):
    if kind == "clustered":
        c = rng.uniform(-300, 300, (8, 2))
        k = rng.integers(0, 8, n)
        x, y = c[k, 0] + rng.normal(0, 6, n), c[k, 1] + rng.normal(0, 6, n)
    elif kind == "street":  # a north-south street: the sweep's worst case
        x, y = rng.normal(0, 2, n), rng.uniform(-500, 500, n)
    elif kind == "same":  # every disc on the same spot
        x, y = np.full(n, 12.5), np.full(n, -3.0)
    else:
        x, y = rng.uniform(-1000, 1000, n), rng.uniform(-1000, 1000, n)
    r = rng.uniform(0.0, 12.0, n)
    r[: n // 7] = 0.0
    return x, y, r


@needs_c
@pytest.mark.parametrize("kind", ["uniform", "clustered", "street", "same"])
def test_near_pairs_same_pairs_same_order(kind):
    rng = np.random.default_rng(len(kind))
    for n in (0, 1, 2, 3, 40, 1000):
        x, y, r = _discs(rng, n, kind)
        ci, cj = near_pairs(x, y, r)
        pi, pj = _near_pairs_numpy(x, y, r)
        assert _bits_equal(ci, pi) and _bits_equal(cj, pj), (kind, n)
        if n >= 40 and kind != "uniform":
            assert len(ci) > 0  # the case is not empty


@needs_c
def test_near_pairs_hands_hostile_input_to_numpy():
    x, y, r = np.array([0.0, 1.0, np.nan]), np.array([0.0, 0.0, 0.0]), np.array([1.0, 1.0, 1.0])
    with np.errstate(all="ignore"):
        for args in ((x, y, r), (np.array([0.0, 1e300]), np.zeros(2), np.ones(2)),
                     (np.zeros(2), np.zeros(2), np.array([1.0, np.inf]))):
            try:
                want = _near_pairs_numpy(*args)
            except Exception as e:  # numpy's own error on such input stays the error
                with pytest.raises(type(e)):
                    near_pairs(*args)
                continue
            got = near_pairs(*args)
            assert _bits_equal(got[0], want[0]) and _bits_equal(got[1], want[1])


@needs_c
def test_the_guard_of_a_real_fleet_step_agrees(monkeypatch):
    """``contacts._near`` (every candidate pair and gap the guard reads) of a 300-car step of
    circle traffic, the same with the C paths and without."""
    from physics_side.daemon import build_fleet
    from protocol.codec import decode_as, encode
    from protocol.messages import StepMessage
    from sumoco.bench.physics import _settings
    from synthetic.traffic import circle_traffic

    fleet = build_fleet(_settings(300, None))
    cap = {}
    orig = contacts._near

    def spy(s, sx, sy):
        cap["args"] = (s, sx, sy)
        return orig(s, sx, sy)

    monkeypatch.setattr(contacts, "_near", spy)
    for k in range(6):
        fleet.apply_step(decode_as(encode(circle_traffic(300, k, 0.1)), StepMessage))
        for _ in range(5):
            fleet.tick()
    assert "args" in cap
    c = orig(*cap["args"])
    monkeypatch.setattr(footprints, "_kernel", None)
    p = orig(*cap["args"])
    assert len(c[0]) > 0
    for a, b in zip(c, p):
        assert _bits_equal(a, b)


def test_kernel_rejects_what_it_cannot_read():
    if not FAST_FOOTPRINTS:
        pytest.skip("physics_side.policies._footprintkernel not built (or SUMOCO_PURE_PHYSICS set)")
    k = footprints._kernel
    f = np.ones(3)
    with pytest.raises(ValueError, match="length"):
        k.footprint_gap(f, f, f, f, f, f, f, f, f, np.ones(2), np.empty(3))
    with pytest.raises(TypeError, match="float64"):
        k.near_pairs(f.astype(np.float32), f, f)
    assert k.gap_floor(f, f, np.array([0, 5]), np.array([1, 1]), f, f, np.empty(2)) is False
