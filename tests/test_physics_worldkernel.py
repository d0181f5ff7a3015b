"""The C fast path of ``PhysicsWorld.observe`` (physics_side._worldkernel) against its numpy
body: every field bit for bit (NaN at the same places, the sign of a zero kept) for every
vehicle family driven by real MuJoCo, and for hostile states written straight into the batch
state (unnormalised, zero, NaN and infinite quaternions, huge velocities, the gimbal poles)."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from physics_side import models as M
from physics_side import world as W
from physics_side.world import FAST_OBSERVE, Observation, PhysicsWorld
from protocol.messages import AgentClass

needs_c = pytest.mark.skipif(not FAST_OBSERVE, reason="physics_side._worldkernel not built (or SUMOCO_PURE_PHYSICS set)")
# every vehicle family at a typical size [m]
FAMILIES = (("car", 5.0, 1.8), ("van", 6.0, 2.1), ("bus", 12.0, 2.5), ("truck", 10.0, 2.5), ("tram", 30.0, 2.6),
            ("motorcycle", 2.2, 0.9), ("bicycle", 1.6, 0.65))
DT = 0.02  # [s] control tick (4 x 0.005 s)


def _bits_equal(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype != np.float64 or b.dtype != np.float64:
        return False
    na, nb = np.isnan(a), np.isnan(b)
    return bool(np.array_equal(na, nb) and np.array_equal(a[~na].view(np.uint64), b[~nb].view(np.uint64)))


def _both(w: PhysicsWorld, slots: np.ndarray, monkeypatch) -> tuple[Observation, Observation]:
    c = w.observe(slots)
    with monkeypatch.context() as m, np.errstate(all="ignore"):
        m.setattr(W, "_kernel", None)
        p = w.observe(slots)
    return c, p


def _same(w: PhysicsWorld, slots: np.ndarray, monkeypatch) -> None:
    c, p = _both(w, slots, monkeypatch)
    for f in fields(Observation):
        assert _bits_equal(getattr(c, f.name), getattr(p, f.name)), f.name


def _fleet(per_class: int = 3, pedestrians: bool = False) -> tuple[PhysicsWorld, np.ndarray]:
    """Every vehicle family (and pedestrians), moving and turning under real MuJoCo."""
    w = PhysicsWorld(0.005, 4, shards=2, initial={AgentClass.PASSENGER: per_class})
    slots = []
    for k, (family, length, width) in enumerate(FAMILIES + ((("pedestrian", 0.215, 0.478),) if pedestrians else ())):
        pool = w.pool_for(family, length, width)
        ids = [f"{family}{i}" for i in range(per_class)]
        x = np.arange(per_class) * 30.0
        y = np.full(per_class, 20.0 * k)
        s = w.allocate(ids, np.full(per_class, pool), x, y)
        w.place(s, x, y, np.full(per_class, 0.3 * k), np.full(per_class, 5.0 + k))
        slots.append(s)
    return w, np.concatenate(slots)


@needs_c
def test_driven_vehicles_of_every_family(monkeypatch):
    w, s = _fleet()
    n = len(s)
    _same(w, s, monkeypatch)
    for k in range(40):
        w.command_vehicles(s, np.full(n, 0.2 * np.sin(0.2 * k)), np.full(n, 800.0), np.zeros(n), np.zeros(n))
        w.step()
        if k % 8 == 0:
            _same(w, s, monkeypatch)
            _same(w, s[::-1].copy(), monkeypatch)  # any order, any subset
            _same(w, s[1::3].copy(), monkeypatch)


@needs_c
def test_vehicles_among_pedestrians(monkeypatch):
    """The mixed path: the vehicles' rows from C, the pedestrians' from numpy, in any order."""
    w, s = _fleet(pedestrians=True)
    n = len(s)
    kind = w.tables.kind[s]
    veh = s[kind != M.KIND_PED]
    ped = s[kind == M.KIND_PED]
    assert len(veh) and len(ped)
    for k in range(30):
        w.command_vehicles(veh, np.full(len(veh), 0.3 * np.sin(0.3 * k)), np.full(len(veh), 900.0),
                           np.zeros(len(veh)), np.zeros(len(veh)))
        w.command_pedestrians(ped, np.full(len(ped), 40.0), np.full(len(ped), -20.0), np.full(len(ped), 1.0))
        w.step()
        if k % 6 == 0:
            _same(w, s, monkeypatch)
            rng = np.random.default_rng(k)
            _same(w, rng.permutation(s), monkeypatch)
            _same(w, ped.copy(), monkeypatch)  # pedestrians only
    assert n == len(veh) + len(ped)


@needs_c
def test_hostile_states(monkeypatch):
    w, s = _fleet(per_class=4)
    plan = w._plan(np.asarray(s, np.int64))
    idx = plan.veh_state
    st = w._state
    rng = np.random.default_rng(3)
    n = len(s)
    special = np.array([0.0, -0.0, 1.0, -1.0, np.nan, np.inf, -np.inf, 1e308, -1e308, 5e-324, 0.5, np.sqrt(0.5)])
    for trial in range(30):
        vals = rng.normal(0.0, 10.0 ** rng.integers(-3, 4), (idx.shape[0], n))
        if trial % 3 == 0:  # special values sprinkled in
            mask = rng.random(vals.shape) < 0.3
            vals[mask] = rng.choice(special, int(mask.sum()))
        if trial % 5 == 1:  # the gimbal poles: 2 (w y - z x) = +-1 exactly
            vals[3:7] = np.array([np.sqrt(0.5), 0.0, np.sqrt(0.5), 0.0])[:, None] * rng.choice([1.0, -1.0], n)
        st[idx] = vals
        _same(w, s, monkeypatch)


@needs_c
def test_an_empty_set_and_the_mixed_path(monkeypatch):
    w, s = _fleet(per_class=1)
    _same(w, np.zeros(0, np.int64), monkeypatch)
    c = w.observe(np.zeros(0, np.int64))
    assert all(len(getattr(c, f.name)) == 0 for f in fields(Observation))


def test_kernel_rejects_what_it_cannot_read():
    if not FAST_OBSERVE:
        pytest.skip("physics_side._worldkernel not built (or SUMOCO_PURE_PHYSICS set)")
    k = W._kernel
    st = np.zeros(100)
    idx = np.zeros((15, 3), np.int64)
    front = np.zeros(3)
    out = np.empty((16, 3))
    k.observe(st, idx, front, out)
    with pytest.raises(IndexError, match="out of range"):
        k.observe(st, np.full((15, 3), 100, np.int64), front, out)
    with pytest.raises(IndexError, match="out of range"):
        k.observe(st, np.full((15, 3), -1, np.int64), front, out)
    with pytest.raises(ValueError, match="expected idx"):
        k.observe(st, np.zeros((14, 3), np.int64), front, out)
    with pytest.raises(ValueError, match="expected idx"):
        k.observe(st, idx, np.zeros(2), out)
    with pytest.raises(TypeError, match="float64"):
        k.observe(st.astype(np.float32), idx, front, out)
    with pytest.raises(TypeError, match="int64"):
        k.observe(st, idx.astype(np.int32), front, out)
    with pytest.raises(TypeError, match="writable|C-contiguous"):
        ro = np.empty((16, 3))
        ro.flags.writeable = False
        k.observe(st, idx, front, ro)
    with pytest.raises(TypeError, match="C-contiguous"):
        k.observe(st, np.zeros((3, 15), np.int64).T, front, out)


def _commanded(w: PhysicsWorld, s: np.ndarray, args: tuple, monkeypatch) -> tuple[np.ndarray, np.ndarray]:
    """Batch state and brake frictionloss after ``command_vehicles(s, *args)`` from the same start."""
    st0, fl0 = w._state.copy(), w._fl.copy()
    w.command_vehicles(s, *args)
    out = w._state.copy(), w._fl.copy()
    w._state[:], w._fl[:] = st0, fl0
    return out


@needs_c
def test_commands_of_every_family(monkeypatch):
    """Steering (Ackermann, rear-axle steering), drive, brakes, traction control and the
    bicycles' stabiliser land in the same state bits either way."""
    w, s = _fleet(per_class=3)
    rng = np.random.default_rng(5)
    n = len(s)
    for trial in range(12):
        steer = rng.uniform(-0.7, 0.7, n)
        if trial % 4 == 3:  # beyond any lock, exactly zero, negative zero
            steer[: 3] = [1.5, 0.0, -0.0]
        drive = rng.uniform(-3000.0, 8000.0, n)
        brake = rng.uniform(0.0, 9000.0, n) * (rng.random(n) < 0.5)
        stab = rng.normal(0.0, 50.0, n) if trial % 2 else None
        rear = rng.uniform(-0.3, 0.3, n) if trial % 3 else None
        speed = rng.uniform(-2.0, 30.0, n) if trial % 2 == 0 else None
        sub = s if trial % 5 else s[::-1].copy()
        k = len(sub)
        args = (steer[:k], drive[:k], brake[:k], None if stab is None else stab[:k], None if rear is None else rear[:k],
                None if speed is None else speed[:k])
        if trial % 6 == 1:  # float32 commands (the numpy body converts them as it writes)
            args = tuple(None if a is None else a.astype(np.float32) for a in args)
        c = _commanded(w, sub, args, monkeypatch)
        with monkeypatch.context() as m:
            m.setattr(W, "_kernel", None)
            p = _commanded(w, sub, args, monkeypatch)
        assert _bits_equal(c[0], p[0]) and _bits_equal(c[1], p[1]), trial
        # and the commands really moved the state (the test is not comparing two no-ops)
        assert not _bits_equal(c[0], w._state)
    # a spinning driven wheel of a heavy vehicle: traction control brakes it
    assert w._plan(np.asarray(s, np.int64)).traction is not None
    assert w._plan(np.asarray(s, np.int64)).rear is not None


