"""The C fast path of the codec (protocol._fastcodec) against the Python codec.

Encoding: byte for byte the Python encoder's output. Decoding: the same message, every
array bit for bit with the same dtype and shape; on anything hostile, the same
ProtocolError (message and field), because the fast path steps aside and the Python
decoder words the error. Each case also asserts that the fast path really took the message
when it should, so a C path that silently always falls back fails here too.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import random
import struct

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from protocol import codec
from protocol.codec import (
    DEFAULT_LIMITS, FAST_CODEC, DecodeLimits, decode, decode_python, encode, encode_python,
)
from protocol.errors import ProtocolError
from protocol.golden_vectors import GOLDEN_DIR, invalid_vectors, valid_messages
from protocol.messages import (
    AgentBatch, PhysicsAgents, PhysicsState, StepAck, StepMessage, TrafficLights, VType,
)
from synthetic.traffic import circle_traffic, synthetic_step
from tests.harness import paths_in

needs_c = pytest.mark.skipif(not FAST_CODEC, reason="protocol._fastcodec not built (or SUMOCO_PURE_CODEC set)")


# --------------------------------------------------------------------------- helpers


def _same(a, b, path: str = "msg") -> None:
    """Equal down to the bits: types, dtypes, shapes, array bytes, float bit patterns."""
    assert type(a) is type(b), (path, type(a), type(b))
    if dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            _same(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, (path, a.dtype, b.dtype, a.shape, b.shape)
        assert a.tobytes() == b.tobytes(), path
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{path}[{i}]")
    elif isinstance(a, dict):
        assert list(a) == list(b), path
        for k in a:
            _same(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, float):
        assert struct.pack("<d", a) == struct.pack("<d", b), (path, a, b)
    else:
        assert a == b, (path, a, b)


def _fast_takes(data, limits: DecodeLimits = DEFAULT_LIMITS) -> bool:
    """Whether ``decode`` builds the message from the C decoder's parts (it checks the
    type and the size of the bytes itself first)."""
    if not isinstance(data, (bytes, bytearray, memoryview)) or len(data) > limits.max_bytes:
        return False
    return codec._fast.decode(data, limits._reader().fast_limits) is not None


def _outcome(fn, *args):
    try:
        return fn(*args), None
    except Exception as e:  # compared below: type, text and field
        return None, e


def _both_decode(data, limits: DecodeLimits = DEFAULT_LIMITS, fast: bool | None = None):
    """decode and decode_python agree (message, or error text and field); ``fast``: whether
    the C decoder must have taken the message (None: either)."""
    got, err = _outcome(decode, data, limits)
    want, want_err = _outcome(decode_python, data, limits)
    if want_err is not None:
        assert err is not None, f"fast path accepted what Python refuses: {want_err}"
        assert type(err) is type(want_err) and str(err) == str(want_err), (str(err), str(want_err))
        assert getattr(err, "field", None) == getattr(want_err, "field", None)
        assert not _fast_takes(data, limits)
        return None
    assert err is None, err
    _same(got, want)
    if fast is not None:
        assert _fast_takes(data, limits) is fast
    return got


def _both_encode(msg) -> bytes | None:
    got, err = _outcome(encode, msg)
    want, want_err = _outcome(encode_python, msg)
    if want_err is not None:
        assert err is not None and type(err) is type(want_err) and str(err) == str(want_err), (err, want_err)
        return None
    assert err is None, err
    assert got == want
    return got


def _tls(k: int, program: bool) -> TrafficLights:
    return TrafficLights([f"J{i}" for i in range(k)], ["rGyY"[: 1 + i % 4] for i in range(k)],
                         np.arange(k, dtype=np.int32), np.linspace(-2, 40, k).astype(np.float32),
                         [str(i % 3) for i in range(k)] if program else None)


def _steps():
    """Synthetic steps over the options the wire has."""
    for n in (0, 1, 1000):
        for pts in (0, 12):
            base = synthetic_step(n, seed=n + pts, step=7, path_points=pts)
            yield base
            yield dataclasses.replace(base, vtypes=None, final=True, epoch=1_700_000_000_123_456_789,
                                      tls=_tls(5, program=True))
            yield dataclasses.replace(base, static_version=3, tls=_tls(3, program=False))
            yield dataclasses.replace(base, vtypes=[VType("a", "passenger"), VType("b\u00e9", "bus")], final=False)
    yield circle_traffic(300, step=4)  # float64 paths, float32 look-ahead points
    yield circle_traffic(17, step=0, run="r\u00fcn")


def _physics(n: int, seed: int) -> PhysicsState:
    rng = np.random.default_rng(seed)
    f4 = lambda lo, hi: rng.uniform(lo, hi, n).astype(np.float32)  # noqa: E731
    agents = PhysicsAgents(
        ids=[f"p{i}" for i in range(n)], cls=rng.integers(0, 6, n).astype(np.uint8),
        mode=rng.integers(0, 4, n).astype(np.uint8), x=rng.uniform(-1e4, 1e4, n), y=rng.uniform(-1e4, 1e4, n),
        z=f4(0, 2), heading=f4(-180, 180), roll=f4(-5, 5), pitch=f4(-5, 5), speed=f4(0, 30), steer=f4(-30, 30),
        drive=f4(0, 900), brake=f4(0, 2000), err_lon=f4(-1, 1), err_lat=f4(-1, 1),
    )
    return PhysicsState("run", seed, seed * 0.02, seed // 5 - 1, agents, {"collisions": n, "placements": 2 ** 40})


# --------------------------------------------------------------------------- equality


@needs_c
@pytest.mark.parametrize("name", [k for k in valid_messages() if k.startswith(("step", "physics"))])
def test_golden_steps_and_physics(name):
    raw = (GOLDEN_DIR / f"{name}.msgpack").read_bytes()
    assert _both_encode(valid_messages()[name]) == raw
    _both_decode(raw, fast=True)


@needs_c
@pytest.mark.parametrize("name", list(invalid_vectors()))
def test_invalid_golden_vectors(name):
    _both_decode(invalid_vectors()[name][0], fast=False)


@needs_c
def test_other_kinds_go_the_python_way():
    for name, msg in valid_messages().items():
        raw = encode(msg)
        assert raw == encode_python(msg)
        _both_decode(raw, fast=name.startswith(("step", "physics")))


@needs_c
def test_synthetic_steps():
    count = 0
    for msg in _steps():
        data = _both_encode(msg)
        m = _both_decode(data, fast=not (msg.vtypes == [] and msg.agents.n))
        if m is not None:
            assert encode(m) == data  # decoded, it encodes to the same bytes again
        count += 1
    assert count > 20


@needs_c
def test_byte_like_inputs():
    data = encode(synthetic_step(50, seed=2, path_points=3))
    for wrapped in (bytearray(data), memoryview(data), memoryview(bytearray(data))):
        _both_decode(wrapped, fast=True)
    _both_decode(memoryview(data)[::2])  # not contiguous: the Python way


@needs_c
@pytest.mark.parametrize("n", [0, 1, 40, 1000])
def test_physics_states(n):
    msg = _physics(n, seed=n + 3)
    data = _both_encode(msg)
    _both_decode(data, fast=True)
    _both_decode(data, DecodeLimits.for_agents(max(n, 1)), fast=True)


@needs_c
def test_decoder_limits():
    data = encode(synthetic_step(1000, seed=1, path_points=12))
    _both_decode(data, DecodeLimits.for_agents(1000), fast=True)
    _both_decode(data, DecodeLimits.for_agents(999), fast=False)  # too many agents
    _both_decode(data, DecodeLimits(max_points=11_999), fast=False)
    _both_decode(data, DecodeLimits(max_points=12_000), fast=True)
    _both_decode(data, DecodeLimits(max_str=5), fast=False)  # "veh100"
    _both_decode(data, DecodeLimits(max_bytes=len(data) - 1), fast=False)
    _both_decode(data, DecodeLimits(max_agents=1000, max_static_rows=1), fast=True)
    _both_decode(encode(synthetic_step(1, seed=1)), DecodeLimits(max_agents=1, max_static_rows=1), fast=False)


# --------------------------------------------------------------------------- encoding fallbacks


@needs_c
def test_encoder_casts_other_dtypes_as_the_python_encoder():
    base = synthetic_step(30, seed=4, path_points=3)
    a = base.agents
    variants = [
        dict(angle=a.angle.astype(np.float64), cls=a.cls.astype(np.int64), lane=a.lane.astype(np.int16)),
        dict(la_x=a.la_x.astype(np.float64) + 0.1, la_y=a.la_y.astype(np.int32), x=a.x.astype(np.float32)),
        dict(path_offsets=a.path_offsets.astype(np.int64), path_xy=a.path_xy.astype(np.float64)),
        dict(path_offsets=list(a.path_offsets), ids=tuple(a.ids), flags=[0] * 30),
        dict(x=a.x[::-1], speed=np.asfortranarray(a.speed)),  # views, not contiguous
        dict(path_offsets=a.path_offsets + 2, path_xy=np.vstack([np.ones((2, 2), np.float32), a.path_xy])),
        dict(signals=a.signals.astype(">u2"), x=a.x.astype(">f8")),
    ]
    for change in variants:
        msg = dataclasses.replace(base, agents=dataclasses.replace(a, **change))
        _both_encode(msg)
    tls = TrafficLights(["a", "b"], ("rG", "Gr"), [1, 2], [0.5, 1], ("x", "y"))
    _both_encode(dataclasses.replace(base, tls=tls))
    _both_encode(dataclasses.replace(base, tls=dataclasses.replace(tls, phase=np.array([1, 2], np.uint64))))
    _both_encode(dataclasses.replace(base, step=np.int64(5), time=np.float32(0.1), epoch=np.uint64(3),
                                     static_version=True, final=np.bool_(True)))
    _both_encode(dataclasses.replace(base, vtypes=(VType("a", "b"),)))


@needs_c
def test_encoder_leaves_odd_inputs_to_the_python_encoder():
    base = synthetic_step(5, seed=5, path_points=2)
    a = base.agents
    odd = [
        dict(ids=["a", "b", "c", "d", 5]),  # not a str
        dict(ids=["a", "b", "c", "d", "\ud800"]),  # a lone surrogate: not UTF-8
        dict(la_x=a.la_x[:3]),  # does not broadcast
        dict(path_offsets=a.path_offsets[::-1].copy()),  # falling offsets
        dict(path_offsets=a.path_offsets * 100),  # beyond the vertices
    ]
    for change in odd:
        _both_encode(dataclasses.replace(base, agents=dataclasses.replace(a, **change)))
    _both_encode(dataclasses.replace(base, run=7))
    _both_encode(dataclasses.replace(base, step=2 ** 64))
    _both_encode(dataclasses.replace(base, step=-(2 ** 63) - 1))
    _both_encode(dataclasses.replace(base, vtypes=[VType(1, "x")]))
    p = _physics(3, 1)
    _both_encode(dataclasses.replace(p, counters={"a": 1, 2: 3}))
    _both_encode(dataclasses.replace(p, counters={"a": np.int64(1)}))
    _both_encode(dataclasses.replace(p, agents=dataclasses.replace(p.agents, z=p.agents.z.astype(np.float64))))


@needs_c
@pytest.mark.parametrize("v", [0, 1, 31, 32, 127, 128, 255, 256, 65535, 65536, 2**32 - 1, 2**32, 2**63 - 1,
                               2**63, 2**64 - 1, -1, -32, -33, -128, -129, -32768, -32769, -2**31, -2**31 - 1,
                               -2**63])
def test_integer_forms(v):
    msg = synthetic_step(2, seed=1)
    _both_encode(dataclasses.replace(msg, step=v, static_version=v, epoch=v))
    k = 3
    phase = np.full(k, max(min(v, 2**63 - 1), -2**63), np.int64)
    _both_encode(dataclasses.replace(msg, tls=TrafficLights(["a", "b", "c"], ["r"] * k, phase, np.zeros(k))))


@needs_c
@pytest.mark.parametrize("length", [0, 1, 31, 32, 255, 256, 65535, 65536])
def test_string_and_bin_forms(length):
    msg = synthetic_step(1, seed=1)
    _both_encode(dataclasses.replace(msg, run="r" * length))
    data = _both_encode(dataclasses.replace(msg, run="\u00e9" * (length // 2)))
    _both_decode(data)
    n = max(length // 8, 0)
    _both_decode(_both_encode(synthetic_step(n, seed=2, path_points=1)), fast=True)


# --------------------------------------------------------------------------- hostile input


def _wire(msg) -> dict:
    return msgpack.unpackb(encode_python(msg), raw=False)


def _pack(d) -> bytes:
    return msgpack.packb(d, use_bin_type=True)


def _edit(d: dict, path: str, value) -> dict:
    d = copy.deepcopy(d)
    *head, last = path.split(".")
    target = d
    for k in head:
        target = target[k]
    if value is _DELETE:
        del target[last]
    else:
        target[last] = value
    return d


_DELETE = object()


def _col(d: dict, name: str, dtype: str, i: int, value) -> dict:
    d = copy.deepcopy(d)
    a = np.frombuffer(d["agents"][name], dtype).copy()
    a[i] = value
    d["agents"][name] = a.tobytes()
    return d


@needs_c
def test_corrupt_and_hostile_steps():
    msg = dataclasses.replace(synthetic_step(40, seed=6, path_points=3), tls=_tls(3, True))
    w = _wire(msg)
    data = _pack(w)
    assert _fast_takes(data)
    off = np.frombuffer(w["agents"]["path"]["off"], "<u4").copy()
    off[5], off[6] = off[6], off[5]
    cases = [
        _col(w, "x", "<f8", 3, np.nan), _col(w, "y", "<f8", 0, np.inf), _col(w, "x", "<f8", 1, 1.1e8),
        _col(w, "speed", "<f4", 39, np.nan), _col(w, "length", "<f4", 2, -0.5), _col(w, "la_dx", "<f4", 3, 2e5),
        _col(w, "la_dy", "<f4", 4, -np.inf), _col(w, "angle", "<f4", 5, 720.5), _col(w, "cls", "<u1", 7, 6),
        _col(w, "lane", "<i4", 8, -2), _col(w, "vtype", "<u2", 9, 1),
        _col(w, "cls", "<u1", 7, 5), _col(w, "lane", "<i4", 8, -1), _col(w, "angle", "<f4", 5, 720.0),
        _edit(w, "agents.id", w["agents"]["id"][:-1] + [w["agents"]["id"][0]]),  # duplicate id
        _edit(w, "agents.id", w["agents"]["id"][:-1] + [b"veh39"]),
        _edit(w, "agents.id", w["agents"]["id"][:-1]),
        _edit(w, "agents.id", w["agents"]["id"][:-1] + ["x" * 1025]),
        _edit(w, "agents.id", w["agents"]["id"][:-1] + ["\u00e9" * 1024]),
        _edit(w, "agents.n", 41), _edit(w, "agents.n", -1), _edit(w, "agents.n", True), _edit(w, "agents.n", 40.0),
        _edit(w, "agents.x", w["agents"]["x"][:-1]), _edit(w, "agents.flags", w["agents"]["flags"] + b"\0"),
        _edit(w, "agents.cls", "x" * 40), _edit(w, "agents.lane", _DELETE), _edit(w, "agents.extra", 1),
        _edit(w, "agents.path.off", off.tobytes()), _edit(w, "agents.path.off", w["agents"]["path"]["off"][:-4]),
        _edit(w, "agents.path.dxy", w["agents"]["path"]["dxy"][:-8]),
        _edit(w, "agents.path.dxy", w["agents"]["path"]["dxy"][:-1]),
        _edit(w, "agents.path.dxy", w["agents"]["path"]["dxy"][:-8] + struct.pack("<ff", np.nan, 0)),
        _edit(w, "agents.path.dxy", w["agents"]["path"]["dxy"][:-8] + struct.pack("<ff", 0, 1e5)),
        _edit(w, "agents.path.dxy", w["agents"]["path"]["dxy"][:-8] + struct.pack("<ff", 0, 1.01e5)),
        _edit(w, "agents.path", _DELETE), _edit(w, "agents.path", {}), _edit(w, "agents.path.xy", b""),
        _edit(w, "vtypes", []), _edit(w, "vtypes", _DELETE), _edit(w, "vtypes", [["a"]]),
        _edit(w, "vtypes", [["a", 1]]), _edit(w, "vtypes", [["a", "b"]] * 65536), _edit(w, "vtypes", None),
        _edit(w, "v", [2, 0]), _edit(w, "v", [1, 99]), _edit(w, "v", [1]), _edit(w, "v", [1, 2**64 - 1]),
        _edit(w, "v", [True, 4]), _edit(w, "kind", "physics"), _edit(w, "kind", "ack"), _edit(w, "kind", b"step"),
        _edit(w, "run", "r" * 1025), _edit(w, "run", 5), _edit(w, "step", -1), _edit(w, "step", 2**63),
        _edit(w, "step", 1.0), _edit(w, "step", False), _edit(w, "t", np.nan), _edit(w, "t", 3),
        _edit(w, "t", 2**60 + 1), _edit(w, "t", -math.inf), _edit(w, "dt", 0), _edit(w, "dt", 3600),
        _edit(w, "dt", 3601), _edit(w, "dt", 1e-6), _edit(w, "dt", 9e-7), _edit(w, "sv", -1),
        _edit(w, "sv", _DELETE), _edit(w, "epoch", -5), _edit(w, "epoch", 2**63 - 1), _edit(w, "final", 1),
        _edit(w, "final", True), _edit(w, "final", None), _edit(w, "extra", 1), _edit(w, "tick", 1),
        _edit(w, "tls.id", ["J0", "J0", "J2"]), _edit(w, "tls.id", _DELETE), _edit(w, "tls.state", ["r"]),
        _edit(w, "tls.phase", [0, 1.0, 2]), _edit(w, "tls.phase", [0, -1, 2]), _edit(w, "tls.phase", [0, 2**31, 2]),
        _edit(w, "tls.phase", [0, 2**31 - 1, True]), _edit(w, "tls.next", [0, np.nan, 1]),
        _edit(w, "tls.next", [0, 1e9, -1e9]), _edit(w, "tls.next", [0, 10**9 + 1, 1]),
        _edit(w, "tls.next", [1.5, 2, np.float32(3.3).item()]), _edit(w, "tls.program", _DELETE),
        _edit(w, "tls.program", ["a"]), _edit(w, "tls.program", None), _edit(w, "tls.extra", []),
        _edit(w, "tls", []), _edit(w, "agents", None),
    ]
    taken = 0
    for d in cases:
        raw = _pack(d)
        _both_decode(raw)
        taken += _fast_takes(raw)
    assert 10 <= taken < len(cases) // 3, taken  # the valid edits went the fast way
    # msgpack-level damage
    for cut in sorted({0, 1, 2, 5, 17, 100, len(data) // 2, len(data) - 9, len(data) - 1}):
        _both_decode(data[:cut], fast=False)
    for junk in (b"\x00", b"\xc0", data):
        _both_decode(data + junk, fast=False)
    dup = _pack(w)[1:]  # the same map with "run" twice (msgpack keeps the last)
    head = bytes([0x80 | (len(w) + 1)]) + _pack("run") + _pack("other")
    _both_decode(head + dup)
    for bad in ([0, 100, 5], [0, 2**32 - 1, 3], [0, 3, 1], [1, 2, 3], [0, 0, 4]):  # rising late, or beyond the points
        d = copy.deepcopy(w)
        d["agents"]["n"] = 2
        for k, dt in codec.STEP_AGENT_COLUMNS:
            d["agents"][k] = d["agents"][k][:2 * np.dtype(dt).itemsize]
        d["agents"]["id"] = d["agents"]["id"][:2]
        d["agents"]["path"] = {"off": np.array(bad, "<u4").tobytes(), "dxy": np.ones(10, "<f4").tobytes()}
        d["agents"] = d.pop("agents")  # the points last in the message: nothing after them to read
        _both_decode(_pack(d), fast=False)
    bad_utf8 = data.replace(b"\xa5veh39", b"\xa5veh\xff9")
    assert bad_utf8 != data
    _both_decode(bad_utf8, fast=False)
    _both_decode(data.replace(b"\xa4kind", b"\xc4\x04kind"), fast=False)  # a bin key


def _with_path_values(w: dict, values: list[float]) -> bytes:
    """``w`` with its last path vertices' float32 offsets replaced by ``values`` (x, y, ...)."""
    d = copy.deepcopy(w)
    dxy = np.frombuffer(d["agents"]["path"]["dxy"], "<f4").copy()
    dxy[len(dxy) - len(values):] = values
    d["agents"]["path"]["dxy"] = dxy.tobytes()
    return _pack(d)


