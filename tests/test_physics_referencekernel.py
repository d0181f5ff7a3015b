"""The C fast paths of ``Reference.at`` / ``Reference.at_and_project`` and ``Reference.point_at``
(physics_side._pathkernel's ``reference`` and ``point_at``) against their Python bodies.

Every output bit for bit (the sign of a zero included; NaN at the same places) on recorded
SUMO steps, synthetic traffic and random ragged polylines; extrapolated and interpolated
(``interpolate_to``) references, with and without a sideways drift; at times before, at
and past the step's end, NaN and infinite; with guesses before the start, past the end and
non-finite, and positions NaN or infinite.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from physics_side import reference
from physics_side.reference import FAST_REFERENCE, PathPoint, Reference, ReferencePoint
from synthetic.traffic import circle_traffic
from tests.test_physics_pathkernel import _bits_equal, _random_paths

needs_c = pytest.mark.skipif(not FAST_REFERENCE, reason="physics_side._pathkernel not built, SUMOCO_PURE_PHYSICS "
                                                         "set, or numpy's cos / sin are not libm's")
STEP_S = 0.5  # [s] the interpolated references' step length
# [s] times after the sample: 0 of both signs, within the step, on its end and one ulp either side, past it
TAUS = [0.0, -0.0, 1e-12, 0.02, 0.3, STEP_S, float(np.nextafter(STEP_S, 0.0)), float(np.nextafter(STEP_S, 1.0)),
        0.9, 7.5, 1e3, 1e9, -0.25, float("nan"), float("inf"), np.float64(0.06)]


# --------------------------------------------------------------------------- helpers


def _fields(r) -> list[np.ndarray]:
    if isinstance(r, (ReferencePoint, PathPoint)):
        return [getattr(r, f.name) for f in dataclasses.fields(r)]
    return [np.asarray(r)]


def _python(ref: Reference, fn):
    """``fn()`` with the Python bodies (the C path off), the cache cleared before."""
    saved = reference.FAST_REFERENCE
    reference.FAST_REFERENCE = False
    try:
        ref._last_at = None
        return fn()
    finally:
        reference.FAST_REFERENCE = saved


def _same_results(a, b) -> None:
    for x, y in zip(_fields(a), _fields(b), strict=True):
        assert _bits_equal(x, y)


def _same(ref: Reference, tau, px, py, s_guess) -> None:
    """at_and_project and at: the C path (when it takes the inputs) and the Python bodies agree."""
    with np.errstate(all="ignore"):  # inf - inf, 0 * inf on purpose (the non-finite inputs)
        ref._last_at = None
        r, (s, lat, g) = ref.at_and_project(tau, px, py, s_guess)
        r2, (s2, lat2, g2) = _python(ref, lambda: ref.at_and_project(tau, px, py, s_guess))
        ref._last_at = None
        r3 = ref.at(tau)
        r4 = _python(ref, lambda: ref.at(tau))
        p = ref.point_at(s_guess, tau)
        p2 = _python(ref, lambda: ref.point_at(s_guess, tau))
        ref.at(tau)  # the cached reference: at_and_project projects with point_at
        _, cached = ref.at_and_project(tau, px, py, s_guess)
        _, cached2 = _python(ref, lambda: (ref.at(tau), ref.at_and_project(tau, px, py, s_guess))[1])
    for a, b in [(r, r2), (s, s2), (lat, lat2), (g, g2), (r3, r4), (r, r4), (p, p2), *zip(cached, cached2)]:
        _same_results(a, b)


def _guesses(ref: Reference, rng: np.random.Generator) -> list[np.ndarray]:
    """Arc-length guesses: random around the path, on its ends (and one ulp either side),
    before its start and far past its end, and non-finite."""
    n, total = ref.n, ref.path.total
    special = np.array([np.nan, np.inf, -np.inf, -0.0, 0.0, -1e308, 1e308, -1e-300])
    return [rng.uniform(-10.0, 1.2 * total + 10.0), np.zeros(n), -np.zeros(n), total.copy(),
            np.nextafter(total, np.inf), np.nextafter(total, -np.inf), total + 1e9, np.resize(special, n)]


def _positions(ref: Reference, s_guess: np.ndarray, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """Points near the path at the guess (metres off), and some NaN / infinite."""
    with np.errstate(all="ignore"):
        p = _python(ref, lambda: ref.point_at(np.nan_to_num(s_guess, posinf=0.0, neginf=0.0)))
    near = (p.x + rng.normal(0, 2.0, ref.n), p.y + rng.normal(0, 2.0, ref.n))
    bad_x = near[0].copy()
    bad_x[::3] = np.nan
    bad_y = near[1].copy()
    bad_y[1::4] = np.inf
    bad_y[2::5] = -np.inf
    return [near, (bad_x, bad_y)]


def _variants(make, n: int, rng: np.random.Generator) -> list[Reference]:
    """The same step as an extrapolated reference, with a sideways drift, interpolated towards
    a next sample (some agents known), and interpolated then drifting."""
    refs = []
    ref = make()
    refs.append(ref)
    rates = rng.normal(0.0, 1.0, n)
    rates[::5] = 0.0
    rates[1::7] = -0.0
    rates[2::11] = np.nan  # (nan_to_num: 0)
    ref = make()
    ref.set_side_rate(rates)
    refs.append(ref)
    for drift_after in (False, True):
        ref = make()
        known = rng.random(n) < 0.7
        s_end = rng.uniform(-1.0, 15.0, n)
        s_end[::6] = 0.0  # standing
        v_end = rng.uniform(-1.0, 20.0, n)
        a_end = rng.normal(0.0, 3.0, n)
        lat_end = rng.normal(0.0, 1.0, n)
        lat_end[::4] = 0.0
        with np.errstate(all="ignore"):
            ref.interpolate_to(STEP_S, known, s_end, v_end, a_end, lat_end)
        if drift_after:
            ref.set_side_rate(rates)
        refs.append(ref)
    return refs


def _check_everything(make, n: int, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    for ref in _variants(make, n, rng):
        for k, s_guess in enumerate(_guesses(ref, rng)):
            for px, py in _positions(ref, s_guess, rng):
                for tau in TAUS if k < 2 else TAUS[::3]:
                    _same(ref, tau, px, py, s_guess)


def _recorded_step() -> tuple:
    """240 steps of a bicycle in a SUMO grid scenario (tests/data) as one step of 240 agents."""
    d = np.load(Path(__file__).parent / "data" / "bicycle_waiting_beside_a_zigzag_lane.npz")
    off = np.asarray(d["path_offsets"], np.int64)
    return (float(d["t"][0]), *np.asarray(d["cols"], np.float64).T, off - off[0], np.asarray(d["path_xy"], np.float64))


# --------------------------------------------------------------------------- equality


@needs_c
def test_recorded_sumo_steps():
    args = _recorded_step()
    n = len(args[1])
    rng = np.random.default_rng(5)
    yaw_rate = rng.normal(0.0, 0.3, n)
    _check_everything(lambda: Reference(*args), n)
    _check_everything(lambda: Reference(*args, yaw_rate=yaw_rate), n, seed=1)


@needs_c
@pytest.mark.parametrize("n", [1, 30, 1000])
def test_synthetic_traffic(n):
    msg = circle_traffic(n, 7)
    _check_everything(lambda: Reference.from_batch(msg.time, msg.agents), n, seed=n)


@needs_c
@pytest.mark.parametrize("seed", range(8))
def test_random_ragged_polylines(seed):
    """Random paths starting off their sample, with speeds and accelerations that stop within
    the step, stand, or are not finite."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 60))
    off, xy = _random_paths(rng, n)
    x, y = xy[off[:-1], 0] + rng.normal(0, 1.0, n), xy[off[:-1], 1] + rng.normal(0, 1.0, n)
    angle = rng.uniform(-720.0, 720.0, n)
    speed = rng.uniform(-1.0, 30.0, n)
    speed[::7] = 0.0
    accel = rng.normal(0.0, 4.0, n)
    accel[::5] = -9.0
    if n > 3:
        speed[1], accel[2], accel[3] = np.inf, np.nan, -np.inf
    la = rng.normal(0.0, 10.0, n)
    yaw_rate = rng.normal(0.0, 0.5, n)
    _check_everything(lambda: Reference(1.0, x, y, angle, speed, accel, la, la, off, xy, yaw_rate), n, seed)


