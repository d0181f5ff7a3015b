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
from typing import Any, Union

import msgpack
import numpy as np

from protocol.errors import ProtocolError
from protocol.messages import (
    SCHEMA_VERSION,
    AgentBatch,
    AgentClass,
    AgentMode,
    EgoPose,
    JunctionTable,
    LaneTable,
    PhysicsAgents,
    PhysicsState,
    StaticData,
    StepAck,
    StepMessage,
    TlsLinks,
    TrafficLights,
    VType,
)

Message = Union[StepMessage, EgoPose, PhysicsState, StepAck, StaticData]

#: Hard limits that make a hostile or corrupt message fail fast instead of allocating.
MAX_AGENTS = 200_000
MAX_POINTS = 20_000_000
MAX_STR = 1_024
MAX_MESSAGE_BYTES = 256 * 1024 * 1024

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
    ("la_x", "<f4"),
    ("la_y", "<f4"),
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

TLS_LINK_COLUMNS: tuple[tuple[str, str], ...] = (
    ("tls", "<u2"),
    ("link", "<u2"),
    ("from_lane", "<i4"),
    ("to_lane", "<i4"),
    ("via_lane", "<i4"),
)

_N_CLASSES = len(AgentClass)
_N_MODES = len(AgentMode)


# --------------------------------------------------------------------------- encoding


def _bin(a: np.ndarray, dtype: str) -> bytes:
    return np.ascontiguousarray(a, dtype=dtype).tobytes()


def _columns(obj: Any, spec: tuple[tuple[str, str], ...]) -> dict[str, bytes]:
    return {name: _bin(getattr(obj, name), dt) for name, dt in spec}


def _head(kind: str) -> dict[str, Any]:
    return {"v": list(SCHEMA_VERSION), "kind": kind}


def _polyline(offsets: np.ndarray, xy: np.ndarray) -> dict[str, bytes]:
    return {"off": _bin(offsets, "<u4"), "xy": _bin(np.asarray(xy).reshape(-1), "<f4")}


