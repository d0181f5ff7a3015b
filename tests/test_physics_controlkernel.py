"""The C fast path of ``control_default`` (physics_side._controlkernel) against its numpy body
``_control_default_numpy``: steering, drive, brake, commanded acceleration and the integral
bit for bit (NaN at the same places, the sign of a zero kept).

On a real fleet driven by MuJoCo (extrapolated and interpolated references, a speed profile
that stops, stands and starts again, SUMO gone: every vehicle braking to rest), and on
hostile inputs (NaN, infinities, signed zeros, huge values) under every branch of the
configuration: Stanley and pure pursuit, preview on and off, yaw damping on and off, the
mean-speed lead on and off, the brake loop with and without an interpolated reference,
roll back on and off, the cross-track limit on and off, rear-steered vehicles or none,
stopping masks, roll-back masks and a sideways drift.

``limit_commands``' C path (``_controlkernel.limit``) against ``_limit_commands_numpy`` the
same way: steering, drive and brake of the same fleets, and of hostile inputs under every
flag (rear axles steered or not, grip-limited drives, the catch-up cuts with a real or a
made-up bend ahead, two-wheelers) with agents exactly on each limit, mixed bicycles and
cars, fixed and steered rear axles, and no agents at all.
"""

from __future__ import annotations

import copy
import itertools
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from physics_side import control as C
from physics_side.config import DefaultControl, PhysicsSettings
from physics_side.daemon import build_fleet
from physics_side.reference import PathPoint, Reference
from protocol.codec import decode_as, encode
from protocol.messages import AgentClass, StepMessage
from synthetic.traffic import circle_traffic
from tests.test_physics_pathkernel import _bits_equal, _random_paths

needs_c = pytest.mark.skipif(not C.FAST_CONTROL, reason="physics_side._controlkernel not built, SUMOCO_PURE_PHYSICS "
                                                         "set, or numpy's math is not libm's")
FIELDS = ("steer", "drive", "brake", "aux")
CONTROL_DEFAULT = C.control_default  # (the fleet's calls are spied on below)
LIMIT_COMMANDS = C.limit_commands
SPECIAL = np.array([np.nan, np.inf, -np.inf, 0.0, -0.0, 1e308, -1e308, 5e-324, -5e-324, 0.2, -0.15])


# --------------------------------------------------------------------------- both paths, compared


def _run(fast: bool, args: tuple, kwargs: dict, state: C.ControlState, monkeypatch) -> tuple:
    """control_default with the C path on or off, on its own copy of ``state``, the
    reference's cache as it was."""
    ref = args[2]
    saved = ref._last_at
    st = copy.deepcopy(state)
    with monkeypatch.context() as m, np.errstate(all="ignore"):
        m.setattr(C, "FAST_CONTROL", fast)
        cmd = CONTROL_DEFAULT(*args[:6], st, *args[6:], **kwargs)
    ref._last_at = saved
    return cmd, st


def _fails(fn, args: list):
    """``fails(i, value, exc, match)``: ``fn`` with argument ``i`` of ``args`` replaced by
    ``value`` raises ``exc`` matching ``match``."""

    def fails(i, value, exc, match):
        a = list(args)
        a[i] = value
        with pytest.raises(exc, match=match):
            fn(*a)

    return fails


def _spy(monkeypatch, name: str) -> list[bool]:
    """``control.<name>`` (a C path that returns None for inputs it does not take) patched to
    note each call: True where the C path ran."""
    calls: list[bool] = []
    real = getattr(C, name)

    def spy(*a):
        out = real(*a)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(C, name, spy)
    return calls


def _same(args: tuple, kwargs: dict, state: C.ControlState, monkeypatch) -> None:
    """The C path runs (it takes these inputs) and gives the numpy body's bits."""
    calls = _spy(monkeypatch, "_control_default_c")
    c, sc = _run(True, args, kwargs, state, monkeypatch)
    assert calls == [True]
    p, sp = _run(False, args, kwargs, state, monkeypatch)
    for f in FIELDS:
        assert _bits_equal(getattr(c, f), getattr(p, f)), f
    assert _bits_equal(sc.integ, sp.integ)
    assert (sc.tau_last, sc.step_s) == (sp.tau_last, sp.step_s) or np.isnan(sc.tau_last) and np.isnan(sp.tau_last)


def _sprinkle(rng: np.random.Generator, a: np.ndarray, share: float = 0.25) -> np.ndarray:
    """``a`` with a ``share`` of its items special values."""
    a = np.array(a, np.float64)
    mask = rng.random(a.shape) < share
    a[mask] = rng.choice(SPECIAL, int(mask.sum()))
    return a


# --------------------------------------------------------------------------- a real fleet


