"""The whole system over loopback: real SUMO and physics processes, real Zenoh, real MuJoCo.

Each test starts its own daemons (so kills in one cannot leak into another) and a probe
session that decodes everything of the run.
"""

from __future__ import annotations

import json
import subprocess
import sys

import msgpack
import numpy as np
import pytest

from protocol.codec import decode, encode
from protocol.keys import Keys
from protocol.messages import AgentFlag, AgentMode, StepAck
from tests.harness import PAPER_CFG, ROOT, Daemon, Probe, endpoint, wait_until

pytestmark = pytest.mark.integration


def _config(tmp_path, timing="realtime", duration=0.0, extra="") -> str:
    p = tmp_path / "run.toml"
    p.write_text(f"""
[run]
id = "e2e"
timing = "{timing}"
duration_s = {duration}
lockstep_timeout_s = 20.0
[sumo]
sumocfg = "{PAPER_CFG}"
[physics]
preset = "default"
{extra}
""")
    return str(p)


class System:
    """SUMO side + one physics instance + probe, all torn down at the end."""

    def __init__(self, tmp_path, timing="realtime", duration=0.0):
        self.tmp = tmp_path
        self.cfg = _config(tmp_path, timing, duration)
        self.keys = Keys("sumoco", "e2e")
        self.sumo_ep = endpoint()
        self.phys_ep = endpoint()
        self.daemons: list[Daemon] = []
        self.probe = Probe(self.keys, [self.sumo_ep, self.phys_ep])
        self.sumo = self.start_sumo()
        self.physics = self.start_physics()
        # The probe's links come up in the background (Zenoh retries connects): start the
        # tests only once both kinds of message reach it.
        wait_until(lambda: self.probe.last_step() is not None and self.probe.last_physics() is not None,
                   60, "steps and physics states at the probe", procs=[self.sumo, self.physics])

    def start_sumo(self, name="sumo") -> Daemon:
        d = Daemon(name, ["sumo", "--config", self.cfg, "--listen", self.sumo_ep, "--quiet"], self.tmp / "logs")
        self.daemons.append(d)
        return d

    def start_physics(self, name="physics") -> Daemon:
        d = Daemon(name, ["physics", "--config", self.cfg, "--listen", self.phys_ep,
                          "--connect", self.sumo_ep, "--quiet"], self.tmp / "logs")
        self.daemons.append(d)
        return d

    def close(self) -> dict[str, int]:
        """Stop everything; exit codes of the daemons not killed on purpose."""
        # SUMO first: its final step lets the physics side leave by itself
        codes = {d.name: d.terminate(5) for d in self.daemons if d.name.startswith("sumo")}
        codes.update({d.name: d.leave(10) for d in self.daemons if not d.name.startswith("sumo")})
        self.probe.close()
        return {n: c for n, c in codes.items() if not next(d for d in self.daemons if d.name == n).killed}


@pytest.fixture
def system(tmp_path):
    s = System(tmp_path)
    yield s
    codes = s.close()
    assert codes and all(c == 0 for c in codes.values()), codes


def _steps_by_index(probe):
    with probe.lock:
        return {m.step: m for m in probe.steps}


def test_agents_appear_within_one_step_and_leave(system):
    p = system.probe
    wait_until(lambda: (m := p.last_physics()) is not None and m.sumo_step > 200, 60,
               "physics state past SUMO step 200 (ref leaves at ~187)", procs=[system.sumo, system.physics])
    steps = _steps_by_index(p)
    with p.lock:
        states = list(p.physics["main"])
    checked = 0
    for st in states:
        ref = steps.get(st.sumo_step)
        if ref is None or st.sumo_step < 1:
            continue
        riding = {i for i, f in zip(ref.agents.ids, ref.agents.flags) if f & AgentFlag.INSIDE_VEHICLE}
        want = set(ref.agents.ids) - riding
        got = set(st.agents.ids)
        assert want <= got, f"step {st.sumo_step}: missing in physics {sorted(want - got)}"
        assert got - riding <= want, f"step {st.sumo_step}: stale in physics {sorted(got - want)}"
        checked += 1
    assert checked > 100
    seen = {i for m in steps.values() for i in m.agents.ids}
    now = set(steps[max(steps)].agents.ids)
    assert seen - now, "no agent left the network in the window; the test proves nothing"


def test_traffic_lights_pass_through_unchanged(tmp_path):
    """The states on the wire equal an in-process libsumo run of the same scenario."""
    import libsumo

    system = System(tmp_path, timing="lockstep")  # lockstep: 45 s of signal plan in a few seconds
    try:
        p = system.probe
        wait_until(lambda: len(p.steps) > 450, 90, "450 steps", procs=[system.sumo, system.physics])
        steps = _steps_by_index(p)
    finally:
        codes = system.close()
    assert codes == {"sumo": 0, "physics": 0}
    libsumo.start(["sumo", "-c", str(PAPER_CFG), "--step-length", "0.1", "--seed", "42",
                   "--no-step-log", "true"])
    try:
        tl = libsumo.trafficlight.getIDList()[0]
        compared = changed = 0
        last = None
        for k in range(max(steps) + 1):
            libsumo.simulationStep()
            m = steps.get(k)
            if m is None:
                continue
            assert abs(m.time - libsumo.simulation.getTime()) < 1e-6
            i = m.tls.ids.index(tl)
            assert m.tls.state[i] == libsumo.trafficlight.getRedYellowGreenState(tl)
            assert m.tls.phase[i] == libsumo.trafficlight.getPhase(tl)
            compared += 1
            changed += last is not None and last != m.tls.state[i]
            last = m.tls.state[i]
    finally:
        libsumo.close()
    assert compared > 400 and changed >= 1


