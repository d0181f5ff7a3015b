"""``sumoco view``: a live view of a run in the browser (3D page with three.js, 2D page linked).

One process, three parts:

- ``ZenohFeed`` subscribes to the SUMO step key and to every physics instance's state
  key and keeps only the **newest** payload per key (``LatestStore``). It fetches the
  static data with one query at start-up, again whenever a SUMO liveliness token
  appears (SUMO (re)started), when steps arrive but no static data is known yet, and when
  a step's static version ``sv`` differs from the held static data's (SPEC 3.2: a vType
  change, new tls links) or its step index goes back (a SUMO side restarted under the same
  run id): one query at a time on one worker thread, asked again until the versions agree
  (the SUMO side re-encodes at most once a second), rounds at most once a second.
- ``ViewerServer`` serves the page (``static/``) over plain HTTP and a WebSocket on
  ``/ws`` from the same port (websockets' ``process_request`` answers the non-upgrade
  GETs), on 127.0.0.1 by default.
- Access: every request must name this server in its ``Host`` header (a loopback name or
  the configured bind address with our port: defeats DNS rebinding); the WebSocket, the
  map and ``/status`` need the per-run ``token`` (``?token=``, printed in the URL that
  ``sumoco view`` shows); a WebSocket with an ``Origin`` header must come from a page of
  this server (any other web page the user opens is refused). Refusals are 403s, counted.
- Each browser gets a ``Mailbox``: a frame is built at most ``max_hz`` times a second from
  the newest step + newest physics state per instance and *replaces* whatever frame the
  client has not taken yet. A slow browser therefore skips frames; nothing queues up.

WebSocket messages (server -> page), each one msgpack map (binary WebSocket frame).
Protocol messages are forwarded **as their raw msgpack bytes** inside a ``bin`` so the
server never decodes the hot path; the page decodes them with its own msgpack reader:

- ``{"type": "hello", "run", "root", "max_hz"}`` once on connect;
- ``{"type": "static", "static": bin, "map": sha256}``: the static-data message (SPEC 3.2),
  on connect when known and again when it changes (a new ``sv``: the page takes its vType
  table and tls links from here, so a page that joined after the step that carried
  ``vtypes`` still knows them);
- ``{"type": "frame", "seq": int, "wall": float [s, server clock], "sumo_alive": bool|nil,
  "step": bin|nil (SPEC 3.1), "physics": {instance: bin (SPEC 3.3)}}``.

``GET /status`` returns JSON counters (clients, frames built/sent/dropped, static known),
for tests and for checking a deployment with curl.
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import ipaddress
import json
import logging
import math
import secrets
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import msgpack
import numpy as np
from websockets.asyncio.server import ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from protocol.codec import COORD_LIMIT, DEFAULT_LIMITS, decode_as, peek
from protocol.errors import ProtocolError
from protocol.keys import Keys
from protocol.messages import StaticData
from protocol.order import StepOrder, Verdict
from sumoco.viewing.camera import CameraPublisher

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).resolve().parent / "static"
_CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".mjs": "text/javascript; charset=utf-8",
    ".glb": "model/gltf-binary",
}


CLOSE_TIMEOUT_S = 2.0  # [s] wait for a page's closing handshake, then drop its connection


@dataclass(frozen=True)
class ViewerConfig:
    """``[viewer]`` table of a run config."""

    host: str = "127.0.0.1"  # HTTP/WebSocket bind address (keep it on loopback)
    port: int = 8765  # TCP port of the page and the WebSocket (0 = any free port)
    max_hz: float = 15.0  # [Hz] at most this many frames per second to each browser
    stale_s: float = 5.0  # [s] forget a physics instance that has been silent this long
    static_timeout_s: float = 2.0  # [s] wait per static-data query
    static_attempts: int = 10  # queries per fetch round before waiting for a SUMO token
    token: str = ""  # access token of the page's data; "" = a new random one per start

    def validate(self) -> None:
        from protocol.errors import ConfigError

        if not 0 <= self.port <= 65535:
            raise ConfigError(f"viewer.port: expected 0..65535, got {self.port}")
        if not 0.5 <= self.max_hz <= 120:
            raise ConfigError(f"viewer.max_hz: expected 0.5..120 Hz, got {self.max_hz}")
        if self.stale_s <= 0 or self.static_timeout_s <= 0 or self.static_attempts < 1:
            raise ConfigError("viewer: stale_s and static_timeout_s must be > 0, static_attempts >= 1")
        if self.token and (len(self.token) < 16 or not self.token.replace("-", "").replace("_", "").isalnum()):
            raise ConfigError("viewer.token: expected at least 16 letters, digits, '-' or '_' (or \"\" for a "
                              "random one)")


# --------------------------------------------------------------------------- newest-only state


class LatestStore:
    """Newest payload per key, written from Zenoh's threads, read by the asyncio loop.

    Only references are swapped under the lock: a callback never waits for the loop.
    ``version`` increases on every change, so the broadcaster can tell "nothing new".
    """

    def __init__(self, stale_s: float = 5.0) -> None:
        self._lock = threading.Lock()
        self.stale_s = stale_s
        self.step: bytes | None = None
        self.physics: dict[str, tuple[bytes, float]] = {}  # instance -> (payload, rx monotonic)
        # Instances whose liveliness token went: their states are ignored until the token is
        # back, because a state sample can overtake the token's DELETE (different priorities).
        self.departed: set[str] = set()
        self.static: bytes | None = None
        self.static_sv: int | None = None  # the ``sv`` of ``static`` (SPEC 3.2), None while unknown
        self.map_glb: bytes | None = None  # the network as glTF (SPEC 9), for the 3D page
        self.map_sha256 = ""
        self.map_source = ""  # "sumo": served by the SUMO side; "static": built here from static data
        self.sumo_alive: bool | None = None  # None: no liveliness information yet
        self.version = 0
        self.static_version = 0
        self.steps_received = 0
        self.physics_received = 0
        self.static_queries = 0  # static-data queries sent (by the feed's one worker)
        self.steps_refused = 0  # steps of an older incarnation, behind or far ahead (SPEC 3.1.1): not relayed
        self._listeners: list[Callable[[], None]] = []

    def add_listener(self, fn: Callable[[], None]) -> None:
        """``fn()`` is called (from any thread) after every change."""
        self._listeners.append(fn)

    def _changed(self) -> None:
        for fn in self._listeners:
            fn()

    def put_step(self, payload: bytes) -> None:
        with self._lock:
            self.step = payload
            self.steps_received += 1
            self.version += 1
        self._changed()

    def put_physics(self, instance: str, payload: bytes) -> None:
        with self._lock:
            if instance in self.departed:
                return
            self.physics[instance] = (payload, time.monotonic())
            self.physics_received += 1
            self.version += 1
        self._changed()

    def revive_physics(self, instance: str) -> None:
        """The instance's liveliness token is (back) up: accept its states again."""
        with self._lock:
            self.departed.discard(instance)

    def drop_physics(self, instance: str) -> None:
        with self._lock:
            self.departed.add(instance)
            if self.physics.pop(instance, None) is None:
                return
            self.version += 1
        self._changed()

    def put_static(self, payload: bytes) -> None:
        sv = int(peek(payload, ("sv",)).get("sv", 0))  # absent: a 1.1 sender, version 0
        with self._lock:
            if payload == self.static:
                return
            self.static = payload
            self.static_sv = sv
            self.static_version += 1
            self.version += 1
        self._changed()

    def put_map(self, glb: bytes, sha256: str, source: str) -> None:
        """Set before the static data it belongs to, so the page's static message names it."""
        with self._lock:
            self.map_glb, self.map_sha256, self.map_source = glb, sha256, source

    def set_sumo_alive(self, alive: bool) -> None:
        with self._lock:
            if self.sumo_alive == alive:
                return
            self.sumo_alive = alive
            self.version += 1
        self._changed()

    def snapshot(self) -> tuple[int, bytes | None, dict[str, bytes], bool | None]:
        """(version, newest step, newest state per live physics instance, SUMO alive)."""
        now = time.monotonic()
        with self._lock:
            stale = [k for k, (_, t) in self.physics.items() if now - t > self.stale_s]
            for k in stale:  # a silent instance (killed without its token going) fades out
                del self.physics[k]
            if stale:
                self.version += 1
            return (self.version, self.step,
                    {k: p for k, (p, _) in sorted(self.physics.items())}, self.sumo_alive)