def _fleet_ticks(monkeypatch, step_s: float, reference: str, n: int = 40,
                 cls: AgentClass = AgentClass.PASSENGER) -> tuple[int, int]:
    """A fleet of ``n`` vehicles of ``cls`` on MuJoCo following circle traffic whose speed
    changes step by step (cruise, brake, stand, start), then SUMO gone; every control_default
    and limit_commands call compared. Returns how many of each (limit_commands': with the
    catch-up cuts)."""
    s = PhysicsSettings()
    slots = {AgentClass.PASSENGER: "passenger", AgentClass.BICYCLE: "bicycle", AgentClass.BUS: "bus"}[cls]
    s = replace(s, physics=replace(s.physics, initial_slots={slots: n + 8}, preset="default", presets={},
                                   sumo_step_s=step_s, reference=reference))
    fleet = build_fleet(s)
    seen, limited = [], []

    def spy(*args, **kwargs):
        args = list(args)
        state = args.pop(6)
        _same(tuple(args), kwargs, state, monkeypatch)
        seen.append(kwargs.get("rolls_back") is not None)
        return CONTROL_DEFAULT(*args[:6], state, *args[6:], **kwargs)

    def limit_spy(*args, **kwargs):
        _limit_same(args, kwargs, monkeypatch)
        limited.append((list(args) + [kwargs.get("catch_up")])[7] is not None)
        return LIMIT_COMMANDS(*args, **kwargs)

    speeds = [10.0, 10.0, 6.0, 2.0, 0.1, 0.0, 0.0, 0.0, 3.0, 8.0, 8.0]
    with monkeypatch.context() as m:
        m.setattr(C, "control_default", spy)
        m.setattr(C, "limit_commands", limit_spy)
        for k, v in enumerate(speeds):
            msg = decode_as(encode(circle_traffic(n, k, step_s, speed=v, cls=cls)), StepMessage)
            fleet.apply_step(msg)
            for _ in range(int(round(step_s * 50))):
                fleet.tick()
        fleet.begin_stop()
        for _ in range(10):
            fleet.tick()
    return len(seen), sum(limited)


@needs_c
@pytest.mark.parametrize("step_s, reference, cls", [(0.1, "extrapolate", AgentClass.PASSENGER),
                                                    (0.5, "interpolate", AgentClass.PASSENGER),
                                                    (0.1, "extrapolate", AgentClass.BICYCLE)])
def test_a_real_fleet_on_mujoco(monkeypatch, step_s, reference, cls):
    controlled, cut = _fleet_ticks(monkeypatch, step_s, reference, cls=cls)
    assert controlled > 50 and cut > 50


# --------------------------------------------------------------------------- hostile inputs


def _reference(rng: np.random.Generator, n: int, interpolated: bool, drift: bool) -> Reference:
    off, xy = _random_paths(rng, n)
    x, y = xy[off[:-1], 0] + rng.normal(0, 0.5, n), xy[off[:-1], 1] + rng.normal(0, 0.5, n)
    speed = rng.uniform(-0.5, 20.0, n)
    speed[::4] = 0.0  # standing references
    speed[1::9] = 0.15
    accel = rng.normal(0.0, 3.0, n)
    accel[::5] = -8.0  # stops within the lead
    ref = Reference(1.0, x, y, rng.uniform(-720.0, 720.0, n), speed, accel, x, y, off, xy, rng.normal(0, 0.3, n))
    if interpolated:
        with np.errstate(all="ignore"):
            ref.interpolate_to(0.5, rng.random(n) < 0.7, rng.uniform(0.0, 10.0, n), rng.uniform(0.0, 15.0, n),
                               rng.normal(0.0, 2.0, n), rng.normal(0.0, 0.5, n))
    if drift:
        rates = rng.normal(0.0, 1.0, n)
        rates[::3] = 0.0
        ref.set_side_rate(rates)
    return ref


