"""The one interface of the policies: a ``Step`` they read, a ``Verdict`` they write.

``Fleet.apply_step`` builds a ``Step`` (this SUMO sample, the previous one of each agent,
the bodies as physics has them) and runs every detect-phase policy of the table
(``physics_side.policies.POLICIES``) in order over it; each one claims agents in the
``Verdict``: placed at SUMO's pose for a cause (first claim wins), carried (shown kinematic
on SUMO's poses), or allowed to roll back. The fleet then acts on the verdict.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np

from protocol.messages import AgentMode

log = logging.getLogger("physics_side.fleet")  # the policies log as the fleet: tools quiet its placements by name
LOG_IDS = 10  # agents named in one log line


class Cause(IntEnum):
    """Why an agent is placed at SUMO's pose at this sample (``placements_<name>``)."""

    NONE = 0
    SPAWN = 1
    JUMP = 2
    FLIP = 3
    DIVERGENCE = 4


@dataclass(frozen=True)
class Previous:
    """Each agent's policy state from the previous step (False / -inf for agents without one)."""

    carried: np.ndarray
    """Carried for a manoeuvre or a contact, bool."""
    guarded: np.ndarray
    """... the carry is the contact guard's, bool."""
    sliding: np.ndarray
    """Carried along SUMO's sideways slide while standing, bool."""
    ghost: np.ndarray
    """Without agent contact until clear, bool."""
    jump_t: np.ndarray
    """SUMO time [s] it was last teleported or placed for a jump."""


def realign_mask(values: np.ndarray, prev: np.ndarray) -> np.ndarray:
    """Per-agent flags of the previous step in this step's order (row ``prev`` of each agent,
    -1: none, which gets False)."""
    if not len(values):
        return np.zeros(len(prev), bool)
    return (prev >= 0) & values[np.maximum(prev, 0)]


def realign(values: np.ndarray, prev: np.ndarray, missing: float) -> np.ndarray:
    """Per-agent numbers of the previous step in this step's order; ``missing`` where -1."""
    return np.where(prev >= 0, values[np.maximum(prev, 0)] if len(values) else missing, missing)


@dataclass(frozen=True)
class Step:
    """One SUMO step as the policies see it: arrays over this step's agents (the fleet's
    order), the previous sample of each, the bodies before any placement."""

    cfg: Any
    """``PhysicsConfig``: the rules' switches and thresholds that are settings."""
    ctl: Any
    """``ControlSettings``: the controllers' settings (standing, rolling back)."""
    t: float
    """SUMO time of the sample [s]."""
    gap: float
    """[s] since the previous sample (0 without one)."""
    step_length: float
    """[s]."""
    interpolating: bool
    """Physics runs between the previous and this sample (long steps)."""
    tau: float
    """[s] physics time past the reference's start (placements use the reference then)."""
    horizon: float
    """``tau`` bounded by the extrapolation limit [s]."""
    ids: list[str]
    index: dict[str, int]
    prev: np.ndarray
    """Row of each agent in the previous step, -1: none (new, retyped, or no usable sample)."""
    is_new: np.ndarray
    """Spawned this step (bool)."""
    flags: np.ndarray
    """``AgentFlag`` bits of the sample."""
    kind: np.ndarray
    """Model kind (``models.KIND_*``)."""
    mode: np.ndarray
    """``AgentMode`` by preset and ego, before any carry."""
    authoritative: np.ndarray
    """Physics owns these (two-way coupling): never carried, bool."""
    x: np.ndarray
    """SUMO front bumper x [m] at the sample."""
    y: np.ndarray
    """[m]."""
    speed: np.ndarray
    """SUMO speed [m/s] at the sample."""
    yaw_rate: np.ndarray
    """SUMO's turn rate [rad/s] over its last two samples."""
    kin_rate: np.ndarray
    """[rad/s] the rate kinematic bodies turn at between samples (``carry_pose.turn_rate``)."""
    old: Any
    """``Reference`` of the previous sample (rows ``prev``), None when there is none."""
    ref: Any
    """``Reference`` physics follows over this step."""
    held: Any
    """``ReferencePoint`` where placements put bodies (the reference at ``tau``)."""
    obs: Any
    """``Observation`` of the bodies before any placement."""
    e_lon: np.ndarray
    """Tracking error along [m] against ``held``."""
    e_lat: np.ndarray
    """... sideways [m]."""
    dist: np.ndarray
    """hypot(e_lon, e_lat) [m]."""
    side_rate: np.ndarray
    """SUMO's sideways speed off its lane's centre line [m/s] (0: none, or a hop)."""
    slow: np.ndarray
    """Slow at both samples (``sync.hops``), bool."""
    hop: np.ndarray
    """Moved sideways at once (``sync.hops``), bool."""
    ped_hop: np.ndarray
    """Pedestrian moved further than it walks (``sync.pedestrian_hops``), bool."""
    length: np.ndarray
    """Body length [m] (the model's)."""
    width: np.ndarray
    """Body width [m]."""
    height: np.ndarray
    """Body height [m]."""
    sumo_len: np.ndarray
    """SUMO's length [m]."""
    sumo_wid: np.ndarray
    """SUMO's width [m]."""
    limits: Any
    """``control.VehicleLimits`` of the agents."""
    reach: np.ndarray
    """Tightest path curvature [1/m] each vehicle's bumper follows (``control.bumper_curvature_limit``)."""
    before: Previous
    """Policy state of the previous step."""
    guard: Any
    """``contacts.ContactGuard``: the guarded pairs (kept across steps)."""

    @property
    def n(self) -> int:
        return len(self.ids)


