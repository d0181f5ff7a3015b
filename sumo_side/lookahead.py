"""Look-ahead point and path ahead for all agents at once.

The paper (3.3.2) evaluates the look-ahead point ``LAD`` metres along the track ahead of
the SUMO pose, with ``LAD = LAD_min if v < LAD_min else min(v * k_LAD, LAD_max)``.

How it is computed here without a per-agent Python loop on the hot path:

1. *Lane sequences* (Python, rare): for a vehicle on lane L with route R and route index
   ri, walk from L through junction-internal lanes along R until the sequence reaches
   ``path_length`` metres past the end of L. Identical sequences are stored once in a
   ``PolylineStore`` and shared by every vehicle that follows them. A vehicle's sequence
   is only re-resolved when its lane or route index changes (once per lane, not per
   step).
2. *Per step* (numpy, all agents): the distance ``s0`` of the front bumper along its
   sequence is ``lanePos * geometry_factor`` (the sequence starts at the start of the
   current lane); the look-ahead point and the path ahead are interpolations on the
   stored polylines, done with one ``searchsorted`` over a global, monotonic
   "sequence base + distance" coordinate.

Agents without a lane sequence (walking persons, vehicles off the road or teleporting)
get a straight path along their heading; persons riding a vehicle get an empty path and
their own position as look-ahead point.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from itertools import repeat
from typing import Callable, Sequence

import numpy as np

from sumo_side.lanes import LaneGraph

log = logging.getLogger(__name__)

#: Distances closer than this are the same point [m].
_EPS = 1e-6
#: Gap in the global coordinate between two stored sequences [m] (any value > 0 works:
#: queries are clamped into their own sequence before the search).
_GAP = 1.0
_SEQ_CAPACITY = 1024  # [polylines] first capacity of the per-polyline arrays (doubled when full)
#: A lane walk never takes more lanes than this (guards against cycles in odd nets).
MAX_WALK_LANES = 64
#: [m/s] lane walks cover the extra path (speed x reach) of agents up to this speed.
MAX_REACH_SPEED = 50.0

# Path modes per agent.
MODE_LANES = 0  # along a lane sequence
MODE_STRAIGHT = 1  # along the heading (walking persons, vehicles without a lane)
MODE_NONE = 2  # no path (persons inside a vehicle)


def look_ahead_distance(speed, lad_min: float, lad_max: float, k_lad: float) -> np.ndarray:
    """The paper's LAD [m] for speeds [m/s] (vectorised).

    ``LAD_min`` if ``v < LAD_min`` (the paper compares the speed with the distance as
    written) else ``min(v * k_LAD, LAD_max)``.
    """
    v = np.asarray(speed, np.float64)
    return np.where(v < lad_min, lad_min, np.minimum(v * k_lad, lad_max))


class PolylineStore:
    """Append-only store of polylines with arc length, queried for many points at once.

    Vertex ``j`` has position ``xy[j]`` and global coordinate ``g[j] = base[seq] + s``,
    where ``s`` is the arc length from the start of its polyline. ``g`` increases over the
    whole store, so one ``searchsorted`` finds the segments for any set of (seq, s).
    """

    def __init__(self, capacity: int = 4096) -> None:
        self._xy = np.zeros((capacity, 2), np.float64)
        self._g = np.zeros(capacity, np.float64)
        self._m = 0
        # per polyline, in arrays grown by doubling: a step that adds one reads them without
        # rebuilding them from lists (at 10,000 vehicles that took 1.3 ms per step)
        self._n = 0
        self._base = np.zeros(_SEQ_CAPACITY)
        self._length = np.zeros(_SEQ_CAPACITY)
        self._first = np.zeros(_SEQ_CAPACITY, np.int64)
        self._last = np.zeros(_SEQ_CAPACITY, np.int64)
        self._expose()

    def _expose(self) -> None:
        """``base`` (start on the store's one arc-length axis [m]), ``length`` [m], ``first``
        and ``last`` (point indexes in ``xy``) of every polyline so far: views, no copies."""
        n = self._n
        self.base, self.length = self._base[:n], self._length[:n]
        self.first, self.last = self._first[:n], self._last[:n]

    @property
    def n(self) -> int:
        return self._n

    @property
    def xy(self) -> np.ndarray:
        return self._xy[: self._m]

    @property
    def g(self) -> np.ndarray:
        return self._g[: self._m]

    def add(self, xy: np.ndarray) -> int:
        """Store one polyline (k >= 1 points) and return its id."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        if len(xy) == 0:
            raise ValueError("a polyline needs at least one point")
        seg = np.hypot(*np.diff(xy, axis=0).T) if len(xy) > 1 else np.zeros(0)
        s = np.concatenate(([0.0], np.cumsum(seg)))
        i = self._n
        base = float(self._base[i - 1] + self._length[i - 1] + _GAP) if i else 0.0
        k = len(xy)
        if self._m + k > len(self._g):
            cap = max(2 * len(self._g), self._m + k)
            self._xy = np.resize(self._xy, (cap, 2))
            self._g = np.resize(self._g, cap)
        self._xy[self._m : self._m + k] = xy
        self._g[self._m : self._m + k] = base + s
        if i == len(self._base):
            cap = 2 * i
            self._base, self._length = np.resize(self._base, cap), np.resize(self._length, cap)
            self._first, self._last = np.resize(self._first, cap), np.resize(self._last, cap)
        self._base[i] = base
        self._length[i] = float(s[-1])
        self._first[i] = self._m
        self._last[i] = self._m + k - 1
        self._m += k
        self._n = i + 1
        self._expose()
        return i

    def locate(self, seq: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Segment index ``i`` (into the store) and fraction ``t`` in [0, 1] of the points at
        arc length ``s`` (clamped to the polyline) along polylines ``seq``.

        One ``searchsorted`` for all queries; it is fastest when the queries come sorted
        by global coordinate (``PathPlanner.compute`` orders them so).
        """
        seq = np.asarray(seq, np.int64)
        s = np.clip(np.asarray(s, np.float64), 0.0, self.length[seq])
        g = self.base[seq] + s
        gs = self.g
        first, last = self.first[seq], self.last[seq]
        i = np.searchsorted(gs, g, side="right") - 1
        # Segment start inside the polyline; single-point polylines use their only point.
        i = np.clip(i, first, np.maximum(last - 1, first))
        j = np.minimum(i + 1, last)
        seg = gs[j] - gs[i]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(seg > _EPS, (g - gs[i]) / seg, 0.0)
        return i, np.clip(t, 0.0, 1.0)

    def interp(self, i: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Points on segments ``i`` at fractions ``t``, shape (n, 2)."""
        xy = self.xy
        j = np.minimum(i + 1, self._m - 1)
        return xy[i] + t[:, None] * (xy[j] - xy[i])

    def point_at(self, seq: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Points at arc length ``s`` (clamped) along polylines ``seq``; shape (n, 2)."""
        if len(seq) == 0:
            return np.zeros((0, 2))
        i, t = self.locate(seq, s)
        return self.interp(i, t)

    def pieces(self, seq: np.ndarray, s0: np.ndarray, s1: np.ndarray):
        """Sub-polylines from ``s0`` to ``s1`` (both clamped, s1 >= s0) of each ``seq``.

        Returns ``(counts, xy)``: piece i has ``counts[i]`` points (start point, the
        stored vertices strictly between, end point; always >= 2) and the pieces are
        concatenated in ``xy``.
        """
        seq = np.asarray(seq, np.int64)
        if len(seq) == 0:
            return np.zeros(0, np.int64), np.zeros((0, 2))
        s0 = np.asarray(s0, np.float64)
        i0, t0 = self.locate(seq, s0)
        i1, t1 = self.locate(seq, np.maximum(np.asarray(s1, np.float64), s0))
        counts, out = self.assemble(i0, t0, i1, t1)
        return counts, out

    def assemble(self, i0, t0, i1, t1):
        """Pieces from located start (i0, t0) to located end (i1, t1), end >= start.

        Piece = start point, vertices ``i0+1 .. i1`` (minus the last one when the end
        point sits on it), end point. Returns ``(counts, xy)``.
        """
        counts = _piece_counts(i0, i1, t1)
        off = np.zeros(len(counts) + 1, np.int64)
        np.cumsum(counts, out=off[1:])
        out = np.empty((int(off[-1]), 2))
        self.write_pieces(out, off[:-1], counts, i0, self.interp(i0, t0), self.interp(i1, t1))
        return counts, out

    def write_pieces(self, out, starts, counts, i0, p0, p1) -> None:
        """Write pieces (start point, stored vertices i0+1.., end point) at rows ``starts``."""
        mid = counts - 2
        out[starts] = p0
        out[starts + counts - 1] = p1
        total_mid = int(mid.sum())
        if total_mid:
            # destination row of every middle vertex and the stored vertex it copies
            within = np.arange(total_mid) - np.repeat(np.cumsum(mid) - mid, mid)
            out[np.repeat(starts + 1, mid) + within] = self.xy[np.repeat(i0 + 1, mid) + within]


def _piece_counts(i0: np.ndarray, i1: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """Points per piece: start, the vertices strictly between, end (>= 2)."""
    return np.maximum(i1 - i0 - (t1 <= 1e-9), 0) + 2


@dataclass
class LookAhead:
    """Per-agent result of one step."""

    la_xy: np.ndarray
    """Look-ahead points, shape (n, 2) [m]."""
    path_offsets: np.ndarray
    """uint32 (n+1) (empty when paths are off)."""
    path_xy: np.ndarray
    """float64 (m, 2) [m] (empty when paths are off)."""
    seq: np.ndarray
    """Lane-sequence id per agent, -1 when the agent has none [int64]."""


class PathPlanner:
    """Resolves and caches lane sequences; computes look-ahead points and paths."""

    def __init__(
        self,
        graph: LaneGraph,
        lad_min: float = 7.0,
        lad_max: float = 10.0,
        k_lad: float = 1.0,
        path_length: float = 25.0,
        reach_s: float = 0.0,
    ) -> None:
        """``path_length`` [m] ahead of the front bumper, plus ``speed x reach_s`` [s] per
        agent: the physics side follows the path until the next SUMO step arrives (one step
        length later), and then still needs its own look-ahead beyond that point."""
        self.graph = graph
        self.lad_min = float(lad_min)
        self.lad_max = float(lad_max)
        self.k_lad = float(k_lad)
        self.path_length = float(max(path_length, lad_max))
        self.reach_s = float(max(reach_s, 0.0))
        self.store = PolylineStore()
        self._seq_of_lanes: dict[tuple[int, ...], int] = {}
        # Per-agent memory from the previous step, aligned with _prev_ids.
        self._prev_ids: list[str] = []
        self._prev_lane = np.zeros(0, np.int64)
        self._prev_seq = np.zeros(0, np.int64)
        self.resolved = 0  # number of lane walks done (statistics)

    # ------------------------------------------------------------------ lane walks

    def walk(self, lane: int, route: Sequence[str], route_index: int) -> tuple[int, ...]:
        """Lanes from ``lane`` along ``route`` until ``path_length`` past the end of ``lane``.

        ``route_index`` is SUMO's: the index of the route edge the vehicle is on, or the
        edge it just left while it is on a junction-internal lane.
        """
        g = self.graph
        lanes = [lane]
        need = self.path_length + MAX_REACH_SPEED * self.reach_s
        acc = 0.0
        cur = lane
        idx = self._route_position(cur, route, route_index)
        while acc < need and len(lanes) < MAX_WALK_LANES:
            if g.internal[cur]:
                links = g.links[cur]
                if not links:
                    break
                nxt = links[0].next
            else:
                if idx < 0 or idx + 1 >= len(route):
                    break  # end of the route (or no route): the path ends with this lane
                nxt = self._next_lane_towards(cur, route, idx)
                if nxt < 0:
                    break
            if not g.internal[nxt]:
                # Entering a normal lane: it is the next route edge.
                idx = idx + 1 if (0 <= idx + 1 < len(route) and route[idx + 1] == g.edges[nxt]) \
                    else self._find_edge(route, g.edges[nxt], idx)
            lanes.append(nxt)
            acc += g.geom_lengths[nxt]
            cur = nxt
        return tuple(lanes)

    def _route_position(self, lane: int, route: Sequence[str], route_index: int) -> int:
        g = self.graph
        if g.internal[lane]:
            return route_index if 0 <= route_index < len(route) else -1
        edge = g.edges[lane]
        if 0 <= route_index < len(route) and route[route_index] == edge:
            return route_index
        return self._find_edge(route, edge, route_index)

    @staticmethod
    def _find_edge(route: Sequence[str], edge: str, hint: int) -> int:
        try:
            return list(route).index(edge, max(hint, 0))
        except ValueError:
            try:
                return list(route).index(edge)
            except ValueError:
                return -1

    def _next_lane_towards(self, cur: int, route: Sequence[str], idx: int) -> int:
        """First lane after ``cur`` on the way to ``route[idx + 1]`` (-1: none)."""
        g = self.graph
        target = route[idx + 1]
        after = route[idx + 2] if idx + 2 < len(route) else None
        cands = [lk for lk in g.links[cur] if g.edges[lk.to] == target]
        if not cands:
            # The vehicle still has to change lanes: continue from the nearest lane of
            # the same edge that connects (the path jumps sideways at the junction).
            siblings = g.edge_lanes.get(g.edges[cur], [])
            pos = siblings.index(cur) if cur in siblings else 0
            for other in sorted(siblings, key=lambda o: abs(siblings.index(o) - pos)):
                cands = [lk for lk in g.links[other] if g.edges[lk.to] == target]
                if cands:
                    break
        if not cands:
            return -1
        if after is not None and len(cands) > 1:
            # Prefer a target lane that continues along the route.
            for lk in cands:
                if any(g.edges[l2.to] == after for l2 in g.links[lk.to]):
                    return lk.next
        return cands[0].next

    def sequence_for(self, lanes: tuple[int, ...]) -> int:
        """Stored polyline id of a lane sequence (stored on first use)."""
        sid = self._seq_of_lanes.get(lanes)
        if sid is None:
            pts = []
            for ln in lanes:
                shp = self.graph.shapes[ln]
                if pts and len(shp) and np.hypot(*(shp[0] - pts[-1][-1])) < 1e-6:
                    shp = shp[1:]
                if len(shp):
                    pts.append(shp)
            xy = np.concatenate(pts) if pts else np.zeros((1, 2))
            sid = self.store.add(xy)
            self._seq_of_lanes[lanes] = sid
        return sid

    def lanes_of(self, seq_id: int) -> tuple[int, ...]:
        """The lanes of a stored sequence (``sequence_for``'s inverse; a lookup for checks and
        tools, not for the per-step path)."""
        return next(lanes for lanes, sid in self._seq_of_lanes.items() if sid == seq_id)

    # ------------------------------------------------------------------ per step

    def update_sequences(
        self,
        ids: list[str],
        lane: np.ndarray,
        use_lanes: np.ndarray,
        get_route: Callable[[str], tuple[Sequence[str], int]],
        prev_index: np.ndarray | None = None,
        rerouted: np.ndarray | None = None,
    ) -> np.ndarray:
        """Lane-sequence id per agent (-1 for agents not following lanes).

        Only agents that are new, changed lanes or were ``rerouted`` (bool per agent) since
        the previous call are walked again; ``get_route(id) -> (route edges, route index)``
        is called for those only. (A vehicle's route index only changes when it enters a
        new edge, i.e. a new lane; its route only on a reroute.) ``prev_index`` (row of
        each agent in the previous call's ``ids``, -1 new) saves the alignment when the
        caller already has it.
        """
        n = len(ids)
        lane = np.asarray(lane, np.int64)
        seq = np.full(n, -1, np.int64)
        if ids == self._prev_ids:
            j = np.arange(n)
        elif prev_index is not None and len(prev_index) == n:
            j = np.asarray(prev_index, np.int64)
        elif self._prev_ids:
            where = dict(zip(self._prev_ids, range(len(self._prev_ids))))
            j = np.fromiter(map(where.get, ids, repeat(-1)), np.int64, n)
        else:
            j = np.full(n, -1, np.int64)
        known = j >= 0
        if len(self._prev_ids):
            jj = np.where(known, j, 0)
            same = known & (self._prev_lane[jj] == lane)
            if rerouted is not None:
                same &= ~np.asarray(rerouted, bool)
            seq[same] = self._prev_seq[jj[same]]
        else:
            same = np.zeros(n, bool)
        use = use_lanes & (lane >= 0)
        todo = np.flatnonzero(use & ~(same & (seq >= 0)))
        for i in todo.tolist():
            route, route_index = get_route(ids[i])
            seq[i] = self.sequence_for(self.walk(int(lane[i]), route, route_index))
        self.resolved += len(todo)
        seq[~use] = -1
        self._prev_ids = list(ids)
        self._prev_lane = lane.copy()
        self._prev_seq = seq.copy()
        return seq

    def compute(
        self,
        seq: np.ndarray,
        lane: np.ndarray,
        lane_pos: np.ndarray,
        x: np.ndarray,
        y: np.ndarray,
        angle: np.ndarray,
        speed: np.ndarray,
        mode: np.ndarray,
        with_paths: bool = True,
    ) -> LookAhead:
        """Look-ahead points (and paths) for all agents.

        ``seq`` from ``update_sequences``; ``mode`` per agent: MODE_LANES (used when the
        agent has a sequence), MODE_STRAIGHT or MODE_NONE.
        """
        n = len(seq)
        g = self.graph
        lad = look_ahead_distance(speed, self.lad_min, self.lad_max, self.k_lad)
        la = np.column_stack([np.asarray(x, np.float64), np.asarray(y, np.float64)]) if n \
            else np.zeros((0, 2))
        mode = np.where((mode == MODE_LANES) & (seq < 0), MODE_STRAIGHT, mode)
        on = np.flatnonzero(mode == MODE_LANES)
        st = np.flatnonzero(mode == MODE_STRAIGHT)
        store = self.store
        if len(on):
            ln = lane[on]
            sq = seq[on]
            base = store.base[sq]
            s0 = np.clip(lane_pos[on] * g.pos_factor[ln], 0.0, g.geom_lengths[ln])
            # Sorted queries make searchsorted ~5x faster (numpy narrows from the last hit).
            order = np.argsort(base + s0, kind="stable")
            on, sq, s0, base = on[order], sq[order], s0[order], base[order]
            # Three distances per agent located in one pass: start, look-ahead, path end.
            ahead = self.path_length + np.minimum(np.asarray(speed, np.float64)[on], MAX_REACH_SPEED) * self.reach_s
            dist = np.stack([s0, s0 + lad[on], s0 + ahead])
            np.clip(dist, 0.0, store.length[sq], out=dist)
            gq = base + dist
            gs = store.g
            first, last = store.first[sq], store.last[sq]
            i = np.searchsorted(gs, gq.ravel(), side="right").reshape(gq.shape) - 1
            np.clip(i, first, np.maximum(last - 1, first), out=i)
            j = np.minimum(i + 1, last)
            seg = gs[j] - gs[i]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(seg > _EPS, (gq - gs[i]) / seg, 0.0)
            np.clip(t, 0.0, 1.0, out=t)
            xy = store.xy
            pts = xy[i] + t[..., None] * (xy[j] - xy[i])  # (3, m, 2)
            la[on] = pts[1]
        rad = np.deg2rad(np.asarray(angle, np.float64)[st])
        dirs = np.column_stack([np.sin(rad), np.cos(rad)])  # SUMO angle: cw from north
        if len(st):
            la[st] = la[st] + lad[st, None] * dirs
        if not with_paths:
            return LookAhead(la, np.zeros(0, np.uint32), np.zeros((0, 2)), seq)

        counts = np.zeros(n, np.int64)
        if len(on):
            c_on = _piece_counts(i[0], i[2], t[2])
            counts[on] = c_on
        counts[st] = 2
        off = np.zeros(n + 1, np.int64)
        np.cumsum(counts, out=off[1:])
        out = np.empty((int(off[-1]), 2))  # float64: UTM-sized coordinates
        if len(on):
            store.write_pieces(out, off[on], c_on, i[0], pts[0], pts[2])
        if len(st):
            p0 = np.column_stack([np.asarray(x, np.float64)[st], np.asarray(y, np.float64)[st]])
            out[off[st]] = p0
            out[off[st] + 1] = p0 + self.path_length * dirs
        return LookAhead(la, off.astype(np.uint32), out, seq)