class Mailbox:
    """Per-client outbox holding at most ONE pending frame (and one pending static).

    ``put_frame`` replaces an untaken frame (counted in ``dropped``), so a browser that
    cannot keep up sees the newest frame next and never a backlog. Static data has its own
    slot and is taken first, so it is never lost behind frames. Used on the event loop only.
    """

    def __init__(self) -> None:
        self._frame: bytes | None = None
        self._static: bytes | None = None
        self._event = asyncio.Event()
        self.static_version = -1  # the store's static_version this client was given (-1: none)
        self.offered = 0
        self.dropped = 0
        self.taken = 0
        self.max_pending = 0

    @property
    def pending(self) -> int:
        return (self._frame is not None) + (self._static is not None)

    def put_frame(self, frame: bytes) -> None:
        self.offered += 1
        if self._frame is not None:
            self.dropped += 1
        self._frame = frame
        self.max_pending = max(self.max_pending, self.pending)
        self._event.set()

    def put_static(self, data: bytes) -> None:
        self._static = data
        self._event.set()

    async def get(self) -> bytes:
        """Wait for the next message: pending static data first, then the newest frame."""
        while True:
            if self._static is not None:
                out, self._static = self._static, None
                return out
            if self._frame is not None:
                out, self._frame = self._frame, None
                self.taken += 1
                return out
            self._event.clear()
            await self._event.wait()


