"""The compact recording codec (protocol/SPEC.md 11) exactly as first written: one numpy pass
per field and message. Frozen here as the reference the vectorised ``sumoco.recording.codec``
must match byte for byte (tests/test_record_codec_equal.py); do not optimise it."""

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


@dataclass
class _KeyState:
    """What both sides remember of the last message on one key."""

    seq: int = -1
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, object))
    q: dict = field(default_factory=dict)  # field -> quantised values of the last message
    dq: dict = field(default_factory=dict)  # field -> last change (valid where ``has_dq``)
    has_dq: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    path_off: np.ndarray = field(default_factory=lambda: np.zeros(1, np.int64))
    path_q: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    extra: dict = field(default_factory=dict)  # vtypes / tls last stored


def _prev_index(ids: list[str], prev: np.ndarray) -> np.ndarray:
    """Index of each id in the previous list, -1 where new (vectorised via a sorted lookup)."""
    cur = np.asarray(ids, dtype=object)
    if not len(prev) or not len(cur):
        return np.full(len(cur), -1, np.int64)
    order = np.argsort(prev.astype(str), kind="stable")
    sp = prev.astype(str)[order]
    cs = cur.astype(str)
    pos = np.clip(np.searchsorted(sp, cs), 0, len(sp) - 1)
    hit = sp[pos] == cs
    return np.where(hit, order[pos], -1).astype(np.int64)


def _quant(v: np.ndarray, unit: float | None) -> np.ndarray:
    a = np.asarray(v, np.float64)
    if unit is None:
        return np.asarray(v).astype(np.int64)
    return np.rint(a / unit).astype(np.int64)


def _dequant(q: np.ndarray, unit: float | None, dt: str) -> np.ndarray:
    if unit is None:
        return q.astype(dt)
    return (q * unit).astype(dt)


class _Columns:
    """Shared residual logic of encoder and decoder for one key."""

    def __init__(self, fields) -> None:
        self.fields = fields

    @staticmethod
    def predict(st: _KeyState, name: str, order: int, pidx: np.ndarray) -> np.ndarray:
        old = pidx >= 0
        pred = np.zeros(len(pidx), np.int64)
        last = st.q.get(name)
        if last is None or not len(last):
            return pred
        j = pidx[old]
        pred[old] = last[j]
        if order == 2 and name in st.dq:
            ok = st.has_dq[j]
            pred[np.flatnonzero(old)[ok]] += st.dq[name][j[ok]]
        return pred

    @staticmethod
    def update(st: _KeyState, fields, q: dict, pidx: np.ndarray) -> None:
        old = pidx >= 0
        dq = {}
        for name, _unit, order, _dt in fields:
            if order == 2:
                d = np.zeros(len(pidx), np.int64)
                if name in st.q and len(st.q[name]):
                    d[old] = q[name][old] - st.q[name][pidx[old]]
                dq[name] = d
        st.q, st.dq, st.has_dq = q, dq, old.copy()


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
            fields, schema, ids = STEP_FIELDS, STEP_SCHEMA, a.ids
        elif isinstance(msg, PhysicsState):
            a = msg.agents
            vals = {f[0]: getattr(a, f[0]) for f in PHYSICS_FIELDS}
            head = {"run": msg.run, "tick": int(msg.tick), "t": float(msg.time), "sumo_step": int(msg.sumo_step),
                    "counters": dict(msg.counters)}
            fields, schema, ids = PHYSICS_FIELDS, PHYSICS_SCHEMA, a.ids
        else:
            raise TypeError(f"no compact encoding for {type(msg).__name__}")
        pidx = _prev_index(ids, st.ids)
        new = pidx < 0
        # agent order as references: consecutive indices pack to a run of 1s
        ref = np.diff(np.concatenate([[-1], pidx]))
        cols = {}
        q = {}
        for name, unit, order, _dt in fields:
            q[name] = _quant(vals[name], unit)
            cols[name] = _pack_int(q[name] - _Columns.predict(st, name, order, pidx))
        rec = {"f": FORMAT, "seq": seq, "key": key, "n": len(ids), "ref": _pack_int(ref),
               "new": [ids[i] for i in np.flatnonzero(new)], "cols": cols, **head}
        if isinstance(msg, StepMessage) and len(msg.agents.path_offsets):
            off = np.asarray(msg.agents.path_offsets, np.int64)
            off = off - off[0]
            pq = np.rint(np.asarray(msg.agents.path_xy, np.float64).reshape(-1, 2)[:off[-1]] / PATH_UNIT).astype(np.int64)
            res = pq - _path_pred(st, pidx, off)
            rec["path"] = {"cnt": _pack_int(np.diff(off)), "x": _pack_int(res[:, 0]), "y": _pack_int(res[:, 1])}
            st.path_off, st.path_q = off, pq
        else:
            st.path_off, st.path_q = np.zeros(1, np.int64), np.zeros((0, 2), np.int64)
        _Columns.update(st, fields, q, pidx)
        st.ids = np.asarray(list(ids), dtype=object)
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
        fields = STEP_FIELDS if schema == STEP_SCHEMA else PHYSICS_FIELDS
        n = int(rec["n"])
        pidx = np.cumsum(_unpack_int(rec["ref"])) - 1 if n else np.zeros(0, np.int64)
        new_names = iter(rec["new"])
        ids = [st.ids[j] if j >= 0 else next(new_names) for j in pidx.tolist()]
        q, vals = {}, {}
        for name, unit, order, dt in fields:
            q[name] = _unpack_int(rec["cols"][name]) + _Columns.predict(st, name, order, pidx)
            vals[name] = _dequant(q[name], unit, dt)
        path_off, path_xy = np.zeros(0, np.uint32), np.zeros((0, 2), np.float64)
        if "path" in rec:
            off = np.concatenate([[0], np.cumsum(_unpack_int(rec["path"]["cnt"]))]).astype(np.int64)
            res = np.column_stack([_unpack_int(rec["path"]["x"]), _unpack_int(rec["path"]["y"])])
            pq = res + _path_pred(st, pidx, off)
            st.path_off, st.path_q = off, pq
            path_off, path_xy = off.astype(np.uint32), pq * PATH_UNIT
        else:
            st.path_off, st.path_q = np.zeros(1, np.int64), np.zeros((0, 2), np.int64)
        _Columns.update(st, fields, q, pidx)
        st.ids = np.asarray(ids, dtype=object)
        st.seq = rec["seq"]
        self._st[topic] = st
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
