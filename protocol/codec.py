"""msgpack codec for every sumoco message, versioned and validating.

Layout (SPEC.md has the language-neutral version): every message is one msgpack map
with ``v`` = [major, minor] and ``kind``. Per-agent fields are *columns*: one msgpack
``bin`` holding ``n`` little-endian values, so a decoder gets numpy-ready arrays with one
``frombuffer`` per field and a C#/C++/TypeScript client gets typed arrays just as cheaply.

Decoding validates structure, types, sizes and finiteness and raises ``ProtocolError``
naming the field, the value and the expectation; no other exception escapes ``decode``.
The expectations live in tables: ``*_COLUMNS`` with ``FLOAT_BOUNDS`` and ``INT_BOUNDS`` for
the agent columns, ``*_FIELDS`` for the scalar fields of each message.

Step and physics messages, the hot ones, take a C fast path (``protocol._fastcodec``) when
it is built: the same bytes out of ``encode``, the same message out of ``decode``. On
anything it does not accept it steps aside and the Python code below runs, so every error
is raised (and worded) here. ``SUMOCO_PURE_CODEC=1`` in the environment forces the Python
path; ``FAST_CODEC`` tells which is active.
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any, NamedTuple, Union

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

    def _reader(self) -> "_Reader":
        """The field readers of these limits (with the unpack options), built once."""
        r = self.__dict__.get("_r")
        if r is None:
            r = _Reader(self)
            object.__setattr__(self, "_r", r)  # a cache, not a field
        return r

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

#: Value bounds per integer column whose range does not depend on the message (the vType
#: index and the lane indexes of tls links do; their decoders check those).
INT_BOUNDS: dict[str, tuple[int, int]] = {
    "cls": (0, len(AgentClass) - 1), "mode": (0, len(AgentMode) - 1), "lane": (-1, 2**31 - 1), "contact": (0, 1),
}


def _load_fast() -> Any:
    """The C fast path, configured with this module's version and bounds; None when it is
    not built (no compiler at install), on a big-endian host, or SUMOCO_PURE_CODEC is set."""
    if os.environ.get("SUMOCO_PURE_CODEC", "") not in ("", "0") or sys.byteorder != "little":
        return None
    try:
        # (the submodule by name: importing it from the package would read as a cycle codec -> protocol)
        from protocol._fastcodec import configure
    except ImportError:
        return None
    fast = sys.modules["protocol._fastcodec"]
    # Not another checkout's build found through an editable install (runtime.native's
    # beside_its_package, which this layer cannot import): the Python path runs then.
    if os.path.dirname(os.path.realpath(fast.__file__)) != os.path.dirname(os.path.realpath(__file__)):
        return None
    return fast if configure(*SCHEMA_VERSION, FLOAT_BOUNDS, INT_BOUNDS) else None


_fast = _load_fast()
#: True when step and physics messages go through the C fast path (``protocol._fastcodec``).
FAST_CODEC: bool = _fast is not None

#: The bounds of a float column without an entry in FLOAT_BOUNDS: any finite value.
_FINITE = (-float(np.finfo(np.float64).max), float(np.finfo(np.float64).max))
_MISSING: Any = object()  # a field's value when it is absent

#: Scalar field kinds: the msgpack types each accepts.
_INT, _NUM, _STR, _BOOL = (int,), (float, int), (str,), (bool,)


class Field(NamedTuple):
    """A scalar field of a message and what a receiver accepts (SPEC.md 3)."""

    key: str
    types: tuple[type, ...]
    """``_INT`` (bools refused), ``_NUM`` (an integer or a float, decoded as float), ``_STR``, ``_BOOL``."""
    lo: float = 0
    """Smallest value (of a string: its length)."""
    hi: float | None = None
    """Largest value (None for a string: ``DecodeLimits.max_str`` characters)."""
    default: Any = _MISSING
    """The value when the field is absent (``_MISSING``: it must be there)."""


_I64_MAX = 2**63 - 1
#: The scalar fields of each message (the agent tables are the ``*_COLUMNS`` above).
STEP_FIELDS = (
    Field("run", _STR), Field("step", _INT, 0, _I64_MAX), Field("t", _NUM, *_FINITE),
    Field("dt", _NUM, 1e-6, 3600.0), Field("sv", _INT, 0, _I64_MAX, 0), Field("final", _BOOL, False, True, False),
    Field("epoch", _INT, 0, _I64_MAX, 0),
)
EGO_FIELDS = (
    Field("id", _STR), Field("x", _NUM, -COORD_LIMIT, COORD_LIMIT), Field("y", _NUM, -COORD_LIMIT, COORD_LIMIT),
    Field("angle", _NUM, -720.0, 720.0), Field("speed", _NUM, -200.0, 200.0), Field("t", _NUM, *_FINITE, 0.0),
    Field("vtype", _STR, 0, None, ""),
)
CAMERA_FIELDS = (
    Field("id", _STR), Field("x", _NUM, -COORD_LIMIT, COORD_LIMIT), Field("y", _NUM, -COORD_LIMIT, COORD_LIMIT),
    Field("t", _NUM, *_FINITE, 0.0),
)
PHYSICS_FIELDS = (
    Field("run", _STR), Field("tick", _INT, 0, _I64_MAX), Field("t", _NUM, *_FINITE),
    Field("sumo_step", _INT, -1, _I64_MAX),
)
FEEDBACK_FIELDS = (Field("run", _STR), Field("step", _INT, 0, _I64_MAX), Field("t", _NUM, *_FINITE))
ACK_FIELDS = (
    Field("run", _STR), Field("step", _INT, 0, _I64_MAX), Field("tick", _INT, 0, _I64_MAX),
    Field("fb", _BOOL, False, True, False),
)
STATIC_FIELDS = (Field("run", _STR), Field("dt", _NUM, 1e-6, 3600.0), Field("sv", _INT, 0, _I64_MAX, 0),
                 Field("epoch", _INT, 0, _I64_MAX, 0))
_PROJECTION = (Field("proj", _STR),)


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
    if _fast is not None:
        fast = _FAST_ENCODERS.get(type(msg))
        if fast is not None:
            data = fast(msg)
            if data is not None:
                return data
    return encode_python(msg)


def encode_python(msg: Message) -> bytes:
    """``encode`` in Python only: the reference the fast path reproduces byte for byte
    (tests and benchmarks compare the two)."""
    enc = _ENCODERS.get(type(msg))
    if enc is None:  # a subclass of a message type
        enc = next((f for cls, f in _ENCODERS.items() if isinstance(msg, cls)), None)
        if enc is None:
            raise TypeError(f"not a protocol message: {type(msg).__name__}")
    return msgpack.packb(enc(msg), use_bin_type=True)


def _encode_step(msg: StepMessage) -> dict[str, Any]:
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
        **({"epoch": int(msg.epoch)} if msg.epoch else {}),  # since 1.4; absent = 0
        "agents": agents,
        "tls": tls,
    }
    if msg.vtypes is not None:
        d["vtypes"] = [[v.id, v.vclass] for v in msg.vtypes]
    if msg.final:  # optional (older readers ignore it); absent means false
        d["final"] = True
    return d


def _encode_ego(msg: EgoPose) -> dict[str, Any]:
    return _head("ego") | {
        "id": msg.id, "x": float(msg.x), "y": float(msg.y), "angle": float(msg.angle),
        "speed": float(msg.speed), "t": float(msg.time), "vtype": msg.vtype,
    }


def _encode_camera(msg: CameraPose) -> dict[str, Any]:
    return _head("camera") | {"id": msg.id, "x": float(msg.x), "y": float(msg.y), "t": float(msg.time)}


def _encode_physics(msg: PhysicsState) -> dict[str, Any]:
    a = msg.agents
    return _head("physics") | {
        "run": msg.run,
        "tick": int(msg.tick),
        "t": float(msg.time),
        "sumo_step": int(msg.sumo_step),
        "agents": {"n": a.n, "id": list(a.ids), **_columns(a, PHYSICS_AGENT_COLUMNS)},
        "counters": {str(k): int(v) for k, v in msg.counters.items()},
    }


def _encode_feedback(msg: PhysicsFeedback) -> dict[str, Any]:
    return _head("feedback") | {
        "run": msg.run, "step": int(msg.step), "t": float(msg.time),
        "agents": {"n": msg.n, "id": list(msg.ids), **_columns(msg, FEEDBACK_COLUMNS)},
    }


def _encode_ack(msg: StepAck) -> dict[str, Any]:
    d = _head("ack") | {"run": msg.run, "step": int(msg.step), "tick": int(msg.tick)}
    if msg.feedback:  # optional (1.3): absent means False
        d["fb"] = True
    return d


def _encode_status(msg: SumoStatus) -> dict[str, Any]:
    return _head("status") | {"counters": {str(k): v if isinstance(v, int) else float(v)
                                           for k, v in msg.counters.items()}}


def _encode_static(msg: StaticData) -> dict[str, Any]:
    ln = msg.lanes
    return _head("static") | {
        "run": msg.run,
        "sv": int(msg.version),
        **({"epoch": int(msg.epoch)} if msg.epoch else {}),  # since 1.4; absent = 0
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


def _fast_encode_step(msg: StepMessage) -> bytes | None:
    """The C encoder; when an array is not of the dtype it reads (or not an array), it gets
    the arrays cast as the Python encoder casts them. None: the Python encoder's turn."""
    try:
        return _fast.encode_step(msg, msg.agents, msg.tls) or _fast.encode_step(
            msg, _step_arrays(msg.agents), _tls_arrays(msg.tls))
    except Exception:  # an input the Python encoder will reject in its own words
        return None


