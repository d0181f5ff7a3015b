"""Recording a run into MCAP and reading it back.

Every key under ``<root>/<run>/**`` is written as it arrives: the raw msgpack payload
(channel = key expression, schema name = message kind, message encoding ``msgpack``),
stamped with the receive time, plus a Foxglove ``/scene`` channel (``scene.py``). Writing
goes through foxglove-sdk's MCAP writer (zstd chunks), the same SDK and scene code as the
live ``sumoco foxglove`` server. The static data is fetched once with a query and
recorded on its key.

The recorder never blocks the transport: Zenoh's callback only appends the payload to a
bounded FIFO (a full queue drops the message and counts it); a writer thread thins the
physics states to ``physics_hz`` by simulated time and writes; the scene is built on its
own drop-oldest worker. Payloads are recorded as they came; where the recorder looks into
one (thinning, compact records, the scene) it decodes with limits from ``[run] max_agents``
(static data and the map with the default ones: their tables are not agents). Reading is streamed: ``open_recording`` yields messages one at a
time and stops cleanly at a truncated end (a crash loses at most the last chunk).
"""

from __future__ import annotations

import functools
import logging
import queue
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, NamedTuple

import zenoh
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader

from protocol.codec import DEFAULT_LIMITS, MAX_AGENTS, DecodeLimits, decode, encode, peek
from protocol.errors import ConfigError, ProtocolError, SumocoError
from protocol.keys import Keys
from protocol.messages import PhysicsState, StepMessage
from sumoco.recording import codec as rc

log = logging.getLogger(__name__)

MESSAGE_ENCODING = "msgpack"
SPEC_URL = "protocol/SPEC.md"
CHUNK_BYTES = 1024 * 1024  # [B] uncompressed chunk: what a crash can lose at most
#: Free space below which the recorder finishes its file: the open chunk plus the summary
#: must still fit, or a full disk cuts the file in the middle of a record [B].
RESERVE_BYTES = 4 * CHUNK_BYTES
SPACE_CHECK_S = 0.25  # [s] between free-space checks
WRITE_BATCH_S = 0.05  # [s] the writer waits this long once its queue is empty (stamps are receive times)
_RESTART_S = 1.0  # [s] simulated time going back this far means the run restarted


#: compact record schema -> the protocol message kind it decodes to
COMPACT_SCHEMAS = {rc.STEP_SCHEMA: "step", rc.PHYSICS_SCHEMA: "physics"}


class RecordingError(SumocoError):
    """A recording file is missing or unreadable."""


@functools.lru_cache(maxsize=4096)  # asked for every message; a run has a few dozen keys
def kind_of_topic(topic: str) -> str:
    """Message kind carried on a key (the key layout of protocol.keys)."""
    parts = topic.split("/")
    if parts[-2:] == ["sumo", "step"]:
        return "step"
    if parts[-2:] == ["sumo", "static"]:
        return "static"
    if parts[-2:] == ["sumo", "map"]:
        return "map"
    if len(parts) >= 3 and parts[-3] == "physics":
        return {"state": "physics", "ack": "ack", "alive": "alive"}.get(parts[-1], "unknown")
    if len(parts) >= 2 and parts[-2] == "ego":
        return "ego"
    return "unknown"


@dataclass(frozen=True)
class RecordConfig:
    """``[record]``: what the recorder keeps."""

    physics_hz: float = 10.0  # [Hz] physics states kept per instance, by simulated time; 0 = every one
    scene: bool = True  # also write the Foxglove /scene channel (needs foxglove-sdk)
    scene_hz: float = 0.5  # [Hz] scene updates per key, by simulated time; 0 = every message (2,500 agents: ~0.5 GB/h per Hz)
    queue: int = 4096  # [messages] bound of the transport -> writer queue (full: drop + count)
    queue_mb: float = 256.0  # [MB] the same queue's bound in payload bytes (full: drop + count)
    scene_queue: int = 8  # [messages] bound of the scene worker's queue (full: drop oldest)
    flush_s: float = 2.0  # [s] wall clock between forced chunk ends: what a crash can lose at most
    #: ``compact``: steps and physics states quantised and delta-coded (SPEC 11, replay gives back
    #: equal messages up to the stated units); ``raw``: every payload as it came (byte-exact replay)
    encoding: str = "compact"

    def __post_init__(self) -> None:
        for name in ("physics_hz", "scene_hz", "flush_s", "queue_mb"):
            if getattr(self, name) < 0:
                raise ConfigError(f"[record] {name} must be >= 0 (0 keeps every message), got {getattr(self, name)}")
        if self.encoding not in ("compact", "raw"):
            raise ConfigError(f"[record] encoding must be 'compact' or 'raw', got {self.encoding!r}")
        for name in ("queue", "scene_queue"):
            if getattr(self, name) < 1:
                raise ConfigError(f"[record] {name} must be >= 1, got {getattr(self, name)}")


