"""Failures a user meets, as real processes: one line, a documented exit code, no traceback.

- a missing or broken .sumocfg, or one SUMO cannot load: ``sumoco demo`` exits 2;
- SUMO failing mid-run: the SUMO side exits 1 with SUMO's message, its liveliness token
  goes (peers see it);
- a daemon killed by a signal: ``sumoco demo`` names the daemon and the signal, exits 2.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import uuid

import pytest

from protocol.keys import Keys
from tests.harness import ROOT, Daemon, Probe, endpoint, pids_with, sumo_steps, wait_until
from tests.sumo_testnet import make_testnet
from tests.test_sumo_scenario_options import BAD_ROUTES

pytestmark = pytest.mark.integration


def _demo(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "sumoco.cli", "demo", "--quiet", *args],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def _one_line(stderr: str) -> str:
    lines = [ln for ln in stderr.splitlines() if ln.startswith("sumoco demo:")]
    assert "Traceback" not in stderr, stderr[-2000:]
    assert len(lines) == 1, stderr[-2000:]
    return lines[0]


def test_missing_and_malformed_sumocfg_exit_2(tmp_path):
    r = _demo("--sumocfg", str(tmp_path / "nope.sumocfg"), "--out", str(tmp_path / "a"))
    assert r.returncode == 2
    assert "nope.sumocfg" in _one_line(r.stderr) and "not found" in r.stderr
    bad = tmp_path / "bad.sumocfg"
    bad.write_text("<configuration><input>")
    r = _demo("--sumocfg", str(bad), "--out", str(tmp_path / "b"))
    assert r.returncode == 2
    assert "bad.sumocfg" in _one_line(r.stderr) and "not well-formed" in r.stderr


def test_scenario_sumo_cannot_load_exits_2(tmp_path):
    cfg = tmp_path / "missing_net.sumocfg"
    cfg.write_text('<configuration><input><net-file value="no_such.net.xml"/></input></configuration>')
    r = _demo("--sumocfg", str(cfg), "--out", str(tmp_path / "out"), "--duration", "5")
    assert r.returncode == 2
    line = _one_line(r.stderr)
    assert "missing_net.sumocfg" in line and "no_such.net.xml" in line


def test_sumo_error_mid_run_exits_1_and_peers_see_it_leave(tmp_path):
    net = make_testnet(tmp_path / "net")
    (net.parent / "bad.rou.xml").write_text(BAD_ROUTES)
    cfg = net.parent / "bad.sumocfg"
    cfg.write_text(net.read_text().replace("routes.rou.xml", "bad.rou.xml")
                   .replace("</time>", '<route-steps value="1"/></time>'))
    run = f"err{uuid.uuid4().hex[:6]}"
    ep = endpoint()
    probe = Probe(Keys("sumoco", run), [ep])
    sumo = Daemon("sumo", ["sumo", "--sumocfg", str(cfg), "--run", run, "--listen", ep, "--timing", "realtime"],
                  tmp_path / "logs")
    try:
        wait_until(lambda: probe.keys.sumo_alive in probe.alive, 30, "the SUMO side's token", procs=[sumo])
        wait_until(lambda: sumo.poll() is not None, 30, "the SUMO side to end on SUMO's error")
        wait_until(lambda: probe.keys.sumo_alive not in probe.alive, 5, "the token to go")
    finally:
        code = sumo.terminate(5)
        probe.close()
    assert code == 1
    log = sumo.log.read_text()
    assert "Traceback" not in log
    last = [ln for ln in log.splitlines() if ln.startswith("sumoco sumo:")]
    assert len(last) == 1 and "NOPE" in last[0] and "SUMO failed" in last[0]
    assert probe.steps and probe.steps[-1].time == pytest.approx(4.0, abs=0.15)


def test_a_crashed_daemon_is_named_with_its_signal_exit_2(tmp_path):
    run = f"crash{uuid.uuid4().hex[:6]}"
    net = make_testnet(tmp_path / "net")
    out = tmp_path / "out"
    demo = subprocess.Popen(
        [sys.executable, "-m", "sumoco.cli", "demo", "--sumocfg", str(net), "--out", str(out),
         "--run", run, "--timing", "realtime", "--duration", "120"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )
    try:
        wait_until(lambda: (out / "logs" / "physics-default.log").is_file() and pids_with(run, "sumo"), 60,
                   "the SUMO side to start")
        wait_until(lambda: sumo_steps(out / "logs" / "sumo.log") >= 10, 60, "SUMO past step 10")
        for pid in pids_with(run, "sumo"):  # the SUMO side: `sumoco sumo ... --run <run>`
            os.kill(pid, signal.SIGSEGV)
        _, err = demo.communicate(timeout=60)
    finally:
        if demo.poll() is None:
            demo.kill()
    assert demo.returncode == 2
    line = _one_line(err)
    assert "sumo" in line and "SIGSEGV" in line
    assert (out / "summary.json").is_file()


def test_a_port_taken_between_choosing_and_listening_is_retried(tmp_path, monkeypatch):
    """The SUMO side's port is taken by someone else: the demo starts the daemons again."""
    import socket

    import sumoco.orchestrate.demo as demo_mod
    from runtime.config import load_common, replace, section

    blocker = socket.socket()
    blocker.bind(("127.0.0.1", 0))
    blocker.listen()
    taken = blocker.getsockname()[1]
    real = demo_mod.free_tcp_port
    calls = []

    def first_sumo_port_taken():
        calls.append(1)
        return taken if len(calls) == 2 else real()  # call 1: the hub, call 2: the SUMO side

    monkeypatch.setattr(demo_mod, "free_tcp_port", first_sumo_port_taken)
    config = ROOT / "configs" / "demo.toml"
    common, data, base = load_common(config)
    common = replace(common, run=replace(common.run, id=f"port{uuid.uuid4().hex[:6]}", duration_s=3.0))
    demo = replace(section(data, "demo", demo_mod.DemoConfig, base, str(config)), presets=("default",),
                   lad_sweep=False)
    try:
        summary = demo_mod.run_demo(config, tmp_path / "out", common, demo, quiet=True)
    finally:
        blocker.close()
    assert summary["daemons"]["exit_codes"] == {"sumo": 0, "physics-default": 0}
    assert summary["daemons"]["completed"] is True and summary["steps"] == 30
    assert len(calls) == 5  # hub, SUMO (taken), physics; then SUMO and physics again
