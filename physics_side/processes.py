"""``sumoco physics --processes N|auto``: one physics instance as N shard processes under a supervisor.

The supervisor is a small parent process without MuJoCo. It starts N children, each the
existing shard mode (``sumoco physics --shard i/N``, instance ``<instance>.<i>ofN``:
``shard.py`` splits the plane into tiles with a halo), relays their output line by line
with a ``[i/N]`` prefix, and watches them:

- A child that ends with 0 finished the run (its final step). The parent waits (bounded,
  ``FINISH_TIMEOUT_S``) for the others to finish too, then exits 0.
- A child that crashes (non-zero code, killed by a signal) is started again with the same
  ``--shard i/N`` after a back-off (``BACKOFF_FIRST_S`` doubling up to ``BACKOFF_MAX_S``).
  Meanwhile its siblings take over its tiles (they see its liveliness token go) and the
  SUMO side stops waiting for it; when it is back it takes its tiles back and the SUMO
  side waits for it again. Restarts are counted and logged.
- More than ``[physics] process_restarts`` failures of one child within
  ``RESTART_WINDOW_S``, or a child that ends with a usage error (exit 2: a restart cannot
  fix a configuration), stop every child; the parent prints one line naming the child and
  its code and exits ``ExitCode.PROCESS_FAILED`` (3), or 2 for the usage error.
- SIGINT / SIGTERM go to every child (SIGTERM); children still running after
  ``STOP_TIMEOUT_S`` are killed. Children get SIGTERM from the kernel if the parent dies.

``--processes 1`` (the default) is one process without a supervisor, as before;
``auto`` is the cores this process may run on minus ``SUMO_SIDE_CORES``, at least 1.
"""

from __future__ import annotations

import collections
import logging
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import mujoco  # noqa: F401  (the physics extra: without it `sumoco physics` names the extra to install)

from protocol.errors import ConfigError
from runtime.errors import ExitCode, exit_text

log = logging.getLogger("physics.supervisor")

SUMO_SIDE_CORES = 1  # [cores] kept free for the SUMO side (one libsumo thread) by --processes auto
MAX_PROCESSES = 256  # [processes] upper bound of --processes
RESTART_WINDOW_S = 300.0  # [s] failures of one child older than this no longer count against its restart limit
BACKOFF_FIRST_S = 0.5  # [s] wait before the first restart of a child; doubles with each failure in the window
BACKOFF_MAX_S = 8.0  # [s] longest wait before a restart
STOP_TIMEOUT_S = 10.0  # [s] after SIGTERM, a child still running is killed (SIGKILL)
FINISH_TIMEOUT_S = 30.0  # [s] after one child finished the run, the others get this long to finish too
POLL_S = 0.05  # [s] how often the supervisor looks at its children
MAX_LINE_BYTES = 16384  # [bytes] a child's output line relayed at most this long (the rest on the next line)
PR_SET_PDEATHSIG = 1  # prctl(2) option: the signal a child gets when its parent dies (Linux)
_ENDPOINT = re.compile(r"^(?P<proto>[A-Za-z0-9]+)/(?P<host>.+):(?P<port>\d+)(?P<rest>[?#].*)?$")