@needs_c
def test_synthesised_arcs():
    """No paths in the message: every agent follows its synthesised arc."""
    n = 6
    speed = np.array([0.0, 0.3, 5.0, 12.0, 30.0, 8.0])
    rate = np.array([0.0, 1.0, -0.4, 0.05, 1e-9, 2.0])
    args = (0.0, np.arange(n, dtype=float), np.zeros(n), np.linspace(0, 350, n), speed, np.full(n, -2.0),
            np.zeros(n), np.zeros(n), np.zeros(0, np.int64), np.zeros((0, 2)), rate)
    _check_everything(lambda: Reference(*args), n)


# --------------------------------------------------------------------------- dispatch


@needs_c
def test_the_tick_goes_through_the_kernel(monkeypatch):
    """Reference.at and at_and_project reach the C path with the fleet's inputs, and leave
    the cache as the Python body does (a second call at the same tau returns the same point)."""
    msg = circle_traffic(40, 3)
    ref = Reference.from_batch(msg.time, msg.agents)
    calls = []
    kernel = reference._kernel

    class Spy:
        at = kernel.at

        @staticmethod
        def reference(*args):
            calls.append(args[12] is not None)
            return kernel.reference(*args)

        @staticmethod
        def point_at(*args):
            calls.append("point_at")
            return kernel.point_at(*args)

    monkeypatch.setattr(reference, "_kernel", Spy)
    px, py = msg.agents.x + 0.2, np.asarray(msg.agents.y, np.float64)
    r, _ = ref.at_and_project(0.1, px, py, np.zeros(40))
    assert ref.at(0.1) is r
    ref._last_at = None
    ref.at(0.05)
    ref.at_and_project(0.05, px, py, np.zeros(40))  # (cached: projects with point_at)
    ref.point_at(np.ones(40), 0.05)
    assert calls == [True, False, "point_at", "point_at"]


