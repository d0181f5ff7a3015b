"""A short run of the coverage-guided decoder fuzzer (the long one is `make fuzz`)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

FUZZER = Path(__file__).with_name("fuzz_protocol.py")


def test_decoder_survives_a_short_fuzzing_run(tmp_path):
    r = subprocess.run(
        [sys.executable, str(FUZZER), "--seconds", "12", "--corpus", str(tmp_path / "corpus"), "--rss-mb", "1024"],
        capture_output=True, text=True, timeout=120,
    )
    out = r.stdout + r.stderr
    assert r.returncode == 0, out[-4000:]
    runs = int(re.search(r"stat::number_of_executed_units:\s+(\d+)", out).group(1))
    assert runs > 2_000, out[-2000:]  # it really fuzzed (~3,000 inputs/s on one core)
    assert not list(tmp_path.glob("fuzz-*")), "no crash or leak artifacts"
