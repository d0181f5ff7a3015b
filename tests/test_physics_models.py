"""Closed-form checks of the MuJoCo vehicle models (real MuJoCo, no controllers in the loop
unless stated): acceleration, braking, kinematic-bicycle yaw rate, parked agents, roll-over."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from physics_side import models as M
from physics_side.control import roll_stabiliser
from physics_side.world import PhysicsWorld
from protocol.messages import AgentClass

DT = 0.02  # [s] control tick (4 x 0.005 s)


def _world(cls=AgentClass.PASSENGER, n=2, **kw) -> PhysicsWorld:
    return PhysicsWorld(0.005, 4, shards=1, initial={cls: n}, **kw)


def _one(w: PhysicsWorld, cls=AgentClass.PASSENGER, speed=0.0, aid="a", x=0.0, y=0.0):
    pool = w.pool_for(M.CLASS_FAMILY[cls], *M.DEFAULT_SIZE[cls])
    s = w.allocate([aid], np.array([pool]), np.array([x]), np.array([y]))
    w.place(s, np.array([x]), np.array([y]), np.zeros(1), np.array([speed]))
    return s


def _run(w, s, seconds, steer=0.0, drive=0.0, brake=0.0, every=None):
    out = []
    for k in range(int(round(seconds / DT))):
        w.command_vehicles(s, np.full(len(s), steer), np.full(len(s), drive), np.full(len(s), brake), np.zeros(len(s)))
        w.step()
        if every:
            out.append(every(w.observe(s)))
    return out


def test_straight_line_acceleration_matches_torque_over_effective_mass():
    w = _world()
    s = _one(w)
    spec = M.default_spec(AgentClass.PASSENGER)
    T = 1200.0  # [N*m] well below wheel spin
    x0 = w.observe(s).fx[0]
    _run(w, s, 3.0, drive=T)
    o = w.observe(s)
    a = T / (spec.wheel_radius * spec.effective_mass)  # ~2.7 m/s^2
    assert o.speed[0] == pytest.approx(a * 3.0, rel=0.03)
    assert o.fx[0] - x0 == pytest.approx(0.5 * a * 9.0, rel=0.03)
    assert abs(o.fy[0]) < 0.05 and abs(math.degrees(o.pitch[0])) < 2.0


def test_braking_distance_from_brake_torque_and_friction_limit():
    spec = M.default_spec(AgentClass.PASSENGER)
    v0 = 20.0
    # moderate brake: decel = B / (r m_eff)
    w = _world()
    s = _one(w, speed=v0)
    B = 2500.0
    d = B / (spec.wheel_radius * spec.effective_mass)
    x0 = w.observe(s).fx[0]
    _run(w, s, v0 / d + 1.5, brake=B)
    o = w.observe(s)
    assert abs(o.speed[0]) < 0.05
    assert o.fx[0] - x0 == pytest.approx(v0 * v0 / (2 * d), rel=0.05)
    # full brake: limited by tyre friction: no shorter than v^2 / (2 mu g), no longer than twice that
    w = _world()
    s = _one(w, speed=v0)
    x0 = w.observe(s).fx[0]
    _run(w, s, 6.0, brake=spec.max_brake)
    dist = w.observe(s).fx[0] - x0
    floor = v0 * v0 / (2 * 9.81 * spec.tyre_mu)
    assert floor * 0.98 < dist < floor * 2.0
    assert abs(w.observe(s).speed[0]) < 0.05


@pytest.mark.parametrize("cls", [AgentClass.PASSENGER, AgentClass.BUS, AgentClass.BICYCLE])
def test_yaw_rate_matches_kinematic_bicycle_at_low_lateral_acceleration(cls):
    spec = M.default_spec(cls)
    v = 5.0
    delta = math.atan(spec.wheelbase * 0.6 / v**2)  # ~0.6 m/s^2 lateral
    w = _world(cls)
    s = _one(w, cls, speed=v)
    m_r = spec.wheel_radius * spec.effective_mass
    yaw_rates = []
    for k in range(int(6.0 / DT)):
        o = w.observe(s)
        # hold the speed with a little drive (cornering drag), steer fixed
        drive = max(0.0, (v - o.speed[0]) * 2.0 * m_r)
        stab = roll_stabiliser(o.roll, o.roll_rate, o.speed, o.yaw_rate, 1500.0, 250.0, np.full(1, spec.stab_max))
        w.command_vehicles(s, np.array([delta]), np.array([drive]), np.zeros(1), stab)
        w.step()
        yaw_rates.append(w.observe(s).yaw_rate[0])
    o = w.observe(s)
    expected = o.speed[0] * math.tan(delta) / spec.wheelbase  # kinematic bicycle: v tan(delta) / L
    assert o.speed[0] * expected < 1.0  # low lateral acceleration [m/s^2]
    assert np.mean(yaw_rates[-50:]) == pytest.approx(expected, rel=0.05)


def test_parked_slots_sleep_and_stay_put_and_a_braked_car_holds():
    w = _world(n=4)
    s = _one(w)
    w.park(s)
    before = w.vehicle_pose(s)
    for _ in range(100):
        w.step()
    assert np.allclose(w.vehicle_pose(s), before, atol=1e-6)
    assert w.awake_trees(shard=0) == 0  # every parked slot asleep: no cost
    # a live car standing with its brakes on does not creep
    s = _one(w, aid="b", x=10.0)
    o0 = w.observe(s)
    _run(w, s, 3.0, brake=1500.0)
    o1 = w.observe(s)
    assert math.hypot(o1.fx[0] - o0.fx[0], o1.fy[0] - o0.fy[0]) < 2e-3


def test_pool_growth_keeps_live_agents_exactly():
    w = _world(n=1, pool_chunk=2)
    s = _one(w, speed=8.0)
    _run(w, s, 0.5, drive=300.0)
    o = w.observe(s)
    gen = w.generation
    # a second passenger does not fit: the pool grows with a recompile
    pool = w.pool_for("car", 5.0, 1.8)
    w.allocate(["b"], np.array([pool]), np.array([100.0]), np.array([0.0]))
    assert w.generation == gen + 1 and w.counters["pool_grows"] == 1
    s2 = w.slot_of(["a"])
    o2 = w.observe(s2)
    for f in ("fx", "fy", "yaw", "speed", "yaw_rate", "z"):
        assert getattr(o2, f)[0] == pytest.approx(getattr(o, f)[0], abs=1e-9), f
    _run(w, s2, 0.5, drive=300.0)
    assert w.observe(s2).speed[0] > o.speed[0]  # still driving


def test_agents_in_contact_are_counted_once_per_contact():
    w = _world(n=2)
    pool = w.pool_for("car", 5.0, 1.8)
    s = w.allocate(["a", "b"], np.array([pool, pool]), np.array([0.0, 30.0]), np.array([0.0, 0.0]))
    # b stands 20 m ahead of a; a drives into it at 8 m/s
    w.place(s, np.array([0.0, 25.0]), np.zeros(2), np.zeros(2), np.array([8.0, 0.0]))
    upright = np.ones(2, bool)
    began = 0
    brake = np.array([0.0, 800.0])
    for _ in range(int(4.0 / DT)):
        w.command_vehicles(s, np.zeros(2), np.zeros(2), brake, np.zeros(2))
        w.step()
        touching, b = w.contacts(s, upright)
        began += int(b.sum())
        if touching.any():
            brake = np.array([3000.0, 3000.0])  # both brake after the crash
    # one crash (with bounces) counts once for each agent involved
    assert began == 2 and w.counters["collisions"] == 2
    # a parked slot far away is never counted
    assert not w.in_contact[~w.live].any()


def test_pedestrian_force_is_bounded():
    w = _world(AgentClass.PEDESTRIAN)
    s = _one(w, AgentClass.PEDESTRIAN)
    spec = M.default_spec(AgentClass.PEDESTRIAN)
    v = []
    for _ in range(25):
        w.command_pedestrians(s, np.array([spec.ped_max_force]), np.zeros(1), np.zeros(1))
        w.step()
        v.append(w.observe(s).vx[0])
    a = np.diff(v) / DT
    assert np.allclose(a, spec.ped_max_force / spec.mass, rtol=0.02)
    assert w.observe(s).z[0] == 0.0


@pytest.mark.parametrize("cls", [AgentClass.PASSENGER, AgentClass.BUS, AgentClass.BICYCLE])
def test_no_roll_over_at_a_hard_lateral_acceleration(cls):
    """Steady circle near 0.45 g (bicycle: stabilised lean) - no flip, no explosion."""
    spec = M.default_spec(cls)
    R, a_lat = 25.0, 4.4
    v = math.sqrt(a_lat * R)
    d = spec.front_offset - spec.rear_axle
    from physics_side.control import roll_stabiliser
    from physics_side.kinematics import steady_state_delta

    delta = float(steady_state_delta(np.array([1 / R]), np.array([d]), np.array([spec.wheelbase]))[0])
    w = _world(cls)
    s = _one(w, cls, speed=v)
    m_r = spec.wheel_radius * spec.effective_mass
    worst = 0.0
    for _ in range(int(8.0 / DT)):
        o = w.observe(s)
        drive = max(0.0, (v - o.speed[0]) * 3.0 * m_r)
        stab = roll_stabiliser(o.roll, o.roll_rate, o.speed, o.yaw_rate, 1500.0, 250.0, np.full(1, spec.stab_max))
        w.command_vehicles(s, np.array([delta]), np.array([drive]), np.zeros(1), stab)
        w.step()
        o = w.observe(s)
        assert np.isfinite(o.fx).all() and np.isfinite(o.speed).all()
        if cls != AgentClass.BICYCLE:
            worst = max(worst, abs(math.degrees(o.roll[0])))
    assert abs(math.degrees(o.pitch[0])) < 5.0 and 0.0 < o.z[0] < 1.0
    if cls == AgentClass.BICYCLE:
        lean = math.degrees(math.atan(o.speed[0] * o.yaw_rate[0] / 9.81))
        assert abs(math.degrees(-o.roll[0]) - lean) < 3.0  # leans into the turn like a rider
    else:
        assert worst < 6.0  # body roll of a rigid chassis on soft contacts
    assert o.speed[0] * abs(o.yaw_rate[0]) == pytest.approx(a_lat, rel=0.2)


SUMO_VCLASSES = ("passenger", "taxi", "bus", "coach", "delivery", "truck", "trailer", "motorcycle", "moped",
                 "bicycle", "pedestrian", "emergency", "evehicle", "tram")


def test_every_default_vclass_gets_a_model_of_its_sumo_size(tmp_path):
    """SUMO's own default vType of each vClass (read from real libsumo): a sensible model
    family whose footprint is SUMO's within 5 %, which settles upright on the ground."""
    import libsumo as t

    from protocol.messages import VCLASS_TO_AGENT_CLASS

    root = Path(__file__).resolve().parents[1]
    net = root / "configs" / "scenarios" / "paper" / "paper.net.xml"
    add = tmp_path / "types.add.xml"
    add.write_text("<additional>" + "".join(f'<vType id="t_{v}" vClass="{v}"/>' for v in SUMO_VCLASSES)
                   + "</additional>")
    t.start(["sumo", "-n", str(net), "-a", str(add), "--no-step-log", "true"])
    try:
        sizes = {v: (t.vehicletype.getLength(f"t_{v}"), t.vehicletype.getWidth(f"t_{v}")) for v in SUMO_VCLASSES}
    finally:
        t.close()
    kinds = {"pedestrian": M.KIND_PED, "bicycle": M.KIND_BIKE, "motorcycle": M.KIND_BIKE, "moped": M.KIND_BIKE}
    for vclass, (length, width) in sizes.items():
        cls = VCLASS_TO_AGENT_CLASS.get(vclass, AgentClass.OTHER)
        family = M.family_for(cls, vclass, length)
        spec = M.spec_for_size(family, length, width)
        assert abs(spec.length / length - 1) <= 0.05 and abs(spec.width / width - 1) <= 0.05, (vclass, spec)
        assert spec.kind == kinds.get(vclass, M.KIND_CAR), vclass
        if spec.kind != M.KIND_PED:
            assert 0.4 * length <= spec.wheelbase < length and spec.total_mass > 50.0, vclass
            rest = M.rest_pose(spec)
            assert 0.2 < rest.z < 1.0 and abs(rest.pitch) < 0.05, (vclass, rest)
    assert M.family_for(AgentClass.OTHER, "truck", 7.1) == "truck" and M.family_for(AgentClass.OTHER, "tram", 22) == "tram"
    assert M.family_for(AgentClass.OTHER, "delivery", 6.5) == "van"


