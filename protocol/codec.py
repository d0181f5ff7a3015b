"""msgpack codec for every sumoco message, versioned and validating.

Layout (SPEC.md has the language-neutral version): every message is one msgpack map
with ``v`` = [major, minor] and ``kind``. Per-agent fields are *columns*: one msgpack
``bin`` holding ``n`` little-endian values, so a decoder gets numpy-ready arrays with one
``frombuffer`` per field and a C#/C++/TypeScript client gets typed arrays just as cheaply.

Decoding validates structure, types, sizes and finiteness and raises ``ProtocolError``
naming the field and the expectation; no other exception escapes ``decode``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Union

import msgpack
import numpy as np

from protocol.errors import ProtocolError
from protocol.messages import (
    SCHEMA_VERSION,
    AgentBatch,
    AgentClass,
    AgentMode,
    CameraPose,
    EgoPose,
    JunctionTable,
    LaneTable,
    PhysicsAgents,
    PhysicsFeedback,
    PhysicsState,
    StaticData,
    StepAck,
    StepMessage,
    SumoStatus,
    TlsLinks,
    TrafficLights,
    VType,
)

Message = Union[StepMessage, EgoPose, CameraPose, PhysicsState, PhysicsFeedback, StepAck, StaticData, SumoStatus]

#: Hard limits that make a hostile or corrupt message fail fast instead of allocating.
MAX_AGENTS = 200_000
MAX_POINTS = 20_000_000
MAX_STR = 1_024
MAX_MESSAGE_BYTES = 256 * 1024 * 1024
MAX_VTYPES = 65_535  # u16 index
MAX_STATIC_ROWS = 2_000_000  # lanes, junctions, tls links of the largest networks, with margin


@dataclass(frozen=True)
class DecodeLimits:
    """Bounds applied while msgpack parses, before any array is built (SPEC.md 5).

    ``max_agents`` is the largest agent table a receiver accepts; every msgpack length
    limit follows from it and from the static-table bounds, so a hostile length prefix
    fails inside the parser instead of allocating.
    """

    max_agents: int = MAX_AGENTS
    """Agents per step or physics message."""
    max_static_rows: int = MAX_STATIC_ROWS
    """Lanes, junctions, traffic lights or tls links in static data."""
    max_points: int = MAX_POINTS
    """Vertices of one polyline table (paths ahead, lane shapes)."""
    max_str: int = MAX_STR
    """Characters of one string (ids)."""
    max_bytes: int = MAX_MESSAGE_BYTES
    """Bytes of one message."""

    def __post_init__(self) -> None:
        for name in ("max_agents", "max_static_rows", "max_points", "max_str", "max_bytes"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"DecodeLimits.{name} must be >= 1, got {getattr(self, name)}")

    @classmethod
    def for_agents(cls, max_agents: int) -> "DecodeLimits":
        """Limits for the live messages (steps, physics states, acks, egos) of a receiver
        configured for at most ``max_agents`` agents: arrays hold at most that many agents
        or 65,535 traffic lights (their index is u16), paths up to 200 vertices per agent.
        Static data needs the default limits (a city has more lanes than agents)."""
        n = max(1, int(max_agents))
        return cls(max_agents=n, max_static_rows=MAX_VTYPES, max_points=max(MAX_POINTS // 100, 200 * n),
                   max_bytes=min(MAX_MESSAGE_BYTES, (1 << 20) + 4096 * n))

    def unpack_kwargs(self) -> dict[str, int]:
        return self._limits_kw()

    def _unpack_kw(self) -> dict[str, Any]:
        """``unpack_kwargs`` plus the decoder's fixed options, built once per limits."""
        kw = self.__dict__.get("_kw")
        if kw is None:
            kw = {"raw": False, "strict_map_key": True, "use_list": True, **self._limits_kw()}
            object.__setattr__(self, "_kw", kw)  # a cache, not a field (eq and hash ignore it)
        return kw

    def _limits_kw(self) -> dict[str, int]:
        rows = max(self.max_agents, self.max_static_rows)
        return {
            "max_str_len": 4 * self.max_str,  # UTF-8 bytes
            "max_bin_len": max(16 * self.max_points, 8 * rows) + 16,
            "max_array_len": rows,
            "max_map_len": 4_096,  # the widest map is a counters map
            "max_ext_len": 0,  # no ext types on this wire
        }


DEFAULT_LIMITS = DecodeLimits()

# Column tables: (field name == wire key, little-endian dtype). Order is the SPEC order.
STEP_AGENT_COLUMNS: tuple[tuple[str, str], ...] = (
    ("cls", "<u1"),
    ("vtype", "<u2"),
    ("x", "<f8"),
    ("y", "<f8"),
    ("angle", "<f4"),
    ("speed", "<f4"),
    ("accel", "<f4"),
    ("signals", "<u2"),
    ("la_dx", "<f4"),
    ("la_dy", "<f4"),
    ("length", "<f4"),
    ("width", "<f4"),
    ("lane", "<i4"),
    ("flags", "<u1"),
)

PHYSICS_AGENT_COLUMNS: tuple[tuple[str, str], ...] = (
    ("cls", "<u1"),
    ("mode", "<u1"),
    ("x", "<f8"),
    ("y", "<f8"),
    ("z", "<f4"),
    ("heading", "<f4"),
    ("roll", "<f4"),
    ("pitch", "<f4"),
    ("speed", "<f4"),
    ("steer", "<f4"),
    ("drive", "<f4"),
    ("brake", "<f4"),
    ("err_lon", "<f4"),
    ("err_lat", "<f4"),
)

FEEDBACK_COLUMNS: tuple[tuple[str, str], ...] = (
    ("x", "<f8"),
    ("y", "<f8"),
    ("heading", "<f4"),
    ("speed", "<f4"),
    ("d_lon", "<f4"),
    ("d_lat", "<f4"),
    ("contact", "<u1"),
)