def _step_arrays(a: AgentBatch) -> SimpleNamespace:
    cols = {name: np.ascontiguousarray(getattr(a, name), dt) for name, dt in STEP_AGENT_COLUMNS
            if name not in ("la_dx", "la_dy")}
    return SimpleNamespace(
        n=a.n, ids=list(a.ids), la_x=np.ascontiguousarray(a.la_x, np.float64),
        la_y=np.ascontiguousarray(a.la_y, np.float64), path_offsets=np.asarray(a.path_offsets, np.int64),
        path_xy=np.ascontiguousarray(a.path_xy, np.float64), **cols)


def _tls_arrays(t: TrafficLights) -> SimpleNamespace:
    return SimpleNamespace(ids=list(t.ids), state=list(t.state), phase=np.asarray(t.phase, np.int64),
                           next_switch=np.asarray(t.next_switch, np.float64),
                           program=None if t.program is None else list(t.program))


def _fast_encode_physics(msg: PhysicsState) -> bytes | None:
    """As ``_fast_encode_step``, for a physics state."""
    try:
        return _fast.encode_physics(msg, msg.agents) or _fast.encode_physics(msg, _physics_arrays(msg.agents))
    except Exception:
        return None


def _physics_arrays(a: PhysicsAgents) -> SimpleNamespace:
    return SimpleNamespace(n=a.n, ids=list(a.ids),
                           **{name: np.ascontiguousarray(getattr(a, name), dt) for name, dt in PHYSICS_AGENT_COLUMNS})