class McapRecorder:
    """Writes raw messages to MCAP through foxglove-sdk (thread-safe ``write``).

    ``context`` is the recorder's own ``foxglove.Context``: channels logged in it (the raw
    keys and the scene) go to this file only.
    """

    def __init__(self, path: str | Path, chunk_size: int = CHUNK_BYTES) -> None:
        import foxglove
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.context = foxglove.Context()
        self._foxglove = foxglove
        self._w = foxglove.open_mcap(
            self.path, allow_overwrite=True, context=self.context,
            writer_options=MCAPWriteOptions(compression=MCAPCompression.Zstd, chunk_size=chunk_size,
                                            profile="sumoco", compression_threads=0),
        )
        self._channels: dict[str, object] = {}
        self._lock = threading.Lock()
        self.count = 0
        self.closed = False

    def _channel(self, topic: str, schema: str):
        # one channel per (key, schema): a key may switch to raw when a message cannot be compacted
        ch = self._channels.get((topic, schema))
        if ch is None:
            fg = self._foxglove
            compact = schema in COMPACT_SCHEMAS
            ch = fg.Channel(topic, message_encoding=rc.ENCODING if compact else MESSAGE_ENCODING,
                            context=self.context,
                            schema=fg.Schema(name=schema, encoding="",
                                             data=(f"sumoco compact recording record ({COMPACT_SCHEMAS[schema]}), "
                                                   f"see {SPEC_URL} section 11" if compact else
                                                   f"sumoco {schema} message, see {SPEC_URL}").encode()))
            self._channels[(topic, schema)] = ch
        return ch

    @property
    def channel_count(self) -> int:
        """MCAP channels opened so far (one per key and schema)."""
        with self._lock:
            return len(self._channels)

    def write(self, topic: str, payload: bytes, stamp_ns: int | None = None,
              schema: str | None = None) -> None:
        stamp = time.time_ns() if stamp_ns is None else stamp_ns
        with self._lock:
            if self.closed:
                return
            self._channel(topic, schema or kind_of_topic(topic)).log(payload, log_time=stamp)
            self.count += 1

    def flush(self) -> None:
        """End the current chunk and write it out (a crash then loses nothing before this)."""
        with self._lock:
            if not self.closed:
                self._w.flush()

    def close(self) -> None:
        with self._lock:
            if self.closed:
                return
            self.closed = True
            for ch in self._channels.values():
                ch.close()
            try:
                self._w.close()
            except RuntimeError as e:  # a write failed earlier (disk full, I/O error)
                raise RecordingError(
                    f"{self.path}: writing the recording failed ({e}); it holds what was written before "
                    "the failure (readers stop at the cut)") from None

    def out_of_space(self) -> str | None:
        """Finish the file while it still fits when free space drops below ``RESERVE_BYTES``.

        A full disk would otherwise cut a chunk in half; closing early leaves a complete
        file (summary and footer written). Returns the reason once closed, else None.
        """
        if self.closed:
            return None
        free = shutil.disk_usage(self.path.parent).free
        if free >= RESERVE_BYTES:
            return None
        self.close()
        return (f"{self.path}: disk nearly full ({free / 2**20:.1f} MiB free, {RESERVE_BYTES / 2**20:.0f} MiB "
                f"kept in reserve): recording stopped after {self.count} messages; the file is complete "
                "up to there")


class RecorderState(NamedTuple):
    """What a ``LiveRecorder`` keeps between messages (``debug_state``): all of it should be
    bounded by the keys of the run, never grow with steps, restarts or agent names."""

    encoder_agents: dict[str, int]  # key -> agents the compact encoder remembers
    thinning_keys: frozenset[str]  # keys whose last kept physics time is remembered
    scene_keys: frozenset[str]  # keys the scene thins by time ({} without a scene)
    scene_sizes: int  # agent sizes the scene remembers (0 without a scene)


