"""The report's reference between SUMO samples: along the curve the samples' headings describe."""

from __future__ import annotations

import numpy as np

from sumoco.analysis.summary import hermite


def test_reference_between_samples_follows_the_curve_not_the_chord():
    R, v = 10.0, 7.0  # a 10 m turn at 7 m/s, sampled at 1 s steps
    t = np.arange(0.0, 3.0, 1.0)
    th = v * t / R
    x, y = R * np.sin(th), R * (1 - np.cos(th))
    pt = np.linspace(0.0, 2.0, 41)
    hx, hy = hermite(pt, t, x, y, th)
    true = v * pt / R
    err = np.hypot(hx - R * np.sin(true), hy - R * (1 - np.cos(true)))
    chord = np.hypot(np.interp(pt, t, x) - R * np.sin(true), np.interp(pt, t, y) - R * (1 - np.cos(true)))
    assert err.max() < 0.03 and chord.max() > 0.5
    # samples are hit exactly; a straight line and a standing agent stay straight
    assert np.allclose(hermite(t, t, x, y, th), (x, y))
    sx, sy = hermite(pt, t, 5.0 * t, np.zeros(3), np.zeros(3))
    assert np.allclose(sx, 5.0 * pt) and np.allclose(sy, 0.0)
    zx, zy = hermite(pt, t, np.ones(3), np.ones(3), np.array([0.0, 1.0, 2.0]))
    assert np.allclose(zx, 1.0) and np.allclose(zy, 1.0)


def test_error_at_samples_ignores_motion_between_samples():
    """At SUMO's sample times the reference is exact: a physics agent on every sample but
    accelerating smoothly in between (not at SUMO's constant speed per step) has no error there."""
    from protocol.messages import AgentMode
    from sumoco.analysis.summary import PhysTable, RefTable, sample_errors

    rt = np.arange(0.0, 4.0, 1.0)
    s = 0.5 * 2.0 * rt**2  # 2 m/s^2 from rest
    n = len(rt)
    ref = RefTable(t=rt, aid=np.zeros(n, np.int64), x=s, y=np.zeros(n), angle=np.full(n, 90.0), speed=2.0 * rt,
                   lane=np.zeros(n, np.int64), cls=np.zeros(n, np.int64), flags=np.zeros(n, np.int64))
    pt = np.arange(0.02, 3.0001, 0.02)
    m = len(pt)
    z = np.zeros(m)
    ph = PhysTable(t=pt, aid=np.zeros(m, np.int64), cls=np.zeros(m, np.int64),
                   mode=np.full(m, AgentMode.PHYSICAL, np.int64), x=pt**2, y=z, heading=z, speed=2 * pt, steer=z,
                   drive=z, brake=z)
    err, cls = sample_errors(ref, ph)
    assert len(err) == 3 and err.max() < 1e-3  # samples at 1, 2, 3 s (0 s is before the first state)
    ph.x = ph.x + 0.4
    assert np.allclose(sample_errors(ref, ph)[0], 0.4)
