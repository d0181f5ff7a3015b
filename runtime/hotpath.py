"""Process settings that keep per-step latency low in the daemons (called once at start-up).

glibc serves every allocation above its mmap threshold (128 KB at first, raised
dynamically) with a fresh ``mmap`` and returns it with ``munmap`` when freed; it also
trims the heap top back to the kernel. A step of 1,000 agents with paths is ~160 KB and
its arrays (paths: ~190 KB each) are exactly that size, so every encode and decode paid
page faults on freshly mapped, zeroed pages: back to back (a lockstep run that never
waits), one encode at 1,000 agents with paths took 160 us instead of 70 us. A fixed,
higher threshold keeps these buffers on the heap and reused (at most 64 MB of free heap
stay with the process). After a pause between steps the cost of a step's encode and
decode is dominated by cold caches instead, where this makes no measurable difference.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging
import os
import threading

log = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8
#: [arenas] for the long-running observers: glibc makes up to 8 x cores arenas, one per thread
#: that contends; each keeps its own high-water mark (``MALLOC_ARENA_MAX`` does the same)
OBSERVER_ARENAS = 2
MMAP_THRESHOLD = 16 << 20  # [bytes] larger blocks still get their own mapping (glibc max: 32 MB)
TRIM_THRESHOLD = 64 << 20  # [bytes] free heap top kept before it goes back to the kernel


def tune_allocator(mmap_threshold: int = MMAP_THRESHOLD, trim_threshold: int = TRIM_THRESHOLD) -> bool:
    """Raise glibc's mmap and trim thresholds; False (and nothing changed) without glibc."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    ok = bool(mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold))) and bool(mallopt(_M_TRIM_THRESHOLD, int(trim_threshold)))
    if not ok:
        log.debug("mallopt refused the thresholds: allocator left as it is")
    return ok


def _libc():
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None


def limit_arenas(arenas: int = OBSERVER_ARENAS) -> bool:
    """At most ``arenas`` glibc malloc arenas (call before threads start); False without glibc.

    The recorder allocates from Zenoh's threads, its writer and its scene worker: with one
    arena each, the freed memory of every burst stays spread over arenas that ``malloc_trim``
    returns only in part. ``MALLOC_ARENA_MAX`` in the environment wins when set."""

    libc = _libc()
    if libc is None or os.environ.get("MALLOC_ARENA_MAX"):
        return False
    return bool(libc.mallopt(_M_ARENA_MAX, int(arenas)))


def start_heap_trimmer(period_s: float = 30.0) -> threading.Event | None:
    """Hand freed heap back to the kernel every ``period_s`` (glibc ``malloc_trim``).

    For the long-running observers (recorder, viewer): they allocate in bursts from several
    threads (Zenoh callbacks, writer, scene worker), and glibc keeps each thread arena's
    high-water mark, so their RSS creeps up to the busiest moment of the run and stays
    there. Returns the event that stops the thread; None without glibc."""
    libc = _libc()
    trim = getattr(libc, "malloc_trim", None) if libc is not None else None
    if trim is None:
        return None
    stop = threading.Event()

    def loop() -> None:
        while not stop.wait(period_s):
            trim(0)

    threading.Thread(target=loop, name="heap-trim", daemon=True).start()
    return stop


def freeze_startup_objects() -> None:
    """Move every object alive now (modules, configuration, models) out of the cyclic
    collector's generations, so that collections during the run scan only what the run
    allocates: a full collection over start-up objects is a latency spike at p99."""
    gc.collect()
    gc.freeze()


__all__ = ["freeze_startup_objects", "limit_arenas", "start_heap_trimmer", "tune_allocator"]
