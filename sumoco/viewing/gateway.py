"""``sumoco gateway``: a run's Zenoh keys over one WebSocket, for engines without a Zenoh binding.

Unity has no official C# Zenoh binding and a browser would need a router plugin; both
speak WebSocket. The gateway relays the **same msgpack payloads** the daemons publish,
each tagged with its key, and takes ego poses upstream. Wire format (SPEC.md, "WebSocket
gateway"):

- binary frame = ``u16`` little-endian key length, the key (UTF-8), the payload bytes
  (unchanged msgpack, SPEC 3.x), in both directions;
- text frame = one JSON object: requests ``{"op": "subscribe" | "unsubscribe", "key":
  pattern}``, ``{"op": "static"}``; answers ``{"op": "hello" | "subscribed" |
  "unsubscribed" | "error", ...}``, ``{"op": "get", "key": "sumo/map", "parameters": ""}``
  for any queryable of the run. Patterns are Zenoh key expressions relative to the
  run (``sumo/step``, ``physics/*/state``, ``**``).

Trust: listens on 127.0.0.1 by default; the handshake must carry the per-run token
(``?token=``, printed at start or taken from ``SUMOCO_GATEWAY_TOKEN``), a ``Host`` that
names this server (against DNS rebinding) and, when a browser sends one, an ``Origin``
from the allowed list (loopback pages by default). Every client has a bounded outbox
that drops its oldest frame when the client lags (counted); upstream frames are size-
bounded, decoded (with tight limits) before they are forwarded, and only ``ego/<id>`` and
``viewer/camera`` (the client's camera, published under an id the gateway assigns) are
accepted. A client drives at most ``ego_per_client`` ego ids and all clients together at
most ``ego_total``; a pose for one more is refused with an error to that client (counted
in ``ego_refused``), and a client's ego ids are freed when it leaves. An ego pose whose
``id`` differs from its key, or an id the SUMO side does not take (``[sumo] ego_id``), is
refused at the gateway with an error to the client and uses no slot. Downstream frames
(subscriptions, query answers) are relayed as they came, never decoded here; a sample that
matches several of a client's subscriptions reaches it once. Liveliness tokens matching a
subscription arrive as text frames ``{"op": "alive", "key": ..., "alive": true|false}``
(SPEC 10), so a client sees a daemon leave and come back.
"""

from __future__ import annotations

import asyncio
import collections
import hmac
import json
import logging
import secrets
import struct
import threading
import time
from dataclasses import dataclass, field
from urllib.parse import parse_qs, urlsplit

import zenoh
from websockets.asyncio.server import ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from protocol.codec import DecodeLimits, decode
from protocol.errors import ConfigError, ProtocolError
from protocol.keys import Keys, check_chunk
from protocol.messages import CameraPose, EgoPose
from sumoco.viewing.camera import CameraPublisher

log = logging.getLogger(__name__)

PATH = "/ws"
MAX_UPSTREAM_BYTES = 64 * 1024  # [B] an EgoPose is ~100 B; anything near this is not one
#: Upstream frames carry one ego pose or one camera, never an agent table: the tightest
#: limits while msgpack parses, whatever the run's ``[run] max_agents``.
UPSTREAM_LIMITS = DecodeLimits(max_agents=1, max_static_rows=16, max_points=1, max_bytes=MAX_UPSTREAM_BYTES)
_KEY_LEN = struct.Struct("<H")
CLOSE_TOO_BIG = 1009  # WebSocket close code "message too big" (RFC 6455 7.4.1)
#: samples remembered per client to deliver one that matches two of its subscriptions once
DEDUP_WINDOW = 1024
_LOOPBACK = ("127.0.0.1", "localhost", "[::1]", "::1")


#: The ``<role>`` chunk of the cameras the gateway relays (SPEC 3.7): its certificate's role in
#: the secure profile (the access control lets it put cameras under ``viewer/gateway/`` only),
#: ``viewer`` without it.
CAMERA_ROLE = "viewer"
SECURE_CAMERA_ROLE = "gateway"


