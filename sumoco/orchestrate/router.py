"""``sumoco router``: a Zenoh router as a Python session in router mode.

There is no zenohd on PyPI; a router-mode session routes just as well (without plugins).
Daemons then run with ``--mode client --connect <router endpoint>``; routers that
``--connect`` to each other form a mesh (a client of one reaches the clients of all).

``--config`` takes the run config the daemons take and opens the session through the same
``runtime.transport.open_session``: its ``[zenoh]`` table (root, shared memory,
message size; the endpoints come from the flags only) and, in the secure profile, TLS
with mutual authentication and the role policy, the router presenting the ``router``
certificate. The router applies the policy to what its clients send it, by their
certificates, before it forwards; its peers let through what it forwards (transport.py).
"""

from __future__ import annotations

import logging
import signal
import threading

from runtime.config import CommonConfig, apply_cli, load_common, replace
from runtime.transport import open_session

log = logging.getLogger(__name__)

DEFAULT_LISTEN = ("tcp/127.0.0.1:7447",)

#: The certificate a router presents in the secure profile (``sumoco certs init`` makes it).
ROUTER_ROLE = "router"


def router_config(args) -> CommonConfig:
    """The run config (``--config``, else defaults) in router mode, on ``--listen`` /
    ``--connect`` only: the file's ``[zenoh]`` mode and endpoints are the daemons' (in
    ``configs/docker.toml`` they point at this very router), everything else is shared."""
    common = load_common(args.config)[0] if getattr(args, "config", None) else CommonConfig()
    common = replace(common, zenoh=replace(common.zenoh, mode="router", listen=(), connect=()))
    common = apply_cli(common, args)
    return replace(common, zenoh=replace(common.zenoh, listen=common.zenoh.listen or DEFAULT_LISTEN))


def cli_main(args) -> int:
    zen = router_config(args).zenoh
    stop = threading.Event()

    def on_signal(signum, _frame):
        log.info("signal %d: stopping the router", signum)
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    with open_session(zen, role=ROUTER_ROLE) as session:
        log.info("zenoh router %s listening on %s%s%s", session.zid(), ", ".join(zen.listen),
                 f", connecting to {', '.join(zen.connect)}" if zen.connect else "",
                 " (TLS, mutual authentication" + (", access control)" if zen.security.acl else ")")
                 if zen.security.enabled else "")
        stop.wait()
    return 0
