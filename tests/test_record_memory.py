"""The recorder's memory across SUMO restarts (the soak's pattern, in process and faster).

A SUMO side that finishes its pass and is started again with the same run id is a new
Zenoh peer whose steps start over at step 0 with agents of new names. Everything the
recorder keeps between messages must be bounded by the keys of the run, not grow with
restarts, steps or agent names: the compact encoder's state per key, the physics
thinning and scene thinning per key, the MCAP channels per (key, schema), its threads,
and the Python heap once the queues are drained.
"""

from __future__ import annotations

import gc
import threading
import time
import tracemalloc

import pytest

from protocol.codec import decode
from protocol.keys import Keys
from sumoco.viewing import scene as scene_mod
from sumoco.recording.record import LiveRecorder, McapRecorder, RecordConfig, read_recording
from runtime.config import ZenohConfig
from runtime.transport import open_session
from synthetic.feed import FakePublisher
from synthetic.traffic import FakeRun
from tests.harness import endpoint

pytestmark = pytest.mark.integration

RESTARTS = 6
PASS_S = 2.0  # [s] wall time of one SUMO pass
AGENTS = 40


class _RenamingRun(FakeRun):
    """Agents that leave and enter under new names every 20 steps, like SUMO's vehicles."""

    def __init__(self, epoch: int, **kw) -> None:
        super().__init__(**kw)
        self._base, self._epoch = list(self.ids), epoch

    def _rename(self, k: int) -> None:
        self.ids = [f"{b}.{self._epoch}.{(i + k // 20) // 5}" for i, b in enumerate(self._base)]

    def step(self, k):
        self._rename(k)
        return super().step(k)

    def physics(self, tick, t, sumo_step, gain=1.0):
        self._rename(max(sumo_step, 0))
        return super().physics(tick, t, sumo_step, gain)


def test_recorder_state_stays_bounded_across_sumo_restarts(tmp_path):
    keys = Keys("sumoco", "soak")
    path = tmp_path / "soak.mcap"
    rec = McapRecorder(path)
    # the soak's recorder: no [record] section, so the defaults (compact records, physics
    # thinned to 10 Hz, the scene at 0.5 Hz per key)
    cfg = RecordConfig()
    ep = endpoint()
    heap: list[int] = []
    threads: list[int] = []
    with open_session(ZenohConfig(listen=(ep,))) as s:
        live = LiveRecorder(s, keys, rec, config=cfg).start()
        tracemalloc.start(1)
        try:
            for i in range(RESTARTS):
                with open_session(ZenohConfig(listen=(endpoint(),), connect=(ep,))) as sumo:
                    pub = FakePublisher(sumo, _RenamingRun(i, grid=1, n=AGENTS, run="soak"), step_hz=40.0,
                                        physics_hz=100.0).start()
                    if i == 0:
                        assert live.fetch_static(5.0, map_timeout_s=0) is not None
                    time.sleep(PASS_S)
                    pub.stop()
                assert live.drain(10.0), "the writer queue and the scene worker drained"
                gc.collect()
                heap.append(tracemalloc.get_traced_memory()[0])
                threads.append(threading.active_count())
        finally:
            tracemalloc.stop()
            live.stop()
    rec.close()

    state_keys = {keys.step} | {Keys(keys.root, keys.run, p).physics_state for p in ("paper", "default")}
    assert live.written > RESTARTS * 50 and live.dropped == 0 and live.compact_errors == 0
    # per key, never per restart, step or agent name
    kept = live.debug_state()
    assert set(kept.encoder_agents) == state_keys
    assert all(n == AGENTS for n in kept.encoder_agents.values())
    assert kept.thinning_keys <= state_keys
    assert rec.channel_count <= len(state_keys) + 1  # + the static data
    if scene_mod.available():
        assert kept.scene_keys <= state_keys
        assert kept.scene_sizes == AGENTS
    # no thread left behind per restart (Zenoh's own threads are not Python threads)
    assert threads[-1] <= threads[1], threads
    # Python heap after passes 2..6 with the queues drained (tracemalloc: Python allocations
    # only). ~900 messages are recorded in those passes, so a structure that kept even 100 B
    # per message, or the soak's 0.25 MB per pass, would exceed this; measured: < 10 kB.
    assert heap[-1] - heap[1] < 64_000, heap
    # every pass is in the file, starting over at step 0
    steps = [decode(m.data).step for m in read_recording(path).messages if m.topic == keys.step]
    assert len(steps) > RESTARTS * 20 and steps.count(0) == RESTARTS