# ---------------------------------------------------------------------- how many, where


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity; the machine's count elsewhere)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def auto_processes(instances: int = 1, cores: int | None = None) -> int:
    """``--processes auto``: the cores minus ``SUMO_SIDE_CORES``, shared by ``instances``
    physics instances on this machine (the demo runs two), at least 1."""
    cores = available_cores() if cores is None else cores
    return max(1, (cores - SUMO_SIDE_CORES) // max(1, instances))


def parse_processes(value: int | str | None, instances: int = 1) -> int:
    """``N`` or ``"auto"`` -> a count of processes (1..MAX_PROCESSES); None -> 1."""
    if value is None:
        return 1
    text = str(value).strip().lower()
    if text == "auto":
        return min(auto_processes(instances), MAX_PROCESSES)
    try:
        n = int(text)
    except ValueError:
        raise ConfigError(f"--processes: expected a number or 'auto', got {value!r}") from None
    if not 1 <= n <= MAX_PROCESSES:
        raise ConfigError(f"--processes: expected 1..{MAX_PROCESSES} or 'auto', got {n}")
    return n


def child_endpoints(listen: list[str] | tuple[str, ...] | None, count: int,
                    free_port: Callable[[], int]) -> list[list[str]]:
    """The ``--listen`` endpoints of each of ``count`` children: child 0 listens where the
    parent was asked to (peers that know that endpoint reach the instance there), the
    others on the same hosts at free ports (``free_port()``). No ``--listen``: none."""
    out: list[list[str]] = [[] for _ in range(count)]
    for ep in listen or ():
        m = _ENDPOINT.match(ep)
        if m is None:
            raise ConfigError(f"--listen {ep!r}: --processes needs endpoints of the form proto/host:port")
        out[0].append(ep)
        for i in range(1, count):
            out[i].append(f"{m['proto']}/{m['host']}:{free_port()}{m['rest'] or ''}")
    return out


# ---------------------------------------------------------------------- the supervisor


@dataclass
class Child:
    """One shard process (and its restarts)."""

    index: int
    count: int
    instance: str  # its physics instance, ``<base>.<i>of<k>``
    argv: list[str]
    proc: subprocess.Popen | None = None
    done: bool = False  # ended with 0: finished the run
    restart_at: float | None = None  # [s, monotonic] scheduled restart
    restarts: int = 0
    failures: collections.deque = field(default_factory=collections.deque)  # [s, monotonic] recent failure times
    last_code: int | None = None
    last_error: str = ""  # its own one-line error (``sumoco physics: ...``), if it printed one
    relay: threading.Thread | None = None

    @property
    def name(self) -> str:
        return f"shard {self.index}/{self.count} ({self.instance})"


class Failure(Exception):
    """The supervisor gives up: ``code`` is its exit code, the message names the child."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """A child of a supervisor that dies (even SIGKILL) gets SIGTERM and shuts down cleanly."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        pass


class Supervisor:
    """Starts, watches and restarts the shard processes of one physics instance."""

    def __init__(self, children: list[Child], max_restarts: int, env: dict[str, str] | None = None,
                 out=None) -> None:
        self.children = children
        self.max_restarts = int(max_restarts)
        self.env = env
        self.out = out if out is not None else sys.stderr.buffer  # where the children's lines go
        self._out_lock = threading.Lock()
        self._stop_signal: int | None = None
        self._wake = threading.Event()
        self.restarts = 0

    # -------------------------------------------------------------- processes

    def _start(self, c: Child, now: float) -> None:
        """Start child ``c``; a start that fails (fork, exec) counts as one of its failures."""
        c.restart_at = None
        c.last_error = ""
        try:
            c.proc = subprocess.Popen(c.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                      stdin=subprocess.DEVNULL, env=self.env,
                                      preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None)
        except (OSError, subprocess.SubprocessError) as e:
            c.proc, c.relay = None, None
            c.last_error = f"could not start it: {e}"
            log.error("%s: %s", c.name, c.last_error)
            self._ended(c, ExitCode.FAILURE, now, run_over=False)
            return
        c.relay = threading.Thread(target=self._relay, args=(c, c.proc), name=f"relay-{c.index}", daemon=True)
        c.relay.start()
        log.info("%s started (pid %d)%s", c.name, c.proc.pid, f", restart {c.restarts}" if c.restarts else "")

    def _relay(self, c: Child, proc: subprocess.Popen) -> None:
        """The child's output, each line prefixed with ``[i/k]``; remembers its error line."""
        prefix = f"[{c.index}/{c.count}] ".encode()
        for line in iter(lambda: proc.stdout.readline(MAX_LINE_BYTES), b""):
            if line.startswith(b"sumoco "):
                c.last_error = line.decode(errors="replace").split(": ", 1)[-1].strip()
            with self._out_lock:
                try:
                    self.out.write(prefix + (line if line.endswith(b"\n") else line + b"\n"))
                    self.out.flush()
                except (OSError, ValueError):
                    pass  # our own output is gone: the children keep running
        proc.stdout.close()

    def _signal_all(self, sig: int) -> None:
        for c in self.children:
            if c.proc is not None and c.proc.poll() is None:
                try:
                    c.proc.send_signal(sig)
                except ProcessLookupError:
                    pass

    def request_stop(self, signum: int = 0) -> None:
        """Stop every child (from a signal handler: ``signum``; 0: the supervisor's own decision)."""
        self._stop_signal = signum
        self._wake.set()

    # -------------------------------------------------------------- policy

    def _ended(self, c: Child, code: int, now: float, run_over: bool) -> None:
        """Child ``c`` ended with ``code``: done, restart later, or raise ``Failure``."""
        c.proc, c.last_code = None, code
        if c.relay is not None:
            c.relay.join(timeout=1.0)  # its last lines (the error) are read
        if code == 0:
            c.done = True
            log.info("%s finished the run", c.name)
            return
        what = f"{c.name} {exit_text(code)}" + (f": {c.last_error}" if c.last_error else "")
        if code == ExitCode.USAGE:
            raise Failure(f"{what} (a usage error: not restarted)", ExitCode.USAGE)
        if run_over:
            raise Failure(f"{what} after a sibling finished the run", ExitCode.PROCESS_FAILED)
        while c.failures and now - c.failures[0] > RESTART_WINDOW_S:
            c.failures.popleft()
        c.failures.append(now)
        if len(c.failures) > self.max_restarts:
            raise Failure(f"{what}; it failed {len(c.failures)} times within {RESTART_WINDOW_S:g} s "
                          f"(restart limit {self.max_restarts}, [physics] process_restarts): giving up",
                          ExitCode.PROCESS_FAILED)
        wait = min(BACKOFF_MAX_S, BACKOFF_FIRST_S * 2 ** (len(c.failures) - 1))
        c.restart_at = now + wait
        c.restarts += 1
        self.restarts += 1
        log.warning("%s; its siblings take over its tiles; restarting it in %.1f s (restart %d of at most %d "
                    "within %g s)", what, wait, len(c.failures), self.max_restarts, RESTART_WINDOW_S)

    def _stop_children(self, sig: int = signal.SIGTERM) -> dict[int, int]:
        """SIGTERM (``sig``) to every running child; SIGKILL after ``STOP_TIMEOUT_S``. Their codes."""
        self._signal_all(sig)
        deadline = time.monotonic() + STOP_TIMEOUT_S
        codes = {}
        for c in self.children:
            c.restart_at = None
            if c.proc is None:
                continue
            try:
                codes[c.index] = c.proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop within %g s of SIGTERM: killing it", c.name, STOP_TIMEOUT_S)
                c.proc.kill()
                codes[c.index] = c.proc.wait(STOP_TIMEOUT_S)
            if c.relay is not None:
                c.relay.join(timeout=1.0)
            c.last_code, c.proc = codes[c.index], None
        return codes

    # -------------------------------------------------------------- main loop

    def run(self) -> int:
        """Start every child and watch them until the run ends; the exit code."""
        try:
            for c in self.children:
                self._start(c, time.monotonic())
            return self._watch()
        except Failure as e:
            self._stop_children()
            print(f"sumoco physics: {e}", file=sys.stderr, flush=True)
            return e.code
        finally:
            self._stop_children()  # none left but after an unexpected error
            log.info("physics supervisor done: %d shard processes, restarts %d%s", len(self.children),
                     self.restarts, "".join(f", {c.index}/{c.count}: {c.restarts}" for c in self.children
                                            if c.restarts))

    def _watch(self) -> int:
        finished_at: float | None = None  # [s, monotonic] when the first child finished the run
        while True:
            now = time.monotonic()
            if self._stop_signal is not None:
                log.info("%sstopping %d shard processes", f"signal {self._stop_signal}: " if self._stop_signal else "",
                         len(self.children))
                codes = self._stop_children()
                # a child still starting (no handler yet) ends by the signal itself: a clean stop too
                bad = {i: c for i, c in codes.items() if c not in (0, -signal.SIGTERM, -signal.SIGINT)}
                if bad:
                    i, code = next(iter(bad.items()))
                    raise Failure(f"{self.children[i].name} {exit_text(code)} while stopping", ExitCode.FAILURE)
                return ExitCode.OK
            for c in self.children:
                if c.proc is not None and (code := c.proc.poll()) is not None:
                    self._ended(c, code, now, run_over=finished_at is not None)
                    if c.done and finished_at is None:
                        finished_at = now
                if c.restart_at is not None and now >= c.restart_at and finished_at is None:
                    self._start(c, now)
            if all(c.done for c in self.children):
                return ExitCode.OK
            if finished_at is not None and now - finished_at > FINISH_TIMEOUT_S:
                late = [c.name for c in self.children if not c.done]
                log.warning("%s still running %g s after a sibling finished the run: stopping it",
                            ", ".join(late), FINISH_TIMEOUT_S)
                self.request_stop()
                continue
            self._wake.wait(POLL_S)
            self._wake.clear()


# ---------------------------------------------------------------------- command line


#: flags of ``sumoco physics`` every child gets as the parent got them (attribute, flag)
_FORWARD = (("config", "--config"), ("run", "--run"), ("mode", "--mode"), ("timing", "--timing"),
            ("duration", "--duration"), ("authority", "--authority"), ("preset", "--preset"),
            ("instance", "--instance"), ("expect", "--expect"))


def child_argv(args, index: int, count: int, listen: list[str]) -> list[str]:
    """The command line of shard ``index`` of ``count``: ``sumoco physics --shard i/k`` with
    the parent's flags, its own ``--listen`` endpoints and the parent's ``--connect`` ones."""
    argv = [sys.executable, "-m", "sumoco.cli", "physics", "--shard", f"{index}/{count}"]
    for attr, flag in _FORWARD:
        v = getattr(args, attr, None)
        if v is not None:
            argv += [flag, str(os.fspath(v)) if not isinstance(v, float) else repr(v)]
    for ep in listen:
        argv += ["--listen", ep]
    for ep in getattr(args, "connect", None) or ():
        argv += ["--connect", ep]
    if getattr(args, "quiet", False):
        argv.append("--quiet")
    if getattr(args, "verbose", False):
        argv.append("--verbose")
    return argv


def child_env() -> dict[str, str]:
    """The children's environment: ours, without SUMOCO_LISTEN (each child gets its own
    ``--listen``; without one it must not take the parent's endpoints from there)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.pop("SUMOCO_LISTEN", None)
    return env


def cli_main(args) -> int:
    """``sumoco physics``: one daemon (``--processes 1``, ``--shard``), or a supervisor of N."""
    from runtime.config import apply_cli, load_common
    from runtime.transport import free_tcp_port
    from physics_side.config import load_physics_config
    from physics_side.shard import shard_instance

    flag = getattr(args, "processes", None)
    if getattr(args, "shard", None):
        if flag is not None and parse_processes(flag) != 1:
            raise ConfigError("--processes and --shard exclude each other (--shard i/k is one process of a set)")
        return _single(args)
    if not args.config:
        raise ConfigError("sumoco physics: --config is required")
    common, data, base = load_common(args.config)
    common = apply_cli(common, args)
    phys = load_physics_config(data, base, str(args.config)).physics
    count = parse_processes(flag if flag is not None else phys.processes)
    if count == 1:
        return _single(args)
    instance = getattr(args, "instance", None) or phys.instance
    listen = common.zenoh.listen  # --listen, else the config's [zenoh] listen: never the same port twice
    if not listen and common.zenoh.mode == "peer":
        # peers without a router reach each other only where they listen: loopback for the siblings here
        listen = (f"tcp/127.0.0.1:{free_tcp_port()}",)
    listens = child_endpoints(listen, count, free_tcp_port)
    children = [Child(i, count, shard_instance(instance, i, count), child_argv(args, i, count, listens[i]))
                for i in range(count)]
    log.info("physics supervisor: %d shard processes of instance %s (%s), %d cores here, up to %d restarts "
             "each within %g s", count, instance, ", ".join(c.instance for c in children), available_cores(),
             phys.process_restarts, RESTART_WINDOW_S)
    sup = Supervisor(children, phys.process_restarts, env=child_env())
    old = {}

    def _handler(signum, frame):
        sup.request_stop(signum)

    for sig in (signal.SIGTERM, signal.SIGINT):
        old[sig] = signal.signal(sig, _handler)
    try:
        return sup.run()
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)


def _single(args) -> int:
    from physics_side.daemon import cli_main as daemon_main

    return daemon_main(args)


__all__ = ["MAX_PROCESSES", "SUMO_SIDE_CORES", "Child", "Supervisor", "auto_processes", "available_cores",
           "child_argv", "child_endpoints", "cli_main", "parse_processes"]
