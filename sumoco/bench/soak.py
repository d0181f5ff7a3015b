"""``sumoco bench soak --minutes N``: a long run that must not grow memory or count errors.

The bundled scenario is looped for N minutes in realtime: the SUMO side runs it to the end
and exits, and the soak starts a new SUMO side with the same run id (the physics side's
resynchronisation path), while two physics instances (``paper`` and ``default``), a
recorder (``sumoco record``), a viewer (``sumoco view``) and a WebSocket client reading
the viewer's frames stay up the whole time. Every ``sample_period_s`` one JSON row gives
the resident memory (RSS) of each process, the steps seen, drops and errors so far; the
last row compares each long-lived process's RSS with its value after the first minute.

Errors are: a process that exits other than the SUMO side finishing a loop with 0,
``ERROR``/``Traceback`` lines in any log, messages rejected by a daemon, a WebSocket
client that lost its connection.
"""

from __future__ import annotations

import json
import logging
import os
import re
import secrets
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from protocol.codec import decode
from protocol.errors import ProtocolError
from protocol.keys import Keys
from protocol.messages import PhysicsState
from runtime.config import load_common, replace
from runtime.transport import free_tcp_port, open_session
from sumoco.bench.scenario import CONFIGS, write_toml
from sumoco.orchestrate.demo import Processes, cli_argv

log = logging.getLogger(__name__)

_ERROR_LINE = re.compile(rb"\bERROR\b|Traceback")
_DONE_LINE = re.compile(rb"SUMO side done: .*?\brejected=(\d+)")


@dataclass(frozen=True)
class SoakConfig:
    minutes: float = 60.0  # [min] wall time of the whole soak
    config: Path = CONFIGS / "soak.toml"
    presets: tuple[str, ...] = ("paper", "default")  # one physics process each
    sample_period_s: float = 60.0  # [s] between rows
    startup_timeout_s: float = 60.0  # [s] for every process to come up
    out: Path = Path("runs/soak")


def _proc_mb(pid: int, file: str, field: str) -> float:
    """A ``field: N kB`` line of ``/proc/<pid>/<file>`` in MB; NaN if the process is gone."""
    try:
        for line in Path(f"/proc/{pid}/{file}").read_text().splitlines():
            if line.startswith(field):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def rss_mb(pid: int) -> float:
    """Resident set size of process ``pid`` [MB] (Linux ``/proc``); NaN if it is gone."""
    return _proc_mb(pid, "status", "VmRSS:")


def heap_mb(pid: int) -> float:
    """Anonymous memory of process ``pid`` [MB] (Linux ``smaps_rollup``): the heap and other
    private allocations, without the shared libraries' pages that RSS gains as new code paths
    run; a leak shows here. NaN if unknown."""
    return _proc_mb(pid, "smaps_rollup", "Anonymous:")


