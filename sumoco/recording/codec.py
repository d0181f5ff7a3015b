"""Compact recording encoding of step and physics messages (protocol/SPEC.md 11).

A recording spends most of its bytes on the per-agent columns of steps and physics
states. The compact encoding stores them quantised to fixed units (``STEP_FIELDS``,
``PHYSICS_FIELDS``) as integer residuals against a prediction from the previous messages
on the same key: agent ids as references into the previous message's list (new names
spelt out), values as the change since the last message (first order) or since a
constant-velocity guess from the last two (second order, positions and headings). Small
residuals of smooth motion then pack into int8/int16 columns that zstd shrinks further.
Every ``KEYFRAME_EVERY`` messages per key a keyframe stores absolute values.

Decoding gives back protocol messages (``StepMessage`` / ``PhysicsState``) equal to the
recorded ones up to the quantisation (half a unit), which ``protocol.codec.encode`` turns
into valid payloads again. The state is per key; a message whose sequence number does not
follow the last decoded one on its key is skipped until the next keyframe.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import msgpack
import numpy as np

from protocol.messages import (AgentBatch, PhysicsAgents, PhysicsState, StepMessage, TrafficLights, VType)

log = logging.getLogger(__name__)

FORMAT = 1
KEYFRAME_EVERY = 100  # [messages per key] absolute values this often (10 s of steps at 10 Hz)
STEP_SCHEMA = "sumoco.rec.step"
PHYSICS_SCHEMA = "sumoco.rec.physics"
ENCODING = "sumoco-rec"

#: (field, unit, order): values are stored as round(value / unit); unit None = exact integer.
#: order 2 predicts from the last two messages (smooth motion), 1 from the last one.
STEP_FIELDS: tuple[tuple[str, float | None, int, str], ...] = (
    ("x", 1e-3, 2, "f8"), ("y", 1e-3, 2, "f8"), ("angle", 1e-2, 2, "f4"),
    ("speed", 1e-3, 1, "f4"), ("accel", 1e-3, 1, "f4"),
    ("la_dx", 1e-2, 1, "f8"), ("la_dy", 1e-2, 1, "f8"),
    ("length", 1e-3, 1, "f4"), ("width", 1e-3, 1, "f4"),
    ("cls", None, 1, "u1"), ("vtype", None, 1, "u2"), ("signals", None, 1, "u2"),
    ("lane", None, 1, "i4"), ("flags", None, 1, "u1"),
)
PHYSICS_FIELDS: tuple[tuple[str, float | None, int, str], ...] = (
    ("x", 5e-3, 2, "f8"), ("y", 5e-3, 2, "f8"), ("z", 1e-3, 1, "f4"),
    ("heading", 5e-2, 2, "f4"), ("roll", 1e-2, 1, "f4"), ("pitch", 1e-2, 1, "f4"),
    ("speed", 1e-3, 1, "f4"), ("steer", 1e-2, 1, "f4"),
    ("drive", 1e-1, 1, "f4"), ("brake", 1e-1, 1, "f4"),
    ("err_lon", 1e-3, 1, "f4"), ("err_lat", 1e-3, 1, "f4"),
    ("cls", None, 1, "u1"), ("mode", None, 1, "u1"),
)
PATH_UNIT = 1e-2  # [m] path vertices (absolute, predicted from the agent's previous path)


class CompactError(ValueError):
    """A compact record that cannot be decoded (corrupt, or its predecessor is missing)."""


def _pack_int(a: np.ndarray) -> tuple[str, bytes]:
    """Smallest little-endian int type that holds every value."""
    if not len(a):
        return "i1", b""
    lo, hi = int(a.min()), int(a.max())
    for dt, lim in (("i1", 2**7), ("i2", 2**15), ("i4", 2**31)):
        if -lim <= lo and hi < lim:
            return dt, np.ascontiguousarray(a, "<" + dt).tobytes()
    return "i8", np.ascontiguousarray(a, "<i8").tobytes()


def _unpack_int(v) -> np.ndarray:
    dt, b = v
    return np.frombuffer(b, "<" + dt).astype(np.int64)


class _Layout:
    """One message kind's fields as index arrays, so that a message's columns are handled as
    one (fields x agents) matrix in a few numpy calls instead of several per field."""

    def __init__(self, fields) -> None:
        self.fields = fields
        self.names = tuple(f[0] for f in fields)
        real = [i for i, f in enumerate(fields) if f[1] is not None]
        exact = [i for i, f in enumerate(fields) if f[1] is None]
        # the tables list the quantised fields first: slices then address them without copies
        if real + exact != list(range(len(fields))):
            raise ValueError("compact fields must list the quantised ones before the exact ones")
        self.n_real = len(real)
        self.real_names = tuple(fields[i][0] for i in real)
        self.exact_names = tuple(fields[i][0] for i in exact)
        self.units = np.array([fields[i][1] for i in real], np.float64).reshape(-1, 1)
        self.order2 = np.array([i for i, f in enumerate(fields) if f[2] == 2], np.intp)
        self.order2_mask = np.array([[f[2] == 2] for f in fields], np.int64)  # (fields x 1) 1 on order-2 rows
        self.dts = tuple(f[3] for f in fields)

    def quantise(self, vals: dict, n: int) -> np.ndarray:
        """(fields x n) int64: ``rint(value / unit)`` per quantised field, the exact ones as
        integers (the same numpy casts as one field at a time)."""
        q = np.empty((len(self.fields), n), np.int64)
        k = self.n_real
        real = np.array([vals[name] for name in self.real_names], np.float64)
        if real.shape != (k, n):
            raise ValueError(f"agent columns of unequal length ({real.shape[1:]} values for {n} agents)")
        np.divide(real, self.units, out=real)
        np.rint(real, out=real)
        np.copyto(q[:k], real, casting="unsafe")
        for i, name in enumerate(self.exact_names, k):
            v = vals[name]
            if len(v) != n:
                raise ValueError(f"agent columns of unequal length ({len(v)} {name} for {n} agents)")
            q[i] = v  # the integer cast of ``astype(int64)``
        return q

    def pack(self, res: np.ndarray) -> dict:
        """Field -> ``[dtype, bytes]``: each row in its smallest int type (as ``_pack_int``)."""
        n = res.shape[1]
        if not n:
            return {name: ("i1", b"") for name in self.names}
        blobs, out = {}, {}
        for i, (name, lo, hi) in enumerate(zip(self.names, res.min(axis=1).tolist(), res.max(axis=1).tolist())):
            m = max(~lo, hi)  # ~lo = -lo - 1: fits iN when m < 2**(N-1)
            lv = 0 if m < 0x80 else 1 if m < 0x8000 else 2 if m < 0x80000000 else 3
            blob = blobs.get(lv)
            if blob is None:  # one cast and one copy per int type, not per field
                blob = blobs[lv] = res.astype(_INT_TYPES[lv]).tobytes()
            w = n << lv
            out[name] = (_INT_NAMES[lv], blob[i * w:(i + 1) * w])
        return out

    def unpack(self, cols: dict, n: int) -> np.ndarray:
        dts, parts = [], []
        for name in self.names:
            dt, b = cols[name]
            size = _INT_SIZES.get(dt)
            if size is None or len(b) != n * size:
                raise CompactError(f"column {name}: {len(b)} bytes of {dt!r} for {n} agents")
            dts.append(dt)
            parts.append(b)
        if dts.count(dts[0]) == len(dts):  # one int type: one conversion
            return np.frombuffer(b"".join(parts), "<" + dts[0]).reshape(len(dts), n).astype(np.int64)
        res = np.empty((len(self.names), n), np.int64)
        for dt in set(dts):  # one conversion per int type, not per field
            rows = [i for i, d in enumerate(dts) if d == dt]
            res[rows] = np.frombuffer(b"".join([parts[i] for i in rows]), "<" + dt).reshape(len(rows), n)
        return res

    def values(self, q: np.ndarray) -> dict:
        """Field -> column of the message: ``q * unit`` (or q) in the field's dtype; the
        columns of one dtype are rows of one new array."""
        k = self.n_real
        real = q[:k] * self.units
        groups = {}
        out = {}
        for i, name in enumerate(self.names):
            dt = self.dts[i]
            conv = groups.get((i < k, dt))
            if conv is None:
                conv = groups[(i < k, dt)] = real.astype(dt) if i < k else q[k:].astype(dt)
            out[name] = conv[i if i < k else i - k]
        return out


_INT_NAMES = ("i1", "i2", "i4", "i8")
_INT_TYPES = tuple(np.dtype("<" + t) for t in _INT_NAMES)
_INT_SIZES = {t: 1 << i for i, t in enumerate(_INT_NAMES)}
# "no paths" (physics states, steps without paths): shared, read-only, not allocated per message
_NO_PATH_OFF = np.zeros(1, np.int64)
_NO_PATH_Q = np.zeros((0, 2), np.int64)
_NO_PATH_OFF.flags.writeable = _NO_PATH_Q.flags.writeable = False
_STEP = _Layout(STEP_FIELDS)
_PHYSICS = _Layout(PHYSICS_FIELDS)


@dataclass
class _KeyState:
    """What both sides remember of the last message on one key."""

    seq: int = -1
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, object))
    id_list: list = field(default_factory=list)  # ``ids`` as a list (compared whole: the same agents?)
    unique: bool = True  # no id twice in ``ids`` (only then does an equal list map to itself)
    q: np.ndarray | None = None  # (fields x agents) quantised values of the last message
    base: np.ndarray | None = None  # the next prediction of each remembered agent: q, plus the
    # last change on order-2 fields (0 where the agent was new in the last message)
    path_off: np.ndarray = field(default_factory=lambda: _NO_PATH_OFF)
    path_q: np.ndarray = field(default_factory=lambda: _NO_PATH_Q)
    extra: dict = field(default_factory=dict)  # vtypes / tls last stored


def _prev_index(ids: list[str], prev: np.ndarray) -> np.ndarray:
    """Index of each id in the previous list, -1 where new (vectorised via a sorted lookup)."""
    cur = np.asarray(ids, dtype=object)
    if not len(prev) or not len(cur):
        return np.full(len(cur), -1, np.int64)
    ps = prev.astype(str)
    order = np.argsort(ps, kind="stable")
    sp = ps[order]
    cs = cur.astype(str)
    pos = np.clip(np.searchsorted(sp, cs), 0, len(sp) - 1)
    hit = sp[pos] == cs
    return np.where(hit, order[pos], -1).astype(np.int64)


def _predict(st: _KeyState, pidx: np.ndarray | None) -> np.ndarray | None:
    """(fields x n) prediction of each agent (SPEC 11); None = all zero. ``pidx`` None: the
    agents are the remembered ones in the same order."""
    if st.base is None:
        return None
    if pidx is None:
        return st.base
    old = pidx >= 0
    if not old.any():
        return None
    pred = st.base[:, np.where(old, pidx, 0)]
    pred[:, ~old] = 0
    return pred


def _remember(st: _KeyState, q: np.ndarray, pidx: np.ndarray | None, lay: _Layout) -> None:
    """Keep ``q`` and the next prediction base: q plus, on order-2 fields, the change since
    the last message of the agents that were in it."""
    if st.q is None or not len(lay.order2):
        st.q, st.base = q, q
        return
    # whole-matrix arithmetic, the change masked to the order-2 rows: cheaper than indexing rows
    if pidx is None:
        change = q - st.q
    else:
        change = np.zeros_like(q)
        old = np.flatnonzero(pidx >= 0)
        change[:, old] = q[:, old] - st.q[:, pidx[old]]
    change *= lay.order2_mask
    change += q
    st.q, st.base = q, change


def _path_pred(st: _KeyState, pidx: np.ndarray, off: np.ndarray) -> np.ndarray:
    """Vertex i of an agent's path predicted by vertex i of its previous path (its last
    vertex past the end); 0 for new agents."""
    cnt = np.diff(off)
    m = int(off[-1])
    pred = np.zeros((m, 2), np.int64)
    if not m or not len(st.path_q):
        return pred
    prev_cnt = np.diff(st.path_off)
    own = np.repeat(np.arange(len(cnt)), cnt)
    i = np.arange(m) - off[:-1][own]
    j = pidx[own]
    pc = np.where(j >= 0, prev_cnt[np.maximum(j, 0)], 0)
    ok = pc > 0
    src = st.path_off[np.maximum(j, 0)] + np.minimum(i, pc - 1)
    pred[ok] = st.path_q[src[ok]]
    return pred


class CompactEncoder:
    """Encodes steps and physics states per key (one instance per recording)."""

    def __init__(self, keyframe_every: int = KEYFRAME_EVERY) -> None:
        self.keyframe_every = keyframe_every
        self._st: dict[str, _KeyState] = {}

    def reset(self, topic: str) -> None:
        """Forget a key's state (its next message is a keyframe): after a failed write."""
        self._st.pop(topic, None)

    def agents_per_key(self) -> dict[str, int]:
        """Agents remembered per key (what the encoder's memory grows with)."""
        return {topic: len(st.ids) for topic, st in self._st.items()}

    def encode(self, topic: str, msg) -> tuple[str, bytes]:
        """(schema name, record bytes) of a step or physics message."""
        st = self._st.get(topic)
        seq = 0 if st is None else st.seq + 1
        if st is None or seq % self.keyframe_every == 0:
            st = _KeyState()
        st.seq = seq
        key = seq % self.keyframe_every == 0
        if isinstance(msg, StepMessage):
            a = msg.agents
            x, y = np.asarray(a.x, np.float64), np.asarray(a.y, np.float64)
            vals = {f[0]: getattr(a, f[0]) for f in STEP_FIELDS if not f[0].startswith("la_")}
            vals["la_dx"], vals["la_dy"] = np.subtract(a.la_x, x), np.subtract(a.la_y, y)
            head = {"run": msg.run, "step": int(msg.step), "t": float(msg.time), "dt": float(msg.step_length),
                    "sv": int(msg.static_version), "final": bool(msg.final),
                    "epoch": int(msg.epoch)}
            tls = [list(msg.tls.ids), list(msg.tls.state), [int(p) for p in msg.tls.phase],
                   [float(s) for s in msg.tls.next_switch], None if msg.tls.program is None else list(msg.tls.program)]
            vt = None if msg.vtypes is None else [[v.id, v.vclass] for v in msg.vtypes]
            # repeated tables are stored once ("same": the previous message's)
            head["tls"] = "same" if st.extra.get("tls") == tls else tls
            head["vtypes"] = "same" if ("vtypes" in st.extra and st.extra["vtypes"] == vt) else vt
            st.extra["tls"], st.extra["vtypes"] = tls, vt
            lay, schema, ids = _STEP, STEP_SCHEMA, a.ids
        elif isinstance(msg, PhysicsState):
            a = msg.agents
            vals = {f[0]: getattr(a, f[0]) for f in PHYSICS_FIELDS}
            head = {"run": msg.run, "tick": int(msg.tick), "t": float(msg.time), "sumo_step": int(msg.sumo_step),
                    "counters": dict(msg.counters)}
            lay, schema, ids = _PHYSICS, PHYSICS_SCHEMA, a.ids
        else:
            raise TypeError(f"no compact encoding for {type(msg).__name__}")
        ids = list(ids)
        n = len(ids)
        q = lay.quantise(vals, n)
        # Mostly the same agents in the same order as last time: then every agent refers to
        # itself (a run of 1s) and the sorted name lookup is not needed. Only for unique ids:
        # the lookup maps a repeated name to its first occurrence.
        if n and st.unique and ids == st.id_list:
            pidx = None
            ref, new_names = ("i1", b"\x01" * n), []
        else:
            pidx = _prev_index(ids, st.ids)
            # agent order as references: consecutive indices pack to a run of 1s
            ref = _pack_int(np.diff(np.concatenate([[-1], pidx])))
            new_names = [ids[i] for i in np.flatnonzero(pidx < 0)]
            st.ids, st.id_list, st.unique = np.asarray(ids, dtype=object), ids, len(set(ids)) == n
        pred = _predict(st, pidx)
        cols = lay.pack(q if pred is None else q - pred)
        rec = {"f": FORMAT, "seq": seq, "key": key, "n": n, "ref": ref,
               "new": new_names, "cols": cols, **head}
        if isinstance(msg, StepMessage) and len(msg.agents.path_offsets):
            off = np.asarray(msg.agents.path_offsets, np.int64)
            off = off - off[0]
            pq = np.rint(np.asarray(msg.agents.path_xy, np.float64).reshape(-1, 2)[:off[-1]] / PATH_UNIT).astype(np.int64)
            res = pq - _path_pred(st, np.arange(n) if pidx is None else pidx, off)
            rec["path"] = {"cnt": _pack_int(np.diff(off)), "x": _pack_int(res[:, 0]), "y": _pack_int(res[:, 1])}
            st.path_off, st.path_q = off, pq
        else:
            st.path_off, st.path_q = _NO_PATH_OFF, _NO_PATH_Q
        _remember(st, q, pidx, lay)
        self._st[topic] = st
        return schema, msgpack.packb(rec, use_bin_type=True)


