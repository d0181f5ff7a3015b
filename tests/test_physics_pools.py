"""Pools that scale: linear build, up-front sizing, growth prepared in the background (real MuJoCo)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from physics_side import layout as L
from physics_side import models as M
from physics_side.config import parse_expect
from physics_side.world import PhysicsWorld
from protocol.errors import ConfigError
from protocol.messages import AgentClass
from tests.harness import wait_until

CAR = M.default_spec(AgentClass.PASSENGER)
PED = M.default_spec(AgentClass.PEDESTRIAN)


def _car_pool(w: PhysicsWorld) -> int:
    return w.pool_for(M.CLASS_FAMILY[AgentClass.PASSENGER], *M.DEFAULT_SIZE[AgentClass.PASSENGER])


def _cpu_build(slots: int) -> tuple[float, PhysicsWorld]:
    t0 = time.process_time()
    w = PhysicsWorld(0.005, 4, shards=1, threads=1, initial={}, expect={AgentClass.PASSENGER: slots})
    return time.process_time() - t0, w


def test_slot_names_and_strides_follow_the_binary_blocks():
    spec = L.build_world_spec([L.Pool(0, CAR, 5), L.Pool(1, PED, 3)], 0.005)
    m = spec.compile()
    # slot i of a pool is at its parking spot, in order of i
    for i in range(5):
        b = m.body(L.slot_prefix(CAR.name, 5, i) + "agent")
        assert b.id == 1 + 5 * i  # world, then 5 bodies per car slot
        x, y = L.park_position(0, i)
        assert m.body_pos[b.id][0] == pytest.approx(x) and m.body_pos[b.id][1] == pytest.approx(y)
    assert m.nu == 5 * 3 + 3 * 3
    assert m.narena == L.arena_bytes(8)
    with pytest.raises(IndexError):
        L.slot_prefix(CAR.name, 5, 5)


def test_pool_build_grows_linearly_in_slots_and_memory_is_sized():
    small, w_small = _cpu_build(320)
    big, w_big = _cpu_build(1280)
    assert w_big.capacity >= 1600 and w_small.capacity >= 400
    # one attach per slot was quadratic (x16 for x4 slots); one model per SLOTS_PER_SIM is linear
    assert big < 4.0 * small + 0.5, (small, big)
    assert w_big.shards >= 1600 / L.SLOTS_PER_SIM
    assert w_big.model.narena <= L.arena_bytes(L.SLOTS_PER_SIM)


def test_expected_agents_fit_without_a_recompile():
    w = PhysicsWorld(0.005, 4, shards=2, initial={}, expect={AgentClass.PASSENGER: 600, AgentClass.PEDESTRIAN: 40})
    p = _car_pool(w)
    n = 600
    x = np.arange(n) * 30.0
    slots = w.allocate([f"v{i}" for i in range(n)], np.full(n, p), x, np.zeros(n))
    assert len(set(slots.tolist())) == n
    assert w.counters["pool_grows"] == 0 and w.counters["growth_waits"] == 0
    w.close()


def test_a_world_holding_the_agents_it_was_sized_for_does_not_start_growing():
    from physics_side.pools import HEADROOM, LOW_WATER_PARTS

    assert HEADROOM > 1.0 / (1.0 - 1.0 / LOW_WATER_PARTS)
    for n in (150, 165, 600):
        w = PhysicsWorld(0.005, 4, shards=1, threads=1, initial={}, expect={AgentClass.PASSENGER: n})
        p = _car_pool(w)
        w.allocate([f"v{i}" for i in range(n)], np.full(n, p), np.arange(n) * 30.0, np.zeros(n))
        assert not w.growing, n  # no model compiled on a second thread for agents that were expected
        w.close()


def test_initial_slots_beyond_one_simulation_are_spread_not_multiplied():
    # 508 per simulation x 2 shards = 1,016 slots, more than two simulations hold: four of 254
    w = PhysicsWorld(0.005, 4, shards=2, threads=1, initial={AgentClass.PASSENGER: 508})
    assert w.shards == 4 and w.capacity == 1016
    w.close()
    w = PhysicsWorld(0.005, 4, shards=2, threads=1, initial={AgentClass.PASSENGER: 40})
    assert w.shards == 2 and w.capacity == 80  # within SLOTS_PER_SIM: per simulation, as configured
    w.close()


def test_growth_is_compiled_in_the_background_and_keeps_live_agents():
    w = PhysicsWorld(0.005, 4, shards=1, initial={AgentClass.PASSENGER: 40}, pool_chunk=8)
    p = _car_pool(w)
    n = 34  # fewer than a quarter free (6 of 40): a bigger model starts compiling
    ids = [f"v{i}" for i in range(n)]
    s = w.allocate(ids, np.full(n, p), np.arange(n) * 30.0, np.zeros(n))
    w.place(s, np.arange(n) * 30.0, np.zeros(n), np.zeros(n), np.full(n, 5.0))
    assert w.growing
    gen = w.generation
    wait_until(lambda: w.growth_ready, timeout_s=60.0, what="background compile")
    for _ in range(5):  # the world keeps stepping meanwhile
        w.step()
    before = w.observe(w.slot_of(ids))
    more = [f"w{i}" for i in range(10)]  # only 6 free: the grown model is switched in
    s2 = w.allocate(more, np.full(10, p), np.arange(10) * 30.0, np.full(10, 50.0))
    assert w.generation == gen + 1 and w.counters["pool_grows"] == 1 and w.counters["growth_waits"] == 0
    after = w.observe(w.slot_of(ids))
    assert np.array_equal(before.fx, after.fx) and np.array_equal(before.speed, after.speed)
    assert len(set(s2.tolist()) | set(w.slot_of(ids).tolist())) == n + 10
    w.close()


def test_a_reserved_size_is_compiled_in_the_background_and_then_spawns_without_a_compile():
    w = PhysicsWorld(0.005, 4, shards=1, initial={AgentClass.PASSENGER: 8})
    car = _car_pool(w)
    s = w.allocate(["a"], np.array([car]), np.array([0.0]), np.array([0.0]))
    w.place(s, np.array([0.0]), np.array([0.0]), np.array([0.0]), np.array([5.0]))
    gen = w.generation
    # a bus size nobody here drives yet (another shard's agent): a pool, compiled off this thread
    assert w.reserve([("bus", 12.0, 2.5), ("bus", 12.0, 2.5)]) == 1
    assert w.growing and w.generation == gen  # returned without compiling on this thread
    bus = w.pool_for("bus", 12.0, 2.5)
    wait_until(lambda: w.growth_ready, timeout_s=60.0, what="background compile of the reserved pool")
    w.step()
    before = w.observe(w.slot_of(["a"]))
    s2 = w.allocate(["b"], np.array([bus]), np.array([100.0]), np.array([0.0]))
    # switched to the model compiled in the background: no compile and no wait on this thread
    assert w.counters["growth_waits"] == 0 and w.build_s == 0.0
    assert w.generation == gen + 1 and w.tables.pool[s2[0]] == bus
    after = w.observe(w.slot_of(["a"]))
    assert np.array_equal(before.fx, after.fx) and np.array_equal(before.speed, after.speed)
    assert w.reserve([("bus", 12.0, 2.5)]) == 0  # known now
    w.close()


def test_parse_expect():
    assert parse_expect("3000") == {"passenger": 3000}
    assert parse_expect("passenger=100, bus=4") == {"passenger": 100, "bus": 4}
    with pytest.raises(ConfigError, match="unknown agent type 'tram'"):
        parse_expect("tram=3")
    with pytest.raises(ConfigError, match="whole number"):
        parse_expect("bus=many")


def test_close_does_not_wait_for_a_background_compile(monkeypatch):
    """A daemon asked to stop must not wait for a compile (uncancellable, seconds on a busy
    machine): close returns while the compile still runs, on a daemon thread."""
    import threading

    from physics_side import pools as pools_mod

    started, release = threading.Event(), threading.Event()

    def held_compile(*args):
        started.set()
        release.wait(30.0)
        raise RuntimeError("a dropped growth's result is never read")

    w = PhysicsWorld(0.005, 4, shards=1, initial={AgentClass.PASSENGER: 8})
    monkeypatch.setattr(pools_mod, "compile_layout", held_compile)
    assert w.reserve([("bus", 12.0, 2.5)]) == 1 and w.growing
    assert started.wait(10.0)
    worker = next(t for t in threading.enumerate() if t.name == "physics-growth")
    assert worker.daemon
    w.close()  # returns although the compile is held
    assert worker.is_alive() and not w.growing
    release.set()
    worker.join(10.0)


def test_a_script_ending_right_after_a_pool_growth_exits_cleanly():
    """A pool growth compiles in a background thread; one that returned into Python while the
    interpreter finalized crashed the process (a segmentation fault, 6 runs of 6 with a
    growth of 8 slots). Interpreter exit now waits briefly for it."""
    import subprocess
    import sys
    from pathlib import Path

    script = (
        "import numpy as np\n"
        "from physics_side.world import PhysicsWorld\n"
        "from protocol.messages import AgentClass\n"
        "w = PhysicsWorld(0.005, 4, shards=1, initial={AgentClass.PASSENGER: 1}, pool_chunk=8)\n"
        "p = w.pool_for('car', 5.0, 1.8)\n"
        "w.allocate(['c'], np.array([p]), np.zeros(1), np.zeros(1))\n"
        "assert w.growing\n"
    )
    root = Path(__file__).resolve().parents[1]
    for _ in range(3):
        r = subprocess.run([sys.executable, "-c", script], cwd=root, capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, (r.returncode, r.stderr[-500:])


def test_default_pools_stay_small_for_a_small_world():
    """Parked slots sleep but MuJoCo still steps their trees (~4 us per slot per tick), so a world of a few dozen agents must not carry hundreds: with the default
    sizes and growth, 20 cars arriving one by one and 6 pedestrians leave at most twice
    their number in slots (the old defaults, 64 car slots and growth by 32, had 80 + 16)."""
    from dataclasses import replace

    from physics_side.config import PhysicsConfig, PhysicsSettings
    from physics_side.daemon import build_fleet

    w = build_fleet(PhysicsSettings(physics=replace(PhysicsConfig(), shards=1, threads=1))).world
    car, ped = _car_pool(w), w.pool_for(M.CLASS_FAMILY[AgentClass.PEDESTRIAN], *M.DEFAULT_SIZE[AgentClass.PEDESTRIAN])
    for i in range(20):
        s = w.allocate([f"v{i}"], np.array([car]), np.array([30.0 * i]), np.array([0.0]))
        w.place(s, np.array([30.0 * i]), np.array([0.0]), np.array([0.0]), np.array([5.0]))
        w.step()
    w.allocate([f"p{i}" for i in range(6)], np.full(6, ped), np.arange(6) * 30.0, np.full(6, 40.0))
    per_pool = {int(p): int(np.sum(w.tables.pool == p)) for p in (car, ped)}
    assert per_pool[car] <= 2 * 20 and per_pool[ped] <= 2 * 6 + 4, per_pool
    assert w.capacity <= 2 * 26 + 4 * 4, w.capacity  # (the other types' first small pools)
    w.close()
