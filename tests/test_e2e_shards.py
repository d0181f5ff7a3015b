"""Two physics shards as OS processes in lockstep; one is killed and the other takes over."""

from __future__ import annotations

import time

import numpy as np
import pytest

from protocol.keys import Keys
from protocol.messages import AgentFlag
from tests.harness import PAPER_CFG, Daemon, Probe, endpoint, wait_until

pytestmark = pytest.mark.integration


def test_two_shards_split_the_agents_and_one_takes_over_a_killed_one(tmp_path):
    cfg = tmp_path / "run.toml"
    cfg.write_text(f"""
[run]
id = "shards"
timing = "lockstep"
duration_s = 40.0
lockstep_timeout_s = 20.0
[sumo]
sumocfg = "{PAPER_CFG}"
lockstep_instances = ["main.0of2", "main.1of2"]
[physics]
preset = "default"
shards = 1
shard_tile_m = 60.0
shard_halo_m = 10.0
""")
    keys = Keys("sumoco", "shards")
    sumo_ep, p0_ep, p1_ep = endpoint(), endpoint(), endpoint()
    logs = tmp_path / "logs"
    probe = Probe(keys, [sumo_ep, p0_ep, p1_ep])
    daemons = []
    try:
        # the bundled scenario is small: tiles of 60 m spread it over both shards
        for i, ep in ((0, p0_ep), (1, p1_ep)):
            daemons.append(Daemon(f"physics{i}", ["physics", "--config", str(cfg), "--shard", f"{i}/2",
                                                  "--listen", ep, "--connect", sumo_ep], logs))
        sumo = Daemon("sumo", ["sumo", "--config", str(cfg), "--listen", sumo_ep, "--quiet"], logs)
        daemons.append(sumo)
        p0, p1 = daemons[0], daemons[1]

        def both_busy():
            s0, s1 = probe.last_physics("main.0of2"), probe.last_physics("main.1of2")
            return s0 is not None and s1 is not None and len(s0.agents.ids) > 0 and len(s1.agents.ids) > 0
        wait_until(both_busy, 120, "both shards simulating agents", procs=daemons)
        # the shards split the agents of a step: no agent in both
        s0, s1 = probe.last_physics("main.0of2"), probe.last_physics("main.1of2")
        assert not set(s0.agents.ids) & set(s1.agents.ids)
        t_kill = time.monotonic()  # before: kill() waits for the process to end
        p1.kill()

        def taken_over():
            st = probe.last_physics("main.0of2")
            steps = {m.step: m for m in probe.steps}
            m = steps.get(st.sumo_step) if st is not None else None
            if m is None or st.counters.get("shards_alive") != 1:
                return None
            a = m.agents
            want = {a.ids[i] for i in range(a.n) if not a.flags[i] & AgentFlag.INSIDE_VEHICLE}
            return st if want and want <= set(st.agents.ids) else None
        st = wait_until(taken_over, 30, "shard 0 simulating every agent", procs=[sumo, p0])
        took = time.monotonic() - t_kill
        print(f"take-over: {took:.3f} s")  # shown with -rP
        assert st.counters["shard_takeovers"] > 0
        # liveliness notice + one lockstep step + spawning its agents (their sizes have pools
        # reserved in the background; `sumoco bench scale` measures the time). The goal is
        # 1 s; 2 s leaves a margin for a loaded machine (0.1-0.3 s measured at load 6-9 on 2 cores)
        assert took < 2.0, took
        # the run goes on to its end in lockstep with the surviving shard
        # (shard 0 may finish its last step and exit before the SUMO side does)
        wait_until(lambda: sumo.poll() is not None, 180, "SUMO side reaching the run's duration")
        assert sumo.returncode == 0, sumo.tail()
        assert max(m.step for m in probe.steps) >= 399
        wait_until(lambda: p0.poll() is not None, 30, "shard 0 finishing")
        assert p0.returncode == 0, p0.tail()
    finally:
        for d in daemons:
            d.terminate(5)
        probe.close()
