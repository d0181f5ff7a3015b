"""Per-agent references from SUMO steps, vectorised over all agents.

A SUMO step gives, per agent, a sample at time ``t_k`` (front-bumper position, angle,
speed, acceleration, look-ahead point) and the *path ahead*, a polyline starting at the
front bumper. ``PathSet`` evaluates many ragged polylines at once by arc length
(one ``searchsorted`` for all agents); ``Reference`` turns one step into:

- the **held** sample (the paper's zero-order hold between 10 Hz steps), and
- the **extrapolated** reference at ``t_k + tau``: the front bumper moves
  ``s = v*tau + a*tau^2/2`` along the path ahead (stopping at ``v = 0``), which removes
  the sample-hold sawtooth (FIELD-NOTES: 1.05 -> 0.04 m), and its heading turns with the
  path.

Without a path in the message the path is synthesised as an arc with the yaw rate of the
last two samples (straight when unknown).

Angles here are MuJoCo yaw [rad, ccw from east]; positions are SUMO/MuJoCo x, y [m]
(same axes, see ``protocol.frames``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from physics_side.kinematics import concat_ranges
from protocol.frames import sumo_angle_to_yaw, wrap_pi
from runtime.native import numpy_math_is_libm, optional_extension

_BIG = 1.0e6  # [m] arc-length gap between agents in the global search key (> any path)
_SEG_ROWS = 15  # rows of the per-segment table (``PathSet._segment_table``, unpacked in ``at``)
MIN_SEG_M = 1e-9  # [m] segment lengths divide as at least this (a repeated vertex, the gap between two paths)
SYNTH_MAX_CURVATURE = 0.5  # [1/m] a synthesised arc turns no tighter than a 2 m radius
STRAIGHT_CURVATURE = 1e-6  # [1/m] a synthesised arc this flat is laid out as a straight line (no 1/kappa)
KAPPA_MIN_SPEED = 0.5  # [m/s] below this SUMO's turn rate says nothing about the path's curvature
DRIFT_MIN_SPEED = 1.0  # [m/s] a sideways drift's angle is taken against at least this forward speed
# [1] Fritsch-Carlson: a cubic through two samples never reverses while its end speeds lie
# within this radius, in units of the chord speed
MONOTONE_RADIUS = 3.0
RATIO_FLOOR = 1e-9  # floor of a divisor that is 0 only where its quotient is unused (a standing agent)
SYNTH_LENGTH = 60.0  # [m] length of a synthesised path
SYNTH_STEP = 2.0  # [m] vertex spacing of a synthesised path
BLEND_M = 3.5  # [m] half-length over which the heading turns at a polyline vertex
FINE_SEG_M = 4.0  # [m] segments up to this long sample a curve (SUMO's internal junction lanes)
SAMPLING_RATIO = 1.5  # [1] an end segment this much longer than its neighbour is no sample of its curve
LANE_WIDTH_M = 3.5  # [m] a sideways drift away from the path's centre line ends after this
# Share of a step's deceleration an interpolated reference carries past the step's end, at
# steps of DECEL_CARRY_STEPS_S[1] and longer (all of it up to DECEL_CARRY_STEPS_S[0], linear
# between). At 1 s steps SUMO's decelerations are often one step long (13.2 -> 8.7 -> 11.3
# m/s): carried on in full, the reference ended such a step 4.9 m/s below the next step's
# start and the car fell 2.8 m behind. Half of it on the 1 s city scenarios: p95 Bologna
# 0.341 -> 0.316, Doerpfeldstrasse 0.390 / 0.410 -> 0.340 / 0.351, Hamburg 0.413 -> 0.425 m
# (lane-change max 2.49 -> 1.58 m); at 0.5 s steps (features grid) it cost 0.19 -> 0.22 m.
DECEL_CARRY = 0.5  # [1]
DECEL_CARRY_STEPS_S = (0.5, 1.0)  # [s]


# The C fast path of ``PathSet.at``; None when it is not built or SUMOCO_PURE_PHYSICS is set.
_kernel = optional_extension("physics_side._pathkernel", "SUMOCO_PURE_PHYSICS")
#: True when ``PathSet.at`` runs in C (``physics_side._pathkernel``, bit-identical to its
#: Python body, which runs otherwise).
FAST_PATHS: bool = _kernel is not None
#: True when ``Reference.at``, ``Reference.at_and_project`` and ``Reference.point_at`` run in C
#: (the same extension's ``reference`` and ``point_at``, bit-identical to their Python bodies).
#: They call libm's cos / sin: off where numpy's are other bits.
FAST_REFERENCE: bool = FAST_PATHS and numpy_math_is_libm()
#: True when ``PathSet``'s tables (``__init__``) and ``PathSet.dedup`` are built in C (the same
#: extension's ``build`` and ``dedup``; libm's hypot / atan2, hence the same condition).
FAST_PATHSET: bool = FAST_REFERENCE


@dataclass(frozen=True)
class PathPoint:
    """Path evaluated at one arc length per agent (arrays of length n)."""

    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    """Tangent [rad]."""
    curvature: np.ndarray
    """[1/m], + = turning left."""


class PathSet:
    """n ragged polylines (each >= 2 distinct vertices), evaluated by arc length, vectorised.

    Arc length 0 is each polyline's first vertex; queries before 0 or past the end
    extrapolate along the first / last segment. Positions lie on the polyline. The
    heading is the segment's, blended linearly across each vertex over
    ``b = min(BLEND_M, half of either segment)`` on both sides (a corner becomes a
    short constant-curvature turn): a finely sampled curve (SUMO's internal junction
    lanes) gets a continuous heading and its curvature, a long straight lane segment
    keeps its exact heading up to BLEND_M before its corner. On a finely sampled curve
    the first and last segments continue their neighbour's turn.
    """

    def __init__(self, offsets: np.ndarray, xy: np.ndarray):
        offsets = np.asarray(offsets, np.int64)
        xy = np.asarray(xy, np.float64)
        n = len(offsets) - 1
        counts = np.diff(offsets)
        if n and counts.min() < 2:
            raise ValueError("every polyline needs at least 2 vertices")
        self.n = n
        self.offsets = offsets
        self.xy = xy
        if FAST_PATHSET and n and len(xy) > 1 and xy.ndim == 2 and xy.flags.c_contiguous and \
                offsets.flags.c_contiguous and self._build_c():
            return
        seglen = self._measure(offsets, xy, np.repeat(np.arange(n), counts))
        turn, b_start, turn_end, b_end = _vertex_turns(seglen, self.h, self.first, self.last_seg)
        _continue_sampled_ends(seglen, self.first, self.last_seg, turn, b_start, turn_end, b_end)
        self.turn_s, self.b_s = turn, b_start
        self.turn_e, self.b_e = turn_end, b_end
        self._seg = self._segment_table(turn, b_start, turn_end, b_end)
        if _kernel is not None:  # the per-agent inputs of the C path, two arrays instead of four
            self._agents_f = np.array([self.total, self._base])
            self._agents_i = np.array([self.first, self.last_seg], np.int64)

    def _build_c(self) -> bool:
        """``__init__``'s tables in C, the same bits; False when the offsets do not span xy
        (the Python body then runs and raises)."""
        n, m = self.n, len(self.xy) - 1
        seg, cum, key, turn, agents_f = np.empty((_SEG_ROWS, m)), np.empty(m + 1), np.empty(m + 1), np.empty(m), \
            np.empty((2, n))
        if not _kernel.build(self.offsets, self.xy, seg, cum, key, turn, agents_f):
            return False
        self.cum, self.key, self.total, self._base = cum, key, agents_f[0], agents_f[1]
        self.first, self.last_seg = self.offsets[:-1], self.offsets[1:] - 2
        self.seglen, self.dir, self.h = seg[5], seg[2:4].T, seg[10]
        self.turn_s, self.b_s, self.turn_e, self.b_e = turn, seg[6], seg[9], seg[7]
        self._seg = seg
        self._agents_f = agents_f
        self._agents_i = np.array([self.first, self.last_seg], np.int64)
        return True

    def _measure(self, offsets: np.ndarray, xy: np.ndarray, owner: np.ndarray) -> np.ndarray:
        """Segments, their headings and the arc length of every vertex (and the search key over
        all polylines); returns each segment's length [m], 0 between two polylines."""
        n = self.n
        m = max(len(xy) - 1, 0)
        seg = xy[1:] - xy[:-1]  # segment j joins vertex j and j+1
        seglen = np.hypot(seg[:, 0], seg[:, 1]) if m else np.zeros(0)
        last = offsets[1:] - 1  # last vertex of each agent
        # the segment leaving an agent's last vertex joins two agents: invalid
        seglen[last[:-1]] = 0.0
        safe = np.maximum(seglen, MIN_SEG_M)
        cum = np.zeros(len(xy))
        if m:
            c = np.empty(m + 1)
            c[0] = 0.0
            np.cumsum(seglen, out=c[1:])
            cum = c - c[offsets[:-1]][owner]
        self.cum = cum
        self.total = cum[last] if n else np.zeros(0)
        self.key = cum + owner * _BIG
        self._base = np.arange(n) * _BIG
        self.first = offsets[:-1]
        self.last_seg = last - 1
        self.seglen = safe
        self.dir = seg / safe[:, None] if m else np.zeros((0, 2))
        self.h = np.arctan2(seg[:, 1], seg[:, 0]) if m else np.zeros(0)
        return seglen

    def _segment_table(self, turn: np.ndarray, b_start: np.ndarray, turn_end: np.ndarray,
                       b_end: np.ndarray) -> np.ndarray:
        """One column per segment (``_SEG_ROWS`` rows), so a query gathers everything it needs
        with one ``take``; blend denominators are 1 where there is no blend (never selected
        then), so ``at`` divides without a floating-point error state."""
        if not len(self.h):
            return np.zeros((_SEG_ROWS, 0))
        two_bs = np.where(b_start > 0, 2 * b_start, 1.0)
        two_be = np.where(b_end > 0, 2 * b_end, 1.0)
        xy = self.xy
        return np.array([
            xy[:-1, 0], xy[:-1, 1], self.dir[:, 0], self.dir[:, 1], self.cum[:-1], self.seglen, b_start, b_end, -turn,
            turn_end, self.h, two_bs, two_be, turn / two_bs, turn_end / two_be,
        ])

    @staticmethod
    def dedup(offsets: np.ndarray, xy: np.ndarray, tol: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
        """Drop vertices within ``tol`` [m] of the previous one of the same polyline
        (SUMO repeats the junction point where a lane ends and the next begins)."""
        offsets = np.asarray(offsets, np.int64)
        xy = np.asarray(xy, np.float64)
        n = len(offsets) - 1
        if len(xy) < 2:
            return offsets, xy
        if FAST_PATHSET and xy.ndim == 2 and xy.flags.c_contiguous and offsets.flags.c_contiguous and \
                isinstance(tol, float):
            new_off, new_xy = np.empty(n + 1, np.int64), np.empty(xy.shape)
            kept = _kernel.dedup(offsets, xy, tol, new_off, new_xy)
            if kept == len(xy):
                return offsets, xy
            if kept >= 0:
                return new_off, new_xy[:kept]
        d = np.hypot(*(xy[1:] - xy[:-1]).T)
        keep = np.ones(len(xy), bool)
        keep[1:] = d >= tol
        keep[offsets[:-1][np.diff(offsets) > 0]] = True  # every polyline keeps its first vertex
        if keep.all():  # nothing to drop (every step of a run without repeated vertices)
            return offsets, xy
        owner = np.repeat(np.arange(n), np.diff(offsets))
        counts = np.bincount(owner[keep], minlength=n)
        return np.concatenate(([0], np.cumsum(counts))), xy[keep]

    @classmethod
    def concat_fallback(
        cls, offsets: np.ndarray, xy: np.ndarray, x0: np.ndarray, y0: np.ndarray,
        yaw0: np.ndarray, kappa0: np.ndarray,
    ) -> "PathSet":
        """Paths from a message, with a synthesised arc for agents with fewer than 2 vertices.

        ``offsets`` may be empty (no paths at all). The synthesised arc starts at
        (x0, y0) with heading yaw0 and curvature kappa0 [1/m].
        """
        n = len(x0)
        if len(offsets) == 0:
            counts = np.zeros(n, np.int64)
            offsets = np.zeros(n + 1, np.int64)
            xy = np.zeros((0, 2))
        else:
            offsets, xy = cls.dedup(offsets, xy)
            counts = np.diff(offsets)
        need = counts < 2
        if not need.any():
            return cls(offsets, xy)
        k = int(SYNTH_LENGTH / SYNTH_STEP) + 1
        s = np.arange(k) * SYNTH_STEP
        idx = np.flatnonzero(need)
        kap = np.clip(kappa0[idx], -SYNTH_MAX_CURVATURE, SYNTH_MAX_CURVATURE)[:, None]
        th = yaw0[idx][:, None] + kap * s[None, :]
        # exact arc: integrate heading; small-kappa safe formula
        with np.errstate(divide="ignore", invalid="ignore"):
            curved = np.abs(kap) > STRAIGHT_CURVATURE
            sx = np.where(curved, (np.sin(th) - np.sin(yaw0[idx])[:, None]) / kap, s * np.cos(th))
            sy = np.where(curved, (np.cos(yaw0[idx])[:, None] - np.cos(th)) / kap, s * np.sin(th))
        synth = np.stack([x0[idx][:, None] + sx, y0[idx][:, None] + sy], axis=-1)
        new_counts = np.where(need, k, counts)
        new_off = np.concatenate(([0], np.cumsum(new_counts)))
        new_xy = np.zeros((int(new_off[-1]), 2))
        # copy kept paths block-wise (vectorised with a gather)
        keep = np.flatnonzero(~need)
        if len(keep):
            src = concat_ranges(offsets[keep], counts[keep])
            dst = concat_ranges(new_off[keep], counts[keep])
            new_xy[dst] = xy[src]
        dst = concat_ranges(new_off[idx], np.full(len(idx), k))
        new_xy[dst] = synth.reshape(-1, 2)
        return cls(new_off, new_xy)

    def at(self, s: np.ndarray) -> PathPoint:
        """Evaluate every polyline at its own arc length ``s`` (length n) [m]; ``s`` of shape
        (k, n) evaluates each polyline at k arc lengths in one go (fewer numpy calls). Runs in
        C (physics_side._pathkernel) when built: per call the Python body's ~20 numpy calls
        cost ~40 us whatever the agent count."""
        s = np.asarray(s, np.float64)
        if self.n == 0:
            z = np.zeros(s.shape)
            return PathPoint(z, z, z, z)
        if _kernel is not None and s.ndim and s.shape[-1] == self.n:
            out = np.empty((4, *s.shape))
            _kernel.at(self._seg, self.key, self._agents_f, self._agents_i, s, out)
            return PathPoint(out[0], out[1], out[2], out[3])
        return self._at_python(s)

    def _at_python(self, s: np.ndarray) -> PathPoint:
        """``at`` in numpy (s: float64, n > 0); physics_side._pathkernel computes the same, bit
        for bit (a binary search per query over its own agent's vertices instead of the
        global key: the same segment, as every other agent's keys lie below or above)."""
        # hot path (several calls per tick): minimum/maximum instead of np.clip, which
        # costs a few microseconds of Python wrapping per call on small arrays
        key = np.minimum(np.maximum(s, 0.0), self.total) + self._base
        j = np.searchsorted(self.key, key, side="right") - 1
        j = np.minimum(np.maximum(j, self.first), self.last_seg)
        x0, y0, dx, dy, c0, L, bs, be, neg_ds, de, h, two_bs, two_be, k_s, k_e = self._seg.take(j, axis=1)
        t = s - c0  # unclipped: extrapolates before 0 / past the end
        tc = np.minimum(np.maximum(t, 0.0), L)
        in_s = tc < bs  # never where bs = 0 (tc >= 0), nor in_e where be = 0 (tc <= L)
        in_e = tc > L - be
        heading = h + np.where(in_s, neg_ds * (bs - tc) / two_bs, np.where(in_e, de * (tc - L + be) / two_be, 0.0))
        kappa = np.where(in_s, k_s, np.where(in_e, k_e, 0.0))
        return PathPoint(x0 + dx * t, y0 + dy * t, wrap_pi(heading), kappa)


def _vertex_turns(
    seglen: np.ndarray, h: np.ndarray, first: np.ndarray, last_seg: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Turn [rad] and blend half-length [m] at the start vertex of each segment (segment j-1
    -> j; 0 at path starts) and at its end vertex (the next segment's start; 0 at path ends)."""
    m = len(seglen)
    turn = np.zeros(m)
    b_start = np.zeros(m)
    if m > 1:
        turn[1:] = wrap_pi(h[1:] - h[:-1])
        b_start[1:] = np.minimum(np.minimum(seglen[1:], seglen[:-1]) * 0.5, BLEND_M)
    # (every polyline has a first segment: >= 2 vertices each)
    turn[first] = 0.0
    b_start[first] = 0.0
    turn_end = np.zeros(m)
    b_end = np.zeros(m)
    if m > 1:
        turn_end[:-1] = turn[1:]
        b_end[:-1] = b_start[1:]
    turn_end[last_seg] = 0.0
    b_end[last_seg] = 0.0
    return turn, b_start, turn_end, b_end


def _continue_sampled_ends(
    seglen: np.ndarray, first: np.ndarray, last_seg: np.ndarray, turn: np.ndarray, b_start: np.ndarray,
    turn_end: np.ndarray, b_end: np.ndarray,
) -> None:
    """On sampled curves the first / last segment continues its neighbour's turn, if it is
    sampled like it (at most SAMPLING_RATIO as long): the last 3.4 m of a straight lane
    before a dead end's U-turn (1.4 m segments) took 2.4 times the U-turn's first 34 deg
    corner, the path's heading at the bumper swung 46 deg and a bicycle steered off its lane.
    Updates the turns and blends (``_vertex_turns``) in place."""
    m = len(seglen)
    if m <= 1:
        return
    first_seg = np.zeros(m, bool)
    first_seg[first] = True
    last = np.zeros(m, bool)
    last[last_seg] = True
    fine = seglen <= FINE_SEG_M
    nxt_ok = first_seg & ~last & fine & np.concatenate((fine[1:], [False]))
    nxt_ok[:-1] &= seglen[:-1] <= SAMPLING_RATIO * seglen[1:]
    idx = np.flatnonzero(nxt_ok)
    turn[idx] = turn_end[idx] * seglen[idx] / np.maximum(seglen[idx + 1], MIN_SEG_M)
    b_start[idx] = 0.5 * seglen[idx]
    prv_ok = last & ~first_seg & fine & np.concatenate(([False], fine[:-1]))
    prv_ok[1:] &= seglen[1:] <= SAMPLING_RATIO * seglen[:-1]
    idx = np.flatnonzero(prv_ok)
    turn_end[idx] = turn[idx] * seglen[idx] / np.maximum(seglen[idx - 1], MIN_SEG_M)
    b_end[idx] = 0.5 * seglen[idx]


def stopping_distance(v: np.ndarray, a: np.ndarray, tau: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance [m] and speed [m/s] after ``tau`` from speed v with constant accel a, never reversing."""
    v = np.asarray(v, np.float64)
    a = np.asarray(a, np.float64)
    vt = v + a * tau
    s = v * tau + 0.5 * a * tau * tau
    stop = vt < 0.0
    if np.any(stop):
        with np.errstate(divide="ignore", invalid="ignore"):
            s_stop = np.where(a < 0, v * v / (-2.0 * np.where(a < 0, a, -1.0)), 0.0)
        s = np.where(stop, s_stop, s)
        vt = np.where(stop, 0.0, vt)
    return s, vt


@dataclass(frozen=True)
class ReferencePoint:
    """Reference front-bumper state of every agent at one time (arrays of length n)."""

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    """Heading [rad]."""
    speed: np.ndarray
    """[m/s]."""
    accel: np.ndarray
    """[m/s^2]."""
    curvature: np.ndarray
    """Path curvature [1/m]."""
    s: np.ndarray
    """Arc length along the path ahead from the sample [m]."""
    tangent: np.ndarray
    """Path tangent at the point [rad] (``yaw`` is SUMO's body angle, which on a curve
    is the rear-to-front chord and differs from the tangent at the front bumper)."""


class Reference:
    """The reference of n agents built from one SUMO step (held and extrapolated)."""

    def __init__(
        self, t_k: float, x: np.ndarray, y: np.ndarray, angle_deg: np.ndarray, speed: np.ndarray,
        accel: np.ndarray, la_x: np.ndarray, la_y: np.ndarray, path_offsets: np.ndarray,
        path_xy: np.ndarray, yaw_rate: np.ndarray | None = None,
    ):
        self.t_k = float(t_k)
        self.x = np.asarray(x, np.float64)
        self.y = np.asarray(y, np.float64)
        self.yaw = sumo_angle_to_yaw(angle_deg)
        self.speed = np.maximum(np.asarray(speed, np.float64), 0.0)
        self.accel = np.asarray(accel, np.float64)
        self.la_x = np.asarray(la_x, np.float64)
        self.la_y = np.asarray(la_y, np.float64)
        n = len(self.x)
        self.n = n
        if yaw_rate is None:
            yaw_rate = np.zeros(n)
        self.yaw_rate = np.asarray(yaw_rate, np.float64)
        """SUMO's turn rate between its last two samples [rad/s] (0: unknown)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            kappa0 = np.where(self.speed > KAPPA_MIN_SPEED, yaw_rate / np.maximum(self.speed, KAPPA_MIN_SPEED), 0.0)
        self.path = PathSet.concat_fallback(path_offsets, path_xy, self.x, self.y, self.yaw, kappa0)
        p0 = self.path.at(np.zeros(n))
        self._k0 = p0.curvature
        self._h0 = p0.heading
        # The path may start a little off the bumper (e.g. mid lane change): carry the
        # offset in the path's frame (along, left), and turn the sample's heading with the path.
        self._dx = self.x - p0.x
        self._dy = self.y - p0.y
        c0, s0 = np.cos(p0.heading), np.sin(p0.heading)
        self._off_lon = self._dx * c0 + self._dy * s0
        self._off_lat = self._dy * c0 - self._dx * s0
        self._dyaw = wrap_pi(self.yaw - p0.heading)
        self._last_at: tuple[float, ReferencePoint] | None = None
        # sideways drift of the sample off its path (SUMO's continuous lane change), left of
        # the path [m/s], and how far it may go before the path's centre line [m]
        self.side_rate = np.zeros(n)
        self._side_cap = np.full(n, np.inf)
        self._drift = False
        self._state: np.ndarray | None = None  # the C path's per-agent inputs (``_c_state``)

    def set_side_rate(self, rate: np.ndarray) -> None:
        """Extrapolate a sideways drift of ``rate`` [m/s, + left of the path] (from the last two
        samples): a continuous lane change moves the sample off its lane's centre line at
        SUMO's lateral speed. The drift stops at the path's centre line when it moves towards
        it (the target lane reached) and after ``LANE_WIDTH_M`` otherwise."""
        rate = np.nan_to_num(np.asarray(rate, np.float64))
        off = self.side_offset
        towards = np.sign(rate) == -np.sign(off)
        self._side_cap = np.where(towards, np.abs(off), np.maximum(LANE_WIDTH_M - np.abs(off), 0.0))
        self.side_rate = np.where(self._side_cap > 0.0, rate, 0.0)
        self._drift = bool(np.any(self.side_rate != 0.0))
        self._last_at = None
        self._state = None

    @property
    def side_offset(self) -> np.ndarray:
        """The sample's offset left of its path's start (its lane's centre line) [m]."""
        return self._off_lat

    def drift_angle(self, tau: float, speed: np.ndarray | None = None) -> np.ndarray | float:
        """Heading of the sideways drift relative to the path [rad] while it lasts at ``tau`` [s],
        for a motion along the path at ``speed`` [m/s] (default: the sample's)."""
        if not self._drift:
            return 0.0
        on = np.abs(self.side_rate) * tau < self._side_cap
        v = self.speed if speed is None else speed
        return np.where(on, np.arctan2(self.side_rate, np.maximum(v, DRIFT_MIN_SPEED)), 0.0)

    def _shift(self, heading: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """World-frame offset [m] of the reference from its path where the path's tangent is
        ``heading`` [rad], ``tau`` [s] after the sample: the sample's offset from the path's
        start plus the sideways drift since, both in the path's frame there. (In the start's
        frame a lane change's offset pointed the wrong way once the path had turned: across a
        96 deg junction turn of one 1 s step a 2.2 m offset put the reference 2.7 m off SUMO's
        next sample.)"""
        lat = self._off_lat
        if self._drift and tau > 0.0:
            lat = lat + np.clip(self.side_rate * tau, -self._side_cap, self._side_cap)
        c, s = np.cos(heading), np.sin(heading)
        return self._off_lon * c - lat * s, self._off_lon * s + lat * c

    @classmethod
    def from_batch(cls, t_k: float, agents, rows: np.ndarray | None = None, yaw_rate=None) -> "Reference":
        """Reference of ``agents`` (an AgentBatch), optionally only ``rows`` of it."""
        a = agents
        every = rows is None
        rows = np.arange(a.n) if every else np.asarray(rows, np.int64)
        if len(a.path_offsets) and every:  # the paths as they are, without a gather
            off = np.asarray(a.path_offsets, np.int64)
            xy = np.asarray(a.path_xy[off[0]:off[-1]], np.float64)
            new_off = off - off[0]
        elif len(a.path_offsets):
            off = np.asarray(a.path_offsets, np.int64)
            counts = off[rows + 1] - off[rows]
            src = concat_ranges(off[rows], counts)
            xy = np.asarray(a.path_xy, np.float64)[src]
            new_off = np.concatenate(([0], np.cumsum(counts)))
        else:
            xy = np.zeros((0, 2))
            new_off = np.zeros(0, np.int64)
        return cls(
            t_k, a.x[rows], a.y[rows], a.angle[rows], a.speed[rows], a.accel[rows],
            a.la_x[rows], a.la_y[rows], new_off, xy, yaw_rate,
        )

    def interpolate_to(self, step_length: float, known: np.ndarray, s_end: np.ndarray, v_end: np.ndarray,
                       a_end: np.ndarray, lat_end: np.ndarray) -> None:
        """Follow the *next* sample instead of guessing: agents ``known`` reach arc length
        ``s_end`` [m] and ``lat_end`` [m, left of the path] ``step_length`` [s] after this
        sample, then go on with ``v_end`` [m/s] and ``a_end`` [m/s^2]. The others are
        extrapolated from their own sample, which is ``step_length`` later than this one
        (new agents).

        In between, the arc length is a cubic in time through both samples (``profile``).
        SUMO's Euler update moves a vehicle at its new speed over the whole step, so a
        reported speed is the mean over the step before its sample, which a smooth
        trajectory reaches mid-step: the speed at this sample is the mean of its speed and
        the step's chord speed ``s_end / step_length``, and the end speed follows for a
        constant acceleration over the step (the cubic is then that parabola). Consecutive
        steps join with a continuous speed unless SUMO's acceleration changes (a jump of
        half a step of the change); a constant speed per step instead jumps ``a * step`` at
        every sample, which no vehicle can follow (0.5 m of lag at 1 s steps). Of a
        decelerating step's end speed only ``DECEL_CARRY`` of the deceleration is carried
        past its end at long steps (SUMO's one-step dips).
        """
        self._interp = np.asarray(known, bool)
        L = self._L = float(step_length)
        S = self._s_end = np.where(self._interp, np.maximum(s_end, 0.0), 0.0)
        self._v_end = np.maximum(np.asarray(v_end, np.float64), 0.0)
        self._a_end = np.asarray(a_end, np.float64)
        mean = S / L
        v0 = 0.5 * (self.speed + mean)
        v1 = 2.0 * mean - v0
        lo, hi = DECEL_CARRY_STEPS_S
        carry = 1.0 - (1.0 - DECEL_CARRY) * min(max((L - lo) / (hi - lo), 0.0), 1.0)
        v1 = np.where(v1 < mean, mean - carry * (mean - v1), v1)  # (see DECEL_CARRY)
        v1 = np.maximum(v1, 0.0)  # < 0: stops within the step (cubic below)
        # never reversing: end speeds inside the monotone region of the cubic (Fritsch-Carlson)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.hypot(v0, v1) / np.maximum(MONOTONE_RADIUS * mean, RATIO_FLOOR)
        sc = np.where(r > 1.0, 1.0 / np.maximum(r, RATIO_FLOOR), 1.0)
        self._v0, self._v1 = v0 * sc, v1 * sc
        lat = np.where(self._interp, lat_end, 0.0)
        self.side_rate = np.where(self._interp, lat / L, self.side_rate)
        self._side_cap = np.where(self._interp, np.abs(lat), self._side_cap)
        self._drift = bool(np.any(self.side_rate != 0.0))
        self._last_at = None
        self._state = None

    def profile(self, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """Arc length [m] and speed [m/s] ``tau`` [s] after the sample (never reversing)."""
        return self._profile(tau)[:2]

    def _profile(self, tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Arc length [m], speed [m/s] and acceleration [m/s^2] ``tau`` [s] after the sample."""
        interp = getattr(self, "_interp", None)
        if interp is None:
            s, v = stopping_distance(self.speed, self.accel, tau)
            return s, v, np.where(v > 0.0, self.accel, 0.0)
        L = self._L
        s_x, v_x = stopping_distance(self.speed, self.accel, tau - L)  # own sample is L later
        a_x = np.where(v_x > 0.0, self.accel, 0.0)
        S, v0, v1 = self._s_end, self._v0, self._v1
        if tau <= L:  # the cubic Hermite through both samples, in u = tau / L, and its derivatives
            u = max(tau, 0.0) / L
            s_i = S * (3.0 - 2.0 * u) * u * u + L * (v0 * (1.0 - u) ** 2 * u + v1 * (u - 1.0) * u * u)
            v_i = S * 6.0 * u * (1.0 - u) / L + v0 * (1.0 - u) * (1.0 - 3.0 * u) + v1 * u * (3.0 * u - 2.0)
            a_i = (S * (6.0 - 12.0 * u) / L + v0 * (6.0 * u - 4.0) + v1 * (6.0 * u - 2.0)) / L
            v_i = np.maximum(v_i, 0.0)
        else:
            s2, v_i = stopping_distance(v1, self._a_end, tau - L)
            s_i = S + s2
            a_i = np.where(v_i > 0.0, self._a_end, 0.0)
        return np.where(interp, s_i, s_x), np.where(interp, v_i, v_x), np.where(interp, a_i, a_x)

    def mean_speed_lead(self, tau: float, lead: float) -> tuple[np.ndarray, np.ndarray]:
        """Corrections (arc length [m], speed [m/s]) to ``at(tau)`` for SUMO's Euler update.

        SUMO moves a vehicle at its *new* speed over the whole step, so a reported speed is
        the mean over the step before its sample: a smooth motion through SUMO's positions
        is ``lead`` = half a step further on in its speed profile, v + a * step / 2. The
        extrapolation from the sample (s = v tau + a tau^2 / 2) then reaches the next sample
        only within a * step^2 / 2 and asks for a speed a * step / 2 off SUMO's; a position
        loop settles 2 zeta / omega times that speed bias off (0.18 m braking at 4.5 m/s^2).
        Returned as ``S(tau + lead) - S(lead) - S(tau)`` and ``V(tau + lead) - V(tau)`` of
        the extrapolated profile (never reversing); 0 for interpolated agents, whose profile
        already goes through the next sample (and a step long enough to interpolate)."""
        if lead <= 0.0 or getattr(self, "_interp", None) is not None:
            return np.zeros(self.n), np.zeros(self.n)
        s0, v0 = stopping_distance(self.speed, self.accel, tau)
        s1, v1 = stopping_distance(self.speed, self.accel, tau + lead)
        sl, _ = stopping_distance(self.speed, self.accel, lead)
        return s1 - sl - s0, v1 - v0

    @property
    def interpolated(self) -> np.ndarray | None:
        """Which agents follow the next sample (``interpolate_to``), None when not interpolating."""
        return getattr(self, "_interp", None)

    @property
    def step_speed(self) -> np.ndarray:
        """Speed [m/s] over the step the reference spans: the chord speed between both samples
        for interpolated agents (``interpolate_to``), else the sample's speed."""
        interp = getattr(self, "_interp", None)
        if interp is None:
            return self.speed
        return np.where(interp, self._s_end / self._L, self.speed)

    @property
    def start_heading(self) -> np.ndarray:
        """The path's heading at its start (the sample's bumper) [rad]."""
        return self._h0

    def held(self) -> ReferencePoint:
        """The sample itself (zero-order hold)."""
        return ReferencePoint(self.x, self.y, self.yaw, self.speed, self.accel, self._k0, np.zeros(self.n), self._h0)

    def at(self, tau: float) -> ReferencePoint:
        """Extrapolated reference ``tau`` [s] after the sample (tau >= 0); the last one is cached."""
        if self._last_at is not None and self._last_at[0] == tau:
            return self._last_at[1]
        r = self._at(tau)
        self._last_at = (tau, r)
        return r

    def _at(self, tau: float) -> ReferencePoint:
        if FAST_REFERENCE and self.n and isinstance(tau, float):
            o = self._run_c(tau, None, None, None, np.empty((8, self.n)))
            return ReferencePoint(o[0], o[1], o[2], o[3], o[4], o[5], o[6], o[7])
        s, v, a = self._profile(tau)
        return self._point(s, v, a, self.path.at(s), tau)

    def _point(self, s: np.ndarray, v: np.ndarray, a: np.ndarray, p: PathPoint, tau: float = 0.0) -> ReferencePoint:
        """The reference point at arc length ``s``, speed ``v``, acceleration ``a``; ``p``: the path there."""
        sx, sy = self._shift(p.heading, tau)
        return ReferencePoint(p.x + sx, p.y + sy, wrap_pi(p.heading + self._dyaw), v, a,
                              p.curvature, s, p.heading)

    def at_and_project(
        self, tau: float, px: np.ndarray, py: np.ndarray, s_guess: np.ndarray,
    ) -> tuple[ReferencePoint, tuple[np.ndarray, np.ndarray, PathPoint]]:
        """``at(tau)`` and ``project(px, py, s_guess)`` with one path evaluation (the end of
        every control tick needs both)."""
        s_guess = np.asarray(s_guess, np.float64)
        if self._last_at is not None and self._last_at[0] == tau:
            return self._last_at[1], self.project(px, py, s_guess, tau)
        n = self.n
        if FAST_REFERENCE and n and isinstance(tau, float) and _vector(px, n) and _vector(py, n) and \
                _vector(s_guess, n):
            o = self._run_c(tau, s_guess, px, py, np.empty((14, n)))
            r = ReferencePoint(o[0], o[1], o[2], o[3], o[4], o[5], o[6], o[7])
            self._last_at = (tau, r)
            return r, (o[8], o[9], PathPoint(o[10], o[11], o[12], o[13]))
        s, v, a = self._profile(tau)
        p = self.path.at(np.array([s, s_guess]))
        r = self._point(s, v, a, PathPoint(p.x[0], p.y[0], p.heading[0], p.curvature[0]), tau)
        self._last_at = (tau, r)
        sx, sy = self._shift(p.heading[1], tau)
        g = PathPoint(p.x[1] + sx, p.y[1] + sy, p.heading[1], p.curvature[1])
        return r, self._project(px, py, s_guess, g)

    def _c_state(self) -> np.ndarray:
        """The per-agent inputs of the C path, rows in _pathkernel.c's order (built once per
        reference and after ``set_side_rate`` / ``interpolate_to``)."""
        if self._state is None:
            interp = getattr(self, "_interp", None)
            z = np.zeros(self.n)
            rows = [self.speed, self.accel, self._off_lon, self._off_lat, self._dyaw, self.side_rate, self._side_cap]
            if interp is None:
                rows += [z, z, z, z, z]
            else:
                rows += [interp.astype(np.float64), self._s_end, self._v0, self._v1, self._a_end]
            self._state = np.array(rows, np.float64)
        return self._state

    def _run_c(self, tau: float, s_guess, px, py, out: np.ndarray) -> np.ndarray:
        """``_at(tau)`` (out[:8]) and, with ``s_guess``, ``project(px, py, s_guess, tau)`` (out[8:])
        in C. The scalars of ``_profile`` are computed here, as its Python body does."""
        mode, tau_l, L, u, c2 = 0, 0.0, 1.0, 0.0, 0.0
        if getattr(self, "_interp", None) is not None:
            L = self._L
            tau_l = tau - L
            if tau <= L:
                mode = 1
                u = max(tau, 0.0) / L
                c2 = (1.0 - u) ** 2
            else:
                mode = 2
        ps = self.path
        _kernel.reference(ps._seg, ps.key, ps._agents_f, ps._agents_i, self._c_state(), mode,
                          self._drift and tau > 0.0, tau, tau_l, L, u, c2, s_guess, px, py, out)
        return out

    def point_at(self, s: np.ndarray, tau: float = 0.0) -> PathPoint:
        """Path (shifted by the sample's offset from its start, and its sideways drift until
        ``tau`` [s]) at arc length s [m]; its heading is the path tangent."""
        n = self.n
        if FAST_REFERENCE and n and isinstance(tau, float) and _vector(s, n):
            ps, out = self.path, np.empty((4, n))
            _kernel.point_at(ps._seg, ps.key, ps._agents_f, ps._agents_i, self._c_state(), self._drift and tau > 0.0,
                             tau, s, out)
            return PathPoint(out[0], out[1], out[2], out[3])
        p = self.path.at(s)
        sx, sy = self._shift(p.heading, tau)
        return PathPoint(p.x + sx, p.y + sy, p.heading, p.curvature)

    def project(
        self, px: np.ndarray, py: np.ndarray, s_guess: np.ndarray, tau: float = 0.0,
    ) -> tuple[np.ndarray, np.ndarray, PathPoint]:
        """Project points on the path near ``s_guess``: (s, lateral offset + left, path point at s).

        One evaluation at the guess, then the tangent line there: exact on straight
        segments, within O(d^2 * curvature) for a guess d off on curves. On the hot path
        the guess is the previous projection advanced by v * dt (millimetres off); call
        ``project_far`` for a rough guess.
        """
        s_guess = np.asarray(s_guess, np.float64)
        return self._project(px, py, s_guess, self.point_at(s_guess, tau))

    def _project(self, px, py, s_guess: np.ndarray, g: PathPoint) -> tuple[np.ndarray, np.ndarray, PathPoint]:
        """``project`` with ``g`` = ``point_at(s_guess)`` already evaluated."""
        c, sn = np.cos(g.heading), np.sin(g.heading)
        dx, dy = px - g.x, py - g.y
        ds = dx * c + dy * sn
        lat = -dx * sn + dy * c
        p = PathPoint(g.x + ds * c, g.y + ds * sn, wrap_pi(g.heading + g.curvature * ds), g.curvature)
        return s_guess + ds, lat, p

    def project_far(self, px: np.ndarray, py: np.ndarray, s_guess: np.ndarray, iterations: int = 2,
                    tau: float = 0.0):
        """``project`` refined ``iterations`` times (for guesses metres off)."""
        s = np.asarray(s_guess, np.float64)
        for _ in range(iterations - 1):
            s = self.project(px, py, s, tau)[0]
        return self.project(px, py, s, tau)


def _vector(a, n: int) -> bool:
    """Is ``a`` what the C path reads: a C-contiguous float64 array of shape (n,)?"""
    return type(a) is np.ndarray and a.dtype == np.float64 and a.shape == (n,) and a.flags.c_contiguous


def tracking_error(px, py, ref) -> tuple[np.ndarray, np.ndarray]:
    """Front-bumper error vs a reference point: (along the path + ahead, across + left) [m].

    Uses ``ref.tangent`` when the reference has one (``ReferencePoint``), else ``ref.yaw``.
    """
    dx, dy = px - ref.x, py - ref.y
    h = getattr(ref, "tangent", None)
    h = ref.yaw if h is None else h
    c, s = np.cos(h), np.sin(h)
    return dx * c + dy * s, -dx * s + dy * c


__all__ = ["PathPoint", "PathSet", "Reference", "ReferencePoint", "stopping_distance", "tracking_error"]
