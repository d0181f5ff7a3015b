"""Footprint geometry the contact rules share: rectangles in the plane, vectorised.

A footprint is a rectangle given by its centre (x, y) [m], heading [rad] and length and
width [m]; SUMO's position is the front bumper, ``centre`` moves it back half a length.
"""

from __future__ import annotations

import numpy as np

from runtime.native import optional_extension

CELL_MIN_M = 1e-3  # [m] smallest grid cell of ``near_pairs`` (every disc of radius 0)
# neighbour cells (dx, dy) each disc is checked against: its own and four of its eight
# neighbours (the other four see it from theirs)
_NEIGHBOURS = ((0, 0), (0, 1), (1, -1), (1, 0), (1, 1))


def centre(fx, fy, yaw, length) -> tuple[np.ndarray, np.ndarray]:
    """Centre (x, y) [m] of bodies whose front bumper is at (``fx``, ``fy``) [m], heading
    ``yaw`` [rad], ``length`` [m]."""
    return fx - 0.5 * length * np.cos(yaw), fy - 0.5 * length * np.sin(yaw)


def footprints_overlap(ax, ay, ah, al, aw, bx, by, bh, bl, bw, margin: float = 0.0) -> np.ndarray:
    """Do rectangles a and b (centre x, y [m], heading [rad], length, width [m]) overlap,
    each grown by ``margin`` [m]? Separating-axis test (``footprint_gap``), vectorised."""
    g = 2.0 * margin
    return footprint_gap(ax, ay, ah, np.asarray(al) + g, np.asarray(aw) + g,
                         bx, by, bh, np.asarray(bl) + g, np.asarray(bw) + g) <= 0.0


def footprint_gap(ax, ay, ah, al, aw, bx, by, bh, bl, bw) -> np.ndarray:
    """Separation [m] of rectangles a and b (centre x, y [m], heading [rad], length, width
    [m]) along the separating axis that parts them most: their distance where an edge faces the
    other (a lower bound corner to corner), negative where they overlap. Vectorised."""
    args = (ax, ay, ah, al, aw, bx, by, bh, bl, bw)
    if _kernel is not None and _same_1d(args):
        out = np.empty(len(ax))
        _kernel.footprint_gap(*(np.ascontiguousarray(a) for a in args), out)
        return out
    return _footprint_gap_numpy(*args)


def _same_1d(args) -> bool:
    """All float64 arrays of one dimension and one length (the C paths' input; else numpy,
    which broadcasts)."""
    n = len(args[0]) if isinstance(args[0], np.ndarray) and args[0].ndim == 1 else -1
    return n >= 0 and all(isinstance(a, np.ndarray) and a.dtype == np.float64 and a.shape == (n,) for a in args)


def _footprint_gap_numpy(ax, ay, ah, al, aw, bx, by, bh, bl, bw) -> np.ndarray:
    """``footprint_gap`` in numpy (the C path's reference, and any broadcast)."""
    ca, sa, cb, sb = np.cos(ah), np.sin(ah), np.cos(bh), np.sin(bh)
    dx, dy = np.asarray(bx) - ax, np.asarray(by) - ay
    hal, haw, hbl, hbw = 0.5 * np.asarray(al), 0.5 * np.asarray(aw), 0.5 * np.asarray(bl), 0.5 * np.asarray(bw)
    gap = np.full(np.broadcast(dx, dy, ca, cb).shape, -np.inf)
    for ux, uy in ((ca, sa), (-sa, ca), (cb, sb), (-sb, cb)):
        ra = hal * np.abs(ca * ux + sa * uy) + haw * np.abs(-sa * ux + ca * uy)
        rb = hbl * np.abs(cb * ux + sb * uy) + hbw * np.abs(-sb * ux + cb * uy)
        gap = np.maximum(gap, np.abs(dx * ux + dy * uy) - ra - rb)
    return gap


def gap_floor(x: np.ndarray, y: np.ndarray, i: np.ndarray, j: np.ndarray, half_long: np.ndarray,
              half_diag: np.ndarray) -> np.ndarray:
    """A lower bound of ``footprint_gap`` [m] of the footprints centred at (x, y) of pairs
    (i, j), from the centres alone (``half_long``: half the longer side, ``half_diag``: half
    the diagonal [m]): on one of a's two axes the centres are at least |d| / sqrt(2) apart, a
    reaches at most half its longer side along it and b at most its half diagonal, so the
    separating-axis gap is at least that. Cheap: prunes pairs before the exact test."""
    if _kernel is not None and _same_1d((x, y, half_long, half_diag)) and _int64_1d(i, j):
        out = np.empty(len(i))
        if _kernel.gap_floor(*(np.ascontiguousarray(a) for a in (x, y, i, j, half_long, half_diag)), out):
            return out
    return _gap_floor_numpy(x, y, i, j, half_long, half_diag)