_FAST_ENCODERS: dict[type, Any] = {StepMessage: _fast_encode_step, PhysicsState: _fast_encode_physics}

_ENCODERS: dict[type, Any] = {
    StepMessage: _encode_step,
    EgoPose: _encode_ego,
    CameraPose: _encode_camera,
    PhysicsState: _encode_physics,
    PhysicsFeedback: _encode_feedback,
    StepAck: _encode_ack,
    SumoStatus: _encode_status,
    StaticData: _encode_static,
}


# --------------------------------------------------------------------------- decoding


def _bad(d: dict, key: str, where: str, expected: str) -> ProtocolError:
    """The error of a field that failed its check: missing, or its value against ``expected``."""
    if key not in d:
        return ProtocolError("missing field", where + key)
    return ProtocolError(f"expected {expected}, got {_show(d[key])}", where + key)


def _show(v: Any) -> str:
    """``v`` for an error message, short (a hostile value may be megabytes)."""
    if isinstance(v, (bytes, str, list, dict)) and len(v) > 40:
        return f"{type(v).__name__} of length {len(v)}"
    s = repr(v)
    return s if len(s) <= 60 else f"{s[:57]}..."


# Every check is one condition on the way through; its message is built only when it fails.
# ``type(v) is int`` also refuses bools, which msgpack keeps apart from integers.


def _fields(d: dict, spec: tuple[Field, ...], where: str, max_str: int) -> list:
    """The values of ``spec``'s fields in ``d`` (numbers as float), each checked against its entry."""
    out = []
    for key, types, lo, hi, default in spec:
        v = d.get(key, default)
        t = type(v)
        if t not in types or not lo <= (len(v) if t is str else v) <= (max_str if hi is None else hi):
            raise _bad(d, key, where, _expected(types, lo, hi, max_str))  # NaN and inf fail the comparison
        out.append(float(v) if t is int and types is _NUM else v)
    return out


def _expected(types: tuple[type, ...], lo: float, hi: float | None, max_str: int) -> str:
    if types is _STR:
        return f"a string of at most {max_str} characters"
    if types is _BOOL:
        return "true or false"
    if types is _INT:
        return f"an integer in {lo}..{hi}"
    return "a finite number" + ("" if (lo, hi) == _FINITE else f" in {lo:g}..{hi:g}")


def _map(d: dict, key: str, where: str) -> dict:
    v = d.get(key, _MISSING)
    if type(v) is not dict:
        raise _bad(d, key, where, "a map")
    return v


def _list(d: dict, key: str, where: str, n: int | None = None) -> list:
    v = d.get(key, _MISSING)
    if type(v) is not list or (n is not None and len(v) != n):
        raise _bad(d, key, where, _an_array(n))
    return v


def _an_array(n: int | None) -> str:
    return "an array" if n is None else f"an array of {n} elements"


def _numbers_ok(v: list, integer: bool, lo: float, hi: float) -> bool:
    """Every item an integer (or, unless ``integer``, a finite number) in lo..hi: C-level
    passes, no Python per item (a city has thousands of traffic lights)."""
    types = set(map(type, v))
    return (types <= ({int} if integer else {int, float}) and (float not in types or all(map(math.isfinite, v)))
            and (not v or (lo <= min(v) and max(v) <= hi)))


def _numbers(v: list, integer: bool, lo: float, hi: float, field: str) -> None:
    if not _numbers_ok(v, integer, lo, hi):
        i = next(i for i, x in enumerate(v) if not _numbers_ok([x], integer, lo, hi))
        kind = f"integers in {lo}..{hi}" if integer else f"finite numbers in {lo:g}..{hi:g}"
        raise ProtocolError(f"expected {kind}, got {_show(v[i])} at [{i}]", field)