class LiveRecorder:
    """Subscribes to every key of a run and records it (use ``start``/``stop``).

    Counters: ``received``, ``dropped`` (queue full), ``thinned`` (physics states skipped by
    ``physics_hz``), ``written``; ``late`` (arrived after ``stop`` began, not recorded and not
    in ``received``); ``scene_errors`` and ``scene_dropped`` for the scene. Every received
    message is written, thinned, dropped or counted in ``write_errors``.
    ``limits``: the decode limits of steps and physics states (``RunConfig.decode_limits``
    of the run; by default those of the largest run).
    """

    def __init__(self, session: zenoh.Session, keys: Keys, recorder: McapRecorder,
                 on_message=None, scene: bool | None = None, config: RecordConfig | None = None,
                 limits: DecodeLimits | None = None) -> None:
        from sumoco.viewing import scene as scene_mod

        self.session, self.keys, self.rec = session, keys, recorder
        self.config = config or RecordConfig()
        self.limits = limits or DecodeLimits.for_agents(MAX_AGENTS)
        self._on_message = on_message
        self._sub = None
        want_scene = self.config.scene if scene is None else scene
        self._scene = None
        self._scene_worker = None
        if want_scene and scene_mod.available():
            period = 1.0 / self.config.scene_hz if self.config.scene_hz > 0 else 0.0
            self._scene = scene_mod.ScenePublisher(recorder.context, min_period_s=period, limits=self.limits)
            self._scene_worker = scene_mod.LatestWorker(self._scene.feed, self.config.scene_queue, "record-scene")
        self._q: queue.Queue = queue.Queue(self.config.queue)
        self._queued_bytes = 0
        self._max_bytes = int(self.config.queue_mb * 1e6)
        self._bytes_lock = threading.Lock()
        self._period = 1.0 / self.config.physics_hz if self.config.physics_hz > 0 else 0.0
        self._last_t: dict[str, float] = {}
        self.received = self.dropped = self.thinned = self.written = self.write_errors = 0
        self.late = 0
        # Set under _bytes_lock by stop(): Zenoh may still be running a callback when the
        # subscriber is undeclared, and a sample queued behind the writer's end marker would be
        # counted as received but never written.
        self._closing = False
        self.compact_errors = 0
        self.idle_waits = 0  # times the writer found its queue empty and paused
        self._encoder = rc.CompactEncoder() if self.config.encoding == "compact" else None
        self._stopped = threading.Event()
        self._static_sv: int | None = None
        self._static_bytes: bytes | None = None  # the newest static data recorded (one payload)
        self._last_step: int | None = None
        self._refetching = threading.Event()
        self.static_versions = 0
        self.failed: str | None = None  # why recording stopped early (disk full), else None
        # Each message's log time; a test swaps in its own clock (patching time.time_ns would
        # also count every other thread's call).
        self.clock_ns = time.time_ns
        self._writer = threading.Thread(target=self._write_loop, name="record-writer", daemon=True)
        self._writer.start()

    @property
    def scene_errors(self) -> int:
        return self._scene.errors if self._scene else 0

    @property
    def scene_dropped(self) -> int:
        return self._scene_worker.dropped if self._scene_worker else 0

    def on_sample(self, sample: zenoh.Sample) -> None:
        """The subscriber's callback (Zenoh's thread): copy the bytes and hand them over to
        the writer, nothing else; a full queue drops the sample and counts it."""
        item = (str(sample.key_expr), sample.payload.to_bytes(), self.clock_ns())
        n = len(item[1])
        with self._bytes_lock:  # the check and the put are one step against stop()
            if self._closing:
                self.late += 1
                return
            self.received += 1
            if self._queued_bytes + n > self._max_bytes:
                self.dropped += 1
            else:
                try:
                    self._q.put_nowait(item)
                    self._queued_bytes += n
                except queue.Full:
                    self.dropped += 1
        if self._on_message is not None:
            self._on_message(item[0], item[1])

    def _keep(self, topic: str, payload: bytes) -> bool:
        if not self._period or not topic.endswith("/state"):
            return True
        t = peek(payload, ("t",), self.limits).get("t")
        if t is None:
            return True
        last = self._last_t.get(topic)
        # A time well before the last kept one is a restarted run: keep it and start over.
        if last is not None and last - _RESTART_S <= t < last + self._period - 1e-6:
            self.thinned += 1
            return False
        self._last_t[topic] = t
        return True

    def _write_loop(self) -> None:
        next_flush = time.monotonic() + self.config.flush_s
        next_space = 0.0
        while True:
            if time.monotonic() >= next_space and not self.failed:
                next_space = time.monotonic() + SPACE_CHECK_S
                # a recorder without a file of its own (a test double) has no disk to fill
                check = getattr(self.rec, "out_of_space", None)
                self.failed = check() if check is not None else None
                if self.failed:
                    log.error("%s", self.failed)
            if self.config.flush_s and time.monotonic() >= next_flush:
                self.rec.flush()
                next_flush = time.monotonic() + self.config.flush_s
            try:
                item = self._q.get_nowait()
            except queue.Empty:
                # Nothing queued: let messages gather before waiting for the next one. Woken
                # for each message, on a host whose cores the daemons keep busy, the writer
                # spent as much CPU on the wake-up as on the message.
                self.idle_waits += 1
                time.sleep(WRITE_BATCH_S)
                try:
                    item = self._q.get(timeout=self.config.flush_s or None)
                except queue.Empty:
                    continue
            try:
                if item is None:
                    return
                topic, payload, stamp, schema = item if len(item) == 4 else (*item, None)
                with self._bytes_lock:
                    self._queued_bytes -= len(payload)
                if self.failed or not self._keep(topic, payload):
                    continue
                data, out_schema, msg = self._compact(topic, payload, schema)
                try:
                    self.rec.write(topic, data, stamp, schema=out_schema)
                except Exception:
                    if self._encoder is not None:
                        self._encoder.reset(topic)  # the next record on this key must not refer to a lost one
                    raise
                self.written += 1
                self._track_static_version(topic, payload, msg)
                # the message decoded for the compact record serves the scene too (no second parse)
                if self._scene_worker is not None and self._scene.offer(
                        topic, payload, None if msg is None else msg.time):
                    self._scene_worker.put(topic, payload, stamp, msg)
            except Exception:  # a write problem is logged and counted; recording goes on
                self.write_errors += 1
                log.exception("recording %s failed", item[0] if item else "?")
            finally:
                self._q.task_done()

    def _compact(self, topic: str, payload: bytes, schema: str | None) -> tuple[bytes, str | None, object]:
        """A step or physics payload as a compact record; anything else (or a payload that does
        not decode) as it came. Also the decoded step or physics message (None if not decoded)."""
        if self._encoder is None or (schema or kind_of_topic(topic)) not in ("step", "physics"):
            return payload, schema, None
        msg = None
        try:
            msg = decode(payload, self.limits)
            out_schema, data = self._encoder.encode(topic, msg)
            return data, out_schema, msg
        except (ProtocolError, TypeError, ValueError) as e:
            self.compact_errors += 1
            self._encoder.reset(topic)
            log.debug("recording %s as it came (%s)", topic, e)
            return payload, schema, msg if isinstance(msg, (StepMessage, PhysicsState)) else None

    def _track_static_version(self, topic: str, payload: bytes, msg=None) -> None:
        """Record every static-data version the steps refer to (SPEC 3.2: tables change in a run).
        ``msg``: the payload already decoded, if it was."""
        if topic == self.keys.static:
            self._static_sv = int(peek(payload, ("sv",)).get("sv", 0))  # static data: the default limits
            self._static_bytes = payload
        elif topic == self.keys.step and self._static_sv is not None:
            if isinstance(msg, StepMessage):
                sv, step = int(msg.static_version), msg.step
            else:
                head = peek(payload, ("sv", "step"), self.limits)
                sv, step = int(head.get("sv", 0)), head.get("step")
            # A step index that goes back is a new SUMO side under the same run id: its static
            # versions start again, and its network may differ although the version is the same.
            restarted = step is not None and self._last_step is not None and step < self._last_step
            self._last_step = None if step is None else int(step)
            if (sv != self._static_sv or restarted) and not self._refetching.is_set():
                self._refetching.set()
                threading.Thread(target=self._refetch_static, args=(sv,), name="record-static",
                                 daemon=True).start()

    def _refetch_static(self, sv: int, timeout_s: float = 5.0) -> None:
        # The SUMO side re-encodes the static data at most once a second: ask until it has caught up.
        try:
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline and not self._stopped.is_set():
                try:
                    replies = [r.ok.payload.to_bytes() for r in self.session.get(self.keys.static, timeout=2.0)
                               if r.ok is not None]
                except zenoh.ZError:
                    return
                for data in replies:
                    if int(peek(data, ("sv",)).get("sv", 0)) >= sv:
                        if data == self._static_bytes:  # the same network again (a restart): on record
                            return
                        with self._bytes_lock:
                            self._queued_bytes += len(data)
                        self._q.put((self.keys.static, data, self.clock_ns(), "static"))
                        self.static_versions += 1
                        return
                self._stopped.wait(0.3)
            log.warning("static data version %d not served within %.0f s", sv, timeout_s)
        finally:
            self._refetching.clear()

    def start(self) -> "LiveRecorder":
        self._sub = self.session.declare_subscriber(self.keys.everything, self.on_sample)
        return self

    def _query(self, key: str, kind: str, timeout_s: float) -> bytes | None:
        """Ask ``key`` until answered (bounded); the answer is recorded on that key."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not self._stopped.is_set():
            try:
                replies = list(self.session.get(key, timeout=min(2.0, timeout_s)))
            except zenoh.ZError:  # the session closed under a background query
                return None
            for reply in replies:
                if reply.ok is not None:
                    data = reply.ok.payload.to_bytes()
                    with self._bytes_lock:
                        self._queued_bytes += len(data)
                    self._q.put((key, data, self.clock_ns(), kind))
                    return data
            self._stopped.wait(0.2)
        return None

    def fetch_static(self, timeout_s: float = 5.0, map_timeout_s: float = 60.0) -> bytes | None:
        """One query for the static data; recorded when it arrives. The glTF map (built by the
        SUMO side after start-up) is asked for in the background and recorded once, so a
        replay can serve it too."""
        data = self._query(self.keys.static, "static", timeout_s)
        if data is not None and map_timeout_s > 0:
            threading.Thread(target=self._query, args=(self.keys.sumo_map, "map", map_timeout_s),
                             name="record-map", daemon=True).start()
        return data

    def drain(self, timeout_s: float = 10.0) -> bool:
        """Wait until everything received so far is written (and its scene built); False on
        timeout."""
        deadline = time.monotonic() + timeout_s
        while self._q.unfinished_tasks:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.02)
        worker = self._scene_worker
        return worker is None or worker.drain(max(0.0, deadline - time.monotonic()))

    def debug_state(self) -> RecorderState:
        """Sizes of what the recorder keeps between messages (read-only, for soak checks)."""
        scene = self._scene
        return RecorderState(
            encoder_agents=self._encoder.agents_per_key() if self._encoder is not None else {},
            thinning_keys=frozenset(self._last_t),
            scene_keys=scene.thinned_keys if scene is not None else frozenset(),
            scene_sizes=scene.known_sizes if scene is not None else 0)

    def stop(self, timeout_s: float = 30.0) -> None:
        """Stop listening, then write what is queued (bounded wait)."""
        self._stopped.set()
        with self._bytes_lock:
            self._closing = True
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
        if self._writer.is_alive():
            self._q.put(None)
            self._writer.join(timeout_s)
        if self._scene_worker is not None:
            self._scene_worker.close(timeout_s)
            self._scene_worker = None
        if self.dropped:
            log.warning("recorder dropped %d of %d messages (writer queue full)", self.dropped, self.received)

    def stats(self) -> dict[str, int]:
        return {"received": self.received, "written": self.written, "dropped": self.dropped, "late": self.late,
                "write_errors": self.write_errors, "static_versions": self.static_versions,
                "thinned": self.thinned, "compact_errors": self.compact_errors, "scene_errors": self.scene_errors, "scene_dropped": self.scene_dropped}


def record_cli(args) -> int:
    """``sumoco record --out run.mcap``: record a live run until Ctrl-C or --duration."""
    import json
    import signal

    from runtime.config import CommonConfig, apply_cli, load_common, replace, section
    from runtime.errors import MissingExtraError
    from runtime.hotpath import limit_arenas, start_heap_trimmer
    from runtime.transport import open_session

    limit_arenas()  # before Zenoh's and the writer's threads: their bursts share two arenas

    try:
        import foxglove  # noqa: F401  (the MCAP writer and the scene)
    except ModuleNotFoundError as e:
        raise MissingExtraError("record", "foxglove", "foxglove") from e

    cfg = RecordConfig()
    if args.config:
        common, data, base = load_common(args.config)
        cfg = section(data, "record", RecordConfig, base, str(args.config))
    else:
        common = CommonConfig()
    common = apply_cli(common, args)
    changes = {k: v for k, v in (("physics_hz", getattr(args, "physics_hz", None)),
                                 ("scene_hz", getattr(args, "scene_hz", None))) if v is not None}
    if getattr(args, "no_scene", False):
        changes["scene"] = False
    if getattr(args, "raw", False):
        changes["encoding"] = "raw"
    if changes:
        cfg = replace(cfg, **changes)
    keys = Keys(common.zenoh.root, common.run.id)
    rec = McapRecorder(args.out)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    start_heap_trimmer()
    try:
        with open_session(common.zenoh) as session:
            live = LiveRecorder(session, keys, rec, config=cfg, limits=common.run.decode_limits).start()
            if live.fetch_static(timeout_s=10.0) is None:
                log.warning("no static data answered on %s (recording the live keys anyway)", keys.static)
            log.info("recording %s/** to %s", keys.base, args.out)
            limit = float(args.duration) if getattr(args, "duration", None) else None
            t_end = None if limit is None else time.monotonic() + limit
            while not stop.wait(0.2) and not live.failed:
                if t_end is not None and time.monotonic() >= t_end:
                    break
            live.stop()
    finally:
        rec.close()
    if live.failed:
        raise RecordingError(live.failed)
    log.info("recorded %d messages to %s", rec.count, args.out)
    print(json.dumps({"out": str(args.out), **live.stats()}))
    return 0


@dataclass
class RecordedMessage:
    topic: str
    schema: str
    log_time_ns: int
    data: bytes


class Recording:
    """A recording read as a stream: iterate ``messages`` (any number of times).

    Memory does not grow with the file's length. After an iteration, ``truncated`` and
    ``error`` say whether the file ended early (what came before is yielded).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise RecordingError(f"{self.path}: recording not found")
        self.truncated = False
        self.error = ""
        self.skipped = 0  # compact records left out (their predecessor was missing)
        self._decoder = rc.CompactDecoder()

    @property
    def messages(self) -> Iterator[RecordedMessage]:
        """Messages in file order; compact records come back as protocol payloads (``encode``
        of the decoded message) under their message kind, so readers see one format."""
        for m in self._records():
            kind = COMPACT_SCHEMAS.get(m.schema)
            if kind is None:
                yield m
                continue
            try:
                msg = self._decoder.decode(m.topic, m.schema, m.data)
            except rc.CompactError as e:
                self.skipped += 1
                log.warning("%s: %s", self.path, e)
                continue
            yield RecordedMessage(m.topic, kind, m.log_time_ns, encode(msg))

    def _records(self) -> Iterator[RecordedMessage]:
        self._decoder = rc.CompactDecoder()
        self.skipped = 0
        schemas: dict[int, str] = {}
        channels: dict[int, tuple[str, int]] = {}
        n = 0
        self.truncated, self.error = False, ""
        with self.path.open("rb") as f:
            try:
                # The streaming reader yields records as it meets them, so everything before a
                # truncated end is kept (the indexed readers need the footer).
                for rec in StreamReader(f, skip_magic=False, emit_chunks=False).records:
                    if isinstance(rec, Message):
                        topic, sid = channels.get(rec.channel_id, ("", 0))
                        n += 1
                        yield RecordedMessage(topic, schemas.get(sid, ""), rec.log_time, rec.data)
                    elif isinstance(rec, Schema):
                        schemas[rec.id] = rec.name
                    elif isinstance(rec, Channel):
                        channels[rec.id] = (rec.topic, rec.schema_id)
            except Exception as e:  # truncated chunk/record: keep what was read
                self.truncated = True
                self.error = f"{type(e).__name__}: {e}"
        if not n and self.truncated:
            raise RecordingError(f"{self.path}: no readable messages ({self.error})")


def open_recording(path: str | Path) -> Recording:
    """A streamed recording (``Recording``); raises ``RecordingError`` if the file is missing."""
    return Recording(path)


@dataclass
class ReadResult:
    messages: list[RecordedMessage] = field(default_factory=list)
    truncated: bool = False
    error: str = ""


def read_recording(path: str | Path) -> ReadResult:
    """Read all messages into memory (small files, tests); ``open_recording`` streams."""
    rec = Recording(path)
    msgs = list(rec.messages)
    return ReadResult(msgs, rec.truncated, rec.error)


def iter_decoded(res: ReadResult | Recording, kinds: tuple[str, ...] = ("step", "physics", "static")
                 ) -> Iterator[tuple[RecordedMessage, object]]:
    """Decoded protocol messages of the given kinds; undecodable ones are skipped. A file may
    come from any run, so the default (largest) decode limits apply: still bounded while
    msgpack parses."""
    for m in res.messages:
        if m.schema not in kinds:
            continue
        try:
            yield m, decode(m.data, DEFAULT_LIMITS)
        except ProtocolError as e:
            log.debug("skipping undecodable %s on %s: %s", m.schema, m.topic, e)