@needs_c
def test_path_offsets_at_and_beyond_their_bound():
    """The C decoder tests path offsets on their float32 bits: each side of the bound, both
    signs, zeros, infinities and NaNs of either sign, as the Python decoder decides."""
    w = _wire(dataclasses.replace(synthetic_step(40, seed=6, path_points=3), tls=_tls(3, True)))
    lim = codec.OFFSET_LIMIT
    above = float(np.nextafter(np.float32(lim), np.float32(np.inf)))
    below = float(np.nextafter(np.float32(lim), np.float32(0)))
    neg_nan = struct.unpack("<f", struct.pack("<I", 0xFFC00000))[0]
    for values, ok in [([lim, -lim], True), ([-lim, below], True), ([0.0, -0.0], True),
                       ([above, 0.0], False), ([0.0, -above], False), ([np.inf, 0.0], False),
                       ([0.0, -np.inf], False), ([np.nan, 0.0], False), ([0.0, neg_nan], False),
                       ([3.4e38, 0.0], False)]:
        data = _with_path_values(w, values)
        got = _both_decode(data, fast=ok)
        assert (got is not None) is ok, values


@needs_c
def test_path_bound_between_two_floats():
    """A bound that no float32 equals: the largest float32 below it passes, the next fails
    (the C decoder rounds the bound down once, at configure)."""
    fast = codec._fast
    w = _wire(dataclasses.replace(synthetic_step(40, seed=6, path_points=3), tls=_tls(3, True)))
    limits = DEFAULT_LIMITS._reader().fast_limits
    lim = codec.OFFSET_LIMIT
    up = float(np.nextafter(np.float32(lim), np.float32(np.inf)))  # lim + 1/128
    try:
        # floats near 1e5 are 1/128 apart: lim + 0.001 rounds to lim, lim + 0.006 rounds up to `up`
        for bound in (lim + 0.001, lim + 0.006):
            bounds = dict(codec.FLOAT_BOUNDS, la_dx=(-bound, bound), la_dy=(-bound, bound))
            assert fast.configure(*codec.SCHEMA_VERSION, bounds, codec.INT_BOUNDS)
            assert fast.decode(_with_path_values(w, [lim, -lim]), limits) is not None, bound
            assert fast.decode(_with_path_values(w, [up, 0.0]), limits) is None, bound
            assert fast.decode(_with_path_values(w, [0.0, -up]), limits) is None, bound
    finally:
        assert fast.configure(*codec.SCHEMA_VERSION, codec.FLOAT_BOUNDS, codec.INT_BOUNDS)