TLS_LINK_COLUMNS: tuple[tuple[str, str], ...] = (
    ("tls", "<u2"),
    ("link", "<u2"),
    ("from_lane", "<i4"),
    ("to_lane", "<i4"),
    ("via_lane", "<i4"),
)

#: 1.1 senders put absolute float32 look-ahead points instead of ``la_dx``/``la_dy``.
STEP_AGENT_COLUMNS_1_1: tuple[tuple[str, str], ...] = tuple(
    (("la_x" if k == "la_dx" else "la_y" if k == "la_dy" else k), dt) for k, dt in STEP_AGENT_COLUMNS
)

#: Value bounds per float column [unit of the column]: generous physical limits so that a
#: corrupt or hostile value is rejected with its field named instead of reaching a solver.
COORD_LIMIT = 1e8  # [m] absolute positions
OFFSET_LIMIT = 1e5  # [m] look-ahead / path offsets from the agent's position
FLOAT_BOUNDS: dict[str, tuple[float, float]] = {
    "x": (-COORD_LIMIT, COORD_LIMIT), "y": (-COORD_LIMIT, COORD_LIMIT),
    "la_x": (-COORD_LIMIT, COORD_LIMIT), "la_y": (-COORD_LIMIT, COORD_LIMIT),
    "la_dx": (-OFFSET_LIMIT, OFFSET_LIMIT), "la_dy": (-OFFSET_LIMIT, OFFSET_LIMIT),
    "angle": (-720.0, 720.0), "heading": (-720.0, 720.0),
    "roll": (-720.0, 720.0), "pitch": (-720.0, 720.0), "steer": (-720.0, 720.0),
    "speed": (-1_000.0, 1_000.0), "accel": (-1e5, 1e5),
    "length": (0.0, 1_000.0), "width": (0.0, 1_000.0), "z": (-1e5, 1e5),
    "drive": (-1e9, 1e9), "brake": (-1e9, 1e9),
    "err_lon": (-COORD_LIMIT, COORD_LIMIT), "err_lat": (-COORD_LIMIT, COORD_LIMIT),
    "d_lon": (-COORD_LIMIT, COORD_LIMIT), "d_lat": (-COORD_LIMIT, COORD_LIMIT),
}

_N_CLASSES = len(AgentClass)
_N_MODES = len(AgentMode)


# --------------------------------------------------------------------------- encoding


def _bin(a: np.ndarray, dtype: str) -> memoryview:
    # msgpack packs any C-contiguous buffer as bin straight from the array (its byte length,
    # whatever its shape or item format): no intermediate bytes copy, no reshape or cast
    return memoryview(np.ascontiguousarray(a, dtype=dtype))


def _columns(obj: Any, spec: tuple[tuple[str, str], ...]) -> dict[str, bytes]:
    return {name: _bin(getattr(obj, name), dt) for name, dt in spec}


def _head(kind: str) -> dict[str, Any]:
    return {"v": list(SCHEMA_VERSION), "kind": kind}


def _polyline(offsets: np.ndarray, xy: np.ndarray) -> dict[str, bytes]:
    """Static polyline: float64 ``xy64`` plus float32 ``xy`` for 1.1 readers."""
    flat = np.asarray(xy, np.float64).reshape(-1)
    return {"off": _bin(offsets, "<u4"), "xy": _bin(flat, "<f4"), "xy64": _bin(flat, "<f8")}


def _anchored_path(offsets: np.ndarray, xy: np.ndarray, x: np.ndarray, y: np.ndarray) -> dict[str, bytes]:
    """Path polyline as float32 offsets from its agent's float64 (x, y) (SPEC.md 3.1)."""
    off = np.asarray(offsets, np.int64)
    first, last = off[[0, -1]].tolist()
    pts = np.asarray(xy, np.float64).reshape(-1, 2)[first:last]
    anchor = np.repeat(np.column_stack((x, y)), np.diff(off), axis=0)
    # float64 difference rounded once to float32, written straight into the wire column
    dxy = np.subtract(pts, anchor, out=np.empty(pts.shape, "<f4"), dtype=np.float64, casting="same_kind")
    return {"off": _bin(off - first if first else off, "<u4"), "dxy": memoryview(dxy)}