def _int64_1d(i, j) -> bool:
    return all(isinstance(a, np.ndarray) and a.dtype == np.int64 and a.ndim == 1 for a in (i, j)) and i.shape == j.shape


def _gap_floor_numpy(x, y, i, j, half_long, half_diag) -> np.ndarray:
    """``gap_floor`` in numpy (the C path's reference; out-of-range indexes raise here)."""
    d = np.hypot(x[i] - x[j], y[i] - y[j]) * INV_SQRT2
    return np.maximum(d - half_long[i] - half_diag[j], d - half_long[j] - half_diag[i])


INV_SQRT2 = 1.0 / np.sqrt(2.0)


def near_pairs(x: np.ndarray, y: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i < j) of discs (centre x, y, radius r [m]) that overlap. A grid of cells
    as wide as the largest disc: every disc against the discs of its own cell and of four of
    its eight neighbours (the other four see it), O(n log n + candidates); a sweep along x
    alone took every car of a north-south street as a candidate of every other."""
    if _kernel is not None and _same_1d((x, y, r)):
        got = _kernel.near_pairs(*(np.ascontiguousarray(a) for a in (x, y, r)))
        if got is not None:  # (None: non-finite input or a grid beyond int64: numpy decides)
            ij = np.frombuffer(got, np.int64).reshape(2, -1)
            return ij[0], ij[1]
    return _near_pairs_numpy(x, y, r)


def _near_pairs_numpy(x: np.ndarray, y: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``near_pairs`` in numpy (the C path's reference)."""
    n = len(x)
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    cell = max(2.0 * float(r.max()), CELL_MIN_M)
    gx, gy = np.floor(x / cell).astype(np.int64), np.floor(y / cell).astype(np.int64)
    gx -= gx.min()
    gy -= gy.min() - 1  # (a row below the lowest: the (1, -1) neighbour's key stays apart)
    rows = int(gy.max()) + 2
    key = gx * rows + gy
    order = np.argsort(key, kind="stable")
    ks = key[order]
    pos = np.arange(n)
    ii, jj = [], []
    for dx, dy in _NEIGHBOURS:
        want = ks + dx * rows + dy
        lo = np.searchsorted(ks, want, side="left")
        hi = np.searchsorted(ks, want, side="right")
        if dx == 0 and dy == 0:
            lo = np.maximum(lo, pos + 1)  # (its own cell: the discs after it)
        cnt = np.maximum(hi - lo, 0)
        a = np.repeat(pos, cnt)
        b = np.repeat(lo, cnt) + np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        ii.append(order[a])
        jj.append(order[b])
    i, j = np.concatenate(ii), np.concatenate(jj)
    keep = np.hypot(x[i] - x[j], y[i] - y[j]) < r[i] + r[j]
    i, j = i[keep], j[keep]
    return np.minimum(i, j), np.maximum(i, j)


def overlaps_any(i: int, cx, cy, yaw, length, width, other: np.ndarray, margin: float = 0.0) -> bool:
    """Does footprint ``i`` (of the arrays ``cx``, ``cy`` [m], ``yaw`` [rad], ``length``,
    ``width`` [m]) overlap, grown by ``margin`` [m], any footprint of the mask ``other``?"""
    return bool(other.any() and footprints_overlap(
        cx[i], cy[i], yaw[i], length[i], width[i], cx[other], cy[other], yaw[other], length[other], width[other],
        margin).any())


def _libm_is_numpy(kernel) -> bool:
    """Does libm's cos / sin (the C path's) give numpy's bits here? Not where numpy uses its
    own SIMD versions (some AVX-512 builds): then the C path stays off."""
    x = np.concatenate([np.linspace(-7.0, 7.0, 4001), np.random.default_rng(0).uniform(-1e4, 1e4, 2000)])
    out = np.empty(2 * len(x))
    kernel.cos_sin(x, out)
    return bool(np.array_equal(out[:len(x)], np.cos(x)) and np.array_equal(out[len(x):], np.sin(x)))


# The C paths of ``footprint_gap``, ``gap_floor`` and ``near_pairs`` (bit-identical; no
# compiler, ``SUMOCO_PURE_PHYSICS=1`` or a numpy whose cos / sin are not libm's: the numpy
# bodies). ``FAST_FOOTPRINTS`` says which run.
_kernel = optional_extension("physics_side.policies._footprintkernel", "SUMOCO_PURE_PHYSICS")
if _kernel is not None and not _libm_is_numpy(_kernel):
    _kernel = None
FAST_FOOTPRINTS: bool = _kernel is not None

__all__ = ["centre", "footprint_gap", "footprints_overlap", "gap_floor", "near_pairs", "overlaps_any"]
