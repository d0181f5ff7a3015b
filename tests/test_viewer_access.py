"""Who may read the live view: Host and Origin checks and the per-run token, tried with a
real WebSocket client against a real server (what a foreign web page or a DNS-rebinding
attack would send), and the URL with the token that ``sumoco view`` prints."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import msgpack
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from sumoco.viewing.viewer.server import LatestStore, ViewerConfig, ViewerServer
from runtime.transport import free_tcp_port

ROOT = Path(__file__).resolve().parents[1]
TOKEN = "access-test-token-0123456789"


async def _with_server(fn):
    server = ViewerServer(ViewerConfig(port=0, token=TOKEN), LatestStore(), run="acc")
    server.store.put_static(b"\x80")  # something to send: the page gets it after hello
    stop, ready = asyncio.Event(), asyncio.Event()
    task = asyncio.create_task(server.run(stop, ready=lambda port: ready.set()))
    await asyncio.wait_for(ready.wait(), 5)
    try:
        return await fn(server)
    finally:
        stop.set()
        await task


async def _status_of(url: str, **headers) -> int:
    """HTTP status of a WebSocket handshake (101 = accepted)."""
    try:
        async with connect(url, additional_headers=headers, open_timeout=5) as ws:
            hello = msgpack.unpackb(await asyncio.wait_for(ws.recv(), 5))
            assert hello["type"] == "hello" and hello["run"] == "acc"
            return 101
    except InvalidStatus as e:
        return e.response.status_code


async def _raw_handshake(port: int, path: str, host: str, origin: str) -> int:
    """Status of a hand-written WebSocket upgrade with exactly these Host and Origin headers."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write((f"GET {path} HTTP/1.1\r\nHost: {host}\r\nOrigin: {origin}\r\nUpgrade: websocket\r\n"
                  "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                  "Sec-WebSocket-Version: 13\r\n\r\n").encode())
    await writer.drain()
    line = await asyncio.wait_for(reader.readline(), 5)
    writer.close()
    return int(line.split()[1])


def test_websocket_refuses_foreign_origin_missing_token_and_foreign_host():
    async def go(server: ViewerServer):
        base = f"ws://127.0.0.1:{server.port}/ws"
        own = f"http://127.0.0.1:{server.port}"
        got = {
            "ok, own page": await _status_of(f"{base}?token={TOKEN}", Origin=own),
            "ok, localhost page": await _status_of(f"{base}?token={TOKEN}", Origin=f"http://localhost:{server.port}"),
            "ok, no Origin (not a browser)": await _status_of(f"{base}?token={TOKEN}"),
            "foreign origin": await _status_of(f"{base}?token={TOKEN}", Origin="http://evil.example"),
            "other port on loopback": await _status_of(f"{base}?token={TOKEN}", Origin="http://127.0.0.1:1"),
            "missing token": await _status_of(base, Origin=own),
            "wrong token": await _status_of(f"{base}?token=x{TOKEN[1:]}", Origin=own),
        }
        # DNS rebinding: the attacker's name resolves to 127.0.0.1, the Host header keeps it.
        got["rebound host"] = await _raw_handshake(server.port, f"/ws?token={TOKEN}", f"evil.example:{server.port}",
                                                   f"http://evil.example:{server.port}")
        got["rebound host, own token and origin"] = await _raw_handshake(
            server.port, f"/ws?token={TOKEN}", f"127.0.0.1:{server.port}", own)
        return got, dict(server.refused), server.clients_total

    got, refused, accepted = asyncio.run(_with_server(go))
    assert got == {
        "ok, own page": 101, "ok, localhost page": 101, "ok, no Origin (not a browser)": 101,
        "foreign origin": 403, "other port on loopback": 403, "missing token": 403, "wrong token": 403,
        "rebound host": 403, "rebound host, own token and origin": 101,
    }
    assert refused == {"host": 1, "origin": 2, "token": 2}
    assert accepted == 4  # refused handshakes never became clients


def test_status_and_page_need_the_right_host_and_status_the_token():
    async def go(server: ViewerServer):
        base = f"http://127.0.0.1:{server.port}"

        def get(path: str, host: str | None = None) -> int:
            req = urllib.request.Request(base + path, headers={"Host": host} if host else {})
            try:
                with urllib.request.urlopen(req, timeout=5) as r:
                    return r.status
            except urllib.error.HTTPError as e:
                return e.code

        loop = asyncio.get_running_loop()
        codes = {}
        for name, path, host in (("page", "/", None), ("status", f"/status?token={TOKEN}", None),
                                 ("status without token", "/status", None),
                                 ("page via a foreign name", "/", f"evil.example:{server.port}")):
            codes[name] = await loop.run_in_executor(None, get, path, host)
        return codes

    assert asyncio.run(_with_server(go)) == {"page": 200, "status": 200, "status without token": 403,
                                             "page via a foreign name": 403}


def test_random_token_per_start_and_bad_configured_token_is_refused():
    from protocol.errors import ConfigError

    a = ViewerServer(ViewerConfig(), LatestStore())
    b = ViewerServer(ViewerConfig(), LatestStore())
    assert a.token != b.token and len(a.token) >= 20
    with pytest.raises(ConfigError, match="viewer.token"):
        ViewerConfig(token="short").validate()


def test_sumoco_view_prints_the_url_with_its_token(tmp_path):
    port, zport = free_tcp_port(), free_tcp_port()
    proc = subprocess.Popen([sys.executable, "-m", "sumoco.cli", "view", "--port", str(port),
                             "--listen", f"tcp/127.0.0.1:{zport}", "--run", "urltest", "--quiet"],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        line = proc.stdout.readline()  # blocks until the server listens (or the process dies)
        m = re.search(r"http://127\.0\.0\.1:(\d+)/\?token=([A-Za-z0-9_\-]{20,})", line)
        assert m and int(m.group(1)) == port, (line, proc.stderr.read() if proc.poll() is not None else "")
        token = m.group(2)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/status?token={token}", timeout=5) as r:
            assert r.status == 200
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/status?token=wrong{token}", timeout=5)
        assert e.value.code == 403
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            rc = proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
    assert rc == 0, proc.stderr.read()
