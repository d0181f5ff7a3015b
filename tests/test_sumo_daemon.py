"""The SUMO side daemon as a real OS process over loopback Zenoh.

A Zenoh session in the test connects to the daemon's endpoint and checks: step messages
with increasing indices and the scenario's agents, static data from the queryable, the
liveliness token, ego poses moving the ego, malformed messages counted and ignored,
lockstep waiting for acknowledgements (and failing cleanly when they stop), and exit
code 2 with the file named for a missing or broken scenario. Every wait is bounded.
"""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

from protocol.codec import decode, encode
from protocol.keys import Keys
from protocol.messages import AgentFlag, EgoPose, StaticData, StepAck, StepMessage
from runtime.config import ZenohConfig
from runtime.transport import free_tcp_port, open_session
from tests.sumo_testnet import EXPECTED_IDS, make_testnet

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[1]


class SumoProcess:
    """``sumoco sumo ...`` as a child process; output captured to a file."""

    def __init__(self, args: list[str], log: Path, env: dict | None = None) -> None:
        self.log = log
        self._f = log.open("wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "sumoco.cli", "sumo", *args],
            stdout=self._f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env=env or dict(os.environ, PYTHONUNBUFFERED="1"), cwd=ROOT,
        )

    def output(self) -> str:
        self._f.flush()
        return self.log.read_text(errors="replace")

    def wait(self, timeout: float) -> int:
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError(
                f"sumoco sumo did not exit within {timeout} s:\n{self.output()[-3000:]}"
            ) from None

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)
        self._f.close()


@pytest.fixture(scope="module")
def scenario(tmp_path_factory) -> Path:
    return make_testnet(tmp_path_factory.mktemp("daemonnet") / "net")


@pytest.fixture()
def procs():
    started: list[SumoProcess] = []
    yield started
    for p in started:
        p.kill()


def client(endpoint: str) -> zenoh.Session:
    return open_session(ZenohConfig(mode="peer", connect=(endpoint,), listen=()))


def collect_steps(session: zenoh.Session, keys: Keys):
    q: queue.Queue = queue.Queue()
    sub = session.declare_subscriber(keys.step, lambda s: q.put(s.payload.to_bytes()))
    return sub, q


def next_step(q: queue.Queue, proc: SumoProcess, timeout: float = 20.0) -> StepMessage:
    deadline = time.monotonic() + timeout
    while True:
        try:
            return decode(q.get(timeout=0.2))
        except queue.Empty:
            if proc.proc.poll() is not None:
                raise AssertionError(f"daemon exited ({proc.proc.returncode}):\n{proc.output()[-3000:]}") from None
            if time.monotonic() > deadline:
                raise AssertionError(f"no step message within {timeout} s:\n{proc.output()[-3000:]}") from None