def pack_frame(seq: int, step: bytes | None, physics: dict[str, bytes],
               sumo_alive: bool | None) -> bytes:
    return msgpack.packb({"type": "frame", "seq": seq, "wall": time.time(),
                          "sumo_alive": sumo_alive, "step": step, "physics": physics},
                         use_bin_type=True)


def pack_static(static: bytes, map_sha256: str = "") -> bytes:
    return msgpack.packb({"type": "static", "static": static, "map": map_sha256}, use_bin_type=True)


# --------------------------------------------------------------------------- HTTP + WebSocket


class CameraRelay:
    """Every connected page's camera on Zenoh (SPEC 3.7): the page sends ``{"op": "camera",
    "x", "y"}`` (SUMO coordinates of the point it looks at) about twice a second; each page
    gets a ``CameraPublisher`` with an id of its own, whose liveliness token goes when the
    page does. Faster messages than ``MIN_PERIOD_S`` are skipped."""

    MIN_PERIOD_S = 0.2

    def __init__(self, session: Any, keys: Keys, role: str = "viewer") -> None:
        self.session, self.keys, self.role = session, keys, role
        self._pubs: dict[object, tuple[CameraPublisher, float]] = {}
        self.sent = 0
        self.rejected = 0

    def put(self, page: object, text: str) -> None:
        """One message from ``page``; raises ``ProtocolError`` naming what is wrong."""
        try:
            req = json.loads(text)
        except ValueError:
            raise ProtocolError("expected a JSON object", "camera") from None
        if not isinstance(req, dict) or req.get("op") != "camera":
            raise ProtocolError('expected {"op": "camera", "x": ..., "y": ...}', "op")
        for k in ("x", "y"):
            v = req.get(k)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or abs(v) > COORD_LIMIT:
                raise ProtocolError(f"expected a finite number of magnitude at most {COORD_LIMIT:g}", f"camera.{k}")
        now = time.monotonic()
        ent = self._pubs.get(page)
        if ent is not None and now - ent[1] < self.MIN_PERIOD_S:
            return
        pub = ent[0] if ent is not None else CameraPublisher(self.session, self.keys, f"page-{secrets.token_hex(4)}",
                                                             self.role)
        pub.put(float(req["x"]), float(req["y"]))
        self._pubs[page] = (pub, now)
        self.sent += 1

    def drop(self, page: object) -> None:
        ent = self._pubs.pop(page, None)
        if ent is not None:
            ent[0].close()