class _Reader:
    """Field readers bound to one set of ``DecodeLimits``."""

    def __init__(self, lim: DecodeLimits) -> None:
        self.lim = lim
        self.unpack_kw = lim._unpack_kw()
        self._counts: dict[int, tuple[Field]] = {}
        kw = self.unpack_kw
        #: what the C decoder needs: the decoder's limits, then msgpack's (DecodeLimits._limits_kw)
        self.fast_limits = (lim.max_agents, lim.max_points, lim.max_str, kw["max_str_len"], kw["max_bin_len"],
                            kw["max_array_len"])

    def strs(self, d: dict, key: str, where: str, n: int | None = None, unique: bool = False) -> list[str]:
        v = d.get(key, _MISSING)
        if type(v) is not list or (n is not None and len(v) != n):  # as _list: a call fewer per list
            raise _bad(d, key, where, _an_array(n))
        if not v:
            return v
        m = self.lim.max_str
        # C-level passes instead of a Python loop per id: join fails on any non-string,
        # and a joined length within the limit bounds every single length.
        try:
            total = len("".join(v))
        except TypeError:
            bad = next(s for s in v if not isinstance(s, str))
            raise ProtocolError(f"expected strings of at most {m} characters, got {_show(bad)}", where + key) from None
        if total > m and max(map(len, v)) > m:
            bad = next(s for s in v if len(s) > m)
            raise ProtocolError(f"expected strings of at most {m} characters, got one of {len(bad)}", where + key)
        if unique and len(set(v)) != len(v):
            seen: set[str] = set()
            dup = next(s for s in v if s in seen or seen.add(s))  # type: ignore[func-returns-value]
            raise ProtocolError(f"expected unique ids, {dup!r} appears twice", where + key)
        return v

    def count(self, d: dict, where: str, limit: int) -> int:
        """A table's row count ``n``, at most ``limit``."""
        spec = self._counts.get(limit)
        if spec is None:
            spec = self._counts[limit] = (Field("n", _INT, 0, limit),)
        return _fields(d, spec, where, 0)[0]

    def polyline(self, d: dict, key: str, n: int, where: str) -> tuple[np.ndarray, np.ndarray]:
        """Static polyline: prefers float64 ``xy64`` (1.2), else float32 ``xy`` (1.1)."""
        p = _map(d, key, where)
        w = f"{where}{key}."
        off = _col(p, "off", "<u4", n + 1, w)
        name, dt = ("xy64", "<f8") if "xy64" in p else ("xy", "<f4")
        xy = self.points(p, name, dt, (-COORD_LIMIT, COORD_LIMIT), w)
        _check_offsets(off, n, len(xy), w)
        return off, xy.astype(np.float64)

    def path(self, a: dict, n: int, anchors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Path ahead: float32 offsets ``dxy`` from each agent's position (1.2; ``anchors``,
        float64 (n, 2)) or absolute float32 ``xy`` (1.1)."""
        p = _map(a, "path", "agents.")
        w = "agents.path."
        off = _col(p, "off", "<u4", n + 1, w)
        rel = "dxy" in p
        if rel:
            xy = self.points(p, "dxy", "<f4", (-OFFSET_LIMIT, OFFSET_LIMIT), w)
        else:
            xy = self.points(p, "xy", "<f4", (-COORD_LIMIT, COORD_LIMIT), w)
        counts = _check_offsets(off, n, len(xy), w)
        if rel and len(xy):
            # one pass: float32 offsets + each agent's float64 (x, y) repeated per vertex
            return off, np.add(xy, anchors.repeat(counts, axis=0))
        return off, xy.astype(np.float64)

    def points(self, p: dict, name: str, dtype: str, bounds: tuple[float, float], w: str) -> np.ndarray:
        """The (x, y) pairs of ``dtype`` in ``p[name]``: at most ``max_points``, finite and
        within ``bounds``; shape (m, 2)."""
        b = p.get(name, _MISSING)
        size = 2 * _ITEMSIZE[dtype]
        if type(b) is not bytes or len(b) % size:
            raise _bad(p, name, w, f"bin of {dtype} (x, y) pairs")
        m = len(b) // size
        if m > self.lim.max_points:
            raise ProtocolError(f"expected at most {self.lim.max_points} points, got {m}", w + name)
        return _col(p, name, dtype, 2 * m, w, bounds).reshape(m, 2)


def _check_offsets(off: np.ndarray, n: int, m: int, w: str) -> np.ndarray:
    """Vertices per row (``n + 1`` offsets rising from 0 to ``m``) [int64]."""
    wide = off.astype(np.int64)
    counts = wide[1:] - wide[:-1]
    if wide[0] != 0 or wide[-1] != m or (n and np.minimum.reduce(counts) < 0):
        i = 0 if wide[0] != 0 else int(np.argmax(counts < 0)) + 1 if n and counts.min() < 0 else n
        raise ProtocolError(f"expected offsets rising from 0 to {m}, got {int(off[i])} at [{i}]", w + "off")
    return counts


# --------------------------------------------------------------------------- columns


class _Layout:
    """A column table (``*_COLUMNS``) prepared for ``_columns_in``: the columns in dtype
    groups (in the table's order of first appearance), each float column's bounds
    (``bounds`` for all, else FLOAT_BOUNDS), each integer column's INT_BOUNDS."""

    def __init__(self, spec: tuple[tuple[str, str], ...], bounds: tuple[float, float] | None = None) -> None:
        by: dict[str, list[str]] = {}
        for name, dt in spec:
            by.setdefault(dt, []).append(name)
        self.names = [k for names in by.values() for k in names]
        self.dtypes = [dt for dt, names in by.items() for _ in names]
        self.sizes = [np.dtype(dt).itemsize for dt in self.dtypes]
        self.ints = [i for i, dt in enumerate(self.dtypes) if np.dtype(dt).kind != "f"]
        self.int_names = [self.names[i] for i in self.ints]
        self.int_dtypes = [self.dtypes[i] for i in self.ints]
        #: per float dtype: (dtype, slice of ``names``, names, each column's (lo, hi), the one
        #: (lo, hi) of all of them when they share it)
        self.floats = []
        start = 0
        for dt, names in by.items():
            if np.dtype(dt).kind == "f":
                fb = [bounds or FLOAT_BOUNDS.get(k, _FINITE) for k in names]
                self.floats.append((dt, slice(start, start + len(names)), names, fb,
                                    fb[0] if len(set(fb)) == 1 else None))
            start += len(names)
        #: per integer column in INT_BOUNDS: (its place in ``names``, name, lo, hi, and for a u8
        #: column the bytes lo..hi, else None)
        self.ranges = [(i, k, *INT_BOUNDS[k], bytes(range(INT_BOUNDS[k][0], INT_BOUNDS[k][1] + 1))
                        if self.dtypes[i] == "<u1" else None)
                       for i, k in zip(self.ints, self.int_names) if k in INT_BOUNDS]


_BYTES = {bytes}


def _columns_in(d: dict, layout: _Layout, n: int, where: str, blocks: dict | None = None) -> dict[str, np.ndarray]:
    """The columns of ``layout``: each a bin of ``n`` values, float ones finite and within
    their bounds, integer ones within INT_BOUNDS. C-level passes over the columns, one
    array and one min/max pass per float dtype instead of per column (a step has 14): every
    call counts, as a step's decode runs with cold caches between steps. ``blocks``
    receives each float dtype's (columns, n) array, rows in the table's order."""
    bins = list(map(d.get, layout.names))
    want = list(map(n.__mul__, layout.sizes))  # bytes per column
    if set(map(type, bins)) != _BYTES or list(map(len, bins)) != want:
        i = next(i for i, (b, m) in enumerate(zip(bins, want)) if type(b) is not bytes or len(b) != m)
        raise _bad(d, layout.names[i], where, _a_bin(n, layout.dtypes[i]))
    out = dict(zip(layout.int_names, map(np.frombuffer, [bins[i] for i in layout.ints], layout.int_dtypes)))
    for dt, part, names, bounds, common in layout.floats:
        cols = bins[part]
        block = np.frombuffer(cols[0] if len(cols) == 1 else b"".join(cols), dt).reshape(len(names), n)
        if n:
            _check_floats(block, names, bounds, common, where)
        if blocks is not None:
            blocks[dt] = block
        out.update(zip(names, block))  # row views, no copies
    if n:
        for i, name, lo, hi, allowed in layout.ranges:
            if allowed is None:
                _check_range(out[name], lo, hi, where + name)
            elif bins[i].translate(None, allowed):  # a byte left over is a value out of range
                raise ProtocolError(f"expected values in {lo}..{hi}, got {bins[i].translate(None, allowed)[0]}",
                                    where + name)
    return out


def _check_floats(block: np.ndarray, names: list[str], bounds: list[tuple[float, float]],
                  common: tuple[float, float] | None, where: str) -> None:
    """Each row of ``block`` finite and within its column's (lo, hi). Columns that share
    their bounds take one min and one max over all of them (cheaper than per row)."""
    if common is not None:
        lo, hi = common
        if lo <= float(np.minimum.reduce(block, axis=None)) and float(np.maximum.reduce(block, axis=None)) <= hi:
            return  # NaN propagates into min and max, and fails both
    lows, highs = np.minimum.reduce(block, axis=1).tolist(), np.maximum.reduce(block, axis=1).tolist()
    for name, a, b, (lo, hi) in zip(names, lows, highs, bounds):
        if not (lo <= a and b <= hi):
            bad = a if not lo <= a else b
            raise ProtocolError(f"expected finite values in {lo:g}..{hi:g}, got {bad:g}", where + name)


def _check_range(a: np.ndarray, lo: int, hi: int, field: str) -> None:
    """Every value of the integer array ``a`` in lo..hi."""
    if not len(a):
        return
    # a bound the dtype already guarantees needs no pass over the data (u8 >= 0, i4 <= 2^31-1)
    bits = 8 * a.dtype.itemsize
    signed = a.dtype.kind == "i"
    if lo > (-(1 << (bits - 1)) if signed else 0):
        m = int(np.minimum.reduce(a))
        if m < lo:
            raise ProtocolError(f"expected values in {lo}..{hi}, got {m}", field)
    if hi < ((1 << (bits - 1)) - 1 if signed else (1 << bits) - 1):
        m = int(np.maximum.reduce(a))
        if m > hi:
            raise ProtocolError(f"expected values in {lo}..{hi}, got {m}", field)


def _col(d: dict, key: str, dtype: str, n: int, where: str, bounds: tuple[float, float] | None = None) -> np.ndarray:
    """One column, checked as ``_columns_in`` checks each: a bin of ``n`` x ``dtype``, float
    values finite and within ``bounds`` (else FLOAT_BOUNDS)."""
    b = d.get(key, _MISSING)
    if type(b) is not bytes or len(b) != n * _ITEMSIZE[dtype]:
        raise _bad(d, key, where, _a_bin(n, dtype))
    a = np.frombuffer(b, dtype)
    if n and dtype[1] == "f":
        bound = bounds or FLOAT_BOUNDS.get(key, _FINITE)
        _check_floats(a.reshape(1, n), [key], [bound], bound, where)
    return a


def _a_bin(n: int, dtype: str) -> str:
    return f"bin of {n} x {dtype} = {n * _ITEMSIZE[dtype]} bytes"


_ITEMSIZE = {dt: np.dtype(dt).itemsize for dt in ("<u1", "<u2", "<i4", "<u4", "<f4", "<f8")}
_STEP_AGENTS = _Layout(STEP_AGENT_COLUMNS)
_STEP_AGENTS_1_1 = _Layout(STEP_AGENT_COLUMNS_1_1)
_PHYSICS_AGENTS = _Layout(PHYSICS_AGENT_COLUMNS)
_FEEDBACK_AGENTS = _Layout(FEEDBACK_COLUMNS)
_TLS_LINKS = _Layout(TLS_LINK_COLUMNS)


def decode(data: bytes | bytearray | memoryview, limits: DecodeLimits = DEFAULT_LIMITS) -> Message:
    """Decode and validate one message; raises ``ProtocolError`` on anything wrong.

    ``limits`` bound every length while msgpack parses (SPEC.md 5).
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"expected bytes, got {type(data).__name__}")
    if len(data) > limits.max_bytes:
        raise ProtocolError(f"message of {len(data)} bytes exceeds {limits.max_bytes}")
    r = limits._reader()
    if _fast is not None:
        parts = _fast.decode(data, r.fast_limits)
        if parts is not None:
            return _FAST_BUILD[parts[0]](parts)
    return _decode_py(data, r)


def decode_python(data: bytes | bytearray | memoryview, limits: DecodeLimits = DEFAULT_LIMITS) -> Message:
    """``decode`` in Python only: the reference the fast path reproduces, and the code
    that words every error (tests and benchmarks compare the two)."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"expected bytes, got {type(data).__name__}")
    if len(data) > limits.max_bytes:
        raise ProtocolError(f"message of {len(data)} bytes exceeds {limits.max_bytes}")
    return _decode_py(data, limits._reader())


def _decode_py(data: bytes | bytearray | memoryview, r: "_Reader") -> Message:
    try:
        d = msgpack.unpackb(data, **r.unpack_kw)
    except Exception as e:  # msgpack raises a zoo of types for corrupt input
        raise ProtocolError(f"not a msgpack document ({type(e).__name__}: {e})") from None
    if not isinstance(d, dict):
        raise ProtocolError(f"expected a map at top level, got {type(d).__name__}")
    try:
        return _decode_map(d, r)
    except ProtocolError:
        raise
    except (ValueError, TypeError, KeyError, IndexError, OverflowError, RecursionError) as e:
        raise ProtocolError(f"malformed message ({type(e).__name__}: {e})") from None


def _check_version(d: dict) -> None:
    v = d.get("v", _MISSING)
    if type(v) is not list or len(v) != 2 or type(v[0]) is not int or type(v[1]) is not int:
        raise _bad(d, "v", "", "[major, minor] integers")
    if v[0] != SCHEMA_VERSION[0]:
        raise ProtocolError(
            f"peer speaks protocol {v[0]}.{v[1]}, this build speaks "
            f"{SCHEMA_VERSION[0]}.{SCHEMA_VERSION[1]} (major versions must match)",
            "v",
        )


def _decode_map(d: dict, r: _Reader) -> Message:
    _check_version(d)
    kind = d.get("kind", _MISSING)
    dec = _DECODERS.get(kind) if type(kind) is str else None
    if dec is None:
        raise _bad(d, "kind", "", f"one of {sorted(_DECODERS)}")
    return dec(d, r)


def _vtype_pairs(d: dict, r: _Reader) -> list[VType] | None:
    if "vtypes" not in d:  # 1.2: only in steps where the table changed
        return None
    vt_raw = _list(d, "vtypes", "")
    if len(vt_raw) > MAX_VTYPES:
        raise ProtocolError(f"expected at most {MAX_VTYPES} vehicle types, got {len(vt_raw)}", "vtypes")
    m = r.lim.max_str
    for i, pair in enumerate(vt_raw):
        if (type(pair) is not list or len(pair) != 2 or type(pair[0]) is not str or type(pair[1]) is not str
                or len(pair[0]) > m or len(pair[1]) > m):
            raise ProtocolError(f"expected [vtype id, vclass] string pairs of at most {m} characters, "
                                f"got {_show(pair)}", f"vtypes[{i}]")
    return [VType(i, c) for i, c in vt_raw]


#: Look-ahead offsets la_dx, la_dy: adjacent rows of the step's float32 block, added to the
#: float64 block of x, y in one pass.
_F4_STEP = tuple(name for name, dt in STEP_AGENT_COLUMNS if dt == "<f4")
_LA_ROWS = slice(_F4_STEP.index("la_dx"), _F4_STEP.index("la_dy") + 1)
assert _LA_ROWS.stop - _LA_ROWS.start == 2, "la_dx and la_dy must be adjacent float32 columns"
assert tuple(name for name, dt in STEP_AGENT_COLUMNS if dt == "<f8") == ("x", "y"), "x, y: the float64 block"


def _decode_step(d: dict, r: _Reader) -> StepMessage:
    vtypes = _vtype_pairs(d, r)
    agents = _step_agents(_map(d, "agents", ""), r, vtypes)
    tls = _decode_tls(_map(d, "tls", ""), r)
    run, step, t, dt, sv, final, epoch = _fields(d, STEP_FIELDS, "", r.lim.max_str)
    return StepMessage(run=run, step=step, time=t, step_length=dt, agents=agents, tls=tls, vtypes=vtypes,
                       static_version=sv, final=final, epoch=epoch)


def _step_agents(a: dict, r: _Reader, vtypes: list[VType] | None) -> AgentBatch:
    n = r.count(a, "agents.", r.lim.max_agents)
    rel = "la_dx" in a  # 1.2: look-ahead points as float32 offsets from the agent's position
    blocks: dict[str, np.ndarray] = {}
    cols = _columns_in(a, _STEP_AGENTS if rel else _STEP_AGENTS_1_1, n, "agents.", blocks)
    xy = blocks["<f8"]  # rows x, y
    if rel:
        del cols["la_dx"], cols["la_dy"]
        la = np.add(xy, blocks["<f4"][_LA_ROWS])  # float64, one pass
        cols["la_x"] = la[0]
        cols["la_y"] = la[1]
    else:
        cols["la_x"] = cols["la_x"].astype(np.float64)
        cols["la_y"] = cols["la_y"].astype(np.float64)
    if vtypes is not None and n:  # (no agents: any table fits)
        if not vtypes:
            raise ProtocolError("expected a vtype table when agents are present, got an empty one", "vtypes")
        _check_range(cols["vtype"], 0, len(vtypes) - 1, "agents.vtype")
    if "path" in a:
        off, pxy = r.path(a, n, xy.T)
    else:
        off, pxy = np.zeros(0, np.uint32), np.zeros((0, 2), np.float64)
    return AgentBatch(ids=r.strs(a, "id", "agents.", n, unique=True), path_offsets=off, path_xy=pxy, **cols)


def _decode_tls(t: dict, r: _Reader) -> TrafficLights:
    ids = r.strs(t, "id", "tls.", None, unique=True)
    k = len(ids)
    phase = _list(t, "phase", "tls.", k)
    nxt = _list(t, "next", "tls.", k)
    if k:
        _numbers(phase, True, 0, 2**31 - 1, "tls.phase")
        _numbers(nxt, False, -1e9, 1e9, "tls.next")  # float32 after decoding
    return TrafficLights(
        ids=ids,
        state=r.strs(t, "state", "tls.", k),
        phase=np.asarray(phase, np.int32) if k else np.zeros(0, np.int32),
        next_switch=np.asarray(nxt, np.float32) if k else np.zeros(0, np.float32),
        program=r.strs(t, "program", "tls.", k) if "program" in t else None,
    )


def _decode_ego(d: dict, r: _Reader) -> EgoPose:
    ego_id, x, y, angle, speed, t, vtype = _fields(d, EGO_FIELDS, "", r.lim.max_str)
    return EgoPose(id=ego_id, x=x, y=y, angle=angle, speed=speed, time=t, vtype=vtype)


def _decode_camera(d: dict, r: _Reader) -> CameraPose:
    cam_id, x, y, t = _fields(d, CAMERA_FIELDS, "", r.lim.max_str)
    return CameraPose(id=cam_id, x=x, y=y, time=t)


def _decode_physics(d: dict, r: _Reader) -> PhysicsState:
    a = _map(d, "agents", "")
    n = r.count(a, "agents.", r.lim.max_agents)
    cols = _columns_in(a, _PHYSICS_AGENTS, n, "agents.")
    c = _map(d, "counters", "")
    for k, v in c.items():
        if not isinstance(v, int) or isinstance(v, bool):
            raise ProtocolError("expected an integer", f"counters.{k}")
    run, tick, t, sumo_step = _fields(d, PHYSICS_FIELDS, "", r.lim.max_str)
    return PhysicsState(
        run=run,
        tick=tick,
        time=t,
        sumo_step=sumo_step,
        agents=PhysicsAgents(ids=r.strs(a, "id", "agents.", n, unique=True), **cols),
        counters=dict(c),
    )


def _decode_feedback(d: dict, r: _Reader) -> PhysicsFeedback:
    a = _map(d, "agents", "")
    n = r.count(a, "agents.", r.lim.max_agents)
    cols = _columns_in(a, _FEEDBACK_AGENTS, n, "agents.")
    run, step, t = _fields(d, FEEDBACK_FIELDS, "", r.lim.max_str)
    return PhysicsFeedback(
        run=run,
        step=step,
        time=t,
        ids=r.strs(a, "id", "agents.", n, unique=True),
        **cols,
    )


def _decode_ack(d: dict, r: _Reader) -> StepAck:
    run, step, tick, fb = _fields(d, ACK_FIELDS, "", r.lim.max_str)
    return StepAck(run=run, step=step, tick=tick, feedback=fb)


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
        cols = _columns_in(tl, _TLS_LINKS, nt, "tls_links.")
        _check_range(cols["tls"], 0, max(len(tls_ids) - 1, 0), "tls_links.tls")
        for k in ("from_lane", "to_lane", "via_lane"):
            _check_range(cols[k], -1, max(nl - 1, -1), f"tls_links.{k}")
        tls_links = TlsLinks(**cols)
    vt = _map(d, "vtypes", "")
    nv = r.count(vt, "vtypes.", MAX_VTYPES)
    vids = r.strs(vt, "id", "vtypes.", nv)
    vcls = r.strs(vt, "vclass", "vtypes.", nv)
    run, dt, sv, epoch = _fields(d, STATIC_FIELDS, "", r.lim.max_str)
    return StaticData(
        run=run,
        step_length=dt,
        net_offset=(float(off[0]), float(off[1])),
        projection=_fields(net, _PROJECTION, "net.", r.lim.max_str)[0],
        bounds=tuple(float(b) for b in bounds),  # type: ignore[arg-type]
        lanes=lanes,
        junctions=JunctionTable(r.strs(jn, "id", "junctions.", nj, unique=True), j_off, j_xy),
        vtypes=[VType(i, c) for i, c in zip(vids, vcls)],
        vtype_length=_col(vt, "length", "<f4", nv, "vtypes.", (0.0, 1_000.0)),
        vtype_width=_col(vt, "width", "<f4", nv, "vtypes.", (0.0, 1_000.0)),
        tls_ids=tls_ids,
        tls_links=tls_links,
        version=sv,
        epoch=epoch,
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


_NDARRAY = np.ndarray
_F8, _F4, _I4, _U4, _U2, _U1 = (np.dtype(t) for t in ("<f8", "<f4", "<i4", "<u4", "<u2", "<u1"))
_NEW = object.__new__
#: ``object.__setattr__(obj, "__dict__", fields)``: a frozen dataclass's fields set at once,
#: without its ``__init__`` (a per-field ``object.__setattr__``, which after an idle wait
#: costs tens of microseconds of cold interpreter code per message). Every field must be in
#: ``fields``: tests compare them with ``dataclasses.fields``.
_SET = object.__setattr__


def _fast_step(p: tuple) -> StepMessage:
    """A StepMessage from the C decoder's parts: one buffer, laid out as decode_step in
    _fastcodec.c writes it (float64, float32, int32, uint32, uint16, uint8 blocks). Every
    array is an ``ndarray`` over its own span of that buffer, made by the same constructor:
    after an idle wait each distinct numpy entry point (frombuffer, slicing, reshape) costs
    tens of microseconds of cold code, the same call repeated little."""
    _, run, step, t, dt, sv, final, epoch, vt, ids, buf, n, m, has_path, tls_ids, tls_state, program, k = p
    a = _NDARRAY
    sh = (n,)
    o = 32 * n + 16 * m  # float32 block
    o4 = o + 20 * n + 4 * k  # int32 block
    o_off = o4 + 4 * (n + k)  # uint32 offsets
    m_off = n + 1 if has_path else 0  # no path: empty offsets and (0, 2) points, as the Python decoder
    o2 = o_off + 4 * m_off  # uint16 block
    o1 = o2 + 4 * n  # uint8 block
    agents = _NEW(AgentBatch)
    _SET(agents, "__dict__", {
        "ids": ids, "cls": a(sh, _U1, buf, o1), "vtype": a(sh, _U2, buf, o2), "x": a(sh, _F8, buf, 0),
        "y": a(sh, _F8, buf, 8 * n), "angle": a(sh, _F4, buf, o), "speed": a(sh, _F4, buf, o + 4 * n),
        "accel": a(sh, _F4, buf, o + 8 * n), "signals": a(sh, _U2, buf, o2 + 2 * n),
        "la_x": a(sh, _F8, buf, 16 * n), "la_y": a(sh, _F8, buf, 24 * n), "length": a(sh, _F4, buf, o + 12 * n),
        "width": a(sh, _F4, buf, o + 16 * n), "lane": a(sh, _I4, buf, o4), "flags": a(sh, _U1, buf, o1 + n),
        "path_offsets": a((m_off,), _U4, buf, o_off), "path_xy": a((m, 2), _F8, buf, 32 * n)})
    tls = _NEW(TrafficLights)
    _SET(tls, "__dict__", {"ids": tls_ids, "state": tls_state, "phase": a((k,), _I4, buf, o4 + 4 * n),
                           "next_switch": a((k,), _F4, buf, o + 20 * n), "program": program})
    msg = _NEW(StepMessage)
    _SET(msg, "__dict__", {
        "run": run, "step": step, "time": t, "step_length": dt, "agents": agents, "tls": tls,
        "vtypes": None if vt is None else [VType(i, c) for i, c in vt], "static_version": sv, "final": final,
        "epoch": epoch})
    return msg


def _fast_physics(p: tuple) -> PhysicsState:
    """A PhysicsState from the C decoder's parts (float64 x, y; float32 z .. err_lat; uint8 cls, mode)."""
    _, run, tick, t, sumo_step, counters, ids, buf, n = p
    f8 = np.frombuffer(buf, np.float64, 2 * n)
    f4 = np.frombuffer(buf, np.float32, 10 * n, 16 * n)
    u1 = np.frombuffer(buf, np.uint8, 2 * n, 56 * n)
    z, heading, roll, pitch, speed, steer, drive, brake, err_lon, err_lat = (f4[i * n:(i + 1) * n] for i in range(10))
    agents = PhysicsAgents(ids=ids, cls=u1[:n], mode=u1[n:], x=f8[:n], y=f8[n:], z=z, heading=heading, roll=roll,
                           pitch=pitch, speed=speed, steer=steer, drive=drive, brake=brake, err_lon=err_lon,
                           err_lat=err_lat)
    return PhysicsState(run=run, tick=tick, time=t, sumo_step=sumo_step, agents=agents, counters=counters)


#: The C decoder's first part says which message its parts make.
_FAST_BUILD = {1: _fast_step, 2: _fast_physics}


def decode_as(data: bytes, cls: type, limits: DecodeLimits = DEFAULT_LIMITS) -> Any:
    """Decode and check the message is of type ``cls`` (e.g. ``StepMessage``)."""
    msg = decode(data, limits)
    if not isinstance(msg, cls):
        raise ProtocolError(f"expected a {cls.__name__} message, got {type(msg).__name__}", "kind")
    return msg


_PEEK_HEAD_BYTES = 4096  # the encoder writes kind, run, step, t, dt, sv, epoch before the agent columns


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
