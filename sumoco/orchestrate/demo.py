"""``sumoco demo``: both daemons as OS processes on loopback, a bounded run, a report.

The demo process is the hub: it opens a Zenoh peer session, records every key of the run
to ``<out>/run.mcap``, starts the SUMO side and one physics process per control preset
(``paper`` and ``default`` side by side on the same SUMO traffic), shows progress, stops
them all cleanly (also on Ctrl-C) and writes ``summary.json``, the figures and
``report.md`` from the recording.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import zenoh

from protocol.errors import ConfigError, SumocoError
from protocol.keys import Keys
from runtime.errors import ExitCode, exit_text
from runtime.config import CommonConfig, ZenohConfig, apply_cli, load_common, replace, section
from sumoco.recording.record import LiveRecorder, McapRecorder, RecordConfig
from runtime.transport import free_tcp_port, open_session

log = logging.getLogger(__name__)

REPO_CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@dataclass(frozen=True)
class DemoConfig:
    presets: tuple[str, ...] = ("paper", "default")  # one physics instance per preset
    processes: int | str = 1  # shard processes per physics instance, N or "auto" (--processes, [physics] processes win)
    wall_limit_s: float = 120.0  # [s] wall-clock bound of the whole run
    startup_timeout_s: float = 60.0  # [s] for the daemons to come up
    stop_timeout_s: float = 10.0  # [s] grace period after SIGTERM before SIGKILL
    progress_period_s: float = 2.0  # [s] between progress lines
    lad_sweep: bool = True  # replay the reference car for the LAD_min figure


class _Progress:
    """Counts what the recorder sees (runs on Zenoh's thread, read by the main loop)."""

    def __init__(self) -> None:
        self.steps = 0
        self.states = 0
        self.last_step_msg: bytes | None = None
        self.lock = threading.Lock()

    def __call__(self, topic: str, payload: bytes) -> None:
        with self.lock:
            if topic.endswith("/sumo/step"):
                self.steps += 1
                self.last_step_msg = payload
            elif topic.endswith("/state"):
                self.states += 1


class Processes:
    """The daemons of one run; guarantees none outlives the demo."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.procs: dict[str, subprocess.Popen] = {}
        self._files = []

    def start(self, name: str, argv: list[str]) -> subprocess.Popen:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        f = (self.log_dir / f"{name}.log").open("wb")
        self._files.append(f)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        log.info("starting %s: %s", name, " ".join(argv[2:]))
        p = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                             preexec_fn=_die_with_parent())
        self.procs[name] = p
        return p

    def stop(self, names: list[str] | None = None, timeout_s: float = 10.0) -> dict[str, int | None]:
        names = list(self.procs) if names is None else names
        for n in names:
            p = self.procs[n]
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        codes = {}
        for n in names:
            p = self.procs[n]
            try:
                codes[n] = p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop after SIGTERM; killing it", n)
                p.kill()
                codes[n] = p.wait(5)
        return codes

    def wait(self, names: list[str], timeout_s: float) -> dict[str, int]:
        """Exit codes of the processes that end by themselves within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        codes = {}
        for n in names:
            try:
                codes[n] = self.procs[n].wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not leave after the last step within %.0f s", n, timeout_s)
        return codes

    def close(self) -> None:
        self.stop(timeout_s=5.0)
        for f in self._files:
            f.close()


#: Linux prctl option: the signal a child gets when the thread that started it ends
PR_SET_PDEATHSIG = 1


def _die_with_parent():
    """A ``preexec_fn`` that makes a daemon receive SIGTERM when its parent dies, even by
    SIGKILL or a test's timeout (which kills the demo, not its daemons); None where that is
    unavailable or unsafe: not Linux, or started from a thread that may end first (the
    signal follows the starting thread, not the process)."""
    if not sys.platform.startswith("linux") or threading.current_thread() is not threading.main_thread():
        return None
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)

    def arm() -> None:  # (in the child, between fork and exec)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)

    return arm


def cli_argv(*args: str) -> list[str]:
    """The command line of ``sumoco <args>`` run by this interpreter (the venv's, not PATH's)."""
    return [sys.executable, "-m", "sumoco.cli", *args]


class DaemonFailed(SumocoError):
    """A daemon of the demo crashed or failed; ``exit_code`` is the demo's."""

    def __init__(self, message: str, exit_code: int) -> None:
        super().__init__(message)
        self.exit_code = exit_code


