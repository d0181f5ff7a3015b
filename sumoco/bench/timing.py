"""Timing helpers shared by the benchmark rows."""

from __future__ import annotations

import time

import numpy as np


def median_ms(fn, repeat: int) -> float:
    """Median wall time of ``fn`` over ``repeat`` calls [ms]: robust to the odd slow call a
    loaded host adds."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


__all__ = ["median_ms"]
