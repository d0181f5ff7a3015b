"""The C fast path of the carry policy's ``path_tightness`` (physics_side.policies._policykernel)
against its numpy body: both outputs bit for bit (NaN at the same places) on a real fleet's
step, at short and long steps, with and without two-wheelers leaning, and on random and
hostile headings, speeds and limits (NaN, inf, zero reach or grip, standing and reversing)."""

from __future__ import annotations

import numpy as np
import pytest

from physics_side import models
from physics_side.policies import carry
from physics_side.policies.carry import FAST_TIGHTNESS, _tightness_numpy, grip_shares, path_tightness

needs_c = pytest.mark.skipif(not FAST_TIGHTNESS, reason="physics_side.policies._policykernel not built "
                                                        "(or SUMOCO_PURE_PHYSICS set)")


def _bits_equal(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype != np.float64 or b.dtype != np.float64:
        return False
    na, nb = np.isnan(a), np.isnan(b)
    return bool(np.array_equal(na, nb) and np.array_equal(a[~na].view(np.uint64), b[~nb].view(np.uint64)))


class _Path:
    """A ``ref.path`` whose headings on the grid are given (the test's own)."""

    def __init__(self, h: np.ndarray):
        self.h = h

    def at(self, s):
        class P:
            heading = self.h
        assert s.shape == self.h.shape
        return P()


class _Ref:
    def __init__(self, h, speed, step_speed):
        self.path, self.speed, self.step_speed, self.n = _Path(h), speed, step_speed, len(speed)


def _both(ref, interpolating, reach, a_lat, kind, share, brake, roll, monkeypatch):
    with np.errstate(all="ignore"):
        c = path_tightness(ref, interpolating, reach, a_lat, kind, share, brake, roll)
        with monkeypatch.context() as m:
            m.setattr(carry, "_kernel", None)
            p = path_tightness(ref, interpolating, reach, a_lat, kind, share, brake, roll)
    return c, p


def _same(*args, monkeypatch) -> tuple[np.ndarray, np.ndarray]:
    c, p = _both(*args, monkeypatch)
    assert _bits_equal(c[0], p[0]), "tight"
    assert _bits_equal(c[1], p[1]), "sustained"
    return c


G = 15  # grid rows of path_tightness (0 .. 28 m every 2 m)


def _random_case(rng: np.random.Generator, n: int, hostile: bool):
    h = np.cumsum(rng.normal(0.0, rng.choice([0.01, 0.2, 1.5]), (G, n)), axis=0) + rng.uniform(-4, 4, n)
    speed = rng.uniform(-2.0, 35.0, n)
    kind = rng.choice([models.KIND_CAR, models.KIND_BIKE, models.KIND_PED], n)
    reach = rng.uniform(0.05, 0.3, n)
    a_lat = rng.uniform(2.0, 9.0, n)
    mass = rng.choice([80.0, 200.0, 1500.0, 12000.0], n)
    max_rear = np.where(rng.random(n) < 0.2, 0.3, 0.0)
    share, brake = grip_shares(kind, max_rear, mass)
    roll = rng.uniform(-1.4, 1.4, n)
    step_speed = rng.uniform(0.0, 30.0, n)
    if hostile:
        for arr in (h, speed, reach, a_lat, roll, step_speed):
            flat = arr.reshape(-1)
            pick = rng.random(flat.shape) < 0.05
            flat[pick] = rng.choice([np.nan, np.inf, -np.inf, 0.0, -0.0, 1e300], int(pick.sum()))
    return _Ref(h, speed, step_speed), reach, a_lat, kind, share, brake, roll


@needs_c
@pytest.mark.parametrize("hostile", [False, True])
@pytest.mark.parametrize("interpolating", [False, True])
def test_random_paths_speeds_and_limits(interpolating, hostile, monkeypatch):
    rng = np.random.default_rng(11 + hostile + 2 * interpolating)
    for trial in range(20):
        n = int(rng.choice([1, 2, 7, 300]))
        ref, reach, a_lat, kind, share, brake, roll = _random_case(rng, n, hostile)
        _same(ref, interpolating, reach, a_lat, kind, share, brake, roll, monkeypatch=monkeypatch)
        _same(ref, interpolating, reach, a_lat, kind, share, brake, None, monkeypatch=monkeypatch)  # no lean
        # no vehicle checked at a share (pedestrians only): tight alone
        none = np.zeros(n)
        _same(ref, interpolating, reach, a_lat, kind, none, none, roll, monkeypatch=monkeypatch)


@needs_c
def test_the_cases_the_policy_is_for(monkeypatch):
    """A car into a 90 deg corner, a motorcycle leaning left into a right-hand bend, a bus
    on a straight: the C path agrees and the numbers are the policy's (not both zero)."""
    n = 3
    s = np.arange(G) * 2.0
    h = np.zeros((G, n))
    h[:, 0] = np.where(s > 6.0, np.minimum((s - 6.0) / 10.0, 1.0) * np.pi / 2, 0.0)  # the car's corner
    h[:, 1] = -np.minimum(s / 20.0, 1.0) * 0.8  # the motorcycle's bend to the right
    kind = np.array([models.KIND_CAR, models.KIND_BIKE, models.KIND_CAR])
    share, brake = grip_shares(kind, np.array([0.0, 0.0, 0.3]), np.array([1500.0, 200.0, 12000.0]))
    ref = _Ref(h, np.array([14.0, 10.0, 10.0]), np.zeros(n))
    tight, sustained = _same(ref, False, np.full(n, 0.2), np.full(n, 7.0), kind, share, brake,
                             np.array([0.0, -0.5, 0.0]), monkeypatch=monkeypatch)
    assert tight[0] > carry.INFEASIBLE_MARGIN and sustained[0] > 0.0  # the car's corner is carried
    assert tight[1] > 0.0 and tight[2] == 0.0  # the straight asks nothing


def test_numpy_body_is_what_the_dispatcher_runs_without_c(monkeypatch):
    """Without the extension ``path_tightness`` is the numpy body (the C comparison's reference)."""
    rng = np.random.default_rng(4)
    ref, reach, a_lat, kind, share, brake, roll = _random_case(rng, 50, False)
    monkeypatch.setattr(carry, "_kernel", None)
    got = path_tightness(ref, False, reach, a_lat, kind, share, brake, roll)
    grid = np.arange(0.0, 28.0 + 1e-9, 2.0)[:, None]
    want = _tightness_numpy(ref.path.h, grid, 4, np.maximum(ref.speed, 0.0), np.clip(np.maximum(ref.speed, 0.0), 2.0,
                            20.0), False, True, True, reach, a_lat, kind == models.KIND_BIKE, share, brake, roll)
    assert _bits_equal(got[0], want[0]) and _bits_equal(got[1], want[1])


def test_kernel_rejects_what_it_cannot_read():
    if not FAST_TIGHTNESS:
        pytest.skip("physics_side.policies._policykernel not built (or SUMOCO_PURE_PHYSICS set)")
    k = carry._kernel
    n = 4
    f = np.ones(n)
    const = (0.0, 1.0, 1.0, 4, 2, 8.0, 4.0, 9.81, 1.0, 1.2, 1e-9)
    args = [np.zeros((G, n)), np.arange(G, dtype=float), f, f, f, f, f, f, f, np.zeros(n, bool), np.empty(n),
            np.empty(n), const]
    k.tightness(*args)
    bad = list(args)
    bad[2] = np.ones(n - 1)
    with pytest.raises(ValueError, match="v has 3 items"):
        k.tightness(*bad)
    bad = list(args)
    bad[0] = np.zeros((G, n), np.float32)
    with pytest.raises(TypeError, match="float64"):
        k.tightness(*bad)
    bad = list(args)
    bad[12] = (0.0, 1.0, 1.0, 40, 2, 8.0, 4.0, 9.81, 1.0, 1.2, 1e-9)
    with pytest.raises(ValueError, match="window offsets"):
        k.tightness(*bad)
    bad = list(args)
    bad[12] = const[:5]
    with pytest.raises(TypeError, match="constants"):
        k.tightness(*bad)
    bad = list(args)
    bad[10] = np.empty(n)
    bad[10].flags.writeable = False
    with pytest.raises(TypeError, match="writable|C-contiguous"):
        k.tightness(*bad)
