"""A session started before its peer links within CONNECT_RETRY_MAX_S of the peer coming up.

Zenoh's own back-off grows to 4 s between connect attempts: a viewer, recorder or client
started before the SUMO side missed the first seconds of its run (166 steps of a lockstep
run, SPEC 3.1.1). Measured here with a real listener that comes up 3.2 s after the client.
"""

from __future__ import annotations

import time

from runtime.config import ZenohConfig
from runtime.transport import CONNECT_RETRY_MAX_S, open_session
from tests.harness import endpoint, wait_until

LATE_S = 3.2  # [s] the listener comes up this long after the client (Zenoh's default: next try at 3 s + 4 s)


def test_a_client_started_first_links_soon_after_the_listener_comes_up():
    ep = endpoint()
    client = open_session(ZenohConfig(connect=(ep,)))
    try:
        time.sleep(LATE_S)
        server = open_session(ZenohConfig(listen=(ep,)))
        try:
            t0 = time.monotonic()
            wait_until(lambda: list(client.info.peers_zid()), 10, "the client's link")
            assert time.monotonic() - t0 < CONNECT_RETRY_MAX_S + 0.5
        finally:
            server.close()
    finally:
        client.close()