@needs_c
def test_decoded_steps_own_their_arrays():
    """Each decoded step has arrays of its own: writing into one message's arrays changes
    neither another message decoded from the same bytes nor the other arrays of its own."""
    data = encode(synthetic_step(50, seed=3, step=1, path_points=4))
    a, b = decode(data), decode(data)
    assert _fast_takes(data)
    _same(a, b)
    before = copy.deepcopy(b)
    for f in dataclasses.fields(AgentBatch):
        v = getattr(a.agents, f.name)
        if isinstance(v, np.ndarray) and v.size:
            v[...] = 0
    a.tls.phase[...] = 0
    _same(b, before)
    for name in ("x", "y", "la_x", "la_y", "path_xy"):
        assert not np.shares_memory(getattr(b.agents, name), a.agents.x)
    assert not np.shares_memory(b.agents.x, b.agents.y) and not np.shares_memory(b.agents.path_xy, b.agents.la_y)


@needs_c
def test_fast_steps_are_whole_dataclasses():
    """The fast path builds the frozen dataclasses without their __init__: every field is
    set (a field added later must be added there too), and they stay frozen and comparable."""
    msg = synthetic_step(20, seed=2, step=3, path_points=2)
    got = decode(encode(msg))
    for obj in (got, got.agents, got.tls):
        assert set(vars(obj)) == {f.name for f in dataclasses.fields(obj)}, type(obj).__name__
        with pytest.raises(dataclasses.FrozenInstanceError):
            obj.foo = 1
    assert dataclasses.replace(got, step=4).step == 4
    _same(got, decode_python(encode(msg)))


