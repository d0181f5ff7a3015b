"""``Wake``: the main loop's wake-up flag, with ``threading.Event``'s semantics."""

from __future__ import annotations

import threading
import time

from runtime.transport import Wake


def test_wake_behaves_as_an_event():
    w = Wake()
    assert not w.is_set() and not w.wait(0.01) and not w.wait(0)
    w.set()
    w.set()  # setting twice is no error and no second token
    assert w.is_set() and w.wait(0) and w.wait(1.0) and w.is_set()  # wait does not clear
    w.clear()
    w.clear()
    assert not w.is_set() and not w.wait(0)


def test_wake_from_another_thread_wakes_a_blocked_wait():
    w = Wake()
    t = threading.Timer(0.05, w.set)
    t0 = time.monotonic()
    t.start()
    assert w.wait(5.0)
    assert time.monotonic() - t0 < 4.0
    t.join()


def test_no_wake_lost_between_wait_and_clear():
    # the daemons' loop: wait, clear, then look at the queue; a set from any thread after
    # the queue was filled must leave either the item visible or the flag set
    w, items, done = Wake(), [], threading.Event()

    def producer():
        for i in range(2_000):
            items.append(i)
            w.set()
        done.set()

    threading.Thread(target=producer).start()
    seen = 0
    deadline = time.monotonic() + 20.0
    while seen < 2_000 and time.monotonic() < deadline:
        if seen == len(items):
            w.wait(0.5)
            w.clear()
            continue
        seen += 1
    assert seen == 2_000 and done.wait(5.0)
