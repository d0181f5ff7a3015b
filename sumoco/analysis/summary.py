"""Tracking analysis of a recorded run: tables of SUMO and physics samples, errors, summary.

Error metric (the same for every preset): the physics agent's *front-bumper centre* at
physics time t against SUMO's front-bumper centre at the same t, interpolated between
the two SUMO steps around t along a cubic Hermite curve with the samples' headings (a
straight line between samples would cut curves at long SUMO steps). Only agents in mode PHYSICAL count; kinematic and
external (ego) agents are reported apart. Samples next to a SUMO step that flags the
agent as jumped (teleport) or riding are left out: there SUMO moves the agent by fiat.

``report`` (summary.json, report.md) and ``figures`` both read from here. A recording is
summarised as a stream (``analyse_recording``): errors are computed window by window of
simulated time and go into fixed-size accumulators (counts, sums, maxima, log-spaced
histograms for the percentiles, within 0.1 %), so memory does not grow with the run's
length; only the reference car's own samples are kept whole, for the figures.

Lane changes (``lane_changes`` per preset): the same error, restricted to the physics
samples of an agent within a window around each of its lane changes in the SUMO steps
(``lane_change_events``: the recorded ``lane`` index changes between two consecutive
steps to another lane of the same edge) whose reference is not inside a junction (that
is a turn's error). ``count`` is the lane changes with at least one such sample of that
preset; ``max_error_m`` / ``p95_error_m`` are over all their samples.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from physics_side.shard import shard_of_instance
from protocol.keys import Keys
from protocol.messages import AgentClass, AgentFlag, AgentMode, PhysicsState, StaticData, StepMessage
from sumo_side.config import SumoConfig
from sumoco.recording.record import ReadResult, Recording, iter_decoded

log = logging.getLogger(__name__)

#: counters of a shard process that describe the set of shards (the same in each): not summed
SHARD_GAUGES = ("shards_alive",)

CLASS_NAMES = {int(c): c.name.lower() for c in AgentClass}
#: Fields of summary.json that depend on the wall clock (excluded from determinism checks).
WALL_CLOCK_FIELDS = ("wall",)


@dataclass
class RefTable:
    """SUMO reference, long format: one row per (step, agent)."""

    t: np.ndarray
    aid: np.ndarray  # global agent index
    x: np.ndarray
    y: np.ndarray
    angle: np.ndarray
    speed: np.ndarray
    lane: np.ndarray
    cls: np.ndarray
    flags: np.ndarray


@dataclass
class PhysTable:
    """Physics state of one instance, long format: one row per (tick, agent)."""

    t: np.ndarray
    aid: np.ndarray
    cls: np.ndarray
    mode: np.ndarray
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    speed: np.ndarray
    steer: np.ndarray
    drive: np.ndarray
    brake: np.ndarray
    counters: dict = field(default_factory=dict)


@dataclass
class RunData:
    static: StaticData | None
    ids: list[str]
    ref: RefTable
    phys: dict[str, PhysTable]
    steps: int
    sim_span_s: float
    wall_span_s: float
    truncated: bool = False
    first_seen: dict[str, tuple[float, int]] = field(default_factory=dict)


class AgentIndex:
    """Agent names -> global agent indexes, numbered in order of first appearance (a name
    keeps its index for the whole run)."""

    def __init__(self, ids=()) -> None:
        self.ids: list[str] = list(ids)
        self.index: dict[str, int] = {n: i for i, n in enumerate(self.ids)}

    def __call__(self, names: list[str]) -> np.ndarray:
        """The indexes of ``names``; names not seen before get the next ones."""
        out = np.empty(len(names), np.int64)
        index, ids = self.index, self.ids
        for i, n in enumerate(names):
            j = index.get(n)
            if j is None:
                j = index[n] = len(ids)
                ids.append(n)
            out[i] = j
        return out


def _cat(parts, dtype):
    return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype)


def load_run(res: ReadResult | Recording) -> RunData:
    """Turn recorded messages into long-format numpy tables (a ``Recording`` is read as a stream)."""
    items = ((Keys.instance_of(m.topic) or "main", m.log_time_ns, msg) for m, msg in iter_decoded(res))
    data = _run_data(items)
    data.truncated = res.truncated  # known only once a stream has been read to its end
    return data


def build_run_data(static: StaticData | None, steps: list[StepMessage], states: dict[str, list[PhysicsState]],
                   wall_s: float = 0.0) -> RunData:
    """``RunData`` from messages held in memory (an in-process run, e.g. ``sumoco bench fidelity``)."""
    items: list = [("", 0, static)] if static is not None else []
    items += [("", 0, m) for m in steps]
    for inst, lst in states.items():
        items += [(inst, 0, m) for m in lst]
    data = _run_data(items)
    data.wall_span_s = float(wall_s)
    return data


def _run_data(items, truncated: bool = False) -> RunData:
    """Tables from (physics instance, log time [ns], message) triples in recording order."""
    aids = AgentIndex()
    static = None
    ref_cols: dict[str, list] = {k: [] for k in ("t", "aid", "x", "y", "angle", "speed", "lane", "cls", "flags")}
    phys_cols: dict[str, dict[str, list]] = {}
    counters: dict[str, dict] = {}
    steps = 0
    t_first = t_last = None
    w_first = w_last = None
    first_seen: dict[str, tuple[float, int]] = {}
    for inst, log_time_ns, msg in items:
        if isinstance(msg, StaticData):
            static = static or msg
        elif isinstance(msg, StepMessage):
            a = msg.agents
            steps += 1
            t_first = msg.time if t_first is None else t_first
            t_last = msg.time
            w_first = log_time_ns if w_first is None else w_first
            w_last = log_time_ns
            ai = aids(a.ids)
            for i, name in enumerate(a.ids):
                first_seen.setdefault(name, (msg.time, i))  # time, then SUMO's order
            ref_cols["t"].append(np.full(a.n, msg.time))
            ref_cols["aid"].append(ai)
            for k in ("x", "y", "angle", "speed", "lane", "cls", "flags"):
                ref_cols[k].append(getattr(a, k))
        elif isinstance(msg, PhysicsState):
            cols = phys_cols.setdefault(inst, {k: [] for k in (
                "t", "aid", "cls", "mode", "x", "y", "heading", "speed", "steer", "drive", "brake")})
            a = msg.agents
            cols["t"].append(np.full(a.n, msg.time))
            cols["aid"].append(aids(a.ids))
            for k in ("cls", "mode", "x", "y", "heading", "speed", "steer", "drive", "brake"):
                cols[k].append(getattr(a, k))
            counters[inst] = dict(msg.counters)
    ref = RefTable(
        t=_cat(ref_cols["t"], np.float64), aid=_cat(ref_cols["aid"], np.int64),
        x=_cat(ref_cols["x"], np.float64), y=_cat(ref_cols["y"], np.float64),
        angle=_cat(ref_cols["angle"], np.float64), speed=_cat(ref_cols["speed"], np.float64),
        lane=_cat(ref_cols["lane"], np.int64), cls=_cat(ref_cols["cls"], np.int64),
        flags=_cat(ref_cols["flags"], np.int64),
    )
    phys = {}
    for inst, cols in phys_cols.items():
        phys[inst] = PhysTable(
            t=_cat(cols["t"], np.float64), aid=_cat(cols["aid"], np.int64),
            cls=_cat(cols["cls"], np.int64), mode=_cat(cols["mode"], np.int64),
            **{k: _cat(cols[k], np.float64) for k in
               ("x", "y", "heading", "speed", "steer", "drive", "brake")},
            counters=counters.get(inst, {}),
        )
    return RunData(
        static=static, ids=aids.ids, ref=ref, phys=phys, steps=steps,
        sim_span_s=float((t_last or 0.0) - (t_first or 0.0)),
        wall_span_s=float(((w_last or 0) - (w_first or 0)) / 1e9),
        truncated=truncated, first_seen=first_seen,
    )


@dataclass
class Errors:
    """Per physics sample: reference at the same time and the error against it."""

    valid: np.ndarray  # bool: a reference exists at that time and the agent is PHYSICAL
    err: np.ndarray  # |front-bumper error| [m]
    lon: np.ndarray  # along the reference heading [m]
    lat: np.ndarray  # across it, + left [m]
    ref_x: np.ndarray
    ref_y: np.ndarray
    ref_speed: np.ndarray
    ref_lane: np.ndarray


def tracking_errors(ref: RefTable, ph: PhysTable) -> Errors:
    """Interpolate each agent's SUMO reference to the physics sample times (loop over agents only)."""
    n = len(ph.t)
    out = Errors(np.zeros(n, bool), *(np.full(n, np.nan) for _ in range(6)),
                 ref_lane=np.full(n, -1, np.int64))
    if n == 0 or len(ref.t) == 0:
        return out
    r_order = np.lexsort((ref.t, ref.aid))
    p_order = np.lexsort((ph.t, ph.aid))
    r_aid, p_aid = ref.aid[r_order], ph.aid[p_order]
    r_bounds = np.searchsorted(r_aid, np.unique(p_aid), side="left"), np.searchsorted(r_aid, np.unique(p_aid), side="right")
    p_u, p_start = np.unique(p_aid, return_index=True)
    p_end = np.append(p_start[1:], len(p_aid))
    for k, aid in enumerate(p_u):
        r0, r1 = r_bounds[0][k], r_bounds[1][k]
        if r1 - r0 < 2:
            continue
        rs = r_order[r0:r1]
        ps = p_order[p_start[k]:p_end[k]]
        rt, pt = ref.t[rs], ph.t[ps]
        inside = (pt >= rt[0]) & (pt <= rt[-1])
        ps, pt = ps[inside], pt[inside]
        if not len(ps):
            continue
        ang = np.unwrap(np.deg2rad(90.0 - ref.angle[rs]))
        rx, ry = hermite(pt, rt, ref.x[rs], ref.y[rs], ang)
        yaw = np.interp(pt, rt, ang)
        dx, dy = ph.x[ps] - rx, ph.y[ps] - ry
        out.lon[ps] = dx * np.cos(yaw) + dy * np.sin(yaw)
        out.lat[ps] = -dx * np.sin(yaw) + dy * np.cos(yaw)
        out.err[ps] = np.hypot(dx, dy)
        out.ref_x[ps], out.ref_y[ps] = rx, ry
        out.ref_speed[ps] = np.interp(pt, rt, ref.speed[rs])
        nearest = np.clip(np.searchsorted(rt, pt), 0, len(rt) - 1)
        out.ref_lane[ps] = ref.lane[rs][nearest]
        # A sample bracketed by a jump (teleport, boarding) or a ride has no reference
        # motion to follow: SUMO moved the agent, physics placed it.
        odd = (ref.flags[rs] & (AgentFlag.INSIDE_VEHICLE | AgentFlag.JUMPED)) != 0
        hi = np.clip(np.searchsorted(rt, pt, side="right"), 0, len(rt) - 1)
        lo = np.clip(hi - 1, 0, len(rt) - 1)
        out.valid[ps] = (ph.mode[ps] == AgentMode.PHYSICAL) & ~odd[lo] & ~odd[hi]
    return out


