"""``sumoco foxglove`` and ``sumoco view --foxglove``: the live scene through foxglove-sdk's
WebSocket server, read by a real client."""

from __future__ import annotations

import json
import struct

import pytest
from websockets.sync.client import connect

from runtime.config import ZenohConfig
from runtime.transport import open_session
from synthetic.feed import FakePublisher
from synthetic.traffic import FakeRun
from tests.harness import Daemon, endpoint, wait_until

pytestmark = pytest.mark.integration


@pytest.mark.parametrize("command", [["foxglove"], ["view", "--foxglove"]], ids=["foxglove", "view-foxglove"])
def test_live_scene_reaches_a_foxglove_websocket_client(tmp_path, command):
    ep = endpoint()
    session = open_session(ZenohConfig(listen=(ep,)))
    pub = FakePublisher(session, FakeRun(grid=1, n=12, run="fox"), instances=("main",)).start()
    fox = Daemon("foxglove", [*command, "--run", "fox", "--connect", ep, "--listen", endpoint(),
                              "--port", "0"], tmp_path)
    try:
        line = wait_until(lambda: next((ln for ln in fox.tail(50).splitlines() if ln.startswith('{"url"')), None),
                          20.0, "the Foxglove server's URL", procs=[fox])
        url = json.loads(line)["url"]
        with connect(url, subprotocols=["foxglove.sdk.v1"], max_size=None, open_timeout=10) as ws:
            channels = {}
            while "/scene" not in channels:
                m = json.loads(ws.recv(timeout=10))
                if m["op"] == "advertise":
                    channels |= {c["topic"]: c for c in m["channels"]}
            ch = channels["/scene"]
            assert ch["schemaName"] == "foxglove.SceneUpdate" and ch["encoding"] == "protobuf"
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": ch["id"]}]}))
            sizes = []
            while len(sizes) < 5:
                m = ws.recv(timeout=10)
                if isinstance(m, bytes) and m[0] == 1:  # message data: op, subscription id, time, payload
                    sub_id, = struct.unpack_from("<I", m, 1)
                    assert sub_id == 7
                    sizes.append(len(m) - 13)
        assert min(sizes) > 100  # a scene with 12 boxes, not an empty update
    finally:
        pub.stop()
        code = fox.terminate(5)
        session.close()
    assert code == 0, fox.tail()


def test_view_foxglove_runs_the_foxglove_command_and_plain_view_stays_the_browser_view():
    from sumoco.cli import _COMMANDS, build_parser

    p = build_parser()
    fox = p.parse_args(["view", "--foxglove", "--port", "0", "--scene-hz", "2"])
    assert (fox.cmd, fox.port, fox.scene_hz) == ("foxglove", 0, 2.0)
    assert _COMMANDS[fox.cmd] == _COMMANDS["foxglove"] == "sumoco.viewing.foxglove_live:cli_main"
    assert p.parse_args(["view", "--max-hz", "5"]).cmd == "view"
    assert p.parse_args(["foxglove"]).cmd == "foxglove"
