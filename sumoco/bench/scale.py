"""``sumoco bench scale``: how far one machine goes, each number beside its limit from the same run.

Rows (one JSON object each; field names stable across versions):

- pool rows: ``pool_slots``, ``build_s`` (world build: spec + compile + batch), ``rss_mb``
  (peak resident memory of a fresh process that only builds the world), with the goals
  ``goal_build_s`` / ``goal_rss_mb`` and ``template_build_s`` (one slot, the floor).
- co-simulation rows, per size and with LOD off / on: ``agents``, ``lod``,
  ``full_physics_agents``, ``sumo_alone_steps_per_s`` and ``cosim_steps_per_s`` (the
  same grid scenario: SUMO's own steps alone, then the whole lockstep chain per step in
  one process: SUMO step, bridge, encode, decode, apply, ``ticks_per_step`` physics
  ticks, state encode), ``bridge_ms``, ``sumo_step_ms``, ``bytes_per_step``,
  ``physics_tick_ms``, ``mujoco_ms`` (MuJoCo's own step of the same bodies),
  ``rss_mb``, ``cosim_to_sumo_ratio``; the same per step in CPU time
  (``sumo_alone_cpu_ms``, ``cosim_cpu_ms``, ``cosim_to_sumo_cpu_ratio``: all threads of
  the process, not inflated by other load) and ``load_avg_1min``. The transport between processes is not in
  these rows (``sumoco bench e2e`` measures it against raw Zenoh).

- per co-simulation row, where its CPU time goes: ``cpu_ms_<phase>`` for the phases of
  ``PHASES`` (SUMO's step; SUMO read + bridge + encode; decode; LOD split; fleet sync;
  MuJoCo; the rest of the control ticks; snapshot + state encode).
- shard rows: ``shards``, ``agents_realtime`` (most full-physics cars that many physics
  processes, one thread each, keep at real-time factor >= 1), ``vs_one_shard``; the same
  from CPU time per tick (``agents_realtime_cpu``, ``vs_one_shard_cpu``).
- ``scale_processes`` rows (``sumoco.bench.processes``): ``processes``, ``agents_realtime``,
  ``vs_linear``: the same figure through one command, ``sumoco physics --processes p``
  (supervisor, shard processes, Zenoh, a lockstep run driven from this process);
  ``bare_vs_one`` (the shard row's ``vs_one_shard`` at the same count: the host's own limit)
  and ``vs_bare`` (``processes x vs_linear / bare_vs_one``).
- take-over row: ``takeover_s`` from a SIGKILL of one of two lockstep shards until the
  survivor publishes every agent (``new_size``: the killed shard had a vehicle size the
  survivor had not simulated).
- lockstep row: the whole system as two OS processes (SUMO side, one physics process) in
  lockstep over Zenoh, LOD on: ``lockstep_ms`` / ``lockstep_cpu_ms`` per step (wall clock;
  CPU time of both daemons) against ``sumo_alone_ms`` / ``sumo_alone_cpu_ms`` on the same
  scenario, ``lockstep_to_sumo_ratio`` / ``lockstep_to_sumo_cpu_ratio`` (the SUMO side
  computes step k+1 while the physics side works on step k, so wall clock overlaps).
- realtime row: ``agents``, ``lag_resets`` (SUMO side in realtime at 10 Hz with a physics
  process, ``steps`` done in ``wall_s`` against ``realtime_steps``).

With LOD on, a region around the network centre holds about ``FULL_AGENTS`` agents in
full physics; the rest never enter MuJoCo (``physics_side.lod.DetailSplit``, as in the
daemon) and are published on their extrapolated SUMO pose.
"""

from __future__ import annotations

import json
import logging
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import numpy as np

from sumoco.bench.processes import process_rows as supervised_rows
from sumoco.bench.scenario import FILL_SHARE, PAPER_SUMOCFG, fill, grid_scenario, write_toml

log = logging.getLogger(__name__)

FULL_AGENTS = 500  # agents in full physics with LOD on (the goal: >= 500)
GOAL_BUILD_S = 5.0  # [s] pool build for 4,096 slots
GOAL_RSS_MB = 2048.0  # [MB]
# where the CPU time of one lockstep step goes (``cpu_ms_<phase>`` per co-simulation row)
PHASES = ("sumo_step", "sumo_read_bridge_encode", "decode", "lod_split", "fleet_apply", "mujoco", "ticks_python",
          "snapshot_encode")

_POOL_CODE = """
import json, resource, time
t0 = time.perf_counter()
from physics_side.world import PhysicsWorld, HEADROOM
from protocol.messages import AgentClass
t1 = time.perf_counter()
w = PhysicsWorld(0.005, 4, shards=2, threads=2, initial={{}}, expect={{AgentClass.PASSENGER: int({slots} / HEADROOM)}})
t2 = time.perf_counter()
print(json.dumps({{"pool_slots": w.capacity, "simulations": w.shards, "build_s": round(t2 - t1, 3),
                  "rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}}))
"""


def _load() -> float:
    """The host's 1-minute load average: other processes share the cores the rows measure."""
    return round(os.getloadavg()[0], 2)


