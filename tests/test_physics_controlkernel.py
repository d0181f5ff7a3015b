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
"""

from __future__ import annotations

import copy
import itertools
from dataclasses import replace

import numpy as np
import pytest

from physics_side import control as C
from physics_side.config import DefaultControl, PhysicsSettings
from physics_side.daemon import build_fleet
from physics_side.reference import PathPoint, Reference
from protocol.codec import decode_as, encode
from protocol.messages import StepMessage
from synthetic.traffic import circle_traffic
from tests.test_physics_pathkernel import _bits_equal, _random_paths

needs_c = pytest.mark.skipif(not C.FAST_CONTROL, reason="physics_side._controlkernel not built, SUMOCO_PURE_PHYSICS "
                                                         "set, or numpy's math is not libm's")
FIELDS = ("steer", "drive", "brake", "aux")
CONTROL_DEFAULT = C.control_default  # (the fleet's calls are spied on below)
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


def _same(args: tuple, kwargs: dict, state: C.ControlState, monkeypatch) -> None:
    """The C path runs (it takes these inputs) and gives the numpy body's bits."""
    calls = []
    real = C._control_default_c

    def spy(*a):
        out = real(*a)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(C, "_control_default_c", spy)
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


def _fleet_ticks(monkeypatch, step_s: float, reference: str, n: int = 40) -> int:
    """A fleet of ``n`` cars on MuJoCo following circle traffic whose speed changes step by
    step (cruise, brake, stand, start), then SUMO gone; every control_default call compared."""
    s = PhysicsSettings()
    s = replace(s, physics=replace(s.physics, initial_slots={"passenger": n + 8}, preset="default", presets={},
                                   sumo_step_s=step_s, reference=reference))
    fleet = build_fleet(s)
    seen = []

    def spy(*args, **kwargs):
        args = list(args)
        state = args.pop(6)
        _same(tuple(args), kwargs, state, monkeypatch)
        seen.append(kwargs.get("rolls_back") is not None)
        return CONTROL_DEFAULT(*args[:6], state, *args[6:], **kwargs)

    speeds = [10.0, 10.0, 6.0, 2.0, 0.1, 0.0, 0.0, 0.0, 3.0, 8.0, 8.0]
    with monkeypatch.context() as m:
        m.setattr(C, "control_default", spy)
        for k, v in enumerate(speeds):
            msg = decode_as(encode(circle_traffic(n, k, step_s, speed=v)), StepMessage)
            fleet.apply_step(msg)
            for _ in range(int(round(step_s * 50))):
                fleet.tick()
        fleet.begin_stop()
        for _ in range(10):
            fleet.tick()
    return len(seen)


@needs_c
@pytest.mark.parametrize("step_s, reference", [(0.1, "extrapolate"), (0.5, "interpolate")])
def test_a_real_fleet_on_mujoco(monkeypatch, step_s, reference):
    assert _fleet_ticks(monkeypatch, step_s, reference) > 50


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

    def fails(i, value, exc, match):
        a = list(args)
        a[i] = value
        with pytest.raises(exc, match=match):
            k.control(*a)

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
