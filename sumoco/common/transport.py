"""Zenoh session set-up shared by every sumoco process.

Embedded default: peer mode, multicast scouting off, explicit loopback endpoints, so two
daemons on one machine find each other without a router and nothing leaves 127.0.0.1.
Scale-out: mode "client" with ``connect`` pointing at routers (``sumoco router`` or zenohd).
"""

from __future__ import annotations

import json
import logging
import socket

import zenoh

from sumoco.common.config import ZenohConfig

log = logging.getLogger(__name__)


def zenoh_config(cfg: ZenohConfig) -> zenoh.Config:
    """Translate our typed ``[zenoh]`` table into a ``zenoh.Config``."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(cfg.mode))
    # An empty listen list would make a peer listen on every interface: keep it on loopback.
    listen = list(cfg.listen) or (["tcp/127.0.0.1:0"] if cfg.mode != "client" else [])
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    conf.insert_json5("transport/shared_memory/enabled", json.dumps(cfg.shared_memory))
    return conf


def open_session(cfg: ZenohConfig) -> zenoh.Session:
    zenoh.try_init_log_from_env()
    log.debug("opening zenoh session mode=%s listen=%s connect=%s", cfg.mode, cfg.listen, cfg.connect)
    return zenoh.open(zenoh_config(cfg))


def free_tcp_port() -> int:
    """A currently free TCP port on 127.0.0.1 (for tests and the demo's endpoints)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