class _Hub:
    """The soak's own Zenoh session: counts steps, keeps the newest physics state."""

    def __init__(self, session: zenoh.Session, keys: Keys) -> None:
        self.keys = keys
        self.lock = threading.Lock()
        self.steps = 0
        self.latest: dict[str, bytes] = {}
        self.alive: set[str] = set()
        self._subs = [
            session.declare_subscriber(keys.step, self._on_step),
            session.declare_subscriber(keys.physics_state_all, self._on_state),
            session.liveliness().declare_subscriber(f"{keys.base}/**", self._on_alive, history=True),
        ]

    def _on_step(self, _sample: zenoh.Sample) -> None:
        with self.lock:
            self.steps += 1

    def _on_state(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.latest[Keys.instance_of(str(sample.key_expr))] = sample.payload.to_bytes()

    def _on_alive(self, sample: zenoh.Sample) -> None:
        with self.lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(str(sample.key_expr))
            else:
                self.alive.discard(str(sample.key_expr))

    def physics_counters(self) -> dict[str, dict[str, int]]:
        with self.lock:
            latest = dict(self.latest)
        out = {}
        for inst, payload in latest.items():
            try:
                msg = decode(payload)
            except ProtocolError:
                continue
            if isinstance(msg, PhysicsState):
                out[inst] = dict(msg.counters)
        return out

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # session already closed
                pass


class _WsClient(threading.Thread):
    """Reads the viewer's WebSocket like a page would; counts frames and disconnects."""

    def __init__(self, url: str) -> None:
        super().__init__(daemon=True, name="soak-ws")
        self.url = url
        self.frames = 0
        self.disconnects = 0
        self.connected = threading.Event()
        self._halt = threading.Event()

    def run(self) -> None:
        from websockets.sync.client import connect

        while not self._halt.is_set():
            try:
                with connect(self.url, max_size=1 << 26, open_timeout=5) as ws:
                    self.connected.set()
                    while not self._halt.is_set():
                        try:
                            ws.recv(timeout=0.5)
                        except TimeoutError:
                            continue
                        self.frames += 1
            except Exception as e:  # refused while the viewer starts, or a lost connection
                if self.connected.is_set() and not self._halt.is_set():
                    self.disconnects += 1
                    log.warning("viewer WebSocket lost: %s", e)
                self._halt.wait(0.5)

    def stop(self) -> None:
        self._halt.set()


def _log_errors(log_dir: Path) -> int:
    n = 0
    for f in log_dir.glob("*.log"):
        try:
            n += len(_ERROR_LINE.findall(f.read_bytes()))
        except OSError:
            pass
    return n


def _sumo_rejected(log_file: Path) -> int:
    try:
        m = _DONE_LINE.search(log_file.read_bytes())
    except OSError:
        return 0
    return int(m.group(1)) if m else 0


class _Soak:
    """The processes of one soak (the SUMO side restarted per loop, the long-lived rest) and
    what they did so far: loops, bad exits, messages the SUMO sides rejected."""

    def __init__(self, cfg: SoakConfig, root: str, run_id: str) -> None:
        self.cfg, self.run_id = cfg, run_id
        self.keys = Keys(root, run_id)
        self.log_dir = cfg.out / "logs"
        self.procs = Processes(self.log_dir)
        self.hub_ep = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.sumo_ep = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.view_port = free_tcp_port()
        self.base = ["--config", str(cfg.config), "--run", run_id, "--timing", "realtime", "--quiet"]
        self.exits: list[dict] = []
        self.loops = 0
        self.sumo_rejected = 0
        self.sumo_started = time.monotonic()

    @property
    def sumo_name(self) -> str:
        return f"sumo-{self.loops:03d}"

    def start_sumo(self) -> None:
        self.loops += 1
        self.sumo_started = time.monotonic()
        self.procs.start(self.sumo_name, cli_argv("sumo", *self.base, "--listen", self.sumo_ep,
                                                  "--connect", self.hub_ep))

    def start_all(self, view_cfg: Path) -> None:
        """The first SUMO side, a physics process per preset, the recorder and the viewer."""
        self.start_sumo()
        for p in self.cfg.presets:
            # --duration 0: physics follows every loop instead of stopping after the first
            self.procs.start(f"physics-{p}", cli_argv(
                "physics", *self.base, "--duration", "0", "--instance", p, "--preset", p,
                "--listen", f"tcp/127.0.0.1:{free_tcp_port()}", "--connect", self.sumo_ep, "--connect", self.hub_ep))
        self.procs.start("record", cli_argv("record", *self.base, "--connect", self.hub_ep,
                                            "--out", str(self.cfg.out / "run.mcap")))
        self.procs.start("view", cli_argv("view", "--config", str(view_cfg), "--run", self.run_id, "--quiet",
                                          "--connect", self.hub_ep, "--port", str(self.view_port)))

    def alive_keys(self) -> set[str]:
        """The liveliness tokens of the SUMO side and every physics instance."""
        return {self.keys.sumo_alive} | {Keys(self.keys.root, self.run_id, p).physics_alive for p in self.cfg.presets}

    def wait(self, cond, what: str) -> None:
        deadline = time.monotonic() + self.cfg.startup_timeout_s
        while not cond():
            if time.monotonic() > deadline:
                raise RuntimeError(f"soak: timed out after {self.cfg.startup_timeout_s:.0f} s waiting for {what}")
            time.sleep(0.1)

    def check(self, loop_again: bool) -> None:
        """A SUMO side that finished its loop is counted (and started again while
        ``loop_again``); any other process that ended is a bad exit."""
        sumo = self.procs.procs.get(self.sumo_name)
        if sumo.poll() is not None:
            self.sumo_rejected += _sumo_rejected(self.log_dir / f"{self.sumo_name}.log")
            if sumo.returncode != 0:
                self.exits.append({"process": self.sumo_name, "code": sumo.returncode})
            if loop_again:
                self.start_sumo()
        for name, p in self.procs.procs.items():
            if not name.startswith("sumo-") and p.poll() is not None and \
                    not any(e["process"] == name for e in self.exits):
                self.exits.append({"process": name, "code": p.returncode})

    def sample(self, hub: _Hub, ws: _WsClient, emit) -> list[dict]:
        """Rows every ``sample_period_s`` until ``minutes`` have passed, SUMO looping meanwhile."""
        rows: list[dict] = []
        t_first = time.monotonic()
        next_row = t_first + self.cfg.sample_period_s
        t_end = t_first + self.cfg.minutes * 60.0
        while True:
            now = time.monotonic()
            self.check(loop_again=now < t_end)
            if now >= next_row or now >= t_end:
                # a SUMO side still loading its scenario would show a partial RSS
                sumo_up = now - self.sumo_started > 5.0
                rows.append(self.row(round((now - t_first) / 60.0, 1), now - t_first, hub, ws, sumo_up))
                emit(rows[-1])
                next_row += self.cfg.sample_period_s
            if now >= t_end:
                return rows
            time.sleep(0.2)

    def row(self, minute: float, elapsed: float, hub: _Hub, ws: _WsClient, sumo_up: bool) -> dict:
        rss, heap = {}, {}
        for name, p in self.procs.procs.items():
            if name.startswith("sumo-"):
                if p.poll() is None and sumo_up:
                    rss["sumo"], heap["sumo"] = round(rss_mb(p.pid), 1), round(heap_mb(p.pid), 1)
            else:
                rss[name], heap[name] = round(rss_mb(p.pid), 1), round(heap_mb(p.pid), 1)
        rss["soak+ws-client"] = round(rss_mb(os.getpid()), 1)
        heap["soak+ws-client"] = round(heap_mb(os.getpid()), 1)
        pc = hub.physics_counters()
        with hub.lock:
            steps = hub.steps
        dropped = sum(c.get("dropped_steps", 0) for c in pc.values())
        rejected = sum(c.get("rejected", 0) for c in pc.values()) + self.sumo_rejected
        log_errors = _log_errors(self.log_dir)
        errors = len(self.exits) + log_errors + rejected + ws.disconnects
        return {
            "bench": "soak", "minute": minute, "wall_s": round(elapsed, 1), "rss_mb": rss, "heap_mb": heap,
            "steps": steps, "sumo_loops": self.loops, "viewer_frames": ws.frames,
            "dropped_steps": dropped, "rejected": rejected, "log_errors": log_errors,
            "ws_disconnects": ws.disconnects, "bad_exits": list(self.exits), "errors": errors,
        }


def run_soak(cfg: SoakConfig, emit=None) -> list[dict]:
    """Run the soak; ``emit(row)`` is called with each row as it is measured."""
    emit = emit or (lambda row: None)
    common = load_common(cfg.config)[0]
    run_id = f"soak{int(time.time()) % 100000}"
    common = replace(common, run=replace(common.run, id=run_id, timing="realtime"))
    cfg.out.mkdir(parents=True, exist_ok=True)
    soak = _Soak(cfg, common.zenoh.root, run_id)
    # The viewer serves its data only with the run's token: give it one we know.
    token = secrets.token_urlsafe(18)
    view_cfg = write_toml(cfg.out / "viewer.toml", {"zenoh": {"root": common.zenoh.root}, "viewer": {"token": token}})
    ws = _WsClient(f"ws://127.0.0.1:{soak.view_port}/ws?token={token}")
    zcfg = replace(common.zenoh, mode="peer", listen=(soak.hub_ep,), connect=())
    t0 = time.monotonic()
    with open_session(zcfg) as session:
        hub = _Hub(session, soak.keys)
        try:
            soak.start_all(view_cfg)
            want = soak.alive_keys()
            soak.wait(lambda: want <= hub.alive, "the SUMO side and the physics instances")
            ws.start()
            soak.wait(ws.connected.is_set, "the viewer's WebSocket")
            rows = soak.sample(hub, ws, emit)
        finally:
            ws.stop()
            codes = soak.procs.stop(timeout_s=15.0)
            soak.procs.close()
            hub.close()
    summary = soak_summary(rows, codes, soak.exits, time.monotonic() - t0, cfg.out)
    emit(summary)
    rows.append(summary)
    return rows


def soak_summary(rows: list[dict], codes: dict, exits: list[dict], wall: float, out: Path) -> dict:
    """Growth of each long-lived process's RSS from the first row to the last [%] (the verdict),
    and of its anonymous memory (``heap_growth_pct``), which tells a leak from library pages."""
    growth = {}
    if len(rows) >= 2:
        first, last = rows[0]["rss_mb"], rows[-1]["rss_mb"]
        for name, v in first.items():
            if name == "sumo" or name not in last:
                continue
            peak = max(r["rss_mb"].get(name, v) for r in rows[1:])
            growth[name] = {"after_min1_mb": v, "last_mb": last[name], "peak_mb": peak,
                            "growth_pct": round((last[name] - v) / v * 100.0, 2) if v else None}
            h0, h1 = rows[0].get("heap_mb", {}).get(name), rows[-1].get("heap_mb", {}).get(name)
            if h0 and h1 and h0 == h0 and h1 == h1:  # both known (not NaN)
                growth[name]["heap_growth_pct"] = round((h1 - h0) / h0 * 100.0, 2)
    sumo = [r["rss_mb"]["sumo"] for r in rows if "sumo" in r["rss_mb"]]
    rec = out / "run.mcap"
    return {
        "bench": "soak", "summary": True, "minutes": round(wall / 60.0, 2),
        "rows": len(rows), "growth": growth,
        "sumo_rss_mb_min_max": [min(sumo), max(sumo)] if sumo else None,
        "errors": rows[-1]["errors"] if rows else None,
        "steps": rows[-1]["steps"] if rows else 0,
        "dropped_steps": rows[-1]["dropped_steps"] if rows else 0,
        "final_exit_codes": codes, "recording_mb": round(rec.stat().st_size / 1e6, 1) if rec.exists() else 0,
        "flat": bool(growth) and all(g["growth_pct"] is not None and g["growth_pct"] < 5.0
                                      for g in growth.values()),
    }


def cli_main(args) -> int:
    cfg = SoakConfig(minutes=float(args.minutes))
    if getattr(args, "config", None):
        cfg = replace(cfg, config=Path(args.config))
    if getattr(args, "out", None):
        cfg = replace(cfg, out=Path(args.out))
    if getattr(args, "sample_s", None):
        cfg = replace(cfg, sample_period_s=float(args.sample_s))

    def emit(row: dict) -> None:
        sys.stdout.write(json.dumps(row) + "\n")
        sys.stdout.flush()

    def on_term(signum, frame):  # stop every process of the soak, as Ctrl-C does
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    rows = run_soak(cfg, emit)
    return 0 if rows and rows[-1].get("errors") == 0 else 1
