"""``sumoco physics --processes 2``: one command, two shard processes under a supervisor.

Real OS processes, real Zenoh on loopback, real MuJoCo: the shards split the agents of a
lockstep run; a shard killed with SIGKILL is restarted while its sibling covers its agents,
and the run ends with exit 0; a shard that keeps failing ends the supervisor with exit 3.
"""

from __future__ import annotations

import os
import re
import signal

import pytest

from physics_side.processes import auto_processes, child_endpoints, parse_processes
from protocol.errors import ConfigError
from protocol.keys import Keys
from protocol.messages import AgentFlag
from runtime.errors import ExitCode
from tests.harness import PAPER_CFG, Daemon, Probe, endpoint, pids_with, wait_until

pytestmark = pytest.mark.integration

SHARDS = ("main.0of2", "main.1of2")


def _config(tmp_path, run_id: str, duration_s: float = 40.0, extra: str = "") -> str:
    cfg = tmp_path / "run.toml"
    cfg.write_text(f"""
[run]
id = "{run_id}"
timing = "lockstep"
duration_s = {duration_s}
lockstep_timeout_s = 20.0
[sumo]
sumocfg = "{PAPER_CFG}"
lockstep_instances = ["main.0of2", "main.1of2"]
[physics]
preset = "default"
shards = 1
shard_tile_m = 60.0
shard_halo_m = 10.0
{extra}
""")
    return str(cfg)


def _simulated(m) -> set[str]:
    """Agents of step ``m`` a physics instance simulates (not persons inside a vehicle)."""
    a = m.agents
    return {a.ids[i] for i in range(a.n) if not a.flags[i] & AgentFlag.INSIDE_VEHICLE}


def _latest_per_step(probe: Probe, inst: str) -> dict:
    """The newest state of ``inst`` for each SUMO step it published."""
    with probe.lock:
        return {st.sumo_step: st for st in probe.physics.get(inst, [])}


def test_processes_flag_values():
    assert parse_processes(None) == 1
    assert parse_processes("3") == 3
    assert parse_processes("auto") == auto_processes() >= 1
    assert auto_processes(cores=16) == 15 and auto_processes(cores=1) == 1 and auto_processes(2, cores=9) == 4
    for bad in ("0", "x", "-2"):
        with pytest.raises(ConfigError):
            parse_processes(bad)
    ports = iter(range(9001, 9100))
    eps = child_endpoints(["tcp/127.0.0.1:7447", "udp/0.0.0.0:7448"], 3, lambda: next(ports))
    assert eps[0] == ["tcp/127.0.0.1:7447", "udp/0.0.0.0:7448"]
    assert eps[1] == ["tcp/127.0.0.1:9001", "udp/0.0.0.0:9003"] and eps[2] == ["tcp/127.0.0.1:9002",
                                                                             "udp/0.0.0.0:9004"]
    assert child_endpoints(None, 2, lambda: 1) == [[], []]


def test_processes_and_shard_exclude_each_other_and_the_config_is_checked(tmp_path):
    from physics_side.config import load_physics_config
    from physics_side.processes import cli_main
    from sumoco.cli import parse_args

    cfg = _config(tmp_path, "procs-args")
    with pytest.raises(ConfigError, match="exclude each other"):
        cli_main(parse_args(["physics", "--config", cfg, "--shard", "0/2", "--processes", "2"]))
    assert load_physics_config({"physics": {"processes": "auto"}}).physics.processes == "auto"
    for bad in ({"processes": "many"}, {"processes": 0}, {"process_restarts": -1}):
        with pytest.raises(ConfigError, match="physics.process"):
            load_physics_config({"physics": bad})


