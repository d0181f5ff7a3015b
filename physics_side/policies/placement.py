"""Placement: a physical body that fell over or ran too far from SUMO is put back on its pose.

Checked last, on the agents no earlier rule placed or carries along a slide: a body rolled
or pitched beyond ``[physics] flip_deg`` is placed upright (``placements_flip``); one further
than ``[physics] divergence_m`` from its reference is placed on it
(``placements_divergence``). Each placement is logged with the agents' ids.
"""

from __future__ import annotations

import math

import numpy as np

from physics_side.policies.base import Cause, Step, Verdict


def flipped(roll: np.ndarray, pitch: np.ndarray, flip_deg: float) -> np.ndarray:
    """Bodies rolled (``roll`` [rad]) or pitched (``pitch`` [rad]) beyond ``flip_deg`` [deg]."""
    flip = math.radians(flip_deg)
    return (np.abs(roll) > flip) | (np.abs(pitch) > flip)


def upright(roll: np.ndarray, pitch: np.ndarray, flip_deg: float) -> np.ndarray:
    """Bodies within ``flip_deg`` [deg] of upright in roll and pitch (the contacts that count as collisions)."""
    flip = math.radians(flip_deg)
    return (np.abs(roll) < flip) & (np.abs(pitch) < flip)


def diverged(dist: np.ndarray, divergence_m: float) -> np.ndarray:
    """Bodies further than ``divergence_m`` [m] (``dist`` [m]) from their reference."""
    return dist > divergence_m


def detect_flip(s: Step, v: Verdict) -> None:
    v.place(v.free() & flipped(s.obs.roll, s.obs.pitch, s.cfg.flip_deg), Cause.FLIP)


def detect_divergence(s: Step, v: Verdict) -> None:
    v.place(v.free() & diverged(s.dist, s.cfg.divergence_m), Cause.DIVERGENCE)


__all__ = ["detect_divergence", "detect_flip", "diverged", "flipped", "upright"]
