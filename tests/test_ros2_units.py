"""The ROS 2 bridge without processes: the frame rules on the golden vectors, the converter's
topics, the checks on ego poses, and a rosbag2 export read back by an independent reader
(rosbags' reader and CDR deserialiser, then rclpy's own deserialisation)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

try:
    import rclpy  # noqa: F401  (the ros2 extra: `make install` installs it)
except ImportError:  # never skipped in CI: the extra is part of [all]
    if os.environ.get("CI"):
        raise
    pytest.skip("rclpy (the ros2 extra) is not installed", allow_module_level=True)

from protocol.codec import decode
from protocol.errors import ConfigError
from protocol.messages import EgoPose
from sumoco.ros2.config import Ros2Config, ros_name
from sumoco.ros2.frames import quaternion_to_yaw, ros_to_sumo, stamp_of, sumo_to_ros, yaw_to_quaternion

GOLDEN = Path(__file__).resolve().parents[1] / "protocol" / "golden"


def _golden(name: str):
    return decode((GOLDEN / f"{name}.msgpack").read_bytes()), json.loads((GOLDEN / f"{name}.json").read_text())


def test_sumo_pose_to_ros_on_the_golden_step():
    step, doc = _golden("step")
    a = doc["agents"]
    cx, cy, yaw = sumo_to_ros(np.array(a["x"]), np.array(a["y"]), np.array(a["angle"]), np.array(a["length"]))
    # every agent heads east (SUMO 90 deg): yaw 0, the body centre half a length west of the front bumper
    np.testing.assert_allclose(yaw, 0.0, atol=1e-12)
    np.testing.assert_allclose(cx, np.array(a["x"]) - 0.5 * np.array(a["length"]), atol=1e-9)
    np.testing.assert_allclose(cy, a["y"], atol=1e-12)
    assert cx[0] == pytest.approx(47.5) and cx[1] == pytest.approx(99.0)  # ref 5 m, bus_0 12 m
    # the decoded message gives the same (float32 angles and lengths)
    c2 = sumo_to_ros(step.agents.x, step.agents.y, step.agents.angle, step.agents.length)
    np.testing.assert_allclose(np.c_[c2], np.c_[cx, cy, yaw], atol=1e-6)


@pytest.mark.parametrize("angle, yaw", [(0.0, math.pi / 2), (90.0, 0.0), (180.0, -math.pi / 2), (270.0, math.pi),
                                        (45.0, math.pi / 4), (359.0, math.radians(91.0)), (-90.0, math.pi)])
def test_angle_to_yaw_and_back(angle, yaw):
    x, y, length = 10.0, -3.0, 4.0
    cx, cy, got = sumo_to_ros(x, y, angle, length)
    assert float(got) == pytest.approx(yaw, abs=1e-12)
    assert float(cx) == pytest.approx(x - 2.0 * math.cos(yaw)) and float(cy) == pytest.approx(y - 2.0 * math.sin(yaw))
    fx, fy, back = ros_to_sumo(cx, cy, got, length)
    assert (float(fx), float(fy)) == (pytest.approx(x), pytest.approx(y))
    assert float(back) == pytest.approx(angle % 360.0, abs=1e-9)
    qz, qw = yaw_to_quaternion(got)
    assert float(quaternion_to_yaw(0.0, 0.0, qz, qw)) == pytest.approx(float(got), abs=1e-12)


def test_stamps_at_simulation_time():
    assert stamp_of(4.2) == (4, 200_000_000)
    assert stamp_of(50300.1) == (50300, 100_000_000)
    assert stamp_of(0.9999999999) == (1, 0)


def test_config_checks_and_ros_names():
    assert ros_name("veh.1-a") == "veh_1_a" and ros_name("7x") == "_7x"
    with pytest.raises(ConfigError, match="ros2.rate_hz"):
        Ros2Config(rate_hz=-1).validate()
    with pytest.raises(ConfigError, match="both become the ROS name 'a_b'"):
        Ros2Config(odometry=("a.b", "a-b")).validate()
    with pytest.raises(ConfigError, match="ros2.prefix"):
        Ros2Config(prefix="sumoco").validate()


def test_converter_topics_from_golden_static_step_and_physics():
    from sumoco.ros2.messages import Converter

    static, _ = _golden("static")
    step, _ = _golden("step")
    phys, _ = _golden("physics")
    conv = Converter(Ros2Config(odometry=("ref",)))
    (topic, mp, _), = conv.static(static)
    assert topic == "/sumoco/map" and {m.ns for m in mp.markers} == {"lanes", "lane_lines", "junctions"}
    assert conv.step(step)[0][0] == "/clock"  # physics source: the step alone gives the clock
    out = {t: m for t, m, _ in conv.physics(phys, "main")}
    assert set(out) == {"/sumoco/agents", "/sumoco/poses", "/sumoco/odom/ref"}
    poses = out["/sumoco/poses"]
    assert len(poses.poses) == step.agents.n and poses.header.frame_id == "map"
    sec, nsec = stamp_of(max(phys.time, step.time))
    assert (poses.header.stamp.sec, poses.header.stamp.nanosec) == (sec, nsec)
    # ref has a physics row: its physics front bumper, moved back half its step length
    i, j = step.agents.ids.index("ref"), phys.agents.ids.index("ref")
    cx, cy, _ = sumo_to_ros(phys.agents.x[j], phys.agents.y[j], phys.agents.heading[j], step.agents.length[i])
    assert (poses.poses[i].position.x, poses.poses[i].position.y) == (pytest.approx(cx), pytest.approx(cy))
    # ped_7 rides the bus: no physics row, SUMO's pose
    k = step.agents.ids.index("ped_7")
    cx, cy, _ = sumo_to_ros(step.agents.x[k], step.agents.y[k], step.agents.angle[k], step.agents.length[k])
    assert poses.poses[k].position.x == pytest.approx(cx)
    markers = out["/sumoco/agents"].markers
    assert markers[0].action == markers[0].DELETEALL
    boxes = [m for m in markers if m.ns == "agents"]
    assert len(boxes) == step.agents.n and boxes[i].scale.x == pytest.approx(step.agents.length[i])
    assert [m.ns for m in markers if m.ns == "tls"] == ["tls"]
    tls = next(m for m in markers if m.ns == "tls")
    assert len(tls.points) == static.tls_links.tls.size and tls.colors[0].g == 1.0  # 'G'
    # the sumo source: stamped with the step's time, thinned to rate_hz by simulation time
    conv = Converter(Ros2Config(source="sumo", rate_hz=5.0))
    assert [t for t, _, _ in conv.step(step)] == ["/clock", "/sumoco/agents", "/sumoco/poses"]
    later = type(step)(**{**vars(step), "time": step.time + 0.1, "step": step.step + 1})
    assert [t for t, _, _ in conv.step(later)] == ["/clock"] and conv.stats.thinned == 1


class _Msg:
    """A PoseStamped-like object (the checks read attributes only)."""

    def __init__(self, frame="map", x=1.0, y=2.0, qz=0.0, qw=1.0, t=10.0):
        from geometry_msgs.msg import PoseStamped

        self.m = PoseStamped()
        self.m.header.frame_id = frame
        self.m.header.stamp.sec, self.m.header.stamp.nanosec = int(t), int(round((t % 1) * 1e9))
        self.m.pose.position.x, self.m.pose.position.y = x, y
        self.m.pose.orientation.z, self.m.pose.orientation.w = qz, qw


def test_ego_poses_are_checked_converted_and_counted(caplog):
    from sumoco.ros2.egos import EgoInput

    sent = []
    ego = EgoInput("ego", sent.append, "map", 4.0, 1e6)
    ego.on_pose(_Msg(frame="odom").m)
    ego.on_pose(_Msg(x=float("nan")).m)
    ego.on_pose(_Msg(qw=0.0).m)
    ego.on_pose(_Msg(x=2e8).m)
    assert ego.stats.rejected == 4 and not sent
    assert set(ego.stats.errors) == {"header.frame_id", "pose.position.x", "pose.orientation", "pose.position"}
    assert "expected frame_id 'map'" in caplog.text
    # facing north (yaw pi/2): the front bumper 2 m north of the centre; speed from the poses
    q = math.sin(math.pi / 4), math.cos(math.pi / 4)
    ego.on_pose(_Msg(x=100.0, y=50.0, qz=q[0], qw=q[1], t=10.0).m)
    ego.on_pose(_Msg(x=100.0, y=51.0, qz=q[0], qw=q[1], t=10.5).m)
    first, second = decode(sent[0]), decode(sent[1])
    assert isinstance(first, EgoPose) and first.id == "ego"
    assert (first.x, first.y, first.angle, first.speed) == (pytest.approx(100.0), pytest.approx(52.0),
                                                            pytest.approx(0.0, abs=1e-9), 0.0)
    assert second.speed == pytest.approx(2.0) and ego.stats.forwarded == 2


def test_rosbag2_export_reads_back_with_rosbags_and_rclpy(tmp_path):
    from rclpy.serialization import deserialize_message
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    from visualization_msgs.msg import MarkerArray
    from geometry_msgs.msg import PoseArray
    from rosgraph_msgs.msg import Clock

    from protocol.messages import StepMessage
    from sumoco.recording.record import iter_decoded, read_recording
    from sumoco.ros2.bag import export_rosbag2
    from tests.recording_fixture import make_recording

    run = tmp_path / "run.mcap"
    make_recording(run, steps=12, agents=15)
    steps = {round(m.time * 1e9): m for _, m in iter_decoded(read_recording(run), ("step",))
             if isinstance(m, StepMessage)}
    out = tmp_path / "bag"
    result = export_rosbag2(run, out, Ros2Config(source="sumo", rate_hz=0.0))
    assert result["topics"]["/sumoco/poses"] == len(steps) and result["topics"]["/sumoco/map"] == 1
    types = {"/clock": Clock, "/sumoco/poses": PoseArray, "/sumoco/agents": MarkerArray, "/sumoco/map": MarkerArray}
    seen: dict[str, int] = {}
    store = get_typestore(Stores.ROS2_KILTED)
    with AnyReader([out], default_typestore=store) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == {
            "/clock": "rosgraph_msgs/msg/Clock", "/sumoco/poses": "geometry_msgs/msg/PoseArray",
            "/sumoco/agents": "visualization_msgs/msg/MarkerArray", "/sumoco/map": "visualization_msgs/msg/MarkerArray"}
        for conn, t_ns, raw in reader.messages():
            pure = reader.deserialize(raw, conn.msgtype)  # rosbags' own CDR reader
            msg = deserialize_message(raw, types[conn.topic])  # and ROS 2's
            seen[conn.topic] = seen.get(conn.topic, 0) + 1
            if conn.topic == "/sumoco/poses":
                m = steps[t_ns]  # bag time = the stamp = the step's simulation time
                assert (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec) == t_ns
                cx, cy, yaw = sumo_to_ros(m.agents.x, m.agents.y, m.agents.angle, m.agents.length)
                got = np.array([[p.position.x, p.position.y] for p in msg.poses])
                assert len(got) == m.agents.n and np.max(np.hypot(got[:, 0] - cx, got[:, 1] - cy)) < 1e-3
                assert [p.position.x for p in pure.poses] == [p.position.x for p in msg.poses]
            if conn.topic == "/sumoco/agents":
                assert sum(mk.ns == "agents" for mk in msg.markers) == steps[t_ns].agents.n
                assert len(pure.markers) == len(msg.markers)
    assert seen == {k: v for k, v in result["topics"].items()}


def test_rviz_config_names_the_bridge_topics_with_matching_qos():
    import yaml

    from sumoco.ros2.node import qos_profiles

    rviz = yaml.safe_load((Path(__file__).resolve().parents[1] / "configs" / "ros2" / "sumoco.rviz").read_text())
    views = rviz["Visualization Manager"]
    assert views["Global Options"]["Fixed Frame"] == "map"
    topics = {d["Topic"]["Value"]: d["Topic"] for d in views["Displays"] if "Topic" in d}
    q = qos_profiles()
    want = {"/sumoco/map": q["latched"], "/sumoco/agents": q["stream"], "/sumoco/poses": q["stream"]}
    assert set(topics) == set(want)
    for name, prof in want.items():  # RViz's names of the same policies
        assert topics[name]["Reliability Policy"].replace(" ", "_").upper() == prof.reliability.name
        assert topics[name]["Durability Policy"].replace(" ", "_").upper() == prof.durability.name