def sample_errors(ref: RefTable, ph: PhysTable, t_range: tuple[float, float] = (-np.inf, np.inf)
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Front-bumper error [m] at SUMO's own sample times only, and the class of each sample.

    Between samples SUMO's position is not defined (``tracking_errors`` assumes a constant
    speed along a Hermite curve, which at 1 s steps differs from any drivable motion by up
    to a * step^2 / 8); at a sample it is exact. The physics pose is interpolated between
    the two published states around the sample time (at most 0.11 s apart). Same validity
    rules as ``tracking_errors`` (PHYSICAL on both sides, no jump or ride next to it).
    ``t_range``: only SUMO samples at lo <= t < hi count (a window of a streamed run)."""
    errs, classes = [], []
    if len(ph.t) == 0 or len(ref.t) == 0:
        return np.zeros(0), np.zeros(0, np.int64)
    r_order = np.lexsort((ref.t, ref.aid))
    p_order = np.lexsort((ph.t, ph.aid))
    r_aid, p_aid = ref.aid[r_order], ph.aid[p_order]
    for aid in np.unique(p_aid):
        rs = r_order[np.searchsorted(r_aid, aid):np.searchsorted(r_aid, aid, side="right")]
        ps = p_order[np.searchsorted(p_aid, aid):np.searchsorted(p_aid, aid, side="right")]
        if len(rs) < 2 or len(ps) < 2:
            continue
        rt, pt = ref.t[rs], ph.t[ps]
        idx = np.flatnonzero((rt >= pt[0]) & (rt <= pt[-1]) & (rt >= t_range[0]) & (rt < t_range[1]))
        if not len(idx):
            continue
        j = np.clip(np.searchsorted(pt, rt[idx]), 1, len(pt) - 1)
        gap = pt[j] - pt[j - 1]
        w = np.clip((rt[idx] - pt[j - 1]) / np.maximum(gap, 1e-9), 0.0, 1.0)
        x = ph.x[ps][j - 1] * (1 - w) + ph.x[ps][j] * w
        y = ph.y[ps][j - 1] * (1 - w) + ph.y[ps][j] * w
        mode = ph.mode[ps]
        odd = (ref.flags[rs] & (AgentFlag.INSIDE_VEHICLE | AgentFlag.JUMPED)) != 0
        ok = ((mode[j - 1] == AgentMode.PHYSICAL) & (mode[j] == AgentMode.PHYSICAL) & (gap < 0.11)
              & ~odd[idx] & ~odd[np.minimum(idx + 1, len(rs) - 1)])
        errs.append(np.hypot(x - ref.x[rs][idx], y - ref.y[rs][idx])[ok])
        classes.append(ref.cls[rs][idx][ok])
    if not errs:
        return np.zeros(0), np.zeros(0, np.int64)
    return np.concatenate(errs), np.concatenate(classes)


def hermite(pt: np.ndarray, rt: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray):
    """SUMO's position between two samples: a cubic Hermite curve through both with the
    samples' headings [rad] and the chord's speed (SUMO does not define it; a straight
    line would cut every curve: 0.6 m in a 10 m turn at 7 m/s and 1 s steps, 6 mm at 0.1 s).
    Standing or turning on the spot (no chord) stays the straight line."""
    k = np.clip(np.searchsorted(rt, pt, side="right") - 1, 0, len(rt) - 2)
    dt = rt[k + 1] - rt[k]
    u = np.where(dt > 0, (pt - rt[k]) / np.where(dt > 0, dt, 1.0), 0.0)
    cx, cy = x[k + 1] - x[k], y[k + 1] - y[k]
    chord = np.hypot(cx, cy)
    # tangents of chord length along each sample's heading (turns up to ~90 deg per step)
    m0x, m0y = chord * np.cos(yaw[k]), chord * np.sin(yaw[k])
    m1x, m1y = chord * np.cos(yaw[k + 1]), chord * np.sin(yaw[k + 1])
    h10, h11 = u * (1 - u) ** 2, u * u * (u - 1)
    h01 = u * u * (3 - 2 * u)
    hx = x[k] + h01 * cx + h10 * m0x + h11 * m1x
    hy = y[k] + h01 * cy + h10 * m0y + h11 * m1y
    # a heading far from the chord (a reversing or jumping agent) gets the straight line
    ok = (chord > 1e-3) & (np.cos(yaw[k] - np.arctan2(cy, cx)) > 0.5) & (np.cos(yaw[k + 1] - np.arctan2(cy, cx)) > 0.5)
    return np.where(ok, hx, x[k] + u * cx), np.where(ok, hy, y[k] + u * cy)


def _stats(e: np.ndarray) -> dict:
    e = e[np.isfinite(e)]
    if not len(e):
        return {"mean": None, "p50": None, "p95": None, "max": None, "samples": 0}
    p50, p95 = np.percentile(e, (50, 95))
    return {"mean": round(float(e.mean()), 4), "p50": round(float(p50), 4), "p95": round(float(p95), 4),
            "max": round(float(e.max()), 4), "samples": int(len(e))}


class ErrorHistogram:
    """Streaming statistics of non-negative errors [m]: exact count, mean and max; p50/p95
    from log-spaced bins (``RATIO`` apart, so within 0.1 % of the exact percentile above
    ``LO``; below it, within ``LO``). Memory is fixed (~74 kB) whatever the sample count."""

    LO, HI, RATIO = 1e-5, 1e3, 1.002
    _LOG_R = float(np.log(RATIO))
    BINS = int(np.ceil(np.log(HI / LO) / np.log(RATIO))) + 2  # + underflow and overflow

    def __init__(self) -> None:
        self.counts = np.zeros(self.BINS, np.int64)
        self.n = 0
        self.total = 0.0
        self.max = -np.inf

    def add(self, e: np.ndarray) -> None:
        e = np.asarray(e, np.float64)
        e = e[np.isfinite(e)]
        if not len(e):
            return
        k = np.where(e < self.LO, 0, np.clip(np.floor(np.log(np.maximum(e, self.LO) / self.LO) / self._LOG_R) + 1,
                                             1, self.BINS - 1)).astype(np.int64)
        self.counts += np.bincount(k, minlength=self.BINS)
        self.n += len(e)
        self.total += float(e.sum())
        self.max = max(self.max, float(e.max()))

    def percentile(self, q: float) -> float:
        """As np.percentile (linear between the samples around rank q/100 * (n - 1)), each
        sample resolved to its bin's geometric centre."""
        rank = q / 100.0 * (self.n - 1)
        lo = int(np.floor(rank))
        k = np.searchsorted(np.cumsum(self.counts), [lo, min(lo + 1, self.n - 1)], side="right")
        v = np.where(k == 0, self.LO / 2, self.LO * self.RATIO ** (k - 0.5))
        return float(min(v[0] + (rank - lo) * (v[1] - v[0]), self.max))

    def stats(self) -> dict:
        if not self.n:
            return {"mean": None, "p50": None, "p95": None, "max": None, "samples": 0}
        return {"mean": round(self.total / self.n, 4), "p50": round(self.percentile(50), 4),
                "p95": round(self.percentile(95), 4), "max": round(self.max, 4), "samples": int(self.n)}