def test_two_shard_processes_cover_every_agent_and_a_killed_one_is_restarted(tmp_path):
    run_id = "procs-kill"
    # long enough that the restart (a new process: imports, compile, join) fits before the end
    # however fast the lockstep run goes with one shard meanwhile (40 s was 5-7 s of wall time)
    duration_s = 120.0
    cfg = _config(tmp_path, run_id, duration_s=duration_s)
    keys = Keys("sumoco", run_id)
    sumo_ep, phys_ep = endpoint(), endpoint()
    logs = tmp_path / "logs"
    probe = Probe(keys, [sumo_ep, phys_ep])
    daemons = []
    try:
        phys = Daemon("physics", ["physics", "--config", cfg, "--processes", "2", "--listen", phys_ep,
                                  "--connect", sumo_ep], logs)
        sumo = Daemon("sumo", ["sumo", "--config", cfg, "--listen", sumo_ep, "--quiet"], logs)
        daemons += [phys, sumo]

        def covered_step():
            """A step both shards published: together every agent, none twice."""
            s0, s1 = (_latest_per_step(probe, i) for i in SHARDS)
            with probe.lock:
                steps = {m.step: m for m in probe.steps[-100:]}
            for k in sorted(set(s0) & set(s1) & set(steps), reverse=True):
                a0, a1 = set(s0[k].agents.ids), set(s1[k].agents.ids)
                if a0 and a1 and a0 | a1 == _simulated(steps[k]):
                    return k, a0, a1
            return None
        k, a0, a1 = wait_until(covered_step, 60, "both shard processes simulating every agent", procs=daemons)
        assert not a0 & a1, f"step {k}: agents in both shards: {a0 & a1}"

        # the shard process of this test's supervisor: its command line names this run's config
        victim = pids_with("--shard", "1/2", "--config", cfg)
        assert len(victim) == 1, victim
        killed_at = probe.last_step().step
        os.kill(victim[0], signal.SIGKILL)

        def shard0_alone():
            st = probe.last_physics(SHARDS[0])
            with probe.lock:
                steps = {m.step: m for m in probe.steps[-100:]}
            m = steps.get(st.sumo_step) if st is not None else None
            return (m is not None and st.counters.get("shards_alive") == 1
                    and _simulated(m) <= set(st.agents.ids))
        wait_until(shard0_alone, 20, "shard 0 covering the killed shard's agents", procs=daemons)

        def back():
            """The restarted shard 1 publishes agents again and shard 0 counts it alive."""
            st1, st0 = probe.last_physics(SHARDS[1]), probe.last_physics(SHARDS[0])
            return (st1 is not None and st1.sumo_step > killed_at and len(st1.agents.ids) > 0
                    and st0.counters.get("shards_alive") == 2)
        wait_until(back, 30, "the restarted shard 1 taking its tiles back", procs=daemons)
        k_back = probe.last_step().step
        # from then on the two shards again publish every agent of a step between them
        k, a0, a1 = wait_until(lambda: (c := covered_step()) is not None and c[0] > k_back and c, 30,
                               "both shards covering every agent after the restart", procs=daemons)
        # shown with -rP: the sibling keeps the agents within its halo, which the restarted shard
        # (no memory of the split) also takes: simulated twice until they leave the halo
        print(f"after the restart, step {k}: {len(a0)} + {len(a1)} agents, {len(a0 & a1)} in both")
        assert pids_with("--shard", "1/2", "--config", cfg) not in ([], victim)  # a new process

        wait_until(lambda: sumo.poll() is not None, 90, "the SUMO side reaching the run's end")
        assert sumo.returncode == 0, sumo.tail()
        assert max(m.step for m in probe.steps) >= round(duration_s / 0.1) - 1
        wait_until(lambda: phys.poll() is not None, 30, "the supervisor ending with its shards")
        assert phys.returncode == 0, phys.tail()
        text = phys.log.read_text(errors="replace")
        assert "shard 1/2 (main.1of2) was killed by SIGKILL" in text
        assert re.search(r"physics supervisor done: 2 shard processes, restarts 1\b", text), phys.tail()
        assert text.count("finished the run") == 2
    finally:
        for d in daemons:
            d.terminate(5)
        probe.close()


def test_a_shard_that_keeps_failing_ends_the_supervisor_with_exit_3(tmp_path):
    # 192.0.2.0/24 (TEST-NET-1) is no address of this host: every shard fails to listen
    cfg = _config(tmp_path, "procs-fail", extra="process_restarts = 1")
    phys = Daemon("physics", ["physics", "--config", cfg, "--processes", "2", "--listen",
                              f"tcp/192.0.2.1:{endpoint().rsplit(':', 1)[1]}"], tmp_path / "logs")
    try:
        wait_until(lambda: phys.poll() is not None, 60, "the supervisor giving up")
        assert phys.returncode == ExitCode.PROCESS_FAILED == 3, phys.tail()
        last = [ln for ln in phys.log.read_text(errors="replace").splitlines() if ln.startswith("sumoco physics: ")]
        assert last, phys.tail()
        assert re.search(r"shard \d/2 \(main\.\dof2\) exited with code 1: cannot open the Zenoh session", last[-1]), \
            last[-1]
        assert "restart limit 1" in last[-1] and "giving up" in last[-1]
        assert not pids_with("--shard", "0/2", "--config", cfg) and not pids_with("--shard", "1/2", "--config", cfg)
    finally:
        phys.terminate(5)
