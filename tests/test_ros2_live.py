"""``sumoco ros2`` with real processes: the bundled scenario in lockstep (SUMO side, physics
side, the ROS 2 bridge) read by a separate rclpy process; and an ego driven by a separate
rclpy publisher that SUMO traffic reacts to. Each test has its own random ROS_DOMAIN_ID and
keeps DDS on loopback."""

from __future__ import annotations

import ast
import json
import re
import os
import secrets
import signal
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest

try:
    import rclpy  # noqa: F401  (the ros2 extra: `make install` installs it)
except ImportError:  # never skipped in CI: the extra is part of [all]
    if os.environ.get("CI"):
        raise
    pytest.skip("rclpy (the ros2 extra) is not installed", allow_module_level=True)

from protocol.keys import Keys
from sumoco.ros2.frames import ros_to_sumo, sumo_to_ros
from tests.harness import PAPER_CFG, ROOT, Daemon, Probe, assert_exit_codes, endpoint, wait_until
from tests.sumo_testnet import make_testnet

pytestmark = pytest.mark.integration


def _domain() -> int:
    return 20 + secrets.randbelow(200)


class Peer:
    """tests/ros2_peer.py as a process; its JSON lines in a file."""

    def __init__(self, tmp_path, mode: str, domain: int, *extra: str) -> None:
        self.out = tmp_path / f"ros2_{mode}.jsonl"
        self.err = (tmp_path / f"ros2_{mode}.err").open("wb")
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen([sys.executable, str(ROOT / "tests" / "ros2_peer.py"), mode, "--out",
                                      str(self.out), *extra], env=env, stdout=subprocess.DEVNULL, stderr=self.err)
        self.name = f"ros2 {mode}"

    def poll(self):
        return self.proc.poll()

    def tail(self) -> str:
        return (self.out.read_text() if self.out.exists() else "")[-2000:]

    def lines(self, topic: str) -> list[dict]:
        if not self.out.exists():
            return []
        rows = []
        for ln in self.out.read_text().splitlines():
            try:
                d = json.loads(ln)
            except json.JSONDecodeError:  # a line being written
                continue
            if d.get("topic") == topic:
                rows.append(d)
        return rows

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self.err.close()
        return self.proc.returncode


def _ready_line(d: Daemon) -> dict | None:
    for ln in d.tail(200).splitlines():
        if ln.startswith('{"ros2": "ready"'):
            return json.loads(ln)
    return None


