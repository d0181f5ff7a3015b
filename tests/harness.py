"""Shared helpers for integration tests: real daemon processes and a Zenoh probe.

Every wait is bounded; every process started here is killed at teardown.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import zenoh

from protocol.codec import decode
from protocol.errors import ProtocolError
from protocol.keys import Keys
from protocol.messages import PhysicsState, StaticData, StepMessage
from runtime.config import SecurityConfig, ZenohConfig
from runtime.transport import free_tcp_port, open_session

ROOT = Path(__file__).resolve().parents[1]
PAPER_CFG = ROOT / "configs" / "scenarios" / "paper" / "paper.sumocfg"


def scenario_pack() -> Path | None:
    """The scenario pack: ``shared/scenarios`` beside the repository (or beside a parent:
    worktrees), None when absent."""
    for base in (ROOT.parent, *ROOT.parent.parents):
        pack = base / "shared" / "scenarios"
        if (pack / "MANIFEST.md").is_file():
            return pack
    return None


def endpoint(port: int | None = None) -> str:
    return f"tcp/127.0.0.1:{port or free_tcp_port()}"


def wait_until(cond, timeout_s: float, what: str, poll_s: float = 0.02, procs=()):
    """Poll ``cond`` until truthy; fail with ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        v = cond()
        if v:
            return v
        for p in procs:
            if p.poll() is not None:
                raise AssertionError(f"{p.name} exited with {p.returncode} while waiting for {what}:\n{p.tail()}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(poll_s)


def pids_with(*args: str) -> list[int]:
    """Processes (other than this one) whose command line has every one of ``args`` as an
    argument: a run's daemons carry ``--run <id>``."""
    want = [a.encode() for a in args]
    pids = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                argv = f.read().split(b"\0")
        except OSError:
            continue
        if all(a in argv for a in want):
            pids.append(int(pid))
    return pids


def sumo_steps(log_file: Path) -> int:
    """The last step the SUMO side's status line reports in its log, 0 before the first."""
    try:
        found = re.findall(r"\bstep (\d+) t=", log_file.read_text(errors="replace"))
    except OSError:
        return 0
    return int(found[-1]) if found else 0


class Daemon:
    """A ``sumoco`` subcommand as a real OS process, output to a log file."""

    def __init__(self, name: str, args: list[str], log_dir: Path) -> None:
        self.name = name
        self.killed = False
        self.log = log_dir / f"{name}.log"
        log_dir.mkdir(parents=True, exist_ok=True)
        self._f = self.log.open("wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "sumoco.cli", *args],
            stdout=self._f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env=dict(os.environ, PYTHONUNBUFFERED="1"), cwd=ROOT,
        )

    @property
    def returncode(self):
        return self.proc.returncode

    def poll(self):
        return self.proc.poll()

    def tail(self, n: int = 40) -> str:
        try:
            return "\n".join(self.log.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""

    def terminate(self, timeout_s: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._f.close()
        return self.proc.returncode

    def leave(self, timeout_s: float = 10.0) -> int:
        """Wait for the process to end by itself (a physics side leaves after SUMO's final
        step), then ``terminate``; a SIGTERM during its own shutdown would kill it (-15)."""
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            pass
        return self.terminate()

    def kill(self) -> None:
        """SIGKILL on purpose (``killed`` tells teardown checks to expect -9)."""
        self.killed = True
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)


def assert_exit_codes(daemons, codes: dict[str, int] | None = None) -> None:
    """Every daemon ended with its expected exit code (README "Exit codes"): ``codes[name]``
    when given, -9 for one the test killed itself (``Daemon.kill``), else 0 (a clean end,
    also after SIGTERM). Call after they ended (``terminate``/``leave``); names them all."""
    wrong = []
    for d in daemons:
        want = (codes or {}).get(d.name, -9 if d.killed else 0)
        if d.returncode != want:
            wrong.append(f"{d.name} exited with {d.returncode}, expected {want}; its log ends:\n{d.tail()}")
    assert not wrong, "\n".join(wrong)


class Probe:
    """A Zenoh session in the test that decodes and keeps everything of one run."""

    def __init__(self, keys: Keys, connect: list[str], security: SecurityConfig | None = None,
                 role: str = "viewer", listen: str | None = None) -> None:
        self.keys = keys
        zcfg = ZenohConfig(listen=(listen or endpoint(),), connect=tuple(connect))
        if security is not None:
            zcfg = ZenohConfig(listen=zcfg.listen, connect=zcfg.connect, security=security)
        self.session = open_session(zcfg, role)
        self.lock = threading.Lock()
        self.steps: list[StepMessage] = []
        self.physics: dict[str, list[PhysicsState]] = {}
        self.alive: set[str] = set()
        self.bad = 0
        self._subs = [
            self.session.declare_subscriber(keys.step, self._on_step),
            self.session.declare_subscriber(keys.physics_state_all, self._on_physics),
            self.session.liveliness().declare_subscriber(f"{keys.base}/**", self._on_alive, history=True),
        ]

    def _decoded(self, s: zenoh.Sample):
        """The sample's message; None (counted in ``bad``) when it does not decode."""
        try:
            return decode(s.payload.to_bytes())
        except ProtocolError:
            self.bad += 1
            return None

    def _on_step(self, s: zenoh.Sample) -> None:
        m = self._decoded(s)
        if m is not None:
            with self.lock:
                self.steps.append(m)

    def _on_physics(self, s: zenoh.Sample) -> None:
        m = self._decoded(s)
        if m is not None:
            with self.lock:
                self.physics.setdefault(Keys.instance_of(str(s.key_expr)), []).append(m)

    def _on_alive(self, s: zenoh.Sample) -> None:
        with self.lock:
            if s.kind == zenoh.SampleKind.PUT:
                self.alive.add(str(s.key_expr))
            else:
                self.alive.discard(str(s.key_expr))

    def last_step(self) -> StepMessage | None:
        with self.lock:
            return self.steps[-1] if self.steps else None

    def last_physics(self, inst: str = "main") -> PhysicsState | None:
        with self.lock:
            lst = self.physics.get(inst)
            return lst[-1] if lst else None

    def static(self, timeout_s: float = 10.0) -> StaticData:
        def ask():
            for r in self.session.get(self.keys.static, timeout=2.0):
                if r.ok is not None:
                    return decode(r.ok.payload.to_bytes())
            return None
        return wait_until(ask, timeout_s, "static data from the queryable")

    def put(self, key: str, payload: bytes) -> None:
        self.session.put(key, payload)

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:
                pass
        self.session.close()


def paths_in(d, pre=()):
    """Every path (a tuple of keys and indexes) into a nested msgpack document of dicts and
    lists, the document's own ``()`` first: where a mutation test may edit it."""
    yield pre
    if isinstance(d, dict):
        for k, v in d.items():
            yield from paths_in(v, pre + (k,))
    elif isinstance(d, list):
        for i, v in enumerate(d):
            yield from paths_in(v, pre + (i,))