def _inputs(rng: np.random.Generator, ref: Reference, tau: float, hostile: bool) -> tuple:
    """(obs, params, proj) near the reference at ``tau``: bumpers up to metres off, some
    standing past a standing reference, rolling back, NaN or infinite (``hostile``)."""
    n = ref.n
    with np.errstate(all="ignore"):
        r = ref.at(tau)
        s_act = r.s + rng.normal(0.0, 0.5, n)
        s_act[::3] = r.s[::3] + rng.uniform(0.0, 0.6, len(s_act[::3]))  # past the reference (roll back)
        pp = ref.point_at(np.nan_to_num(s_act), tau)
    e_lat = rng.normal(0.0, 1.0, n)
    speed = rng.normal(5.0, 6.0, n)
    speed[::4] = rng.uniform(-0.1, 0.06, len(speed[::4]))  # at rest, rolling back
    yaw = pp.heading + rng.normal(0.0, 0.3, n)
    cols = dict(fx=pp.x + rng.normal(0, 0.3, n), fy=pp.y + rng.normal(0, 0.3, n), yaw=yaw, speed=speed,
                yaw_rate=rng.normal(0.0, 0.4, n), fvx=speed * np.cos(yaw), fvy=speed * np.sin(yaw))
    cols["cx"], cols["cy"] = cols["fx"] - 2.0 * np.cos(yaw), cols["fy"] - 2.0 * np.sin(yaw)
    if hostile:
        cols = {k: _sprinkle(rng, v, 0.1) for k, v in cols.items()}
        s_act, e_lat = _sprinkle(rng, s_act, 0.1), _sprinkle(rng, e_lat, 0.1)
    obs = C.VehicleObs(**cols)
    wb = rng.uniform(1.0, 6.0, n)
    par = dict(wheelbase=wb, d_bumper=wb + rng.uniform(0.0, 1.5, n), rear_axle=-rng.uniform(0.5, 3.0, n),
               front_offset=rng.uniform(1.0, 5.0, n), m_eff=rng.uniform(80.0, 20000.0, n),
               r_wheel=rng.uniform(0.3, 0.6, n), max_steer=rng.uniform(0.3, 0.7, n),
               max_drive=rng.uniform(100.0, 5000.0, n), max_brake=rng.uniform(500.0, 20000.0, n))
    if hostile:
        par = {k: _sprinkle(rng, v, 0.05) for k, v in par.items()}
    p = C.VehicleParams(**par)
    return obs, p, (s_act, e_lat, pp)


CONFIGS = list(itertools.product(
    ["stanley", "pursuit"],  # lateral
    [0.0, 0.05],  # preview_s
    [0.0, 0.05],  # k_yaw
    [0.0, 0.5, -0.5],  # mean_speed_lead (< 0: Reference.mean_speed_lead gives zeros)
    [4.0, 2.0],  # brake_omega (> pos_omega: on)
    [0.0, 0.15],  # creep_back_m
    [15.0, 0.0],  # max_correction_deg
))


@needs_c
@pytest.mark.parametrize("interpolated, drift", [(False, False), (False, True), (True, False), (True, True)])
@pytest.mark.parametrize("hostile", [False, True])
def test_every_branch_of_the_configuration(monkeypatch, interpolated, drift, hostile):
    rng = np.random.default_rng(int(interpolated) + 2 * int(drift) + 4 * int(hostile))
    n = 64
    ref = _reference(rng, n, interpolated, drift)
    tau = 0.06
    obs, p, proj = _inputs(rng, ref, tau, hostile)
    integ = rng.normal(0.0, 1.0, n)
    if hostile:
        integ = _sprinkle(rng, integ)
    stop = rng.random(n) < 0.5
    stop_speed = np.maximum(rng.normal(1.0, 2.0, n), 0.0)
    stop_speed[::3] = -0.0
    rolls = rng.random(n) < 0.7
    max_rear = np.where(rng.random(n) < 0.3, rng.uniform(0.0, 0.2, n), 0.0)
    for k, (lateral, preview, k_yaw, lead, brake_omega, creep, mc) in enumerate(CONFIGS):
        cfg = DefaultControl(lateral=lateral, preview_s=preview, k_yaw=k_yaw, mean_speed_lead=lead,
                             brake_omega=brake_omega, creep_back_m=creep, max_correction_deg=mc)
        # a state that has seen a sample: step 0.1 s (the mean-speed lead acts)
        state = C.ControlState(integ=integ, tau_last=0.14, step_s=0.0)
        pk = p if k % 2 else replace(p, max_rear=max_rear)
        masks = [dict(), dict(stopping=stop, stop_speed=stop_speed), dict(rolls_back=rolls),
                 dict(stopping=np.zeros(n, bool), stop_speed=stop_speed, rolls_back=~rolls),
                 dict(stopping=stop, stop_speed=stop_speed, stop_decel=5.5, rolls_back=rolls)]
        for kw in masks if k % 7 == 0 else masks[k % 5:k % 5 + 1]:
            _same((obs, pk, ref, tau, 0.02, cfg), dict(kw, proj=proj), state, monkeypatch)
        # the projection done here (at_and_project, or at and project)
        _same((obs, pk, ref, tau, 0.02, cfg), dict(s_guess=proj[0]), state, monkeypatch)
        _same((obs, pk, ref, tau, 0.02, cfg), {}, C.ControlState.zeros(n), monkeypatch)


