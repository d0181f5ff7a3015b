"""``sumoco replay``: a recording republished on Zenoh as the daemons published it."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import msgpack
import numpy as np
import pytest

from protocol.codec import decode
from protocol.keys import Keys
from protocol.messages import StaticData, StepMessage
from sumoco.recording.record import read_recording
from runtime.config import ZenohConfig
from runtime.transport import open_session
from tests.harness import PAPER_CFG, ROOT, Daemon, endpoint, wait_until
from tests.recording_fixture import make_recording

KEYS = Keys("sumoco", "synth")


@pytest.fixture(scope="module")
def map_reply():
    from sumo_side.mapmesh import MapService

    svc = MapService(PAPER_CFG.parent / "paper.net.xml", "synth")
    assert svc.wait(60.0), svc.error
    return svc.reply("")


@pytest.fixture(scope="module")
def recording(tmp_path_factory, map_reply):
    path = tmp_path_factory.mktemp("rec") / "run.mcap"
    stats = make_recording(path, steps=15, map_reply=map_reply)
    assert stats["dropped"] == 0 and stats["written"] > 30
    return path


def test_recording_holds_raw_keys_and_scene(recording):
    res = read_recording(recording)
    assert not res.truncated
    topics = {m.topic for m in res.messages}
    inst = {Keys("sumoco", "synth", i).physics_state for i in ("paper", "default")}
    assert {KEYS.step, KEYS.static, KEYS.sumo_map, "/scene"} | inst <= topics
    steps = [decode(m.data).step for m in res.messages if m.topic == KEYS.step]
    assert len(steps) >= 12 and steps == sorted(steps)


def test_truncated_recording_reads_up_to_the_cut(recording, tmp_path):
    data = recording.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    res = read_recording(cut)
    assert res.truncated and res.error
    assert 0 < len(res.messages) < len(read_recording(recording).messages)


class _Listener:
    """A client written as SPEC.md says: subscribe to the run, query static, watch tokens."""

    def __init__(self, connect: str) -> None:
        self.s = open_session(ZenohConfig(listen=(endpoint(),), connect=(connect,)))
        self.lock = threading.Lock()
        self.got: list[tuple[str, bytes, float]] = []
        self.alive: set[str] = set()
        self.sub = self.s.declare_subscriber(KEYS.everything, self._cb)
        self.tok = self.s.liveliness().declare_subscriber(
            f"{KEYS.base}/**", lambda smp: self.alive.add(str(smp.key_expr)), history=True)

    def _cb(self, smp) -> None:
        with self.lock:
            self.got.append((str(smp.key_expr), smp.payload.to_bytes(), time.monotonic()))

    def steps(self):
        with self.lock:
            return [g for g in self.got if g[0] == KEYS.step]

    def static(self) -> bytes | None:
        for r in self.s.get(KEYS.static, timeout=2.0):
            if r.ok is not None:
                return r.ok.payload.to_bytes()
        return None

    def close(self) -> None:
        self.s.close()


def _sans_epoch(payload: bytes) -> bytes:
    d = msgpack.unpackb(payload, raw=False)
    d.pop("epoch", None)
    return msgpack.packb(d, use_bin_type=True)


@pytest.mark.integration
def test_replay_republishes_keys_static_map_and_tokens(recording, map_reply, tmp_path):
    ep = endpoint()
    rec = read_recording(recording)
    recorded_steps = [(m.data, m.log_time_ns) for m in rec.messages if m.topic == KEYS.step]
    replay = Daemon("replay", ["replay", str(recording), "--loop", "--listen", ep, "--quiet"], tmp_path)
    lis = None
    try:
        lis = _Listener(ep)
        wait_until(lambda: len(lis.steps()) >= 25, 20.0, "replayed steps", procs=[replay])
        wait_until(lambda: {KEYS.sumo_alive, Keys("sumoco", "synth", "paper").physics_alive,
                            Keys("sumoco", "synth", "default").physics_alive} <= lis.alive,
                   5.0, "liveliness tokens", procs=[replay])
        static = lis.static()
        assert static is not None and isinstance(decode(static), StaticData)
        # as recorded but for the epoch: a replay is an incarnation of its own (SPEC 3.1.1, 11)
        recorded_static = next(m.data for m in rec.messages if m.topic == KEYS.static)
        assert decode(static).epoch > decode(recorded_static).epoch
        assert _sans_epoch(static) == _sans_epoch(recorded_static)
        # The recorded glTF map is served like the SUMO side serves it, hash check included.
        full = [r.ok.payload.to_bytes() for r in lis.s.get(KEYS.sumo_map, timeout=5.0) if r.ok is not None]
        assert full == [map_reply]
        sha = msgpack.unpackb(map_reply)["sha256"]
        short = [msgpack.unpackb(r.ok.payload.to_bytes()) for r in lis.s.get(f"{KEYS.sumo_map}?sha256={sha}",
                                                                              timeout=5.0) if r.ok is not None]
        assert short[0]["glb"] is None and short[0]["sha256"] == sha
        got = lis.steps()
        # Byte-exact but for the epoch: every replayed step is one of the recorded payloads,
        # in recorded order; each pass of the loop is a newer incarnation
        index = {_sans_epoch(d): i for i, (d, _) in enumerate(recorded_steps)}
        order = [index[_sans_epoch(d)] for _, d, _ in got]
        assert all(b == (a + 1) % len(recorded_steps) for a, b in zip(order, order[1:])), order
        epochs = [decode(d).epoch for _, d, _ in got]
        assert all(e > 0 for e in epochs) and epochs == sorted(epochs)
        assert len(set(epochs)) == 1 + sum(b < a for a, b in zip(order, order[1:]))
        assert isinstance(decode(got[0][1]), StepMessage)
        # Pacing: replayed intervals follow the recorded ones (10 Hz) within scheduling noise.
        rec_dt = np.diff([t for _, t in recorded_steps]) / 1e9
        rep_dt = np.diff([t for _, _, t in got if True])
        rep_dt = rep_dt[rep_dt > 0.01]  # the loop's wrap-around is back to back
        assert abs(np.median(rep_dt) - np.median(rec_dt)) < 0.02, (np.median(rep_dt), np.median(rec_dt))
    finally:
        if lis is not None:
            lis.close()
        code = replay.terminate(5)
    assert code == 0, replay.tail()


@pytest.mark.integration
def test_replay_at_four_times_speed_waits_for_a_subscriber_and_ends(recording, tmp_path):
    import json

    ep = endpoint()
    got: list[bytes] = []
    when: list[float] = []
    with open_session(ZenohConfig(listen=(ep,))) as s:
        s.declare_subscriber(KEYS.step, lambda smp: (got.append(smp.payload.to_bytes()), when.append(time.monotonic())))
        r = subprocess.run([sys.executable, "-m", "sumoco.cli", "replay", str(recording), "--speed", "4",
                            "--connect", ep, "--listen", endpoint(), "--wait-subscriber", "10", "--quiet"],
                           capture_output=True, text=True, timeout=30, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    stats = json.loads(r.stdout.strip().splitlines()[-1])
    steps = [m for m in read_recording(recording).messages if m.topic == KEYS.step]
    assert stats["steps"] == len(steps) and stats["loops"] == 1
    # every step, byte-exact but for the replay's own epoch, in order
    assert [_sans_epoch(d) for d in got] == [_sans_epoch(m.data) for m in steps]
    rec_dt = np.median(np.diff([m.log_time_ns for m in steps])) / 1e9
    assert rec_dt / 8 < np.median(np.diff(when)) < rec_dt / 2  # paced at 4x: neither 1x nor unpaced


def test_replay_rejects_a_missing_file_and_a_bad_speed(tmp_path, recording):
    r = subprocess.run([sys.executable, "-m", "sumoco.cli", "replay", str(tmp_path / "nope.mcap")],
                       capture_output=True, text=True, timeout=30, cwd=ROOT)
    assert r.returncode == 2 and "nope.mcap" in r.stderr and "not found" in r.stderr
    r = subprocess.run([sys.executable, "-m", "sumoco.cli", "replay", str(recording), "--speed", "0"],
                       capture_output=True, text=True, timeout=30, cwd=ROOT)
    assert r.returncode == 2 and "speed" in r.stderr
