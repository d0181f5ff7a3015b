"""Recording a run into MCAP and reading it back.

Every key under ``<root>/<run>/**`` is written as it arrives: the raw msgpack payload
(channel = key expression, schema name = message kind, message encoding ``msgpack``),
stamped with the receive time. The static data is fetched once with a query and
recorded on its key. Chunks are small so a crash loses at most the last chunk, and the
reader stops cleanly at a truncated end and says how much it read.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import zenoh
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from protocol.codec import decode
from protocol.errors import ProtocolError, SumocoError
from protocol.keys import Keys

log = logging.getLogger(__name__)

MESSAGE_ENCODING = "msgpack"
SPEC_URL = "protocol/SPEC.md"


class RecordingError(SumocoError):
    """A recording file is missing or unreadable."""


def kind_of_topic(topic: str) -> str:
    """Message kind carried on a key (the key layout of protocol.keys)."""
    parts = topic.split("/")
    if parts[-2:] == ["sumo", "step"]:
        return "step"
    if parts[-2:] == ["sumo", "static"]:
        return "static"
    if len(parts) >= 3 and parts[-3] == "physics":
        return {"state": "physics", "ack": "ack", "alive": "alive"}.get(parts[-1], "unknown")
    if len(parts) >= 2 and parts[-2] == "ego":
        return "ego"
    return "unknown"


class McapRecorder:
    """Writes raw messages to an MCAP file; thread-safe ``write``."""

    def __init__(self, path: str | Path, chunk_size: int = 64 * 1024) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = self.path.open("wb")
        self._w = Writer(self._f, chunk_size=chunk_size, compression=CompressionType.NONE)
        self._w.start(profile="sumoco", library="sumoco")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._seq: dict[int, int] = {}
        self._lock = threading.Lock()
        self.count = 0
        self.closed = False

    def _channel(self, topic: str, schema: str, encoding: str = MESSAGE_ENCODING,
                 schema_encoding: str = "", schema_data: bytes = b"") -> int:
        ch = self._channels.get(topic)
        if ch is None:
            sid = self._schemas.get(schema)
            if sid is None:
                sid = self._w.register_schema(
                    name=schema, encoding=schema_encoding,
                    data=schema_data or f"sumoco {schema} message, see {SPEC_URL}".encode(),
                )
                self._schemas[schema] = sid
            ch = self._w.register_channel(topic=topic, message_encoding=encoding, schema_id=sid)
            self._channels[topic] = ch
            self._seq[ch] = 0
        return ch

    def write(self, topic: str, payload: bytes, stamp_ns: int | None = None,
              schema: str | None = None) -> None:
        stamp = time.time_ns() if stamp_ns is None else stamp_ns
        with self._lock:
            if self.closed:
                return
            ch = self._channel(topic, schema or kind_of_topic(topic))
            self._seq[ch] += 1
            self._w.add_message(channel_id=ch, log_time=stamp, publish_time=stamp,
                                data=payload, sequence=self._seq[ch])
            self.count += 1

    def write_encoded(self, topic: str, payload: bytes, schema: str, encoding: str,
                      schema_encoding: str, schema_data: bytes, stamp_ns: int) -> None:
        """Write a message of a foreign encoding (e.g. a Foxglove JSON scene)."""
        with self._lock:
            if self.closed:
                return
            ch = self._channel(topic, schema, encoding, schema_encoding, schema_data)
            self._seq[ch] += 1
            self._w.add_message(channel_id=ch, log_time=stamp_ns, publish_time=stamp_ns,
                                data=payload, sequence=self._seq[ch])
            self.count += 1

    def close(self) -> None:
        with self._lock:
            if self.closed:
                return
            self.closed = True
            self._w.finish()
            self._f.close()


class LiveRecorder:
    """Subscribes to every key of a run and records it (use ``start``/``stop``).

    With ``scene=True`` (and foxglove-sdk installed) it also writes a Foxglove 3D scene
    channel built from the step and physics messages as they arrive.
    """

    def __init__(self, session: zenoh.Session, keys: Keys, recorder: McapRecorder,
                 on_message=None, scene: bool = True) -> None:
        from sumoco.app import scene as scene_mod

        self.session, self.keys, self.rec = session, keys, recorder
        self._on_message = on_message
        self._sub = None
        self._scene = scene_mod if scene and scene_mod.available() else None
        self._sizes: dict[str, tuple[float, float]] = {}
        self.scene_errors = 0

    def _cb(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        topic = str(sample.key_expr)
        stamp = time.time_ns()
        self.rec.write(topic, payload, stamp)
        if self._scene is not None:
            self._write_scene(topic, payload, stamp)
        if self._on_message is not None:
            self._on_message(topic, payload)

    def _write_scene(self, topic: str, payload: bytes, stamp: int) -> None:
        kind = kind_of_topic(topic)
        if kind not in ("step", "physics", "static"):
            return
        try:
            msg = decode(payload)
            if kind == "step":
                a = msg.agents
                self._sizes = dict(zip(a.ids, zip(a.length.tolist(), a.width.tolist())))
                data = self._scene.step_scene(msg)
            elif kind == "physics":
                data = self._scene.physics_scene(msg, Keys.instance_of(topic), self._sizes)
            else:
                data = self._scene.network_scene(msg)
        except Exception as e:  # a scene problem must never stop the raw recording
            self.scene_errors += 1
            log.debug("scene update failed for %s: %s", topic, e)
            return
        name, enc, sch = self._scene.schema()
        self.rec.write_encoded(self._scene.SCENE_TOPIC, data, name, "protobuf", enc, sch, stamp)

    def start(self) -> "LiveRecorder":
        self._sub = self.session.declare_subscriber(self.keys.everything, self._cb)
        return self

    def fetch_static(self, timeout_s: float = 5.0) -> bytes | None:
        """One query for the static data; recorded when it arrives."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for reply in self.session.get(self.keys.static, timeout=min(2.0, timeout_s)):
                if reply.ok is not None:
                    data = reply.ok.payload.to_bytes()
                    stamp = time.time_ns()
                    self.rec.write(self.keys.static, data, stamp, schema="static")
                    if self._scene is not None:
                        self._write_scene(self.keys.static, data, stamp)
                    return data
            time.sleep(0.05)
        return None

    def stop(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None


def record_cli(args) -> int:
    """``sumoco record --out run.mcap``: record a live run until Ctrl-C or --duration."""
    import signal

    from sumoco.common.config import apply_cli, load_common, CommonConfig
    from sumoco.common.transport import open_session

    common = load_common(args.config)[0] if args.config else CommonConfig()
    common = apply_cli(common, args)
    keys = Keys(common.zenoh.root, common.run.id)
    rec = McapRecorder(args.out)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        with open_session(common.zenoh) as session:
            live = LiveRecorder(session, keys, rec).start()
            if live.fetch_static(timeout_s=10.0) is None:
                log.warning("no static data answered on %s (recording the live keys anyway)", keys.static)
            limit = float(args.duration) if getattr(args, "duration", None) else None
            stop.wait(limit)
            live.stop()
    finally:
        rec.close()
    log.info("recorded %d messages to %s", rec.count, args.out)
    return 0


@dataclass
class RecordedMessage:
    topic: str
    schema: str
    log_time_ns: int
    data: bytes


@dataclass
class ReadResult:
    messages: list[RecordedMessage] = field(default_factory=list)
    truncated: bool = False
    error: str = ""


def read_recording(path: str | Path) -> ReadResult:
    """Read all messages; a truncated file yields what it holds with ``truncated=True``."""
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"{p}: recording not found")
    out = ReadResult()
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, int]] = {}
    with p.open("rb") as f:
        try:
            # The streaming reader yields records as it meets them, so everything before a
            # truncated end is kept (the indexed readers need the footer).
            for rec in StreamReader(f, skip_magic=False, emit_chunks=False).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec.name
                elif isinstance(rec, Channel):
                    channels[rec.id] = (rec.topic, rec.schema_id)
                elif isinstance(rec, Message):
                    topic, sid = channels.get(rec.channel_id, ("", 0))
                    out.messages.append(RecordedMessage(topic, schemas.get(sid, ""), rec.log_time, rec.data))
        except Exception as e:  # truncated chunk/record: keep what was read
            out.truncated = True
            out.error = f"{type(e).__name__}: {e}"
    if not out.messages and out.truncated:
        raise RecordingError(f"{p}: no readable messages ({out.error})")
    return out


def iter_decoded(res: ReadResult, kinds: tuple[str, ...] = ("step", "physics", "static")
                 ) -> Iterator[tuple[RecordedMessage, object]]:
    """Decoded protocol messages of the given kinds; undecodable ones are skipped."""
    for m in res.messages:
        if m.schema not in kinds:
            continue
        try:
            yield m, decode(m.data)
        except ProtocolError as e:
            log.debug("skipping undecodable %s on %s: %s", m.schema, m.topic, e)