@needs_c
def test_corrupt_and_hostile_physics():
    w = _wire(_physics(20, 4))
    cases = [
        _col(w, "mode", "<u1", 1, 4), _col(w, "z", "<f4", 3, 1e6), _col(w, "drive", "<f4", 3, np.nan),
        _col(w, "x", "<f8", 0, -np.inf), _edit(w, "counters.a", 1.5), _edit(w, "counters.b", True),
        _edit(w, "counters", {"x" * 2000: 1}), _edit(w, "counters", {"n": 2**64 - 1}), _edit(w, "counters", []),
        _edit(w, "sumo_step", -2), _edit(w, "sumo_step", -1), _edit(w, "tick", -1), _edit(w, "step", 1),
        _edit(w, "agents.id", ["p0"] * 20), _edit(w, "agents.n", 19), _edit(w, "counters", _DELETE),
    ]
    for d in cases:
        _both_decode(_pack(d))
    _both_decode(_pack(_edit(w, "counters", {b"raw": 1})))


VALUES = [None, True, False, 0, -1, 1, 5, 6, 2**31, 2**63 - 1, 2**64 - 1, 1.5, 1e-6, float("nan"), float("inf"),
          -1e9, 1e10, "", "x" * 1025, "a", "step", b"", b"\x00" * 8, b"\xff" * 8, b"\x00" * 16, [], ["a", "a"],
          ["a", "b"], {}, [1, 2], [["a", "b"]], [1, 4], [2, 0]]


