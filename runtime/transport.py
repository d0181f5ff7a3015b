"""Zenoh session set-up shared by every sumoco process.

Embedded default: peer mode, multicast scouting off, explicit loopback endpoints, so two
daemons on one machine find each other without a router and nothing leaves 127.0.0.1.
Scale-out: mode "client" with ``connect`` pointing at routers (``sumoco router`` or zenohd).

Secure profile (``[zenoh.security] certs = DIR``, see ``configs/secure.toml``): every link
is TLS with mutual authentication (each process presents the certificate of its role,
made by ``sumoco certs init DIR``), ``tcp/`` endpoints are used as ``tls/`` ones, and an
access-control policy by certificate common name decides what each role may send:
``access_control`` below. Every process loads the same policy and applies it to what it
receives, so a refused message never reaches the daemon it was aimed at.
"""

from __future__ import annotations

import json
import os
import logging
import socket
import threading
import time
from pathlib import Path

import zenoh

from protocol.errors import ConfigError, SumocoError
from runtime.config import SecurityConfig, ZenohConfig

log = logging.getLogger(__name__)

#: Roles with one certificate each (CN = role); renderers have one per ego id. The gateway
#: relays engines that have no Zenoh binding; it checks its WebSocket clients' token itself.
#: ``router`` is ``sumoco router``: access control applies per link by the CN of the peer
#: at its other end, so what a router forwards carries the router's CN, not its sender's.
ROLES = ("sumo", "physics", "viewer", "gateway", "router")

#: Every message kind Zenoh's access control knows (Zenoh >= 1.0 names).
_ALL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
                 "liveliness_token", "declare_liveliness_subscriber", "liveliness_query")


def renderer_role(ego_id: str) -> str:
    """Certificate common name of the renderer that drives ego ``ego_id``."""
    return f"renderer-{ego_id}"