def pack_frame(key: str, payload: bytes) -> bytes:
    """One binary frame: u16 LE key length, key, payload."""
    k = key.encode()
    return _KEY_LEN.pack(len(k)) + k + payload


def unpack_frame(frame: bytes) -> tuple[str, bytes]:
    """Inverse of ``pack_frame``; ``ProtocolError`` when the frame is too short or the key is not UTF-8."""
    if len(frame) < 2:
        raise ProtocolError(f"expected at least 2 bytes (key length), got {len(frame)}", "gateway frame")
    (n,) = _KEY_LEN.unpack_from(frame)
    if len(frame) < 2 + n:
        raise ProtocolError(f"key length {n} exceeds the frame ({len(frame)} bytes)", "gateway frame")
    try:
        key = frame[2:2 + n].decode()
    except UnicodeDecodeError:
        raise ProtocolError("key is not UTF-8", "gateway frame") from None
    return key, frame[2 + n:]


@dataclass(frozen=True)
class GatewayConfig:
    host: str = "127.0.0.1"  # loopback by default; another address exposes the run to that network
    port: int = 8766  # [TCP port] 0 = any free port
    token: str = ""  # per-run token; empty = a random one at start
    allow_origins: tuple[str, ...] = ()  # extra allowed Origin values (scheme://host:port)
    allow_hosts: tuple[str, ...] = ()  # extra allowed Host header names (besides loopback)
    outbox: int = 256  # [frames] per client; full: drop the oldest (counted)
    ego_per_client: int = 4  # [ego ids] one client may drive at once; a pose for one more is refused (counted)
    ego_total: int = 32  # [ego ids] all clients together; a pose for one more is refused (counted)
    subscriptions_per_client: int = 64  # [subscriptions] one client may hold; one more is refused (counted)
    ego_ids: tuple[str, ...] = ("*",)  # ego ids the SUMO side takes ([sumo] ego_id); "*" = any

    def __post_init__(self) -> None:
        if self.outbox < 1 or self.ego_per_client < 1 or self.ego_total < 1 or self.subscriptions_per_client < 1:
            raise ConfigError(f"gateway: outbox, ego_per_client, ego_total and subscriptions_per_client must be "
                              f">= 1, got {self.outbox}, {self.ego_per_client}, {self.ego_total} and "
                              f"{self.subscriptions_per_client}")


class Outbox:
    """A client's bounded frame queue: drops the oldest frame when full (counted)."""

    def __init__(self, maxlen: int) -> None:
        self._q: collections.deque = collections.deque(maxlen=maxlen)
        self._ev = asyncio.Event()
        self.dropped = 0
        self.sent = 0

    def put(self, frame: bytes | str) -> None:
        if len(self._q) == self._q.maxlen:
            self.dropped += 1
        self._q.append(frame)
        self._ev.set()

    async def get(self) -> bytes | str:
        while not self._q:
            self._ev.clear()
            await self._ev.wait()
        return self._q.popleft()


@dataclass(eq=False)  # identity: clients live in a set
class _Client:
    ws: ServerConnection
    box: Outbox
    subs: dict[str, object] = field(default_factory=dict)
    alive_subs: dict[str, object] = field(default_factory=dict)
    seen: collections.deque = field(default_factory=lambda: collections.deque(maxlen=DEDUP_WINDOW))
    seen_set: set = field(default_factory=set)
    upstream: int = 0
    rejected: int = 0
    camera_id: str = field(default_factory=lambda: f"gw-{secrets.token_hex(4)}")
    camera: CameraPublisher | None = None  # declared with the client's first camera
    egos: dict[str, zenoh.Publisher] = field(default_factory=dict)  # full ego key -> its publisher


