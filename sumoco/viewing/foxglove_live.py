"""``sumoco foxglove`` (also ``sumoco view --foxglove``): a live run as a 3D scene in the
Foxglove app (foxglove-sdk server).

The same scene code as recordings (``scene.ScenePublisher``), logged on a context whose
sink is ``foxglove.start_server`` instead of an MCAP writer. Zenoh's callback only hands
the payload to a ``LatestWorker``; when scene building falls behind, the oldest pending
payloads are dropped (counted) and the transport never waits. The static network is
fetched with one query at start and whenever the SUMO side's liveliness token appears,
and is re-sent every few seconds so a Foxglove app that connects later draws the roads.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import foxglove  # the `foxglove` extra: without it the CLI names the extra to install
import zenoh

from protocol.keys import Keys
from sumoco.viewing.scene import LatestWorker, ScenePublisher

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FoxgloveConfig:
    host: str = "127.0.0.1"  # loopback by default
    port: int = 8767  # [TCP port] of the Foxglove WebSocket server; 0 = any free port
    scene_hz: float = 10.0  # [Hz of simulated time] scene updates per key at most; 0 = every message
    queue: int = 8  # [messages] scene worker queue; full: drop the oldest
    network_every_s: float = 5.0  # [s] wall clock between re-sends of the network for late joiners


class LiveScene:
    """Zenoh run -> scene updates on a foxglove context (with a server or any other sink)."""

    def __init__(self, session: zenoh.Session, keys: Keys, context, cfg: FoxgloveConfig) -> None:
        self.session, self.keys, self.cfg = session, keys, cfg
        period = 1.0 / cfg.scene_hz if cfg.scene_hz > 0 else 0.0
        self.scene = ScenePublisher(context, min_period_s=period)
        self.worker = LatestWorker(self.scene.feed, cfg.queue, "foxglove-scene")
        self._static: bytes | None = None
        self._decl: list = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._network_loop, name="foxglove-network", daemon=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        topic, payload = str(sample.key_expr), sample.payload.to_bytes()
        if self.scene.offer(topic, payload):
            self.worker.put(topic, payload)

    def _on_token(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT and str(sample.key_expr) == self.keys.sumo_alive:
            threading.Thread(target=self.fetch_static, name="foxglove-static", daemon=True).start()

    def fetch_static(self) -> bool:
        for reply in self.session.get(self.keys.static, timeout=5.0):
            if reply.ok is not None:
                self._static = reply.ok.payload.to_bytes()
                self.worker.put(self.keys.static, self._static)
                return True
        return False

    def _network_loop(self) -> None:
        while not self._stop.wait(self.cfg.network_every_s):
            if self._static is not None:
                self.worker.put(self.keys.static, self._static)

    def start(self) -> "LiveScene":
        s, k = self.session, self.keys
        self._decl.append(s.declare_subscriber(k.step, self._on_sample))
        self._decl.append(s.declare_subscriber(k.physics_state_all, self._on_sample))
        self._decl.append(s.liveliness().declare_subscriber(k.sumo_alive, self._on_token, history=True))
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for d in self._decl:
            d.undeclare()
        self._decl.clear()
        self.worker.close(5.0)

    def stats(self) -> dict:
        return {"updates": self.scene.updates, "dropped": self.worker.dropped, "errors": self.scene.errors,
                "thinned": self.scene.thinned}


def cli_main(args) -> int:
    """``sumoco foxglove`` / ``sumoco view --foxglove``: serve the live scene until Ctrl-C (or
    --duration seconds). ``view``'s own options (``--max-hz``) do not apply here."""
    import json
    import signal

    from runtime.config import CommonConfig, apply_cli, load_common
    from runtime.transport import open_session

    common = load_common(args.config)[0] if args.config else CommonConfig()
    common = apply_cli(common, args)
    cfg = FoxgloveConfig(host=args.host or "127.0.0.1", port=8767 if args.port is None else args.port,
                         scene_hz=10.0 if args.scene_hz is None else args.scene_hz)
    keys = Keys(common.zenoh.root, common.run.id)
    ctx = foxglove.Context()
    server = foxglove.start_server(name=f"sumoco {keys.run}", host=cfg.host, port=cfg.port, context=ctx)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        with open_session(common.zenoh) as session:
            live = LiveScene(session, keys, ctx, cfg).start()
            print(json.dumps({"url": f"ws://{cfg.host}:{server.port}", "run": keys.run,
                              "open": "Foxglove app > Open connection > Foxglove WebSocket"}), flush=True)
            t0 = time.monotonic()
            stop.wait(getattr(args, "duration", None))
            live.stop()
            log.info("foxglove server stopped after %.0f s: %s", time.monotonic() - t0, live.stats())
    finally:
        server.stop()
    return 0