def test_a_long_vehicle_steers_its_rear_axle_and_turns_tighter():
    """Buses, coaches, trucks and trams steer both axles (SUMO puts their body on the chord of
    the lane): counter-phase rear steering about doubles the yaw rate of the front axle alone,
    as the kinematic bicycle with two steered axles says; cars keep a fixed rear axle."""
    bus = M.spec_for_size("bus", 12.0, 2.5)
    car = M.spec_for_size("car", 5.0, 1.8)
    assert bus.rear_steer_deg > 0 and car.rear_steer_deg == 0
    w = _world(AgentClass.BUS, n=2)
    pool = w.pool_for("bus", 12.0, 2.5)
    s = w.allocate(["a", "b"], np.array([pool, pool]), np.array([0.0, 60.0]), np.zeros(2))
    w.place(s, np.array([0.0, 60.0]), np.zeros(2), np.zeros(2), np.full(2, 3.0))
    assert (w.tables.max_rsteer[s] > 0).all()
    for _ in range(int(round(3.0 / DT))):
        w.command_vehicles(s, np.full(2, 0.3), np.full(2, 3000.0), np.zeros(2), None, np.array([0.0, -0.3]))
        w.step()
    o = w.observe(s)
    L = bus.wheelbase
    for k, rear in enumerate((0.0, -0.3)):
        expected = o.speed[k] * (math.tan(0.3) - math.tan(rear)) / L
        assert o.yaw_rate[k] == pytest.approx(expected, rel=0.25), (k, o.yaw_rate, o.speed)
    assert o.yaw_rate[1] > 1.6 * o.yaw_rate[0]