class Gateway:
    """WebSocket server relaying one run's keys; ``run`` serves until ``stop`` is set."""

    def __init__(self, session: zenoh.Session, keys: Keys, cfg: GatewayConfig, camera_role: str = CAMERA_ROLE) -> None:
        """``camera_role``: the role chunk of relayed cameras' keys (``SECURE_CAMERA_ROLE`` when
        the session presents the gateway certificate)."""
        self.session, self.keys, self.cfg = session, keys, cfg
        self.camera_role = check_chunk(camera_role, "camera role")
        self.token = cfg.token or secrets.token_urlsafe(24)
        self.clients: set[_Client] = set()
        self.port = cfg.port
        self._loop: asyncio.AbstractEventLoop | None = None
        self.refused = 0
        self.relayed = 0
        self.ego_forwarded = 0
        self.cameras_forwarded = 0
        self.ego_refused = 0  # poses for an ego id beyond ego_per_client or ego_total
        self.rejected = 0  # upstream frames and requests refused, over every client that ever connected
        self.duplicates = 0  # samples that matched two subscriptions of one client, delivered once
        self.oversized = 0  # connections closed for a frame over MAX_UPSTREAM_BYTES (also in ``rejected``)
        self._lock = threading.Lock()

    # --- handshake checks -------------------------------------------------------------
    def _hosts(self) -> set[str]:
        names = {*_LOOPBACK, *self.cfg.allow_hosts}
        if self.cfg.host not in ("0.0.0.0", "::"):
            names.add(self.cfg.host)
        return {f"{h}:{self.port}" for h in names} | set(self.cfg.allow_hosts)

    def _origin_ok(self, origin: str) -> bool:
        if origin in self.cfg.allow_origins:
            return True
        u = urlsplit(origin)
        return u.scheme in ("http", "https") and u.hostname in ("127.0.0.1", "localhost", "::1")

    def _process_request(self, connection: ServerConnection, request: Request) -> Response | None:
        url = urlsplit(request.path)
        reason = None
        if url.path not in (PATH, "/status"):
            reason = (404, f"not found: {url.path} (the WebSocket is at {PATH})")
        elif request.headers.get("Host", "") not in self._hosts():
            reason = (403, f"Host {request.headers.get('Host', '')!r} is not this gateway")
        elif "Origin" in request.headers and not self._origin_ok(request.headers["Origin"]):
            reason = (403, f"Origin {request.headers['Origin']!r} is not allowed (--allow-origin)")
        else:
            token = parse_qs(url.query).get("token", [""])[0]
            if not hmac.compare_digest(token.encode(), self.token.encode()):
                reason = (401, "missing or wrong token (?token=...)")
        if reason is None:
            if url.path == "/status":  # the same Host and token as the WebSocket
                return _response(200, json.dumps(self.status()).encode(), "application/json")
            return None
        self.refused += 1
        log.warning("refused a WebSocket from %s: %s", connection.remote_address, reason[1])
        return _response(reason[0], (reason[1] + "\n").encode(), "text/plain; charset=utf-8")

    # --- relaying ----------------------------------------------------------------------
    def _pattern(self, rel: str) -> str:
        rel = str(rel).strip("/")
        if not rel or rel.startswith(self.keys.base + "/"):
            rel = rel[len(self.keys.base) + 1:] if rel else ""
        if not rel:
            raise ProtocolError("expected a key pattern relative to the run, e.g. 'sumo/step'", "key")
        full = f"{self.keys.base}/{rel}"
        zenoh.KeyExpr(full)  # raises on an invalid key expression
        return full

    def _on_sample(self, client: _Client, sample: zenoh.Sample) -> None:
        # Zenoh's thread: frame it and hand it to the event loop; never wait here. The payload
        # is relayed as it came, not decoded: the client decodes it with its own limits.
        frame = pack_frame(str(sample.key_expr), sample.payload.to_bytes())
        ts = sample.timestamp
        ident = None if ts is None else str(ts)  # publisher id + time: one sample, whichever subscription
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self._deliver, client, frame, ident)

    def _deliver(self, client: _Client, frame: bytes | str, ident: str | None = None) -> None:
        if client not in self.clients:
            return
        if ident is not None:
            if ident in client.seen_set:
                self.duplicates += 1
                return
            if len(client.seen) == client.seen.maxlen:
                client.seen_set.discard(client.seen[0])
            client.seen.append(ident)
            client.seen_set.add(ident)
        client.box.put(frame)
        self.relayed += 1

    def _on_alive(self, client: _Client, sample: zenoh.Sample) -> None:
        # Zenoh's thread: a liveliness token came (PUT) or went (DELETE).
        text = json.dumps({"op": "alive", "key": str(sample.key_expr),
                           "alive": sample.kind == zenoh.SampleKind.PUT})
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self._deliver, client, text, None)

    async def _get(self, client: _Client, key: str, parameters: str = "") -> None:
        """One Zenoh query; the first answer goes to the client as a binary frame (relayed
        as it came, not decoded here)."""
        def fetch() -> tuple[list[tuple[str, bytes]], list[str]]:
            ok, err = [], []
            t0 = time.monotonic()
            sel = f"{key}?{parameters}" if parameters else key
            for r in self.session.get(sel, timeout=5.0):
                if r.ok is not None:
                    ok.append((str(r.ok.key_expr), r.ok.payload.to_bytes()))
                else:
                    err.append(r.err.payload.to_string())
            if not ok and not err:
                waited = time.monotonic() - t0
                err.append("no answer within 5 s" if waited >= 4.5 else
                           f"nothing answers this key (no queryable found after {waited:.2f} s: is the SUMO side up?)")
            return ok, err

        replies, errors = await asyncio.to_thread(fetch)
        if not replies:
            why = "; ".join(errors)
            client.box.put(json.dumps({"op": "error", "key": key, "error": f"{key}: {why}"}))
        for k, data in replies[:1]:
            client.box.put(pack_frame(k, data))

    def _upstream(self, client: _Client, frame: bytes) -> None:
        key, payload = unpack_frame(frame)
        rel = key[len(self.keys.base) + 1:] if key.startswith(self.keys.base + "/") else key
        parts = rel.split("/")
        if parts == ["viewer", "camera"]:
            return self._camera(client, payload)
        if len(parts) != 2 or parts[0] != "ego":
            raise ProtocolError(f"expected 'ego/<id>' or 'viewer/camera' (only ego poses and cameras go "
                                f"upstream), got {key!r}", "key")
        ego_id = check_chunk(parts[1], "ego id")
        msg = decode(payload, UPSTREAM_LIMITS)
        if not isinstance(msg, EgoPose):
            raise ProtocolError(f"expected an ego pose message, got {type(msg).__name__}", key)
        if msg.id != ego_id:  # SPEC 3.5: the SUMO side would drop it; say so here
            raise ProtocolError(f"ego pose id {msg.id!r} differs from its key's id {ego_id!r} (they must be equal)",
                                "id")
        ids = self.cfg.ego_ids
        if "*" not in ids and ego_id not in ids:
            raise ProtocolError(f"the SUMO side takes ego ids {', '.join(map(repr, ids))} only ([sumo] ego_id), "
                                f"got {ego_id!r}", "id")
        full = self.keys.ego(ego_id)
        pub = client.egos.get(full)
        if pub is None:
            self._admit_ego(client, ego_id)
            pub = client.egos[full] = self.session.declare_publisher(full)
        pub.put(payload)
        client.upstream += 1
        self.ego_forwarded += 1

    def _admit_ego(self, client: _Client, ego_id: str) -> None:
        """A new ego id for ``client``: within ``ego_per_client`` and ``ego_total``, else
        ``ProtocolError`` (the client is told, the refusal counted)."""
        total = sum(len(c.egos) for c in self.clients)
        if len(client.egos) >= self.cfg.ego_per_client:
            why = (f"this connection drives {len(client.egos)} ego ids already, the most the gateway "
                   f"allows per client ({self.cfg.ego_per_client})")
        elif total >= self.cfg.ego_total:
            why = f"the gateway's clients drive {total} ego ids already, the most it allows ({self.cfg.ego_total})"
        else:
            return
        self.ego_refused += 1
        raise ProtocolError(f"refused: {why}; poses for the ids already driven are still forwarded",
                            f"ego/{ego_id}")

    def _release(self, client: _Client) -> None:
        """Undeclare what a leaving client held: its ego publishers (freeing their ids) and its camera."""
        pubs, client.egos = list(client.egos.values()), {}
        for pub in pubs:
            try:
                pub.undeclare()
            except zenoh.ZError:  # the session is closing
                pass
        if client.camera is not None:  # its token goes: the physics side drops the camera
            client.camera.close()
            client.camera = None

    def _camera(self, client: _Client, payload: bytes) -> None:
        """The client's camera (SPEC 3.7) under an id of the gateway's choosing, with a
        liveliness token for as long as the client is connected."""
        msg = decode(payload, UPSTREAM_LIMITS)
        if not isinstance(msg, CameraPose):
            raise ProtocolError(f"expected a camera message, got {type(msg).__name__}", "viewer/camera")
        if client.camera is None:
            client.camera = CameraPublisher(self.session, self.keys, client.camera_id, role=self.camera_role)
        client.camera.put(msg.x, msg.y, msg.time)
        client.upstream += 1
        self.cameras_forwarded += 1

    def _request(self, client: _Client, text: str) -> None:
        try:
            req = json.loads(text)
        except json.JSONDecodeError as e:
            raise ProtocolError(f"expected a JSON object ({e.msg})", "request") from None
        if not isinstance(req, dict):
            raise ProtocolError("expected a JSON object", "request")
        op = req.get("op")
        if op == "subscribe":
            full = self._pattern(req.get("key", ""))
            if full not in client.subs:
                if len(client.subs) >= self.cfg.subscriptions_per_client:
                    raise ProtocolError(f"refused: this connection holds {len(client.subs)} subscriptions, the most "
                                        f"the gateway allows per client ({self.cfg.subscriptions_per_client})", "key")
                client.subs[full] = self.session.declare_subscriber(
                    full, lambda s, c=client: self._on_sample(c, s))
                client.alive_subs[full] = self.session.liveliness().declare_subscriber(
                    full, lambda s, c=client: self._on_alive(c, s), history=True)
            client.box.put(json.dumps({"op": "subscribed", "key": full}))
        elif op == "unsubscribe":
            full = self._pattern(req.get("key", ""))
            for held in (client.subs, client.alive_subs):
                sub = held.pop(full, None)
                if sub is not None:
                    sub.undeclare()
            client.box.put(json.dumps({"op": "unsubscribed", "key": full}))
        elif op == "static":
            asyncio.get_running_loop().create_task(self._get(client, self.keys.static))
        elif op == "get":
            full = self._pattern(req.get("key", ""))
            params = str(req.get("parameters", ""))
            asyncio.get_running_loop().create_task(self._get(client, full, params))
        else:
            raise ProtocolError(f"expected op 'subscribe', 'unsubscribe', 'static' or 'get', got {op!r}", "op")

    async def _handler(self, ws: ServerConnection) -> None:
        client = _Client(ws, Outbox(self.cfg.outbox))
        self.clients.add(client)
        client.box.put(json.dumps({"op": "hello", "root": self.keys.root, "run": self.keys.run,
                                   "base": self.keys.base, "format": "u16le key length, key, msgpack payload"}))
        sender = asyncio.create_task(self._send_loop(client))
        log.info("client connected from %s (%d connected)", ws.remote_address, len(self.clients))
        try:
            async for msg in ws:
                try:
                    if isinstance(msg, str):
                        self._request(client, msg)
                    else:
                        self._upstream(client, msg)
                except (ProtocolError, zenoh.ZError, ValueError) as e:
                    # Bad input: say what was wrong, count it, keep the connection.
                    client.rejected += 1
                    self.rejected += 1
                    client.box.put(json.dumps({"op": "error", "error": str(e)}))
                    log.info("rejected a message from %s: %s", ws.remote_address, e)
        except ConnectionClosed:
            pass
        finally:
            if ws.close_code == CLOSE_TOO_BIG:  # a frame over MAX_UPSTREAM_BYTES: closed unread (SPEC 10)
                client.rejected += 1
                self.rejected += 1
                self.oversized += 1
            self.clients.discard(client)
            sender.cancel()
            for sub in (*client.subs.values(), *client.alive_subs.values()):
                sub.undeclare()
            self._release(client)
            log.info("client %s left: %d frames sent, %d dropped, %d ego poses, %d rejected",
                     ws.remote_address, client.box.sent, client.box.dropped, client.upstream, client.rejected)

    async def _send_loop(self, client: _Client) -> None:
        try:
            while True:
                frame = await client.box.get()
                await client.ws.send(frame)
                client.box.sent += 1
        except (ConnectionClosed, asyncio.CancelledError):
            pass

    def status(self) -> dict:
        return {"run": self.keys.run, "clients": len(self.clients), "relayed": self.relayed,
                "dropped": sum(c.box.dropped for c in self.clients), "refused": self.refused,
                "ego_forwarded": self.ego_forwarded, "cameras_forwarded": self.cameras_forwarded,
                "egos": sum(len(c.egos) for c in self.clients), "ego_refused": self.ego_refused,
                "rejected": self.rejected, "duplicates": self.duplicates, "oversized": self.oversized}

    def url(self) -> str:
        host = f"[{self.cfg.host}]" if ":" in self.cfg.host else self.cfg.host
        return f"ws://{host}:{self.port}{PATH}?token={self.token}"

    async def run(self, stop: asyncio.Event, ready=None) -> None:
        self._loop = asyncio.get_running_loop()
        async with serve(self._handler, self.cfg.host, self.cfg.port, process_request=self._process_request,
                         compression=None, max_size=MAX_UPSTREAM_BYTES, max_queue=16,
                         ping_interval=20, ping_timeout=20) as server:
            self.port = next(iter(server.sockets)).getsockname()[1]
            if ready is not None:
                ready(self)
            await stop.wait()
        for client in list(self.clients):  # handlers normally release their own on the way out
            self._release(client)