def encode(msg: Message) -> bytes:
    """Encode any protocol message to msgpack bytes."""
    if isinstance(msg, StepMessage):
        a = msg.agents
        x = np.asarray(a.x, np.float64)
        y = np.asarray(a.y, np.float64)
        agents = {"n": a.n, "id": list(a.ids)}
        for name, dt in STEP_AGENT_COLUMNS:
            if name == "la_dx":
                agents[name] = _bin(np.subtract(a.la_x, x, dtype=np.float64), dt)
            elif name == "la_dy":
                agents[name] = _bin(np.subtract(a.la_y, y, dtype=np.float64), dt)
            else:
                agents[name] = _bin(getattr(a, name), dt)
        if len(a.path_offsets):
            agents["path"] = _anchored_path(a.path_offsets, a.path_xy, x, y)
        tls = {
            "id": list(msg.tls.ids),
            "state": list(msg.tls.state),
            "phase": np.asarray(msg.tls.phase, np.int64).tolist(),  # Python ints and floats, one call each
            "next": np.asarray(msg.tls.next_switch, np.float64).tolist(),
        }
        if msg.tls.program is not None:
            tls["program"] = list(msg.tls.program)
        d = _head("step") | {
            "run": msg.run,
            "step": int(msg.step),
            "t": float(msg.time),
            "dt": float(msg.step_length),
            "sv": int(msg.static_version),
            "agents": agents,
            "tls": tls,
        }
        if msg.vtypes is not None:
            d["vtypes"] = [[v.id, v.vclass] for v in msg.vtypes]
        if msg.final:  # optional (older readers ignore it); absent means false
            d["final"] = True
    elif isinstance(msg, EgoPose):
        d = _head("ego") | {
            "id": msg.id, "x": float(msg.x), "y": float(msg.y), "angle": float(msg.angle),
            "speed": float(msg.speed), "t": float(msg.time), "vtype": msg.vtype,
        }
    elif isinstance(msg, CameraPose):
        d = _head("camera") | {"id": msg.id, "x": float(msg.x), "y": float(msg.y), "t": float(msg.time)}
    elif isinstance(msg, PhysicsState):
        a = msg.agents
        d = _head("physics") | {
            "run": msg.run,
            "tick": int(msg.tick),
            "t": float(msg.time),
            "sumo_step": int(msg.sumo_step),
            "agents": {"n": a.n, "id": list(a.ids), **_columns(a, PHYSICS_AGENT_COLUMNS)},
            "counters": {str(k): int(v) for k, v in msg.counters.items()},
        }
    elif isinstance(msg, PhysicsFeedback):
        d = _head("feedback") | {
            "run": msg.run, "step": int(msg.step), "t": float(msg.time),
            "agents": {"n": msg.n, "id": list(msg.ids), **_columns(msg, FEEDBACK_COLUMNS)},
        }
    elif isinstance(msg, StepAck):
        d = _head("ack") | {"run": msg.run, "step": int(msg.step), "tick": int(msg.tick)}
        if msg.feedback:  # optional (1.3): absent means False
            d["fb"] = True
    elif isinstance(msg, SumoStatus):
        d = _head("status") | {"counters": {str(k): v if isinstance(v, int) else float(v)
                                            for k, v in msg.counters.items()}}
    elif isinstance(msg, StaticData):
        ln = msg.lanes
        d = _head("static") | {
            "run": msg.run,
            "sv": int(msg.version),
            "dt": float(msg.step_length),
            "net": {
                "offset": [float(v) for v in msg.net_offset],
                "proj": msg.projection,
                "bounds": [float(v) for v in msg.bounds],
            },
            "lanes": {
                "n": len(ln.ids),
                "id": list(ln.ids),
                "edge": list(ln.edge),
                "width": _bin(ln.width, "<f4"),
                "length": _bin(ln.length, "<f4"),
                "allow": [list(a) for a in ln.allow],
                "shape": _polyline(ln.shape_offsets, ln.shape_xy),
            },
            "junctions": {
                "n": len(msg.junctions.ids),
                "id": list(msg.junctions.ids),
                "shape": _polyline(msg.junctions.shape_offsets, msg.junctions.shape_xy),
            },
            "vtypes": {
                "n": len(msg.vtypes),
                "id": [v.id for v in msg.vtypes],
                "vclass": [v.vclass for v in msg.vtypes],
                "length": _bin(msg.vtype_length, "<f4"),
                "width": _bin(msg.vtype_width, "<f4"),
            },
            "tls": list(msg.tls_ids),
            "tls_links": {"n": len(msg.tls_links.tls), **_columns(msg.tls_links, TLS_LINK_COLUMNS)},
        }
    else:
        raise TypeError(f"not a protocol message: {type(msg).__name__}")
    return msgpack.packb(d, use_bin_type=True)


# --------------------------------------------------------------------------- decoding


def _get(d: dict, key: str, where: str) -> Any:
    try:
        return d[key]
    except KeyError:
        raise ProtocolError("missing field", f"{where}{key}") from None


def _int(d: dict, key: str, where: str, lo: int = -(2**63), hi: int = 2**63 - 1) -> int:
    v = _get(d, key, where)
    if not isinstance(v, int) or isinstance(v, bool):
        raise ProtocolError(f"expected an integer, got {type(v).__name__}", where + key)
    if not lo <= v <= hi:
        raise ProtocolError(f"expected {lo}..{hi}, got {v}", where + key)
    return v


def _float(d: dict, key: str, where: str, lo: float = -math.inf, hi: float = math.inf) -> float:
    v = _get(d, key, where)
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        raise ProtocolError(f"expected a number, got {type(v).__name__}", where + key)
    v = float(v)
    if not math.isfinite(v):
        raise ProtocolError(f"expected a finite number, got {v}", where + key)
    if not lo <= v <= hi:
        raise ProtocolError(f"expected {lo}..{hi}, got {v}", where + key)
    return v