class ViewerServer:
    """Serves the page and feeds every connected browser from a ``LatestStore``."""

    def __init__(self, cfg: ViewerConfig, store: LatestStore, run: str = "", root: str = "") -> None:
        self.cfg, self.store, self.run_id, self.root = cfg, store, run, root
        self.token = cfg.token or secrets.token_urlsafe(18)
        self.refused: dict[str, int] = {"host": 0, "origin": 0, "token": 0}
        self.clients: set[Mailbox] = set()
        self.frames_built = 0
        self.frames_sent = 0
        self.clients_total = 0
        self.cameras: CameraRelay | None = None  # set when there is a Zenoh session to put cameras on
        self.port: int | None = None
        self._wake: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._files = {
            "/" + p.relative_to(STATIC_DIR).as_posix(): (p.read_bytes(),
                                                         _CONTENT_TYPES.get(p.suffix, "application/octet-stream"))
            for p in STATIC_DIR.rglob("*") if p.is_file()
        }
        self._files["/"] = self._files["/index.html"]

    # -- called from Zenoh threads through the store
    def _notify(self) -> None:
        loop, wake = self._loop, self._wake
        if loop is not None and wake is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(wake.set)
            except RuntimeError:  # loop closing during shutdown
                pass

    def status(self) -> dict[str, Any]:
        return {
            "run": self.run_id,
            "clients": len(self.clients),
            "clients_total": self.clients_total,
            "frames_built": self.frames_built,
            "frames_sent": self.frames_sent,
            "frames_dropped": sum(c.dropped for c in self.clients),
            "max_pending": max((c.max_pending for c in self.clients), default=0),
            "static": self.store.static is not None,
            "static_sv": self.store.static_sv,
            "static_queries": self.store.static_queries,
            "steps_received": self.store.steps_received,
            "steps_refused": self.store.steps_refused,
            "physics_received": self.store.physics_received,
            "physics_instances": sorted(self.store.physics),
            "sumo_alive": self.store.sumo_alive,
            "refused": dict(self.refused),
            "map_sha256": self.store.map_sha256,
            "map_source": self.store.map_source,
            "map_bytes": len(self.store.map_glb or b""),
            "cameras_sent": self.cameras.sent if self.cameras is not None else 0,
            "cameras_rejected": self.cameras.rejected if self.cameras is not None else 0,
        }

    @property
    def url(self) -> str:
        """The page's address with the access token."""
        return f"http://{_url_host(self.cfg.host)}:{self.port}/?token={self.token}"

    def _allowed_hosts(self) -> set[str]:
        names = {"127.0.0.1", "localhost", "[::1]", _url_host(self.cfg.host)}
        return {f"{n}:{self.port}".lower() for n in names}

    def _refuse(self, why: str, detail: str) -> Response:
        self.refused[why] += 1
        log.warning("refused a request: %s", detail)
        return _response(403, f"forbidden: {detail}\n".encode(), "text/plain; charset=utf-8")

    def _check_access(self, request: Request, path: str, query: str, needs_token: bool) -> Response | None:
        """None when the request may go on, else the 403 to send."""
        hosts = request.headers.get_all("Host")
        host = hosts[0].strip().lower() if len(hosts) == 1 else repr(hosts)
        if host not in self._allowed_hosts():
            return self._refuse("host", f"Host {host!r} is not this viewer (expected one of "
                                        f"{', '.join(sorted(self._allowed_hosts()))})")
        if path == "/ws":
            origins = request.headers.get_all("Origin")
            origin = origins[0] if len(origins) == 1 else (None if not origins else repr(origins))
            if origin is not None and origin.lower().rstrip("/") not in {f"http://{h}" for h in self._allowed_hosts()}:
                return self._refuse("origin", f"WebSocket from a page of {origin!r}, not of this viewer")
        if needs_token:
            given = _query_value(query, "token") or ""
            if not hmac.compare_digest(given.encode(), self.token.encode()):
                return self._refuse("token", f"{path} without the run's token (open the URL that sumoco view printed)")
        return None

    def _process_request(self, connection: ServerConnection, request: Request) -> Response | None:
        path, _, query = request.path.partition("?")
        refusal = self._check_access(request, path, query, needs_token=path in ("/ws", "/status", "/map.glb"))
        if refusal is not None:
            return refusal
        if path == "/ws":
            return None  # go on with the WebSocket handshake
        if path == "/status":
            return _response(200, json.dumps(self.status()).encode(), "application/json")
        if path == "/map.glb":
            glb = self.store.map_glb
            if glb is None:
                return _response(404, b"no map yet: the SUMO side has sent no static data\n", "text/plain")
            return _response(200, glb, "model/gltf-binary")
        if path == "/favicon.ico":
            return _response(204, b"", "text/plain")
        hit = self._files.get(path)
        if hit is None:
            return _response(404, f"not found: {path}\n".encode(), "text/plain; charset=utf-8")
        return _response(200, hit[0], hit[1])

    async def _handler(self, ws: ServerConnection) -> None:
        box = Mailbox()
        peer = ws.remote_address
        await ws.send(msgpack.packb({"type": "hello", "run": self.run_id, "root": self.root,
                                     "max_hz": self.cfg.max_hz}, use_bin_type=True))
        version = self.store.static_version  # before the data: a change in between is sent again, never missed
        static = self.store.static
        if static is not None:
            box.static_version = version
            box.put_static(pack_static(static, self.store.map_sha256))
        self.clients.add(box)
        self.clients_total += 1
        log.info("browser connected from %s (%d connected)", peer, len(self.clients))
        self._wake_now()  # give the newcomer the current frame without waiting for new data
        sender = asyncio.create_task(self._send_loop(ws, box))
        try:
            async for msg in ws:  # the page sends only its camera; this also waits for the close
                if isinstance(msg, str) and self.cameras is not None:
                    try:
                        self.cameras.put(box, msg)
                    except (ProtocolError, ValueError) as e:  # bad input: counted, the page stays
                        self.cameras.rejected += 1
                        log.info("rejected a message from %s: %s", peer, e)
        except ConnectionClosed:
            pass
        finally:
            self.clients.discard(box)
            sender.cancel()
            log.info("browser %s left after %d frames (%d dropped as it lagged)",
                     peer, box.taken, box.dropped)
            if self.cameras is not None:
                self.cameras.drop(box)
                log.info("camera of %s retired", peer)

    async def _send_loop(self, ws: ServerConnection, box: Mailbox) -> None:
        try:
            while True:
                msg = await box.get()
                # send() waits while the socket buffer is full (write_limit): meanwhile newer
                # frames replace the pending one in the mailbox instead of queueing.
                await ws.send(msg)
                self.frames_sent += 1
        except (ConnectionClosed, asyncio.CancelledError):
            pass

    def _wake_now(self) -> None:
        self._last_version = -1
        if self._wake is not None:
            self._wake.set()

    async def _broadcast_loop(self) -> None:
        assert self._wake is not None
        period = 1.0 / self.cfg.max_hz
        self._last_version = -1
        static_version = self.store.static_version
        seq = 0
        last = 0.0
        while True:
            await self._wake.wait()
            self._wake.clear()
            # Rate limit: at most one frame per period; data arriving meanwhile is merged.
            delay = last + period - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
                self._wake.clear()
            last = time.monotonic()
            if self.store.static_version != static_version and self.store.static is not None:
                static_version = self.store.static_version
                msg = pack_static(self.store.static, self.store.map_sha256)
                for box in self.clients:
                    if box.static_version != static_version:  # not given on connect already
                        box.static_version = static_version
                        box.put_static(msg)
            version, step, physics, alive = self.store.snapshot()
            if version == self._last_version or not self.clients:
                continue
            if step is None and not physics:
                continue
            self._last_version = version
            seq += 1
            frame = pack_frame(seq, step, physics, alive)
            self.frames_built += 1
            for box in self.clients:
                box.put_frame(frame)

    async def run(self, stop: asyncio.Event, ready: Callable[[int], None] | None = None) -> None:
        """Serve until ``stop`` is set; ``ready(port)`` is called once listening."""
        self._loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        self.store.add_listener(self._notify)
        async with serve(self._handler, self.cfg.host, self.cfg.port,
                         process_request=self._process_request,
                         compression=None,  # binary columns barely compress; save the CPU
                         max_size=1 << 16,  # the page only ever sends tiny messages
                         ping_interval=20, ping_timeout=20,
                         # On shutdown a page that does not read (busy drawing, its socket
                         # buffer full) must not hold the exit for websockets' default 10 s.
                         close_timeout=CLOSE_TIMEOUT_S) as server:
            self.port = next(iter(server.sockets)).getsockname()[1]
            log.info("viewer for run %r at %s", self.run_id, self.url)
            if ready is not None:
                ready(self.port)
            bcast = asyncio.create_task(self._broadcast_loop())
            try:
                await stop.wait()
            finally:
                bcast.cancel()


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def _query_value(query: str, name: str) -> str | None:
    from urllib.parse import parse_qs

    values = parse_qs(query, keep_blank_values=True).get(name)
    return values[0] if values else None


