"""Physics level of detail: full physics in interest zones, kinematic placement elsewhere."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from physics_side.config import PhysicsConfig, PhysicsSettings
from physics_side.daemon import build_fleet
from physics_side.lod import HYSTERESIS, DetailSplit, DetailZones
from protocol.errors import ConfigError
from protocol.messages import AgentFlag, AgentMode
from synthetic.traffic import circle_traffic


def test_zones_regions_egos_and_hysteresis():
    z = DetailZones.from_config(50.0, [[1000.0, 0.0, 10.0]])
    x = np.array([0.0, 30.0, 49.0, 200.0, 1005.0, 0.96 * 50.0])
    y = np.zeros(6)
    ego = np.array([True, False, False, False, False, False])
    full = z.full(x, y, ego)
    # the ego, inside 0.9 r of it, the region; 49 m and 48 m are in the hysteresis band
    assert full.tolist() == [True, True, False, False, True, False]
    kept = z.full(x, y, ego, was_full=np.ones(6, bool))
    assert kept.tolist() == [True, True, True, False, True, True]
    assert HYSTERESIS < 1.0
    assert DetailZones.from_config(0.0, []) is None


def test_lod_config_is_checked():
    with pytest.raises(ConfigError, match=r"lod_regions\[0\]"):
        PhysicsConfig(lod_regions=((1.0, 2.0),)).validate()
    with pytest.raises(ConfigError, match="lod_radius_m"):
        PhysicsConfig(lod_radius_m=-1.0).validate()


def test_physics_authoritative_agents_always_run_full_physics():
    """A vehicle SUMO follows (flag PHYSICS_AUTHORITY) is driven by physics wherever it is:
    the level of detail never places it (SUMO's zones and the viewer cameras may differ)."""
    split = DetailSplit(DetailZones.from_config(0.0, [[0.0, 0.0, 1.0]]))
    msg = circle_traffic(6, 0)
    flags = np.asarray(msg.agents.flags).copy()
    flags[[1, 4]] |= np.uint8(AgentFlag.PHYSICS_AUTHORITY)
    msg = replace(msg, agents=replace(msg.agents, flags=flags))
    near = split.apply(msg)
    assert set(near.agents.ids) == {msg.agents.ids[1], msg.agents.ids[4]}
    assert split.far.n == 4


def test_far_agents_never_reach_the_fleet_and_follow_their_sumo_trajectory():
    # circle traffic on a 300 m circle around (1000, 1000); a region on it that the
    # eighth car (at 0.51 rad, 10 m/s) reaches after about a second
    cx, cy = 1000.0 + 300.0 * np.cos(0.6), 1000.0 + 300.0 * np.sin(0.6)
    split = DetailSplit(DetailZones.from_config(0.0, [[cx, cy, 12.0]]))
    f = build_fleet(PhysicsSettings(physics=replace(PhysicsConfig(), shards=1, initial_slots={"passenger": 4})))
    n = 20
    entered = set()
    for k in range(30):
        msg = circle_traffic(n, k)
        near = split.apply(msg)
        f.apply_step(near)
        for _ in range(f.rates.ticks_per_step):
            f.tick()
        a = msg.agents
        d = np.hypot(a.x - cx, a.y - cy)
        assert set(near.agents.ids) >= {a.ids[i] for i in np.flatnonzero(d < 12.0 * HYSTERESIS)}
        assert not set(near.agents.ids) & {a.ids[i] for i in np.flatnonzero(d > 12.0)}
        entered |= set(near.agents.ids)
        t = msg.time + 0.05
        snap = split.snapshot(f.snapshot(), t)
        assert sorted(snap.ids) == sorted(a.ids) and len(snap.ids) == n
        far = snap.mode == AgentMode.KINEMATIC
        assert far.sum() == n - near.agents.n and np.all(snap.mode[~far] == AgentMode.PHYSICAL)
        # far agents: on the circle, 0.5 m (10 m/s x 0.05 s) past their SUMO pose
        idx = [a.ids.index(i) for i in np.array(snap.ids)[far]]
        moved = np.hypot(snap.x[far] - a.x[idx], snap.y[far] - a.y[idx])
        assert np.allclose(moved, 0.5, atol=0.02)
        assert np.allclose(np.hypot(snap.x[far] - 1000.0, snap.y[far] - 1000.0), 300.0 + 4.0 * a.lane[idx], atol=0.05)
    assert entered and f.world.counters["spawned"] == len(entered) < n // 2  # only the zone's agents got a slot
    assert f.world.capacity < n


def test_daemon_publishes_far_agents_as_kinematic_without_simulating_them():
    from physics_side.daemon import PhysicsDaemon
    from protocol.codec import encode
    from protocol.keys import Keys
    from runtime.config import RunConfig

    cx, cy = 1000.0 + 300.0 * np.cos(0.6), 1000.0 + 300.0 * np.sin(0.6)
    settings = PhysicsSettings(physics=replace(
        PhysicsConfig(), shards=1, initial_slots={"passenger": 4}, lod_regions=((cx, cy, 12.0),)))
    fleet = build_fleet(settings)
    d = PhysicsDaemon(None, Keys("sumoco", "lod"), fleet, settings, RunConfig(timing="lockstep"))
    for k in range(3):
        assert d.handle_step(encode(circle_traffic(20, k))) is not None  # as received
        for _ in range(fleet.rates.ticks_per_step):
            fleet.tick()
    snap = d.snapshot()
    c = d.all_counters()
    assert len(snap.ids) == 20 and fleet.n == c["physical"] < 20
    assert c["lod_far"] == 20 - fleet.n and c["kinematic"] == c["lod_far"]
    assert int((snap.mode == AgentMode.KINEMATIC).sum()) == c["lod_far"]


@pytest.mark.integration
def test_viewer_camera_is_an_interest_point_of_a_real_physics_daemon(tmp_path):
    """A camera on ``viewer/<role>/<client>/camera`` makes agents near it run full physics in
    a real physics daemon; moving it away or closing it (liveliness) puts them back."""
    import threading
    import time

    from protocol.codec import decode, encode
    from protocol.keys import Keys
    from protocol.messages import CameraPose
    from sumoco.viewing.camera import CameraPublisher
    from runtime.config import ZenohConfig
    from runtime.transport import open_session
    from tests.harness import Daemon, Probe, endpoint, wait_until

    run, r = "lod-camera", 30.0
    keys = Keys("sumoco", run)
    cfg = tmp_path / "physics.toml"
    cfg.write_text(f"""
[run]
id = "{run}"
timing = "lockstep"
[physics]
shards = 1
initial_slots = {{passenger = 8}}
lod_radius_m = {r}
""")
    sumo_ep = endpoint()
    sumo = open_session(ZenohConfig(listen=(sumo_ep,)))
    acked: set[int] = set()
    lock = threading.Lock()

    def on_ack(s):
        with lock:
            acked.add(decode(s.payload.to_bytes()).step)

    ack_sub = sumo.declare_subscriber(keys.ack_all, on_ack)
    token = sumo.liveliness().declare_token(keys.sumo_alive)
    daemon = Daemon("physics", ["physics", "--config", str(cfg), "--connect", sumo_ep, "--listen", endpoint()],
                    tmp_path / "logs")
    probe = Probe(keys, connect=[sumo_ep])
    cam = None
    sent = {}
    k = 0
    here = [None]  # where the camera is (re-put at every step, as a viewer does at 2 Hz)
    try:
        wait_until(lambda: keys.physics_alive in probe.alive, 30.0, "the physics liveliness token", procs=[daemon])

        def steps_until(cond, what: str, timeout_s: float = 60.0):
            nonlocal k
            deadline = time.monotonic() + timeout_s
            while True:
                if cam is not None and not cam.closed and here[0] is not None:
                    cam.put(*here[0])
                sent[k] = msg = circle_traffic(20, k, run=run)
                sumo.put(keys.step, encode(msg))
                wait_until(lambda: k in acked, 20.0, f"ack of step {k}", procs=[daemon])
                k += 1
                st = probe.last_physics()
                if st is not None and st.sumo_step in sent and st.agents.n == 20 and cond(st, sent[st.sumo_step]):
                    return st
                assert time.monotonic() < deadline, f"timed out waiting for {what}: {st and st.counters} {daemon.tail(10)}"

        def all_kinematic(st, msg):
            return bool(np.all(st.agents.mode == AgentMode.KINEMATIC))

        def near_full(st, msg):
            a = msg.agents
            d = dict(zip(a.ids, np.hypot(a.x - here[0][0], a.y - here[0][1])))
            mode = dict(zip(st.agents.ids, st.agents.mode.tolist()))
            near = [i for i in a.ids if d[i] < HYSTERESIS * r]
            far = [i for i in a.ids if d[i] > r]
            return bool(near) and all(mode[i] == AgentMode.PHYSICAL for i in near) \
                and all(mode[i] == AgentMode.KINEMATIC for i in far)

        # no ego, no region, no camera: nothing runs full physics
        steps_until(all_kinematic, "every agent kinematic without a camera")
        cam = CameraPublisher(probe.session, keys, "page1")
        ahead = circle_traffic(20, k + 5, run=run).agents
        here[0] = (float(ahead.x[10]), float(ahead.y[10]))  # where veh10 will be in 5 steps
        st = steps_until(near_full, "agents near the camera in full physics, far ones kinematic")
        assert st.counters["viewer_cameras"] == 1
        assert 0 < int((st.agents.mode == AgentMode.PHYSICAL).sum()) < 20
        # the camera moves away from every agent: all back to kinematic
        here[0] = (0.0, 0.0)
        steps_until(all_kinematic, "every agent kinematic after the camera moved away")
        # and back; then the viewer closes: its liveliness token goes and so does the camera
        ahead = circle_traffic(20, k + 5, run=run).agents
        here[0] = (float(ahead.x[5]), float(ahead.y[5]))
        steps_until(near_full, "agents near the camera's new place in full physics")
        cam.close()
        st = steps_until(all_kinematic, "every agent kinematic after the viewer closed")
        assert st.counters["viewer_cameras"] == 0
        # a camera whose id is not its key's client id is refused and counted
        probe.put(keys.viewer_camera("viewer", "page2"), encode(CameraPose("other", *here[0])))
        st = steps_until(lambda st, msg: st.counters["rejected_cameras"] >= 1, "the bad camera counted")
        assert st.counters["viewer_cameras"] == 0 and np.all(st.agents.mode == AgentMode.KINEMATIC)
        assert daemon.terminate(15.0) == 0, daemon.tail()
    finally:
        if cam is not None:
            cam.close()
        daemon.kill()
        ack_sub.undeclare()
        token.undeclare()
        probe.close()
        sumo.close()