def _response(status: int, body: bytes, ctype: str) -> Response:
    reason = {200: "OK", 401: "Unauthorized", 403: "Forbidden", 404: "Not Found"}.get(status, "")
    return Response(status, reason, Headers([("Content-Type", ctype), ("Content-Length", str(len(body))),
                                             ("Cache-Control", "no-store")]), body)


def cli_main(args) -> int:
    """``sumoco gateway``: serve until Ctrl-C; prints the client URL (with the token) as JSON."""
    import os
    import signal

    from runtime.config import CommonConfig, apply_cli, load_common
    from runtime.transport import open_session

    common = load_common(args.config)[0] if args.config else CommonConfig()
    common = apply_cli(common, args)
    token = os.environ.get("SUMOCO_GATEWAY_TOKEN", "")
    if token and len(token) < 16:
        raise ConfigError("SUMOCO_GATEWAY_TOKEN must be at least 16 characters")
    ego_ids: tuple[str, ...] = ("*",)
    if args.config:  # the SUMO side's [sumo] ego_id: refuse other ids here, where the client hears it
        from runtime.config import load_toml
        from sumo_side.config import sumo_config_from

        data, base = load_toml(args.config)
        ego_ids = (sumo_config_from(data, base, str(args.config)).ego_id,)
    cfg = GatewayConfig(host=args.host or "127.0.0.1", port=8766 if args.port is None else args.port, token=token,
                        allow_origins=tuple(args.allow_origin or ()), allow_hosts=tuple(args.allow_host or ()),
                        ego_ids=ego_ids)
    keys = Keys(common.zenoh.root, common.run.id)
    logging.getLogger("websockets").setLevel(logging.WARNING)

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)

        def ready(gw: Gateway) -> None:
            # The token file is complete (written aside, then renamed) before the URL is announced,
            # so whoever waits for the URL can read the token at once.
            if args.token_file:
                tmp = f"{args.token_file}.tmp{os.getpid()}"
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
                with os.fdopen(fd, "w") as f:
                    f.write(gw.token + "\n")
                os.replace(tmp, args.token_file)
            print(json.dumps({"url": gw.url(), "run": keys.run}), flush=True)

        limit = getattr(args, "duration", None)
        if limit:
            loop.call_later(float(limit), stop.set)
        await gw.run(stop, ready)

    with open_session(common.zenoh, role="gateway") as session:
        gw = Gateway(session, keys, cfg, SECURE_CAMERA_ROLE if common.zenoh.security.enabled else CAMERA_ROLE)
        t0 = time.monotonic()
        asyncio.run(main())
        log.info("gateway stopped after %.0f s: %s", time.monotonic() - t0, gw.status())
    return 0
