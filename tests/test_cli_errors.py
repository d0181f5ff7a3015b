"""Bad input to the command line ends in one line and exit code 2, never a traceback."""

from __future__ import annotations

import socket
import subprocess
import sys

from tests.harness import ROOT


def _sumoco(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sumoco.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT)


def test_non_utf8_toml_negative_duration_and_a_taken_port_are_one_line_errors(tmp_path):
    bad = tmp_path / "latin1.toml"
    bad.write_bytes('[run]\nid = "caf\xe9"\n'.encode("latin-1"))
    r = _sumoco("sumo", "--config", str(bad))
    assert r.returncode == 2 and "not UTF-8" in r.stderr and "Traceback" not in r.stderr, r.stderr
    r = _sumoco("sumo", "--config", str(ROOT / "configs" / "demo.toml"), "--duration", "-5")
    assert r.returncode == 2 and "run.duration_s: expected >= 0" in r.stderr, r.stderr
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = _sumoco("view", "--run", "x", "--port", str(port), "--quiet", timeout=60)
    assert r.returncode == 2 and "choose another --port" in r.stderr and "Traceback" not in r.stderr, r.stderr