def pool_row(slots: int) -> dict:
    """Build a world of about ``slots`` passenger slots in a fresh process."""
    out = subprocess.run([sys.executable, "-c", _POOL_CODE.format(slots=slots)], capture_output=True, text=True,
                         timeout=600, check=True)
    row = json.loads(out.stdout.strip().splitlines()[-1])
    one = json.loads(subprocess.run([sys.executable, "-c", _POOL_CODE.format(slots=2)], capture_output=True,
                                    text=True, timeout=600, check=True).stdout.strip().splitlines()[-1])
    row.update(load_avg_1min=_load(), template_build_s=one["build_s"], template_rss_mb=one["rss_mb"],
               goal_build_s=GOAL_BUILD_S, goal_rss_mb=GOAL_RSS_MB)
    return row


def _lod_region(x: np.ndarray, y: np.ndarray, n_full: int) -> tuple[float, float, float]:
    """A circle around the agents' centre holding about ``n_full`` of them [m]."""
    cx, cy = float(np.median(x)), float(np.median(y))
    d = np.sort(np.hypot(x - cx, y - cy))
    r = float(d[min(n_full, len(d)) - 1]) if len(d) else 1.0
    return cx, cy, max(r, 1.0)


@contextmanager
def _filled(sumocfg, size: int, seed: int):
    """SUMO on ``sumocfg`` in this process, filled to about ``size`` vehicles: (simulation,
    bridge, last step index, snapshot); closed on leaving."""
    from sumo_side.bridge import Bridge
    from sumo_side.config import SumoConfig
    from sumo_side.simulation import SumoSim

    cfg = SumoConfig(sumocfg=sumocfg)
    sim = SumoSim(cfg, seed=seed, run_id="bench")
    sim.start()
    try:
        bridge = Bridge(sim, cfg, "bench")
        yield (sim, bridge, *fill(sim, bridge, size))
    finally:
        sim.close()


def _alone_steps(sim, bridge, k: int, snap, steps: int):
    """SUMO's own step [s] (wall and CPU lists) for ``steps`` steps after step ``k``; the
    read and bridge run between steps, untimed. Returns the last step index and snapshot too."""
    wall, cpu = [], []
    for _ in range(steps):
        k += 1
        t0, c0 = time.perf_counter(), time.process_time()
        sim.step()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        snap = sim.read()
        bridge.build(k, snap)
    return k, snap, wall, cpu


def _cosim_fleet(snap, lod: bool):
    """The physics side of one co-simulation row, sized for ``snap``: its fleet, rates and
    (LOD on) the detail split that keeps agents outside its zone out of the fleet."""
    from physics_side.config import PhysicsConfig, PhysicsSettings, check_rates
    from physics_side.daemon import build_fleet
    from physics_side.lod import DetailSplit, DetailZones

    split = None
    expect = snap.n * 1.1
    if lod:  # as the daemon does: agents outside the zone never reach the fleet
        region = _lod_region(np.asarray(snap.x), np.asarray(snap.y), FULL_AGENTS)
        split = DetailSplit(DetailZones.from_config(0.0, [region]))
        expect = FULL_AGENTS * 1.3
    phys = PhysicsConfig(shards=2, threads=2, initial_slots={}, expect={"passenger": int(expect)}, preset="default")
    rates = check_rates(phys.sumo_step_s, phys.control_hz, phys.timestep_s)
    fleet = build_fleet(PhysicsSettings(physics=phys))
    fleet.world.measure_cpu = True  # the rows split CPU time into MuJoCo's and the rest
    return fleet, rates, split


def _cosim_steps(sim, bridge, fleet, rates, split, k: int, steps: int) -> dict[str, list]:
    """The lockstep chain for ``steps`` steps (after 5 that spawn the whole network): per
    step its wall and CPU times by part, message size, agents and agents in full physics."""
    from protocol.codec import decode_as, encode
    from protocol.messages import AgentMode, PhysicsState, StepMessage

    perf, cpu = time.perf_counter, time.process_time
    t = {name: [] for name in ("sumo_wall", "bridge_wall", "total_wall", "total_cpu", "tick_wall", "mujoco_wall",
                               "bytes", "agents", "full", *PHASES)}
    for i in range(steps + 5):
        k += 1
        t0, c0 = perf(), cpu()
        sim.step()
        t1, c1 = perf(), cpu()
        snap = sim.read()
        data = encode(bridge.build(k, snap))
        t2, c2 = perf(), cpu()
        msg = decode_as(data, StepMessage)
        cd = cpu()
        near = msg if split is None else split.apply(msg)
        cl = cpu()
        fleet.apply_step(near)
        ca = cpu()
        m0 = fleet.world.mujoco_s
        mc0 = fleet.world.mujoco_cpu_s
        ticks = []
        for _ in range(rates.ticks_per_step):
            tt = perf()
            fleet.tick()
            ticks.append(perf() - tt)
        ct = cpu()
        agents = fleet.snapshot() if split is None else split.snapshot(fleet.snapshot(), msg.time)
        encode(PhysicsState(run="bench", tick=fleet.tick_count, time=msg.time, sumo_step=msg.step,
                            agents=agents, counters={}))
        t3, c3 = perf(), cpu()
        if i < 5:  # the first steps spawn the whole network
            continue
        mj_cpu = fleet.world.mujoco_cpu_s - mc0
        for p, v in zip(PHASES, (c1 - c0, c2 - c1, cd - c2, cl - cd, ca - cl, mj_cpu, ct - ca - mj_cpu, c3 - ct)):
            t[p].append(v)
        t["sumo_wall"].append(t1 - t0)
        t["bridge_wall"].append(t2 - t1)
        t["total_wall"].append(t3 - t0)
        t["total_cpu"].append(c3 - c0)
        t["tick_wall"].append(float(np.mean(ticks)))
        t["mujoco_wall"].append((fleet.world.mujoco_s - m0) / rates.ticks_per_step)
        t["bytes"].append(len(data))
        t["agents"].append(msg.agents.n)
        t["full"].append(int((fleet.mode == AgentMode.PHYSICAL).sum()))
    return t


