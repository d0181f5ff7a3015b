"""Motorcycles and mopeds (SUMO's default vTypes, OTHER on the wire) through the daemon's code
path (``Fleet``, ``sumoco.analysis.experiments.track_reference``) at SUMO's 0.05 s steps: pulling
away, stopping and junction turns at SUMO's own accelerations stay upright and on its track.

Measured before the fix (the bicycle's stabiliser gains on a 280 kg model, 85 % front brakes,
mu 1.2 tyres, leaning up to ~48 deg): in every turn below both leant *out* of the turn (roll
-45 deg in a right turn), reached 61-63 deg at 12 m/s (a flip) and were 3.7 m off SUMO's
track at 15 m/s; the motorcycle stopping at 10 m/s^2 while SUMO drifted it 0.3 m sideways
locked its unloaded rear wheel, slid and fell (roll 60 deg). Pulling away and the moped's
7 m/s^2 stop passed.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from sumoco.analysis import experiments as E
from physics_side.config import PhysicsConfig, PhysicsSettings
from protocol.messages import AgentClass

# SUMO's default vTypes: (length, width) [m], accel, decel [m/s^2]
SUMO = {"motorcycle": ((2.2, 0.9), 6.0, 10.0), "moped": ((2.1, 0.78), 1.1, 7.0)}
STEP_S = 0.05  # [s] the SUMO step of the scenarios where they flipped


def _run(vclass: str, traj: E.Trajectory) -> dict[str, np.ndarray]:
    (length, width), _, _ = SUMO[vclass]
    settings = PhysicsSettings(replace(PhysicsConfig(), sumo_step_s=STEP_S))
    return E.track_reference("default", AgentClass.OTHER, traj, settings=settings, vclass=vclass, length=length,
                             width=width)


def _profile(duration: float, v0: float, phases: list[tuple[float, float, float]], hz: float = 1000.0):
    """t, s, v, a of a speed profile: constant accelerations ``(t0, t1, a)`` [s, s, m/s^2]."""
    t = np.arange(0.0, duration + 1e-9, 1.0 / hz)
    a = np.zeros_like(t)
    for t0, t1, acc in phases:
        a[(t >= t0) & (t < t1)] = acc
    v = np.maximum(v0 + np.concatenate(([0.0], np.cumsum(0.5 * (a[1:] + a[:-1]) / hz))), 0.0)
    s = np.concatenate(([0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) / hz)))
    return t, s, v, a


def _placements(r) -> tuple[int, int]:
    return int(r["placements_flip"][0]), int(r["placements_divergence"][0])


@pytest.mark.parametrize("vclass", list(SUMO))
def test_two_wheelers_pull_away_from_rest_to_15_m_s_upright(vclass):
    _, accel, _ = SUMO[vclass]
    t1 = 1.0 + 15.0 / accel
    t, s, v, a = _profile(t1 + 3.0, 0.0, [(1.0, t1, accel)])
    xy = np.c_[100.0 + np.arange(0.0, s[-1] + 90.0), np.full(int(np.ceil(s[-1] + 90.0)), 100.0)]
    r = _run(vclass, E.Trajectory(xy, t, s, v, a))
    assert r["speed"].max() == pytest.approx(15.0, abs=0.6)
    assert np.abs(r["roll"]).max() < 5.0 and np.abs(r["pitch"]).max() < 5.0  # no wheelie, no fall
    assert r["err"].max() < 0.3, r["err"].max()
    assert _placements(r) == (0, 0)


@pytest.mark.parametrize("vclass", list(SUMO))
def test_two_wheelers_stop_from_15_m_s_at_sumo_decel_upright(vclass):
    """SUMO stops them at its decel (motorcycle 10 m/s^2) while its sublane model moves them
    0.3 m sideways: the rear wheel, nearly unloaded, must not lock and slide out."""
    _, _, decel = SUMO[vclass]
    t1 = 1.0 + 15.0 / decel
    t, s, v, a = _profile(t1 + 2.0, 15.0, [(1.0, t1, -decel)])
    x = np.arange(0.0, s[-1] + 90.0, 0.25)
    u = np.clip((x - 15.0) / 10.0, 0.0, 1.0)
    xy = np.c_[100.0 + x, 100.0 + 0.3 * 0.5 * (1.0 - np.cos(np.pi * u))]
    r = _run(vclass, E.Trajectory(xy, t, s, v, a))
    assert r["speed"][-1] < 0.3
    assert np.abs(r["roll"]).max() < 15.0, np.abs(r["roll"]).max()
    assert np.abs(r["pitch"]).max() < 5.0  # no stoppie
    assert r["err"].max() < 0.4, r["err"].max()
    assert _placements(r) == (0, 0)


@pytest.mark.parametrize("vclass", list(SUMO))
@pytest.mark.parametrize("v, radius", [(8.0, 7.0), (10.0, 10.0), (12.0, 14.0), (15.0, 25.0)])
def test_two_wheelers_lean_into_a_90_deg_junction_turn(vclass, v, radius):
    """SUMO's junction turns at ~9-10 m/s^2 of lateral acceleration (more than a rider leans
    for): the model leans into the turn (right turn: right side down, roll > 0) through the
    arc, at most 50 deg, comes back upright after it, and stays within a metre of SUMO's track."""
    lead_in = 30.0
    traj = E.turn90(radius=radius, v=v, lead_in=lead_in, lead_out=120.0, right=True)
    r = _run(vclass, traj)
    roll, pitch = r["roll"], r["pitch"]
    s = np.interp(r["t"], traj.t, traj.s)  # the reference's bumper along the path [m]
    arc = (s > lead_in + 0.5 * v) & (s < lead_in + 0.5 * np.pi * radius)  # from 0.5 s into the arc
    after = s > lead_in + 0.5 * np.pi * radius
    assert np.abs(roll).max() < 50.0, np.abs(roll).max()
    assert np.abs(pitch).max() < 5.0
    assert roll[arc].min() > 0.0 and roll[arc].max() > 15.0, (roll[arc].min(), roll[arc].max())  # never out of it
    assert roll[after].min() > -25.0 and abs(roll[-1]) < 10.0, (roll[after].min(), roll[-1])  # the exit's swing
    assert r["err"].max() < 1.0, r["err"].max()
    assert _placements(r) == (0, 0)


def test_stabiliser_gains_and_lean_limit_per_agent():
    """The roll stabiliser takes per-agent gains and lean limits: a turn asking 1.02 g leans a
    motorcycle to its 42 deg (a bicycle's default target stops at atan 0.6 = 31 deg)."""
    from physics_side import control as C
    from physics_side import models as M

    bike, moto = M.default_spec(AgentClass.BICYCLE), M.spec_for_size("motorcycle", 2.2, 0.9)
    assert moto.roll_stiffness / bike.roll_stiffness == pytest.approx(1.73, abs=0.02)
    assert 1500.0 > 1.7 * bike.roll_stiffness  # the configured gain, with a margin over gravity
    z, v, r = np.zeros(2), np.full(2, 10.0), np.full(2, 1.0)
    kp = np.array([1000.0, 2000.0])
    lean = np.array([0.6, np.tan(np.radians(42.0))])
    t = C.roll_stabiliser(z, z, v, r, kp, 0.0, np.full(2, 1e4), lean)
    assert t == pytest.approx(-kp * np.arctan(lean))  # left turn: left side down (roll < 0)
    assert C.roll_stabiliser(z[:1], z[:1], v[:1], r[:1], 1000.0, 0.0, np.full(1, 1e4))[0] == pytest.approx(
        -1000.0 * np.arctan(0.6))