def test_loopback_steps_static_ego_and_malformed(tmp_path, scenario, procs):
    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    toml = tmp_path / "run.toml"
    rel = os.path.relpath(scenario, tmp_path)
    toml.write_text(
        '[run]\nid = "loop"\nduration_s = 60.0\n\n'
        f'[sumo]\nsumocfg = "{rel}"  # relative to this file\nego_timeout_s = 30.0\n'
    )
    p = SumoProcess(["--config", str(toml), "--listen", ep], tmp_path / "sumo.log")
    procs.append(p)
    keys = Keys("sumoco", "loop")
    with client(ep) as s:
        sub, q = collect_steps(s, keys)
        first = next_step(q, p)
        steps = [first]
        seen: set[str] = set(first.agents.ids)
        while len(steps) < 25:
            m = next_step(q, p)
            steps.append(m)
            seen.update(m.agents.ids)
        idx = [m.step for m in steps]
        assert idx == list(range(idx[0], idx[0] + len(idx)))  # increasing, none lost
        assert all(abs(b.time - a.time - 0.1) < 1e-6 for a, b in zip(steps, steps[1:]))
        assert seen <= EXPECTED_IDS and {"v0", "p0", "bus0", "p1", "f0.0"} <= seen
        assert all(m.run == "loop" and m.step_length == pytest.approx(0.1) for m in steps)
        last = steps[-1]
        assert len(last.tls.ids) == 5 and len(last.agents.path_offsets) == last.agents.n + 1

        # static data from the queryable, one get
        replies = list(s.get(keys.static, timeout=10.0))
        assert len(replies) == 1 and replies[0].ok is not None
        st = decode(replies[0].ok.payload.to_bytes())
        assert isinstance(st, StaticData) and st.run == "loop"
        assert any(i.startswith(":") for i in st.lanes.ids) and len(st.tls_ids) == 5
        assert all(0 <= m.agents.lane.max() < len(st.lanes.ids) for m in steps if m.agents.n)

        # liveliness token
        alive = list(s.liveliness().get(keys.sumo_alive, timeout=5.0))
        assert len(alive) == 1

        # ego: poses published by us move the ego vehicle in SUMO
        pub = s.declare_publisher(keys.ego("ego"))
        x = 30.0
        ego_seen = []
        deadline = time.monotonic() + 20.0
        while len(ego_seen) < 10:
            assert time.monotonic() < deadline, p.output()[-3000:]
            pub.put(encode(EgoPose("ego", x, -1.6, 90.0, 5.0)))
            m = next_step(q, p)
            if "ego" in m.agents.ids:
                i = m.agents.ids.index("ego")
                assert m.agents.flags[i] & AgentFlag.EGO
                ego_seen.append((m.agents.x[i], m.agents.y[i]))
            x += 0.5
        # SUMO put it where we asked (the pose of the step before or this one)
        assert all(abs(ey - (-1.6)) < 1e-6 and 30.0 <= ex <= x for ex, ey in ego_seen)
        assert ego_seen[-1][0] > ego_seen[0][0]

        # malformed ego messages: counted, ignored, the daemon keeps stepping
        pub.put(b"\xc1 not msgpack")
        pub.put(encode(StepAck("loop", 1, 1)))  # valid message, wrong kind for this key
        before = next_step(q, p).step
        for _ in range(5):
            after = next_step(q, p).step
        assert after == before + 5
        pub.undeclare()
        sub.undeclare()

        # SIGTERM: clean exit 0, summary with the counters
        p.proc.send_signal(signal.SIGTERM)
        assert p.wait(20) == 0
        out = p.output()
        assert "rejected=2" in out and "ego_created=1" in out
        assert "ego_drift_max_m=0.0," in out  # keepRoute=2 puts the ego exactly there
        assert "rejected message on sumoco/loop/ego/ego" in out
        # liveliness token gone with the process
        assert list(s.liveliness().get(keys.sumo_alive, timeout=2.0)) == []


def test_lockstep_waits_for_acks_then_fails_cleanly(tmp_path, scenario, procs):
    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    toml = tmp_path / "lock.toml"
    toml.write_text(
        '[run]\nid = "lock"\ntiming = "lockstep"\nlockstep_timeout_s = 1.5\n\n'
        f'[sumo]\nsumocfg = "{scenario}"\nlockstep_instances = ["main"]\nlockstep_start_timeout_s = 20.0\n'
    )
    p = SumoProcess(["--config", str(toml), "--listen", ep], tmp_path / "lock.log")
    procs.append(p)
    keys = Keys("sumoco", "lock")
    with client(ep) as s:
        sub, q = collect_steps(s, keys)
        token = s.liveliness().declare_token(keys.physics_alive)  # we are physics "main"
        ack = s.declare_publisher(keys.ack)
        for k in range(4):
            m = next_step(q, p)
            assert m.step == k
            # SUMO must not publish step k+1 before we acknowledge step k
            with pytest.raises(queue.Empty):
                q.get(timeout=0.25 if k < 2 else 0.05)
            ack.put(encode(StepAck("lock", k, k)))
        assert next_step(q, p).step == 4
        # no ack for step 4: a clear error and a non-zero exit, not a hang
        t0 = time.monotonic()
        code = p.wait(20)
        assert code == 1 and time.monotonic() - t0 < 10
        assert "no acknowledgement of step 4 from physics instance(s) main within 1.5 s" in p.output()
        token.undeclare()
        sub.undeclare()


