"""``sumoco ros2``: a ROS 2 node that joins a run over Zenoh like any client.

Threads (nothing on Zenoh's thread waits for ROS):

- Zenoh's callbacks only append the raw payload to a bounded deque per kind (steps, the
  chosen physics instance's states, static data; ``[ros2] queue`` each, the oldest dropped
  and counted) and wake the publishing thread;
- the publishing thread decodes (with the run's size limits), converts (``messages``) and
  publishes; when it falls behind it skips to the newest messages, and ``rate_hz`` thins
  agents, poses and odometry by simulation time;
- a ROS executor thread serves the ego subscriptions (``egos``), whose callbacks check a
  pose and put one ego message on Zenoh with congestion control *drop*.

A ROS subscriber that stalls or vanishes slows nothing: high-rate topics are best effort
with a history of 1, the latched map and the clock are reliable with a history of 1 (Fast
DDS replaces an unacknowledged sample rather than wait), and the Zenoh side never waits
for the publishing thread. DDS stays on loopback (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``)
unless ``[ros2] localhost_only = false``.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import threading
import time

import zenoh

from protocol.codec import DecodeLimits, decode
from protocol.errors import ProtocolError
from protocol.keys import Keys
from protocol.messages import PhysicsState, StaticData, StepMessage
from runtime.transport import Wake
from sumoco.ros2.config import Ros2Config, ros_name

log = logging.getLogger(__name__)

STATIC_RETRY_S = 2.0  # [s] between static-data queries while a step's version is unknown


def ros_environment(cfg: Ros2Config) -> None:
    """What rclpy needs from the environment, set before ``rclpy.init`` so a plain shell
    works: Fast DDS as the middleware, discovery on loopback, the domain id."""
    os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    if cfg.localhost_only:
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    if cfg.domain_id is not None:
        os.environ["ROS_DOMAIN_ID"] = str(cfg.domain_id)


def qos_profiles():
    """name -> QoSProfile (README "ROS 2" lists them per topic)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    def q(rel, dur):
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=rel, durability=dur)

    return {
        "stream": q(ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.VOLATILE),  # agents, poses, odometry
        "latched": q(ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL),  # the map
        "clock": q(ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE),
        "ego": q(ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE),
    }


class Inbox:
    """Bounded deques of raw payloads, one per kind; the oldest is dropped when full (counted)."""

    def __init__(self, maxlen: int) -> None:
        self._lock = threading.Lock()
        self._q: dict[str, collections.deque] = {}
        self.maxlen = maxlen
        self.dropped = 0
        self.wake = Wake()

    def put(self, kind: str, key: str, data: bytes) -> None:
        with self._lock:
            q = self._q.get(kind)
            if q is None:
                q = self._q[kind] = collections.deque(maxlen=self.maxlen)
            if len(q) == q.maxlen:
                self.dropped += 1
            q.append((key, data))
        self.wake.set()

    def take(self) -> dict[str, list[tuple[str, bytes]]]:
        with self._lock:
            self.wake.clear()
            out = {k: list(q) for k, q in self._q.items() if q}
            for q in self._q.values():
                q.clear()
        return out


