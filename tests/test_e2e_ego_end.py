"""A lockstep run with an ego ends cleanly: the step at the run's duration is marked final
whatever the ego does, every daemon leaves on it and exits 0 (before, SUMO published a step
past the duration, never marked one final, and waited out its lockstep timeout)."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from protocol.keys import Keys
from tests.harness import ROOT, Daemon, Probe, endpoint, wait_until
from tests.sumo_testnet import make_testnet

pytestmark = pytest.mark.integration

DURATION_S = 8.0


def test_lockstep_with_an_ego_marks_the_duration_step_final_and_everyone_exits(tmp_path):
    cfg = tmp_path / "end.toml"
    cfg.write_text(f"""
[run]
id = "egoend"
timing = "lockstep"
duration_s = {DURATION_S}
lockstep_timeout_s = 20.0
[sumo]
sumocfg = "{make_testnet(tmp_path / 'net')}"
[physics]
preset = "kinematic"
""")
    keys = Keys("sumoco", "egoend")
    sumo_ep, phys_ep = endpoint(), endpoint()
    phys = Daemon("physics", ["physics", "--config", str(cfg), "--listen", phys_ep, "--quiet"], tmp_path / "logs")
    probe = Probe(keys, [phys_ep])
    client = subprocess.Popen(
        [sys.executable, str(ROOT / "examples" / "python_client" / "client.py"), "--connect", phys_ep,
         "--run", "egoend", "--duration", "60", "--ego-id", "ego", "--ego-lane", "A0B0_2", "--ego-start", "60",
         "--ego-speed", "5", "--ego-rate", "20"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    sumo = None
    try:
        time.sleep(0.5)  # the client's first poses are out before SUMO's first step (not required)
        sumo = Daemon("sumo", ["sumo", "--config", str(cfg), "--listen", sumo_ep, "--connect", phys_ep, "--quiet"],
                      tmp_path / "logs")
        wait_until(lambda: (m := probe.last_step()) is not None and "ego" in m.agents.ids, 60,
                   "the ego in SUMO's steps", procs=[sumo, phys])
        t0 = time.monotonic()
        assert sumo.proc.wait(40) == 0, sumo.tail()
        ended_s = time.monotonic() - t0
        assert phys.proc.wait(20) == 0, phys.tail()
    finally:
        client.kill()
        probe.close()
        if sumo is not None and sumo.poll() is None:
            sumo.terminate(5)
        if phys.poll() is None:
            phys.terminate(5)
    with probe.lock:
        steps = list(probe.steps)
    last = max(steps, key=lambda m: m.step)
    assert last.final, "the last step is marked final"
    assert last.step == round(DURATION_S / last.step_length) - 1  # the duration's step, none past it
    assert "ego" in last.agents.ids  # the ego was still driving when the run ended
    del ended_s
    assert "no acknowledgement" not in sumo.log.read_text()  # no lockstep timeout waited out