def encode(msg: Message) -> bytes:
    """Encode any protocol message to msgpack bytes."""
    if isinstance(msg, StepMessage):
        a = msg.agents
        agents = {"n": a.n, "id": list(a.ids), **_columns(a, STEP_AGENT_COLUMNS)}
        if len(a.path_offsets):
            agents["path"] = _polyline(a.path_offsets, a.path_xy)
        d = _head("step") | {
            "run": msg.run,
            "step": int(msg.step),
            "t": float(msg.time),
            "dt": float(msg.step_length),
            "vtypes": [[v.id, v.vclass] for v in msg.vtypes],
            "agents": agents,
            "tls": {
                "id": list(msg.tls.ids),
                "state": list(msg.tls.state),
                "phase": [int(p) for p in msg.tls.phase],
                "next": [float(s) for s in msg.tls.next_switch],
            },
        }
    elif isinstance(msg, EgoPose):
        d = _head("ego") | {
            "id": msg.id, "x": float(msg.x), "y": float(msg.y), "angle": float(msg.angle),
            "speed": float(msg.speed), "t": float(msg.time), "vtype": msg.vtype,
        }
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
    elif isinstance(msg, StepAck):
        d = _head("ack") | {"run": msg.run, "step": int(msg.step), "tick": int(msg.tick)}
    elif isinstance(msg, StaticData):
        ln = msg.lanes
        d = _head("static") | {
            "run": msg.run,
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


def _str(d: dict, key: str, where: str) -> str:
    v = _get(d, key, where)
    if not isinstance(v, str):
        raise ProtocolError(f"expected a string, got {type(v).__name__}", where + key)
    if len(v) > MAX_STR:
        raise ProtocolError(f"expected at most {MAX_STR} characters, got {len(v)}", where + key)
    return v


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


def _strs(d: dict, key: str, where: str, n: int | None = None) -> list[str]:
    v = _list(d, key, where, n)
    for s in v:
        if not isinstance(s, str) or len(s) > MAX_STR:
            raise ProtocolError(f"expected strings of at most {MAX_STR} characters", where + key)
    return v


def _col(d: dict, key: str, dtype: str, n: int, where: str) -> np.ndarray:
    b = _get(d, key, where)
    if not isinstance(b, bytes):
        raise ProtocolError(f"expected bin of {n} x {dtype}, got {type(b).__name__}", where + key)
    size = np.dtype(dtype).itemsize
    if len(b) != n * size:
        raise ProtocolError(
            f"expected {n} x {dtype} = {n * size} bytes, got {len(b)}", where + key
        )
    a = np.frombuffer(b, dtype=dtype)
    if a.dtype.kind == "f" and n and not np.isfinite(a).all():
        raise ProtocolError("expected finite values, got NaN or inf", where + key)
    return a


def _columns_in(d: dict, spec, n: int, where: str) -> dict[str, np.ndarray]:
    return {name: _col(d, name, dt, n, where) for name, dt in spec}


def _count(d: dict, where: str, limit: int = MAX_AGENTS) -> int:
    return _int(d, "n", where, 0, limit)


def _polyline_in(d: dict, key: str, n: int, where: str) -> tuple[np.ndarray, np.ndarray]:
    p = _map(d, key, where)
    w = f"{where}{key}."
    off = _col(p, "off", "<u4", n + 1, w)
    xy_b = _get(p, "xy", w)
    if not isinstance(xy_b, bytes) or len(xy_b) % 8:
        raise ProtocolError("expected bin of float32 (x, y) pairs", w + "xy")
    m = len(xy_b) // 8
    if m > MAX_POINTS:
        raise ProtocolError(f"expected at most {MAX_POINTS} points, got {m}", w + "xy")
    xy = _col(p, "xy", "<f4", 2 * m, w).reshape(m, 2)
    if off[0] != 0 or off[-1] != m or (n and np.any(np.diff(off.astype(np.int64)) < 0)):
        raise ProtocolError(f"expected offsets rising from 0 to {m}", w + "off")
    return off, xy


def _check_range(a: np.ndarray, lo: int, hi: int, field: str) -> None:
    if len(a) and (int(a.min()) < lo or int(a.max()) > hi):
        raise ProtocolError(f"expected values in {lo}..{hi}", field)


def decode(data: bytes | bytearray | memoryview) -> Message:
    """Decode and validate one message; raises ``ProtocolError`` on anything wrong."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"expected bytes, got {type(data).__name__}")
    if len(data) > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"message of {len(data)} bytes exceeds {MAX_MESSAGE_BYTES}")
    try:
        d = msgpack.unpackb(
data, raw=False, strict_map_key=True, use_list=True)
    except Exception as e:  # msgpack raises a zoo of types for corrupt input
        raise ProtocolError(f"not a msgpack document ({type(e).__name__}: {e})") from None
    if not isinstance(d, dict):
        raise ProtocolError(f"expected a map at top level, got {type(d).__name__}")
    try:
        return _decode_map(d)
    except ProtocolError:
        raise
    except (ValueError, TypeError, KeyError, IndexError, OverflowError) as e:
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


def _decode_map(d: dict) -> Message:
    _check_version(d)
    kind = _str(d, "kind", "")
    dec = _DECODERS.get(kind)
    if dec is None:
        raise ProtocolError(f"expected one of {sorted(_DECODERS)}, got {kind!r}", "kind")
    return dec(d)


def _decode_step(d: dict) -> StepMessage:
    vt_raw = _list(d, "vtypes", "")
    vtypes = []
    for i, pair in enumerate(vt_raw):
        if (
            not isinstance(pair, list) or len(pair) != 2
            or not all(isinstance(s, str) and len(s) <= MAX_STR for s in pair)
        ):
            raise ProtocolError("expected [vtype id, vclass] string pairs", f"vtypes[{i}]")
        vtypes.append(VType(pair[0], pair[1]))
    a = _map(d, "agents", "")
    n = _count(a, "agents.")
    cols = _columns_in(a, STEP_AGENT_COLUMNS, n, "agents.")
    _check_range(cols["cls"], 0, _N_CLASSES - 1, "agents.cls")
    _check_range(cols["vtype"], 0, max(len(vtypes) - 1, 0), "agents.vtype")
    if n and not vtypes:
        raise ProtocolError("expected a vtype table when agents are present", "vtypes")
    _check_range(cols["lane"], -1, 2**31 - 1, "agents.lane")
    if "path" in a:
        off, xy = _polyline_in(a, "path", n, "agents.")
    else:
        off, xy = np.zeros(0, np.uint32), np.zeros((0, 2), np.float32)
    agents = AgentBatch(
        ids=_strs(a, "id", "agents.", n), path_offsets=off, path_xy=xy, **cols
    )
    t = _map(d, "tls", "")
    ids = _strs(t, "id", "tls.")
    k = len(ids)
    phase = _list(t, "phase", "tls.", k)
    nxt = _list(t, "next", "tls.", k)
    if not all(isinstance(p, int) and not isinstance(p, bool) for p in phase):
        raise ProtocolError("expected integers", "tls.phase")
    if not all(isinstance(s, (int, float)) and math.isfinite(s) for s in nxt):
        raise ProtocolError("expected finite numbers", "tls.next")
    tls = TrafficLights(
        ids=ids,
        state=_strs(t, "state", "tls.", k),
        phase=np.asarray(phase, np.int32) if k else np.zeros(0, np.int32),
        next_switch=np.asarray(nxt, np.float32) if k else np.zeros(0, np.float32),
    )
    return StepMessage(
        run=_str(d, "run", ""),
        step=_int(d, "step", "", 0),
        time=_float(d, "t", ""),
        step_length=_float(d, "dt", "", 1e-6, 3600.0),
        agents=agents,
        tls=tls,
        vtypes=vtypes,
    )


def _decode_ego(d: dict) -> EgoPose:
    return EgoPose(
        id=_str(d, "id", ""),
        x=_float(d, "x", ""),
        y=_float(d, "y", ""),
        angle=_float(d, "angle", ""),
        speed=_float(d, "speed", "", -200.0, 200.0),
        time=_float(d, "t", "") if "t" in d else 0.0,
        vtype=_str(d, "vtype", "") if "vtype" in d else "",
    )


def _decode_physics(d: dict) -> PhysicsState:
    a = _map(d, "agents", "")
    n = _count(a, "agents.")
    cols = _columns_in(a, PHYSICS_AGENT_COLUMNS, n, "agents.")
    _check_range(cols["cls"], 0, _N_CLASSES - 1, "agents.cls")
    _check_range(cols["mode"], 0, _N_MODES - 1, "agents.mode")
    c = _map(d, "counters", "")
    for k, v in c.items():
        if not isinstance(v, int) or isinstance(v, bool):
            raise ProtocolError("expected an integer", f"counters.{k}")
    return PhysicsState(
        run=_str(d, "run", ""),
        tick=_int(d, "tick", "", 0),
        time=_float(d, "t", ""),
        sumo_step=_int(d, "sumo_step", "", -1),
        agents=PhysicsAgents(ids=_strs(a, "id", "agents.", n), **cols),
        counters=dict(c),
    )


def _decode_ack(d: dict) -> StepAck:
    return StepAck(run=_str(d, "run", ""), step=_int(d, "step", "", 0), tick=_int(d, "tick", "", 0))


def _decode_static(d: dict) -> StaticData:
    net = _map(d, "net", "")
    off = _list(net, "offset", "net.", 2)
    bounds = _list(net, "bounds", "net.", 4)
    if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in off + bounds):
        raise ProtocolError("expected finite numbers", "net.offset/bounds")
    ln = _map(d, "lanes", "")
    nl = _count(ln, "lanes.", MAX_POINTS)
    allow = _list(ln, "allow", "lanes.", nl)
    for i, a in enumerate(allow):
        if not isinstance(a, list) or not all(isinstance(s, str) for s in a):
            raise ProtocolError("expected arrays of vClass strings", f"lanes.allow[{i}]")
    l_off, l_xy = _polyline_in(ln, "shape", nl, "lanes.")
    lanes = LaneTable(
        ids=_strs(ln, "id", "lanes.", nl),
        edge=_strs(ln, "edge", "lanes.", nl),
        width=_col(ln, "width", "<f4", nl, "lanes."),
        length=_col(ln, "length", "<f4", nl, "lanes."),
        allow=allow,
        shape_offsets=l_off,
        shape_xy=l_xy,
    )
    jn = _map(d, "junctions", "")
    nj = _count(jn, "junctions.", MAX_POINTS)
    j_off, j_xy = _polyline_in(jn, "shape", nj, "junctions.")
    tls_ids = _strs(d, "tls", "")
    tls_links = TlsLinks.empty()
    if "tls_links" in d:  # optional: added in 1.1
        tl = _map(d, "tls_links", "")
        nt = _count(tl, "tls_links.", MAX_POINTS)
        cols = _columns_in(tl, TLS_LINK_COLUMNS, nt, "tls_links.")
        _check_range(cols["tls"], 0, max(len(tls_ids) - 1, 0), "tls_links.tls")
        for k in ("from_lane", "to_lane", "via_lane"):
            _check_range(cols[k], -1, max(nl - 1, -1), f"tls_links.{k}")
        tls_links = TlsLinks(**cols)
    vt = _map(d, "vtypes", "")
    nv = _count(vt, "vtypes.", 65_535)
    vids = _strs(vt, "id", "vtypes.", nv)
    vcls = _strs(vt, "vclass", "vtypes.", nv)
    return StaticData(
        run=_str(d, "run", ""),
        step_length=_float(d, "dt", "", 1e-6, 3600.0),
        net_offset=(float(off[0]), float(off[1])),
        projection=_str(net, "proj", "net."),
        bounds=tuple(float(b) for b in bounds),  # type: ignore[arg-type]
        lanes=lanes,
        junctions=JunctionTable(_strs(jn, "id", "junctions.", nj), j_off, j_xy),
        vtypes=[VType(i, c) for i, c in zip(vids, vcls)],
        vtype_length=_col(vt, "length", "<f4", nv, "vtypes."),
        vtype_width=_col(vt, "width", "<f4", nv, "vtypes."),
        tls_ids=tls_ids,
        tls_links=tls_links,
    )


_DECODERS = {
    "step": _decode_step,
    "ego": _decode_ego,
    "physics": _decode_physics,
    "ack": _decode_ack,
    "static": _decode_static,
}


def decode_as(data: bytes, cls: type) -> Any:
    """Decode and check the message is of type ``cls`` (e.g. ``StepMessage``)."""
    msg = decode(data)
    if not isinstance(msg, cls):
        raise ProtocolError(f"expected a {cls.__name__} message, got {type(msg).__name__}", "kind")
    return msg
