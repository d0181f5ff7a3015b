"""``sumoco bench scale`` rows ``scale_processes``: physics on every core from one command.

For each process count p, ``sumoco physics --processes p`` (the supervisor and its shard
processes, as a user starts them) follows a lockstep run that this process drives as the
SUMO side would: it publishes steps of synthetic circle traffic (encoded before the clock
starts, so its own cost is a ``put``) and waits for every shard's acknowledgement before
the next step. Each step asks the physics side for ``ticks_per_step`` control ticks of
every agent, with the transport, decoding, the shard filter and the state messages of the
real daemon. At two sizes per process count the wall time per step is measured; the most
agents at real time (a step's work within its step length) is where the line through
them crosses the step length, as ``shard_rows`` does for bare workers.

Row: ``{"bench": "scale_processes", "processes", "agents_realtime", "vs_linear"
(agents_realtime / (processes x the one-process figure)), "step_ms_at" (wall time per
step at each probe size), "step_s", "exit_code" (the supervisor's, after the final step),
"restarts", "load_avg_1min"}``, and the same from CPU time: ``agents_realtime_cpu``,
``vs_linear_cpu``, ``step_cpu_ms_at`` (the busiest process's CPU time per step: what it
needs of a core of its own, whatever else the host runs).
"""

from __future__ import annotations

import logging
import os
import re
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

log = logging.getLogger(__name__)

STEP_S = 0.1  # [s] SUMO step length of the synthetic run (real time: a step's work within it)
WARMUP_STEPS = 10  # [steps] spawn and settle before the clock starts
ACK_TIMEOUT_S = 60.0  # [s] a step not acknowledged by every shard in this long fails the row
RESEND_S = 1.0  # [s] a step not yet acknowledged by every shard is sent again (a late subscriber)
START_TIMEOUT_S = 120.0  # [s] for every shard process to be up
EXIT_TIMEOUT_S = 60.0  # [s] for the supervisor to end after the final step
TILE_M = 100.0  # [m] shard tiles: the circle traffic's ring (radius 300-320 m) touches ~25 of them
HALO_M = 10.0  # [m] (a car crosses a tile every ~10 s: each crossing of a shard border is a hand-over)
SHARD_SHARE = 1.1  # [1] agents a shard expects per agent of an even split: tiles never split them evenly
POLL_S = 0.002  # [s] while waiting for acknowledgements


def _load() -> float:
    return round(os.getloadavg()[0], 2)


class _LockstepDriver:
    """The SUMO side's part of a lockstep run: liveliness, steps out, acknowledgements in."""

    def __init__(self, run: str, listen: str) -> None:
        from protocol.codec import decode_as
        from protocol.keys import Keys
        from protocol.messages import StepAck
        from runtime.config import ZenohConfig
        from runtime.transport import open_session

        self.keys = Keys("sumoco", run)
        self.session = open_session(ZenohConfig(listen=(listen,)), "sumo")
        self.lock = threading.Lock()
        self.acked: dict[str, int] = {}
        self.alive: set[str] = set()
        self.bad_acks = 0

        def on_ack(s) -> None:
            try:
                a = decode_as(s.payload.to_bytes(), StepAck)
            except Exception:
                self.bad_acks += 1
                return
            inst = Keys.instance_of(str(s.key_expr))
            with self.lock:
                self.acked[inst] = max(self.acked.get(inst, -1), a.step)

        def on_alive(s) -> None:
            import zenoh

            inst = Keys.instance_of(str(s.key_expr))
            with self.lock:
                (self.alive.add if s.kind == zenoh.SampleKind.PUT else self.alive.discard)(inst)

        self.pub = self.session.declare_publisher(self.keys.step)
        self.decl = [self.session.declare_subscriber(self.keys.ack_all, on_ack),
                     self.session.liveliness().declare_subscriber(self.keys.physics_alive_all, on_alive,
                                                                  history=True),
                     self.session.liveliness().declare_token(self.keys.sumo_alive), self.pub]

    def wait_up(self, instances: set[str], timeout_s: float, proc) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            with self.lock:
                if instances <= self.alive:
                    return
            if proc.poll() is not None:
                raise RuntimeError(f"physics supervisor exited with {proc.returncode} before its shards were up")
            if time.monotonic() > deadline:
                raise RuntimeError(f"shard processes {sorted(instances - self.alive)} not up within {timeout_s} s")
            time.sleep(0.05)

    def step(self, k: int, payload: bytes, instances: set[str]) -> None:
        """Publish step ``k`` and wait until every instance acknowledged it."""
        self.pub.put(payload)
        t0 = sent = time.monotonic()
        while True:
            with self.lock:
                if all(self.acked.get(i, -1) >= k for i in instances):
                    return
            now = time.monotonic()
            if now - t0 > ACK_TIMEOUT_S:
                raise RuntimeError(f"step {k}: no acknowledgement from {sorted(instances)} within {ACK_TIMEOUT_S} s")
            if now - sent > RESEND_S:
                self.pub.put(payload)
                sent = now
            time.sleep(POLL_S)

    def close(self) -> None:
        for d in reversed(self.decl):
            try:
                d.undeclare()
            except Exception:
                pass
        self.session.close()


def _encoded_steps(n: int, count: int, run: str) -> list[bytes]:
    """``count`` steps of ``n`` cars of circle traffic, encoded; the last marked final."""
    from protocol.codec import encode
    from synthetic.traffic import circle_traffic

    steps = [circle_traffic(n, k, STEP_S, run=run) for k in range(count)]
    steps[-1] = replace(steps[-1], final=True)
    return [encode(m) for m in steps]


def _cpu_s(pid: int) -> float:
    """CPU time [s] (user + system, all threads) of process ``pid`` so far, 0 when gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` (the supervisor's shard processes)."""
    out = []
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                if int(f.read().rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(d))
        except (OSError, ValueError, IndexError):
            continue
    return out