@needs_c
def test_inputs_the_kernel_does_not_take_run_the_python_body():
    """Positions or guesses that are not float64 (n,) C-contiguous arrays, and a tau that is
    no float, run the Python bodies, with their results."""
    msg = circle_traffic(20, 3)
    ref = Reference.from_batch(msg.time, msg.agents)
    px, py, sg = msg.agents.x + 0.2, np.asarray(msg.agents.y, np.float64), np.linspace(0, 5, 20)
    for args in [(0.1, list(px), py, sg), (0.1, px.astype(np.float32), py, sg), (0.1, px, np.tile(py, 2)[::2], sg),
                 (0.1, px, py, list(sg)), (0, px, py, sg), (np.float32(0.1), px, py, sg)]:
        _same(ref, *args)
    empty = Reference(0.0, *[np.zeros(0)] * 7, np.zeros(0, np.int64), np.zeros((0, 2)))
    r, (s, lat, g) = empty.at_and_project(0.1, np.zeros(0), np.zeros(0), np.zeros(0))
    assert r.x.shape == s.shape == g.x.shape == (0,)


@needs_c
def test_kernel_rejects_what_it_cannot_read():
    msg = circle_traffic(4, 3)
    ref = Reference.from_batch(msg.time, msg.agents)
    ps, k = ref.path, reference._kernel
    z = np.zeros(4)
    args = [ps._seg, ps.key, ps._agents_f, ps._agents_i, ref._c_state(), 0, False, 0.1, 0.0, 1.0, 0.0, 0.0, z, z, z,
            np.empty((14, 4))]
    k.reference(*args)

    def fails(i, value, exc, match):
        a = list(args)
        a[i] = value
        with pytest.raises(exc, match=match):
            k.reference(*a)

    fails(4, ref._c_state()[:5], ValueError, r"state: needs shape \(12, 4\)")
    fails(5, 3, ValueError, "mode: needs 0")
    fails(7, "0.1", TypeError, "tau: needs a float")
    fails(12, z[:3], ValueError, r"s_guess: needs shape \(4,\)")
    fails(13, z.astype(np.float32), TypeError, "px: needs float64")
    fails(14, np.zeros(8)[::2], TypeError, "py: needs a C-contiguous")
    fails(15, np.empty((8, 4)), ValueError, r"out: needs shape \(14, 4\)")
    pa = [ps._seg, ps.key, ps._agents_f, ps._agents_i, ref._c_state(), False, 0.1, z, np.empty((4, 4))]
    k.point_at(*pa)
    with pytest.raises(ValueError, match=r"s: needs shape \(4,\)"):
        k.point_at(*pa[:7], z[:3], pa[8])
    with pytest.raises(TypeError, match="takes 9 arguments"):
        k.point_at(*pa[:8])
    fails(3, np.array([[0, 1, 2, 3], [0, 1, 2, 400]]), ValueError, "outside seg")
    a = list(args)
    a[12], a[15] = None, np.empty((8, 4))  # at only
    k.reference(*a)
    with pytest.raises(TypeError, match="takes 16 arguments"):
        k.reference(*args[:15])