def access_control(root: str, sec: SecurityConfig, routed: bool = True) -> dict:
    """The role policy as Zenoh's ``access_control`` table (deny unless allowed).

    Ingress rules say what a peer of a role may send us: every role may subscribe and
    query; only ``sumo`` may put steps, serve static data, the map and status and hold the SUMO
    liveliness token; only ``physics`` may put states, acks and coupling feedback and hold physics tokens;
    ``renderer-<id>`` may put ego poses on ``ego/<id>`` alone; ``gateway`` may put ego poses
    for any id (it relays engines that hold its token, SPEC 10); ``viewer``, ``gateway`` and every
    ``renderer-<id>`` may put cameras and hold camera tokens under their own role only
    (``viewer/<role>/*/camera``, ``viewer/<role>/*/alive``, SPEC 3.7).
    ``router`` may send everything under the root: a router applies this same policy to
    what its own clients send it (by their CN) and then forwards under its own CN, so the
    check happens at the first hop; router-to-router links of a mesh pass it on as it is.
    Only where routers are part of the run (``routed``: a router or a client session, or
    ``[zenoh.security] routers = true``): a peer-to-peer run grants a router certificate
    nothing but reading, so a stolen or stray one cannot originate steps there.
    Egress is open to every authenticated role: anyone with a certificate may read.
    """
    r = root

    def rule(rid: str, flow: str, messages, keys) -> dict:
        return {"id": rid, "permission": "allow", "flows": [flow], "messages": list(messages),
                "key_exprs": list(keys)}

    rules = [
        rule("receive", "egress", _ALL_MESSAGES, [f"{r}/**"]),
        rule("read", "ingress", ("declare_subscriber", "declare_liveliness_subscriber", "liveliness_query",
                                 "query"), [f"{r}/**"]),
        rule("sumo-put", "ingress", ("put", "delete"), [f"{r}/*/sumo/step"]),
        rule("sumo-serve", "ingress", ("declare_queryable", "reply"),
             [f"{r}/*/sumo/static", f"{r}/*/sumo/map", f"{r}/*/sumo/status"]),
        rule("sumo-token", "ingress", ("liveliness_token",), [f"{r}/*/sumo/alive"]),
        rule("physics-put", "ingress", ("put", "delete"),
             [f"{r}/*/physics/*/state", f"{r}/*/physics/*/ack", f"{r}/*/physics/*/feedback"]),
        rule("physics-token", "ingress", ("liveliness_token",), [f"{r}/*/physics/*/alive"]),
        rule("gateway-ego", "ingress", ("put", "delete"), [f"{r}/*/ego/*"]),
        rule("router-forward", "ingress", _ALL_MESSAGES, [f"{r}/**"]),
    ]
    grants = {"sumo": ["sumo-put", "sumo-serve", "sumo-token"], "physics": ["physics-put", "physics-token"],
              "viewer": [], "gateway": ["gateway-ego"], "router": ["router-forward"] if routed else []}
    for ego in sec.renderers:
        rules.append(rule(f"ego-{ego}", "ingress", ("put", "delete"), [f"{r}/*/ego/{ego}"]))
        grants[renderer_role(ego)] = [f"ego-{ego}"]
    for role in ["viewer", "gateway", *(renderer_role(e) for e in sec.renderers)]:
        rules.append(rule(f"camera-{role}", "ingress", ("put", "delete"), [f"{r}/*/viewer/{role}/*/camera"]))
        rules.append(rule(f"camera-token-{role}", "ingress", ("liveliness_token",), [f"{r}/*/viewer/{role}/*/alive"]))
        grants[role] = [*grants[role], f"camera-{role}", f"camera-token-{role}"]
    subjects, policies = [], []
    for role, own in grants.items():
        # By certificate only: user/password authenticates the connecting side alone, so a
        # peer that connected to us could not match a username subject on its own side.
        subjects.append({"id": role, "cert_common_names": [role]})
        policies.append({"id": role, "rules": ["receive", "read", *own], "subjects": [role]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def _role_files(sec: SecurityConfig, role: str) -> tuple[Path, Path, Path]:
    d = sec.certs
    files = (d / "ca.pem", d / f"{role}.pem", d / f"{role}.key")
    for f in files:
        if not f.is_file():
            raise ConfigError(f"zenoh.security.certs: {f} not found (role {role!r}); make the certificates "
                              f"with `sumoco certs init {d}`")
    return files


def _password_of(users: Path, role: str) -> str:
    try:
        lines = users.read_text().splitlines()
    except OSError as e:
        raise ConfigError(f"zenoh.security.users: cannot read {users} ({e.strerror})") from None
    for line in lines:
        user, sep, password = line.partition(":")
        if sep and user == role:
            return password
    raise ConfigError(f"zenoh.security.users: {users} has no line for user {role!r}")


def _as_tls(endpoint: str) -> str:
    return "tls/" + endpoint[4:] if endpoint.startswith("tcp/") else endpoint


#: [s] an incoming link must finish its handshake within this
ACCEPT_TIMEOUT_S = 2.0
#: incoming links that may be mid-handshake at once (each a socket and a small task)
ACCEPT_PENDING = 4096

#: [s] a session whose peer is not up yet retries connecting at least this often (Zenoh's own
#: back-off grows to 4 s: a viewer or recorder started before the SUMO side missed the first
#: ~4 s of its run, 166 steps of a lockstep run); the first retry comes after a quarter of it
CONNECT_RETRY_MAX_S = 0.5

#: Link protocols the secure profile accepts: TLS (``tcp/`` endpoints are turned into ``tls/``).
SECURE_LINKS = ("tcp/", "tls/")


def _secure(conf: zenoh.Config, cfg: ZenohConfig, role: str) -> None:
    sec = cfg.security
    plain = [e for e in (*cfg.listen, *cfg.connect) if not e.startswith(SECURE_LINKS)]
    if plain:
        raise ConfigError(f"zenoh.security: endpoint {plain[0]!r} would be a plain link outside TLS; the secure "
                          f"profile takes tcp/ (run as tls/) or tls/ endpoints only")
    ca, cert, key = _role_files(sec, role)
    tls = {
        "root_ca_certificate": str(ca),
        "listen_certificate": str(cert), "listen_private_key": str(key),
        "connect_certificate": str(cert), "connect_private_key": str(key),
        "enable_mtls": True,  # a peer without a certificate from our CA cannot open a link
        "verify_name_on_connect": True,
    }
    for k, v in tls.items():
        conf.insert_json5(f"transport/link/tls/{k}", json.dumps(v))
    if sec.users is not None:
        usr = {"user": role, "password": _password_of(sec.users, role), "dictionary_file": str(sec.users)}
        for k, v in usr.items():
            conf.insert_json5(f"transport/auth/usrpwd/{k}", json.dumps(v))
    if sec.acl:
        routed = sec.routers or cfg.mode in ("router", "client")
        conf.insert_json5("access_control", json.dumps(access_control(cfg.root, sec, routed)))


def zenoh_config(cfg: ZenohConfig, role: str = "viewer") -> zenoh.Config:
    """Translate our typed ``[zenoh]`` table into a ``zenoh.Config``.

    ``role`` picks the certificate in the secure profile (``sumo``, ``physics``,
    ``viewer`` or ``renderer-<ego id>``); without ``[zenoh.security]`` it is unused.
    """
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(cfg.mode))
    # An empty listen list would make a peer listen on every interface: keep it on loopback.
    listen = list(cfg.listen) or (["tcp/127.0.0.1:0"] if cfg.mode != "client" else [])
    connect = list(cfg.connect)
    if cfg.security.enabled:
        listen, connect = [_as_tls(e) for e in listen], [_as_tls(e) for e in connect]
        _secure(conf, cfg, role)
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    retry_ms = int(CONNECT_RETRY_MAX_S * 1000)
    conf.insert_json5("connect/retry", json.dumps({"period_init_ms": retry_ms // 4, "period_max_ms": retry_ms,
                                                   "period_increase_factor": 2}))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    conf.insert_json5("transport/shared_memory/enabled", json.dumps(cfg.shared_memory))
    # Bounds what one peer can make us buffer while reassembling a message (default 1 GiB).
    conf.insert_json5("transport/link/rx/max_message_size", json.dumps(int(cfg.max_message_mb * (1 << 20))))
    # Every sample carries its publisher's HLC timestamp, so a client can measure latency (SPEC 1).
    conf.insert_json5("timestamping/enabled", json.dumps(True))
    # Links that connect but never finish the (TLS) handshake are dropped after this, and
    # enough of them may wait at once that they cannot crowd out a real peer (Zenoh's
    # defaults, 10 s and 100, let 120 half-open connections block new peers).
    conf.insert_json5("transport/unicast/accept_timeout", json.dumps(int(ACCEPT_TIMEOUT_S * 1000)))
    conf.insert_json5("transport/unicast/accept_pending", json.dumps(ACCEPT_PENDING))
    return conf


def open_session(cfg: ZenohConfig, role: str = "viewer") -> zenoh.Session:
    """Open a session; ``role`` names this process in the secure profile (least: viewer)."""
    level = os.environ.get("RUST_LOG", "").lower()
    if cfg.security.users is not None and ("debug" in level or "trace" in level):
        # Zenoh's debug log prints the configuration, this process's password included
        log.warning("RUST_LOG=%s would print this process's password (user/password authentication): "
                    "Zenoh's own log stays off", level)
    else:
        zenoh.try_init_log_from_env()
    log.debug("opening zenoh session mode=%s listen=%s connect=%s%s", cfg.mode, cfg.listen, cfg.connect,
              f" (TLS as {role!r})" if cfg.security.enabled else "")
    try:
        return zenoh.open(zenoh_config(cfg, role))
    except zenoh.ZError as e:  # e.g. a listen port taken meanwhile: one line, not a traceback
        raise SumocoError(f"cannot open the Zenoh session ({' '.join(str(e).split())})") from None


def free_tcp_port() -> int:
    """A currently free TCP port on 127.0.0.1 (for tests and the demo's endpoints)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Wake:
    """``threading.Event``'s ``set`` / ``wait`` / ``clear`` / ``is_set`` on one C-level lock.

    For a daemon's main loop woken by Zenoh callbacks: ``threading.Event`` runs a
    ``Condition`` in Python on both sides (a waiter lock allocated per wait, a notify loop
    under a second lock), which after an idle wait costs tens of microseconds of cold
    code per step. Here the flag *is* the lock: unlocked = set. ``set`` releases it (from
    any thread, never blocks), ``wait`` acquires and releases it again (blocking in C,
    the GIL released), ``clear`` takes it without blocking.
    """

    __slots__ = ("_lock",)

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._lock.acquire()  # starts cleared

    def set(self) -> None:
        try:
            self._lock.release()
        except RuntimeError:  # already set
            pass

    def wait(self, timeout: float | None = None) -> bool:
        """True once set (it stays set), False after ``timeout`` [s]; None waits forever."""
        if self._lock.acquire(timeout=-1 if timeout is None else max(0.0, timeout)):
            self.set()
            return True
        return False

    def clear(self) -> None:
        self._lock.acquire(blocking=False)

    def is_set(self) -> bool:
        return not self._lock.locked()


POLL_IDLE_S = 0.001  # [s] outside its window a ``RingPoll`` looks this often (and its loop runs)


class RingPoll:
    """A subscriber polled from a ring of samples instead of called back, for latency-sensitive
    runs (``physics.busy_poll_ms``).

    A callback wakes the waiting loop through the OS and the GIL: ~50 us per message after an
    idle wait on a 2-core host, a third of what a 1,000-agent step adds to Zenoh's own
    latency. Here Zenoh's receive thread only pushes into the ring (no Python); within a
    window after ``arm`` (the next message is due) ``wait`` spins on it, a core busy while it
    does; outside the window it looks every POLL_IDLE_S. Each sample goes to ``on_sample``,
    as a callback's would. The ring keeps the newest ``capacity`` samples (the loop pulls
    every pass, so it fills only when the loop stalls)."""

    def __init__(self, session: zenoh.Session, key: str, capacity: int, window_s: float, on_sample) -> None:
        self._sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(int(capacity)))
        self.window_s = float(window_s)
        self._on_sample = on_sample
        self._until = 0.0
        self.spins = 0  # passes that found the ring empty inside the window

    def arm(self) -> None:
        """The next sample is due: spin for it for up to ``window_s`` from now."""
        self._until = time.monotonic() + self.window_s

    def pull(self) -> int:
        """Hand every sample the ring holds to ``on_sample``; how many."""
        n = 0
        while (sample := self._sub.try_recv()) is not None:
            self._on_sample(sample)
            n += 1
        return n

    def wait(self, stop: threading.Event, timeout_s: float, wake: "Wake | None" = None) -> bool:
        """Until a sample was pulled (True), ``stop`` or ``wake`` (the loop's other callbacks)
        is set, or ``timeout_s`` passed outside the window (False)."""
        end = time.monotonic() + timeout_s
        while not stop.is_set():
            if self.pull():
                return True
            if wake is not None and wake.is_set():
                return False
            now = time.monotonic()
            if now < self._until:
                self.spins += 1
                os.sched_yield()  # (the GIL too: the process's callbacks still run at once)
                continue
            if now >= end:
                return False
            stop.wait(min(POLL_IDLE_S, end - now))
        return False

    def undeclare(self) -> None:
        self._sub.undeclare()