def _mutated(docs: list[dict], rng: random.Random) -> bytes:
    d = copy.deepcopy(rng.choice(docs))
    for _ in range(rng.choice((1, 1, 2, 3))):
        p = rng.choice(list(paths_in(d))[1:])
        target = d
        for k in p[:-1]:
            target = target[k]
        r = rng.random()
        v = target[p[-1]]
        if r < 0.1 and isinstance(target, dict):
            del target[p[-1]]
        elif r < 0.45 and isinstance(v, bytes) and v:
            b = bytearray(v)
            for _ in range(rng.choice((1, 2, 8))):
                b[rng.randrange(len(b))] = rng.randrange(256)
            target[p[-1]] = bytes(b)
        elif r < 0.55 and isinstance(v, bytes):
            cut = rng.randrange(len(v) + 1)
            target[p[-1]] = v[:cut] if rng.random() < 0.5 else v + v[:cut]
        else:
            target[p[-1]] = copy.deepcopy(rng.choice(VALUES))
    return _pack(d)


@needs_c
@pytest.mark.parametrize("seed", range(3))
def test_mutations_agree(seed):
    rng = random.Random(seed)
    msgs = [synthetic_step(6, seed=1, path_points=2), dataclasses.replace(synthetic_step(3, seed=2), tls=_tls(2, True)),
            dataclasses.replace(synthetic_step(0, seed=3, path_points=1), vtypes=None, final=True, epoch=9),
            _physics(4, 2), valid_messages()["step"]]
    docs = [_wire(m) for m in msgs]
    limits = [DEFAULT_LIMITS, DecodeLimits.for_agents(5), DecodeLimits(max_agents=4, max_static_rows=3, max_points=6,
                                                                       max_str=4, max_bytes=4096)]
    for _ in range(600):
        raw = _mutated(docs, rng)
        _both_decode(raw, rng.choice(limits))
        if rng.random() < 0.2:  # and the bytes themselves, damaged
            b = bytearray(raw)
            b[rng.randrange(len(b))] = rng.randrange(256)
            _both_decode(bytes(b), rng.choice(limits))


