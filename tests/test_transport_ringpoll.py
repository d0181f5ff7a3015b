"""``runtime.transport.RingPoll`` on a real Zenoh session: samples from the ring in order, a
spin within the window, and the ways ``wait`` ends (a sample, the loop's wake, stop, timeout)."""

from __future__ import annotations

import threading
import time

import zenoh

from runtime.config import ZenohConfig
from runtime.transport import RingPoll, Wake, free_tcp_port, open_session

KEY = "sumocotest/ringpoll/step"


def test_ring_poll_hands_every_sample_over_in_order_and_each_wait_ends():
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    got: list[bytes] = []
    with open_session(ZenohConfig(listen=(ep,))) as s:
        poll = RingPoll(s, KEY, 16, window_s=0.2, on_sample=lambda smp: got.append(smp.payload.to_bytes()))
        pub = s.declare_publisher(KEY)
        stop, wake = threading.Event(), Wake()
        try:
            for i in range(5):
                pub.put(b"%d" % i)
            deadline = time.monotonic() + 5.0
            while len(got) < 5 and time.monotonic() < deadline:
                poll.wait(stop, 0.05)
            assert got == [b"0", b"1", b"2", b"3", b"4"] and poll.pull() == 0

            # within the window it spins until the sample comes
            poll.arm()
            threading.Timer(0.05, lambda: pub.put(b"late")).start()
            t0 = time.monotonic()
            assert poll.wait(stop, 1.0) is True and got[-1] == b"late"
            assert poll.spins > 0 and time.monotonic() - t0 < 0.2

            # outside it (the 0.2 s window over): the timeout, the loop's other wake-ups and
            # stop end the wait
            time.sleep(max(0.0, t0 + 0.25 - time.monotonic()))
            spins = poll.spins
            t0 = time.monotonic()
            assert poll.wait(stop, 0.05) is False and 0.04 < time.monotonic() - t0 < 1.0
            assert poll.spins == spins  # (no window armed: it looked every POLL_IDLE_S, no spin)
            wake.set()
            assert poll.wait(stop, 5.0, wake) is False
            stop.set()
            t0 = time.monotonic()
            assert poll.wait(stop, 5.0) is False and time.monotonic() - t0 < 0.5
        finally:
            pub.undeclare()
            poll.undeclare()