@dataclass
class Verdict:
    """What the detect phase decided for each agent of a ``Step``."""

    cause: np.ndarray
    """``Cause`` (int8) each agent is placed for at this sample; NONE: not placed."""
    mode: np.ndarray
    """``AgentMode`` after the carries (uint8)."""
    manoeuvre: np.ndarray
    """Carried through a manoeuvre it cannot drive, bool (``carry``)."""
    guard: np.ndarray
    """Carried to keep a contact SUMO does not have from happening, bool (``contacts``)."""
    sliding: np.ndarray
    """Carried along SUMO's sideways slide while standing, bool (``sync``)."""
    rolls_back: np.ndarray
    """May roll back to a standing reference it came to rest past, bool (``carry``)."""
    counts: dict[str, int] = field(default_factory=dict)
    """Counter increments (``summary.json`` ``counters.*``)."""

    @classmethod
    def empty(cls, s: Step) -> "Verdict":
        n = s.n
        return cls(cause=np.zeros(n, np.int8), mode=s.mode.copy(), manoeuvre=np.zeros(n, bool),
                   guard=np.zeros(n, bool), sliding=np.zeros(n, bool), rolls_back=np.ones(n, bool))

    @property
    def physical(self) -> np.ndarray:
        """Driven by physics after the carries, bool."""
        return self.mode == AgentMode.PHYSICAL

    def placed(self, cause: Cause) -> np.ndarray:
        return self.cause == cause

    def place(self, mask: np.ndarray, cause: Cause) -> None:
        """Place the agents of ``mask`` for ``cause`` unless an earlier rule claimed them."""
        take = mask & (self.cause == Cause.NONE)
        self.cause[take] = cause

    def carry(self, mask: np.ndarray) -> None:
        """Show the agents of ``mask`` kinematic on SUMO's poses this step."""
        if mask.any():
            self.mode = np.where(mask, AgentMode.KINEMATIC, self.mode).astype(np.uint8)

    def free(self) -> np.ndarray:
        """Physical agents no rule has placed or carried along a slide, bool."""
        return (self.cause == Cause.NONE) & ~self.sliding & self.physical

    def count(self, name: str, k: int) -> None:
        self.counts[name] = self.counts.get(name, 0) + int(k)


__all__ = ["LOG_IDS", "Cause", "Previous", "Step", "Verdict", "log", "realign", "realign_mask"]
