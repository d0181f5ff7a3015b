"""The step decoder's checks, through ``decode`` alone: whatever it accepts holds every
bound SPEC.md 3.1 and 5 set and decodes again to an equal message; whatever it refuses
raises ``ProtocolError`` naming a field of the message and what was expected there."""

from __future__ import annotations

import copy
import dataclasses
import math
import random
import re

import msgpack
import numpy as np
import pytest

from protocol import AgentClass, ProtocolError, StepMessage, decode, encode
from protocol.codec import DEFAULT_LIMITS, FLOAT_BOUNDS, STEP_AGENT_COLUMNS
from protocol.messages import TrafficLights
from synthetic.traffic import synthetic_step
from tests.harness import paths_in


def _equal(a, b) -> None:
    if dataclasses.is_dataclass(a):
        assert type(a) is type(b)
        for f in dataclasses.fields(a):
            _equal(getattr(a, f.name), getattr(b, f.name))
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)
    elif isinstance(a, list):
        assert type(b) is list and len(a) == len(b)
        for x, y in zip(a, b):
            _equal(x, y)
    else:
        assert type(a) is type(b) and a == b


def _docs() -> list[dict]:
    out = []
    for n, pts, k, with_vtypes in ((0, 0, 0, True), (3, 4, 2, False), (20, 0, 5, True), (20, 4, 0, False)):
        m = synthetic_step(n, seed=n, step=3, path_points=pts)
        tls = TrafficLights([f"j{i}" for i in range(k)], ["rG"] * k, np.arange(k, dtype=np.int32),
                            np.linspace(0, 5, k).astype(np.float32), ["0"] * k if k % 2 else None)
        m = dataclasses.replace(m, tls=tls, vtypes=m.vtypes if with_vtypes else None)
        out.append(msgpack.unpackb(encode(m), raw=False))
    old = copy.deepcopy(out[1])  # a protocol 1.1 step: absolute float32 look-ahead points and path
    a = old["agents"]
    x, y = np.frombuffer(a["x"], "<f8"), np.frombuffer(a["y"], "<f8")
    a["la_x"] = (x + np.frombuffer(a.pop("la_dx"), "<f4")).astype("<f4").tobytes()
    a["la_y"] = (y + np.frombuffer(a.pop("la_dy"), "<f4")).astype("<f4").tobytes()
    a["path"]["xy"] = np.zeros(len(a["path"].pop("dxy")) // 4, "<f4").tobytes()
    return out + [old]


VALUES = [None, True, 0, -1, 1, 2**31, 2**63 - 1, 1.5, float("nan"), float("inf"), -1e9, 1e10, "",
          "x" * 1025, "a", b"", b"\x00" * 8, b"\xff" * 8, [], ["a", "a"], ["a", "b"], {}, [1, 2], [["a", "b"]]]


def _mutate(d: dict, rng: random.Random) -> None:
    for _ in range(rng.choice((1, 1, 2))):
        p = rng.choice(list(paths_in(d))[1:])
        target = d
        for k in p[:-1]:
            target = target[k]
        r = rng.random()
        if r < 0.1 and isinstance(target, dict):
            del target[p[-1]]
        elif r < 0.4 and isinstance(target[p[-1]], bytes) and target[p[-1]]:
            b = bytearray(target[p[-1]])
            b[rng.randrange(len(b))] = rng.randrange(256)
            target[p[-1]] = bytes(b)
        else:
            target[p[-1]] = copy.deepcopy(rng.choice(VALUES))


def _holds_the_spec(m: StepMessage) -> None:
    """The bounds of SPEC.md 3.1 and 5, written out here apart from the decoder."""
    a, n, lim = m.agents, m.agents.n, DEFAULT_LIMITS
    assert 0 <= m.step < 2**63 and 0 <= m.static_version < 2**63 and math.isfinite(m.time)
    assert 1e-6 <= m.step_length <= 3600.0 and isinstance(m.final, bool) and len(m.run) <= lim.max_str
    assert n <= lim.max_agents and len(set(a.ids)) == n and all(len(i) <= lim.max_str for i in a.ids)
    for name, _ in STEP_AGENT_COLUMNS:
        col = getattr(a, {"la_dx": "la_x", "la_dy": "la_y"}.get(name, name))
        assert len(col) == n
        if name in ("x", "y", "angle", "speed", "accel", "length", "width"):
            lo, hi = FLOAT_BOUNDS[name]
            assert np.all((col >= lo) & (col <= hi)), name
    assert np.all(a.cls < len(AgentClass)) and np.all(a.lane >= -1)
    if m.vtypes is not None and n:
        assert np.all(a.vtype < len(m.vtypes))
    assert np.all(np.isfinite(a.la_x)) and np.all(np.isfinite(a.la_y)) and np.all(np.isfinite(a.path_xy))
    if len(a.path_offsets):
        assert a.path_offsets[0] == 0 and a.path_offsets[-1] == len(a.path_xy)
        assert np.all(np.diff(a.path_offsets.astype(np.int64)) >= 0)
    k = len(m.tls.ids)
    assert len(set(m.tls.ids)) == k == len(m.tls.state) == len(m.tls.phase) == len(m.tls.next_switch)
    assert np.all((m.tls.phase >= 0)) and np.all(np.abs(m.tls.next_switch) <= 1e9)


def test_valid_steps_decode_to_what_was_sent_and_again_to_the_same():
    for d in _docs():
        m = decode(msgpack.packb(d, use_bin_type=True))
        _holds_the_spec(m)
        if "la_dx" in d["agents"]:  # (a 1.1 step comes back as 1.2: float32 offsets, not points)
            _equal(decode(encode(m)), m)


@pytest.mark.parametrize("seed", range(4))
def test_mutated_steps_are_decoded_within_the_spec_or_refused_with_the_field_named(seed):
    rng = random.Random(seed)
    docs = _docs()
    refused = 0
    for _ in range(500):
        original = rng.choice(docs)
        d = copy.deepcopy(original)
        _mutate(d, rng)
        try:
            m = decode(msgpack.packb(d, use_bin_type=True))
        except ProtocolError as e:
            refused += 1
            root = re.split(r"[.\[]", e.field or "")[0]
            assert root in original, (e.field, str(e))  # a field of the message, named
            s = str(e)  # the expectation and the value, or why none applies
            assert ("expected" in s and "got" in s) or "missing field" in s or "appears twice" in s \
                or "major versions must match" in s, s
            continue
        assert isinstance(m, StepMessage)
        _holds_the_spec(m)
        _equal(decode(encode(m)), decode(encode(decode(encode(m)))))  # a fixed point once re-encoded
    assert refused > 250  # most mutations break a bound