class _Measured(NamedTuple):
    step_ms: float  # [ms] wall time per lockstep step
    cpu_ms: float  # [ms] CPU time per step of the busiest physics process
    exit_code: int  # the supervisor's (the daemon's with one process)
    restarts: int


def _step_ms(processes: int, agents: int, steps: int, folder: Path) -> _Measured:
    """``sumoco physics --processes <processes>`` following a lockstep run of ``agents`` cars
    for ``steps`` steps: wall time per step, CPU time per step of the busiest shard
    process, the supervisor's exit code and restarts."""
    from runtime.transport import free_tcp_port
    from sumoco.bench.scenario import write_toml
    from sumoco.orchestrate.demo import Processes, cli_argv

    run = f"procs{processes}x{agents}"
    # pools sized from the agents each process expects (``expect``: no parked slots beyond its
    # headroom, the same number of MuJoCo simulations per agent at every count)
    per = int(agents / processes * (1.0 if processes == 1 else SHARD_SHARE))
    cfg = write_toml(folder / f"{run}.toml", {
        "run": {"id": run, "timing": "lockstep", "duration_s": 0.0, "lockstep_timeout_s": ACK_TIMEOUT_S},
        # one thread per process: processes, not threads, use the cores here
        "physics": {"preset": "default", "shards": 1, "threads": 1, "initial_slots": {}, "expect": {"passenger": per},
                    "shard_tile_m": TILE_M, "shard_halo_m": HALO_M}})
    payloads = _encoded_steps(agents, WARMUP_STEPS + steps + 1, run)
    sumo_ep, phys_ep = (f"tcp/127.0.0.1:{free_tcp_port()}" for _ in range(2))
    instances = {"main"} if processes == 1 else {f"main.{i}of{processes}" for i in range(processes)}
    driver = _LockstepDriver(run, sumo_ep)
    procs = Processes(folder / "logs")
    name = f"physics-{processes}x{agents}"
    try:
        p = procs.start(name, cli_argv("physics", "--config", str(cfg), "--processes", str(processes),
                                       "--listen", phys_ep, "--connect", sumo_ep))
        driver.wait_up(instances, START_TIMEOUT_S, p)
        t0, cpu0, pids = 0.0, {}, []
        for k, payload in enumerate(payloads[:-1]):
            if k == WARMUP_STEPS:
                pids = [p.pid] if processes == 1 else _children(p.pid)
                cpu0 = {q: _cpu_s(q) for q in pids}
                t0 = time.perf_counter()
            driver.step(k, payload, instances)
        wall = (time.perf_counter() - t0) / steps
        cpu = max((_cpu_s(q) - c for q, c in cpu0.items()), default=0.0) / steps
        driver.step(len(payloads) - 1, payloads[-1], instances)  # final: the shards leave
        code = p.wait(EXIT_TIMEOUT_S)
    finally:
        procs.close()
        driver.close()
    text = (folder / "logs" / f"{name}.log").read_text(errors="replace")
    m = re.search(r"physics supervisor done: \d+ shard processes, restarts (\d+)", text)
    return _Measured(wall * 1e3, cpu * 1e3, code, int(m[1]) if m else 0)


def process_counts() -> tuple[int, ...]:
    """1, 2, 4, 8, ... up to ``--processes auto`` on this machine, and that; at least 1 and 2."""
    from physics_side.processes import auto_processes

    top = auto_processes()
    counts = {1, 2, top}
    p = 4
    while p < top:
        counts.add(p)
        p *= 2
    return tuple(sorted(counts))


def process_rows(counts=None, probe=(150, 450), steps: int = 30) -> list[dict]:
    """One ``scale_processes`` row per process count (default ``process_counts()``;
    ``probe``: cars per process at the two sizes measured)."""
    counts = process_counts() if counts is None else counts
    folder = Path(tempfile.mkdtemp(prefix="sumoco-processes-"))
    rows: list[dict] = []
    for p in counts:
        m = {n * p: _step_ms(p, n * p, steps, folder) for n in probe}
        rows.append({"bench": "scale_processes", "processes": p,
                     "agents_realtime": _most({n: x.step_ms for n, x in m.items()}),
                     # the same from CPU time per step of the busiest process: what it needs of a
                     # core of its own (independent of other load; equal on an idle host)
                     "agents_realtime_cpu": _most({n: x.cpu_ms for n, x in m.items()}),
                     "step_ms_at": {str(n): round(x.step_ms, 2) for n, x in m.items()},
                     "step_cpu_ms_at": {str(n): round(x.cpu_ms, 2) for n, x in m.items()}, "step_s": STEP_S,
                     "steps": steps, "exit_code": max((x.exit_code for x in m.values()), key=abs),
                     "restarts": sum(x.restarts for x in m.values()),
                     "cores": len(os.sched_getaffinity(0)), "load_avg_1min": _load()})
        log.info("bench scale: %s", rows[-1])
    one = {r["processes"]: r for r in rows}.get(1)
    for r in rows:
        for field in ("agents_realtime", "agents_realtime_cpu"):
            base = one[field] if one else 0
            r[field.replace("agents_realtime", "vs_linear")] = (
                round(r[field] / (r["processes"] * base), 2) if base else None)
    return rows


def _most(step_ms: dict[int, float]) -> int:
    """Agents at which the line through two (agents, ms per step) points reaches the step length."""
    (n_a, t_a), (n_b, t_b) = step_ms.items()
    slope = max((t_b - t_a) / (n_b - n_a), 1e-9)  # [ms per car]
    return max(0, int(n_a + (STEP_S * 1e3 - t_a) / slope))


__all__ = ["process_counts", "process_rows"]