# --------------------------------------------------------------------------- generated messages

_F32 = dict(width=32, allow_subnormal=True)


@st.composite
def _steps_drawn(draw):
    n = draw(st.integers(0, 12))
    wild = draw(st.booleans())  # values anywhere (then many messages are refused, both ways alike)
    f64 = st.floats(-1e8, 1e8) if not wild else st.floats(allow_nan=True, allow_infinity=True)
    f32 = (lambda lo, hi: st.floats(lo, hi, **_F32)) if not wild else (lambda lo, hi: st.floats(width=32))
    ids = draw(st.lists(st.text(max_size=6), min_size=n, max_size=n, unique=not wild))
    x = draw(hnp.arrays(np.float64, n, elements=f64))
    y = draw(hnp.arrays(np.float64, n, elements=f64))
    dla = draw(hnp.arrays(np.float64, (2, n), elements=st.floats(-2e5, 2e5) if wild else st.floats(-50, 50)))
    counts = draw(st.lists(st.integers(0, 3), min_size=n, max_size=n)) if draw(st.booleans()) else None
    if counts is not None:
        off = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]).astype(np.uint32)
        m = int(off[-1])
        anchor = np.repeat(np.column_stack((x, y)), counts, axis=0) if n else np.zeros((0, 2))
        pxy = (anchor + draw(hnp.arrays(np.float64, (m, 2), elements=st.floats(-1e3, 1e3)))).astype(
            draw(st.sampled_from([np.float32, np.float64])))
    else:
        off, pxy = np.zeros(0, np.uint32), np.zeros((0, 2), np.float64)
    nv = draw(st.integers(0, 3))
    vtypes = draw(st.sampled_from([None, [VType(f"t{i}", "passenger") for i in range(nv)]]))
    vt_hi = max(nv - 1, 0) if not wild else 65535
    with np.errstate(invalid="ignore", over="ignore"):
        la_x, la_y = (x + dla[0]).astype(np.float32), (y + dla[1]).astype(np.float32)
    agents = AgentBatch(
        ids=ids, cls=draw(hnp.arrays(np.uint8, n, elements=st.integers(0, 255 if wild else 5))),
        vtype=draw(hnp.arrays(np.uint16, n, elements=st.integers(0, vt_hi))), x=x, y=y,
        angle=draw(hnp.arrays(np.float32, n, elements=f32(-720, 720))),
        speed=draw(hnp.arrays(np.float32, n, elements=f32(-1000, 1000))),
        accel=draw(hnp.arrays(np.float32, n, elements=f32(-1e5, 1e5))),
        signals=draw(hnp.arrays(np.uint16, n)), la_x=la_x, la_y=la_y,
        length=draw(hnp.arrays(np.float32, n, elements=f32(0, 1000))),
        width=draw(hnp.arrays(np.float32, n, elements=f32(0, 1000))),
        lane=draw(hnp.arrays(np.int32, n, elements=st.integers(-3 if wild else -1, 2**31 - 1))),
        flags=draw(hnp.arrays(np.uint8, n)), path_offsets=off, path_xy=pxy,
    )
    k = draw(st.integers(0, 4))
    tls = TrafficLights(
        draw(st.lists(st.text(max_size=4), min_size=k, max_size=k, unique=True)),
        draw(st.lists(st.text(alphabet="rRyYgGuos", max_size=8), min_size=k, max_size=k)),
        draw(hnp.arrays(np.int32, k, elements=st.integers(0 if not wild else -5, 2**31 - 1))),
        draw(hnp.arrays(np.float32, k, elements=st.floats(-1e9, 1e9, **_F32) if not wild else st.floats(width=32))),
        draw(st.none() | st.lists(st.text(max_size=3), min_size=k, max_size=k)),
    )
    return StepMessage(
        run=draw(st.text(max_size=10)), step=draw(st.integers(0, 2**63 - 1)),
        time=draw(st.floats(allow_nan=wild, allow_infinity=wild)),
        step_length=draw(st.floats(1e-6, 3600) if not wild else st.floats()),
        agents=agents, tls=tls, vtypes=vtypes, static_version=draw(st.integers(0, 2**63 - 1)),
        final=draw(st.booleans()), epoch=draw(st.integers(0, 2**63 - 1)),
    )


