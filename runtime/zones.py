"""Level-of-detail zones: where agents run full physics (and, with ``[coupling] authority =
"zones"``, where physics owns their motion).

A zone is a circle of ``radius`` around every interest point (each ego vehicle, extra points
a caller passes such as viewer cameras) or a fixed region ``[x, y, r]``. Both sides read the
same definition (``[physics] lod_radius_m`` and ``lod_regions``): the physics side to split
full physics from placed agents (``physics_side.lod``), the SUMO side to decide which
vehicles are physics-authoritative (``sumo_side.coupling``). ``HYSTERESIS`` keeps an agent
driving along a boundary from flapping between the two.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

REGION_FIELDS = 3  # a detail region: centre x, centre y, radius [m]
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
        reg = np.asarray(regions, np.float64).reshape(-1, REGION_FIELDS)
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


__all__ = ["DetailZones", "HYSTERESIS", "MIN_RADIUS_M", "REGION_FIELDS", "ZONE_CHUNK"]