class _Reader:
    """Field readers bound to one set of ``DecodeLimits``."""

    def __init__(self, lim: DecodeLimits) -> None:
        self.lim = lim

    def str(self, d: dict, key: str, where: str) -> str:
        v = _get(d, key, where)
        if not isinstance(v, str):
            raise ProtocolError(f"expected a string, got {type(v).__name__}", where + key)
        if len(v) > self.lim.max_str:
            raise ProtocolError(f"expected at most {self.lim.max_str} characters, got {len(v)}", where + key)
        return v

    def strs(self, d: dict, key: str, where: str, n: int | None = None, unique: bool = False) -> list[str]:
        v = _list(d, key, where, n)
        m = self.lim.max_str
        # C-level passes instead of a Python loop per id: join fails on any non-string,
        # and a joined length within the limit bounds every single length.
        try:
            total = len("".join(v))
        except TypeError:
            raise ProtocolError(f"expected strings of at most {m} characters", where + key) from None
        if total > m and max(map(len, v)) > m:
            raise ProtocolError(f"expected strings of at most {m} characters", where + key)
        if unique and len(set(v)) != len(v):
            seen: set[str] = set()
            dup = next(s for s in v if s in seen or seen.add(s))  # type: ignore[func-returns-value]
            raise ProtocolError(f"expected unique ids, {dup!r} appears twice", where + key)
        return v

    def count(self, d: dict, where: str, limit: int) -> int:
        return _int(d, "n", where, 0, limit)

    def polyline(self, d: dict, key: str, n: int, where: str) -> tuple[np.ndarray, np.ndarray]:
        """Static polyline: prefers float64 ``xy64`` (1.2), else float32 ``xy`` (1.1)."""
        p = _map(d, key, where)
        w = f"{where}{key}."
        off = _col(p, "off", "<u4", n + 1, w)
        wide = "xy64" in p
        name, dt, size = ("xy64", "<f8", 16) if wide else ("xy", "<f4", 8)
        b = _get(p, name, w)
        if not isinstance(b, bytes) or len(b) % size:
            raise ProtocolError(f"expected bin of {dt} (x, y) pairs", w + name)
        m = len(b) // size
        self._points(m, w + name)
        xy = _col(p, name, dt, 2 * m, w, (-COORD_LIMIT, COORD_LIMIT)).reshape(m, 2)
        _check_offsets(off, n, m, w)
        return off, xy.astype(np.float64)

    def path(self, a: dict, n: int, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Path ahead: float32 offsets ``dxy`` from each agent's (x, y) (1.2) or absolute ``xy`` (1.1)."""
        p = _map(a, "path", "agents.")
        w = "agents.path."
        off = _col(p, "off", "<u4", n + 1, w)
        rel = "dxy" in p
        name = "dxy" if rel else "xy"
        b = _get(p, name, w)
        if not isinstance(b, bytes) or len(b) % 8:
            raise ProtocolError("expected bin of float32 (x, y) pairs", w + name)
        m = len(b) // 8
        self._points(m, w + name)
        bound = (-OFFSET_LIMIT, OFFSET_LIMIT) if rel else (-COORD_LIMIT, COORD_LIMIT)
        xy = _col(p, name, "<f4", 2 * m, w, bound).reshape(m, 2)
        _check_offsets(off, n, m, w)
        if rel and m:
            # one pass: float32 offsets + each agent's float64 (x, y) repeated per vertex
            return off, np.add(xy, np.repeat(np.column_stack((x, y)), np.diff(off.astype(np.int64)), axis=0))
        return off, xy.astype(np.float64)

    def _points(self, m: int, field: str) -> None:
        if m > self.lim.max_points:
            raise ProtocolError(f"expected at most {self.lim.max_points} points, got {m}", field)


def _check_offsets(off: np.ndarray, n: int, m: int, w: str) -> None:
    if off[0] != 0 or off[-1] != m or (n and np.any(np.diff(off.astype(np.int64)) < 0)):
        raise ProtocolError(f"expected offsets rising from 0 to {m}", w + "off")


def _map(d: dict, key: str, where: str) -> dict:
    v = _get(d, key, where)
    if not isinstance(v, dict):
        raise ProtocolError(f"expected a map, got {type(v).__name__}", where + key)
    return v


def _list(d: dict, key: str, where: str, n: int | None = None) -> list:
    v = _get(d, key, where)
    if not isinstance(v, list):
        raise ProtocolError(f"expected an array, got {type(v).__name__}", where + key)
    if n is not None and len(v) != n:
        raise ProtocolError(f"expected {n} elements, got {len(v)}", where + key)
    return v


def _col(d: dict, key: str, dtype: str, n: int, where: str,
         bounds: tuple[float, float] | None = None) -> np.ndarray:
    b = _get(d, key, where)
    if not isinstance(b, bytes):
        raise ProtocolError(f"expected bin of {n} x {dtype}, got {type(b).__name__}", where + key)
    size = np.dtype(dtype).itemsize
    if len(b) != n * size:
        raise ProtocolError(
            f"expected {n} x {dtype} = {n * size} bytes, got {len(b)}", where + key
        )
    a = np.frombuffer(b, dtype=dtype)
    if a.dtype.kind == "f" and n:
        lo, hi = bounds if bounds is not None else FLOAT_BOUNDS.get(key, (-math.inf, math.inf))
        amin, amax = float(a.min()), float(a.max())  # NaN propagates into both
        if not (math.isfinite(amin) and math.isfinite(amax)):
            raise ProtocolError("expected finite values, got NaN or inf", where + key)
        if amin < lo or amax > hi:
            bad = amin if amin < lo else amax
            raise ProtocolError(f"expected values in {lo:g}..{hi:g}, got {bad:g}", where + key)
    return a


_GROUPS: dict[tuple, list[tuple[str, list[str], list[tuple[float, float]]]]] = {}


def _groups(spec: tuple[tuple[str, str], ...]) -> list[tuple[str, list[str], list[tuple[float, float]]]]:
    """``spec``'s columns grouped by dtype, with each float column's bounds (cached)."""
    g = _GROUPS.get(spec)
    if g is None:
        by: dict[str, list[str]] = {}
        for name, dt in spec:
            by.setdefault(dt, []).append(name)
        g = [(dt, names, [FLOAT_BOUNDS.get(k, (-math.inf, math.inf)) for k in names]) for dt, names in by.items()]
        _GROUPS[spec] = g
    return g


def _columns_in(d: dict, spec, n: int, where: str) -> dict[str, np.ndarray]:
    """The columns of ``spec``, validated as ``_col`` does, with one array and one
    min/max pass per dtype instead of per column (a step has 14 columns): every numpy
    call counts, as a step's decode runs with cold caches between steps."""
    out: dict[str, np.ndarray] = {}
    for dt, names, bounds in _groups(spec):
        size = np.dtype(dt).itemsize
        bins = []
        for name in names:
            b = _get(d, name, where)
            if not isinstance(b, bytes):
                raise ProtocolError(f"expected bin of {n} x {dt}, got {type(b).__name__}", where + name)
            if len(b) != n * size:
                raise ProtocolError(f"expected {n} x {dt} = {n * size} bytes, got {len(b)}", where + name)
            bins.append(b)
        block = np.frombuffer(bins[0] if len(bins) == 1 else b"".join(bins), dt).reshape(len(names), n)
        if n and block.dtype.kind == "f":
            # NaN propagates into min and max, and fails every comparison below
            for i, (a, b, (lo, hi)) in enumerate(zip(block.min(axis=1).tolist(), block.max(axis=1).tolist(), bounds)):
                if not (lo <= a and b <= hi and math.isfinite(a) and math.isfinite(b)):
                    _col(d, names[i], dt, n, where)  # raises with the column's message
        out.update(zip(names, block))  # row views, no copies
    return out


def _check_range(a: np.ndarray, lo: int, hi: int, field: str) -> None:
    if not len(a):
        return
    # a bound the dtype already guarantees needs no pass over the data (u8 >= 0, i4 <= 2^31-1)
    bits = 8 * a.dtype.itemsize
    signed = a.dtype.kind == "i"
    if lo > (-(1 << (bits - 1)) if signed else 0):
        m = int(a.min())
        if m < lo:
            raise ProtocolError(f"expected values in {lo}..{hi}, got {m}", field)
    if hi < ((1 << (bits - 1)) - 1 if signed else (1 << bits) - 1):
        m = int(a.max())
        if m > hi:
            raise ProtocolError(f"expected values in {lo}..{hi}, got {m}", field)


def decode(data: bytes | bytearray | memoryview, limits: DecodeLimits = DEFAULT_LIMITS) -> Message:
    """Decode and validate one message; raises ``ProtocolError`` on anything wrong.

    ``limits`` bound every length while msgpack parses (SPEC.md 5).
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"expected bytes, got {type(data).__name__}")
    if len(data) > limits.max_bytes:
        raise ProtocolError(f"message of {len(data)} bytes exceeds {limits.max_bytes}")
    try:
        d = msgpack.unpackb(data, **limits._unpack_kw())
    except Exception as e:  # msgpack raises a zoo of types for corrupt input
        raise ProtocolError(f"not a msgpack document ({type(e).__name__}: {e})") from None
    if not isinstance(d, dict):
        raise ProtocolError(f"expected a map at top level, got {type(d).__name__}")
    if d.get("kind") == "step":
        try:
            msg = _fast_step(d, limits)
        except Exception:  # anything unexpected: the full decoder below names the field
            msg = None
        if msg is not None:
            return msg
    try:
        return _decode_map(d, _Reader(limits))
    except ProtocolError:
        raise
    except (ValueError, TypeError, KeyError, IndexError, OverflowError, RecursionError) as e:
        raise ProtocolError(f"malformed message ({type(e).__name__}: {e})") from None


def _check_version(d: dict) -> None:
    v = _get(d, "v", "")
    if (
        not isinstance(v, list) or len(v) != 2
        or not all(isinstance(x, int) and not isinstance(x, bool) for x in v)
    ):
        raise ProtocolError("expected [major, minor] integers", "v")
    if v[0] != SCHEMA_VERSION[0]:
        raise ProtocolError(
            f"peer speaks protocol {v[0]}.{v[1]}, this build speaks "
            f"{SCHEMA_VERSION[0]}.{SCHEMA_VERSION[1]} (major versions must match)",
            "v",
        )


def _decode_map(d: dict, r: _Reader) -> Message:
    _check_version(d)
    kind = r.str(d, "kind", "")
    dec = _DECODERS.get(kind)
    if dec is None:
        raise ProtocolError(f"expected one of {sorted(_DECODERS)}, got {kind!r}", "kind")
    return dec(d, r)


def _vtype_pairs(d: dict, r: _Reader) -> list[VType] | None:
    if "vtypes" not in d:  # 1.2: only in steps where the table changed
        return None
    vt_raw = _list(d, "vtypes", "")
    if len(vt_raw) > MAX_VTYPES:
        raise ProtocolError(f"expected at most {MAX_VTYPES} vehicle types, got {len(vt_raw)}", "vtypes")
    m = r.lim.max_str
    out = []
    for i, pair in enumerate(vt_raw):
        if (
            not isinstance(pair, list) or len(pair) != 2
            or not all(isinstance(s, str) and len(s) <= m for s in pair)
        ):
            raise ProtocolError("expected [vtype id, vclass] string pairs", f"vtypes[{i}]")
        out.append(VType(pair[0], pair[1]))
    return out


def _decode_step(d: dict, r: _Reader) -> StepMessage:
    vtypes = _vtype_pairs(d, r)
    a = _map(d, "agents", "")
    n = r.count(a, "agents.", r.lim.max_agents)
    spec = STEP_AGENT_COLUMNS if "la_dx" in a else STEP_AGENT_COLUMNS_1_1
    cols = _columns_in(a, spec, n, "agents.")
    x = cols["x"]
    y = cols["y"]
    if "la_dx" in cols:  # 1.2: offsets from the agent's position
        cols["la_x"] = x + cols.pop("la_dx")
        cols["la_y"] = y + cols.pop("la_dy")
    else:
        cols["la_x"] = cols["la_x"].astype(np.float64)
        cols["la_y"] = cols["la_y"].astype(np.float64)
    _check_range(cols["cls"], 0, _N_CLASSES - 1, "agents.cls")
    if vtypes is not None:
        if n and not vtypes:
            raise ProtocolError("expected a vtype table when agents are present", "vtypes")
        _check_range(cols["vtype"], 0, max(len(vtypes) - 1, 0), "agents.vtype")
    _check_range(cols["lane"], -1, 2**31 - 1, "agents.lane")
    if "path" in a:
        off, xy = r.path(a, n, x, y)
    else:
        off, xy = np.zeros(0, np.uint32), np.zeros((0, 2), np.float64)
    agents = AgentBatch(
        ids=r.strs(a, "id", "agents.", n, unique=True), path_offsets=off, path_xy=xy, **cols
    )
    t = _map(d, "tls", "")
    ids = r.strs(t, "id", "tls.", None, unique=True)
    k = len(ids)
    phase = _list(t, "phase", "tls.", k)
    nxt = _list(t, "next", "tls.", k)
    if not all(isinstance(p, int) and not isinstance(p, bool) and 0 <= p < 2**31 for p in phase):
        raise ProtocolError("expected integers 0..2^31-1", "tls.phase")
    if not all(isinstance(s, (int, float)) and not isinstance(s, bool) and -1e9 <= s <= 1e9 for s in nxt):
        raise ProtocolError("expected finite numbers in -1e9..1e9 (float32 after decoding)", "tls.next")
    tls = TrafficLights(
        ids=ids,
        state=r.strs(t, "state", "tls.", k),
        phase=np.asarray(phase, np.int32) if k else np.zeros(0, np.int32),
        next_switch=np.asarray(nxt, np.float32) if k else np.zeros(0, np.float32),
        program=r.strs(t, "program", "tls.", k) if "program" in t else None,
    )
    final = d.get("final", False)
    if not isinstance(final, bool):
        raise ProtocolError(f"expected true or false, got {type(final).__name__}", "final")
    return StepMessage(
        run=r.str(d, "run", ""),
        step=_int(d, "step", "", 0),
        time=_float(d, "t", ""),
        step_length=_float(d, "dt", "", 1e-6, 3600.0),
        agents=agents,
        tls=tls,
        vtypes=vtypes,
        static_version=_int(d, "sv", "", 0) if "sv" in d else 0,
        final=final,
    )


_F4_STEP = tuple(name for name, dt in STEP_AGENT_COLUMNS if dt == "<f4")
_F4_LO = [FLOAT_BOUNDS[k][0] for k in _F4_STEP]
_F4_HI = [FLOAT_BOUNDS[k][1] for k in _F4_STEP]
_LA_ROWS = (_F4_STEP.index("la_dx"), _F4_STEP.index("la_dy") + 1)
assert _LA_ROWS[1] - _LA_ROWS[0] == 2, "la_dx and la_dy must be adjacent float32 columns"
assert _F4_STEP == ("angle", "speed", "accel", "la_dx", "la_dy", "length", "width"), "update _fast_step"
_VALID_CLS = bytes(range(_N_CLASSES))


def _fast_step(d: dict, lim: DecodeLimits) -> StepMessage | None:
    """A protocol 1.2 step with every check of ``_decode_step``
    done in bulk: few numpy calls, no per-field helpers. A step decodes right after the
    receiver wakes, with cold caches, where each distinct call costs tens of microseconds.

    Returns None for anything it does not accept (any other shape, any invalid value):
    ``_decode_step`` then decodes it, or raises the error naming the field. It accepts
    exactly what ``_decode_step`` accepts and returns an equal message."""
    v = d["v"]
    if (type(v) is not list or len(v) != 2 or type(v[0]) is not int or type(v[1]) is not int
            or v[0] != SCHEMA_VERSION[0]):
        return None
    vtypes = None
    if "vtypes" in d:
        vt = d["vtypes"]
        if type(vt) is not list or len(vt) > MAX_VTYPES:
            return None
        m = lim.max_str
        for pair in vt:
            if (type(pair) is not list or len(pair) != 2 or type(pair[0]) is not str or type(pair[1]) is not str
                    or len(pair[0]) > m or len(pair[1]) > m):
                return None
        vtypes = [VType(i, c) for i, c in vt]
    a = d["agents"]
    n = a["n"]
    if type(a) is not dict or type(n) is not int or not 0 <= n <= lim.max_agents or "la_dx" not in a:
        return None
    f8 = (a["x"], a["y"])
    f4 = [a[k] for k in _F4_STEP]
    cls, vtype, signals, lane, flags = a["cls"], a["vtype"], a["signals"], a["lane"], a["flags"]
    n2, n4, n8 = 2 * n, 4 * n, 8 * n
    for b in f8:
        if type(b) is not bytes or len(b) != n8:
            return None
    for b in f4:
        if type(b) is not bytes or len(b) != n4:
            return None
    if (type(cls) is not bytes or len(cls) != n or type(flags) is not bytes or len(flags) != n
            or type(vtype) is not bytes or len(vtype) != n2 or type(signals) is not bytes
            or len(signals) != n2 or type(lane) is not bytes or len(lane) != n4):
        return None
    xy = np.frombuffer(f8[0] + f8[1], "<f8").reshape(2, n)
    b4 = np.frombuffer(b"".join(f4), "<f4").reshape(len(f4), n)
    if n:
        lo, hi = float(xy.min()), float(xy.max())  # NaN fails every comparison
        if not (-COORD_LIMIT <= lo and hi <= COORD_LIMIT):
            return None
        for mn, mx, lo, hi in zip(b4.min(axis=1).tolist(), b4.max(axis=1).tolist(), _F4_LO, _F4_HI):
            if not (lo <= mn and mx <= hi):
                return None
        if cls.translate(None, _VALID_CLS):  # a byte left over is a class out of range
            return None
    lane_a = np.frombuffer(lane, "<i4")
    vtype_a = np.frombuffer(vtype, "<u2")
    if n and (int(lane_a.min()) < -1 or (vtypes is not None and (not vtypes or int(vtype_a.max()) >= len(vtypes)))):
        return None
    x, y = xy
    la = np.add(xy, b4[_LA_ROWS[0]:_LA_ROWS[1]])  # float64 look-ahead points, one pass
    if "path" in a:  # as _Reader.path (1.2: float32 offsets from each agent's position)
        p = a["path"]
        offb, db = p["off"], p["dxy"]
        if type(p) is not dict or type(offb) is not bytes or type(db) is not bytes or len(offb) != 4 * (n + 1) \
                or len(db) % 8 or len(db) // 8 > lim.max_points:
            return None
        pm = len(db) // 8
        off = np.frombuffer(offb, "<u4")
        counts = np.diff(off.astype(np.int64))
        if off[0] != 0 or off[-1] != pm or (n and int(counts.min()) < 0):
            return None
        dxy = np.frombuffer(db, "<f4").reshape(pm, 2)
        if pm:
            lo, hi = float(dxy.min()), float(dxy.max())
            if not (-OFFSET_LIMIT <= lo and hi <= OFFSET_LIMIT):
                return None
            pxy = np.add(dxy, np.repeat(xy.T, counts, axis=0))  # float64: offsets + anchors, one pass
        else:
            pxy = dxy.astype(np.float64)
    else:
        off, pxy = np.zeros(0, np.uint32), np.zeros((0, 2), np.float64)
    ids = a["id"]
    m = lim.max_str
    if type(ids) is not list or len(ids) != n or (len("".join(ids)) > m and max(map(len, ids)) > m) \
            or len(set(ids)) != n:
        return None
    t = d["tls"]
    tids, state, phase, nxt = t["id"], t["state"], t["phase"], t["next"]
    program = t["program"] if "program" in t else None
    k = len(tids)
    if (type(t) is not dict or type(tids) is not list or type(state) is not list or type(phase) is not list
            or type(nxt) is not list or len(state) != k or len(phase) != k or len(nxt) != k
            or ("program" in t and (type(program) is not list or len(program) != k))):
        return None
    if k:
        for strs in (tids, state) if program is None else (tids, state, program):
            if len("".join(strs)) > m and max(map(len, strs)) > m:
                return None
        if len(set(tids)) != k:
            return None
        if not all(type(p) is int and 0 <= p < 2**31 for p in phase):
            return None
        if not all((type(s) is float or type(s) is int) and -1e9 <= s <= 1e9 for s in nxt):
            return None
        tls = TrafficLights(tids, state, np.asarray(phase, np.int32), np.asarray(nxt, np.float32), program)
    else:
        tls = TrafficLights(tids, state, np.zeros(0, np.int32), np.zeros(0, np.float32), program)
    final = d.get("final", False)
    run, step, tm, dt, sv = d["run"], d["step"], d["t"], d["dt"], d.get("sv", 0)
    if (type(final) is not bool or type(run) is not str or len(run) > m or type(step) is not int
            or not 0 <= step < 2**63 or type(sv) is not int or not 0 <= sv < 2**63
            or type(tm) not in (float, int) or type(dt) not in (float, int)):
        return None
    tm, dt = float(tm), float(dt)
    if not (math.isfinite(tm) and 1e-6 <= dt <= 3600.0):
        return None
    agents = AgentBatch(
        ids=ids, cls=np.frombuffer(cls, "<u1"), vtype=vtype_a, x=x, y=y,
        angle=b4[0], speed=b4[1], accel=b4[2], signals=np.frombuffer(signals, "<u2"),
        la_x=la[0], la_y=la[1], length=b4[5], width=b4[6], lane=lane_a, flags=np.frombuffer(flags, "<u1"),
        path_offsets=off, path_xy=pxy,
    )
    return StepMessage(run=run, step=step, time=tm, step_length=dt, agents=agents, tls=tls, vtypes=vtypes,
                       static_version=sv, final=final)


def _decode_ego(d: dict, r: _Reader) -> EgoPose:
    return EgoPose(
        id=r.str(d, "id", ""),
        x=_float(d, "x", "", -COORD_LIMIT, COORD_LIMIT),
        y=_float(d, "y", "", -COORD_LIMIT, COORD_LIMIT),
        angle=_float(d, "angle", "", -720.0, 720.0),
        speed=_float(d, "speed", "", -200.0, 200.0),
        time=_float(d, "t", "") if "t" in d else 0.0,
        vtype=r.str(d, "vtype", "") if "vtype" in d else "",
    )


def _decode_camera(d: dict, r: _Reader) -> CameraPose:
    return CameraPose(
        id=r.str(d, "id", ""),
        x=_float(d, "x", "", -COORD_LIMIT, COORD_LIMIT),
        y=_float(d, "y", "", -COORD_LIMIT, COORD_LIMIT),
        time=_float(d, "t", "") if "t" in d else 0.0,
    )


def _decode_physics(d: dict, r: _Reader) -> PhysicsState:
    a = _map(d, "agents", "")
    n = r.count(a, "agents.", r.lim.max_agents)
    cols = _columns_in(a, PHYSICS_AGENT_COLUMNS, n, "agents.")
    _check_range(cols["cls"], 0, _N_CLASSES - 1, "agents.cls")
    _check_range(cols["mode"], 0, _N_MODES - 1, "agents.mode")
    c = _map(d, "counters", "")
    for k, v in c.items():
        if not isinstance(v, int) or isinstance(v, bool):
            raise ProtocolError("expected an integer", f"counters.{k}")
    return PhysicsState(
        run=r.str(d, "run", ""),
        tick=_int(d, "tick", "", 0),
        time=_float(d, "t", ""),
        sumo_step=_int(d, "sumo_step", "", -1),
        agents=PhysicsAgents(ids=r.strs(a, "id", "agents.", n, unique=True), **cols),
        counters=dict(c),
    )


def _decode_feedback(d: dict, r: _Reader) -> PhysicsFeedback:
    a = _map(d, "agents", "")
    n = r.count(a, "agents.", r.lim.max_agents)
    cols = _columns_in(a, FEEDBACK_COLUMNS, n, "agents.")
    _check_range(cols["contact"], 0, 1, "agents.contact")
    return PhysicsFeedback(
        run=r.str(d, "run", ""),
        step=_int(d, "step", "", 0),
        time=_float(d, "t", ""),
        ids=r.strs(a, "id", "agents.", n, unique=True),
        **cols,
    )


def _decode_ack(d: dict, r: _Reader) -> StepAck:
    fb = d.get("fb", False)
    if not isinstance(fb, bool):
        raise ProtocolError(f"expected true or false, got {fb!r}", "fb")
    return StepAck(run=r.str(d, "run", ""), step=_int(d, "step", "", 0), tick=_int(d, "tick", "", 0), feedback=fb)


def _decode_status(d: dict, r: _Reader) -> SumoStatus:
    c = _map(d, "counters", "")
    for k, v in c.items():
        if not isinstance(k, str) or len(k) > r.lim.max_str:
            raise ProtocolError(f"expected counter names of at most {r.lim.max_str} characters", "counters")
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
            raise ProtocolError(f"expected a finite number, got {v!r}", f"counters.{k}")
    return SumoStatus(counters=dict(c))


def _decode_static(d: dict, r: _Reader) -> StaticData:
    rows = r.lim.max_static_rows
    net = _map(d, "net", "")
    off = _list(net, "offset", "net.", 2)
    bounds = _list(net, "bounds", "net.", 4)
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in off + bounds):
        raise ProtocolError("expected finite numbers", "net.offset/bounds")
    ln = _map(d, "lanes", "")
    nl = r.count(ln, "lanes.", rows)
    allow = _list(ln, "allow", "lanes.", nl)
    for i, a in enumerate(allow):
        if not isinstance(a, list) or not all(isinstance(s, str) for s in a):
            raise ProtocolError("expected arrays of vClass strings", f"lanes.allow[{i}]")
    l_off, l_xy = r.polyline(ln, "shape", nl, "lanes.")
    lanes = LaneTable(
        ids=r.strs(ln, "id", "lanes.", nl, unique=True),
        edge=r.strs(ln, "edge", "lanes.", nl),
        width=_col(ln, "width", "<f4", nl, "lanes.", (0.0, 1_000.0)),
        length=_col(ln, "length", "<f4", nl, "lanes.", (0.0, 1e7)),
        allow=allow,
        shape_offsets=l_off,
        shape_xy=l_xy,
    )
    jn = _map(d, "junctions", "")
    nj = r.count(jn, "junctions.", rows)
    j_off, j_xy = r.polyline(jn, "shape", nj, "junctions.")
    tls_ids = r.strs(d, "tls", "", None, unique=True)
    if len(tls_ids) > rows:
        raise ProtocolError(f"expected at most {rows} traffic lights", "tls")
    tls_links = TlsLinks.empty()
    if "tls_links" in d:  # optional: added in 1.1
        tl = _map(d, "tls_links", "")
        nt = r.count(tl, "tls_links.", rows)
        cols = _columns_in(tl, TLS_LINK_COLUMNS, nt, "tls_links.")
        _check_range(cols["tls"], 0, max(len(tls_ids) - 1, 0), "tls_links.tls")
        for k in ("from_lane", "to_lane", "via_lane"):
            _check_range(cols[k], -1, max(nl - 1, -1), f"tls_links.{k}")
        tls_links = TlsLinks(**cols)
    vt = _map(d, "vtypes", "")
    nv = r.count(vt, "vtypes.", MAX_VTYPES)
    vids = r.strs(vt, "id", "vtypes.", nv)
    vcls = r.strs(vt, "vclass", "vtypes.", nv)
    return StaticData(
        run=r.str(d, "run", ""),
        step_length=_float(d, "dt", "", 1e-6, 3600.0),
        net_offset=(float(off[0]), float(off[1])),
        projection=r.str(net, "proj", "net."),
        bounds=tuple(float(b) for b in bounds),  # type: ignore[arg-type]
        lanes=lanes,
        junctions=JunctionTable(r.strs(jn, "id", "junctions.", nj, unique=True), j_off, j_xy),
        vtypes=[VType(i, c) for i, c in zip(vids, vcls)],
        vtype_length=_col(vt, "length", "<f4", nv, "vtypes.", (0.0, 1_000.0)),
        vtype_width=_col(vt, "width", "<f4", nv, "vtypes.", (0.0, 1_000.0)),
        tls_ids=tls_ids,
        tls_links=tls_links,
        version=_int(d, "sv", "", 0) if "sv" in d else 0,
    )


_DECODERS = {
    "step": _decode_step,
    "ego": _decode_ego,
    "camera": _decode_camera,
    "physics": _decode_physics,
    "ack": _decode_ack,
    "feedback": _decode_feedback,
    "static": _decode_static,
    "status": _decode_status,
}


def decode_as(data: bytes, cls: type, limits: DecodeLimits = DEFAULT_LIMITS) -> Any:
    """Decode and check the message is of type ``cls`` (e.g. ``StepMessage``)."""
    msg = decode(data, limits)
    if not isinstance(msg, cls):
        raise ProtocolError(f"expected a {cls.__name__} message, got {type(msg).__name__}", "kind")
    return msg


_PEEK_HEAD_BYTES = 4096  # the encoder writes kind, run, step, t, dt, sv before the agent columns


def peek(data: bytes, names: tuple[str, ...], limits: DecodeLimits = DEFAULT_LIMITS) -> dict[str, int | float]:
    """Top-level numbers ``names`` of a message (``step``, ``t``, ``sv``) without building the
    agent arrays: the first bytes are parsed first (the encoder writes these keys before the
    columns), other values are skipped, every length bounded by ``limits`` while msgpack
    parses. A name that is absent, not a number, or in an undecodable message is left out."""
    want = set(names)
    out: dict[str, int | float] = {}
    if len(data) > limits.max_bytes:
        return out
    for chunk in ((data[:_PEEK_HEAD_BYTES], data) if len(data) > _PEEK_HEAD_BYTES else (data,)):
        u = msgpack.Unpacker(raw=False, max_buffer_size=max(len(chunk), 1), **limits.unpack_kwargs())
        u.feed(chunk)
        try:
            for _ in range(u.read_map_header()):
                k = u.unpack()
                if k not in want:
                    u.skip()
                    continue
                v = u.unpack()
                if isinstance(v, (int, float)) and not isinstance(v, bool):
                    out[k] = v
                if len(out) == len(want):
                    break
            return out  # the map read (or all names found): what is missing is absent
        except msgpack.OutOfData:
            continue  # cut off inside the head: read the whole message
        except Exception:  # msgpack raises a zoo of types for corrupt or oversized input
            return out
    return out