@needs_c
@pytest.mark.parametrize("tau", [0.0, -0.0, 0.3, 0.5, 2.0, np.inf, np.nan])
def test_times_and_first_ticks(monkeypatch, tau):
    """Reference ages up to past the step, not finite; states that have seen no sample yet
    (no lead) or whose sample just arrived."""
    rng = np.random.default_rng(11)
    n = 50
    for interpolated in (False, True):
        ref = _reference(rng, n, interpolated, True)
        obs, p, proj = _inputs(rng, ref, 0.06, True)
        for state in (C.ControlState.zeros(n), C.ControlState(rng.normal(0, 1, n), tau_last=5.0, step_s=0.3)):
            _same((obs, p, ref, tau, 0.02, DefaultControl()), dict(proj=proj), state, monkeypatch)
            _same((obs, p, ref, tau, 0.02, DefaultControl(lateral="pursuit")), dict(s_guess=proj[0]), state,
                  monkeypatch)


@needs_c
@pytest.mark.parametrize("interpolated", [False, True])
def test_signed_zeros_and_ties(monkeypatch, interpolated):
    """Every input a zero of either sign or a value on a clip's bound: numpy's minimum /
    maximum keep the second of two equal values, and adding the mean-speed lead's zeros
    (an interpolated reference) turns -0.0 into 0.0. The reference point itself is set (the
    reference's cache): its arc length, speed and acceleration zeros of either sign too."""
    rng = np.random.default_rng(3)
    n = 200
    tau = 0.06
    ref = _reference(rng, n, interpolated, False)
    cfg = DefaultControl()
    zeros = np.where(rng.random(n) < 0.5, 0.0, -0.0)
    obs = C.VehicleObs(*[np.where(rng.random(n) < 0.5, 0.0, -0.0) for _ in range(9)])
    ties = rng.choice([0.0, -0.0, cfg.creep_speed, -cfg.creep_speed, C.STANLEY_BETA_MAX, 1.0, -1.0], n)
    p = C.VehicleParams(np.ones(n), np.ones(n), -np.ones(n), np.ones(n), np.abs(ties) + 1.0, np.ones(n),
                        np.abs(ties), np.abs(ties), np.abs(ties), zeros)
    pp = PathPoint(zeros, zeros, ties, zeros)
    speeds = rng.choice([0.0, -0.0, cfg.hold_speed, 5.0], n)
    with np.errstate(all="ignore"):
        r = replace(ref.at(tau), x=zeros, y=zeros, s=zeros[::-1].copy(), speed=speeds, accel=zeros[::-1].copy())
    for e in (zeros, ties, -ties):
        for integ in (zeros, ties, -ties):
            state = C.ControlState(integ=integ.copy(), tau_last=0.14)
            for c in (cfg, replace(cfg, lateral="pursuit"), replace(cfg, int_limit=0.0, k_int=0.0)):
                ref._last_at = (tau, r)
                _same((obs, p, ref, tau, 0.02, c), dict(proj=(e, ties, pp)), state, monkeypatch)


# --------------------------------------------------------------------------- dispatch


@needs_c
def test_inputs_the_kernel_does_not_read_run_the_numpy_body(monkeypatch):
    """float32, strided, list, length-1 (broadcast) arrays, masks that are not bool and a
    stopping mask without stop speeds give the numpy body's results through the numpy body."""
    rng = np.random.default_rng(5)
    n = 20
    ref = _reference(rng, n, False, False)
    obs, p, proj = _inputs(rng, ref, 0.06, False)
    state = C.ControlState(rng.normal(0, 1, n), tau_last=0.14)
    cfg = DefaultControl()
    cases = [
        (replace(obs, speed=obs.speed.astype(np.float32)), p, {}),
        (replace(obs, fvx=np.repeat(obs.fvx, 2)[::2]), p, {}),
        (obs, replace(p, m_eff=np.full(1, 1500.0)), {}),
        (obs, replace(p, max_rear=list(np.zeros(n))), {}),
        (obs, p, dict(rolls_back=np.ones(n, np.uint8))),
        (obs, p, dict(stopping=np.zeros(n, bool))),
        (obs, p, dict(stopping=np.ones(n, bool), stop_speed=1.0)),
        (replace(obs, speed=list(obs.speed)), p, {}),
    ]
    for o, pk, kw in cases:
        args = (o, pk, ref, 0.06, 0.02, cfg)
        kw = dict(kw, proj=proj)
        assert C._control_default_c(*args, copy.deepcopy(state), ref.at(0.06), proj, 0.1, kw.get("stopping"), 3.0,
                                    kw.get("stop_speed"), kw.get("rolls_back")) is None
        try:
            c, sc = _run(True, args, kw, state, monkeypatch)
        except Exception as e:  # (the numpy body's own error, both ways)
            with pytest.raises(type(e)):
                _run(False, args, kw, state, monkeypatch)
            continue
        pn, sp = _run(False, args, kw, state, monkeypatch)
        for f in FIELDS:
            assert _bits_equal(getattr(c, f), getattr(pn, f)), f
        assert _bits_equal(sc.integ, sp.integ)