def test_bad_scenarios_exit_2_naming_the_file(tmp_path, procs):
    broken = tmp_path / "broken.sumocfg"
    broken.write_text("<configuration><input>")
    no_net = tmp_path / "nonet.sumocfg"
    no_net.write_text('<configuration><input><net-file value="missing.net.xml"/></input></configuration>')
    missing = tmp_path / "does-not-exist.sumocfg"
    bad_toml = tmp_path / "bad.toml"
    bad_toml.write_text('[sumo]\nsumocfg = "x.sumocfg"\nlad_min_m = "seven"\n')
    env_no_display = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    cases = [
        (["--sumocfg", str(missing)], None, [str(missing), "not found"]),
        (["--sumocfg", str(broken)], None, [str(broken), "not well-formed"]),
        (["--sumocfg", str(no_net)], None, [str(no_net), "could not load"]),
        (["--config", str(bad_toml)], None, [str(bad_toml), "sumo.lad_min_m", "expected a number"]),
        (["--sumocfg", str(broken), "--gui"], env_no_display, ["configuration error"]),
        ([], None, ["no SUMO scenario"]),
    ]
    running = []
    for i, (args, env, _) in enumerate(cases):
        p = SumoProcess(args + ["--listen", f"tcp/127.0.0.1:{free_tcp_port()}"], tmp_path / f"bad{i}.log", env)
        procs.append(p)
        running.append(p)
    for p, (args, _, needles) in zip(running, cases):
        assert p.wait(60) == 2, (args, p.output())
        out = p.output()
        for needle in needles:
            assert needle in out, (args, out)
    # with a well-formed config, --gui without a display says why
    ok_cfg = tmp_path / "gui.sumocfg"
    ok_cfg.write_text("<configuration/>")
    p = SumoProcess(["--sumocfg", str(ok_cfg), "--gui"], tmp_path / "gui.log", env_no_display)
    procs.append(p)
    assert p.wait(60) == 2 and "needs a display" in p.output()


def test_lockstep_ends_on_a_final_step_that_waits_for_its_ack(tmp_path, scenario, procs):
    """The scenario ends (end 1 s) before --duration (10 s): the last step says so, SUMO waits
    for its acknowledgement and exits 0."""
    short = tmp_path / "short.sumocfg"
    short.write_text(scenario.read_text().replace('<begin value="0"/>', '<begin value="0"/><end value="1"/>')
                     .replace('value="net.net.xml"', f'value="{scenario.parent / "net.net.xml"}"')
                     .replace('value="routes.rou.xml"', f'value="{scenario.parent / "routes.rou.xml"}"'))
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    toml = tmp_path / "final.toml"
    toml.write_text('[run]\nid = "fin"\ntiming = "lockstep"\nlockstep_timeout_s = 10.0\nduration_s = 10.0\n\n'
                    f'[sumo]\nsumocfg = "{short}"\nlockstep_instances = ["main"]\n')
    p = SumoProcess(["--config", str(toml), "--listen", ep], tmp_path / "final.log")
    procs.append(p)
    keys = Keys("sumoco", "fin")
    with client(ep) as s:
        sub, q = collect_steps(s, keys)
        token = s.liveliness().declare_token(keys.physics_alive)
        ack = s.declare_publisher(keys.ack)
        seen = []
        while not (seen and seen[-1].final):
            m = next_step(q, p)
            seen.append(m)
            if not m.final:
                ack.put(encode(StepAck("fin", m.step, m.step)))
        assert [m.step for m in seen] == list(range(10)) and seen[-1].time == pytest.approx(1.0)
        assert not any(m.final for m in seen[:-1])
        time.sleep(0.3)  # not acknowledged yet: SUMO must still be waiting for it
        assert p.proc.poll() is None
        ack.put(encode(StepAck("fin", seen[-1].step, 0)))
        assert p.wait(10) == 0
        assert "the scenario's end time 1 s reached" in p.output()
        token.undeclare()
        sub.undeclare()
