"""Vehicle geometry and index helpers shared by the world (placement) and the controllers.

Pure numpy functions with no state: the world places agents and the controllers steer them
with the same geometry, and neither has to import the other for it.
"""

from __future__ import annotations

import numpy as np

# [1] curvature x the bumper's lever over the rear axle is held below 1: the bumper's circle
# is never smaller than its lever, so asin and sqrt(1 - (k d)^2) stay finite
MAX_KAPPA_D = 0.95


def steady_state_delta(curvature: np.ndarray, d_bumper: np.ndarray, wheelbase: np.ndarray) -> np.ndarray:
    """Road-wheel angle [rad] that keeps the front bumper on a circle of the given curvature.

    The bumper's radius is sqrt(R^2 + d^2) with R the rear-axle radius: R = sqrt(1/k^2 - d^2).
    """
    k = np.asarray(curvature, np.float64)
    kd = np.clip(np.abs(k) * d_bumper, 0.0, MAX_KAPPA_D)
    with np.errstate(divide="ignore"):
        tan_d = wheelbase * np.abs(k) / np.sqrt(1.0 - kd * kd)
    return np.sign(k) * np.arctan(tan_d)


def ackermann(delta: np.ndarray, wheelbase: np.ndarray, track: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) road-wheel angles [rad] sharing the turn centre of a bicycle-model angle."""
    t = np.tan(delta)
    half = 0.5 * track * t
    lt = wheelbase * t
    left = np.arctan2(lt, wheelbase - half)
    right = np.arctan2(lt, wheelbase + half)
    # atan2 keeps the sign of t through the numerator; denominators stay > 0 for sane tracks
    return left, right


def ackermann_4ws(
    front: np.ndarray, rear: np.ndarray, wheelbase: np.ndarray, track: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(front left, front right, rear left, rear right) road-wheel angles [rad] sharing the turn
    centre of bicycle-model angles ``front`` and ``rear`` (all-wheel steering). With the rear
    axle at x = 0, the front at L and q = tan(front) - tan(rear), the centre is at
    (-tan(rear) L / q, L / q); a wheel at (x, y) points along tan = (x q + tan(rear) L) / (L - y q),
    which stays finite when q -> 0 (crabbing: every wheel parallel)."""
    tf, tr = np.tan(front), np.tan(rear)
    q = tf - tr
    half = 0.5 * track * q
    lf, lr = wheelbase * tf, wheelbase * tr
    return (np.arctan2(lf, wheelbase - half), np.arctan2(lf, wheelbase + half),
            np.arctan2(lr, wheelbase - half), np.arctan2(lr, wheelbase + half))


def concat_ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concatenated ``arange(start, start + count)`` for every pair (vectorised)."""
    counts = np.asarray(counts, np.int64)
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    rep = np.repeat(np.asarray(starts, np.int64) - np.concatenate(([0], np.cumsum(counts)[:-1])), counts)
    return rep + np.arange(total)
