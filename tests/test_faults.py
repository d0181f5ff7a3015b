"""Faults with nothing lost: killed, stopped and restarted daemons, a full disk.

Real processes over loopback Zenoh in lockstep (the timing where a lost peer matters most):
(a) a physics instance killed with SIGKILL and restarted rejoins: the SUMO side waits for
    it and sends it the step it missed, the new process queries the static data again, and
    it holds SUMO's agents again; no step index is skipped;
(b) the SUMO side killed with SIGKILL: physics keeps its agents (braking to rest), stays
    announced through its liveliness token and resumes under a new SUMO side of the same
    run id;
(c) a physics instance stopped (SIGSTOP) longer than the lockstep timeout: the run ends
    with a clear message and the recording is complete and readable up to that step;
(d) a full disk under the recorder: a clear error and a complete file (a small tmpfs
    mounted by the test; needs root, as on the development machines and in CI).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import uuid
from pathlib import Path

import msgpack
import numpy as np
import pytest

from protocol.codec import decode
from protocol.keys import Keys
from protocol.messages import AgentFlag, AgentMode
from sumoco.recording.record import open_recording
from tests.harness import PAPER_CFG, Daemon, Probe, assert_exit_codes, endpoint, wait_until

pytestmark = pytest.mark.integration


def _config(tmp_path: Path, run: str, timeout_s: float, duration: float = 0.0) -> str:
    p = tmp_path / f"{run}.toml"
    p.write_text(f"""