def _response(status: int, body: bytes, content_type: str) -> Response:
    reason = {200: "OK", 204: "No Content", 403: "Forbidden", 404: "Not Found"}.get(status, "")
    headers = Headers([("Content-Type", content_type), ("Content-Length", str(len(body))),
                       ("Cache-Control", "no-cache"), ("Connection", "close")])
    return Response(status, reason, headers, body)


# --------------------------------------------------------------------------- Zenoh side


STATIC_RETRY_S = 1.0  # [s] at least this long between static-data fetch rounds started by steps


class ZenohFeed:
    """Fills a ``LatestStore`` from a Zenoh session (callbacks keep only the newest)."""

    def __init__(self, session: Any, keys: Keys, store: LatestStore, cfg: ViewerConfig) -> None:
        self.session, self.keys, self.store, self.cfg = session, keys, store, cfg
        self._want_static = threading.Event()
        self._stop = threading.Event()
        self._last_step_idx: int | None = None
        self._step_sv: int | None = None  # ``sv`` of the newest step
        self._restarted = False  # a newer epoch: a new SUMO side under the same run id
        self._order = StepOrder()  # which steps to relay (SPEC 3.1.1); Zenoh may call from several threads
        self._order_lock = threading.Lock()
        self._fetching = False  # the worker is in a fetch round (it asks until the versions agree)
        self._network_hash = ""  # lanes + junctions of the held static data (the map depends on them only)
        self._last_static_ask = 0.0
        self._handles: list[Any] = []
        self._thread = threading.Thread(target=self._static_worker, name="viewer-static", daemon=True)

    def start(self) -> "ZenohFeed":
        s, k = self.session, self.keys
        self._handles = [
            s.declare_subscriber(k.step, self._on_step),
            s.declare_subscriber(k.physics_state_all, self._on_physics),
            s.liveliness().declare_subscriber(k.sumo_alive, self._on_sumo_token, history=True),
            s.liveliness().declare_subscriber(k.physics_alive_all, self._on_physics_token, history=True),
        ]
        self._want_static.set()
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._want_static.set()
        for h in self._handles:
            try:
                h.undeclare()
            except Exception:  # session may already be closing
                pass
        self._thread.join(timeout=self.cfg.static_timeout_s + 1.0)

    # Zenoh callbacks: keep them to a reference swap, never block Zenoh's thread.
    # Steps and physics states are relayed to the pages as they came, never decoded here: each
    # page decodes them with its own msgpack reader.
    def _on_step(self, sample: Any) -> None:
        payload = sample.payload.to_bytes()
        head = peek(payload, ("step", "sv", "epoch"))  # the first bytes only: the agents stay undecoded
        sv, idx = int(head.get("sv", 0)), head.get("step")
        if idx is not None:
            with self._order_lock:
                verdict = self._order.judge(int(head.get("epoch", 0)), int(idx))
            if not verdict.accepted:  # a replay, a re-send or an absurd jump: the pages never see it
                self.store.steps_refused += verdict is not Verdict.DUPLICATE
                return
            if verdict is Verdict.RESTART:
                self._restarted = True  # its static versions start again, its network may differ
        self.store.put_step(payload)
        self._last_step_idx = idx
        self._step_sv = sv
        since = time.monotonic() - self._last_static_ask
        if self.store.static is None:
            if since > 2.0:
                self._ask_static()  # steps flow but we missed the static data: ask again
        elif (sv != self.store.static_sv or self._restarted) and not self._fetching and since > STATIC_RETRY_S:
            if self._restarted:
                log.info("step index back to %s (a SUMO side restarted under this run id): fetching the "
                         "static data", idx)
            else:  # SPEC 3.2: the step refers to other vType / tls-link tables than we hold
                log.info("step %s refers to static version %d (held: %s): fetching the static data", idx, sv,
                         self.store.static_sv)
            self._ask_static()

    def _on_physics(self, sample: Any) -> None:
        inst = Keys.instance_of(str(sample.key_expr))
        if inst:
            self.store.put_physics(inst, sample.payload.to_bytes())

    def _on_sumo_token(self, sample: Any) -> None:
        import zenoh

        alive = sample.kind == zenoh.SampleKind.PUT
        self.store.set_sumo_alive(alive)
        self._last_step_idx = None  # a new SUMO side's steps start at 0: its token (here) fetches already
        if alive:
            log.info("SUMO side is up: fetching static data")
            self._ask_static()
        else:
            log.info("SUMO side left")

    def _on_physics_token(self, sample: Any) -> None:
        import zenoh

        inst = Keys.instance_of(str(sample.key_expr))
        if not inst:
            return
        if sample.kind == zenoh.SampleKind.DELETE:
            log.info("physics instance %r left", inst)
            self.store.drop_physics(inst)
        else:
            self.store.revive_physics(inst)

    def _ask_static(self) -> None:
        self._last_static_ask = time.monotonic()
        self._want_static.set()

    def _query_static(self) -> tuple[bytes, StaticData] | None:
        self.store.static_queries += 1
        for reply in self.session.get(self.keys.static, timeout=self.cfg.static_timeout_s):
            if reply.ok is None:
                continue
            data = reply.ok.payload.to_bytes()
            try:  # validate once here so a broken reply is reported in our log, not the page's
                # static tables are not agents: the default limits, bounded while msgpack parses
                msg = decode_as(data, StaticData, DEFAULT_LIMITS)
            except ProtocolError as e:
                log.warning("ignoring invalid static data: %s", e)
                continue
            return data, msg
        return None

    @staticmethod
    def _network_of(st: StaticData) -> str:
        """A hash of the network (lanes, junctions): a new static version with the same network
        (a vType or tls-link change) needs no new map."""
        h = hashlib.sha256()
        for part in (st.lanes.ids, st.junctions.ids):
            h.update("\0".join(part).encode())
            h.update(b"\1")
        for arr in (st.lanes.width, st.lanes.shape_offsets, st.lanes.shape_xy, st.junctions.shape_offsets,
                    st.junctions.shape_xy):
            h.update(np.ascontiguousarray(arr).data)
        h.update(repr((st.net_offset, st.projection, st.bounds)).encode())
        return h.hexdigest()

    def _query_map(self) -> tuple[bytes, str] | None:
        """The SUMO side's GLB (SPEC 9), asking with the hash we hold so it is sent once."""
        have = self.store.map_sha256
        key = self.keys.sumo_map + (f"?sha256={have}" if have else "")
        for reply in self.session.get(key, timeout=self.cfg.static_timeout_s):
            if reply.ok is None:
                continue
            data = reply.ok.payload.to_bytes()
            if len(data) > DEFAULT_LIMITS.max_bytes:
                log.warning("ignoring a map reply of %d bytes (at most %d)", len(data), DEFAULT_LIMITS.max_bytes)
                continue
            try:  # a map is static data: the default limits, applied while msgpack parses
                doc = msgpack.unpackb(data, raw=False, **DEFAULT_LIMITS.unpack_kwargs())
            except Exception as e:  # msgpack raises a zoo of types for corrupt or oversized input
                log.warning("ignoring an undecodable map reply: %s", e)
                continue
            if not isinstance(doc, dict) or doc.get("kind") != "map":
                continue
            if doc.get("glb") is None and doc.get("sha256") == have and self.store.map_glb is not None:
                return self.store.map_glb, have
            glb = doc.get("glb")
            if isinstance(glb, bytes) and hashlib.sha256(glb).hexdigest() == doc.get("sha256"):
                return glb, doc["sha256"]
        return None

    def _fetch_map(self, static: bytes) -> None:
        """The map for this static data: from the SUMO side, else built here from the data."""
        try:
            got = self._query_map()
        except Exception as e:  # zenoh raises on a closing session; a SUMO side without maps
            log.debug("map query failed: %s", e)
            got = None
        if got is not None:
            if got[1] != self.store.map_sha256:
                log.info("map from the SUMO side: %d KiB", len(got[0]) // 1024)
            self.store.put_map(got[0], got[1], "sumo")
            return
        try:
            from sumo_side.mapmesh import build_map, geometry_from_static

            mesh = build_map(geometry_from_static(decode_as(static, StaticData, DEFAULT_LIMITS)))
        except Exception as e:  # a page without a map still shows the agents
            log.warning("could not build a map from the static data: %s", e)
            return
        log.info("map built from the static data: %d KiB (the SUMO side serves none)", len(mesh.glb) // 1024)
        self.store.put_map(mesh.glb, mesh.sha256, "static")

    def _static_worker(self) -> None:
        # The only place that queries: one query outstanding at most, however often steps ask.
        while not self._stop.is_set():
            if not self._want_static.wait(timeout=1.0):
                continue
            self._want_static.clear()
            self._fetching = True
            try:
                self._fetch_round()
            finally:
                self._fetching = False
                self._last_static_ask = time.monotonic()  # the next round at least STATIC_RETRY_S later

    def _fetch_round(self) -> None:
        """Query until static data arrives whose ``sv`` is the newest step's (or newer), at most
        ``static_attempts`` times with a growing pause."""
        self._restarted = False
        got = False
        for attempt in range(1, self.cfg.static_attempts + 1):
            if self._stop.is_set():
                return
            try:
                reply = self._query_static()
            except Exception as e:  # zenoh raises on a closing session
                log.debug("static query failed: %s", e)
                reply = None
            if reply is not None:
                got = True
                data, msg = reply
                fresh = data != self.store.static
                if fresh:
                    network = self._network_of(msg)
                    if network != self._network_hash or self.store.map_glb is None:
                        self._fetch_map(data)
                        self._network_hash = network
                    self.store.put_static(data)
                    log.info("static data version %d received (%d bytes, %d vTypes, attempt %d)", msg.version,
                             len(data), len(msg.vtypes), attempt)
                elif self.store.map_glb is None:
                    self._fetch_map(data)
                want = self._step_sv
                if want is None or msg.version >= want:
                    return
                # the SUMO side re-encodes its static data at most once a second: ask again shortly
                log.debug("static data version %d, the steps' is %d: asking again", msg.version, want)
            if self._stop.wait(min(0.2 * attempt, 1.0)):
                return
        if got:
            log.warning("static data on %s still at version %s after %d queries, the steps' is %s; asking "
                        "again on a later step", self.keys.static, self.store.static_sv, self.cfg.static_attempts,
                        self._step_sv)
        else:
            log.warning("no static data on %s after %d queries; drawing agents without the "
                        "network until the SUMO side (re)appears", self.keys.static,
                        self.cfg.static_attempts)


# --------------------------------------------------------------------------- entry point


def load_config(args: Any) -> tuple[Any, ViewerConfig]:
    """Common config + ``[viewer]`` table, with the command-line overrides applied."""
    from runtime.config import CommonConfig, apply_cli, load_common, replace, section

    if getattr(args, "config", None):
        common, data, base = load_common(args.config)
        vcfg = section(data, "viewer", ViewerConfig, base, str(args.config))
    else:
        common, vcfg = CommonConfig(), ViewerConfig()
    common = apply_cli(common, args)
    changes = {k: getattr(args, a) for k, a in (("host", "host"), ("port", "port"), ("max_hz", "max_hz"))
               if getattr(args, a, None) is not None}
    if changes:
        vcfg = replace(vcfg, **changes)
        vcfg.validate()
    return common, vcfg


def cli_main(args: Any) -> int:
    from runtime.transport import open_session

    common, vcfg = load_config(args)
    if not logging.getLogger().isEnabledFor(logging.DEBUG):
        logging.getLogger("websockets").setLevel(logging.WARNING)  # one line per page GET is noise
    try:
        if not ipaddress.ip_address(vcfg.host).is_loopback:
            log.warning("viewer bound to %s: it is reachable from other machines", vcfg.host)
    except ValueError:
        pass
    keys = Keys(common.zenoh.root, common.run.id)
    store = LatestStore(vcfg.stale_s)
    server = ViewerServer(vcfg, store, run=common.run.id, root=common.zenoh.root)

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        # The one line of output: where to look (the token makes the data private to this URL).
        await server.run(stop, ready=lambda port: print(f"sumoco view: open {server.url}", flush=True))

    from runtime.hotpath import start_heap_trimmer

    trimmer = start_heap_trimmer()
    with open_session(common.zenoh) as session:
        feed = ZenohFeed(session, keys, store, vcfg).start()
        server.cameras = CameraRelay(session, keys)
        try:
            asyncio.run(main())
        finally:
            feed.stop()
            if trimmer is not None:
                trimmer.set()
    log.info("viewer stopped (%d frames sent)", server.frames_sent)
    return 0