class RosBridge:
    """One run on ROS 2 topics, and egos from ROS 2 into the run."""

    def __init__(self, session: zenoh.Session, keys: Keys, cfg: Ros2Config, node, limits: DecodeLimits,
                 ego_ids: tuple[str, ...] = ("*",), ego_max: int = 8) -> None:
        from rclpy.executors import SingleThreadedExecutor
        from geometry_msgs.msg import PoseArray, PoseStamped
        from nav_msgs.msg import Odometry
        from rosgraph_msgs.msg import Clock
        from visualization_msgs.msg import MarkerArray

        from sumoco.ros2.egos import EgoInput
        from sumoco.ros2.messages import Converter

        self.session, self.keys, self.cfg, self.node, self.limits = session, keys, cfg, node, limits
        self.conv = Converter(cfg)
        self.inbox = Inbox(cfg.queue)
        self.decode_errors = 0
        self.publish_errors = 0
        self.egos_refused = 0
        self._static_sv: int | None = None
        self._static_asked = 0.0
        self._stop = threading.Event()
        self._decl: list = []
        qos = qos_profiles()
        self._pubs = {"/clock": node.create_publisher(Clock, "/clock", qos["clock"]),
                      cfg.topic("map"): node.create_publisher(MarkerArray, cfg.topic("map"), qos["latched"]),
                      cfg.topic("agents"): node.create_publisher(MarkerArray, cfg.topic("agents"), qos["stream"]),
                      cfg.topic("poses"): node.create_publisher(PoseArray, cfg.topic("poses"), qos["stream"])}
        for agent in cfg.odometry:
            t = cfg.topic("odom", ros_name(agent))
            self._pubs[t] = node.create_publisher(Odometry, t, qos["stream"])
        self.egos: dict[str, EgoInput] = {}
        for ego in cfg.egos:
            if "*" not in ego_ids and ego not in ego_ids:
                self.egos_refused += 1
                log.error("ego %r refused: the SUMO side takes ego ids %s only ([sumo] ego_id); no subscription "
                          "for it", ego, ", ".join(map(repr, ego_ids)))
                continue
            if len(self.egos) >= ego_max:
                self.egos_refused += 1
                log.error("ego %r refused: the SUMO side drives at most %d egos ([sumo] ego_max)", ego, ego_max)
                continue
            pub = session.declare_publisher(keys.ego(ego), congestion_control=zenoh.CongestionControl.DROP)
            self._decl.append(pub)
            inp = self.egos[ego] = EgoInput(ego, pub.put, cfg.frame_id, cfg.ego_length_m, cfg.ego_max_hz)
            node.create_subscription(PoseStamped, cfg.topic("ego", ros_name(ego), "pose"), inp.on_pose, qos["ego"])
            node.create_subscription(Odometry, cfg.topic("ego", ros_name(ego), "odom"), inp.on_odometry, qos["ego"])
        self.executor = SingleThreadedExecutor(context=node.context)
        self.executor.add_node(node)
        self._threads = [threading.Thread(target=self._publish_loop, name="ros2-publish", daemon=True),
                         threading.Thread(target=self._spin, name="ros2-executor", daemon=True)]

    @property
    def topics(self) -> list[str]:
        subs = [self.cfg.topic("ego", ros_name(e), s) for e in self.egos for s in ("pose", "odom")]
        return [*self._pubs, *subs]

    # --- Zenoh's thread: hand over, never wait ----------------------------------------
    def _on_step(self, sample: zenoh.Sample) -> None:
        self.inbox.put("step", str(sample.key_expr), sample.payload.to_bytes())

    def _on_physics(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        inst = Keys.instance_of(key)
        if self.conv.instance and inst != self.conv.instance:
            return
        self.inbox.put("physics", key, sample.payload.to_bytes())

    def _on_token(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT and str(sample.key_expr) == self.keys.sumo_alive:
            threading.Thread(target=self.fetch_static, name="ros2-static", daemon=True).start()

    def fetch_static(self) -> bool:
        self._static_asked = time.monotonic()
        for reply in self.session.get(self.keys.static, timeout=5.0):
            if reply.ok is not None:
                self.inbox.put("static", self.keys.static, reply.ok.payload.to_bytes())
                return True
        return False

    # --- the publishing thread ------------------------------------------------------------
    def _publish_loop(self) -> None:
        while not self._stop.is_set():
            if not self.inbox.wake.wait(0.5):
                continue
            batch = self.inbox.take()
            for kind in ("static", "step", "physics"):
                for key, data in batch.get(kind, ()):
                    try:
                        msg = decode(data, self.limits)
                    except ProtocolError as e:
                        self.decode_errors += 1
                        log.warning("undecodable %s on %s: %s", kind, key, e)
                        continue
                    self._handle(msg, key)

    def _handle(self, msg, key: str) -> None:
        out = []
        if isinstance(msg, StaticData):
            self._static_sv = msg.version
            log.info("static data (version %d): %d lanes, %d traffic lights; network offset %s (map = SUMO network "
                     "x/y; projected = map - offset)", msg.version, len(msg.lanes.ids), len(msg.tls_ids),
                     msg.net_offset)
            out = self.conv.static(msg)
        elif isinstance(msg, StepMessage):
            for ego, inp in self.egos.items():
                if ego in msg.agents.ids:
                    inp.length_m = float(msg.agents.length[msg.agents.ids.index(ego)])
            if msg.static_version != self._static_sv and time.monotonic() - self._static_asked > STATIC_RETRY_S:
                self._static_asked = time.monotonic()
                threading.Thread(target=self.fetch_static, name="ros2-static", daemon=True).start()
            out = self.conv.step(msg)
        elif isinstance(msg, PhysicsState):
            out = self.conv.physics(msg, Keys.instance_of(key))
        for topic, ros_msg, _ in out:
            try:
                self._pubs[topic].publish(ros_msg)
            except Exception as e:  # a closing context: count, never kill the thread
                self.publish_errors += 1
                log.debug("publish on %s failed: %s", topic, e)

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception as e:  # shutdown races (ExternalShutdownException) end the thread
            log.debug("ROS executor ended: %s", e)

    # --- life cycle ------------------------------------------------------------------------
    def start(self) -> "RosBridge":
        s, k = self.session, self.keys
        self._decl.append(s.declare_subscriber(k.step, self._on_step))
        if self.cfg.source == "physics":
            inst = self.cfg.instance
            self._decl.append(s.declare_subscriber(f"{k.base}/physics/{inst}/state" if inst else k.physics_state_all,
                                                   self._on_physics))
        self._decl.append(s.liveliness().declare_subscriber(k.sumo_alive, self._on_token, history=True))
        for t in self._threads:
            t.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for d in self._decl:
            try:
                d.undeclare()
            except zenoh.ZError:
                pass
        self._decl.clear()
        self.executor.shutdown(timeout_sec=2.0)
        for t in self._threads:
            t.join(5.0)

    def stats(self) -> dict:
        c = self.conv.stats
        return {"steps": c.steps, "physics": c.physics, "frames": c.frames, "thinned": c.thinned,
                "unjoined": c.unjoined, "physics_rows_missing": c.physics_rows_missing,
                "dropped": self.inbox.dropped, "decode_errors": self.decode_errors,
                "publish_errors": self.publish_errors, "egos_refused": self.egos_refused,
                "egos": {e: vars(i.stats) for e, i in self.egos.items()}}


def _ros2_config(args, data: dict, base) -> Ros2Config:
    from runtime.config import replace, section

    cfg = section(data, "ros2", Ros2Config, base, str(args.config or ""))
    changes = {}
    for name in ("source", "instance", "rate_hz", "domain_id"):
        v = getattr(args, name, None)
        if v is not None:
            changes[name] = v
    if args.odometry:
        changes["odometry"] = tuple(args.odometry)
    if args.ego:
        changes["egos"] = tuple(args.ego)
    cfg = replace(cfg, **changes)
    cfg.validate()
    return cfg


def cli_main(args) -> int:
    """``sumoco ros2``: publish the run on ROS 2 until Ctrl-C / SIGTERM (or --duration wall seconds)."""
    import signal

    from runtime.config import CommonConfig, apply_cli, load_common
    from runtime.transport import open_session

    if args.config:
        common, data, base = load_common(args.config)
    else:
        common, data, base = CommonConfig(), {}, None
    common = apply_cli(common, args)
    cfg = _ros2_config(args, data, base)
    ego_ids, ego_max = ("*",), 8
    if args.config and cfg.egos:  # the SUMO side's [sumo] ego_id and ego_max: refuse other ids here
        from sumo_side.config import sumo_config_from

        sc = sumo_config_from(data, base, str(args.config))
        ego_ids, ego_max = (sc.ego_id,), sc.ego_max
    ros_environment(cfg)
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    keys = Keys(common.zenoh.root, common.run.id)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    ctx = rclpy.Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = rclpy.create_node(f"sumoco_{ros_name(keys.run)}", context=ctx)
        with open_session(common.zenoh) as session:
            bridge = RosBridge(session, keys, cfg, node, common.run.decode_limits, ego_ids, ego_max).start()
            print(json.dumps({"ros2": "ready", "run": keys.run, "node": node.get_fully_qualified_name(),
                              "domain_id": ctx.get_domain_id(), "source": cfg.source, "rate_hz": cfg.rate_hz,
                              "topics": bridge.topics}), flush=True)
            t0 = time.monotonic()
            stop.wait(getattr(args, "duration", None))
            bridge.stop()
            log.info("ROS 2 bridge stopped after %.0f s: %s", time.monotonic() - t0, bridge.stats())
        node.destroy_node()
    finally:
        if ctx.ok():
            rclpy.shutdown(context=ctx)
    return 0