@needs_c
def test_kernel_rejects_what_it_cannot_read():
    n = 4
    k = C._kernel
    z = np.zeros(n)
    cp, cc = C._default_constants(DefaultControl())
    k.prepare(z, z, z, np.empty((3, n)), cp)
    with pytest.raises(ValueError, match=r"out: needs shape \(3, 4\)"):
        k.prepare(z, z, z, np.empty((2, n)), cp)
    with pytest.raises(TypeError, match="constants must be a tuple of 9"):
        k.prepare(z, z, z, np.empty((3, n)), cp[:5])
    with pytest.raises(ValueError, match=r"e_lat needs shape \(4,\)"):
        k.prepare(z, z, z[:3], np.empty((3, n)), cp)
    consts = (cc[0], cc[1], -3.0, 0.02, *cc[2:7], 1.0, *cc[7:], 2.0, 0.06, 0.05, 0.11)
    args = [z] * 19 + [None, None] + [z] * 9 + [None, None, z, z, None, z, np.empty((5, n)), consts]
    k.control(*args)
    fails = _fails(k.control, args)

    fails(0, z.astype(np.float32), TypeError, "fx: needs float64")
    fails(3, np.zeros(8)[::2], TypeError, "cy: needs a C-contiguous")
    fails(14, z[:3], ValueError, r"control: r_accel needs shape \(4,\)")
    fails(19, np.zeros(n, bool), ValueError, "stopping needs stop_speed")
    fails(18, None, TypeError, "a0: needs")
    fails(31, z, TypeError, "rolls_back: needs bool")
    fails(35, None, TypeError, "corr: needs")
    fails(36, np.empty((4, n)), ValueError, r"out: needs shape \(5, 4\)")
    fails(37, consts[:-1], TypeError, "constants must be a tuple of 34")
    with pytest.raises(TypeError, match="takes 38 arguments"):
        k.control(*args[:-1])



# --------------------------------------------------------------------------- limit_commands


def _limit_same(args: tuple, kwargs: dict, monkeypatch) -> tuple:
    """limit_commands through the C path (it takes these inputs) and through the numpy body:
    the same bits, the inputs not written. Returns the numpy body's (steer, drive, brake)."""
    before = [np.array(a, copy=True) for a in args[:3]]
    with monkeypatch.context() as m, np.errstate(all="ignore"):
        calls = _spy(m, "_limit_commands_c")
        m.setattr(C, "FAST_CONTROL", True)
        fast = LIMIT_COMMANDS(*args, **kwargs)
        m.setattr(C, "FAST_CONTROL", False)
        slow = LIMIT_COMMANDS(*args, **kwargs)
    assert calls == [True]
    for f, a, b in zip(("steer", "drive", "brake"), fast, slow):
        assert _bits_equal(a, b), f
    for a, b in zip(args[:3], before):
        assert _bits_equal(a, b)
    return slow


class _Ahead:
    """What limit_commands reads of a reference: the path's curvature at the preview points
    (3, n) and the reference speed."""

    def __init__(self, curvature: np.ndarray, speed: np.ndarray):
        self.path = SimpleNamespace(at=lambda s: SimpleNamespace(curvature=curvature))
        self.speed = speed

    def at(self, tau):
        return SimpleNamespace(speed=self.speed)


