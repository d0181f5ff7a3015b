"""``sumoco demo``: both daemons as OS processes on loopback, a bounded run, a report.

The demo process is the hub: it opens a Zenoh peer session, records every key of the run
to ``<out>/run.mcap``, starts the SUMO side and one physics process per control preset
(``paper`` and ``default`` side by side on the same SUMO traffic), shows progress, stops
them all cleanly (also on Ctrl-C) and writes ``summary.json``, the figures and
``report.md`` from the recording.
"""

from __future__ import annotations

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

from protocol.keys import Keys
from sumoco.common.config import CommonConfig, ZenohConfig, apply_cli, load_common, replace, section
from sumoco.app.record import LiveRecorder, McapRecorder, RecordConfig
from sumoco.common.transport import free_tcp_port, open_session

log = logging.getLogger(__name__)

REPO_CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@dataclass(frozen=True)
class DemoConfig:
    presets: tuple[str, ...] = ("paper", "default")  # one physics process per preset
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
        p = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        self.procs[name] = p
        return p

    def stop(self, names: list[str] | None = None, timeout_s: float = 10.0) -> dict[str, int | None]:
        names = names or list(self.procs)
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

    def close(self) -> None:
        self.stop(timeout_s=5.0)
        for f in self._files:
            f.close()


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "sumoco.app.cli", *args]


def _wait_for(cond, timeout_s: float, what: str, procs: Processes) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        for name, p in procs.procs.items():
            if p.poll() is not None:
                raise RuntimeError(f"{name} exited with code {p.returncode} while waiting for {what}; "
                                   f"see {procs.log_dir / (name + '.log')}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(0.05)


def run_demo(config_path: Path, out: Path, common: CommonConfig, demo: DemoConfig,
             sumocfg: str | None = None, quiet: bool = False, record: RecordConfig | None = None) -> dict:
    """Run the whole demo; returns the summary dict.

    ``record`` defaults to every physics state (the report's figures follow the 50 Hz ticks).
    """
    from sumoco.app.report import write_report

    out.mkdir(parents=True, exist_ok=True)
    keys = Keys(common.zenoh.root, common.run.id)
    hub_port, sumo_port = free_tcp_port(), free_tcp_port()
    hub = f"tcp/127.0.0.1:{hub_port}"
    sumo_ep = f"tcp/127.0.0.1:{sumo_port}"
    rec_path = out / "run.mcap"
    progress = _Progress()
    procs = Processes(out / "logs")
    recorder = McapRecorder(rec_path)
    zcfg = replace(common.zenoh, mode="peer", listen=(hub,), connect=())
    t_start = time.monotonic()
    interrupted = False

    def _on_sigint(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, _on_sigint)
    try:
        with open_session(zcfg) as session:
            live = LiveRecorder(session, keys, recorder, on_message=progress,
                                config=record or RecordConfig(physics_hz=0.0)).start()
            alive = set()
            tok_sub = session.liveliness().declare_subscriber(
                f"{keys.base}/**", lambda s: (alive.add(str(s.key_expr)) if s.kind == zenoh.SampleKind.PUT
                                               else alive.discard(str(s.key_expr))),
                history=True)
            common_args = ["--config", str(config_path), "--run", common.run.id,
                           "--timing", common.run.timing]
            if common.run.duration_s:
                common_args += ["--duration", str(common.run.duration_s)]
            if quiet:
                common_args.append("--quiet")
            sumo_args = ["sumo", *common_args, "--listen", sumo_ep, "--connect", hub]
            for p in demo.presets:
                sumo_args += ["--wait-for", p]
            if sumocfg:
                sumo_args += ["--sumocfg", str(sumocfg)]
            procs.start("sumo", _cli(*sumo_args))
            for p in demo.presets:
                procs.start(f"physics-{p}", _cli(
                    "physics", *common_args, "--instance", p, "--preset", p,
                    "--listen", f"tcp/127.0.0.1:{free_tcp_port()}", "--connect", sumo_ep, "--connect", hub))
            _wait_for(lambda: keys.sumo_alive in alive, demo.startup_timeout_s, "the SUMO side", procs)
            if live.fetch_static(timeout_s=10.0) is None:
                log.warning("no static data from the SUMO side")
            want = {Keys(keys.root, keys.run, p).physics_alive for p in demo.presets}
            _wait_for(lambda: want <= alive, demo.startup_timeout_s, "the physics processes", procs)
            log.info("all daemons up after %.1f s; running (wall limit %.0f s)",
                     time.monotonic() - t_start, demo.wall_limit_s)
            t_run = time.monotonic()
            next_progress = t_run
            while procs.procs["sumo"].poll() is None:
                now = time.monotonic()
                for name, p in procs.procs.items():
                    if name != "sumo" and p.poll() not in (None, 0):
                        raise RuntimeError(f"{name} exited with code {p.returncode}; see {procs.log_dir / (name + '.log')}")
                if now - t_run > demo.wall_limit_s:
                    log.info("wall-clock limit reached; stopping")
                    break
                if now >= next_progress:
                    _print_progress(progress, now - t_run)
                    next_progress = now + demo.progress_period_s
                time.sleep(0.05)
            sumo_code = procs.stop(["sumo"], demo.stop_timeout_s)["sumo"]
            # Let the physics side finish the last step's ticks before stopping it.
            time.sleep(0.3)
            codes = procs.stop(timeout_s=demo.stop_timeout_s)
            codes["sumo"] = sumo_code
            tok_sub.undeclare()
            live.stop()
    except KeyboardInterrupt:
        interrupted = True
        log.warning("interrupted: stopping the daemons")
        codes = {}
    finally:
        signal.signal(signal.SIGTERM, old)
        procs.close()
        recorder.close()
    bad = {n: c for n, c in codes.items() if c not in (0, None, -signal.SIGTERM)}
    if bad:
        log.warning("daemon exit codes: %s (logs in %s)", bad, procs.log_dir)
    summary = write_report(rec_path, out, lad_sweep=demo.lad_sweep)
    summary["exit_codes"] = codes
    summary["interrupted"] = interrupted
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


def cli_main(args) -> int:
    config = Path(args.config) if args.config else REPO_CONFIGS / "demo.toml"
    common, data, base = load_common(config)
    common = apply_cli(common, args)
    demo = section(data, "demo", DemoConfig, base, str(config))
    if getattr(args, "wall", None):
        demo = replace(demo, wall_limit_s=float(args.wall))
    record = section(data, "record", RecordConfig, base, str(config)) if "record" in data else None
    out = Path(args.out)
    summary = run_demo(config, out, common, demo, sumocfg=getattr(args, "sumocfg", None),
                       quiet=bool(args.quiet), record=record)
    print(f"report: {out / 'report.md'}", file=sys.stderr)
    for inst, p in summary["presets"].items():
        e = p["error_m"]["overall"]
        print(f"  {inst:8s} error mean {e['mean']} m, p95 {e['p95']} m, max {e['max']} m, "
              f"collisions {p['collisions']}, placements {p['placements']}", file=sys.stderr)
    return 130 if summary.get("interrupted") else 0
