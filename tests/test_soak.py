"""The soak bench's memory figures: RSS and anonymous memory per process, growth from the first row."""

from __future__ import annotations

import math
import os
from pathlib import Path

from sumoco.bench.soak import heap_mb, rss_mb, soak_summary


def test_heap_is_part_of_rss_and_gone_processes_are_nan():
    rss, heap = rss_mb(os.getpid()), heap_mb(os.getpid())
    assert 0 < heap < rss
    assert math.isnan(rss_mb(2**22 + 7)) and math.isnan(heap_mb(2**22 + 7))


def test_summary_growth_is_from_the_first_row_and_flat_is_judged_on_rss(tmp_path: Path):
    def row(rec_rss, rec_heap):
        return {"rss_mb": {"record": rec_rss, "sumo": 150.0}, "heap_mb": {"record": rec_heap},
                "errors": 0, "steps": 10, "dropped_steps": 0}
    rows = [row(80.0, 30.0), row(90.0, 30.3), row(83.0, 30.6)]
    s = soak_summary(rows, {}, [], 120.0, tmp_path)
    g = s["growth"]["record"]
    assert g["after_min1_mb"] == 80.0 and g["peak_mb"] == 90.0 and g["growth_pct"] == 3.75
    assert g["heap_growth_pct"] == 2.0
    assert "sumo" not in s["growth"] and s["flat"] is True
    s = soak_summary([row(80.0, 30.0), row(85.0, 30.0)], {}, [], 120.0, tmp_path)
    assert s["growth"]["record"]["growth_pct"] == 6.25 and s["flat"] is False