def test_command_kernel_rejects_what_it_cannot_read():
    if not FAST_OBSERVE:
        pytest.skip("physics_side._worldkernel not built (or SUMOCO_PURE_PHYSICS set)")
    k = W._kernel
    st, fl = np.zeros(50), np.zeros(20)
    i1 = np.arange(3, dtype=np.int64)
    i4 = np.arange(12, dtype=np.int64).reshape(3, 4)
    f1, f4 = np.ones(3), np.ones((3, 4))
    k.command(st, fl, i1, i1 + 3, i1 + 6, i4, f1, f1, f4, f1, f1, f1)
    assert st[6:9].tolist() == [1.0, 1.0, 1.0] and fl[:12].tolist() == [1.0] * 12
    with pytest.raises(IndexError, match="spin_fl index 20"):
        k.command(st, fl, i1, i1, i1, i4 + 10, f1, f1, f4, f1, f1, f1)
    with pytest.raises(IndexError, match="steer_l index 50"):
        k.command(st, fl, i1 + 48, i1, i1, i4, f1, f1, f4, f1, f1, f1)
    with pytest.raises(ValueError, match="drive has 2 rows"):
        k.command(st, fl, i1, i1, i1, i4, f1, f1, f4, f1, np.ones(2), f1)
    with pytest.raises(TypeError, match="writable|C-contiguous"):
        ro = np.zeros(50)
        ro.flags.writeable = False
        k.command(ro, fl, i1, i1, i1, i4, f1, f1, f4, f1, f1, f1)
