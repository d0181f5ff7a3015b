"""``sumoco record`` against live daemons: every key recorded raw, plus a Foxglove scene."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import msgpack
import numpy as np
import pytest

from protocol.codec import decode, encode
from protocol.keys import Keys
from protocol.messages import PhysicsState, StaticData, StepMessage
from sumoco.recording.record import kind_of_topic, read_recording
from tests.harness import PAPER_CFG, ROOT, Daemon, assert_exit_codes, endpoint

pytestmark = pytest.mark.integration


def test_record_live_run_to_mcap(tmp_path):
    cfg = tmp_path / "r.toml"
    cfg.write_text(f'[run]\nid = "rec"\n[sumo]\nsumocfg = "{PAPER_CFG}"\n')
    sumo_ep = endpoint()
    sumo = Daemon("sumo", ["sumo", "--config", str(cfg), "--listen", sumo_ep, "--quiet"], tmp_path / "logs")
    phys = Daemon("physics", ["physics", "--config", str(cfg), "--listen", endpoint(), "--connect", sumo_ep,
                              "--quiet"], tmp_path / "logs")
    out = tmp_path / "run.mcap"
    try:
        r = subprocess.run(
            [sys.executable, "-m", "sumoco.cli", "record", "--config", str(cfg), "--connect", sumo_ep,
             "--listen", endpoint(), "--out", str(out), "--duration", "6", "--quiet"],
            capture_output=True, text=True, timeout=60, cwd=ROOT,
        )
        assert r.returncode == 0, r.stderr
    finally:
        sumo.terminate(15)
        phys.terminate(15)
    assert_exit_codes([sumo, phys])  # both stopped by SIGTERM: a clean end
    res = read_recording(out)
    assert not res.truncated
    keys = Keys("sumoco", "rec")
    topics = {m.topic for m in res.messages}
    assert {keys.step, keys.static, keys.sumo_map, keys.physics_state, "/scene"} <= topics
    kinds = {StepMessage: 0, StaticData: 0, PhysicsState: 0}
    for m in res.messages:
        if m.topic == "/scene":
            assert m.schema == "foxglove.SceneUpdate" and len(m.data) > 0
            continue
        if m.topic == keys.sumo_map:  # the SUMO side's glTF map answer (SPEC 9), recorded once
            d = msgpack.unpackb(m.data)
            assert m.schema == "map" and d["kind"] == "map" and len(d["glb"]) == d["size"] > 1000
            continue
        assert m.schema == kind_of_topic(m.topic)
        t = type(decode(m.data))
        kinds[t] = kinds.get(t, 0) + 1
    assert kinds[StepMessage] > 20 and kinds[PhysicsState] > 5 and kinds[StaticData] == 1
    steps = [decode(m.data).step for m in res.messages if m.topic == keys.step]
    assert steps == sorted(steps) and len(set(steps)) == len(steps)
    # Physics states are thinned to the default 10 Hz of simulated time (published at 50 Hz).
    t = np.array([decode(m.data).time for m in res.messages if m.topic == keys.physics_state])
    assert np.all(np.diff(t) >= 0.1 - 1e-6), np.diff(t).min()
    stats = json.loads(r.stdout.strip().splitlines()[-1])
    assert stats["dropped"] == 0 and stats["write_errors"] == 0 and stats["thinned"] > len(t)
    assert stats["received"] == stats["written"] + stats["thinned"] - 2  # static and map came by query


class _Sample:
    def __init__(self, key: str, data: bytes) -> None:
        self.key_expr, self._data = key, data
        self.payload = self

    def to_bytes(self) -> bytes:
        return self._data


class _SlowRecorder:
    """Stands in for the MCAP writer: blocks until released, like a stalled disk."""

    def __init__(self) -> None:
        import threading

        self.release = threading.Event()
        self.written: list[str] = []
        self.context = None

    def write(self, topic, payload, stamp_ns=None, schema=None) -> None:
        self.release.wait(10)
        self.written.append(topic)

    def flush(self) -> None:
        pass


def test_recorder_never_blocks_the_transport_and_counts_drops():
    import time

    from sumoco.recording.record import LiveRecorder, RecordConfig

    keys = Keys("sumoco", "unit")
    slow = _SlowRecorder()
    live = LiveRecorder(None, keys, slow, config=RecordConfig(queue=10, queue_mb=1.0, scene=False, physics_hz=0))
    t0 = time.perf_counter()
    for _ in range(200):  # the writer is stalled: the callback must still return at once
        live.on_sample(_Sample(keys.step, b"x" * 1000))
    assert time.perf_counter() - t0 < 0.5
    assert live.received == 200 and 185 <= live.dropped <= 190  # 10 queued, 1 in the writer's hands
    big = _Sample(keys.step, b"x" * 2_000_000)  # over the byte bound on its own
    live.on_sample(big)
    slow.release.set()
    live.stop(10)
    assert live.dropped >= 186 and live.written == len(slow.written) == live.received - live.dropped


def test_a_sample_after_stop_is_counted_late_and_every_received_one_is_accounted_for():
    """Zenoh can still run a callback while the subscriber is undeclared: such a sample must
    not be counted as received and then lost behind the writer's end marker."""
    import threading

    from sumoco.recording.record import LiveRecorder, RecordConfig

    keys = Keys("sumoco", "late")
    out = _CountingRecorder()
    live = LiveRecorder(None, keys, out, config=RecordConfig(scene=False, physics_hz=0))
    go = threading.Event()

    def feed(k: int) -> None:
        go.wait(5)
        for i in range(3000):
            live.on_sample(_Sample(keys.ack, b"%d-%d" % (k, i)))

    feeders = [threading.Thread(target=feed, args=(k,)) for k in range(3)]
    for t in feeders:
        t.start()
    go.set()
    deadline = time.monotonic() + 5
    while live.received < 500 and time.monotonic() < deadline:  # stop while they are feeding
        time.sleep(0.0005)
    live.stop(10)
    for t in feeders:
        t.join(10)
    assert not any(t.is_alive() for t in feeders)
    assert live.received + live.late == 3 * 3000 and live.received >= 500
    assert live.received == live.written + live.dropped == len(out.written)
    before = live.received
    live.on_sample(_Sample(keys.ack, b"after"))
    assert live.received == before and live.late >= 1 and len(out.written) == live.written
    assert live.stats()["late"] == live.late


