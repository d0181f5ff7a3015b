"""Physics level of detail: which agents run full MuJoCo dynamics and which are placed.

Agents within ``radius`` of an interest point (every ego vehicle, the extra points a
caller passes, e.g. viewer cameras) or inside a configured region run full physics;
the rest are placed kinematically on their interpolated SUMO pose (mode KINEMATIC in
the published state: cheap, no controller). An agent switches back to full physics
only once it is ``HYSTERESIS`` of the radius inside, so an agent driving along the
boundary does not flap between modes; the switch to physics is a counted placement in
the steady-turn state of its path, so it starts without a transient.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

HYSTERESIS = 0.9  # full physics within 0.9 r, kinematic beyond r, unchanged between


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
        reg = np.asarray(regions, np.float64).reshape(-1, 3)
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
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        n = len(x)
        centres = np.column_stack([x[ego], y[ego]])
        if points is not None and len(points):
            centres = np.concatenate([centres, np.asarray(points, np.float64).reshape(-1, 2)])
        cx = np.concatenate([centres[:, 0], self.regions[:, 0]])
        cy = np.concatenate([centres[:, 1], self.regions[:, 1]])
        r = np.concatenate([np.full(len(centres), self.radius), self.regions[:, 2]])
        if n == 0 or len(r) == 0:
            return np.asarray(ego, bool).copy() if n else np.zeros(0, bool)
        # distance to each zone's edge in units of its radius: < 1 inside
        rel = np.full(n, np.inf)
        for k in range(0, len(r), 256):  # bounded temporaries: n x 256 at most
            d2 = (x[:, None] - cx[None, k:k + 256]) ** 2 + (y[:, None] - cy[None, k:k + 256]) ** 2
            rel = np.minimum(rel, (d2 / np.maximum(r[None, k:k + 256], 1e-9) ** 2).min(axis=1))
        inner, outer = rel < HYSTERESIS**2, rel < 1.0
        full = inner if was_full is None else np.where(was_full, outer, inner)
        return full | np.asarray(ego, bool)


__all__ = ["DetailZones", "HYSTERESIS"]