@needs_c
@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # numpy on the wild values inside the Python encoder
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(_steps_drawn())
def test_generated_steps(msg):
    data = _both_encode(msg)
    assume(data is not None)
    m = _both_decode(data)
    if m is not None:
        assert encode(m) == encode_python(m)


@needs_c
@settings(max_examples=100, deadline=None)
@given(st.integers(0, 8), st.integers(0, 2**32), st.integers(-1, 2**40),
       st.dictionaries(st.text(max_size=5), st.integers(-2**63, 2**64 - 1), max_size=4))
def test_generated_physics(n, seed, sumo_step, counters):
    msg = dataclasses.replace(_physics(n, seed % 1000), sumo_step=sumo_step, counters=counters, tick=seed)
    _both_decode(_both_encode(msg), fast=True)


def test_acks_and_others_are_untouched():
    """Messages outside the fast path: encode is the Python encoder's, with or without C."""
    for msg in (StepAck("r", 1, 2, True), StepAck("r", 0, 0)):
        assert encode(msg) == encode_python(msg)
        _same(decode(encode(msg)), msg)


@needs_c
def test_id_cache_stays_bounded_and_correct():
    """Ids are shared between decodes through a bounded cache: correct across refills,
    duplicates caught whether cached or not."""
    codec._fast.clear_cache()
    for step in range(40):  # 1,000 ids a step, 500 of them new each step: the cache refills
        ids = [f"v{step * 500 + i}" for i in range(1000)]
        msg = synthetic_step(1000, seed=step, step=step)
        msg = dataclasses.replace(msg, agents=dataclasses.replace(msg.agents, ids=ids))
        m = _both_decode(encode(msg), fast=True)
        assert m.agents.ids == ids
        used, slots = codec._fast.cache_size()
        assert used <= slots // 2 + 1000 and slots <= 1 << 18
    base = synthetic_step(3, seed=1)
    for ids in (["a", "b", "a"], ["\u00e9", "b", "\u00e9"], ["x" * 40, "y", "x" * 40], ["a", "\u00e9", "a"]):
        _both_decode(encode(dataclasses.replace(base, agents=dataclasses.replace(base.agents, ids=ids))), fast=False)
    for ids in (["a", "b", "c"], ["\u00e9", "b", "c"], ["x" * 40, "y", "z"]):
        _both_decode(encode(dataclasses.replace(base, agents=dataclasses.replace(base.agents, ids=ids))), fast=True)
    big = synthetic_step(70_000, seed=1)  # more ids than the cache takes: decoded without it
    _both_decode(encode(big), fast=True)
    dup = dataclasses.replace(big, agents=dataclasses.replace(big.agents, ids=big.agents.ids[:-1] + ["veh7"]))
    _both_decode(encode(dup), fast=False)
    assert codec._fast.cache_size()[1] <= 1 << 18
    codec._fast.clear_cache()
    assert codec._fast.cache_size() == (0, 0)


