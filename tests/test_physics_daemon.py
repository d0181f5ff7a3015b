"""The physics daemon as a real OS process against a fake SUMO side in the test.

The test's Zenoh session plays the SUMO side: it declares the SUMO liveliness token and
publishes synthetic StepMessages (cars on circular lanes, ``sumoco.bench.physics``);
the daemon (``sumoco physics``) runs in lockstep and must: acknowledge every step,
report the agents of each step in PhysicsState, drop agents that left, count a
malformed step as rejected and carry on, bring agents to a safe stop (mode STOPPING)
when the SUMO token disappears, resynchronise when SUMO comes back at step 0, and exit
cleanly on SIGTERM.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

try:  # tests/ as a package or as rootdir-relative modules
    from tests.harness import Daemon, Probe, endpoint, wait_until
except ImportError:  # pragma: no cover
    from harness import Daemon, Probe, endpoint, wait_until
from synthetic.traffic import circle_traffic
from protocol.codec import decode, encode
from protocol.keys import Keys
from protocol.messages import AgentMode, StepAck

pytestmark = pytest.mark.integration

CONFIG = """
[run]
id = "{run}"
timing = "lockstep"
[zenoh]
mode = "peer"
[physics]
shards = 1
initial_slots = {{passenger = 8}}
stop_decel = 6.0
"""


def _drop(msg, keep: int):
    """The first ``keep`` agents of a step (agents leaving the simulation)."""
    from dataclasses import replace

    a = msg.agents
    off = a.path_offsets[: keep + 1]
    cols = {k: getattr(a, k)[:keep] for k in ("cls", "vtype", "x", "y", "angle", "speed", "accel", "signals",
                                              "la_x", "la_y", "length", "width", "lane", "flags")}
    agents = replace(a, ids=a.ids[:keep], path_offsets=off, path_xy=a.path_xy[: int(off[-1])], **cols)
    return replace(msg, agents=agents)


def test_daemon_lockstep_liveliness_and_rejects(tmp_path):
    run = "phys-daemon-test"
    keys = Keys("sumoco", run)
    cfg = tmp_path / "physics.toml"
    cfg.write_text(CONFIG.format(run=run))
    sumo_ep = endpoint()
    # the fake SUMO side listens; the daemon and the probe connect to it
    from runtime.config import ZenohConfig
    from runtime.transport import open_session

    sumo = open_session(ZenohConfig(listen=(sumo_ep,)))
    acks: list[StepAck] = []
    lock = threading.Lock()

    def on_ack(s):
        with lock:
            acks.append(decode(s.payload.to_bytes()))

    ack_sub = sumo.declare_subscriber(keys.ack_all, on_ack)
    token = sumo.liveliness().declare_token(keys.sumo_alive)
    daemon = Daemon("physics", ["physics", "--config", str(cfg), "--connect", sumo_ep,
                                "--listen", endpoint(), "--verbose"], tmp_path / "logs")
    probe = Probe(keys, connect=[sumo_ep])
    try:
        wait_until(lambda: keys.physics_alive in probe.alive, 30.0, "the physics liveliness token", procs=[daemon])

        def acked(step: int):
            with lock:
                return any(a.step == step for a in acks)

        def put_step(msg):
            sumo.put(keys.step, encode(msg))

        # steps 0..4: three cars; each step is acknowledged before the next (lockstep)
        for k in range(5):
            put_step(circle_traffic(3, k, run=run))
            wait_until(lambda: acked(k), 20.0, f"ack of step {k}", procs=[daemon])
        st = wait_until(lambda: probe.last_physics(), 5.0, "a physics state")
        assert sorted(st.agents.ids) == ["veh0", "veh1", "veh2"]
        assert np.all(st.agents.mode == AgentMode.PHYSICAL)
        assert st.sumo_step == 4 and st.counters["placements"] == 3
        # the agents drive: front bumper within 0.2 m of the SUMO pose after 0.5 s
        ref = circle_traffic(3, 4, run=run).agents
        order = [st.agents.ids.index(i) for i in ref.ids]
        gap = np.hypot(st.agents.x[order] - ref.x, st.agents.y[order] - ref.y)
        assert gap.max() < 0.2 + 10.0 * 0.1, gap  # extrapolated 0.1 s ahead of step 4 at 10 m/s
        assert np.all(np.abs(st.agents.err_lon) < 0.2) and np.all(np.abs(st.agents.err_lat) < 0.2)

        # veh2 leaves at step 5
        put_step(_drop(circle_traffic(3, 5, run=run), 2))
        wait_until(lambda: acked(5), 20.0, "ack of step 5", procs=[daemon])
        wait_until(lambda: probe.last_physics().sumo_step == 5, 5.0, "state of step 5")
        assert sorted(probe.last_physics().agents.ids) == ["veh0", "veh1"]

        # malformed step: rejected, counted, daemon carries on
        sumo.put(keys.step, b"\x93not a step")
        put_step(_drop(circle_traffic(3, 6, run=run), 2))
        wait_until(lambda: acked(6), 20.0, "ack of step 6 after a malformed one", procs=[daemon])
        wait_until(lambda: probe.last_physics().sumo_step == 6, 5.0, "state of step 6")
        assert probe.last_physics().counters["rejected"] == 1

        # SUMO disappears: every agent brakes to rest (STOPPING)
        token.undeclare()

        def stopped():
            p = probe.last_physics()
            return p is not None and p.agents.n == 2 and np.all(p.agents.mode == AgentMode.STOPPING) \
                and np.all(np.abs(p.agents.speed) < 0.1)

        wait_until(stopped, 20.0, "agents at rest in mode STOPPING", procs=[daemon])
        assert probe.last_physics().counters["stopping"] == 2

        # SUMO comes back as a new run starting at step 0 again: resync to its agent set
        token = sumo.liveliness().declare_token(keys.sumo_alive)
        wait_until(lambda: daemon.tail(200).count("SUMO side is up again") >= 1, 10.0, "SUMO seen again",
                   procs=[daemon])
        with lock:
            acks.clear()
        put_step(circle_traffic(2, 0, run=run, id_prefix="car"))
        wait_until(lambda: acked(0), 20.0, "ack of the restarted step 0", procs=[daemon])
        wait_until(lambda: probe.last_physics().sumo_step == 0, 5.0, "state after the resync")
        p = probe.last_physics()
        assert sorted(p.agents.ids) == ["car0", "car1"]
        assert np.all(p.agents.mode == AgentMode.PHYSICAL)
        assert p.counters["resyncs"] >= 1 and p.counters["parked"] >= 3

        assert daemon.terminate(15.0) == 0, daemon.tail()
    finally:
        daemon.kill()
        ack_sub.undeclare()
        try:
            token.undeclare()
        except Exception:
            pass
        probe.close()
        sumo.close()


def test_daemon_realtime_paces_ticks_by_the_wall_clock(tmp_path):
    """Realtime: ticks at ~50 Hz of wall time, each using the newest step; no acks awaited."""
    import time

    run = "phys-rt-test"
    keys = Keys("sumoco", run)
    cfg = tmp_path / "physics.toml"
    cfg.write_text(CONFIG.format(run=run).replace('timing = "lockstep"', 'timing = "realtime"'))
    from runtime.config import ZenohConfig
    from runtime.transport import open_session

    sumo_ep = endpoint()
    sumo = open_session(ZenohConfig(listen=(sumo_ep,)))
    token = sumo.liveliness().declare_token(keys.sumo_alive)
    daemon = Daemon("physics-rt", ["physics", "--config", str(cfg), "--connect", sumo_ep, "--listen", endpoint()],
                    tmp_path / "logs")
    probe = Probe(keys, connect=[sumo_ep])
    try:
        wait_until(lambda: keys.physics_alive in probe.alive, 30.0, "the physics liveliness token", procs=[daemon])
        t0 = time.monotonic()
        k = 0
        while time.monotonic() - t0 < 2.0:  # SUMO at 10 Hz of wall time
            sumo.put(keys.step, encode(circle_traffic(4, k, run=run)))
            k += 1
            time.sleep(max(0.0, t0 + k * 0.1 - time.monotonic()))
        with probe.lock:
            states = list(probe.physics.get("main", []))
        assert states, daemon.tail()
        span = states[-1].time - states[0].time
        rate = (len(states) - 1) / max(span, 1e-9)
        assert 40.0 < rate <= 51.0, rate  # one state per 20 ms tick
        wall = len(states) / 50.0
        assert 1.2 < wall < 2.2, wall  # paced: about as many ticks as wall-clock 20 ms slots
        last = states[-1]
        assert sorted(last.agents.ids) == ["veh0", "veh1", "veh2", "veh3"]
        assert last.sumo_step >= k - 3  # uses the newest steps
        assert np.abs(last.agents.err_lat).max() < 0.2 and np.abs(last.agents.err_lon).max() < 0.5
        assert daemon.terminate(15.0) == 0, daemon.tail()
    finally:
        daemon.kill()
        token.undeclare()
        probe.close()
        sumo.close()


def test_late_joiner_queries_static_data_for_an_unknown_static_version(tmp_path):
    """Steps without their vType table (protocol 1.2) whose static version the daemon has
    not seen: it queries the static data (once, not per step) and keeps following."""
    from dataclasses import replace

    from protocol.golden_vectors import valid_messages
    from runtime.config import ZenohConfig
    from runtime.transport import open_session

    run = "phys-static-test"
    keys = Keys("sumoco", run)
    cfg = tmp_path / "physics.toml"
    cfg.write_text(CONFIG.format(run=run))
    sumo_ep = endpoint()
    sumo = open_session(ZenohConfig(listen=(sumo_ep,)))
    static = encode(replace(valid_messages()["static"], run=run, version=3))
    queries: list[int] = []
    acks: list[int] = []
    lock = threading.Lock()

    def on_query(q):
        with lock:
            queries.append(1)
        q.reply(keys.static, static)

    def on_ack(s):
        with lock:
            acks.append(decode(s.payload.to_bytes()).step)

    qable = sumo.declare_queryable(keys.static, on_query)
    ack_sub = sumo.declare_subscriber(keys.ack_all, on_ack)
    token = sumo.liveliness().declare_token(keys.sumo_alive)
    daemon = Daemon("physics-static", ["physics", "--config", str(cfg), "--connect", sumo_ep,
                                       "--listen", endpoint(), "--verbose"], tmp_path / "logs")
    probe = Probe(keys, connect=[sumo_ep])
    try:
        wait_until(lambda: keys.physics_alive in probe.alive, 30.0, "the physics liveliness token", procs=[daemon])
        for k in range(12):
            sumo.put(keys.step, encode(replace(circle_traffic(3, k, run=run), vtypes=None, static_version=3)))
            wait_until(lambda: k in acks, 20.0, f"ack of step {k}", procs=[daemon])
        with lock:
            assert len(queries) == 1, queries  # asked once: the reply's version matched
        assert "refers to static version 3" in daemon.tail(400)
        st = wait_until(lambda: probe.last_physics(), 5.0, "a physics state")
        assert sorted(st.agents.ids) == ["veh0", "veh1", "veh2"] and st.counters["rejected"] == 0
        assert daemon.terminate(15.0) == 0, daemon.tail()
    finally:
        daemon.kill()
        for d in (qable, ack_sub, token):
            d.undeclare()
        probe.close()
        sumo.close()