def reference_car(data: RunData, prefer: str = "ref") -> str | None:
    """``ref`` if present, else the first passenger car SUMO reported."""
    if prefer in data.ids:
        return prefer
    cars = np.unique(data.ref.aid[data.ref.cls == AgentClass.PASSENGER])
    if not len(cars):
        return None
    return min((data.ids[i] for i in cars), key=lambda n: data.first_seen.get(n, (0.0, 0)))


def internal_lane_mask(static: StaticData | None, lane_idx: np.ndarray) -> np.ndarray:
    """True where the lane is a junction-internal lane (SUMO ids starting with ':')."""
    if static is None:
        return np.zeros(len(lane_idx), bool)
    internal = np.array([i.startswith(":") for i in static.lanes.ids] + [False])
    return internal[np.where(lane_idx >= 0, lane_idx, len(internal) - 1)]


# The window around a lane change. SUMO's continuous lane change (``--lanechange.duration
# D``, which the SUMO side sets to ``sumo.lanechange_duration_s`` unless the scenario chose
# its own lateral model) moves the vehicle sideways over D seconds and reports the target
# lane from the step the manoeuvre passes its midpoint: the recorded lane index changes at
# mid-manoeuvre, so the sideways motion spans t_change - D/2 .. t_change + D/2. The window
# reaches D before it (the start of the manoeuvre, and the physics steering towards a
# look-ahead point that moves sideways before the vehicle's own front does) and D/2 + 2 s
# after it (the end of the manoeuvre plus 2 s for the vehicle to settle on the new lane's
# centre line). A one-step hop (D = 0 in a scenario that chose it) lies well inside.
LANE_CHANGE_DURATION_S = SumoConfig.lanechange_duration_s
LANE_CHANGE_BEFORE_S = LANE_CHANGE_DURATION_S
LANE_CHANGE_AFTER_S = LANE_CHANGE_DURATION_S / 2 + 2.0
# SUMO often starts a lane change on the first step of the edge after a junction, so the
# window reaches back into the turn: samples up to this long after the agent's last SUMO
# sample inside a junction are the turn's (its exit and settling), not the lane change's.
TURN_SETTLE_S = 1.5


