"""Process settings for long runs (``runtime.hotpath``)."""

from __future__ import annotations

import time

from runtime import hotpath


class _FakeLibc:
    def __init__(self) -> None:
        self.calls = 0

    def malloc_trim(self, pad: int) -> int:
        assert pad == 0
        self.calls += 1
        return 1


def test_heap_trimmer_trims_periodically_until_stopped(monkeypatch):
    fake = _FakeLibc()
    monkeypatch.setattr(hotpath, "_libc", lambda: fake)
    stop = hotpath.start_heap_trimmer(period_s=0.01)
    deadline = time.monotonic() + 5.0
    while fake.calls < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert fake.calls >= 3
    stop.set()
    time.sleep(0.05)  # the thread sees the event within one period
    n = fake.calls
    time.sleep(0.1)
    assert fake.calls == n


def test_heap_trimmer_is_a_no_op_without_glibc(monkeypatch):
    monkeypatch.setattr(hotpath, "_libc", lambda: None)
    assert hotpath.start_heap_trimmer() is None