def test_recorder_records_each_static_version_and_replay_serves_it(tmp_path):
    """SPEC 3.2: when a step's `sv` moves on, the recorder asks again; replay serves each version."""
    import dataclasses

    from sumoco.recording.record import LiveRecorder, McapRecorder, RecordConfig
    from runtime.config import ZenohConfig
    from runtime.transport import open_session
    from synthetic.traffic import FakeRun
    from tests.harness import wait_until

    fake = FakeRun(grid=1, n=8, run="sv")
    keys = Keys("sumoco", "sv")
    served = [encode(fake.static())]
    path = tmp_path / "sv.mcap"
    rec = McapRecorder(path)
    with open_session(ZenohConfig(listen=(endpoint(),))) as s:
        s.declare_queryable(keys.static, lambda q: q.reply(keys.static, served[0]))
        live = LiveRecorder(s, keys, rec, config=RecordConfig(scene=False)).start()
        assert live.fetch_static(5.0, map_timeout_s=0) is not None
        pub = s.declare_publisher(keys.step)
        for k in range(20):
            if k == 10:
                served[0] = encode(dataclasses.replace(fake.static(), version=1))
            pub.put(encode(dataclasses.replace(fake.step(k), static_version=int(k >= 10))))
            time.sleep(0.05)
        wait_until(lambda: live.static_versions == 1, 5.0, "the second static version recorded")
        live.stop()
    rec.close()
    order = [(m.topic, decode(m.data)) for m in read_recording(path).messages]
    statics = [(i, msg.version) for i, (t, msg) in enumerate(order) if t == keys.static]
    assert [v for _, v in statics] == [0, 1]
    first_v1_step = next(i for i, (t, msg) in enumerate(order) if t == keys.step and msg.static_version == 1)
    assert statics[1][0] > first_v1_step
    # Replay: while steps of version 1 are replayed, the queryable answers version 1.
    import threading

    from sumoco.recording.replay import Replayer

    ep = endpoint()
    with open_session(ZenohConfig(listen=(ep,))) as a, open_session(ZenohConfig(listen=(endpoint(),),
                                                                                  connect=(ep,))) as b:
        newest: list[StepMessage] = []
        b.declare_subscriber(keys.step, lambda smp: newest.append(decode(smp.payload.to_bytes())))
        rep = Replayer(a, path, speed=0.25, loop=True, wait_subscriber_s=5.0)  # 0.2 s per step
        th = threading.Thread(target=rep.run)
        th.start()
        try:
            wait_until(lambda: newest and newest[-1].step >= 13, 20.0, "replayed steps of version 1")
            assert newest[-1].static_version == 1
            got = [decode(r.ok.payload.to_bytes()).version for r in b.get(keys.static, timeout=5.0)
                   if r.ok is not None]
        finally:
            rep.stop()
            th.join(10)
            rep.close()
    assert got == [1]


