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

from protocol.frames import sumo_angle_to_yaw, wrap_pi

_BIG = 1.0e6  # [m] arc-length gap between agents in the global search key (> any path)
SYNTH_LENGTH = 60.0  # [m] length of a synthesised path
SYNTH_STEP = 2.0  # [m] vertex spacing of a synthesised path


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
    """n ragged polylines (each >= 2 vertices), evaluated by arc length, vectorised.

    Arc length 0 is each polyline's first vertex; queries before 0 or past the end
    extrapolate along the first / last segment.
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
        owner = np.repeat(np.arange(n), counts)
        seg = xy[1:] - xy[:-1]  # segment j from vertex j to j+1 (invalid across agents)
        seglen = np.hypot(seg[:, 0], seg[:, 1])
        last = offsets[1:] - 1  # last vertex of each agent: no segment starts there
        # segment j joins vertex j and j+1; the one leaving an agent's last vertex joins
        # two different agents and is invalid
        valid = np.ones(max(len(xy) - 1, 0), bool)
        valid[last[:-1]] = False
        seglen = np.where(valid, seglen, 0.0)
        # Zero-length segments get the direction of their neighbour via a tiny length.
        seglen_safe = np.maximum(seglen, 1e-9)
        heading_seg = np.arctan2(seg[:, 1], seg[:, 0]) if len(seg) else np.zeros(0)
        # cumulative arc length at each vertex, restarting per agent
        cum = np.zeros(len(xy))
        if len(xy) > 1:
            c = np.concatenate(([0.0], np.cumsum(seglen)))
            cum = c - c[offsets[:-1]][owner]
        self.cum = cum
        self.total = cum[last] if n else np.zeros(0)
        self.owner = owner
        self.key = cum + owner * _BIG
        self.first = offsets[:-1]
        self.last_seg = last - 1
        self.seglen = seglen_safe
        self.dir = np.zeros((len(seg), 2))
        if len(seg):
            self.dir = seg / seglen_safe[:, None]
        # Vertex headings: mean of the adjacent segments (first/last: their segment),
        # so the heading varies continuously along the path.
        hv = np.zeros(len(xy))
        if len(seg):
            hin = np.concatenate(([0.0], heading_seg))  # segment ending at vertex v
            hout = np.concatenate((heading_seg, [0.0]))  # segment starting at vertex v
            is_first = np.zeros(len(xy), bool)
            is_first[offsets[:-1]] = True
            is_last = np.zeros(len(xy), bool)
            is_last[last] = True
            mid = hin + 0.5 * wrap_pi(hout - hin)
            # end vertices: continue the turn of the neighbouring vertex, so the first and
            # last segments get their neighbours' curvature instead of half of it
            hs = heading_seg
            nxt = np.concatenate((hs[1:], [0.0, 0.0]))  # heading of segment v+1
            prv = np.concatenate(([0.0, 0.0], hs[:-1]))  # heading of segment v-2
            first_v = hout - 0.5 * wrap_pi(nxt - hout)
            last_v = hin + 0.5 * wrap_pi(hin - prv)
            two = np.diff(offsets) == 2  # one segment: no neighbour to continue
            single = np.zeros(len(xy), bool)
            single[offsets[:-1][two]] = True
            single[last[two]] = True
            first_v = np.where(single, hout, first_v)
            last_v = np.where(single, hin, last_v)
            hv = np.where(is_first, first_v, np.where(is_last, last_v, mid))
        self.hv = hv
        # Per-segment rate of heading change [1/m] (curvature), heading interpolated
        # linearly between the segment's vertex headings.
        if len(seg):
            dh = wrap_pi(hv[1:] - hv[:-1])
            self.kappa = np.where(valid, dh / seglen_safe, 0.0)
        else:
            self.kappa = np.zeros(0)

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
            offsets = np.asarray(offsets, np.int64)
            counts = np.diff(offsets)
        need = counts < 2
        if not need.any():
            return cls(offsets, xy)
        k = int(SYNTH_LENGTH / SYNTH_STEP) + 1
        s = np.arange(k) * SYNTH_STEP
        idx = np.flatnonzero(need)
        kap = np.clip(kappa0[idx], -0.5, 0.5)[:, None]
        th = yaw0[idx][:, None] + kap * s[None, :]
        # exact arc: integrate heading; small-kappa safe formula
        with np.errstate(divide="ignore", invalid="ignore"):
            sx = np.where(np.abs(kap) > 1e-6, (np.sin(th) - np.sin(yaw0[idx])[:, None]) / kap, s * np.cos(th))
            sy = np.where(np.abs(kap) > 1e-6, (np.cos(yaw0[idx])[:, None] - np.cos(th)) / kap, s * np.sin(th))
        synth = np.stack([x0[idx][:, None] + sx, y0[idx][:, None] + sy], axis=-1)
        new_counts = np.where(need, k, counts)
        new_off = np.concatenate(([0], np.cumsum(new_counts)))
        new_xy = np.zeros((int(new_off[-1]), 2))
        # copy kept paths block-wise (vectorised with a gather)
        keep = np.flatnonzero(~need)
        if len(keep):
            src = _ranges(offsets[keep], counts[keep])
            dst = _ranges(new_off[keep], counts[keep])
            new_xy[dst] = xy[src]
        dst = _ranges(new_off[idx], np.full(len(idx), k))
        new_xy[dst] = synth.reshape(-1, 2)
        return cls(new_off, new_xy)

    def at(self, s: np.ndarray) -> PathPoint:
        """Evaluate every polyline at its own arc length ``s`` (length n) [m]."""
        s = np.asarray(s, np.float64)
        if self.n == 0:
            z = np.zeros(0)
            return PathPoint(z, z, z, z)
        sc = np.clip(s, 0.0, self.total)
        key = sc + np.arange(self.n) * _BIG
        j = np.searchsorted(self.key, key, side="right") - 1
        j = np.clip(j, self.first, self.last_seg)
        t = s - self.cum[j]  # unclipped: extrapolates before 0 / past the end
        p = self.xy[j] + self.dir[j] * t[:, None]
        tc = np.clip(t, 0.0, self.seglen[j])
        heading = self.hv[j] + self.kappa[j] * tc
        return PathPoint(p[:, 0], p[:, 1], wrap_pi(heading), self.kappa[j])


def _ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concatenated ``arange(start, start + count)`` for every pair (vectorised)."""
    counts = np.asarray(counts, np.int64)
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    rep = np.repeat(np.asarray(starts, np.int64) - np.concatenate(([0], np.cumsum(counts)[:-1])), counts)
    return rep + np.arange(total)


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
        with np.errstate(divide="ignore", invalid="ignore"):
            kappa0 = np.where(self.speed > 0.5, yaw_rate / np.maximum(self.speed, 0.5), 0.0)
        self.path = PathSet.concat_fallback(path_offsets, path_xy, self.x, self.y, self.yaw, kappa0)
        p0 = self.path.at(np.zeros(n))
        # The path may start a little off the bumper (e.g. mid lane change): carry the
        # offset, and turn the sample's heading with the path.
        self._dx = self.x - p0.x
        self._dy = self.y - p0.y
        self._dyaw = wrap_pi(self.yaw - p0.heading)

    @classmethod
    def from_batch(cls, t_k: float, agents, rows: np.ndarray | None = None, yaw_rate=None) -> "Reference":
        """Reference of ``agents`` (an AgentBatch), optionally only ``rows`` of it."""
        a = agents
        if rows is None:
            rows = np.arange(a.n)
        rows = np.asarray(rows, np.int64)
        if len(a.path_offsets):
            off = np.asarray(a.path_offsets, np.int64)
            counts = off[rows + 1] - off[rows]
            src = _ranges(off[rows], counts)
            xy = np.asarray(a.path_xy, np.float64)[src]
            new_off = np.concatenate(([0], np.cumsum(counts)))
        else:
            xy = np.zeros((0, 2))
            new_off = np.zeros(0, np.int64)
        return cls(
            t_k, a.x[rows], a.y[rows], a.angle[rows], a.speed[rows], a.accel[rows],
            a.la_x[rows], a.la_y[rows], new_off, xy, yaw_rate,
        )

    def held(self) -> ReferencePoint:
        """The sample itself (zero-order hold)."""
        z = np.zeros(self.n)
        p = self.path.at(z)
        return ReferencePoint(self.x, self.y, self.yaw, self.speed, self.accel, p.curvature, z)

    def at(self, tau: float | np.ndarray) -> ReferencePoint:
        """Extrapolated reference ``tau`` [s] after the sample (tau >= 0)."""
        s, v = stopping_distance(self.speed, self.accel, tau)
        p = self.path.at(s)
        a = np.where(v > 0.0, self.accel, 0.0)
        return ReferencePoint(p.x + self._dx, p.y + self._dy, wrap_pi(p.heading + self._dyaw), v, a, p.curvature, s)

    def point_at(self, s: np.ndarray) -> PathPoint:
        """Path (with the sample's offset) at arc length s [m] from the sample."""
        p = self.path.at(s)
        return PathPoint(p.x + self._dx, p.y + self._dy, wrap_pi(p.heading + self._dyaw), p.curvature)

    def project(self, px: np.ndarray, py: np.ndarray, s_guess: np.ndarray) -> tuple[np.ndarray, np.ndarray, PathPoint]:
        """Project points on the path near ``s_guess``: returns (s, lateral offset + left, path point).

        One tangent-line refinement from the guess (the guess is within centimetres of the
        answer on the hot path): exact on straight segments and within O(d^2 * curvature)
        on curves for a guess d off, which is all the controllers need.
        """
        s = np.asarray(s_guess, np.float64)
        p = self.point_at(s)
        c, sn = np.cos(p.heading), np.sin(p.heading)
        s = s + (px - p.x) * c + (py - p.y) * sn
        p = self.point_at(s)
        c, sn = np.cos(p.heading), np.sin(p.heading)
        lat = -(px - p.x) * sn + (py - p.y) * c
        return s, lat, p


def tracking_error(px, py, ref: ReferencePoint) -> tuple[np.ndarray, np.ndarray]:
    """Front-bumper error vs a reference point: (longitudinal + ahead, lateral + left) [m]."""
    dx, dy = px - ref.x, py - ref.y
    c, s = np.cos(ref.yaw), np.sin(ref.yaw)
    return dx * c + dy * s, -dx * s + dy * c


__all__ = ["PathPoint", "PathSet", "Reference", "ReferencePoint", "stopping_distance", "tracking_error"]
