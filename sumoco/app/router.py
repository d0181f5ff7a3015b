"""``sumoco router``: a Zenoh router as a Python session in router mode.

There is no zenohd on PyPI; a router-mode session routes just as well (without plugins).
Daemons then run with ``--mode client --connect <router endpoint>``.
"""

from __future__ import annotations

import logging
import signal
import threading

from sumoco.common.config import ZenohConfig
from sumoco.common.transport import open_session

log = logging.getLogger(__name__)


def cli_main(args) -> int:
    listen = tuple(args.listen or ["tcp/127.0.0.1:7447"])
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    with open_session(ZenohConfig(mode="router", listen=listen)) as session:
        log.info("zenoh router %s listening on %s", session.zid(), ", ".join(listen))
        stop.wait()
    return 0