def test_recorder_records_the_network_of_a_restarted_sumo_side(tmp_path):
    """A SUMO side restarted under the same run id starts again at step 0 and static version
    0: a different network is recorded again, the same one is not written twice."""
    from sumoco.recording.record import LiveRecorder, McapRecorder, RecordConfig
    from runtime.config import ZenohConfig
    from runtime.transport import open_session
    from synthetic.traffic import FakeRun
    from tests.harness import wait_until

    keys = Keys("sumoco", "rs")
    runs = [FakeRun(grid=1, n=8, run="rs"), FakeRun(grid=1, n=8, run="rs"), FakeRun(grid=2, n=8, run="rs")]
    served = [encode(runs[0].static())]
    path = tmp_path / "rs.mcap"
    rec = McapRecorder(path)
    with open_session(ZenohConfig(listen=(endpoint(),))) as s:
        s.declare_queryable(keys.static, lambda q: q.reply(keys.static, served[0]))
        live = LiveRecorder(s, keys, rec, config=RecordConfig(scene=False)).start()
        assert live.fetch_static(5.0, map_timeout_s=0) is not None
        pub = s.declare_publisher(keys.step)
        for i, fake in enumerate(runs):  # the same network again, then another one
            served[0] = encode(fake.static())
            for k in range(10):
                pub.put(encode(fake.step(k)))
                time.sleep(0.03)
            if i == 2:
                wait_until(lambda: live.static_versions == 1, 5.0, "the new network recorded")
        time.sleep(0.5)  # the restart with the same network had as long to be (wrongly) recorded
        live.stop()
    rec.close()
    statics = [decode(m.data) for m in read_recording(path).messages if m.topic == keys.static]
    assert [len(st.junctions.ids) for st in statics] == [len(runs[0].junctions.ids), len(runs[2].junctions.ids)]
    assert len(runs[2].junctions.ids) != len(runs[0].junctions.ids)


class _Log:
    """Stands in for the scene's channel: keeps each update's bytes and stamp."""

    def __init__(self) -> None:
        self.updates: list[tuple[bytes, int | None]] = []

    def log(self, upd, log_time=None) -> None:
        self.updates.append((upd.encode(), log_time))


