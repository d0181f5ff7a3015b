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
from mcap.reader import NonSeekingReader
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

    def __init__(self, path: str | Path, chunk_size: int = 256 * 1024) -> None:
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
    """Subscribes to every key of a run and records it (use as a context manager)."""

    def __init__(self, session: zenoh.Session, keys: Keys, recorder: McapRecorder,
                 on_message=None) -> None:
        self.session, self.keys, self.rec = session, keys, recorder
        self._on_message = on_message
        self._sub = None

    def _cb(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        topic = str(sample.key_expr)
        self.rec.write(topic, payload)
        if self._on_message is not None:
            self._on_message(topic, payload)

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
                    self.rec.write(self.keys.static, data, schema="static")
                    return data
            time.sleep(0.05)
        return None

    def stop(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None


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
    with p.open("rb") as f:
        try:
            reader = NonSeekingReader(f, validate_crcs=False)
            for schema, channel, message in reader.iter_messages():
                out.messages.append(RecordedMessage(
                    channel.topic, schema.name if schema else "", message.log_time, message.data,
                ))
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
