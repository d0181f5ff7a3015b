"""Tracking analysis of a recorded run: tables of SUMO and physics samples, errors, summary.

Error metric (the same for every preset): the physics agent's *front-bumper centre* at
physics time t against SUMO's front-bumper centre at the same t, interpolated between
the two SUMO steps around t along a cubic Hermite curve with the samples' headings (a
straight line between samples would cut curves at long SUMO steps). Only agents in mode PHYSICAL count; kinematic and
external (ego) agents are reported apart. Samples next to a SUMO step that flags the
agent as jumped (teleport) or riding are left out: there SUMO moves the agent by fiat.

``report`` (summary.json, report.md) and ``figures`` both read from here.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from protocol.keys import Keys
from protocol.messages import AgentClass, AgentFlag, AgentMode, PhysicsState, StaticData, StepMessage
from sumoco.app.record import ReadResult, Recording, iter_decoded, read_recording

log = logging.getLogger(__name__)

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
    index: dict[str, int] = {}
    ids: list[str] = []

    def aids(names: list[str]) -> np.ndarray:
        out = np.empty(len(names), np.int64)
        for i, n in enumerate(names):
            j = index.get(n)
            if j is None:
                j = index[n] = len(ids)
                ids.append(n)
            out[i] = j
        return out

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
        static=static, ids=ids, ref=ref, phys=phys, steps=steps,
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
        rx, ry = _hermite(pt, rt, ref.x[rs], ref.y[rs], ang)
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


def sample_errors(ref: RefTable, ph: PhysTable) -> tuple[np.ndarray, np.ndarray]:
    """Front-bumper error [m] at SUMO's own sample times only, and the class of each sample.

    Between samples SUMO's position is not defined (``tracking_errors`` assumes a constant
    speed along a Hermite curve, which at 1 s steps differs from any drivable motion by up
    to a * step^2 / 8); at a sample it is exact. The physics pose is interpolated between
    the two published states around the sample time (at most 0.11 s apart). Same validity
    rules as ``tracking_errors`` (PHYSICAL on both sides, no jump or ride next to it)."""
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
        idx = np.flatnonzero((rt >= pt[0]) & (rt <= pt[-1]))
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


def _hermite(pt: np.ndarray, rt: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray):
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


def summarise(data: RunData, ref_id: str | None = None) -> dict:
    ref_id = ref_id or reference_car(data)
    summary: dict = {
        "steps": data.steps,
        "sim_time_s": round(data.sim_span_s, 3),
        "reference_car": ref_id,
        "agents_seen_sumo": _seen(data.ref.aid, data.ref.cls),
        "presets": {},
        "wall": {
            "wall_s": round(data.wall_span_s, 3),
            "rtf": round(data.sim_span_s / data.wall_span_s, 3) if data.wall_span_s > 0 else None,
        },
    }
    if data.truncated:
        summary["truncated_recording"] = True
    rid = data.ids.index(ref_id) if ref_id in data.ids else -1
    for inst, ph in sorted(data.phys.items()):
        e = tracking_errors(data.ref, ph)
        v = e.valid
        per_type = {CLASS_NAMES[int(c)]: _stats(e.err[v & (ph.cls == c)]) for c in np.unique(ph.cls[v])}
        modes = {m.name.lower(): int(len(np.unique(ph.aid[ph.mode == m]))) for m in AgentMode}
        es, ec = sample_errors(data.ref, ph)
        entry = {
            "error_m": {"overall": _stats(e.err[v]), "per_type": per_type,
                        "at_samples": {"overall": _stats(es), "per_type": {
                            CLASS_NAMES[int(c)]: _stats(es[ec == c]) for c in np.unique(ec)}}},
            "collisions": int(ph.counters.get("collisions", 0)),
            # a physics contact where SUMO had its own collision / teleport, or physics only
            "collisions_sumo_reported": int(ph.counters.get("collisions_sumo_reported", 0)),
            "collisions_physics_only": int(ph.counters.get("collisions_physics_only", 0)),
            "placements": int(ph.counters.get("placements", 0)),
            "placements_by_cause": {c: int(ph.counters.get(f"placements_{c}", 0))
                                    for c in ("spawn", "jump", "divergence", "flip")},
            "ghost_spawns": int(ph.counters.get("ghost_spawns", 0)),
            "rejected": int(ph.counters.get("rejected", 0)),
            "agents_seen": _seen(ph.aid, ph.cls),
            "agents_by_mode": modes,
            "counters": {k: int(x) for k, x in sorted(ph.counters.items())},
        }
        if rid >= 0:
            r = v & (ph.aid == rid)
            turn = internal_lane_mask(data.static, e.ref_lane)
            entry["reference_car"] = {
                "overall": _stats(e.err[r]),
                "straight": _stats(e.err[r & ~turn]),
                "turn": _stats(e.err[r & turn]),
                "lateral_abs_max": _stats(np.abs(e.lat[r]))["max"],
            }
        summary["presets"][inst] = entry
    return summary


def _seen(aid: np.ndarray, cls: np.ndarray) -> dict:
    out = {}
    for c in np.unique(cls):
        out[CLASS_NAMES.get(int(c), str(int(c)))] = int(len(np.unique(aid[cls == c])))
    return out


def ref_series(data: RunData, inst: str, ref_id: str) -> dict[str, np.ndarray]:
    """Time series of the reference car in one instance (for the figures)."""
    ph = data.phys[inst]
    rid = data.ids.index(ref_id)
    e = tracking_errors(data.ref, ph)
    sel = (ph.aid == rid) & np.isfinite(e.err)
    order = np.argsort(ph.t[sel])
    s = {k: getattr(ph, k)[sel][order] for k in ("t", "x", "y", "speed", "steer", "drive", "brake")}
    s.update({k: getattr(e, k)[sel][order] for k in ("err", "lon", "lat", "ref_x", "ref_y", "ref_speed")})
    s["dist"] = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(s["ref_x"]), np.diff(s["ref_y"])))])
    return s


def ref_track(data: RunData, ref_id: str) -> dict[str, np.ndarray]:
    """The reference car's SUMO samples (10 Hz): t, x, y, angle, speed."""
    rid = data.ids.index(ref_id)
    sel = data.ref.aid == rid
    order = np.argsort(data.ref.t[sel])
    return {k: getattr(data.ref, k)[sel][order] for k in ("t", "x", "y", "angle", "speed", "lane")}