def test_the_writer_decodes_each_step_and_state_once_and_the_scene_is_the_same(tmp_path, monkeypatch):
    from protocol.codec import encode
    from sumoco.recording import record as record_mod
    from sumoco.recording.record import LiveRecorder, McapRecorder, RecordConfig
    from sumoco.viewing import scene as scene_mod
    from synthetic.traffic import FakeRun

    fake = FakeRun(grid=1, n=12, run="o")
    keys = Keys("sumoco", "o")
    paper, default = Keys("sumoco", "o", "paper"), Keys("sumoco", "o", "default")
    feed = [(keys.static, encode(fake.static()))]
    for k in range(60):  # 6 s: steps at 10 Hz, two physics instances at 50 Hz
        step = fake.step(k)
        feed.append((keys.step, encode(step)))
        for j in range(5):
            t = step.time + 0.02 * j
            feed += [(inst.physics_state, encode(fake.physics(5 * k + j, t, k))) for inst in (paper, default)]
    n_agent_msgs = len(feed) - 1

    # the scene as a publisher fed the payloads alone draws it (thinned to 0.5 Hz)
    want = scene_mod.ScenePublisher(None, min_period_s=2.0)
    want.channel = _Log()
    for i, (topic, payload) in enumerate(feed):
        if want.offer(topic, payload):
            want.feed(topic, payload, 1_000 + i)
    assert len(want.channel.updates) == 1 + 3 * 3  # the network, and 3 each of steps and two instances

    calls = {"record": 0, "scene": 0, "peek": 0}

    def counting(name, fn):
        def wrapped(*a, **kw):
            calls[name] += 1
            return fn(*a, **kw)
        return wrapped

    monkeypatch.setattr(record_mod, "decode", counting("record", record_mod.decode))
    monkeypatch.setattr(scene_mod, "decode", counting("scene", scene_mod.decode))
    monkeypatch.setattr(scene_mod, "peek", counting("peek", scene_mod.peek))
    rec = McapRecorder(tmp_path / "o.mcap")
    # a scene queue that holds every update: a slow scene thread must not drop one here
    live = LiveRecorder(None, keys, rec, config=RecordConfig(physics_hz=0.0, scene_hz=0.5, scene_queue=64))
    live.clock_ns = lambda it=iter(range(1_000, 10**6)): next(it)  # stamps as above
    live._scene.channel = _Log()
    for topic, payload in feed:
        live.on_sample(_Sample(topic, payload))
    assert live.drain(20)
    live.stop()
    rec.close()
    assert live.stats()["written"] == len(feed) and live.compact_errors == 0 and live.scene_dropped == 0
    assert live._scene.channel.updates == want.channel.updates  # the same updates, stamps included
    # each step and state decoded once, for its compact record; the scene decodes only the static data
    assert calls == {"record": n_agent_msgs, "scene": 1, "peek": 0}


class _CountingRecorder:
    """Stands in for the MCAP writer: keeps what was written."""

    context = None

    def __init__(self) -> None:
        self.written: list[str] = []

    def write(self, topic, payload, stamp_ns=None, schema=None) -> None:
        self.written.append(topic)

    def flush(self) -> None:
        pass


def test_the_writer_takes_messages_in_batches_not_one_wake_up_each():
    from sumoco.recording.record import WRITE_BATCH_S, LiveRecorder, RecordConfig

    keys = Keys("sumoco", "b", "paper")
    out = _CountingRecorder()
    t0 = time.monotonic()
    live = LiveRecorder(None, keys, out, config=RecordConfig(scene=False, physics_hz=0))
    n = 100
    for i in range(n):  # a message every 2 ms, like a live run's acks and states
        live.on_sample(_Sample(keys.ack, b"%d" % i))
        time.sleep(0.002)
    assert live.drain(10)
    elapsed = time.monotonic() - t0
    live.stop()
    assert out.written == [keys.ack] * n and live.written == n
    # every pause lasts WRITE_BATCH_S, so there are at most elapsed / WRITE_BATCH_S of them
    # (+1 for the one under way): the writer woke per batch, not per message
    assert 1 <= live.idle_waits <= elapsed / WRITE_BATCH_S + 1
    assert live.idle_waits <= n // 4