def _cosim_row(lod: bool, steps: int, alone: list, alone_cpu: list, t: dict[str, list], ticks_per_step: int,
               simulations: int) -> dict:
    ms = lambda xs: round(float(np.mean(xs)) * 1e3, 3)  # noqa: E731
    return {
        "agents": int(round(float(np.mean(t["agents"])))), "lod": lod, "full_physics_agents": int(np.mean(t["full"])),
        "sumo_alone_steps_per_s": round(1.0 / float(np.mean(alone)), 2),
        "cosim_steps_per_s": round(1.0 / float(np.mean(t["total_wall"])), 2),
        "cosim_to_sumo_ratio": round(float(np.mean(alone)) / float(np.mean(t["total_wall"])), 3),
        "bridge_ms": ms(t["bridge_wall"]), "sumo_step_ms": ms(t["sumo_wall"]),
        "bridge_to_sumo_ratio": round(float(np.mean(t["bridge_wall"])) / float(np.mean(t["sumo_wall"])), 3),
        "bytes_per_step": int(np.mean(t["bytes"])), "physics_tick_ms": ms(t["tick_wall"]),
        "mujoco_ms": ms(t["mujoco_wall"]),
        "ticks_per_step": ticks_per_step, "simulations": simulations,
        "rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1), "steps": steps,
        # CPU time (all threads of this process): robust to other load on the machine
        "sumo_alone_cpu_ms": ms(alone_cpu), "cosim_cpu_ms": ms(t["total_cpu"]),
        "cosim_to_sumo_cpu_ratio": round(float(np.mean(alone_cpu)) / float(np.mean(t["total_cpu"])), 3),
        "load_avg_1min": _load(),
        **{f"cpu_ms_{p}": ms(t[p]) for p in PHASES},
    }


def cosim_rows(size: int, steps: int, lod_modes=(False, True), seed: int = 42) -> list[dict]:
    """SUMO alone, then the lockstep chain with LOD off / on, on one grid scenario."""
    sumocfg = grid_scenario(size, seed=seed)
    rows = []
    for lod in lod_modes:
        with _filled(sumocfg, size, seed) as (sim, bridge, k, snap):
            k, snap, alone, alone_cpu = _alone_steps(sim, bridge, k, snap, steps)
            fleet, rates, split = _cosim_fleet(snap, lod)
            times = _cosim_steps(sim, bridge, fleet, rates, split, k, steps)
            fleet.world.close()
        rows.append(_cosim_row(lod, steps, alone, alone_cpu, times, rates.ticks_per_step, fleet.world.shards))
        log.info("bench scale: %s", rows[-1])
    return rows


# ---------------------------------------------------------------------- shard processes

_SHARD_WORKER = """
import json, sys, time
import numpy as np
from dataclasses import replace
from physics_side.config import PhysicsSettings, check_rates
from physics_side.daemon import build_fleet
from protocol.codec import decode_as, encode
from protocol.messages import StepMessage
from synthetic.traffic import circle_traffic
n, seconds = {n}, {seconds}
s = PhysicsSettings()
s = replace(s, physics=replace(s.physics, shards=1, threads=1, initial_slots={{"passenger": n + 8}}, preset="default",
                               presets={{}}))
cfg = s.physics
rates = check_rates(cfg.sumo_step_s, cfg.control_hz, cfg.timestep_s)
fleet = build_fleet(s)
for k in range(3):  # spawn and settle before the clock starts
    fleet.apply_step(decode_as(encode(circle_traffic(n, k, cfg.sumo_step_s)), StepMessage))
    for _ in range(rates.ticks_per_step):
        fleet.tick()
print("ready", flush=True)
sys.stdin.readline()  # every shard process starts measuring at once
ticks, cpu = [], []
k = 3
t_end = time.perf_counter() + seconds
while time.perf_counter() < t_end:
    t0, c0 = time.perf_counter(), time.process_time()
    fleet.apply_step(decode_as(encode(circle_traffic(n, k, cfg.sumo_step_s)), StepMessage))
    for _ in range(rates.ticks_per_step):
        fleet.tick()
    ticks.append((time.perf_counter() - t0) / rates.ticks_per_step)
    cpu.append((time.process_time() - c0) / rates.ticks_per_step)
    k += 1
print(json.dumps({{"tick_ms": 1e3 * float(np.mean(ticks)), "tick_cpu_ms": 1e3 * float(np.mean(cpu)),
                  "control_dt_ms": 1e3 * rates.control_dt}}), flush=True)
"""


