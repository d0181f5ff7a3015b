"""Hostile volume: every queue between Zenoh and a daemon is bounded, egos are capped.

The hand-over queues on their own (``DropOldest``: physics steps; ``LatestPerKey``: the
SUMO side's acks and liveliness changes), then the real SUMO side as a process under a
flood of acknowledgements (newest per key: memory stays flat and lockstep still advances
on the real acks; keys beyond ``max_peer_keys`` refused) and of ego poses under many ids
(at most ``[sumo] ego_max_per_client`` egos of one client and ``ego_max`` in all are created,
the rest refused and counted; another client still gets its egos in).
"""

from __future__ import annotations

import threading
import time

import msgpack
import pytest
import zenoh

from protocol.codec import decode, encode
from protocol.keys import Keys
from protocol.messages import AgentFlag, EgoPose, StepAck
from sumoco.bench.soak import rss_mb
from runtime.config import ZenohConfig
from runtime.queues import DropOldest, LatestPerKey
from runtime.transport import open_session
from tests.harness import Daemon, endpoint, wait_until
from tests.sumo_testnet import make_testnet


def test_drop_oldest_bounds_items_and_bytes_and_counts_drops():
    q: DropOldest[bytes] = DropOldest(3, max_bytes=10)
    for i in range(5):
        assert q.put(bytes([i]) * 2)
    assert len(q) == 3 and q.dropped == 2 and q.nbytes == 6
    assert [q.get(), q.get(), q.get()] == [b"\x02\x02", b"\x03\x03", b"\x04\x04"]  # the newest kept, in order
    assert q.get() is None
    q.put(b"a" * 6)
    q.put(b"b" * 6)  # 12 bytes would exceed 10: the older one goes
    assert len(q) == 1 and q.dropped == 3 and q.nbytes == 6
    assert not q.put(b"c" * 11) and q.refused == 1 and len(q) == 1  # too big alone: refused, nothing lost
    t0 = time.monotonic()
    q.get(), q.get(timeout=0.2)
    assert 0.15 < time.monotonic() - t0 < 2.0  # waits for an item, bounded
    threading.Timer(0.05, q.put, args=(b"late",)).start()
    assert q.get(timeout=5.0) == b"late"  # and wakes as soon as one comes
    with pytest.raises(ValueError, match="maxlen and max_bytes must be >= 1"):
        DropOldest(0)


def test_latest_per_key_keeps_the_newest_per_key_and_bounds_the_keys():
    q: LatestPerKey[int] = LatestPerKey(2)
    for i in range(1000):
        q.put("flood", i)
    assert q.put("main", 7) and not q.put("third", 1)
    assert q.replaced == 999 and q.refused == 1
    assert q.drain() == {"flood": 999, "main": 7} and len(q) == 0
    r: LatestPerKey[int] = LatestPerKey(1, reserved=frozenset({"main"}))
    assert r.put("a", 1) and not r.put("b", 1) and r.put("main", 2)  # a reserved key always fits
    assert r.drain() == {"a": 1, "main": 2}
    t0 = time.monotonic()
    assert q.drain(timeout=0.2) == {} and 0.15 < time.monotonic() - t0 < 2.0


def _status(session, keys):
    for r in session.get(keys.sumo_status, timeout=3.0):
        if r.ok is not None:
            return msgpack.unpackb(r.ok.payload.to_bytes(), raw=False)["counters"]
    return None


