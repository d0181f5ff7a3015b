"""A separate rclpy process for the ROS 2 tests (no sumoco import): ``listen`` writes what it
receives on the bridge's topics as JSON lines; ``drive`` publishes an ego's PoseStamped at a
fixed rate (and a few malformed ones first). Runs until SIGTERM, exits 0."""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import threading
import time

os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

import rclpy  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402


def listen(node, out) -> None:
    from geometry_msgs.msg import PoseArray
    from nav_msgs.msg import Odometry
    from rosgraph_msgs.msg import Clock
    from visualization_msgs.msg import MarkerArray

    lock = threading.Lock()

    def write(d: dict) -> None:
        d["wall"] = time.time()
        with lock:
            out.write(json.dumps(d) + "\n")
            out.flush()

    def ns(stamp) -> int:
        return stamp.sec * 1_000_000_000 + stamp.nanosec

    def yaw(q) -> float:
        return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))

    def on_poses(m) -> None:
        write({"topic": "poses", "frame": m.header.frame_id, "stamp": ns(m.header.stamp),
               "poses": [[p.position.x, p.position.y, yaw(p.orientation)] for p in m.poses]})

    def on_agents(m) -> None:
        by_ns: dict[str, int] = {}
        for mk in m.markers:
            by_ns[mk.ns] = by_ns.get(mk.ns, 0) + 1
        first = next((mk for mk in m.markers if mk.ns == "agents"), None)
        write({"topic": "agents", "stamp": ns(m.markers[-1].header.stamp) if m.markers else -1, "ns": by_ns,
               "first": None if first is None else [first.pose.position.x, first.pose.position.y,
                                                    first.scale.x, first.scale.y, first.type]})

    def on_map(m) -> None:
        write({"topic": "map", "ns": {mk.ns: len(mk.points) for mk in m.markers}})

    def on_clock(m) -> None:
        write({"topic": "clock", "stamp": ns(m.clock)})

    def on_odom(m) -> None:
        write({"topic": "odom", "stamp": ns(m.header.stamp), "child": m.child_frame_id,
               "pose": [m.pose.pose.position.x, m.pose.pose.position.y, yaw(m.pose.pose.orientation)],
               "speed": m.twist.twist.linear.x})

    stream = QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(PoseArray, "/sumoco/poses", on_poses, stream)
    node.create_subscription(MarkerArray, "/sumoco/agents", on_agents, stream)
    node.create_subscription(Odometry, "/sumoco/odom/ref", on_odom, stream)
    node.create_subscription(MarkerArray, "/sumoco/map", on_map, latched)
    node.create_subscription(Clock, "/clock", on_clock, QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
    # ready once the bridge's publishers are discovered
    t0 = time.monotonic()
    while node.count_publishers("/sumoco/poses") == 0 and time.monotonic() - t0 < 30:
        time.sleep(0.05)
    write({"topic": "ready", "discovery_s": time.monotonic() - t0, "publishers": node.count_publishers("/sumoco/poses")})


def drive(node, args, out) -> threading.Thread:
    from geometry_msgs.msg import PoseStamped

    pub = node.create_publisher(PoseStamped, f"/sumoco/ego/{args.ego}/pose", 10)
    stop = threading.Event()

    def pose(frame: str, x: float, y: float, yaw: float) -> PoseStamped:
        m = PoseStamped()
        now = node.get_clock().now().to_msg()
        m.header.stamp, m.header.frame_id = now, frame
        m.pose.position.x, m.pose.position.y = x, y
        m.pose.orientation.z, m.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
        return m

    def loop() -> None:
        t0 = time.monotonic()
        while node.count_subscribers(pub.topic_name) == 0 and time.monotonic() - t0 < 30:
            time.sleep(0.05)
        out.write(json.dumps({"topic": "ready", "discovery_s": time.monotonic() - t0}) + "\n")
        out.flush()
        # among the good poses, now and then the malformed ones: a pose in the wrong frame, a NaN
        # position, a zero quaternion (the first ones may go before the subscriber matched)
        bad = pose("map", args.x, args.y, args.yaw)
        bad.pose.orientation.z = bad.pose.orientation.w = 0.0
        cycle = 0
        malformed = (pose("odom", args.x, args.y, args.yaw), pose("map", float("nan"), args.y, args.yaw), bad)
        while not stop.wait(1.0 / args.rate):
            # one malformed pose in a cycle of its own: the ego topic keeps the last message
            # only, so a burst would leave the node just its last one
            k = cycle % 10 - 5
            if cycle < 60 and 0 <= k < len(malformed):
                pub.publish(malformed[k])
            else:
                pub.publish(pose("map", args.x, args.y, args.yaw))
            cycle += 1

    th = threading.Thread(target=loop, daemon=True)
    th.stop = stop  # type: ignore[attr-defined]
    th.start()
    return th


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("mode", choices=["listen", "drive"])
    ap.add_argument("--out", required=True)
    ap.add_argument("--ego", default="ego")
    ap.add_argument("--x", type=float, default=0.0)
    ap.add_argument("--y", type=float, default=0.0)
    ap.add_argument("--yaw", type=float, default=0.0)
    ap.add_argument("--rate", type=float, default=20.0)
    args = ap.parse_args()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    ctx = rclpy.Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"test_{args.mode}", context=ctx)
    from rclpy.executors import SingleThreadedExecutor

    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    spin = threading.Thread(target=ex.spin, daemon=True)
    with open(args.out, "w") as out:
        spin.start()
        if args.mode == "listen":
            listen(node, out)
        else:
            th = drive(node, args, out)
        stop.wait(120)
        if args.mode == "drive":
            th.stop.set()  # type: ignore[attr-defined]
        ex.shutdown(timeout_sec=2)
        spin.join(5)
    node.destroy_node()
    rclpy.shutdown(context=ctx)
    return 0


if __name__ == "__main__":
    sys.exit(main())
