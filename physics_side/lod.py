"""Physics level of detail: which agents run full MuJoCo dynamics and which are placed.

Agents within ``radius`` of an interest point (every ego vehicle, the extra points a
caller passes, e.g. viewer cameras) or inside a configured region run full physics in
the fleet; the rest never enter MuJoCo: ``DetailSplit`` keeps them apart and publishes
them on their interpolated SUMO pose (mode KINEMATIC in the state: no slot, no
controller, no MuJoCo step). An agent switches back to full physics only once it is
``HYSTERESIS`` of the radius inside, so an agent driving along the boundary does not
flap between modes; entering full physics is a spawn in the steady-turn state of its
path at its reference pose, so it starts without a transient. The zones themselves
(``DetailZones``) are in ``runtime.zones``: the SUMO side reads the same ones for
``[coupling] authority = "zones"``, and a physics-authoritative vehicle always runs full
physics here.
"""

from __future__ import annotations

import operator
from dataclasses import replace

import numpy as np

from physics_side.reference import Reference
from physics_side.shard import subset
from protocol.frames import yaw_to_sumo_angle
from protocol.messages import AgentBatch, AgentFlag, AgentMode, PhysicsAgents, StepMessage
from runtime.zones import HYSTERESIS, DetailZones


class FarAgents:
    """Agents outside every zone: their SUMO trajectory extrapolated, nothing simulated."""

    def __init__(self, max_extrapolation_s: float = 0.3) -> None:
        self.max_extrapolation_s = float(max_extrapolation_s)
        self.ids: list[str] = []
        self.cls = np.zeros(0, np.uint8)
        self.ref: Reference | None = None

    @property
    def n(self) -> int:
        return len(self.ids)

    def update(self, t_k: float, agents: AgentBatch) -> None:
        """The far agents of the step at SUMO time ``t_k`` [s]."""
        self.ids = list(agents.ids)
        self.cls = np.asarray(agents.cls, np.uint8)
        self.ref = Reference.from_batch(t_k, agents) if agents.n else None

    def snapshot(self, t: float) -> PhysicsAgents:
        """Their state at physics time ``t`` [s] (mode KINEMATIC)."""
        n = self.n
        f32 = np.float32
        z = np.zeros(n, f32)
        if self.ref is None:
            x = y = np.zeros(n)
            heading = speed = z
        else:
            r = self.ref.at(min(max(t - self.ref.t_k, 0.0), self.max_extrapolation_s))
            x, y = np.asarray(r.x, np.float64), np.asarray(r.y, np.float64)
            heading, speed = yaw_to_sumo_angle(r.yaw).astype(f32), np.asarray(r.speed, f32)
        return PhysicsAgents(
            ids=list(self.ids), cls=self.cls, mode=np.full(n, AgentMode.KINEMATIC, np.uint8), x=x, y=y, z=z,
            heading=heading, roll=z, pitch=z, speed=speed, steer=z, drive=z, brake=z, err_lon=z, err_lat=z,
        )


def _take(ids: list[str], rows: np.ndarray) -> tuple[str, ...]:
    """``ids`` at ``rows`` (one C call)."""
    if len(rows) == 0:
        return ()
    got = operator.itemgetter(*rows.tolist())(ids)
    return got if len(rows) > 1 else (got,)


def concat_agents(a: PhysicsAgents, b: PhysicsAgents) -> PhysicsAgents:
    """``a`` then ``b`` in one batch."""
    if not b.ids:
        return a
    cols = {k: np.concatenate([getattr(a, k), getattr(b, k)]) for k in (
        "cls", "mode", "x", "y", "z", "heading", "roll", "pitch", "speed", "steer", "drive", "brake", "err_lon",
        "err_lat")}
    return replace(a, ids=[*a.ids, *b.ids], **cols)


class DetailSplit:
    """Per step: full-detail agents go on to the fleet, far ones to ``FarAgents``."""

    def __init__(self, zones: DetailZones, max_extrapolation_s: float = 0.3) -> None:
        self.zones = zones
        self.far = FarAgents(max_extrapolation_s)
        self._not_full: set[str] = set()  # ids outside full detail in the previous step
        self.points: np.ndarray | None = None  # (m, 2) [m] extra interest points (viewer cameras)

    def apply(self, msg: StepMessage) -> StepMessage:
        """``msg`` with only the agents in full detail (the far ones are kept here)."""
        a = msg.agents
        flags = np.asarray(a.flags)
        ego = (flags & AgentFlag.EGO) != 0
        rel = self.zones.rel(a.x, a.y, ego, self.points)
        full = rel < HYSTERESIS**2
        # Only agents between 0.9 r and r keep their previous mode (an agent not seen
        # before counts as full): one set lookup for those few, not a dict of every agent.
        band = np.flatnonzero((rel < 1.0) & ~full)
        if len(band):
            kept = self._not_full
            full[band] = ~np.fromiter(map(kept.__contains__, _take(a.ids, band)), bool, len(band))
        # a physics-authoritative vehicle is driven by physics wherever it is (SUMO follows it)
        full |= ego | ((flags & AgentFlag.PHYSICS_AUTHORITY) != 0)
        riding = (flags & AgentFlag.INSIDE_VEHICLE) != 0
        far = np.flatnonzero(~full & ~riding)
        self._not_full = set(_take(a.ids, np.flatnonzero(~full)))
        self.far.update(msg.time, subset(a, far))
        return replace(msg, agents=subset(a, np.flatnonzero(full)))

    def snapshot(self, near: PhysicsAgents, t: float) -> PhysicsAgents:
        """The fleet's agents followed by the far ones at physics time ``t`` [s]."""
        return concat_agents(near, self.far.snapshot(t))


__all__ = ["DetailSplit", "DetailZones", "FarAgents", "HYSTERESIS", "concat_agents"]