def _limit_case(rng: np.random.Generator, n: int, hostile: bool, any_grip: bool, bikes: bool) -> tuple:
    """(steer, drive, brake, obs, params, limits, catch-up mask, err_lat, v_ref, curvature
    (3, n)) with agents on every limit: steering at +-the friction circle's limit and at the
    saturation shares, speeds at STEER_LIMIT_V_MIN, at the reference and at the bend's speed,
    offsets at GRIP_SAT_LAT_M, curvatures at CURVATURE_FLOOR, grip use at MAX_GRIP_USE,
    rear axles 0, -0.0, steered, negative; bicycles mixed with cars."""
    u = rng.uniform
    speed = rng.normal(8.0, 8.0, n)
    speed[::7] = u(-2.0, 0.3, len(speed[::7]))
    speed[1::11] = C.STEER_LIMIT_V_MIN
    speed[2::13] = rng.choice([0.0, -0.0], len(speed[2::13]))
    wb = u(0.9, 7.0, n)
    a_lat = u(2.0, 9.0, n)
    a_lat[3::17] = rng.choice([0.0, C.A_LAT_FLOOR, -1.0], len(a_lat[3::17]))
    max_steer = u(0.2, 0.8, n)
    with np.errstate(all="ignore"):
        lim_f = C.steer_limit(speed, wb, a_lat, max_steer)
    steer = rng.normal(0.0, 0.6, n)
    k = rng.integers(0, 7, n)  # on a limit, either side
    sign = rng.choice([-1.0, 1.0], n)
    steer = np.select([k == 0, k == 1, k == 2, k == 3], [sign * lim_f, sign * C.STEER_SAT_SHARE * lim_f,
                                                         sign * C.STEER_SAT_SHARE * max_steer,
                                                         np.nextafter(sign * lim_f, 0.0)], steer)
    v_ref = np.where(rng.random(n) < 0.3, speed, np.abs(rng.normal(6.0, 6.0, n)))
    curv = rng.normal(0.0, 0.05, (3, n))
    curv[rng.integers(0, 3, n), np.arange(n)] = rng.choice([C.CURVATURE_FLOOR, -C.CURVATURE_FLOOR, 0.0, -0.0, 0.3], n)
    at_curve = rng.random(n) < 0.2  # speed exactly the bend's sqrt(a_lat / kappa)
    curv[0, at_curve] = a_lat[at_curve] / np.maximum(speed[at_curve] ** 2, 1e-3)
    err_lat = np.where(rng.random(n) < 0.3, rng.choice([-1.0, 1.0], n) * C.GRIP_SAT_LAT_M, rng.normal(0.0, 0.5, n))
    yaw_rate = rng.normal(0.0, 0.5, n)
    yaw_rate[::5] = C.MAX_GRIP_USE * C.G / np.where(speed[::5] == 0.0, 1.0, speed[::5])  # grip use at its cap
    roll = rng.normal(0.0, 0.4, n)
    roll[::9] = rng.choice([np.pi / 2, -0.0, 1.2, -1.2], len(roll[::9]))
    grip = np.where(rng.random(n) < 0.5, u(50.0, 3000.0, n), np.inf)
    max_rear = rng.choice([0.0, -0.0, 0.3, -0.1, 0.6], n)
    cols = dict(speed=speed, yaw_rate=yaw_rate, roll=roll)
    par = dict(wheelbase=wb, d_bumper=wb + 0.8, rear_axle=-np.ones(n), front_offset=np.ones(n),
               m_eff=u(80.0, 20000.0, n), r_wheel=u(0.3, 0.6, n), max_steer=max_steer, max_drive=u(100.0, 5000.0, n),
               max_brake=u(500.0, 20000.0, n))
    lims = dict(a_lat=a_lat, grip_torque=grip, max_rear=max_rear)
    drive = np.where(rng.random(n) < 0.8, u(0.0, 4000.0, n), rng.choice([0.0, -0.0, -200.0], n))
    brake = np.where(rng.random(n) < 0.5, 0.0, u(0.0, 20000.0, n))
    if hostile:
        cols = {k: _sprinkle(rng, v, 0.1) for k, v in cols.items()}
        par = {k: _sprinkle(rng, v, 0.05) for k, v in par.items()}
        lims = {k: _sprinkle(rng, v, 0.05) for k, v in lims.items()}
        steer, drive, brake, v_ref, err_lat = (_sprinkle(rng, a, 0.1) for a in (steer, drive, brake, v_ref, err_lat))
        curv = _sprinkle(rng, curv, 0.05)
    bike = (rng.random(n) < 0.4) if bikes else np.zeros(n, bool)
    lim = C.VehicleLimits(a_lat=lims["a_lat"], grip_torque=lims["grip_torque"], max_rear=lims["max_rear"],
                          stab_gain=np.ones(n), stab_max=np.full(n, 200.0), mass=np.full(n, 120.0), bike=bike,
                          any_grip=any_grip, any_bike=bikes)
    mask = rng.random(n) < 0.8
    return steer, drive, brake, SimpleNamespace(**cols), C.VehicleParams(**par), lim, mask, err_lat, v_ref, curv


LIMIT_FLAGS = list(itertools.product([False, True], [False, True], ["none", "made up", "real"], [False, True]))


@needs_c
@pytest.mark.parametrize("hostile", [False, True])
@pytest.mark.parametrize("n", [0, 1, 7, 300])
def test_limit_commands_every_flag(monkeypatch, hostile, n):
    """Every combination of rear_steered, lim.any_grip, catch_up (None, a made-up bend ahead,
    a real reference) and lim.any_bike; the flags are the caller's (grip limits given but not
    flagged, bikes flagged where there are none: the numpy body reads the flag only)."""
    rng = np.random.default_rng(100 + n + int(hostile))
    ref = _reference(rng, n, False, True) if n else None
    for rear_steered, any_grip, catch, bikes in LIMIT_FLAGS:
        steer, drive, brake, obs, p, lim, mask, err_lat, v_ref, curv = _limit_case(rng, n, hostile, any_grip, bikes)
        if catch == "none":
            catch_up = None
        elif catch == "made up" or ref is None:
            catch_up = C.CatchUp(_Ahead(curv, v_ref), np.zeros(n), 0.06, mask, err_lat)
        else:
            with np.errstate(all="ignore"):
                s_act = ref.at(0.06).s + rng.normal(0.0, 2.0, n)
            if hostile:
                s_act = _sprinkle(rng, s_act, 0.1)
            catch_up = C.CatchUp(ref, s_act, 0.06, mask, err_lat)
        _limit_same((steer, drive, brake, obs, p, lim, rear_steered, catch_up), {}, monkeypatch)


