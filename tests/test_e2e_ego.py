"""The ego loop over loopback: an outside client (examples/python_client, its own process)
publishes ego poses at 20 Hz; the SUMO side moves its ego there and SUMO traffic reacts;
the physics side shows the ego as EXTERNAL without controlling it."""

from __future__ import annotations

import signal
import subprocess
import sys

import numpy as np
import pytest

from protocol.keys import Keys
from protocol.messages import AgentFlag, AgentMode
from tests.harness import ROOT, Daemon, Probe, endpoint, wait_until
from tests.sumo_testnet import make_testnet

pytestmark = pytest.mark.integration

EGO_LANE = "A0B0_2"  # left lane eastbound in the test net; v0 drives it first


def test_ego_stops_traffic_is_held_removed_and_comes_back(tmp_path):
    cfg = tmp_path / "ego.toml"
    cfg.write_text(f"""
[run]
id = "egorun"
[sumo]
sumocfg = "{make_testnet(tmp_path / 'net')}"
ego_hold_s = 0.3
ego_timeout_s = 2.0
# SUMO's one-step lane change: with continuous ones (3 s) v0 was seen passing through the
# standing ego (gap -6.2 m) -- an open question for the lane-change work, not this test's
lanechange_duration_s = 0.0
[physics]
preset = "default"
""")
    keys = Keys("sumoco", "egorun")
    sumo_ep, phys_ep = endpoint(), endpoint()
    sumo = Daemon("sumo", ["sumo", "--config", str(cfg), "--listen", sumo_ep], tmp_path / "logs")
    phys = Daemon("physics", ["physics", "--config", str(cfg), "--listen", phys_ep, "--connect", sumo_ep,
                              "--quiet"], tmp_path / "logs")
    probe = Probe(keys, [sumo_ep, phys_ep])
    client = None
    try:
        wait_until(lambda: probe.last_physics() is not None, 60, "both daemons up", procs=[sumo, phys])
        # Stand at 60 m along the lane. The poses stop when the test ends this client (not at a
        # wall-clock time of the client's: under load SUMO's realtime pacing lags, and a pause
        # at a fixed wall time could come before v0 had reached the ego).
        def start_client(duration_s: float) -> subprocess.Popen:
            return subprocess.Popen(
                [sys.executable, str(ROOT / "examples" / "python_client" / "client.py"),
                 "--connect", sumo_ep, "--run", "egorun", "--duration", str(duration_s), "--ego-id", "ego",
                 "--ego-lane", EGO_LANE, "--ego-start", "60", "--ego-speed", "0", "--ego-rate", "20"],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            )
        client = start_client(120)
        step_has_ego = lambda: (m := probe.last_step()) is not None and "ego" in m.agents.ids  # noqa: E731
        wait_until(step_has_ego, 20, "the ego in SUMO's steps", procs=[sumo])
        m = probe.last_step()
        i = m.agents.ids.index("ego")
        assert m.agents.flags[i] & AgentFlag.EGO
        ego_x, ego_y = float(m.agents.x[i]), float(m.agents.y[i])

        # The ego appears in physics state, placed (EXTERNAL), not controlled.
        def ego_in_physics():
            st = probe.last_physics()
            return st is not None and "ego" in st.agents.ids and st
        st = wait_until(ego_in_physics, 10, "the ego in physics state", procs=[phys])
        j = st.agents.ids.index("ego")
        assert st.agents.mode[j] == AgentMode.EXTERNAL
        assert np.hypot(st.agents.x[j] - ego_x, st.agents.y[j] - ego_y) < 0.5

        # v0 comes up behind the standing ego and stops there, in its lane, no collision.
        def v0_stopped_behind():
            m = probe.last_step()
            if m is None or "v0" not in m.agents.ids or "ego" not in m.agents.ids:
                return False
            k = m.agents.ids.index("v0")
            return abs(m.agents.y[k] - ego_y) < 0.2 and m.agents.speed[k] < 0.05 and m
        m = wait_until(v0_stopped_behind, 40, "v0 to stop behind the ego", procs=[sumo])
        k = m.agents.ids.index("v0")
        gap = ego_x - float(m.agents.x[k]) - 5.0  # ego length 5 m (SUMO default type)
        assert 0.0 < gap < 5.0, f"v0 stopped {gap:.2f} m behind the ego's rear"

        # Publishing stops: held, then removed after ego_timeout_s, with a log line.
        client.terminate()
        assert client.wait(10) == -signal.SIGTERM
        wait_until(lambda: (m := probe.last_step()) is not None and "ego" not in m.agents.ids, 12,
                   "the ego to be removed after the timeout", procs=[sumo])
        assert "ego" in sumo.log.read_text() and "remov" in sumo.log.read_text().lower()
        # Publishing resumes (a new client, the same ego id): the ego comes back.
        client = start_client(6)
        wait_until(step_has_ego, 12, "the ego to come back when poses resume", procs=[sumo])
        out, err = client.communicate(timeout=30)
        assert client.returncode == 0, err
        assert sumo.poll() is None and phys.poll() is None
    finally:
        if client is not None and client.poll() is None:
            client.kill()
        probe.close()
        codes = {"sumo": sumo.terminate(5)}
        codes["physics"] = phys.leave(10)  # it leaves after SUMO's final step
    assert codes == {"sumo": 0, "physics": 0}