def _sumo_side_stats(folder: Path) -> dict | None:
    """The SUMO side's final counters (steps, rejected, acks, egos, ...), None if it wrote none."""
    from sumo_side.daemon import STATS_FILE

    try:
        return json.loads((folder / STATS_FILE).read_text())
    except (OSError, ValueError):
        return None


def _last_error_line(log_file: Path, name: str) -> str:
    """The daemon's own one-line error (``sumoco <cmd>: ...``) from its log, if it wrote one."""
    try:
        lines = log_file.read_text(errors="replace").splitlines()
    except OSError:
        return ""
    for line in reversed(lines[-200:]):
        if line.startswith("sumoco "):
            return line.split(": ", 1)[-1].strip()
    return ""


def _sumo_error(log_file: Path) -> str:
    """SUMO's own last ``Error:`` line in a log, if any."""
    try:
        lines = log_file.read_text(errors="replace").splitlines()
    except OSError:
        return ""
    errors = [ln.removeprefix("Error: ").strip() for ln in lines if ln.startswith("Error: ")]
    return errors[-1] if errors else ""


def daemon_failure(name: str, code: int, log_dir: Path) -> DaemonFailed:
    """One line naming the daemon, its signal or code and its own message; the demo's exit
    code: 2 for a crash (signal) or a broken configuration/scenario, 1 for a failed run (also
    a physics supervisor's 3: one of its shard processes kept failing)."""
    log_file = log_dir / f"{name}.log"
    own = _last_error_line(log_file, name)
    text = f"{name} {exit_text(code)}" + (f": {own}" if own else "") + f" (log: {log_file})"
    return DaemonFailed(text, ExitCode.FAILURE if code in (ExitCode.FAILURE, ExitCode.PROCESS_FAILED)
                        else ExitCode.USAGE)


def _wait_for(cond, timeout_s: float, what: str, procs: Processes) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        for name, p in procs.procs.items():
            if p.poll() is not None:
                raise daemon_failure(name, p.returncode, procs.log_dir)
        if time.monotonic() > deadline:
            raise DaemonFailed(f"timed out after {timeout_s:.0f} s waiting for {what} "
                               f"(logs in {procs.log_dir})", ExitCode.FAILURE)
        time.sleep(0.05)


#: Start-up attempts when a chosen port was taken before a daemon could listen on it.
PORT_ATTEMPTS = 3


def _port_clash(procs: Processes) -> bool:
    """A daemon ended because its listen port was taken (its log says so)."""
    for name, p in procs.procs.items():
        if p.poll() is None:
            continue
        try:
            if "Address already in use" in (procs.log_dir / f"{name}.log").read_text(errors="replace"):
                return True
        except OSError:
            pass
    return False


def physics_instances(demo: DemoConfig) -> list[str]:
    """The physics instances the SUMO side waits for: one per preset, or its shard processes
    (``<preset>.<i>of<N>``) when each preset runs as ``demo.processes`` processes."""
    if demo.processes == 1:
        return list(demo.presets)
    return [f"{p}.{i}of{demo.processes}" for p in demo.presets for i in range(demo.processes)]


def _start_daemons(procs: Processes, common_args: list[str], hub: str, sumo_ep: str, demo: DemoConfig,
                   out: Path, sumocfg: str | None, begin: float | None, common: CommonConfig) -> None:
    """The SUMO side listening on ``sumo_ep`` and one physics instance per preset (a process,
    or a supervisor of ``demo.processes`` shard processes)."""
    sumo_args = ["sumo", *common_args, "--listen", sumo_ep, "--connect", hub, "--output-dir", str(out / "sumo")]
    for inst in physics_instances(demo):
        sumo_args += ["--wait-for", inst]
    if sumocfg:
        sumo_args += ["--sumocfg", str(sumocfg)]
    if begin is not None:
        sumo_args += ["--begin", repr(float(begin))]
    if common.run.seed is not None:
        sumo_args += ["--seed", str(common.run.seed)]
    procs.start("sumo", cli_argv(*sumo_args))
    for p in demo.presets:
        procs.start(f"physics-{p}", cli_argv(
            "physics", *common_args, "--instance", p, "--preset", p, "--processes", str(demo.processes),
            "--listen", f"tcp/127.0.0.1:{free_tcp_port()}", "--connect", sumo_ep, "--connect", hub))


