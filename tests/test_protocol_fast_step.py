"""The bulk step decoder accepts exactly what the full decoder accepts and returns an equal
message; whatever it declines, the full decoder decodes or rejects with the field named."""

from __future__ import annotations

import copy
import dataclasses
import random

import msgpack
import numpy as np
import pytest

import protocol.codec as codec
from protocol.errors import ProtocolError
from protocol.messages import TrafficLights
from synthetic.traffic import synthetic_step


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
        out.append(msgpack.unpackb(codec.encode(m), raw=False))
    return out


VALUES = [None, True, 0, -1, 1, 2**31, 2**63 - 1, 1.5, float("nan"), float("inf"), -1e9, 1e10, "",
          "x" * 1025, "a", b"", b"\x00" * 8, b"\xff" * 8, [], ["a", "a"], ["a", "b"], {}, [1, 2], [["a", "b"]]]


def _paths(d, pre=()):
    yield pre
    if isinstance(d, dict):
        for k, v in d.items():
            yield from _paths(v, pre + (k,))
    elif isinstance(d, list):
        for i, v in enumerate(d):
            yield from _paths(v, pre + (i,))


def _both(d: dict):
    try:
        fast = codec._fast_step(d, codec.DEFAULT_LIMITS) if d.get("kind") == "step" else None
    except Exception:
        fast = None
    try:
        full = codec._decode_map(d, codec._Reader(codec.DEFAULT_LIMITS))
    except ProtocolError:
        full = None
    return fast, full


def test_valid_steps_take_the_bulk_path_and_decode_equal():
    for d in _docs():
        fast, full = _both(d)
        assert fast is not None and full is not None
        _equal(fast, full)


@pytest.mark.parametrize("seed", range(4))
def test_mutated_steps_never_pass_the_bulk_path_alone(seed):
    rng = random.Random(seed)
    docs = _docs()
    for _ in range(500):
        d = copy.deepcopy(rng.choice(docs))
        for _ in range(rng.choice((1, 1, 2))):
            p = rng.choice(list(_paths(d))[1:])
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
        fast, full = _both(d)
        if fast is not None:
            assert full is not None, d
            _equal(fast, full)
