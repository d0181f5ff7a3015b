"""Scene building for recordings and the live Foxglove server: thinning and the drop-oldest worker."""

from __future__ import annotations

import threading

import foxglove

from protocol.codec import encode
from protocol.keys import Keys
from sumoco.viewing.scene import LatestWorker, ScenePublisher
from synthetic.traffic import FakeRun


def test_latest_worker_drops_the_oldest_and_keeps_the_newest():
    gate = threading.Event()
    seen: list[int] = []

    def handle(i: int) -> None:
        gate.wait(5)
        seen.append(i)

    w = LatestWorker(handle, maxlen=3, name="t")
    for i in range(10):
        w.put(i)
    gate.set()
    assert w.drain(5)
    w.close()
    # The first item was already taken when the rest arrived; of the others only the newest 3 stay.
    assert seen[-3:] == [7, 8, 9] and w.dropped == 10 - len(seen)
    assert w.handled == len(seen) and w.failed == 0


def test_scene_publisher_thins_by_simulated_time_and_survives_bad_payloads():
    ctx = foxglove.Context()  # no sink: logging costs nothing, the publisher's counters still count
    fake = FakeRun(grid=1, n=10, run="s")
    keys = Keys("sumoco", "s", "paper")
    pub = ScenePublisher(ctx, min_period_s=0.5)
    assert pub.feed(keys.static, encode(fake.static()))
    for k in range(20):  # 2 s of steps at 10 Hz -> updates at 0.5 s of simulated time
        pub.feed(keys.step, encode(fake.step(k)))
        pub.feed(keys.physics_state, encode(fake.physics(k, fake.step(k).time, k)))
    assert pub.updates == 1 + 4 + 4 and pub.thinned == 2 * 20 - 8
    assert not pub.feed(keys.step, b"\x93garbage") and pub.errors == 1
    assert not pub.feed(keys.ack, b"")  # not a scene key: ignored, not an error
    assert pub.errors == 1
