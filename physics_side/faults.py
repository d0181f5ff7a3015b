"""Faults put into physics on purpose: a vehicle held stopped (a stall), for experiments
with two-way coupling (does SUMO's traffic queue behind a car that stalls in physics?) and
their tests. ``[physics] stall = ["lead@15-35"]``: agent ``lead`` brakes with its full
brake torque and gets no drive from SUMO time 15 s to 35 s; it keeps whatever physics
makes of that (it stops, or is pushed by whoever hits it). ``[physics] brake_failure =
["f.1@14-40"]``: agent ``f.1`` gets neither drive nor brakes then (it coasts on, into
whatever is ahead: a crash in physics).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from protocol.errors import ConfigError

_SPEC = re.compile(r"^(?P<id>[^@\s]+)@(?P<t0>\d+(?:\.\d*)?)-(?P<t1>\d+(?:\.\d*)?)$")


@dataclass(frozen=True)
class Stall:
    agent: str
    from_s: float  # [s] SUMO time the stall starts
    to_s: float  # [s] SUMO time it ends (the vehicle drives again)


def parse_stall(spec: str, where: str = "physics.stall") -> Stall:
    """``ID@FROM-TO`` (SUMO time [s]) -> ``Stall``; a ``ConfigError`` naming the entry otherwise."""
    m = _SPEC.match(spec)
    if m is None:
        raise ConfigError(f"{where}: expected 'ID@FROM-TO' (SUMO time in seconds, e.g. 'lead@15-35'), got {spec!r}")
    t0, t1 = float(m["t0"]), float(m["t1"])
    if t1 <= t0:
        raise ConfigError(f"{where}: {spec!r} ends before it starts")
    return Stall(m["id"], t0, t1)


def _active(faults: list[Stall], index: dict[str, int], n: int, t: float) -> np.ndarray | None:
    rows = [index[s.agent] for s in faults if s.from_s <= t < s.to_s and s.agent in index]
    if not rows:
        return None
    out = np.zeros(n, bool)
    out[rows] = True
    return out


class Faults:
    """The configured faults, asked once per SUMO step which agents they hold."""

    def __init__(self, stall: tuple[str, ...] = (), brake_failure: tuple[str, ...] = ()) -> None:
        self.stalls = [parse_stall(s) for s in stall]
        self.brake_failures = [parse_stall(s, "physics.brake_failure") for s in brake_failure]

    def stalled(self, index: dict[str, int], n: int, t: float) -> np.ndarray | None:
        """Agents (by row of ``index``) stalled at SUMO time ``t``, None when none is."""
        return _active(self.stalls, index, n, t)

    def unbraked(self, index: dict[str, int], n: int, t: float) -> np.ndarray | None:
        """Agents without drive or brakes at SUMO time ``t``, None when none is."""
        return _active(self.brake_failures, index, n, t)


__all__ = ["Faults", "Stall", "parse_stall"]
