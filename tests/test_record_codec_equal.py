"""The vectorised compact codec writes exactly the bytes of the format-1 reference
(tests/compact_reference.py) and decodes every record to the same message, on a real recorded
sequence and on agents that come, go, reorder, repeat and jump."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest

from protocol.codec import decode
from sumoco.recording import codec
from sumoco.recording.record import RecordConfig, Recording
from synthetic.traffic import FakeRun
from tests import compact_reference as reference
from tests.recording_fixture import make_recording
from tests.test_record_codec import _check, _subset


def _same(a, b) -> bool:
    """Equal values and types, arrays with equal dtype and shape."""
    if dataclasses.is_dataclass(a):
        return type(a) is type(b) and all(_same(getattr(a, f.name), getattr(b, f.name))
                                          for f in dataclasses.fields(a))
    if isinstance(a, np.ndarray):
        return (isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape
                and np.array_equal(a, b, equal_nan=True))
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return type(a) is type(b) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return type(a) is type(b) and a == b


def _check_equal(msgs: list[tuple[str, object]], keyframe_every: int) -> int:
    """Encode ``msgs`` with both codecs, compare the bytes, decode with both, compare the
    messages; returns how many records were compared."""
    old, new = reference.CompactEncoder(keyframe_every), codec.CompactEncoder(keyframe_every)
    recs = []
    for i, (topic, msg) in enumerate(msgs):
        want, got = old.encode(topic, msg), new.encode(topic, msg)
        assert got == want, f"record {i} on {topic} differs"
        recs.append((topic, *got))
    old_dec, new_dec = reference.CompactDecoder(), codec.CompactDecoder()
    for i, rec in enumerate(recs):
        want, got = old_dec.decode(*rec), new_dec.decode(*rec)
        assert _same(got, want), f"record {i} decodes differently"
        if len(set(got.agents.ids)) == len(got.agents.ids):  # (the protocol has no repeated names)
            _check(msgs[i][1], got, codec.STEP_FIELDS if rec[1] == codec.STEP_SCHEMA else codec.PHYSICS_FIELDS)
    assert new.agents_per_key() == old.agents_per_key()
    return len(recs)


def test_a_real_recording_encodes_to_the_reference_bytes(tmp_path):
    path = tmp_path / "raw.mcap"
    make_recording(path, steps=25, agents=40, config=RecordConfig(physics_hz=0.0, encoding="raw"))
    msgs = [(m.topic, decode(m.data)) for m in Recording(path)._records() if m.schema in ("step", "physics")]
    kinds = {type(m).__name__ for _, m in msgs}
    assert kinds == {"StepMessage", "PhysicsState"} and len(msgs) > 60
    for every in (codec.KEYFRAME_EVERY, 7):
        assert _check_equal(msgs, every) == len(msgs)


def _churn(seed: int, n: int, k: int) -> list[tuple[str, object]]:
    """Steps and physics states whose agents come, go, reorder, repeat a name, vanish all at
    once and jump far (residuals of every int width)."""
    fake = FakeRun(grid=2, n=n, run="e")
    rng = np.random.default_rng(seed)
    keep = np.arange(n)
    out = []
    for i in range(k):
        r = i % 9
        if r == 2:
            keep = np.sort(rng.choice(n, size=rng.integers(1, n), replace=False))  # some leave, some return
        elif r == 4:
            keep = keep[rng.permutation(len(keep))]  # the same agents in another order
        elif r == 5:
            keep = np.concatenate([keep, keep[:2]])  # a name twice: it maps to its first occurrence
        elif r == 6:
            keep = keep[:0] if i % 2 else np.unique(keep)  # nobody, or unique again
        elif r == 7:
            keep = np.arange(n)
        step, phys = _subset(fake.step(i), keep), _subset(fake.physics(i, i * 0.1, i), keep)
        if r == 3 and len(keep):  # teleports: residuals that need i2, i4 and i8
            step.agents.x[0] += 30.0
            phys.agents.y[-1] -= 3e3
            phys.agents.x[0] = 5e7  # 1e10 units: i8
            step.agents.lane[-1] = 2**31 - 1
        out += [("s", step), ("p", phys)]
        if r == 5:  # the repeated name again, in the same list
            out += [("s", step), ("p", phys)]
        if r == 8:  # the same agents twice in a row: the common case
            out += [("s", _subset(fake.step(i), keep)), ("p", _subset(fake.physics(i, i * 0.1 + 0.05, i), keep))]
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_agents_that_come_go_reorder_and_jump_encode_to_the_reference_bytes(seed):
    msgs = _churn(seed, 60, 40)
    widths = set()
    for every in (codec.KEYFRAME_EVERY, 5, 1):
        _check_equal(msgs, every)
    enc = codec.CompactEncoder(5)
    for topic, msg in msgs:
        rec = msgpack.unpackb(enc.encode(topic, msg)[1])
        widths |= {dt for dt, _b in rec["cols"].values()}
    assert widths == {"i1", "i2", "i4", "i8"}  # every residual width was exercised


def test_residual_columns_take_the_smallest_int_type_at_every_boundary():
    edges = [0, 127, 128, -128, -129, 2**15 - 1, 2**15, -2**15, -2**15 - 1, 2**31 - 1, 2**31, -2**31,
             -2**31 - 1, 2**62, -2**63, 2**63 - 1]
    rows = [[a, b] for a in edges for b in edges]
    lay = codec._Layout(codec.PHYSICS_FIELDS)
    f = len(codec.PHYSICS_FIELDS)
    for start in range(0, len(rows), f):
        chunk = rows[start:start + f]
        chunk += [[0, 0]] * (f - len(chunk))
        res = np.array(chunk, np.int64)
        cols = lay.pack(res)
        assert list(cols.values()) == [reference._pack_int(r) for r in res]
        assert np.array_equal(lay.unpack(cols, 2), res)
    assert lay.pack(np.zeros((f, 0), np.int64)) == {name: ("i1", b"") for name, *_ in codec.PHYSICS_FIELDS}


def test_the_same_agents_again_skip_the_name_lookup(monkeypatch):
    calls = []
    lookup = codec._prev_index

    def counted(ids, prev):
        calls.append(len(ids))
        return lookup(ids, prev)

    monkeypatch.setattr(codec, "_prev_index", counted)
    fake = FakeRun(grid=1, n=30, run="e")
    enc = codec.CompactEncoder(keyframe_every=50)
    for k in range(120):
        enc.encode("p", fake.physics(k, k * 0.02, k))
    assert calls == [30] * 3  # the keyframes only (records 0, 50, 100)
    dup = _subset(fake.physics(0, 0.0, 0), np.array([0, 1, 1, 2]))
    enc.encode("d", dup)
    enc.encode("d", dup)  # a repeated name: the lookup each time (it maps to the first one)
    assert calls[3:] == [4, 4]


def test_a_record_with_a_column_of_the_wrong_length_is_an_error():
    fake = FakeRun(grid=1, n=10, run="e")
    enc = codec.CompactEncoder()
    _schema, data = enc.encode("p", fake.physics(0, 0.0, 0))
    rec = msgpack.unpackb(data)
    rec["cols"]["x"] = ["i1", rec["cols"]["x"][1][:-1]]
    with pytest.raises(codec.CompactError, match="column x"):
        codec.CompactDecoder().decode("p", codec.PHYSICS_SCHEMA, msgpack.packb(rec, use_bin_type=True))
    good = fake.physics(1, 0.1, 1)
    bad = dataclasses.replace(good, agents=dataclasses.replace(good.agents, cls=good.agents.cls[:-1]))
    with pytest.raises(ValueError, match="unequal length"):
        enc.encode("p", bad)