@needs_c
def test_limit_commands_signed_zeros_and_ties(monkeypatch):
    """Every input a zero of either sign or a value on a bound: numpy's minimum / maximum
    keep the second of two equal values (np.clip too, with array bounds)."""
    rng = np.random.default_rng(7)
    n = 400
    pick = lambda *v: rng.choice(np.array(v, np.float64), n)  # noqa: E731
    z = (0.0, -0.0)
    obs = SimpleNamespace(speed=pick(*z, C.STEER_LIMIT_V_MIN, 1.0, -1.0), yaw_rate=pick(*z, 1.0),
                          roll=pick(*z, np.pi / 4))
    p = C.VehicleParams(pick(*z, 1.0), np.ones(n), -np.ones(n), np.ones(n), pick(*z, 1.0), pick(*z, 1.0),
                        pick(*z, 0.5, np.pi / 4), pick(*z, 100.0), pick(*z, 100.0))
    lim = C.VehicleLimits(a_lat=pick(*z, C.A_LAT_FLOOR, 1.0), grip_torque=pick(*z, np.inf, 100.0),
                          max_rear=pick(*z, 0.3), stab_gain=np.ones(n), stab_max=np.ones(n), mass=np.ones(n),
                          bike=rng.random(n) < 0.5, any_grip=True, any_bike=True)
    curv = rng.choice(np.array([0.0, -0.0, C.CURVATURE_FLOOR, 1.0]), (3, n))
    for rear_steered in (False, True):
        for _ in range(4):
            steer, drive, brake = pick(*z, 0.5, -0.5, np.pi / 4), pick(*z, 100.0, 2.0), pick(*z, 100.0)
            cu = C.CatchUp(_Ahead(curv, pick(*z, 1.0, np.inf)), np.zeros(n), 0.0, rng.random(n) < 0.5,
                           pick(*z, C.GRIP_SAT_LAT_M, -C.GRIP_SAT_LAT_M))
            _limit_same((steer, drive, brake, obs, p, lim, rear_steered, cu), {}, monkeypatch)


@needs_c
def test_limit_commands_takes_the_modules_constants(monkeypatch):
    """The kernel gets each constant from control.py per call (no copy in C): with one of them
    changed (and the numpy body's result changing with it) both paths still agree. The
    saturation cut's share and braking are saturation_speed_cut's defaults in the numpy body
    (bound when it was defined, so not patched here): the module's values."""
    assert C.saturation_speed_cut.__defaults__ == (C.STEER_SAT_SHARE, C.STEER_SAT_DECEL)
    rng = np.random.default_rng(9)
    n = 300
    steer, drive, brake, obs, p, lim, mask, err_lat, v_ref, curv = _limit_case(rng, n, False, True, True)
    args = (steer, drive, brake, obs, p, lim, False, C.CatchUp(_Ahead(curv, v_ref), np.zeros(n), 0.0, mask, err_lat))
    base = _limit_same(args, {}, monkeypatch)
    for name, value in (("G", 3.0), ("MAX_GRIP_USE", 0.3), ("GRIP_LATERAL", 0.5), ("CURVATURE_FLOOR", 0.2),
                        ("STEER_LIMIT_V_MIN", 6.0), ("A_LAT_FLOOR", 5.0), ("GRIP_SAT_LAT_M", 0.01)):
        with monkeypatch.context() as m:
            m.setattr(C, name, value)
            got = _limit_same(args, {}, monkeypatch)
        assert not all(_bits_equal(a, b) for a, b in zip(got, base)), name