def lane_change_events(ref: RefTable, static: StaticData | None, after_t: float = -np.inf
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Lane changes in SUMO samples: (time of the first sample on the new lane, agent), in
    (time, agent) order. A lane change is one agent on two different lanes of the same
    (non-internal) edge in two consecutive steps of ``ref``, the later one after ``after_t``,
    not jumped (teleport, moveToXY) or riding there, and not a pedestrian. Lanes of another
    edge are route progress; without static data (no lane -> edge table) none are found."""
    none = np.zeros(0), np.zeros(0, np.int64)
    if static is None or len(ref.t) < 2:
        return none
    n_lanes = len(static.lanes.ids)
    _, edge_idx = np.unique(np.asarray(static.lanes.edge, dtype=object).astype(str), return_inverse=True)
    edge_of = np.append(edge_idx, -1)  # lane -1 (not on a lane) -> edge -1
    internal = internal_lane_mask(static, np.arange(n_lanes))
    order = np.lexsort((ref.t, ref.aid))
    t, aid, lane = ref.t[order], ref.aid[order], ref.lane[order]
    steps = np.unique(ref.t)
    k = np.searchsorted(steps, t)
    lane_ok = (lane >= 0) & (lane < n_lanes)
    lane_c = np.where(lane_ok, lane, n_lanes)
    edge = edge_of[lane_c]
    inner = np.append(internal, True)[lane_c]
    odd = (ref.flags[order] & (AgentFlag.INSIDE_VEHICLE | AgentFlag.JUMPED)) != 0
    a, b = slice(None, -1), slice(1, None)
    change = ((aid[a] == aid[b]) & (k[b] == k[a] + 1) & (t[b] > after_t)
              & lane_ok[a] & lane_ok[b] & (lane[a] != lane[b]) & (edge[a] == edge[b])
              & ~inner[a] & ~inner[b] & ~odd[b] & (ref.cls[order][b] != AgentClass.PEDESTRIAN))
    j = np.flatnonzero(change) + 1
    ev = np.lexsort((aid[j], t[j]))
    return t[j][ev], aid[j][ev]


def lane_change_cover(t: np.ndarray, aid: np.ndarray, ev_t: np.ndarray, ev_aid: np.ndarray,
                      before: float = LANE_CHANGE_BEFORE_S, after: float = LANE_CHANGE_AFTER_S) -> np.ndarray:
    """For each sample (t, aid): the index into the events of a lane change of the same agent
    whose window ev_t - before <= t <= ev_t + after holds it (the earliest such), else -1."""
    out = np.full(len(t), -1, np.int64)
    if not len(t) or not len(ev_t):
        return out
    u = np.unique(ev_aid)
    r = np.searchsorted(u, aid)
    has = (r < len(u)) & (u[np.minimum(r, len(u) - 1)] == aid)
    # one sorted key per (agent, time): agents in bands of width K, wider than every time
    # span involved, times relative to the earliest so the key keeps its precision
    t0 = min(float(t.min()), float(ev_t.min()))
    K = max(float(t.max()), float(ev_t.max())) - t0 + before + after + 1.0
    ev_r = np.searchsorted(u, ev_aid)
    ev_key = ev_r * K + (ev_t - t0)
    order = np.argsort(ev_key, kind="stable")
    j = np.searchsorted(ev_key[order], r * K + (t - t0 - after), side="left")
    jj = order[np.minimum(j, len(order) - 1)]
    ok = has & (j < len(order)) & (ev_r[jj] == r) & (ev_t[jj] - before <= t)
    out[ok] = jj[ok]
    return out


_SERIES = ("t", "x", "y", "speed", "steer", "drive", "brake")
_ERR_SERIES = ("err", "lon", "lat", "ref_x", "ref_y", "ref_speed", "ref_lane")
_TRACK = ("t", "x", "y", "angle", "speed", "lane")


class _Instance:
    """What the summary keeps of one physics instance: fixed-size histograms, sets of agents,
    and the samples of the reference-car candidates only."""

    def __init__(self) -> None:
        self.overall, self.at_samples = ErrorHistogram(), ErrorHistogram()
        self.per_type: dict[int, ErrorHistogram] = {}
        self.at_type: dict[int, ErrorHistogram] = {}
        self.modes: dict[int, set] = {}
        # agent-time by class: (samples driven by physics, all samples), EXTERNAL (egos) left out
        self.physical: dict[int, list[int]] = {}
        self.seen: dict[int, set] = {}
        self.counters: dict = {}
        self.cand: dict[int, dict[str, list]] = {}  # aid -> series parts
        self.lane_change = ErrorHistogram()  # errors inside lane-change windows
        self.lc_events: set[int] = set()  # lane changes with a sample here (event numbers)
        self.lc_worst: tuple | None = None  # (error, agent, lane-change time, sample time)


class Analysis:
    """The run summary built window by window, so that memory stays flat in the run's length.

    ``feed`` takes (physics instance, log time [ns], message) in recording order; SUMO steps
    and physics states are buffered until the run is ``WINDOW_S`` past a window's end, then
    the window's errors go into the accumulators and the buffers keep only what brackets
    the next window. ``summary`` and ``figure_data`` finish it."""

    WINDOW_S = 5.0  # [s of simulated time] buffers hold about two windows

    def __init__(self, ref_id: str | None = None, window_s: float = WINDOW_S) -> None:
        self.window_s = float(window_s)
        self.agents = AgentIndex()
        self.static: StaticData | None = None
        self.steps = 0
        self.t_first = self.t_last = None
        self.w_first = self.w_last = None
        self.sumo_seen: dict[int, set] = {}
        self.inst: dict[str, _Instance] = {}
        self._shard_counters: dict[str, dict[str, dict]] = {}  # base instance -> shard instance -> newest counters
        self.track: dict[int, dict[str, list]] = {}
        # reference-car candidates: an explicit id, "ref", the first passenger car SUMO reported
        self.wanted: set[str] = {ref_id or "ref", "ref"}
        self.first_passenger: str | None = None
        self._ref_buf: list[tuple[float, dict]] = []
        self._phys_buf: dict[str, list[tuple[float, dict]]] = {}
        self._w_lo: float | None = None
        self._t_max = -np.inf
        self.late = 0  # samples older than the window already summarised (left out)
        # lane changes found in the SUMO steps so far (time, agent, event number), and up to
        # which SUMO time they have been looked for
        self._lc = (np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64))
        self._lc_until = -np.inf
        self._lc_next = 0

    @property
    def ids(self) -> list[str]:
        return self.agents.ids

    @property
    def index(self) -> dict[str, int]:
        return self.agents.index

    # ---------------------------------------------------------------- input
    def feed(self, inst: str, log_time_ns: int, msg) -> None:
        if isinstance(msg, StaticData):
            self.static = self.static or msg
            return
        if not isinstance(msg, (StepMessage, PhysicsState)):
            return
        t = float(msg.time)
        if self._w_lo is None:
            self._w_lo = float(np.floor(t / self.window_s) * self.window_s)
        elif t < self._w_lo - 1.0:  # the run restarted: finish what came before
            self.flush()
            self._w_lo = float(np.floor(t / self.window_s) * self.window_s)
        if t < self._w_lo:
            self.late += 1
            return
        a = msg.agents
        aid = self.agents(a.ids)
        if isinstance(msg, StepMessage):
            self.steps += 1
            self.t_first = t if self.t_first is None else self.t_first
            self.t_last = t
            self.w_first = log_time_ns if self.w_first is None else self.w_first
            self.w_last = log_time_ns
            cls = np.asarray(a.cls, np.int64)
            if self.first_passenger is None:
                cars = np.flatnonzero(cls == AgentClass.PASSENGER)
                if len(cars):  # first in time, then in SUMO's order
                    self.first_passenger = a.ids[cars[0]]
                    self.wanted.add(self.first_passenger)
            for c in np.unique(cls).tolist():
                self.sumo_seen.setdefault(c, set()).update(aid[cls == c].tolist())
            cols = {"t": np.full(a.n, t), "aid": aid, "x": np.asarray(a.x, np.float64),
                    "y": np.asarray(a.y, np.float64), "angle": np.asarray(a.angle, np.float64),
                    "speed": np.asarray(a.speed, np.float64), "lane": np.asarray(a.lane, np.int64),
                    "cls": cls, "flags": np.asarray(a.flags, np.int64)}
            for name in self.wanted:
                j = self.index.get(name)
                sel = aid == j if j is not None else None
                if sel is not None and sel.any():
                    part = self.track.setdefault(j, {k: [] for k in _TRACK})
                    for k in _TRACK:
                        part[k].append(cols[k][sel])
            self._ref_buf.append((t, cols))
        else:
            cols = {"t": np.full(a.n, t), "aid": aid, "cls": np.asarray(a.cls, np.int64),
                    "mode": np.asarray(a.mode, np.int64),
                    **{k: np.asarray(getattr(a, k), np.float64)
                       for k in ("x", "y", "heading", "speed", "steer", "drive", "brake")}}
            shard = shard_of_instance(inst)
            if shard is None:
                counters = dict(msg.counters)
            else:  # one instance run as shard processes (``--processes``): its samples and summed counters
                per = self._shard_counters.setdefault(shard[0], {})
                per[inst] = msg.counters
                inst = shard[0]
                counters = {}
                for c in per.values():
                    for k, v in c.items():  # counts add up; the shards' own view of their set does not
                        counters[k] = max(counters.get(k, 0), v) if k in SHARD_GAUGES else counters.get(k, 0) + v
            self.inst.setdefault(inst, _Instance()).counters = counters
            self._phys_buf.setdefault(inst, []).append((t, cols))
        self._t_max = max(self._t_max, t)
        while self._t_max >= self._w_lo + 2 * self.window_s:
            self._window(self._w_lo, self._w_lo + self.window_s)
            self._w_lo += self.window_s

    def flush(self) -> None:
        """Summarise everything buffered (the end of the run, or before a restart)."""
        if self._w_lo is not None:
            self._window(self._w_lo, np.inf)
        self._ref_buf.clear()
        self._phys_buf.clear()
        self._lc = (np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64))
        self._lc_until = -np.inf

    # ---------------------------------------------------------------- windows
    @staticmethod
    def _ref_table(buf) -> RefTable:
        keys = ("t", "aid", "x", "y", "angle", "speed", "lane", "cls", "flags")
        return RefTable(**{k: np.concatenate([c[k] for _, c in buf]) if buf else np.zeros(0) for k in keys})

    @staticmethod
    def _phys_table(buf, counters) -> PhysTable:
        keys = ("t", "aid", "cls", "mode", "x", "y", "heading", "speed", "steer", "drive", "brake")
        return PhysTable(**{k: np.concatenate([c[k] for _, c in buf]) if buf else np.zeros(0) for k in keys},
                         counters=counters)

    def _window(self, lo: float, hi: float) -> None:
        """Errors of physics samples at lo <= t < hi (and of SUMO samples in the same range)."""
        ref = self._ref_table(self._ref_buf)
        want = np.array([self.index[n] for n in self.wanted if n in self.index], np.int64)
        # lane changes up to the newest buffered step (the buffer runs a window past hi, so
        # the windows reaching back into this one are known); each looked for once
        ev_t, ev_aid = lane_change_events(ref, self.static, self._lc_until)
        if len(ref.t):
            self._lc_until = max(self._lc_until, float(ref.t.max()))
        if len(ev_t):
            num = np.arange(self._lc_next, self._lc_next + len(ev_t))
            self._lc_next += len(ev_t)
            self._lc = tuple(np.concatenate(p) for p in zip(self._lc, (ev_t, ev_aid, num)))
        lc_t, lc_aid, lc_num = self._lc
        in_junction = internal_lane_mask(self.static, ref.lane)
        for inst, buf in self._phys_buf.items():
            acc = self.inst[inst]
            ph_all = self._phys_table(buf, acc.counters)
            rows = np.flatnonzero((ph_all.t >= lo) & (ph_all.t < hi))
            ph = PhysTable(**{k: getattr(ph_all, k)[rows] for k in (
                "t", "aid", "cls", "mode", "x", "y", "heading", "speed", "steer", "drive", "brake")})
            e = tracking_errors(ref, ph)
            v = e.valid
            acc.overall.add(e.err[v])
            for c in np.unique(ph.cls[v]).tolist():
                acc.per_type.setdefault(c, ErrorHistogram()).add(e.err[v & (ph.cls == c)])
            for m in np.unique(ph.mode).tolist():
                acc.modes.setdefault(m, set()).update(np.unique(ph.aid[ph.mode == m]).tolist())
            own = ph.mode != AgentMode.EXTERNAL
            for c in np.unique(ph.cls[own]).tolist():
                sel = own & (ph.cls == c)
                tally = acc.physical.setdefault(c, [0, 0])
                tally[0] += int(np.count_nonzero(sel & (ph.mode == AgentMode.PHYSICAL)))
                tally[1] += int(np.count_nonzero(sel))
            for c in np.unique(ph.cls).tolist():
                acc.seen.setdefault(c, set()).update(np.unique(ph.aid[ph.cls == c]).tolist())
            # samples whose reference is inside a junction, or that follow one within
            # TURN_SETTLE_S, are the turn's (SUMO changes lanes on normal lanes only; a lane
            # change just before or after a turn must not take its error)
            after_turn = lane_change_cover(ph.t, ph.aid, ref.t[in_junction], ref.aid[in_junction],
                                           before=0.0, after=TURN_SETTLE_S) >= 0
            lv = np.flatnonzero(v & ~internal_lane_mask(self.static, e.ref_lane) & ~after_turn)
            cover = lane_change_cover(ph.t[lv], ph.aid[lv], lc_t, lc_aid)
            inside = cover >= 0
            if inside.any():
                le, c_in, t_in = e.err[lv][inside], cover[inside], ph.t[lv][inside]
                acc.lane_change.add(le)
                acc.lc_events.update(lc_num[c_in].tolist())
                w = int(np.argmax(le))
                if acc.lc_worst is None or le[w] > acc.lc_worst[0]:
                    acc.lc_worst = (float(le[w]), int(lc_aid[c_in[w]]), float(lc_t[c_in[w]]), float(t_in[w]))
            es, ec = sample_errors(ref, ph_all, (lo, hi))
            acc.at_samples.add(es)
            for c in np.unique(ec).tolist():
                acc.at_type.setdefault(c, ErrorHistogram()).add(es[ec == c])
            for j in want.tolist():
                sel = ph.aid == j
                if not sel.any():
                    continue
                part = acc.cand.setdefault(j, {k: [] for k in (*_SERIES, *_ERR_SERIES, "valid")})
                for k in _SERIES:
                    part[k].append(getattr(ph, k)[sel])
                for k in _ERR_SERIES:
                    part[k].append(getattr(e, k)[sel])
                part["valid"].append(v[sel])
        if not np.isfinite(hi):
            return
        keep = lc_t >= hi - LANE_CHANGE_AFTER_S  # windows that reach into the next window
        self._lc = (lc_t[keep], lc_aid[keep], lc_num[keep])
        # keep what brackets the next window: the last SUMO step and physics state before hi
        self._ref_buf = self._keep(self._ref_buf, hi)
        self._phys_buf = {inst: self._keep(buf, hi, back_s=0.0) for inst, buf in self._phys_buf.items()}

    @staticmethod
    def _keep(buf, hi: float, back_s: float = TURN_SETTLE_S):
        """The samples from the last one before ``hi`` on, and ``back_s`` before it (a
        junction sample that far back still tells the next window's samples apart)."""
        before = [t for t, _ in buf if t < hi]
        if not before:
            return buf
        t0 = max(before) - back_s
        return [(t, c) for t, c in buf if t >= t0]

    # ---------------------------------------------------------------- output
    def reference_car(self) -> str | None:
        for name in sorted(self.wanted - {"ref", self.first_passenger}):
            if name in self.index:
                return name
        if "ref" in self.index:
            return "ref"
        return self.first_passenger

    def _cand(self, inst: str, rid: int) -> dict[str, np.ndarray]:
        part = self.inst[inst].cand.get(rid)
        if not part:
            return {k: np.zeros(0) for k in (*_SERIES, *_ERR_SERIES, "valid")}
        return {k: np.concatenate(v) for k, v in part.items()}

    def summary(self) -> dict:
        self.flush()
        ref_id = self.reference_car()
        sim_span = float((self.t_last or 0.0) - (self.t_first or 0.0))
        wall_span = float(((self.w_last or 0) - (self.w_first or 0)) / 1e9)
        out: dict = {
            "steps": self.steps,
            "sim_time_s": round(sim_span, 3),
            "reference_car": ref_id,
            "agents_seen_sumo": self._seen(self.sumo_seen),
            "presets": {},
            "wall": {"wall_s": round(wall_span, 3), "rtf": round(sim_span / wall_span, 3) if wall_span > 0 else None},
        }
        rid = self.index.get(ref_id, -1) if ref_id else -1
        for inst, acc in sorted(self.inst.items()):
            c = acc.counters
            entry = {
                "error_m": {"overall": acc.overall.stats(),
                            "per_type": {CLASS_NAMES[k]: h.stats() for k, h in sorted(acc.per_type.items())},
                            "at_samples": {"overall": acc.at_samples.stats(), "per_type": {
                                CLASS_NAMES[k]: h.stats() for k, h in sorted(acc.at_type.items())}}},
                "collisions": int(c.get("collisions", 0)),
                # a physics contact where SUMO had its own collision / teleport, or physics only
                "collisions_sumo_reported": int(c.get("collisions_sumo_reported", 0)),
                "collisions_physics_only": int(c.get("collisions_physics_only", 0)),
                "placements": int(c.get("placements", 0)),
                "placements_by_cause": {k: int(c.get(f"placements_{k}", 0))
                                        for k in ("spawn", "jump", "divergence", "flip")},
                # manoeuvres beyond the vehicle's steering or a rider's lean (U-turns...) shown kinematic: how many
                # and for how long; their samples are not PHYSICAL, so not in the errors above
                "carries_infeasible": {"count": int(c.get("carries_infeasible", 0)),
                                       "agent_s": round(int(c.get("carried_infeasible_ms", 0)) / 1e3, 3)},
                # agents about to touch where SUMO has a gap, shown kinematic on SUMO's poses
                # (the contact guard): how many and for how long; not in the errors either
                "carries_contact": {"count": int(c.get("carries_contact", 0)),
                                    "agent_s": round(int(c.get("carried_contact_ms", 0)) / 1e3, 3)},
                "ghost_spawns": int(c.get("ghost_spawns", 0)),
                # placed (teleport, slide, divergence, flip) into an occupied spot: passes through until clear
                "ghost_placements": int(c.get("ghost_placements", 0)),
                "rejected": int(c.get("rejected", 0)),
                "agents_seen": self._seen(acc.seen),
                "agents_by_mode": {m.name.lower(): len(acc.modes.get(int(m), ())) for m in AgentMode},
                **physical_share(acc.physical),
                "counters": {k: int(x) for k, x in sorted(c.items())},
            }
            lc = acc.lane_change.stats()
            entry["lane_changes"] = {
                "count": len(acc.lc_events), "max_error_m": lc["max"], "p95_error_m": lc["p95"],
                "samples": lc["samples"],
                # where the maximum is: the agent, the time its lane index changed and the
                # time of the sample [s]
                "worst": None if acc.lc_worst is None else {
                    "agent": self.ids[acc.lc_worst[1]], "t": round(acc.lc_worst[2], 3),
                    "at_s": round(acc.lc_worst[3], 3), "error_m": round(acc.lc_worst[0], 4)},
            }
            if rid >= 0:
                s = self._cand(inst, rid)
                r = s["valid"].astype(bool)
                turn = internal_lane_mask(self.static, s["ref_lane"].astype(np.int64))
                entry["reference_car"] = {
                    "overall": _stats(s["err"][r]),
                    "straight": _stats(s["err"][r & ~turn]),
                    "turn": _stats(s["err"][r & turn]),
                    "lateral_abs_max": _stats(np.abs(s["lat"][r]))["max"],
                }
            out["presets"][inst] = entry
        return out

    @staticmethod
    def _seen(sets: dict[int, set]) -> dict:
        return {CLASS_NAMES.get(c, str(c)): len(v) for c, v in sorted(sets.items())}

    def figure_data(self, ref_id: str) -> "FigureData":
        """The reference car's series per instance (physics samples with a reference) and its
        SUMO samples, each in time order."""
        rid = self.index[ref_id]
        series = {}
        for inst in sorted(self.inst):
            s = self._cand(inst, rid)
            sel = np.isfinite(s["err"])
            order = np.argsort(s["t"][sel], kind="stable")
            d = {k: s[k][sel][order] for k in (*_SERIES, *_ERR_SERIES) if k != "ref_lane"}
            d["dist"] = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(d["ref_x"]), np.diff(d["ref_y"])))]) \
                if len(d["t"]) else np.zeros(0)
            series[inst] = d
        part = self.track.get(rid)
        track = {k: np.concatenate(part[k]) if part else np.zeros(0) for k in _TRACK}
        order = np.argsort(track["t"], kind="stable")
        track = {k: v[order] for k, v in track.items()}
        return FigureData(self.static, series, track)