def default_out(sumocfg: str | Path | None) -> Path:
    """``runs/demo`` for the bundled scenario, ``runs/<folder>/<name>`` for a .sumocfg."""
    if not sumocfg:
        return Path("runs") / "demo"
    p = Path(sumocfg).expanduser().resolve()
    return Path("runs") / p.parent.name / p.stem


class _DemoRun:
    """One demo run's daemons and how they ended: started, watched, collected."""

    def __init__(self, config_path: Path, out: Path, common: CommonConfig, demo: DemoConfig,
                 sumocfg: str | None, begin: float | None, quiet: bool) -> None:
        from physics_side.processes import parse_processes

        demo = replace(demo, processes=parse_processes(demo.processes, len(demo.presets)))
        self.config_path, self.out, self.common, self.demo = config_path, out, common, demo
        self.sumocfg, self.begin, self.quiet = sumocfg, begin, quiet
        self.keys = Keys(common.zenoh.root, common.run.id)
        self.hub = f"tcp/127.0.0.1:{free_tcp_port()}"  # the demo's own session: recorder and liveliness
        self.sumo_ep = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.progress = _Progress()
        self.procs = Processes(out / "logs")
        self.alive: set[str] = set()  # liveliness tokens seen
        self.t_start = time.monotonic()
        self.interrupted = False
        self.ended_by = ""
        self.failure: DaemonFailed | None = None
        self.codes: dict[str, int | None] = {}

    def zenoh(self) -> ZenohConfig:
        return replace(self.common.zenoh, mode="peer", listen=(self.hub,), connect=())

    def watch_liveliness(self, session: zenoh.Session):
        def on_token(s: zenoh.Sample) -> None:
            if s.kind == zenoh.SampleKind.PUT:
                self.alive.add(str(s.key_expr))
            else:
                self.alive.discard(str(s.key_expr))

        return session.liveliness().declare_subscriber(f"{self.keys.base}/**", on_token, history=True)

    def daemon_args(self) -> list[str]:
        """The flags every daemon of the run gets."""
        run = self.common.run
        args = ["--config", str(self.config_path), "--run", run.id, "--timing", run.timing,
                "--duration", repr(float(run.duration_s)), "--authority", self.common.coupling.authority]
        if self.quiet:
            args.append("--quiet")
        return args

    def start(self, live: LiveRecorder) -> None:
        """Start the daemons and wait until each is up (the static data recorded meanwhile);
        on a port taken between choosing and listening, again on new ports."""
        demo, keys, procs = self.demo, self.keys, self.procs
        for attempt in range(1, PORT_ATTEMPTS + 1):
            try:
                _start_daemons(procs, self.daemon_args(), self.hub, self.sumo_ep, demo, self.out, self.sumocfg,
                               self.begin, self.common)
                _wait_for(lambda: keys.sumo_alive in self.alive, demo.startup_timeout_s, "the SUMO side", procs)
                if live.fetch_static(timeout_s=10.0) is None:
                    log.warning("no static data from the SUMO side")
                want = {Keys(keys.root, keys.run, p).physics_alive for p in physics_instances(demo)}
                _wait_for(lambda: want <= self.alive, demo.startup_timeout_s, "the physics processes", procs)
                break
            except DaemonFailed as e:
                if procs.procs["sumo"].poll() == ExitCode.USAGE:
                    raise self._scenario_error(e) from None
                if attempt == PORT_ATTEMPTS or not _port_clash(procs):
                    raise
                # Another program took a port between choosing and listening: new ports.
                log.warning("a daemon's port was taken meanwhile; starting the daemons again on new ports")
                procs.stop(timeout_s=demo.stop_timeout_s)
                self.sumo_ep = f"tcp/127.0.0.1:{free_tcp_port()}"
        log.info("all daemons up after %.1f s; running (wall limit %.0f s)",
                 time.monotonic() - self.t_start, self.demo.wall_limit_s)

    def _scenario_error(self, e: DaemonFailed) -> ConfigError:
        """SUMO could not load the scenario: a configuration problem, not a run."""
        log_file = self.procs.log_dir / "sumo.log"
        own = (_last_error_line(log_file, "sumo")
               .removeprefix("configuration error: ").replace("; SUMO's own messages are above", ""))
        said = _sumo_error(log_file)
        return ConfigError((own or str(e)) + (f"; SUMO said: {said}" if said else ""))

    def wait_for_end(self) -> None:
        """Progress lines until the SUMO side ends, another daemon fails or the wall-clock limit."""
        procs, demo = self.procs, self.demo
        t_run = time.monotonic()
        next_progress = t_run
        while procs.procs["sumo"].poll() is None:
            now = time.monotonic()
            for name, p in procs.procs.items():
                if name != "sumo" and p.poll() not in (None, 0):
                    self.failure = daemon_failure(name, p.returncode, procs.log_dir)
            if self.failure is not None:
                break
            if now - t_run > demo.wall_limit_s:
                log.info("wall-clock limit reached; stopping")
                self.ended_by = "wall-clock limit"
                break
            if now >= next_progress:
                _print_progress(self.progress, now - t_run)
                next_progress = now + demo.progress_period_s
            time.sleep(0.05)

    def collect(self) -> None:
        """Every daemon's exit code, and the first failure among them."""
        # SUMO ends on its own (or on SIGTERM) with a step marked final; the physics
        # processes acknowledge it and leave by themselves.
        procs, timeout, codes = self.procs, self.demo.stop_timeout_s, self.codes
        codes["sumo"] = procs.stop(["sumo"], timeout)["sumo"]
        others = [n for n in procs.procs if n != "sumo"]
        if codes["sumo"] == 0:
            codes.update(procs.wait(others, timeout))
        codes.update(procs.stop([n for n in others if n not in codes], timeout))
        if self.failure is None:
            for name, code in codes.items():
                if code not in (0, None):
                    self.failure = daemon_failure(name, code, procs.log_dir)
                    break

    def report(self, rec_path: Path) -> dict:
        """Summary, figures and report of the recording, with how the daemons ended; written
        to ``summary.json``."""
        from sumoco.analysis.report import render_markdown, write_report

        try:
            summary = write_report(rec_path, self.out, lad_sweep=self.demo.lad_sweep)
        except Exception as e:  # nothing usable recorded: the failure is the news
            if self.failure is None:
                raise
            log.warning("no report: %s", e)
            summary = {}
        codes, failure, interrupted, ended_by = self.codes, self.failure, self.interrupted, self.ended_by
        summary["daemons"] = {
            "exit_codes": codes,
            "completed": bool(codes) and not interrupted and failure is None and not ended_by
            and all(c == 0 for c in codes.values()),
            "ended_by": "interrupted" if interrupted else ended_by or (str(failure) if failure else "the run's end"),
        }
        summary["interrupted"] = interrupted
        summary["authority"] = self.common.coupling.authority
        summary["sumo_side"] = _sumo_side_stats(self.out / "sumo")
        (self.out / "summary.json").write_text(json.dumps(summary, indent=1, sort_keys=True) + "\n")
        if summary.get("presets"):  # again, with what only the run knows (the authority)
            (self.out / "report.md").write_text(render_markdown(summary, rec_path))
        return summary


