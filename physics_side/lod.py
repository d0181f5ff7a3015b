"""Physics level of detail: which agents run full MuJoCo dynamics and which are placed.

Agents within ``radius`` of an interest point (every ego vehicle, the extra points a
caller passes, e.g. viewer cameras) or inside a configured region run full physics in
the fleet; the rest never enter MuJoCo: ``DetailSplit`` keeps them apart and publishes
them on their interpolated SUMO pose (mode KINEMATIC in the state: no slot, no
controller, no MuJoCo step). An agent switches back to full physics only once it is
``HYSTERESIS`` of the radius inside, so an agent driving along the boundary does not
flap between modes; entering full physics is a spawn in the steady-turn state of its
path at its reference pose, so it starts without a transient.
"""

from __future__ import annotations

import operator
from dataclasses import dataclass, replace

import numpy as np

from physics_side.config import LOD_REGION_FIELDS
from physics_side.reference import Reference
from physics_side.shard import subset
from protocol.frames import yaw_to_sumo_angle
from protocol.messages import AgentBatch, AgentFlag, AgentMode, PhysicsAgents, StepMessage

HYSTERESIS = 0.9  # full physics within 0.9 r, kinematic beyond r, unchanged between
ZONE_CHUNK = 256  # [zones] per pass of the distance test: temporaries of n agents x this at most
MIN_RADIUS_M = 1e-9  # [m] a zone radius divides as at least this


@dataclass(frozen=True)
class DetailZones:
    """Where agents run full physics (see module docstring)."""

    radius: float
    """Around each interest point [m]; 0 = every agent runs full physics."""
    regions: np.ndarray
    """(k, 3) fixed regions: centre x, centre y, radius [m]."""

    @classmethod
    def from_config(cls, radius_m: float, regions) -> "DetailZones | None":
        """``None`` when LOD is off (radius 0 and no regions)."""
        reg = np.asarray(regions, np.float64).reshape(-1, LOD_REGION_FIELDS)
        if radius_m <= 0 and len(reg) == 0:
            return None
        return cls(float(radius_m), reg)

    def full(
        self, x: np.ndarray, y: np.ndarray, ego: np.ndarray, was_full: np.ndarray | None = None,
        points: np.ndarray | None = None,
    ) -> np.ndarray:
        """Which agents at (x, y) [m] run full physics (bool, length n).

        ``ego``: interest agents (always full, and centres of the radius); ``was_full``:
        the previous decision per agent (hysteresis; None = no history); ``points``:
        (m, 2) extra interest points [m].
        """
        rel = self.rel(x, y, ego, points)
        inner, outer = rel < HYSTERESIS**2, rel < 1.0
        full = inner if was_full is None else np.where(was_full, outer, inner)
        return full | np.asarray(ego, bool)

    def rel(self, x: np.ndarray, y: np.ndarray, ego: np.ndarray, points: np.ndarray | None = None) -> np.ndarray:
        """Squared distance to the nearest zone centre in units of its radius (< 1: inside;
        inf without zones), per agent."""
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        n = len(x)
        ego = np.asarray(ego, bool)
        centres = np.column_stack([x[ego], y[ego]])
        if points is not None and len(points):
            centres = np.concatenate([centres, np.asarray(points, np.float64).reshape(-1, 2)])
        cx = np.concatenate([centres[:, 0], self.regions[:, 0]])
        cy = np.concatenate([centres[:, 1], self.regions[:, 1]])
        r = np.concatenate([np.full(len(centres), self.radius), self.regions[:, 2]])
        rel = np.full(n, np.inf)
        if n == 0 or len(r) == 0:
            return rel
        for k in range(0, len(r), ZONE_CHUNK):
            z = slice(k, k + ZONE_CHUNK)
            d2 = (x[:, None] - cx[None, z]) ** 2 + (y[:, None] - cy[None, z]) ** 2
            rel = np.minimum(rel, (d2 / np.maximum(r[None, z], MIN_RADIUS_M) ** 2).min(axis=1))
        return rel


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
        full |= ego
        riding = (flags & AgentFlag.INSIDE_VEHICLE) != 0
        far = np.flatnonzero(~full & ~riding)
        self._not_full = set(_take(a.ids, np.flatnonzero(~full)))
        self.far.update(msg.time, subset(a, far))
        return replace(msg, agents=subset(a, np.flatnonzero(full)))

    def snapshot(self, near: PhysicsAgents, t: float) -> PhysicsAgents:
        """The fleet's agents followed by the far ones at physics time ``t`` [s]."""
        return concat_agents(near, self.far.snapshot(t))


__all__ = ["DetailSplit", "DetailZones", "FarAgents", "HYSTERESIS", "concat_agents"]