@needs_c
def test_limit_inputs_the_kernel_does_not_read_run_the_numpy_body(monkeypatch):
    """float32, strided, list, length-1 (broadcast), 2-d and scalar inputs and a catch-up mask
    that is not bool give the numpy body's results (or its error) through the numpy body; a
    uint8 bicycle mask (np.where's truth: nonzero) is read."""
    rng = np.random.default_rng(13)
    n = 30
    steer, drive, brake, obs, p, lim, mask, err_lat, v_ref, curv = _limit_case(rng, n, True, True, True)
    cu = C.CatchUp(_Ahead(curv, v_ref), np.zeros(n), 0.0, mask, err_lat)
    base = (steer, drive, brake, obs, p, lim, True, cu)
    with np.errstate(over="ignore"):
        speed32 = obs.speed.astype(np.float32)
    cases = [
        dict(obs=SimpleNamespace(**{**obs.__dict__, "speed": speed32})),
        dict(obs=SimpleNamespace(**{**obs.__dict__, "roll": np.repeat(obs.roll, 2)[::2]})),
        dict(steer=np.repeat(steer, 2)[::2]),
        dict(steer=steer[None, :]),
        dict(drive=list(drive)),
        dict(steer=list(steer)),
        dict(p=replace(p, m_eff=np.full(1, 1500.0))),
        dict(lim=replace(lim, a_lat=8.0)),
        dict(lim=replace(lim, max_rear=np.zeros(n, np.float32))),
        dict(cu=replace(cu, mask=mask.astype(np.uint8) * 2)),  # (2 & True: 0)
        dict(cu=replace(cu, mask=list(mask))),
        dict(cu=replace(cu, err_lat=np.repeat(err_lat, 2)[::2])),
        dict(cu=C.CatchUp(_Ahead(curv, np.repeat(v_ref, 2)[::2]), np.zeros(n), 0.0, mask, err_lat)),
        dict(cu=replace(cu, mask=np.ones(n + 1, bool))),
        dict(lim=replace(lim, bike=lim.bike.astype(np.float64))),
    ]
    names = ("steer", "drive", "brake", "obs", "p", "lim", "rear_steered", "cu")
    raised = []
    for case in cases:
        args = tuple(case.get(k, v) for k, v in zip(names, base))
        calls = []
        real = C._limit_commands_c

        def spy(*a):
            out = real(*a)
            calls.append(out is not None)
            return out

        with monkeypatch.context() as m, np.errstate(all="ignore"):
            m.setattr(C, "_limit_commands_c", spy)
            try:
                fast = C.limit_commands(*args)
            except Exception as e:  # (the numpy body's own error, both ways)
                m.setattr(C, "FAST_CONTROL", False)
                with pytest.raises(type(e)):
                    C.limit_commands(*args)
                assert calls in ([False], []), case
                raised.append(type(e))
                continue
            m.setattr(C, "FAST_CONTROL", False)
            slow = C.limit_commands(*args)
        assert calls == [False], case
        for a, b in zip(fast, slow):
            assert _bits_equal(np.asarray(a, np.float64), np.asarray(b, np.float64)), case
    assert raised == [ValueError]  # (the mask of another length)
    # a uint8 bicycle mask (values 0, 1, 2) is np.where's nonzero: the kernel reads it
    bike = rng.integers(0, 3, n).astype(np.uint8)
    _limit_same((steer, drive, brake, obs, p, replace(lim, bike=bike), True, cu), {}, monkeypatch)


@needs_c
def test_limit_kernel_rejects_what_it_cannot_read():
    n = 4
    k = C._kernel
    z, t = np.zeros(n), np.ones(n, bool)
    consts = (0.0, C.STEER_LIMIT_V_MIN, C.G, C.MAX_GRIP_USE, C.GRIP_LATERAL, C.CURVATURE_FLOOR, C.STEER_SAT_SHARE,
              C.STEER_SAT_DECEL, C.GRIP_SAT_LAT_M, C.A_LAT_FLOOR)
    args = [z] * 8 + [z, z] + [z, z, t, z, z, z] + [z, t, z, z] + [np.empty((3, n)), consts]
    k.limit(*args)
    k.limit(*args[:8], *[None] * 12, *args[20:])
    fails = _fails(k.limit, args)

    fails(0, z.astype(np.float32), TypeError, "steer: needs float64")
    fails(0, np.zeros((2, n)), ValueError, "steer needs 1 dimension")
    fails(3, np.zeros(8)[::2], TypeError, "speed: needs a C-contiguous")
    fails(6, z[:3], ValueError, r"limit: max_steer needs shape \(4,\)")
    fails(7, None, TypeError, "max_rear: needs")
    fails(9, None, ValueError, "yaw_rate and grip_torque are None together")
    fails(13, None, ValueError, "kap and err_lat are None together")
    fails(16, None, ValueError, "roll and bike are None together")
    fails(12, z, TypeError, "mask: needs bool")
    fails(17, np.zeros(n, np.int64), TypeError, "bike: needs bool")
    fails(20, np.empty((2, n)), ValueError, r"out: needs shape \(3, 4\)")
    out = np.empty((3, n))
    out.flags.writeable = False
    fails(20, out, TypeError, "out: needs a writable")
    fails(21, consts[:-1], TypeError, "constants must be a tuple of 10")
    with pytest.raises(TypeError, match="takes 22 arguments"):
        k.limit(*args[:-1])
