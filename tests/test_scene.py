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


def test_offer_thins_physics_states_before_they_are_queued_and_feed_agrees():
    ctx = foxglove.Context()
    fake = FakeRun(grid=1, n=10, run="s")
    keys = Keys("sumoco", "s", "paper")
    pub = ScenePublisher(ctx, min_period_s=0.5)
    offered = fed = 0
    for k in range(20):  # 2 s at 10 Hz: 20 steps and 20 physics states
        step = encode(fake.step(k))
        state = encode(fake.physics(k, fake.step(k).time, k))
        assert pub.offer(keys.step, step)  # steps always pass: the sizes come from each one
        pub.feed(keys.step, step)
        if pub.offer(keys.physics_state, state):
            offered += 1
            fed += pub.feed(keys.physics_state, state)
    # 4 physics states reach the worker instead of 20, and every one of them is drawn.
    assert offered == 4 and fed == 4
    assert pub.offer(keys.physics_state, b"\x93garbage")  # undecodable: feed counts the error
    assert not pub.feed(keys.physics_state, b"\x93garbage") and pub.errors == 1
    # A run that starts again (time back by more than 1 s) is drawn at once.
    assert pub.offer(keys.physics_state, encode(fake.physics(0, 0.0, 0)))
    assert ScenePublisher(ctx, min_period_s=0.0).offer(keys.physics_state, b"")  # no thinning: all pass