def test_pedestrian_body_is_sumo_footprint():
    """A pedestrian's body is SUMO's footprint (0.215 m deep, 0.478 m wide by default), not a
    disc of the width: a capsule stood 0.13 m into passing vehicles."""
    import mujoco

    spec = M.spec_for_size("pedestrian", 0.215, 0.478)
    m = M.template(spec).compile()
    g = m.geom("chassis")
    assert g.type[0] == mujoco.mjtGeom.mjGEOM_BOX
    assert 2 * g.size[0] == pytest.approx(spec.length) and 2 * g.size[1] == pytest.approx(spec.width)


def test_a_heavy_vehicles_spinning_wheel_is_braked_by_its_traction_control():
    """Full drive in a tight turn unloads a bus's inner rear wheel: without traction control it
    spins up to hundreds of m/s (its tyre then carries no side force); with it, within tens."""
    from physics_side.world import TCS_BAND_MPS, TCS_MARGIN_MPS, TCS_SLIP

    def excess_spin(with_tcs: bool) -> tuple[float, float]:
        w = _world(AgentClass.BUS, n=1)
        s = _one(w, AgentClass.BUS, speed=4.0)
        r = w.tables.r_wheel[s][0]
        top = 0.0
        for _ in range(150):
            o = w.observe(s)
            w.command_vehicles(s, np.array([0.5]), np.array([M.default_spec(AgentClass.BUS).max_drive]), np.zeros(1),
                               None, np.zeros(1), o.speed if with_tcs else None)
            w.step()
            o = w.observe(s)
            top = max(top, float(np.max(w.wheel_spin(s)[0] * r) - o.speed[0]))
        return top, float(o.speed[0])

    free, _ = excess_spin(False)
    held, v = excess_spin(True)
    assert free > 100.0, free
    assert held < (TCS_SLIP - 1.0) * v + TCS_MARGIN_MPS + TCS_BAND_MPS + 10.0, (held, v)  # (+ one tick's spin-up)
    assert M.default_spec(AgentClass.BUS).traction_control and not M.default_spec(AgentClass.PASSENGER).traction_control


@pytest.mark.parametrize("placed, touch", [((True, True), False), ((True, False), True), ((False, False), True)])
def test_bodies_placed_every_tick_touch_driven_ones_but_not_each_other(placed, touch):
    """Two cars overlapping 0.3 m side by side: kinematic (placed) bodies touch driven bodies
    and pedestrians but not each other (neither answers a contact: no physics between them)."""
    w = _world(n=2)
    pool = w.pool_for("car", 5.0, 1.8)
    s = w.allocate(["a", "b"], np.array([pool, pool]), np.array([0.0, 0.0]), np.array([0.0, 1.5]))
    w.set_ghost(s, False, np.array(placed))
    touching = np.zeros(2, bool)
    for _ in range(10):
        w.place(s, np.array([0.0, 0.0]), np.array([0.0, 1.5]), np.zeros(2), np.zeros(2), count=False)
        w.command_vehicles(s, np.zeros(2), np.zeros(2), np.full(2, 3000.0), np.zeros(2))
        w.step()
        touching |= w.contacts(s, np.ones(2, bool))[0]
    assert bool(touching.all()) == touch