@needs_c
@pytest.mark.parametrize("seed", range(3))
def test_ids_evolving_from_step_to_step(seed):
    """The decoder reuses the previous step's ids in order: arrivals, departures, reorders,
    repeated and non-ASCII ids, all as the Python decoder sees them."""
    rng = random.Random(seed)
    codec._fast.clear_cache()
    ids = [f"veh{i}" for i in range(300)]
    fresh = iter(range(300, 10**6))
    for step in range(120):
        ids = [i for i in ids if rng.random() > 0.02]  # departures
        for _ in range(rng.randrange(8)):  # arrivals, anywhere
            ids.insert(rng.randrange(len(ids) + 1), rng.choice([f"veh{next(fresh)}", f"v\u00e9h{next(fresh)}",
                                                                 "x" * 40 + str(next(fresh))]))
        if rng.random() < 0.2 and len(ids) > 2:  # a reorder
            a, b = rng.randrange(len(ids)), rng.randrange(len(ids))
            ids[a], ids[b] = ids[b], ids[a]
        sent = list(ids)
        if rng.random() < 0.25 and len(ids) > 2:  # a hostile repeat (refused, the Python way)
            sent[rng.randrange(len(sent))] = sent[rng.randrange(len(sent))]
        kind = rng.random()
        if kind < 0.7:
            msg = synthetic_step(len(sent), seed=step, step=step)
            msg = dataclasses.replace(msg, agents=dataclasses.replace(msg.agents, ids=sent))
        else:
            p = _physics(len(sent), step)
            msg = dataclasses.replace(p, agents=dataclasses.replace(p.agents, ids=sent))
        got = _both_decode(encode(msg), fast=len(set(sent)) == len(sent))
        if len(set(sent)) == len(sent):
            assert got is not None and got.agents.ids == sent
        else:
            assert got is None
    codec._fast.clear_cache()


@needs_c
def test_repeats_among_ids_of_the_previous_step():
    """Ids taken from the previous step's list in order skip the pointer set (they are
    unique by construction); a repeat among them still goes to the cache and is refused."""
    codec._fast.clear_cache()
    ids = [f"veh{i}" for i in range(50)]
    base = synthetic_step(50, seed=1, step=1)
    step = lambda sent: dataclasses.replace(base, agents=dataclasses.replace(base.agents, ids=sent))  # noqa: E731
    for _ in range(2):  # the second time every id comes from the previous list
        got = _both_decode(encode(step(ids)), fast=True)
        assert got.agents.ids == ids
    for i, d in [(10, 1), (10, 2), (0, 49), (48, 1), (20, 4), (20, 5)]:
        sent = list(ids)
        sent[i + d] = sent[i]
        assert _both_decode(encode(step(sent)), fast=False) is None
        assert _both_decode(encode(step(ids)), fast=True).agents.ids == ids  # and back
    codec._fast.clear_cache()