def test_rviz_topics_from_a_lockstep_run_match_the_steps(tmp_path):
    cfg = tmp_path / "run.toml"
    cfg.write_text(f"""
[run]
id = "rosrun"
timing = "lockstep"
duration_s = 15.0
lockstep_timeout_s = 20.0
[sumo]
sumocfg = "{PAPER_CFG}"
[physics]
preset = "default"
""")
    keys, domain = Keys("sumoco", "rosrun"), _domain()
    sumo_ep, phys_ep, node_ep, probe_ep = endpoint(), endpoint(), endpoint(), endpoint()
    logs = tmp_path / "logs"
    listener = Peer(tmp_path, "listen", domain)
    node = Daemon("ros2", ["ros2", "--config", str(cfg), "--listen", node_ep, "--source", "sumo",
                           "--odometry", "ref", "--domain-id", str(domain)], logs)
    daemons, probe = [node], Probe(keys, [], listen=probe_ep)
    try:
        wait_until(lambda: _ready_line(node), 30, "the ROS 2 bridge ready", procs=[node])
        ready = wait_until(lambda: (r := listener.lines("ready")) and r[0], 40, "the listener to discover the bridge",
                           procs=[listener, node])
        assert ready["publishers"] >= 1
        # the run starts only now and links to the bridge and the probe at once: every step of it
        # reaches both
        sumo = Daemon("sumo", ["sumo", "--config", str(cfg), "--listen", sumo_ep, "--connect", node_ep,
                               "--connect", probe_ep], logs)
        phys = Daemon("physics", ["physics", "--config", str(cfg), "--listen", phys_ep, "--connect", sumo_ep,
                                  "--quiet"], logs)
        daemons += [sumo, phys]
        assert sumo.proc.wait(120) == 0, sumo.tail()
        assert phys.proc.wait(30) == 0, phys.tail()
        final_t = probe.last_step().time
        wait_until(lambda: any(c["stamp"] == round(final_t * 1e9) for c in listener.lines("clock")), 10,
                   "the run's last /clock", procs=[node])
    finally:
        probe.close()
        for d in daemons:
            d.terminate(15)
        code = listener.stop()
    assert_exit_codes(daemons)
    assert code == 0, listener.err.name

    steps = {round(m.time * 1e9): m for m in probe.steps}
    poses, agents = listener.lines("poses"), listener.lines("agents")
    assert len(steps) == 150 and len(poses) >= 100 and len(agents) >= 100, (len(poses), len(agents), len(steps))
    worst_xy = worst_yaw = 0.0
    for msg in poses:
        assert msg["frame"] == "map"
        m = steps[msg["stamp"]]  # stamped with a step's simulation time
        got = np.array(msg["poses"], np.float64).reshape(-1, 3)
        assert len(got) == m.agents.n
        a = m.agents
        cx, cy, yaw = sumo_to_ros(a.x, a.y, a.angle, a.length.astype(np.float64))
        # the documented rule written out: yaw = radians(90 - angle), centre = front - L/2 (cos, sin)
        yaw_doc = np.deg2rad(90.0 - a.angle.astype(np.float64))
        cx_doc = a.x - 0.5 * a.length * np.cos(yaw_doc)
        np.testing.assert_allclose(cx, cx_doc, atol=1e-9)
        worst_xy = max(worst_xy, float(np.max(np.hypot(got[:, 0] - cx, got[:, 1] - cy), initial=0.0)))
        worst_yaw = max(worst_yaw, float(np.max(np.abs(np.angle(np.exp(1j * (got[:, 2] - yaw)))), initial=0.0)))
        # and back: the body centre gives SUMO's front bumper
        fx, fy, ang = ros_to_sumo(got[:, 0], got[:, 1], got[:, 2], a.length.astype(np.float64))
        assert np.all(np.hypot(fx - a.x, fy - a.y) < 1e-3)
    assert worst_xy < 1e-3 and worst_yaw < 0.01, (worst_xy, worst_yaw)
    for msg in agents:
        m = steps[msg["stamp"]]
        assert msg["ns"].get("agents", 0) == m.agents.n
        assert msg["ns"].get("tls", 0) == (1 if m.tls.ids else 0)
    assert any(msg["ns"].get("brake", 0) for msg in agents), "no brake light in the whole run"
    clocks = [c["stamp"] for c in listener.lines("clock")]
    assert clocks == sorted(clocks) and set(clocks) <= set(steps)
    odom = listener.lines("odom")
    assert odom and all(o["child"] == "ref/base_link" for o in odom)
    maps = listener.lines("map")
    assert maps and maps[0]["ns"]["lanes"] > 0 and maps[0]["ns"]["junctions"] > 0
    print(f"ros2 lockstep: {len(poses)} PoseArrays, {len(agents)} MarkerArrays, discovery "
          f"{ready['discovery_s']:.2f} s, pose error max {worst_xy * 1e3:.4f} mm / {worst_yaw:.2e} rad")


EGO_LANE = "A0B0_2"  # left lane eastbound in the test net; v0 drives it first (tests/test_e2e_ego.py)