@dataclass
class FigureData:
    """What the figures draw: the reference car only."""

    static: StaticData | None
    series: dict[str, dict[str, np.ndarray]]  # per instance: physics samples with their reference
    track: dict[str, np.ndarray]  # SUMO samples: t, x, y, angle, speed, lane


def analyse_recording(res: ReadResult | Recording, ref_id: str | None = None,
                      window_s: float = Analysis.WINDOW_S) -> tuple[dict, FigureData | None]:
    """Summary and figure data of a recording, read as a stream (memory flat in its length)."""
    an = Analysis(ref_id, window_s)
    for m, msg in iter_decoded(res):
        an.feed(Keys.instance_of(m.topic) or "main", m.log_time_ns, msg)
    summary = an.summary()
    if res.truncated:  # known only once a stream has been read to its end
        summary["truncated_recording"] = True
    rid = summary["reference_car"]
    return summary, (an.figure_data(rid) if rid and an.inst else None)


def _feed_tables(an: Analysis, data: RunData) -> None:
    """Run data already in memory, summarised as one window."""
    an.static = data.static
    an.agents = AgentIndex(data.ids)
    an.steps = data.steps
    an.t_first, an.t_last = 0.0, data.sim_span_s
    an.w_first, an.w_last = 0, int(round(data.wall_span_s * 1e9))
    for c in np.unique(data.ref.cls).tolist():
        an.sumo_seen[c] = set(np.unique(data.ref.aid[data.ref.cls == c]).tolist())
    rows = np.argsort(data.ref.t, kind="stable")
    an._ref_buf = [(float(data.ref.t[rows[-1]]) if len(rows) else 0.0,
                    {k: getattr(data.ref, k)[rows] for k in ("t", "aid", "x", "y", "angle", "speed", "lane", "cls",
                                                             "flags")})]
    for inst, ph in data.phys.items():
        an.inst[inst] = _Instance()
        an.inst[inst].counters = dict(ph.counters)
        an._phys_buf[inst] = [(0.0, {k: getattr(ph, k) for k in (
            "t", "aid", "cls", "mode", "x", "y", "heading", "speed", "steer", "drive", "brake")})]
    rid = an.index.get(an.reference_car())
    if rid is not None:
        sel = data.ref.aid[rows] == rid
        an.track[rid] = {k: [getattr(data.ref, k)[rows][sel]] for k in _TRACK}
    an._w_lo = -np.inf


def physical_share(tally: dict[int, list[int]]) -> dict:
    """Share of agent-time driven by physics (mode PHYSICAL: not carried, not placed
    kinematically) over all vehicle agent-time, egos left out; pedestrians apart."""
    ped = int(AgentClass.PEDESTRIAN)
    veh = [v for c, v in tally.items() if c != ped]
    num, den = sum(v[0] for v in veh), sum(v[1] for v in veh)
    p = tally.get(ped, [0, 0])
    return {
        "physical_share": round(num / den, 4) if den else None,
        "physical_share_by_type": {CLASS_NAMES[c]: round(v[0] / v[1], 4) for c, v in sorted(tally.items())
                                   if v[1] and c != ped},
        "physical_share_pedestrians": round(p[0] / p[1], 4) if p[1] else None,
    }


def summarise(data: RunData, ref_id: str | None = None) -> dict:
    """Summary of run data held in memory (the same numbers as ``analyse_recording``)."""
    an = Analysis(ref_id or reference_car(data))
    an.first_passenger = reference_car(data, prefer="\0")
    _feed_tables(an, data)
    summary = an.summary()
    if data.truncated:
        summary["truncated_recording"] = True
    return summary
