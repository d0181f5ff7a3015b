"""Placement: a physical body that fell over or ran too far from SUMO is put back on its pose.

Checked last, on the agents no earlier rule placed or carries along a slide: a body rolled
or pitched beyond ``[physics] flip_deg`` is placed upright (``placements_flip``); one further
than ``[physics] divergence_m`` from its reference is placed on it
(``placements_divergence``). Each placement is logged with the agents' ids. ``place`` puts
bodies on a reference point (every placement, and kinematic bodies each tick).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from physics_side.policies.base import LOG_IDS, Cause, Step, Verdict, log
from physics_side.policies.sync import CARRY_SPEED
from physics_side.reference import ReferencePoint

COUNTED = (Cause.JUMP, Cause.DIVERGENCE, Cause.FLIP)  # the causes ``StepStats`` counts (jumped, diverged, flipped)


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


def place(world, slots: np.ndarray, idx: np.ndarray, at: ReferencePoint, max_rear: np.ndarray | None, count: bool,
          steady_turn: bool = True, yaw: np.ndarray | None = None) -> None:
    """Place agents ``idx`` (their world ``slots``) at reference point ``at`` (full-length
    arrays). Physical placements (``steady_turn``): the steady-turn pose for the path
    tangent, but a standing vehicle stands on SUMO's angle, wheels straight (in the
    steady-turn pose of a bend that starts at its bumper, a car inserted standing there stood
    37 deg off), and a vehicle that steers its rear axle (``max_rear`` [rad] > 0) is placed on
    SUMO's chord, as it drives. Kinematic ones: SUMO's own body angle, or ``yaw`` [rad] (full
    length) when given."""
    if yaw is None:
        yaw = at.tangent if steady_turn else at.yaw
    if steady_turn:
        still = at.speed[idx] < CARRY_SPEED
        if still.any():
            s_ = idx[still]
            world.place(slots[s_], at.x[s_], at.y[s_], at.yaw[s_], at.speed[s_], None, steady_turn=False, count=count)
            idx = idx[~still]
        rear = max_rear[idx] > 0
        if rear.any():
            r = idx[rear]
            world.place(slots[r], at.x[r], at.y[r], at.yaw[r], at.speed[r], at.curvature[r], steady_turn=False,
                        count=count)
            idx = idx[~rear]
    world.place(slots[idx], at.x[idx], at.y[idx], yaw[idx], at.speed[idx], at.curvature[idx],
                steady_turn=steady_turn, count=count)


def place_slide(world, slots: np.ndarray, idx: np.ndarray, at: ReferencePoint, yaw: np.ndarray, count: bool) -> None:
    """Place standing agents ``idx`` that SUMO slides sideways at ``at`` as they stand (body
    ``yaw`` [rad], full length), wheels straight: in the steady-turn pose of a bend at the
    bumper a stopped 6.5 m van turned 11 deg, its rear into passing traffic; on SUMO's angle
    (which turns with the lane change, 38 deg while standing) a car's rear swung into the
    next lane."""
    place(world, slots, idx, replace(at, curvature=np.zeros_like(at.curvature)), None, count, steady_turn=False,
          yaw=yaw)


def act(world, slots: np.ndarray, s: Step, v: Verdict, max_rear: np.ndarray, step: int) -> np.ndarray:
    """Place every agent the verdict names (its world ``slots``; a slide's start as it
    stands) at the reference, count the placements by cause in ``v`` (``placements_<cause>``)
    and log flips and divergences of SUMO step ``step``; returns who was placed (bool)."""
    placed = v.cause != Cause.NONE
    if placed.any():
        idx = np.flatnonzero(placed)
        slide = v.sliding[idx]
        if slide.any():
            place_slide(world, slots, idx[slide], s.held, s.obs.yaw, count=True)
        place(world, slots, idx[~slide], s.held, max_rear, count=True)
    for cause in (Cause.SPAWN, Cause.JUMP, Cause.DIVERGENCE, Cause.FLIP):
        v.count(f"placements_{cause.name.lower()}", v.placed(cause).sum())
    diverged, flipped = np.flatnonzero(v.placed(Cause.DIVERGENCE)), np.flatnonzero(v.placed(Cause.FLIP))
    if len(diverged) or len(flipped):
        log.warning("step %d: placed %d diverged %s, %d flipped %s", step, len(diverged),
                    [s.ids[i] for i in diverged][:LOG_IDS], len(flipped), [s.ids[i] for i in flipped][:LOG_IDS])
    return placed


__all__ = ["act", "detect_divergence", "detect_flip", "diverged", "flipped", "place", "place_slide", "upright"]
