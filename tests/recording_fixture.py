"""A small real recording of a synthetic run (FakePublisher -> LiveRecorder), for replay tests."""

from __future__ import annotations

from pathlib import Path

from protocol.keys import Keys
from sumoco.recording.record import LiveRecorder, McapRecorder, RecordConfig
from runtime.config import ZenohConfig
from runtime.transport import open_session
from synthetic.feed import FakePublisher
from synthetic.traffic import FakeRun
from tests.harness import endpoint, wait_until


def make_recording(path: Path, steps: int = 15, agents: int = 20, run: str = "synth",
                   config: RecordConfig | None = None, chunk_size: int = 32 * 1024,
                   map_reply: bytes | None = None) -> dict:
    """Record ``steps`` SUMO steps of a FakeRun at 10 Hz (plus physics at 20 Hz, two instances).

    ``map_reply``: the answer a SUMO side would give on ``sumo/map`` (SPEC 9), if any.
    """
    cfg = ZenohConfig(listen=(endpoint(),))
    rec = McapRecorder(path, chunk_size=chunk_size)
    with open_session(cfg) as s:
        pub = FakePublisher(s, FakeRun(grid=1, n=agents, run=run), step_hz=10.0, physics_hz=20.0)
        keys = Keys("sumoco", run)
        if map_reply is not None:
            s.declare_queryable(keys.sumo_map, lambda q: q.reply(keys.sumo_map, map_reply))
        live = LiveRecorder(s, Keys("sumoco", run), rec, config=config or RecordConfig(physics_hz=0.0))
        live.start()
        pub.start()
        try:
            assert live.fetch_static(timeout_s=5.0, map_timeout_s=5.0 if map_reply else 0.0) is not None
            wait_until(lambda: pub.steps_sent >= steps, 30.0, f"{steps} synthetic steps")
        finally:
            pub.stop()
            live.stop()
            rec.close()
    return live.stats()
