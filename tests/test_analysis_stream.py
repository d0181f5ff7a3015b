"""``sumoco report`` summarises a recording as a stream: the same numbers as the run held
in memory, percentiles within the histogram's stated precision, memory flat in length."""

from __future__ import annotations

import numpy as np

from sumoco.analysis.summary import ErrorHistogram, analyse_recording, load_run, summarise
from sumoco.recording.record import open_recording, read_recording
from sumoco.bench.record import synthetic_recording


def test_histogram_percentiles_within_their_precision():
    rng = np.random.default_rng(3)
    for e in (rng.exponential(0.2, 50_000), rng.uniform(0, 3, 7), np.array([0.0, 0.0, 1e-7, 5.0])):
        h = ErrorHistogram()
        for part in np.array_split(e, 5):
            h.add(part)
        s = h.stats()
        assert s["samples"] == len(e) and s["max"] == round(e.max(), 4)
        assert abs(s["mean"] - e.mean()) < 1e-4
        for q in (50, 95):
            exact = np.percentile(e, q)
            assert abs(h.percentile(q) - exact) <= 0.0011 * exact + ErrorHistogram.LO, q
    assert ErrorHistogram().stats()["samples"] == 0


def test_streamed_summary_equals_the_in_memory_one_across_windows(tmp_path):
    path = tmp_path / "s.mcap"
    synthetic_recording(path, 60, 23.0, physics_hz=20.0)
    streamed, fig = analyse_recording(open_recording(path), window_s=2.0)  # many windows
    whole = summarise(load_run(read_recording(path)))
    assert streamed == whole
    assert streamed["steps"] == 230 and set(streamed["presets"]) == {"paper", "default"}
    p = streamed["presets"]["default"]
    assert p["error_m"]["overall"]["samples"] > 20_000 and p["error_m"]["overall"]["mean"] > 0.1
    assert p["error_m"]["at_samples"]["overall"]["samples"] > 10_000
    # the reference car's series: every physics sample of it, in time order
    s = fig.series["default"]
    assert len(s["t"]) > 400 and np.all(np.diff(s["t"]) > 0)
    assert len(fig.track["t"]) == 230