@pytest.mark.integration
def test_sumo_side_survives_an_ack_flood_and_caps_egos_per_client_and_in_total(tmp_path):
    scenario = make_testnet(tmp_path / "net")
    ep = endpoint()
    toml = tmp_path / "flood.toml"
    toml.write_text(
        '[run]\nid = "flood"\ntiming = "lockstep"\nlockstep_timeout_s = 10.0\n\n'
        f'[sumo]\nsumocfg = "{scenario}"\nlockstep_instances = ["main"]\nego_id = "*"\nego_max = 4\n'
        'ego_max_per_client = 2\n'
        'max_peer_keys = 4\n'
    )
    sumo = Daemon("sumo", ["sumo", "--config", str(toml), "--listen", ep, "--quiet"], tmp_path)
    keys = Keys("sumoco", "flood")
    steps: list = []
    try:
        with open_session(ZenohConfig(connect=(ep,), listen=())) as s:
            # like the physics side: acknowledgements are never dropped, even behind the flood
            ack = s.declare_publisher(keys.ack, congestion_control=zenoh.CongestionControl.BLOCK)

            def on_step(sample):  # we are physics "main": acknowledge every step at once
                m = decode(sample.payload.to_bytes())
                steps.append(m)
                ack.put(encode(StepAck("flood", m.step, m.step)))
            sub = s.declare_subscriber(keys.step, on_step)
            token = s.liveliness().declare_token(keys.physics_alive)
            wait_until(lambda: len(steps) > 20, 30, "lockstep steps", procs=[sumo])
            rss0 = rss_mb(sumo.proc.pid)

            flood = s.declare_publisher(Keys("sumoco", "flood", "flood").ack)
            junk = encode(StepAck("flood", 0, 0))
            n_flood = 30_000
            for _ in range(n_flood):
                flood.put(junk)
            k0 = len(steps)
            wait_until(lambda: len(steps) > k0 + 20, 30, "lockstep to go on after the flood", procs=[sumo])
            st = wait_until(lambda: _status(s, keys), 10, "SUMO status")
            # newest ack per key: the flood coalesced into one slot instead of queueing, and
            # could not push the real acks of "main" out (lockstep went on)
            assert st["acks_coalesced"] > 0 and st["acks"] + st["acks_coalesced"] <= len(steps) + n_flood
            assert rss_mb(sumo.proc.pid) - rss0 < 30.0  # [MB]
            # more keys than max_peer_keys: refused, counted, and "main" still served
            for i in range(10):
                s.put(Keys("sumoco", "flood", f"x{i}").ack, junk)
            # a status query can go unanswered under load (None): ask again until the deadline
            wait_until(lambda: (c := _status(s, keys)) is not None and c["peer_keys_refused"] > 0, 10,
                       "keys beyond max_peer_keys refused")
            k1 = len(steps)
            wait_until(lambda: len(steps) > k1 + 10, 30, "lockstep to go on", procs=[sumo])

            def pose(ego_id: str, i: int) -> bytes:
                m = steps[-1]
                return encode(EgoPose(ego_id, float(m.agents.x[0]) + 5.0 * i, float(m.agents.y[0]),
                                      float(m.agents.angle[0]), 0.0))

            def flood(ids: list[str], rounds: int = 10) -> None:
                for _ in range(rounds):
                    for i, ego_id in enumerate(ids):
                        s.put(keys.ego(ego_id), pose(ego_id, i))
                    time.sleep(0.05)

            def egos_by_client() -> dict[str, set[str]]:
                m = steps[-1]
                out: dict[str, set[str]] = {}
                for i, f in zip(m.agents.ids, m.agents.flags):
                    if f & AgentFlag.EGO:
                        out.setdefault(i.split(".")[0], set()).add(i)
                return out

            # one client ("a.<n>") floods twelve ids: its two get in, the rest are refused
            flood([f"a.{i}" for i in range(12)])
            wait_until(lambda: (c := _status(s, keys)) and c["ego_created"] >= 2, 20,
                       "the first client's egos in SUMO", procs=[sumo])
            time.sleep(0.5)  # let any ego beyond the cap arrive before counting (none must be created)
            st = wait_until(lambda: _status(s, keys), 10, "SUMO status")
            assert st["ego_created"] == 2 and st["ego_refused_client"] >= 10 and st["ego_refused"] == 0, st
            # another client still gets its egos in, up to its own cap
            flood([f"b.{i}" for i in range(12, 16)])
            wait_until(lambda: (c := _status(s, keys)) and c["ego_created"] >= 4, 20,
                       "the second client's egos in SUMO", procs=[sumo])
            # the total cap holds for anyone: a third client and ids without a client part
            flood(["c.0", "solo", "e16"])
            time.sleep(0.5)
            st = wait_until(lambda: _status(s, keys), 10, "SUMO status")
            assert st["ego_created"] == 4 and st["ego_refused"] >= 3 and st["rejected"] >= 13, st
            k2 = len(steps)
            wait_until(lambda: len(steps) > k2 + 2, 20, "steps after the flood", procs=[sumo])
            by_client = egos_by_client()
            assert {c: len(v) for c, v in by_client.items()} == {"a": 2, "b": 2}, by_client
            sub.undeclare()
            token.undeclare()
    finally:
        code = sumo.terminate(10)
    assert code == 0, sumo.tail()