def test_an_ego_driven_from_ros2_is_placed_and_followed(tmp_path):
    cfg = tmp_path / "ego.toml"
    cfg.write_text(f"""
[run]
id = "rosego"
[sumo]
sumocfg = "{make_testnet(tmp_path / 'net')}"
lanechange_duration_s = 0.0
""")
    keys, domain = Keys("sumoco", "rosego"), _domain()
    sumo_ep, node_ep = endpoint(), endpoint()
    logs = tmp_path / "logs"
    # the lane from the network file: the ego stands 60 m along it before SUMO starts
    shape = next(ln.get("shape") for ln in ET.parse(tmp_path / "net" / "net.net.xml").iter("lane")
                 if ln.get("id") == EGO_LANE)
    pts = np.array([[float(v) for v in p.split(",")] for p in shape.split()])
    d = pts[1] - pts[0]
    heading = float(np.arctan2(d[1], d[0]))
    front = pts[0] + 60.0 * d / np.hypot(*d)  # 60 m along the (straight) lane
    cx, cy = front - 2.5 * np.array([np.cos(heading), np.sin(heading)])  # body centre of a 5 m car
    node = Daemon("ros2", ["ros2", "--config", str(cfg), "--listen", node_ep, "--source", "sumo",
                           "--ego", "ego", "--ego", "intruder", "--domain-id", str(domain)], logs)
    daemons, driver, probe = [node], None, None
    try:
        ready = wait_until(lambda: _ready_line(node), 30, "the ROS 2 bridge ready", procs=[node])
        assert "/sumoco/ego/ego/pose" in ready["topics"]
        assert "/sumoco/ego/intruder/pose" not in ready["topics"]  # [sumo] ego_id is "ego": refused
        driver = Peer(tmp_path, "drive", domain, "--ego", "ego", "--x", repr(float(cx)), "--y", repr(float(cy)),
                      "--yaw", repr(heading), "--rate", "20")
        wait_until(lambda: driver.lines("ready"), 40, "the driver to discover the bridge", procs=[driver, node])
        # SUMO starts now and links to the bridge at once: the ego is there from its first steps
        sumo = Daemon("sumo", ["sumo", "--config", str(cfg), "--listen", sumo_ep, "--connect", node_ep], logs)
        daemons.append(sumo)
        probe = Probe(keys, [sumo_ep])

        def ego_step():
            m = probe.last_step()
            return m if m is not None and "ego" in m.agents.ids else None
        m = wait_until(ego_step, 40, "the ego in SUMO's steps", procs=[sumo, node, driver])
        discovery = driver.lines("ready")[0]["discovery_s"]
        # placed where ROS put it (SUMO's front bumper back to the body centre, the documented rule)
        errs = []
        for m in probe.steps[-5:]:
            if "ego" in m.agents.ids:
                i = m.agents.ids.index("ego")
                gx, gy, gyaw = sumo_to_ros(m.agents.x[i], m.agents.y[i], m.agents.angle[i], m.agents.length[i])
                errs.append(float(np.hypot(gx - cx, gy - cy)))
                assert abs(np.angle(np.exp(1j * (gyaw - heading)))) < 0.01
        assert errs and max(errs) < 1e-3, errs

        # a car on route r0 (v0, then v1 two seconds later) comes up behind the standing ego and stops there
        speeds: dict[str, list[float]] = {}

        def follower_stopped_behind():
            m = probe.last_step()
            if m is None or "ego" not in m.agents.ids:
                return False
            i = m.agents.ids.index("ego")
            for v in ("v0", "v1"):
                if v in m.agents.ids:
                    k = m.agents.ids.index(v)
                    speeds.setdefault(v, []).append(float(m.agents.speed[k]))
                    behind = 0.0 < m.agents.x[i] - m.agents.x[k] < 15.0  # fronts: the gap is this - 5 m
                    if abs(m.agents.y[k] - front[1]) < 0.2 and behind and m.agents.speed[k] < 0.05:
                        return v, m
            return False
        v, m = wait_until(follower_stopped_behind, 60, "v0 or v1 to stop behind the ego", procs=[sumo, node, driver])
        k, i = m.agents.ids.index(v), m.agents.ids.index("ego")
        gap = float(m.agents.x[i] - m.agents.x[k]) - 5.0
        assert 0.0 < gap < 5.0, f"{v} stopped {gap:.2f} m behind the ego's rear"
        assert max(speeds[v]) > 2.0  # it was driving before it braked
        print(f"ros2 ego: discovery {discovery:.2f} s, ego pose error max {max(errs) * 1e3:.4f} mm, {v} "
              f"{max(speeds[v]):.2f} m/s -> {m.agents.speed[k]:.3f} m/s, gap {gap:.2f} m")
    finally:
        if probe is not None:
            probe.close()
        codes = {}
        if driver is not None:
            codes["driver"] = driver.stop()
        for dmn in daemons:
            dmn.terminate(15)
    assert_exit_codes(daemons)
    assert codes.get("driver") == 0
    log = node.log.read_text()
    # the malformed poses: each refused with its reason, counted, the node kept running
    assert "header.frame_id: expected frame_id 'map'" in log
    assert "pose.position.x: expected a finite number" in log
    assert "pose.orientation: expected a unit quaternion" in log
    assert "ego 'intruder' refused" in log
    errors = re.search(r"'egos': \{'ego': \{[^}]*'errors': (\{[^}]*\})", log)
    assert errors and set(ast.literal_eval(errors.group(1))) == {"header.frame_id", "pose.position.x",
                                                                  "pose.orientation"}, log[-2000:]