def test_killing_physics_leaves_sumo_running_and_restart_catches_up(system):
    p = system.probe
    wait_until(lambda: p.last_physics() is not None and p.last_physics().agents.n > 3, 60,
               "physics with agents", procs=[system.physics])
    system.physics.kill()
    k0 = p.last_step().step
    wait_until(lambda: p.last_step().step > k0 + 20, 20, "SUMO to keep stepping", procs=[system.sumo])
    assert system.sumo.poll() is None
    with p.lock:
        p.physics.clear()
    restarted = system.start_physics("physics2")

    def caught_up():
        st = p.last_physics()
        if st is None:
            return False
        ref = _steps_by_index(p).get(st.sumo_step)
        if ref is None:
            return False
        riding = {i for i, f in zip(ref.agents.ids, ref.agents.flags) if f & AgentFlag.INSIDE_VEHICLE}
        return set(ref.agents.ids) - riding == set(st.agents.ids) - riding and st.agents.n > 3
    wait_until(caught_up, 40, "restarted physics to hold SUMO's current agents", procs=[system.sumo, restarted])


def test_killing_sumo_stops_agents_and_resume_when_it_returns(system):
    p = system.probe
    wait_until(lambda: (st := p.last_physics()) is not None and (st.agents.speed > 2).sum() >= 2, 60,
               "moving physics agents", procs=[system.physics])
    old_epoch = p.last_step().epoch
    system.sumo.kill()
    wait_until(lambda: system.keys.sumo_alive not in p.alive, 10, "the SUMO token to drop")

    def all_stopping():
        st = p.last_physics()
        return st is not None and st.agents.n > 0 and bool(np.all(st.agents.mode == AgentMode.STOPPING))
    wait_until(all_stopping, 10, "physics agents in mode STOPPING", procs=[system.physics])
    wait_until(lambda: float(np.abs(p.last_physics().agents.speed).max()) < 0.5, 20,
               "agents to come to a stop", procs=[system.physics])
    assert system.physics.poll() is None
    with p.lock:
        p.steps.clear()
    system.start_sumo("sumo2")
    wait_until(lambda: len(p.steps) > 30, 40, "the new SUMO run's steps")
    wait_until(lambda: (st := p.last_physics()) is not None and st.agents.n > 0
               and bool(np.all(st.agents.mode != AgentMode.STOPPING)) and st.sumo_step < 200, 30,
               "physics to resume on the new SUMO run", procs=[system.physics])
    # the restart is visible: a newer epoch in every step of the new run (SPEC 3.1.1), and
    # physics reset its fleet for it once instead of reading a step that went backwards
    with p.lock:
        epochs = {m.epoch for m in p.steps}
    assert len(epochs) == 1 and epochs.pop() > old_epoch > 0
    c = p.last_physics().counters
    assert c["sumo_restarts"] == 1 and c["restarts"] == 1 and c["replayed_steps"] == 0, c
    assert "went back" not in system.physics.tail(400)


def test_late_joining_outside_client_gets_static_and_live_steps(system):
    p = system.probe
    wait_until(lambda: p.last_physics() is not None, 60, "physics up", procs=[system.physics])
    r = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "python_client" / "client.py"),
         "--connect", system.sumo_ep, "--run", "e2e", "--duration", "4"],
        capture_output=True, text=True, timeout=60,
    )
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    static = p.static()
    assert out["static"]["lanes"] == len(static.lanes.ids) > 10
    assert out["steps_received"] > 15 and out["steps_increasing"]
    # SPEC 3.1.1 with zenoh + msgpack only: the incarnation it followed and how late it joined
    assert out["epoch"] == p.last_step().epoch > 0 and out["sumo_restarts"] == 0 and out["steps_refused"] == 0
    assert out["missed_at_join"] > 0
    assert "main" in out["physics_instances"] and out["physics_states_received"] > 50
    assert out["rejected"] == 0


def _sumo_status(probe):
    for r in probe.session.get(probe.keys.sumo_status, timeout=3.0):
        if r.ok is not None:
            return msgpack.unpackb(r.ok.payload.to_bytes(), raw=False)["counters"]
    return None


def test_malformed_messages_on_every_input_key_are_rejected_and_change_nothing(system):
    p, keys = system.probe, system.keys
    wait_until(lambda: (st := p.last_physics()) is not None and st.agents.n > 3, 60,
               "physics with agents", procs=[system.physics])
    before_phys = p.last_physics().counters.get("rejected", 0)
    before_sumo = wait_until(lambda: _sumo_status(p), 10, "SUMO status")["rejected"]
    garbage = [b"\x00\x01garbage", msgpack.packb({"v": [1, 0], "kind": "step"}),
               msgpack.packb({"v": [9, 0], "kind": "ego"}), encode(StepAck("e2e", 1, 1))]
    for g in garbage:
        p.put(keys.step, g)  # physics side input
        p.put(keys.ego("ego"), g)  # SUMO side input
    wait_until(lambda: p.last_physics().counters.get("rejected", 0) >= before_phys + len(garbage), 10,
               "physics to count the rejected steps")
    wait_until(lambda: (c := _sumo_status(p)) is not None and c["rejected"] >= before_sumo + len(garbage), 10,
               "SUMO side to count the rejected ego messages")
    assert system.sumo.poll() is None and system.physics.poll() is None
    k = p.last_step().step
    wait_until(lambda: p.last_step().step > k + 10, 10, "SUMO to keep stepping")
    st = p.last_physics()
    assert "ego" not in st.agents.ids
    ref = _steps_by_index(p)[st.sumo_step]
    assert set(ref.agents.ids) >= set(st.agents.ids) - {"ego"}