class CompactDecoder:
    """Decodes compact records back to protocol messages (one instance per read)."""

    def __init__(self) -> None:
        self._st: dict[str, _KeyState] = {}
        self.skipped = 0

    def decode(self, topic: str, schema: str, data: bytes):
        try:
            rec = msgpack.unpackb(data, raw=False)
            if rec.get("f") != FORMAT:
                raise CompactError(f"unknown compact format {rec.get('f')!r}")
        except CompactError:
            raise
        except Exception as e:
            raise CompactError(f"undecodable compact record: {e}") from None
        st = self._st.get(topic)
        if rec["key"]:
            st = _KeyState()
        elif st is None or rec["seq"] != st.seq + 1:
            self._st.pop(topic, None)
            self.skipped += 1
            raise CompactError(f"{topic}: record {rec['seq']} follows a missing one (skipped to the next keyframe)")
        lay = _STEP if schema == STEP_SCHEMA else _PHYSICS
        n = int(rec["n"])
        ref = rec["ref"]
        if n and n == len(st.id_list) and not rec["new"] and ref[0] == "i1" and ref[1] == b"\x01" * n:
            # every agent is the remembered one at its place (the encoder's common case)
            pidx, ids = None, st.id_list
        else:
            pidx = np.cumsum(_unpack_int(ref)) - 1 if n else np.zeros(0, np.int64)
            old = pidx >= 0
            names = np.empty(n, object)
            names[old] = st.ids[pidx[old]]
            new = rec["new"]
            if len(new) != n - int(old.sum()):
                raise CompactError(f"{topic}: record {rec['seq']} names {len(new)} new agents for "
                                   f"{n - int(old.sum())} references to none")
            names[~old] = new
            ids = names.tolist()
            st.ids, st.id_list = names, ids
        res = lay.unpack(rec["cols"], n)
        pred = _predict(st, pidx)
        q = res if pred is None else res + pred
        vals = lay.values(q)
        path_off, path_xy = np.zeros(0, np.uint32), np.zeros((0, 2), np.float64)
        if "path" in rec:
            off = np.concatenate([[0], np.cumsum(_unpack_int(rec["path"]["cnt"]))]).astype(np.int64)
            res = np.column_stack([_unpack_int(rec["path"]["x"]), _unpack_int(rec["path"]["y"])])
            pq = res + _path_pred(st, np.arange(n) if pidx is None else pidx, off)
            st.path_off, st.path_q = off, pq
            path_off, path_xy = off.astype(np.uint32), pq * PATH_UNIT
        else:
            st.path_off, st.path_q = _NO_PATH_OFF, _NO_PATH_Q
        _remember(st, q, pidx, lay)
        st.seq = rec["seq"]
        self._st[topic] = st
        ids = list(ids)  # the message's own list (the state keeps its copy)
        if schema == STEP_SCHEMA:
            tls = st.extra["tls"] if rec["tls"] == "same" else rec["tls"]
            vt = st.extra.get("vtypes") if rec["vtypes"] == "same" else rec["vtypes"]
            st.extra["tls"], st.extra["vtypes"] = tls, vt
            x, y = vals["x"], vals["y"]
            la_x, la_y = x + vals.pop("la_dx"), y + vals.pop("la_dy")
            agents = AgentBatch(ids=ids, la_x=la_x, la_y=la_y, path_offsets=path_off, path_xy=path_xy, **vals)
            lights = TrafficLights(list(tls[0]), list(tls[1]), np.asarray(tls[2], np.int32).reshape(-1),
                                   np.asarray(tls[3], np.float32).reshape(-1),
                                   None if tls[4] is None else list(tls[4]))
            return StepMessage(rec["run"], rec["step"], rec["t"], rec["dt"], agents, lights,
                               None if vt is None else [VType(i, c) for i, c in vt],
                               static_version=rec["sv"], final=rec["final"], epoch=rec.get("epoch", 0))
        return PhysicsState(rec["run"], rec["tick"], rec["t"], rec["sumo_step"],
                            PhysicsAgents(ids=ids, **vals), dict(rec["counters"]))
