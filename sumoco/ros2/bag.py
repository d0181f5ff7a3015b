"""``sumoco export rosbag2 run.mcap --out DIR``: a recording as a rosbag2 with the topics of
``sumoco ros2`` (the same ``Converter``), for ``ros2 bag play``, RViz and any ROS tool.

Messages are serialised by rclpy (CDR, exactly as a live publisher sends them) and written
by ``rosbags`` (rosbag2 format version 9, MCAP storage by default, or SQLite 3), with the
message definitions and type hashes of ROS 2 Kilted and each topic's QoS as ``sumoco ros2``
offers it. Each message's bag time is its header stamp, i.e. **simulation time** (so
``ros2 bag play --clock`` gives ``/clock`` in simulation time too; the recorded ``/clock``
is there as well). The map is written once per static-data version.
"""

from __future__ import annotations

import logging
from pathlib import Path

from protocol.codec import DEFAULT_LIMITS, decode
from protocol.errors import ConfigError, ProtocolError
from protocol.keys import Keys
from protocol.messages import PhysicsState, StaticData, StepMessage
from sumoco.recording.record import kind_of_topic, open_recording
from sumoco.ros2.config import Ros2Config

log = logging.getLogger(__name__)

#: ROS type of each topic family (by the topic's last part)
ROS_TYPES = {"clock": "rosgraph_msgs/msg/Clock", "agents": "visualization_msgs/msg/MarkerArray",
             "poses": "geometry_msgs/msg/PoseArray", "map": "visualization_msgs/msg/MarkerArray",
             "odom": "nav_msgs/msg/Odometry"}


def _qos(kind: str):
    """rosbags' QoS record of ``sumoco ros2``'s profile ``kind`` (node.qos_profiles)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    rel = QosReliability.BEST_EFFORT if kind == "stream" else QosReliability.RELIABLE
    dur = QosDurability.TRANSIENT_LOCAL if kind == "latched" else QosDurability.VOLATILE
    inf = QosTime(0x7FFFFFFF, 0xFFFFFFFF)
    return Qos(QosHistory.KEEP_LAST, 1, rel, dur, inf, inf, QosLiveliness.AUTOMATIC, inf, False)


def _type_of(topic: str, cfg: Ros2Config) -> tuple[str, str]:
    """(ROS type, QoS profile name) of one of the converter's topics."""
    if topic == "/clock":
        return ROS_TYPES["clock"], "clock"
    rel = topic[len(cfg.prefix.rstrip("/")) + 1:]
    head = rel.split("/")[0]
    return ROS_TYPES[head], ("latched" if head == "map" else "stream")


def export_rosbag2(recording: str | Path, out: str | Path, cfg: Ros2Config, storage: str = "mcap") -> dict:
    """Write ``out`` (a new rosbag2 folder); returns counts per topic."""
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from sumoco.ros2.messages import Converter

    out = Path(out)
    if out.exists():
        raise ConfigError(f"{out}: exists already; rosbag2 export writes a new folder")
    rec = open_recording(recording)
    conv = Converter(cfg)
    store = get_typestore(Stores.ROS2_KILTED)
    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
    counts: dict[str, int] = {}
    conns: dict[str, object] = {}
    static_versions: set[int] = set()
    skipped = 0
    last_t = 0.0
    with Writer(out, version=9, storage_plugin=plugin) as writer:
        def write(items) -> None:
            for topic, msg, stamp in items:
                conn = conns.get(topic)
                if conn is None:
                    rtype, qos = _type_of(topic, cfg)
                    conn = conns[topic] = writer.add_connection(topic, rtype, typestore=store,
                                                                offered_qos_profiles=[_qos(qos)])
                writer.write(conn, max(0, int(round(stamp * 1e9))), serialize_message(msg))
                counts[topic] = counts.get(topic, 0) + 1

        for m in rec.messages:
            if m.schema not in ("step", "physics", "static"):
                continue
            try:
                msg = decode(m.data, DEFAULT_LIMITS)
            except ProtocolError as e:
                skipped += 1
                log.debug("skipping undecodable %s on %s: %s", m.schema, m.topic, e)
                continue
            if isinstance(msg, StaticData):
                if msg.version not in static_versions:
                    static_versions.add(msg.version)
                    write(conv.static(msg, last_t))
            elif isinstance(msg, StepMessage):
                last_t = msg.time
                write(conv.step(msg))
            elif isinstance(msg, PhysicsState) and kind_of_topic(m.topic) == "physics":
                write(conv.physics(msg, Keys.instance_of(m.topic)))
    if rec.truncated:
        log.warning("%s ends early (%s): exported what it holds", recording, rec.error)
    return {"out": str(out), "storage": storage, "source": cfg.source, "topics": counts, "skipped": skipped,
            "truncated": rec.truncated}


def cli_main(args) -> int:
    """``sumoco export rosbag2``."""
    import json

    from sumoco.ros2.node import _ros2_config

    data, base = {}, None
    if args.config:
        from runtime.config import load_toml

        data, base = load_toml(args.config)
    args.domain_id = None
    args.ego = None
    cfg = _ros2_config(args, data, base)
    result = export_rosbag2(args.recording, args.out, cfg, args.storage)
    print(json.dumps(result))
    return 0