def _on_stop_signal(signum, frame):
    raise KeyboardInterrupt


def run_demo(config_path: Path, out: Path, common: CommonConfig, demo: DemoConfig,
             sumocfg: str | None = None, quiet: bool = False, begin: float | None = None,
             record: RecordConfig | None = None) -> dict:
    """Run the whole demo; returns the summary dict (also written to ``out/summary.json``).

    ``record`` defaults to every physics state (the report's figures follow the 50 Hz ticks).
    A daemon that crashes or fails raises ``DaemonFailed`` after the report of what was
    recorded is written.
    """
    out.mkdir(parents=True, exist_ok=True)
    run = _DemoRun(config_path, out, common, demo, sumocfg, begin, quiet)
    rec_path = out / "run.mcap"
    recorder = McapRecorder(rec_path)
    old = signal.signal(signal.SIGTERM, _on_stop_signal)
    # Ctrl-C stops the run even when the shell that started us ignores SIGINT (a script's
    # background job inherits SIG_IGN, and Python then installs no KeyboardInterrupt)
    old_int = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with open_session(run.zenoh()) as session:
            live = LiveRecorder(session, run.keys, recorder, on_message=run.progress,
                                config=record or RecordConfig(physics_hz=0.0),
                                limits=common.run.decode_limits).start()
            tok_sub = run.watch_liveliness(session)
            run.start(live)
            run.wait_for_end()
            run.collect()
            tok_sub.undeclare()
            live.stop()
    except KeyboardInterrupt:
        run.interrupted = True
        log.warning("interrupted: stopping the daemons")
    finally:
        signal.signal(signal.SIGTERM, old)
        signal.signal(signal.SIGINT, old_int)
        run.procs.close()
        recorder.close()
    summary = run.report(rec_path)
    if run.failure is not None:
        raise run.failure
    return summary