[run]
id = "{run}"
timing = "lockstep"
duration_s = {duration}
lockstep_timeout_s = {timeout_s}
[sumo]
sumocfg = "{PAPER_CFG}"
lockstep_instances = ["main"]
[physics]
preset = "default"
""")
    return str(p)


class Run:
    def __init__(self, tmp_path: Path, run: str, timeout_s: float, duration: float = 0.0) -> None:
        self.tmp = tmp_path
        self.cfg = _config(tmp_path, run, timeout_s, duration)
        self.keys = Keys("sumoco", run)
        self.sumo_ep, self.phys_ep = endpoint(), endpoint()
        self.daemons: list[Daemon] = []
        self.probe = Probe(self.keys, [self.sumo_ep, self.phys_ep])
        self.sumo = self.start_sumo()
        self.physics = self.start_physics()
        wait_until(lambda: self.probe.last_step() is not None and self.probe.last_physics() is not None,
                   60, "steps and physics states at the probe", procs=[self.sumo, self.physics])

    def start_sumo(self, name: str = "sumo") -> Daemon:
        d = Daemon(name, ["sumo", "--config", self.cfg, "--listen", self.sumo_ep, "--connect", self.phys_ep,
                          "--quiet"], self.tmp / "logs")
        self.daemons.append(d)
        return d

    def start_physics(self, name: str = "physics") -> Daemon:
        d = Daemon(name, ["physics", "--config", self.cfg, "--listen", self.phys_ep, "--connect", self.sumo_ep,
                          "--quiet"], self.tmp / "logs")
        self.daemons.append(d)
        return d

    def status(self) -> dict | None:
        for r in self.probe.session.get(self.keys.sumo_status, timeout=3.0):
            if r.ok is not None:
                return msgpack.unpackb(r.ok.payload.to_bytes(), raw=False)["counters"]
        return None

    def stop(self) -> None:
        """SIGTERM to every daemon still running, SUMO sides first (in lockstep a SUMO side
        would otherwise wait for the acknowledgements of a physics instance that is gone)."""
        for d in sorted(self.daemons, key=lambda d: not d.name.startswith("sumo")):
            if d.poll() is None:
                try:
                    os.kill(d.proc.pid, signal.SIGCONT)  # a stopped process cannot handle SIGTERM
                except ProcessLookupError:
                    pass
            d.terminate(15)

    def close(self) -> None:
        self.stop()
        self.probe.close()


@pytest.fixture
def runs():
    made: list[Run] = []
    yield lambda *a, **k: made.append(Run(*a, **k)) or made[-1]
    for r in made:
        r.close()


def _holds_sumo_agents(probe: Probe, min_agents: int = 3) -> bool:
    st = probe.last_physics()
    if st is None:
        return False
    with probe.lock:
        ref = next((m for m in reversed(probe.steps) if m.step == st.sumo_step), None)
    if ref is None:
        return False
    riding = {i for i, f in zip(ref.agents.ids, ref.agents.flags) if f & AgentFlag.INSIDE_VEHICLE}
    return set(ref.agents.ids) - riding == set(st.agents.ids) - riding and st.agents.n >= min_agents


def test_a_killed_physics_instance_restarts_rejoins_and_catches_up(tmp_path, runs):
    r = runs(tmp_path, "fa", timeout_s=30.0)
    p = r.probe
    wait_until(lambda: p.last_physics().agents.n > 3 and p.last_step().step > 30, 60,
               "physics with agents", procs=[r.physics])
    r.physics.kill()  # SIGKILL: no goodbye
    k_kill = p.last_step().step
    # lockstep holds: SUMO waits for its instance instead of running on or giving up
    wait_until(lambda: r.keys.physics_alive not in p.alive, 10, "the killed instance's token to go")
    assert r.sumo.poll() is None
    with p.lock:
        p.physics.clear()
    restarted = r.start_physics("physics2")
    wait_until(lambda: p.last_step().step > k_kill + 50, 60, "lockstep to go on with the restarted instance",
               procs=[r.sumo, restarted])
    wait_until(lambda: _holds_sumo_agents(p), 30, "the restarted instance to hold SUMO's agents",
               procs=[r.sumo, restarted])
    st = p.last_physics()
    assert st.counters["rejected"] == 0
    # the new process knew no static data: it asked the SUMO side for it (its counters start
    # at zero, and the probe kept only its states), and the answer ended the asking
    assert st.counters["static_queries"] >= 1, st.counters
    asked = st.counters["static_queries"]
    k_asked = p.last_step().step
    wait_until(lambda: p.last_step().step > k_asked + 30, 30, "more lockstep steps", procs=[r.sumo, restarted])
    assert p.last_physics().counters["static_queries"] <= asked + 1, "static data asked for again and again"
    assert wait_until(r.status, 10, "SUMO status")["rejoined"] == 1
    with p.lock:
        seen = {m.step for m in p.steps}
    assert seen >= set(range(min(seen), max(seen) + 1)), "a step index was skipped"
    r.stop()
    assert_exit_codes(r.daemons)  # sumo and the restarted instance 0 after SIGTERM, the killed one -9


def test_b_killed_sumo_side_physics_holds_then_resumes_with_a_new_one(tmp_path, runs):
    r = runs(tmp_path, "fb", timeout_s=30.0)
    p = r.probe
    wait_until(lambda: (st := p.last_physics()) is not None and (st.agents.speed > 2).sum() >= 2, 60,
               "moving physics agents", procs=[r.physics])
    r.sumo.kill()
    wait_until(lambda: r.keys.sumo_alive not in p.alive, 10, "the SUMO token to go")

    def all_stopping():
        st = p.last_physics()
        return st is not None and st.agents.n > 0 and bool(np.all(st.agents.mode == AgentMode.STOPPING))
    wait_until(all_stopping, 15, "physics to keep its agents, braking (mode STOPPING)", procs=[r.physics])
    kept = set(p.last_physics().agents.ids)
    wait_until(lambda: float(np.percentile(np.abs(p.last_physics().agents.speed), 90)) < 0.5, 30,
               "agents (nine in ten) at rest", procs=[r.physics])
    assert set(p.last_physics().agents.ids) == kept  # the last state is held, nobody dropped
    tick = p.last_physics().tick
    wait_until(lambda: p.last_physics().tick > tick, 5, "states to keep coming while SUMO is away")
    assert r.keys.physics_alive in p.alive and r.physics.poll() is None  # still announced
    with p.lock:
        p.steps.clear()
    sumo2 = r.start_sumo("sumo2")  # same run id: physics resynchronises to the new run
    wait_until(lambda: len(p.steps) > 50, 60, "the new SUMO side's steps (lockstep: physics acks them)",
               procs=[sumo2, r.physics])
    wait_until(lambda: (st := p.last_physics()) is not None and st.sumo_step < 300 and st.agents.n > 0
               and bool(np.all(st.agents.mode != AgentMode.STOPPING)), 30, "physics to follow the new run",
               procs=[r.physics])
    assert p.last_physics().counters["rejected"] == 0
    r.stop()
    assert_exit_codes(r.daemons)  # physics and the new SUMO side 0 after SIGTERM, the killed one -9


def test_c_a_stopped_peer_ends_the_run_cleanly_and_the_recording_is_complete(tmp_path, runs):
    r = runs(tmp_path, "fc", timeout_s=8.0)  # well below Zenoh's 10 s lease: the stopped peer stays "alive"
    out = tmp_path / "run.mcap"
    rec = Daemon("record", ["record", "--config", r.cfg, "--connect", r.sumo_ep, "--connect", r.phys_ep,
                            "--out", str(out)], tmp_path / "logs")
    r.daemons.append(rec)
    p = r.probe
    # the recorder is slow to start under load: count steps from when it says it records
    wait_until(lambda: "recording " in rec.log.read_text(), 60, "the recorder to subscribe", procs=[rec])
    k_rec = p.last_step().step
    wait_until(lambda: p.last_step().step > k_rec + 60, 60, "the run to be under way with the recorder",
               procs=[r.sumo, r.physics, rec])
    os.kill(r.physics.proc.pid, signal.SIGSTOP)
    try:
        code = r.sumo.proc.wait(60)
    finally:
        os.kill(r.physics.proc.pid, signal.SIGCONT)
    last = p.last_step().step
    assert code == 1
    assert (f"no acknowledgement of step {last} from physics instance(s) main within 8 s"
            in r.sumo.log.read_text()), r.sumo.tail()
    assert "main is alive but silent" in r.sumo.log.read_text(), r.sumo.tail()
    assert rec.terminate(20) == 0, rec.tail()
    assert r.physics.terminate(20) == 0, r.physics.tail()
    recording = open_recording(out)
    steps = sorted(decode(m.data).step for m in recording.messages if m.topic == r.keys.step)
    assert not recording.truncated, recording.error
    # every step from the recorder's first to the one SUMO stopped at, each once
    assert steps == list(range(steps[0], last + 1)), f"recorded {steps[:3]}..{steps[-3:]}, SUMO stopped at {last}"
    assert len(steps) > 10


def _mount_tmpfs(where: Path, size_mb: int) -> None:
    where.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", f"sumoco-test-{uuid.uuid4().hex[:8]}",
                        str(where)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.fail(f"this test mounts a small tmpfs and needs root: mount said {r.stderr.strip()!r}")


def test_d_a_full_disk_stops_the_recorder_with_a_clear_error_and_a_complete_file(tmp_path):
    disk = tmp_path / "small"
    _mount_tmpfs(disk, 16)
    feed = None
    try:
        (disk / "filler").write_bytes(b"\0" * (10 << 20))  # 6 MiB left, 4 MiB of them the reserve
        ep = endpoint()
        feed = subprocess.Popen([sys.executable, "-m", "synthetic.feed", "--listen", ep, "--run", "fd",
                                 "--agents", "1000", "--hz", "20"], stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        out = disk / "run.mcap"
        rec = subprocess.run([sys.executable, "-m", "sumoco.cli", "record", "--connect", ep, "--run", "fd",
                              "--duration", "60", "--out", str(out), "--quiet"],
                             capture_output=True, text=True, timeout=90)
        assert rec.returncode == 1, rec.stderr
        lines = [ln for ln in rec.stderr.splitlines() if ln.startswith("sumoco record:")]
        assert len(lines) == 1 and "disk nearly full" in lines[0] and "Traceback" not in rec.stderr, rec.stderr
        recording = open_recording(out)
        steps = [decode(m.data).step for m in recording.messages if m.topic.endswith("/sumo/step")]
        assert not recording.truncated, recording.error
        assert len(steps) > 5 and steps == sorted(steps)
    finally:
        if feed is not None:
            feed.kill()
            feed.wait(5)
        subprocess.run(["umount", str(disk)], check=True)
