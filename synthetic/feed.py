"""The viewer's demo feed: a ``FakeRun`` published on Zenoh like a real run.

``FakePublisher`` puts step messages, physics states (one or more instances) and static
data (queryable) on Zenoh with the real key layout and liveliness tokens, so ``sumoco
view`` cannot tell it from a real run. Run it by hand next to ``sumoco view``::

    python -m synthetic.feed --listen tcp/127.0.0.1:7447 --grid 3 --agents 1000
    sumoco view --connect tcp/127.0.0.1:7447 --run synthetic
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from typing import Any

from protocol.codec import encode
from protocol.keys import Keys
from synthetic.traffic import FakeRun

log = logging.getLogger(__name__)


class FakePublisher:
    """Publishes a ``FakeRun`` on a Zenoh session in a background thread, in real time."""

    def __init__(self, session: Any, fake: FakeRun, root: str = "sumoco", step_hz: float = 10.0,
                 physics_hz: float = 20.0, instances: tuple[str, ...] = ("paper", "default")) -> None:
        self.session, self.fake = session, fake
        self.keys = Keys(root, fake.run)
        self.step_hz, self.physics_hz, self.instances = step_hz, physics_hz, instances
        self.static_bytes = encode(fake.static())
        self.steps_sent = 0
        self.static_queries = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="fake-run", daemon=True)
        self._decl: list[Any] = []

    def _on_query(self, query: Any) -> None:
        self.static_queries += 1
        query.reply(self.keys.static, self.static_bytes)

    def start(self) -> "FakePublisher":
        s, k = self.session, self.keys
        self._decl.append(s.declare_queryable(k.static, self._on_query))
        self._decl.append(s.liveliness().declare_token(k.sumo_alive))
        self._step_pub = s.declare_publisher(k.step)
        self._phys_pubs = {}
        for inst in self.instances:
            ki = Keys(k.root, k.run, inst)
            self._phys_pubs[inst] = s.declare_publisher(ki.physics_state)
            self._decl.append(s.liveliness().declare_token(ki.physics_alive))
        self._decl += [self._step_pub, *self._phys_pubs.values()]
        self._thread.start()
        return self

    def _loop(self) -> None:
        t0 = time.monotonic()
        next_step, next_phys = 0, 0
        while not self._stop.is_set():
            now = time.monotonic() - t0
            if now >= next_step / self.step_hz:
                self._step_pub.put(encode(self.fake.step(next_step)))
                self.steps_sent += 1
                next_step += 1
            if self.instances and now >= next_phys / self.physics_hz:
                t = next_phys / self.physics_hz * self.step_hz * self.fake.dt  # same clock as steps
                for j, (inst, pub) in enumerate(self._phys_pubs.items()):
                    pub.put(encode(self.fake.physics(next_phys, t, next_step - 1, gain=1.0 + j)))
                next_phys += 1
            wait = min(next_step / self.step_hz,
                       next_phys / self.physics_hz if self.instances else 1e9) - (time.monotonic() - t0)
            if wait > 0:
                self._stop.wait(wait)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        for d in reversed(self._decl):
            try:
                d.undeclare()
            except Exception:  # already gone with the session
                pass


def main(argv: list[str] | None = None) -> int:
    from runtime.config import ZenohConfig
    from runtime.logs import setup_logging
    from runtime.transport import open_session

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--listen", default="tcp/127.0.0.1:7447", help="zenoh endpoint to listen on")
    ap.add_argument("--run", default="synthetic")
    ap.add_argument("--root", default="sumoco")
    ap.add_argument("--grid", type=int, default=2, help="junctions per side")
    ap.add_argument("--agents", type=int, default=200)
    ap.add_argument("--hz", type=float, default=10.0, help="step messages per second")
    args = ap.parse_args(argv)
    setup_logging()
    fake = FakeRun(grid=args.grid, n=args.agents, run=args.run)
    with open_session(ZenohConfig(listen=(args.listen,))) as session:
        pub = FakePublisher(session, fake, root=args.root, step_hz=args.hz).start()
        log.info("synthetic run %r: %d agents on %dx%d junctions, listening on %s",
                 args.run, args.agents, args.grid, args.grid, args.listen)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        finally:
            pub.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
