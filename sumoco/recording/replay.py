"""``sumoco replay run.mcap``: a recording republished on Zenoh as the daemons published it.

Renderer and game-engine authors can develop against a recorded run without SUMO or
MuJoCo (this needs only the bare ``pip install sumoco``). What a client sees is what the
daemons offered live:

- every recorded step, physics state and ack on its own key (the recorded key), paced by the
  recorded receive times divided by ``speed``: as the recorded msgpack bytes from a raw
  recording, re-encoded protocol messages (equal within SPEC 11's units) from a compact one;
- the static data answered by a queryable on ``<root>/<run>/sumo/static`` (each recorded
  version from the point it was recorded on, SPEC 3.2), and the glTF
  map on ``<root>/<run>/sumo/map`` when the recording holds it (SPEC 9);
- liveliness tokens ``<root>/<run>/sumo/alive`` and ``.../physics/<inst>/alive`` for every
  physics instance in the recording (declared when it first appears).

Ego poses in the recording came from outside clients and the Foxglove ``/scene`` channel
is not a Zenoh key: neither is republished. With ``loop`` the recording starts over at the
end (step indices and simulated time then go back: a client sees a restarted run). A
replay is an incarnation of the run of its own (SPEC 3.1.1): steps and static data go out
with the replayer's ``epoch`` instead of the recorded one, a new one for every pass, so a
receiver takes each pass as a restart and not as a replay of old steps. A recording that
ends early (a crash) is replayed up to its last readable message.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import msgpack
import zenoh

from protocol.errors import ConfigError
from protocol.order import new_epoch
from sumoco.recording.record import RecordedMessage, RecordingError, kind_of_topic, open_recording

log = logging.getLogger(__name__)

#: Kinds the daemons publish with ``put`` (the static data is served by the queryable).
REPUBLISHED = ("step", "physics", "ack")


@dataclass
class ReplayStats:
    published: int = 0
    steps: int = 0
    loops: int = 0
    static_queries: int = 0
    map_queries: int = 0
    late_ms_max: float = 0.0  # [ms] worst lateness of a put against its schedule
    truncated: bool = False


#: [s of recording] how far past the static data to look for the recorded glTF map
MAP_SEARCH_S = 120.0


def _static_and_map(rec) -> tuple[tuple[str, bytes] | None, tuple[str, bytes] | None]:
    """The first static-data and map messages of a recording.

    The map is recorded after the static data (the SUMO side builds it after start-up), so
    the search goes on for ``MAP_SEARCH_S`` of recording past the static data, not through
    the whole file.
    """
    static = mapped = None
    t_static = None
    for m in rec.messages:
        kind = m.schema if m.schema in ("static", "map") else kind_of_topic(m.topic)
        if kind == "static" and static is None:
            static, t_static = (m.topic, m.data), m.log_time_ns
        elif kind == "map" and mapped is None:
            mapped = (m.topic, m.data)
        if static is not None and (mapped is not None or m.log_time_ns - t_static > MAP_SEARCH_S * 1e9):
            break
    return static, mapped


def restamp(payload: bytes, epoch: int) -> bytes:
    """A recorded step or static data with ``epoch`` in place of the recorded one (SPEC 3.1.1);
    everything else as recorded (a payload that is not a msgpack map goes out unchanged)."""
    try:
        d = msgpack.unpackb(payload, raw=False)
    except Exception:  # msgpack raises a zoo of types; a receiver rejects it as it would have
        return payload
    if not isinstance(d, dict):
        return payload
    d["epoch"] = int(epoch)
    return msgpack.packb(d, use_bin_type=True)


def map_reply(recorded: bytes, parameters: str) -> bytes:
    """The recorded map answer, without the GLB when the asker already holds that hash (SPEC 9)."""
    pairs = (p.partition("=") for p in str(parameters or "").replace("&", ";").split(";"))
    want = {k.strip(): v.strip() for k, _, v in pairs}.get("sha256", "")
    if not want:
        return recorded
    d = msgpack.unpackb(recorded, raw=False)
    if isinstance(d, dict) and d.get("sha256") == want:
        d["glb"] = None
        return msgpack.packb(d, use_bin_type=True)
    return recorded


class Replayer:
    """Publishes a recording on a Zenoh session; ``run`` blocks until done or ``stop``."""

    def __init__(self, session: zenoh.Session, path, speed: float = 1.0, loop: bool = False,
                 limit_s: float | None = None, wait_subscriber_s: float = 0.0) -> None:
        if not speed > 0:
            raise ConfigError(f"replay speed must be > 0 (1 = as recorded), got {speed}")
        self.session = session
        self.recording = open_recording(path)
        self.speed = float(speed)
        self.loop = loop
        self.limit_s = limit_s
        self.wait_subscriber_s = float(wait_subscriber_s)
        self.stats = ReplayStats()
        self._stop = threading.Event()
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._decl: list = []
        self._tokens: dict[str, object] = {}
        self._static: tuple[str, bytes] | None = None
        self._map: tuple[str, bytes] | None = None
        self.epoch = new_epoch()  # this pass's incarnation (a new one for every pass)

    def _on_query(self, query: zenoh.Query) -> None:
        self.stats.static_queries += 1
        query.reply(self._static[0], restamp(self._static[1], self.epoch))

    def _on_map_query(self, query: zenoh.Query) -> None:
        self.stats.map_queries += 1
        try:
            query.reply(self._map[0], map_reply(self._map[1], str(query.parameters)))
        except Exception as e:  # a corrupt recorded map must not stop the replay
            query.reply_err(f"recorded map unreadable: {e}".encode())

    def _token(self, key: str) -> None:
        if key not in self._tokens:
            self._tokens[key] = self.session.liveliness().declare_token(key)

    def _announce(self, topic: str) -> None:
        """Liveliness tokens of the daemon that published ``topic``."""
        parts = topic.split("/")
        if parts[-2:] == ["sumo", "step"]:
            self._token("/".join(parts[:-1] + ["alive"]))
        elif len(parts) >= 3 and parts[-3] == "physics":
            self._token("/".join(parts[:-1] + ["alive"]))

    def setup(self) -> None:
        """Declare the static queryable and the SUMO side's token before the first put."""
        self._static, self._map = _static_and_map(self.recording)
        if self._map is not None:
            self._decl.append(self.session.declare_queryable(self._map[0], self._on_map_query))
        if self._static is None:
            log.warning("%s holds no static data: nothing answers %s queries", self.recording.path, "sumo/static")
        else:
            key = self._static[0]
            self._decl.append(self.session.declare_queryable(key, self._on_query))
            self._token(key.rsplit("/", 1)[0] + "/alive")
            if self.wait_subscriber_s > 0:
                self._wait_for_subscriber(key.rsplit("/", 1)[0] + "/step")

    def _wait_for_subscriber(self, step_key: str) -> None:
        """Hold the first put until someone subscribes to the steps (bounded)."""
        pub = self._pubs[step_key] = self.session.declare_publisher(step_key)
        deadline = time.monotonic() + self.wait_subscriber_s
        while not pub.matching_status.matching and time.monotonic() < deadline:
            if self._stop.wait(0.02):
                return
        if not pub.matching_status.matching:
            log.warning("no subscriber to %s after %.1f s: replaying anyway", step_key, self.wait_subscriber_s)

    def _put(self, m: RecordedMessage) -> None:
        pub = self._pubs.get(m.topic)
        if pub is None:
            self._announce(m.topic)
            pub = self._pubs[m.topic] = self.session.declare_publisher(m.topic)
        pub.put(restamp(m.data, self.epoch) if m.schema == "step" else m.data)
        self.stats.published += 1
        if m.schema == "step":
            self.stats.steps += 1

    def _one_pass(self) -> bool:
        """Publish the recording once; False when stopped."""
        if self.stats.loops:
            self.epoch = max(new_epoch(), self.epoch + 1)
        t0_rec = None
        t0_wall = time.monotonic()
        first_static = self._static
        for m in self.recording.messages:
            kind = m.schema if m.schema in REPUBLISHED else kind_of_topic(m.topic)
            if kind == "static" and self._static is not None:
                # A later static version (SPEC 3.2) is served from the point it was recorded on.
                self._static = (m.topic, m.data)
                continue
            if kind not in REPUBLISHED:
                continue
            if t0_rec is None:  # the clock starts at the first put, not at opening the file
                t0_rec, t0_wall = m.log_time_ns, time.monotonic()
            rec_s = (m.log_time_ns - t0_rec) / 1e9
            if self.limit_s is not None and rec_s > self.limit_s:
                break
            due = t0_wall + rec_s / self.speed
            wait = due - time.monotonic()
            if wait > 0:
                if self._stop.wait(wait):
                    return False
            elif -wait * 1e3 > self.stats.late_ms_max:
                self.stats.late_ms_max = -wait * 1e3
            if self._stop.is_set():
                return False
            self._put(m)
        self.stats.truncated = self.stats.truncated or self.recording.truncated
        self._static = first_static  # the next loop starts with the first version again
        return True

    def run(self) -> ReplayStats:
        self.setup()
        while not self._stop.is_set():
            if not self._one_pass():
                break
            self.stats.loops += 1
            if not self.loop:
                break
        return self.stats

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        for d in [*self._pubs.values(), *self._decl, *self._tokens.values()]:
            try:
                d.undeclare()
            except Exception:  # session already closed
                pass
        self._pubs.clear()
        self._decl.clear()
        self._tokens.clear()


def cli_main(args) -> int:
    """``sumoco replay run.mcap [--speed x] [--loop]``."""
    import json
    import signal

    from runtime.config import CommonConfig, apply_cli, load_common
    from runtime.transport import open_session

    common = load_common(args.config)[0] if getattr(args, "config", None) else CommonConfig()
    common = apply_cli(common, args)
    try:
        rep_path = args.recording
        open_recording(rep_path)
    except RecordingError as e:
        raise ConfigError(str(e)) from None
    with open_session(common.zenoh) as session:
        rep = Replayer(session, rep_path, speed=args.speed, loop=args.loop,
                       limit_s=getattr(args, "duration", None), wait_subscriber_s=args.wait_subscriber)
        signal.signal(signal.SIGTERM, lambda *_: rep.stop())
        signal.signal(signal.SIGINT, lambda *_: rep.stop())
        try:
            stats = rep.run()
        finally:
            rep.close()
    print(json.dumps(stats.__dict__))
    return 0