def _print_progress(progress: _Progress, elapsed: float) -> None:
    from protocol.codec import decode

    with progress.lock:
        steps, states, last = progress.steps, progress.states, progress.last_step_msg
    t, n = 0.0, 0
    if last is not None:
        try:
            m = decode(last)
            t, n = m.time, m.agents.n
        except Exception:
            pass
    print(f"[demo] {elapsed:6.1f} s wall | sim t={t:6.1f} s | steps {steps} | agents {n} | "
          f"physics states {states}", file=sys.stderr, flush=True)


def _processes(args, data: dict, base: Path, config: Path, instances: int, demo_processes: int | str) -> int:
    """Shard processes per physics instance: ``--processes``, else ``[physics] processes``;
    ``auto`` shares the cores left beside the SUMO side among the ``instances``."""
    from physics_side.config import load_physics_config
    from physics_side.processes import parse_processes

    value = getattr(args, "processes", None)
    if value is None and "processes" in data.get("physics", {}):
        value = load_physics_config(data, base, str(config)).physics.processes
    return parse_processes(value if value is not None else demo_processes, instances)


def cli_main(args) -> int:
    from sumo_side.simulation import check_sumocfg

    config = Path(args.config) if args.config else REPO_CONFIGS / "demo.toml"
    common, data, base = load_common(config)
    common = apply_cli(common, args)
    demo = section(data, "demo", DemoConfig, base, str(config))
    if getattr(args, "wall", None):
        demo = replace(demo, wall_limit_s=float(args.wall))
    demo = replace(demo, processes=_processes(args, data, base, config, len(demo.presets), demo.processes))
    record = section(data, "record", RecordConfig, base, str(config)) if "record" in data else None
    sumocfg = getattr(args, "sumocfg", None)
    if sumocfg:
        sumocfg = str(check_sumocfg(Path(sumocfg)))  # a missing or broken file: exit 2 before any daemon
    begin = getattr(args, "begin", None)
    if begin is not None and begin < 0:
        raise ConfigError(f"--begin: expected >= 0 s, got {begin}")
    out = Path(args.out) if getattr(args, "out", None) else default_out(sumocfg)
    if getattr(args, "compare_authority", False):
        return _compare_authority(config, out, common, demo, sumocfg, bool(args.quiet), begin, record)
    try:
        summary = run_demo(config, out, common, demo, sumocfg=sumocfg, quiet=bool(args.quiet), begin=begin,
                           record=record)
    except DaemonFailed as e:
        print(f"sumoco demo: {e}", file=sys.stderr)
        return int(e.exit_code)
    print(f"report: {out / 'report.md'}", file=sys.stderr)
    for inst, p in summary["presets"].items():
        e = p["error_m"]["overall"]
        print(f"  {inst:8s} error mean {e['mean']} m, p95 {e['p95']} m, max {e['max']} m, "
              f"collisions {p['collisions']}, placements {p['placements']}", file=sys.stderr)
    return 130 if summary.get("interrupted") else 0


#: ``--compare-authority``: the scenario once in each mode, in these sub-folders of ``--out``
AUTHORITY_MODES = ("sumo", "physics")


def _compare_authority(config: Path, out: Path, common: CommonConfig, demo: DemoConfig, sumocfg, quiet: bool,
                       begin, record) -> int:
    """The same scenario shadowed (SUMO-authoritative) and two-way (physics-authoritative),
    then ``modes.md`` comparing them."""
    from sumoco.analysis.modes import write_modes

    dirs = []
    for mode in AUTHORITY_MODES:
        sub = out / f"{mode}-authority"
        mode_common = replace(common, coupling=replace(common.coupling, authority=mode))
        try:
            run_demo(config, sub, mode_common, demo, sumocfg=sumocfg, quiet=quiet, begin=begin, record=record)
        except DaemonFailed as e:
            print(f"sumoco demo ({mode} authority): {e}", file=sys.stderr)
            return int(e.exit_code)
        dirs.append(sub)
    rows = write_modes(dirs, out)
    print(f"comparison: {out / 'modes.md'}", file=sys.stderr)
    for r in rows:
        print(f"  {r['authority']:8s} physical share {r['physical_share']}, tracking p95 {r['error_p95_m']} m, "
              f"trips {r['trips_arrived']}, travel time {r['travel_time_mean_s']} s, vanished {r['vanished']}",
              file=sys.stderr)
    return 0