def _shard_ticks(shards: int, per_shard: int, seconds: float = 3.0) -> float:
    """Mean control-tick time [ms] of the slowest of ``shards`` physics processes (one thread
    each) stepping ``per_shard`` cars at once: a physics step and its controllers, SUMO
    steps decoded as the daemon does (no transport)."""
    procs = [subprocess.Popen([sys.executable, "-c", _SHARD_WORKER.format(n=per_shard, seconds=seconds)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True) for _ in range(shards)]
    try:
        for p in procs:
            if p.stdout.readline().strip() != "ready":
                raise RuntimeError(f"shard worker failed (exit {p.wait()})")
        for p in procs:
            p.stdin.write("go\n")
            p.stdin.flush()
        out = [json.loads(p.stdout.readline()) for p in procs]
    finally:
        for p in procs:
            p.kill() if p.poll() is None and p.wait(30) is None else None
    return max(o["tick_ms"] for o in out), max(o["tick_cpu_ms"] for o in out), out[0]["control_dt_ms"]


def shard_rows(counts=(1, 2), probe=(150, 450), seconds: float = 3.0) -> list[dict]:
    """``agents_realtime`` per shard count: the most full-physics cars that ``shards``
    processes keep at real-time factor >= 1 (a control tick within its period), from the
    tick time at two sizes per shard (linear in the cars), each measured for ``seconds``."""
    rows = []

    def most(t_a: float, t_b: float, dt: float) -> int:
        slope = max((t_b - t_a) / (probe[1] - probe[0]), 1e-9)
        return max(0, int(probe[0] + (dt - t_a) / slope))

    for k in counts:
        (t_a, c_a, dt), (t_b, c_b, _) = (_shard_ticks(k, n, seconds) for n in probe)
        rows.append({"shards": k, "agents_realtime": most(t_a, t_b, dt) * k,
                     # the same from CPU time per tick: what each process needs of one core
                     # (independent of other load; equal to the wall figure on an idle host)
                     "agents_realtime_cpu": most(c_a, c_b, dt) * k,
                     "tick_ms_at": {probe[0]: round(t_a, 3), probe[1]: round(t_b, 3)},
                     "tick_cpu_ms_at": {probe[0]: round(c_a, 3), probe[1]: round(c_b, 3)},
                     "control_dt_ms": dt, "threads_per_shard": 1, "load_avg_1min": _load()})
        log.info("bench scale: %s", rows[-1])
    if len(rows) >= 2 and rows[0]["agents_realtime"]:
        for r in rows[1:]:
            r["vs_one_shard"] = round(r["agents_realtime"] / rows[0]["agents_realtime"], 2)
            r["vs_one_shard_cpu"] = round(r["agents_realtime_cpu"] / max(rows[0]["agents_realtime_cpu"], 1), 2)
    return rows


class _Procs:
    """``sumoco`` daemons as OS processes (the demo's ``Processes``: output to log files, none
    outlives the row), and a Zenoh probe of the run."""

    def __init__(self, run: str, connect: list[str], log_dir, probe: bool = True):
        """``connect``: the endpoints the daemons listen on (``endpoints``), the probe connects
        to them. ``probe`` False: no subscription to steps and states (decoding 10,000 agents
        at 50 Hz would take a core from the daemons being measured)."""
        import threading

        from protocol.codec import decode
        from protocol.keys import Keys
        from runtime.config import ZenohConfig
        from runtime.transport import free_tcp_port, open_session
        from sumoco.orchestrate.demo import Processes

        self.keys = Keys("sumoco", run)
        self.endpoints = list(connect)
        self.log_dir = log_dir
        self.daemons = Processes(log_dir)
        self.procs: dict[str, subprocess.Popen] = self.daemons.procs
        self.lock = threading.Lock()
        self.steps: dict = {}
        self.states: dict = {}
        self.session = open_session(ZenohConfig(listen=(f"tcp/127.0.0.1:{free_tcp_port()}",),
                                                connect=tuple(connect)), "viewer")

        def on_step(s):
            m = decode(s.payload.to_bytes())
            with self.lock:
                self.steps[m.step] = m
                self.steps.pop(m.step - 200, None)  # bounded: only recent steps are looked up

        def on_state(s):
            m = decode(s.payload.to_bytes())
            with self.lock:
                self.states[Keys.instance_of(str(s.key_expr))] = m

        self.subs = [self.session.declare_subscriber(self.keys.step, on_step),
                     self.session.declare_subscriber(self.keys.physics_state_all, on_state)] if probe else []

    def start(self, name: str, args: list[str]) -> None:
        from sumoco.orchestrate.demo import cli_argv

        self.daemons.start(name, cli_argv(*args))

    def start_pair(self, config) -> None:
        """The SUMO side on the first endpoint and one physics process on the second."""
        eps = self.endpoints
        self.start("physics", ["physics", "--config", str(config), "--listen", eps[1], "--connect", eps[0]])
        self.start("sumo", ["sumo", "--config", str(config), "--listen", eps[0]])  # INFO: its summary

    def wait(self, cond, timeout_s: float, what: str):
        deadline = time.monotonic() + timeout_s
        while True:
            v = cond()
            if v:
                return v
            for n, p in self.procs.items():
                if p.poll() is not None and p.returncode not in (0, -9):
                    raise RuntimeError(f"{n} exited with {p.returncode} while waiting for {what}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"timed out after {timeout_s} s waiting for {what}")
            time.sleep(0.01)

    def sumo_counters(self) -> dict | None:
        """The SUMO side's counters (SPEC.md 3.6), None when it does not answer."""
        import msgpack

        for r in self.session.get(self.keys.sumo_status, timeout=3.0):
            if r.ok is not None:
                return msgpack.unpackb(r.ok.payload.to_bytes(), raw=False)["counters"]
        return None

    def cpu_s(self) -> dict[str, float]:
        """CPU time [s] (user + system, all threads) of each daemon so far."""
        tick = os.sysconf("SC_CLK_TCK")
        out = {}
        for name, p in self.procs.items():
            try:
                with open(f"/proc/{p.pid}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            out[name] = (int(fields[11]) + int(fields[12])) / tick
        return out

    def close(self) -> None:
        self.daemons.stop(timeout_s=15.0)
        self.daemons.close()
        for s in self.subs:
            s.undeclare()
        self.session.close()


SURVIVOR, VICTIM = "main.0of2", "main.1of2"  # the take-over row's shards: the second is killed


class _Takeover:
    """What the probe of the take-over row's run says about its two shards."""

    def __init__(self, run: _Procs, kill_at_s: float) -> None:
        self.run, self.kill_at_s = run, kill_at_s
        self.seen: set = set()  # vehicle sizes the survivor has simulated

    @staticmethod
    def sizes(st, m) -> set:
        """(class, length, width) of the agents of state ``st``, from their step ``m``."""
        a = m.agents
        size = {a.ids[i]: (int(a.cls[i]), round(float(a.length[i]), 1), round(float(a.width[i]), 1))
                for i in range(a.n)}
        return {size[i] for i in st.agents.ids if i in size}

    def _latest(self, inst: str):
        with self.run.lock:
            st = self.run.states.get(inst)
            return st, self.run.steps.get(st.sumo_step) if st is not None else None

    def busy(self, new_size: bool) -> bool:
        """Both shards simulate agents past ``kill_at_s``; with ``new_size``, the one to kill
        also has a vehicle size the survivor has not simulated (so far)."""
        with self.run.lock:
            s0, s1 = self.run.states.get(SURVIVOR), self.run.states.get(VICTIM)
            m = self.run.steps.get(s1.sumo_step) if s1 is not None else None
        if not (s0 is not None and m is not None and s0.time >= self.kill_at_s and len(s0.agents.ids) > 0
                and len(s1.agents.ids) > 0):
            return False
        return not new_size or bool(self.sizes(s1, m) - self.seen)

    def track(self) -> bool:
        """``busy(True)``, noting the sizes the survivor simulates meanwhile."""
        st, m = self._latest(SURVIVOR)
        if m is not None:
            self.seen.update(self.sizes(st, m))
        return self.busy(True)

    def taken_over(self):
        """The survivor's state once it simulates every agent of its step alone, else None."""
        from protocol.messages import AgentFlag

        st, m = self._latest(SURVIVOR)
        if m is None or st.counters.get("shards_alive") != 1:
            return None
        a = m.agents
        want = {a.ids[i] for i in range(a.n) if not a.flags[i] & AgentFlag.INSIDE_VEHICLE}
        return st if want and want <= set(st.agents.ids) else None


TAKEOVER_TIMEOUT_S = 60.0  # [s] a take-over slower than this fails the row


def takeover_row(kill_at_s: float = 20.0, timeout_s: float = TAKEOVER_TIMEOUT_S) -> dict:
    """Two physics shards in lockstep on the bundled scenario; one is killed (SIGKILL) once
    SUMO time passes ``kill_at_s``: ``takeover_s`` is the wall time from the kill until the
    survivor publishes a state with every agent of that step. A row that times out raises
    ``RuntimeError`` naming the folder with the daemons' logs."""
    tmp = Path(tempfile.mkdtemp(prefix="sumoco-takeover-"))
    cfg = write_toml(tmp / "run.toml", {
        "run": {"id": "takeover", "timing": "lockstep", "duration_s": kill_at_s + 200.0, "lockstep_timeout_s": 20.0},
        "sumo": {"sumocfg": PAPER_SUMOCFG, "lockstep_instances": [SURVIVOR, VICTIM]},
        "physics": {"preset": "default", "shards": 1, "shard_tile_m": 60.0, "shard_halo_m": 10.0}})
    eps = _endpoints(3)
    run = _Procs("takeover", eps, tmp)
    watch = _Takeover(run, kill_at_s)
    try:
        for i in (0, 1):
            run.start(f"physics{i}", ["physics", "--config", str(cfg), "--shard", f"{i}/2", "--listen", eps[1 + i],
                                      "--connect", eps[0]])
        run.start("sumo", ["sumo", "--config", str(cfg), "--listen", eps[0], "--quiet"])
        run.wait(lambda: watch.busy(False), 300, "both shards simulating agents")
        try:
            run.wait(watch.track, 20, "a vehicle size only the shard to kill has")
            new_size = True
        except RuntimeError:
            new_size = False
        with run.lock:
            victim = len(run.states[VICTIM].agents.ids)
        run.procs["physics1"].kill()
        t_kill = time.monotonic()
        try:
            st = run.wait(watch.taken_over, timeout_s, "shard 0 simulating every agent")
        except RuntimeError as e:
            raise RuntimeError(f"{e} (logs in {tmp})") from None
        took = time.monotonic() - t_kill
    finally:
        run.close()
    shutil.rmtree(tmp, ignore_errors=True)
    c = st.counters
    row = {"shards": 2, "takeover_s": round(took, 3), "agents_of_killed_shard": victim, "new_size": new_size,
           "agents_after": len(st.agents.ids), "shard_takeovers": c.get("shard_takeovers"),
           "pool_grows": c.get("pool_grows"), "growth_waits": c.get("growth_waits"), "goal_takeover_s": 1.0,
           "load_avg_1min": _load()}
    log.info("bench scale: %s", row)
    return row


def takeover_bench(runs: int = 20, kill_at_s: float = 8.0) -> list[dict]:
    """``takeover_row`` ``runs`` times in a row, then one summary row: take-over times p50 and
    max [s] and the runs that failed (timed out; each failure row says why and where its logs are)."""
    rows = []
    for i in range(runs):
        try:
            row = takeover_row(kill_at_s)
        except RuntimeError as e:
            row = {"shards": 2, "error": str(e)}
            log.warning("bench takeover: run %d of %d failed: %s", i + 1, runs, e)
        rows.append({"run": i, **row})
    took = [r["takeover_s"] for r in rows if "takeover_s" in r]
    rows.append({"summary": "takeover", "runs": runs, "ok": len(took), "failed": runs - len(took),
                 "takeover_p50_s": round(float(np.median(took)), 3) if took else None,
                 "takeover_max_s": round(max(took), 3) if took else None, "kill_at_s": kill_at_s,
                 "load_avg_1min": _load()})
    return rows


def _sumo_alone(sumocfg, size: int, steps: int, seed: int = 42) -> tuple[float, float, np.ndarray, np.ndarray]:
    """SUMO's own step [s] (wall, CPU) on ``sumocfg`` filled to ``size`` vehicles, averaged
    over ``steps`` (the read and bridge run between steps, untimed, as in ``cosim_rows``),
    and the vehicles' last positions x, y [m]."""
    with _filled(sumocfg, size, seed) as (sim, bridge, k, snap):
        _, snap, wall, cpu = _alone_steps(sim, bridge, k, snap, steps)
    return float(np.mean(wall)), float(np.mean(cpu)), np.asarray(snap.x), np.asarray(snap.y)


def _endpoints(n: int) -> list[str]:
    from runtime.transport import free_tcp_port

    return [f"tcp/127.0.0.1:{free_tcp_port()}" for _ in range(n)]


class _GridRun(NamedTuple):
    folder: Path  # the run's config and the daemons' logs
    config: Path  # its run TOML
    alone_wall_s: float  # [s] SUMO's own step on the same scenario, wall clock
    alone_cpu_s: float  # [s] the same in CPU time

    def alone_ms(self) -> dict:
        return {"sumo_alone_ms": round(self.alone_wall_s * 1e3, 2),
                "sumo_alone_cpu_ms": round(self.alone_cpu_s * 1e3, 2)}

    def full_physics_counts(self) -> list[int]:
        """Agents in full physics in the physics process's status lines, in order."""
        text = (self.folder / "physics.log").read_text(errors="replace")
        return [int(n) for n in re.findall(r"\(phys (\d+) ", text)]


def _grid_run(timing: str, agents: int, full: int, alone_steps: int, shards: int, run: dict,
              sumo: dict | None = None) -> _GridRun:
    """The lockstep and realtime rows' set-up: the grid scenario of ``agents`` vehicles, SUMO
    alone on it in this process (before any daemon starts), and the run config of a SUMO side
    and one physics process of ``shards`` simulations (one thread each) with LOD, a region of
    about ``full`` agents in full physics. ``run`` and ``sumo`` add to those tables."""
    from physics_side.lod import HYSTERESIS

    sumocfg = grid_scenario(agents, seed=42)
    alone_wall, alone_cpu, x, y = _sumo_alone(sumocfg, agents, alone_steps)
    # the same run (seed) in the daemons: a region around ``full`` / HYSTERESIS agents of this
    # fill keeps about ``full`` in full physics (an agent enters at 0.9 r and leaves at r)
    cx, cy, radius = _lod_region(x, y, int(full / HYSTERESIS))
    folder = Path(tempfile.mkdtemp(prefix=f"sumoco-{timing}-"))
    config = write_toml(folder / "run.toml", {
        "run": {"id": timing, "timing": timing, "seed": 42, **run},
        "sumo": {"sumocfg": sumocfg, **(sumo or {})},
        # a thread per simulation; with one, the SUMO process has the other core of two
        "physics": {"preset": "default", "shards": shards, "threads": shards,
                    "expect": {"passenger": int(full * 1.3)},
                    "lod_regions": [[round(cx, 1), round(cy, 1), round(radius, 1)]]}})
    return _GridRun(folder, config, alone_wall, alone_cpu)


def lockstep_row(agents: int = 10000, seconds: float = 20.0, full: int = FULL_AGENTS, alone_steps: int = 20,
                 shards: int = 1) -> dict:
    """The whole system in lockstep: the SUMO side and a physics process (LOD: a region of
    about ``full`` agents in full physics) as separate OS processes over Zenoh on the grid
    scenario of ``agents`` vehicles, measured for ``seconds`` of wall time once the network
    is full, against SUMO alone on the same scenario (in this process, before the daemons
    start). ``lockstep_to_sumo_ratio``: SUMO alone's step over the system's wall time per
    step; ``lockstep_to_sumo_cpu_ratio``: over the CPU time of both daemons per step;
    ``lockstep_to_sumo_critical_ratio``: SUMO alone's CPU time over the busier daemon's
    (``sumo_side_cpu_ms``, ``physics_cpu_ms``): the wall-clock ratio with a core per process
    and nothing else running, which a loaded host cannot show. The
    physics process runs ``shards`` simulations on as many threads (1: on 2 cores the SUMO
    process has the other)."""
    grid = _grid_run("lockstep", agents, full, alone_steps, shards,
                     run={"duration_s": 3600.0, "lockstep_timeout_s": 60.0},
                     sumo={"lockstep_instances": ["main"], "lockstep_start_timeout_s": 120.0})
    tmp = grid.folder
    run = _Procs("lockstep", _endpoints(2), tmp, probe=False)
    try:
        run.start_pair(grid.config)

        def filled():
            c = run.sumo_counters()
            return c if c is not None and c.get("max_agents", 0) >= FILL_SHARE * agents else None
        run.wait(filled, 600, "the network filled")
        # the map mesh is built once on a worker thread of the SUMO side: not in the window
        sumo_log = tmp / "sumo.log"
        run.wait(lambda: re.search(r"map ready|no map for", sumo_log.read_text(errors="replace")), 300,
                 "the SUMO side's map")
        time.sleep(3.0)
        c0, t0, cpu0 = run.sumo_counters(), time.monotonic(), run.cpu_s()
        time.sleep(seconds)
        c1, t1, cpu1 = run.sumo_counters(), time.monotonic(), run.cpu_s()
        if c0 is None or c1 is None:
            raise RuntimeError("lockstep run: the SUMO side stopped answering status queries")
    finally:
        run.close()
    steps = max(int(c1["steps"]) - int(c0["steps"]), 1)
    wall = (t1 - t0) / steps
    per = {n: (cpu1[n] - cpu0[n]) / steps for n in cpu0 if n in cpu1}
    cpu = sum(per.values())
    # each process on a core of its own (an idle 2-core host): the busier one paces the chain
    critical = max(per.values())
    phys = grid.full_physics_counts()
    row = {"timing": "lockstep", "agents": int(c1["max_agents"]), "processes": 2, "steps": steps,
           "wall_s": round(t1 - t0, 2), "full_physics_agents": max(phys[-5:]) if phys else None,
           **grid.alone_ms(),
           "lockstep_ms": round(wall * 1e3, 2), "lockstep_cpu_ms": round(cpu * 1e3, 2),
           "lockstep_to_sumo_ratio": round(grid.alone_wall_s / wall, 3),
           "lockstep_to_sumo_cpu_ratio": round(grid.alone_cpu_s / cpu, 3),
           "sumo_side_cpu_ms": round(per.get("sumo", 0.0) * 1e3, 2), "physics_cpu_ms": round(per.get("physics", 0.0) * 1e3, 2),
           "lockstep_to_sumo_critical_ratio": round(grid.alone_cpu_s / critical, 3),
           "strict_steps": int(c1.get("strict_steps", 0)) - int(c0.get("strict_steps", 0)),
           "goal_ratio": 0.6, "load_avg_1min": _load()}
    log.info("bench scale: %s", row)
    return row


def realtime_row(agents: int = 5000, seconds: float = 15.0, full: int = FULL_AGENTS, alone_steps: int = 20) -> dict:
    """SUMO side in realtime at its 10 Hz with ``agents`` vehicles and a physics process
    (LOD: a region of about ``full`` agents in full physics), as separate OS processes, for
    ``seconds`` of wall time from the first step: ``lag_resets`` counts the times SUMO fell
    more than ``max_lag_s`` behind the wall clock; ``steps`` against ``seconds`` * 10 shows
    how far from real time it ran; ``sumo_alone_ms`` / ``sumo_alone_cpu_ms`` are SUMO's own
    step on the same scenario in this process before the daemons start (above the step
    length, real time is out of reach whatever the rest costs), ``sumo_ms`` / ``bridge_ms``
    the SUMO side's own figures per step during the run (its status lines)."""
    grid = _grid_run("realtime", agents, full, alone_steps, 1, run={"duration_s": seconds + 120.0})
    # The SUMO side's own duration leaves room for a late probe (its Zenoh connect is retried
    # until the SUMO side listens): the row's window is wall time from the first step seen,
    # and SIGTERM ends the SUMO side after it.
    tmp = grid.folder
    run = _Procs("realtime", _endpoints(2), tmp, probe=False)
    try:
        run.start_pair(grid.config)
        run.wait(lambda: (run.sumo_counters() or {}).get("steps", 0) > 0, 180, "the first step")
        t_end = time.monotonic() + seconds  # wall clock: a SUMO side behind real time ends here
        while time.monotonic() < t_end and run.procs["sumo"].poll() is None:
            time.sleep(0.1)
        run.procs["sumo"].send_signal(signal.SIGTERM)  # ends on the next step with its summary
        run.wait(lambda: run.procs["sumo"].poll() is not None, 60, "the SUMO side's end")
    finally:
        run.close()
    text = (tmp / "sumo.log").read_text(errors="replace")
    m = re.search(r"SUMO side done: (.*)", text)
    if m is None:
        raise RuntimeError(f"realtime run: no summary in the SUMO log:\n{text[-2000:]}")
    stats = dict(kv.split("=", 1) for kv in m[1].split(", "))
    phys = grid.full_physics_counts()
    status = re.findall(r"sumo ([\d.]+) ms bridge ([\d.]+) ms", text)
    row = {"timing": "realtime", "agents": int(stats["max_agents"]), "lag_resets": int(stats["lag_resets"]),
           "steps": int(stats["steps"]), "wall_s": seconds, "realtime_steps": int(seconds / 0.1), "sumo_step_s": 0.1,
           # most in full physics in the physics side's status lines (it stops them when SUMO ends)
           "full_physics_agents": max(phys) if phys else None,
           **grid.alone_ms(),
           "sumo_ms": round(float(np.mean([float(a) for a, _ in status])), 2) if status else None,
           "bridge_ms": round(float(np.mean([float(b) for _, b in status])), 2) if status else None,
           "goal_lag_resets": 0, "load_avg_1min": _load()}
    log.info("bench scale: %s", row)
    return row


def run_scale_bench(sizes=(1000, 2500, 5000, 10000), pool_sizes=(1024, 2048, 4096), steps: int = 30,
                    quick: bool = False, lod_off_max: int = 2500) -> list[dict]:
    """Pool rows, co-simulation rows per size (LOD off only up to ``lod_off_max`` agents: every
    agent in full physics beyond that is minutes per row), shard rows, the take-over of a
    killed shard and the realtime row. Quick (a smoke run of every kind of row but the
    take-over, which ``tests/test_e2e_shards.py`` covers): 1,024 slots, 1,000 agents for
    10 steps, one shard probed at 20 and 60 cars for 1 s each, 1 and 2 supervised processes
    at 20 and 60 cars per process for 10 steps, and 1,000 agents in realtime
    for 3 s with about 100 in full physics."""
    if quick:
        sizes, pool_sizes, steps = (1000,), (1024,), 10
    rows = [pool_row(n) for n in pool_sizes]
    for size in sizes:
        rows.extend(cosim_rows(size, steps, lod_modes=(False, True) if size <= lod_off_max else (True,)))
    if quick:
        process_rows = (("shards", lambda: shard_rows(counts=(1,), probe=(20, 60), seconds=1.0)),
                        ("processes", lambda: supervised_rows(counts=(1, 2), probe=(20, 60), steps=10)),
                        ("lockstep", lambda: [lockstep_row(agents=1000, seconds=3.0, full=100, alone_steps=5)]),
                        ("realtime", lambda: [realtime_row(agents=1000, seconds=3.0, full=100, alone_steps=5)]))
    else:
        process_rows = (("shards", shard_rows), ("processes", supervised_rows), ("takeover", lambda: [takeover_row()]),
                        ("lockstep", lambda: [lockstep_row()]), ("realtime", lambda: [realtime_row()]))
    for name, f in process_rows:
        try:  # processes under load may miss a deadline: the other rows still count
            rows.extend(f())
        except (RuntimeError, OSError, subprocess.SubprocessError) as e:
            log.error("bench scale: %s rows failed: %s", name, e)
            rows.append({"row": name, "error": str(e)})
    _beside_bare_workers(rows)
    return rows


def _beside_bare_workers(rows: list[dict]) -> None:
    """Each ``scale_processes`` row's ``vs_linear`` against what as many bare workers (the
    shard rows: MuJoCo and the fleet, no transport, no supervisor) reach on this host
    (``bare_vs_one``, ``vs_bare``): two copies of one workload on the two cores of a shared
    host do not run at twice the speed of one, and that part is the host's."""
    bare = {r["shards"]: r.get("vs_one_shard") for r in rows if "shards" in r and "agents_realtime" in r}
    for r in rows:
        b = bare.get(r.get("processes"))
        if r.get("bench") == "scale_processes" and b and r.get("vs_linear") is not None:
            r["bare_vs_one"] = b
            r["vs_bare"] = round(r["vs_linear"] * r["processes"] / b, 2)


__all__ = ["cosim_rows", "lockstep_row", "pool_row", "realtime_row", "run_scale_bench", "shard_rows", "takeover_bench",
           "takeover_row"]
