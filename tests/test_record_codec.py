"""The compact recording encoding (protocol/SPEC.md 11): decoded messages equal the recorded
ones within the stated units, whatever agents come, go or change order."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from protocol.codec import decode, encode
from protocol.keys import Keys
from sumoco.recording.record import McapRecorder, open_recording, read_recording
from sumoco.recording.codec import (PHYSICS_FIELDS, STEP_FIELDS, CompactDecoder, CompactEncoder, CompactError)
from synthetic.traffic import FakeRun


def _subset(msg, keep: np.ndarray):
    """The same message with only agents ``keep`` (in that order)."""
    a = msg.agents
    cols = {}
    for f in dataclasses.fields(a):
        v = getattr(a, f.name)
        if f.name == "ids":
            cols[f.name] = [v[i] for i in keep]
        elif f.name in ("path_offsets", "path_xy"):
            continue
        else:
            cols[f.name] = np.asarray(v)[keep]
    if hasattr(a, "path_offsets") and len(a.path_offsets):
        paths = [a.path(i) for i in keep]
        cols["path_offsets"] = np.concatenate([[0], np.cumsum([len(p) for p in paths])]).astype(np.uint32)
        cols["path_xy"] = np.concatenate(paths) if paths else np.zeros((0, 2))
    return dataclasses.replace(msg, agents=type(a)(**cols))


def _check(orig, back, fields) -> None:
    assert list(back.agents.ids) == list(orig.agents.ids)
    for name, unit, _order, _dt in fields:
        if name.startswith("la_"):
            continue
        a, b = np.asarray(getattr(orig.agents, name), float), np.asarray(getattr(back.agents, name), float)
        tol = 1e-9 if unit is None else unit / 2 * 1.001 + 1e-6 * np.abs(a).max(initial=0)
        assert np.abs(a - b).max(initial=0) <= tol, name
    # the result is a valid protocol message again
    assert type(decode(encode(back))) is type(orig)


def test_steps_and_states_round_trip_while_agents_come_go_and_reorder():
    fake = FakeRun(grid=2, n=120, run="c")
    rng = np.random.default_rng(1)
    enc, dec = CompactEncoder(keyframe_every=7), CompactDecoder()
    for k in range(30):
        keep = np.sort(rng.choice(120, size=rng.integers(0, 120), replace=False))
        if k % 5 == 3:
            rng.shuffle(keep)
        step = _subset(fake.step(k), keep)
        phys = _subset(fake.physics(k, k * 0.1, k), keep)
        back = dec.decode("s", *enc.encode("s", step))
        _check(step, back, STEP_FIELDS)
        assert np.abs(back.agents.la_x - step.agents.la_x).max(initial=0) <= 0.006
        assert np.abs(back.agents.path_xy - step.agents.path_xy).max(initial=0) <= 0.0051
        assert list(back.agents.path_offsets) == list(step.agents.path_offsets)
        assert back.tls.state == step.tls.state and back.vtypes == step.vtypes
        assert (back.step, back.time, back.static_version) == (step.step, step.time, step.static_version)
        pb = dec.decode("p", *enc.encode("p", phys))
        _check(phys, pb, PHYSICS_FIELDS)
        assert pb.counters == phys.counters and pb.time == phys.time


def test_a_missing_record_skips_to_the_next_keyframe():
    fake = FakeRun(grid=1, n=20, run="c")
    enc, dec = CompactEncoder(keyframe_every=4), CompactDecoder()
    recs = [enc.encode("s", fake.step(k)) for k in range(9)]
    dec.decode("s", *recs[0])
    with pytest.raises(CompactError, match="missing"):
        dec.decode("s", *recs[2])  # record 1 lost
    with pytest.raises(CompactError):
        dec.decode("s", *recs[3])
    assert dec.decode("s", *recs[4]).step == 4  # keyframe
    with pytest.raises(CompactError, match="undecodable"):
        dec.decode("s", recs[5][0], b"\x00garbage")


def test_recording_reads_compact_records_back_as_protocol_payloads(tmp_path):
    fake = FakeRun(grid=1, n=30, run="c")
    keys = Keys("sumoco", "c")
    path = tmp_path / "c.mcap"
    rec, enc = McapRecorder(path), CompactEncoder()
    for k in range(25):
        schema, data = enc.encode(keys.step, fake.step(k))
        rec.write(keys.step, data, 1_000 + k, schema=schema)
        schema, data = enc.encode(keys.physics_state, fake.physics(k, k * 0.1, k))
        rec.write(keys.physics_state, data, 1_000 + k, schema=schema)
    rec.close()
    res = read_recording(path)
    assert [m.schema for m in res.messages] == ["step", "physics"] * 25
    steps = [decode(m.data) for m in res.messages if m.schema == "step"]
    assert [s.step for s in steps] == list(range(25))
    assert np.abs(steps[-1].agents.x - fake.step(24).agents.x).max() <= 0.0005
    assert open_recording(path).skipped == 0
