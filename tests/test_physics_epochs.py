"""The physics daemon (a real OS process) against a fake SUMO side: incarnations (SPEC 3.1.1).

The test's session plays the SUMO side and publishes synthetic steps with an ``epoch``.
The daemon must take a newer epoch as a restart (every agent of the old incarnation
parked, the new one's spawned afresh), refuse and count replays of old steps, steps of an
older incarnation and absurd index jumps (never acknowledging them), and, following the
next run in realtime, publish no state after a final step until a new incarnation starts.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import pytest

from protocol.codec import decode, encode
from protocol.keys import Keys
from protocol.order import NS_PER_S, new_epoch
from runtime.config import ZenohConfig
from runtime.transport import open_session
from synthetic.traffic import circle_traffic
from tests.harness import Daemon, Probe, endpoint, wait_until

pytestmark = pytest.mark.integration

CONFIG = """
[run]
id = "{run}"
timing = "{timing}"
[zenoh]
mode = "peer"
[physics]
shards = 1
initial_slots = {{passenger = 8}}
follow_next_run = {follow}
"""


class FakeSumo:
    def __init__(self, tmp_path, run: str, timing: str, follow: bool = False, args: tuple[str, ...] = (),
                 instance: str = "main") -> None:
        self.run, self.keys = run, Keys("sumoco", run)
        cfg = tmp_path / "physics.toml"
        cfg.write_text(CONFIG.format(run=run, timing=timing, follow=str(follow).lower()))
        ep = endpoint()
        self.session = open_session(ZenohConfig(listen=(ep,)))
        self.acks: list = []
        self.lock = threading.Lock()
        self._sub = self.session.declare_subscriber(self.keys.ack_all, self._on_ack)
        self.token = self.session.liveliness().declare_token(self.keys.sumo_alive)
        self.daemon = Daemon("physics", ["physics", "--config", str(cfg), "--connect", ep, "--listen", endpoint(),
                                         *args], tmp_path / "logs")
        self.probe = Probe(self.keys, connect=[ep])
        self.instance = instance
        token = Keys("sumoco", run, instance).physics_alive
        wait_until(lambda: token in self.probe.alive, 30.0, "the physics token", procs=[self.daemon])

    def _on_ack(self, s) -> None:
        with self.lock:
            self.acks.append(decode(s.payload.to_bytes()).step)

    def put(self, epoch: int, step: int, n: int = 3, final: bool = False, prefix: str = "veh") -> None:
        msg = replace(circle_traffic(n, step, run=self.run, id_prefix=prefix), epoch=epoch, final=final)
        self.session.put(self.keys.step, encode(msg))

    def step(self, epoch: int, step: int, **kw) -> None:
        """Put a step and wait for its acknowledgement (lockstep)."""
        self.put(epoch, step, **kw)
        wait_until(lambda: self.acked(step), 20.0, f"ack of step {step}", procs=[self.daemon])

    def acked(self, step: int) -> bool:
        with self.lock:
            return step in self.acks

    def counters(self) -> dict:
        return self.probe.last_physics(self.instance).counters

    def close(self) -> int:
        code = self.daemon.terminate(15.0)
        self.probe.close()
        self._sub.undeclare()
        self.token.undeclare()
        self.session.close()
        return code


def test_replays_old_epochs_and_jumps_are_refused_and_a_new_epoch_resets_the_fleet(tmp_path):
    s = FakeSumo(tmp_path, "epochs", "lockstep")
    try:
        first = new_epoch()
        for k in range(6):
            s.step(first, k)
        wait_until(lambda: s.probe.last_physics().sumo_step == 5, 5.0, "the state of step 5")
        placed = s.counters()["placements"]
        with s.lock:
            s.acks.clear()
        for _ in range(5):  # a step captured earlier, put again: a replay
            s.put(first, 1)
        s.put(first, 2**40)  # the huge index
        s.put(first - NS_PER_S, 9)  # a step of an older incarnation
        s.step(first, 6)  # the run goes on
        wait_until(lambda: s.counters()["replayed_steps"] == 6 and s.counters()["step_jumps"] == 1, 5.0,
                   "replays and the jump counted")
        with s.lock:
            assert s.acks == [6]  # nothing refused was acknowledged
        assert s.probe.last_physics().sumo_step == 6 and s.counters()["sumo_restarts"] == 0
        # the SUMO side restarts: a newer epoch, step 0, the same vehicle ids (new vehicles)
        s.step(first + 30 * NS_PER_S, 0)
        wait_until(lambda: s.probe.last_physics().sumo_step == 0, 5.0, "the state of the new incarnation's step 0")
        c = s.counters()
        assert c["sumo_restarts"] == 1 and c["restarts"] == 1 and c["resyncs"] == 1
        assert c["placements"] == placed + 3  # the same ids, spawned and placed afresh
        assert "went back" not in s.daemon.tail(400)
        assert sorted(s.probe.last_physics().agents.ids) == ["veh0", "veh1", "veh2"]
    finally:
        assert s.close() == 0, s.daemon.tail()


def test_realtime_follower_publishes_no_state_after_the_final_step(tmp_path):
    s = FakeSumo(tmp_path, "final-rt", "realtime", follow=True)
    try:
        epoch = new_epoch()
        t0 = time.monotonic()
        for k in range(15):  # 10 Hz of wall time
            s.put(epoch, k, final=k == 14)
            time.sleep(max(0.0, t0 + (k + 1) * 0.1 - time.monotonic()))
        wait_until(lambda: s.probe.last_physics() is not None and s.probe.last_physics().sumo_step == 14, 10.0,
                   "the state of the final step", procs=[s.daemon])
        time.sleep(0.1)  # a state on its way
        with s.probe.lock:
            n0 = len(s.probe.physics["main"])
        time.sleep(1.5)  # 75 control ticks
        with s.probe.lock:
            after = len(s.probe.physics["main"]) - n0
        assert after == 0, f"{after} states published in 1.5 s after the final step"
        # the next run (a new incarnation) brings the states back
        s.put(new_epoch(), 0, prefix="car")
        wait_until(lambda: s.probe.last_physics().sumo_step == 0 and "car0" in s.probe.last_physics().agents.ids,
                   10.0, "states of the next run", procs=[s.daemon])
    finally:
        assert s.close() == 0, s.daemon.tail()


def test_a_shard_that_never_hears_its_sibling_takes_over_its_tiles(tmp_path):
    """Bench scale's take-over timed out once in two runs: in peer mode a shard hears a sibling
    leave only over a direct link; without one it kept the sibling's tiles forever. A sibling
    whose token never came within SIBLING_SEEN_S of the first step is taken as not running."""
    from physics_side.daemon import SIBLING_SEEN_S

    s = FakeSumo(tmp_path, "siblings", "lockstep", args=("--shard", "0/2"), instance="main.0of2")
    try:
        epoch = new_epoch()
        t0 = time.monotonic()
        k = 0
        s.step(epoch, k, n=40)
        wait_until(lambda: s.probe.last_physics("main.0of2").sumo_step == 0, 10.0, "the state of step 0")
        assert 0 < s.probe.last_physics("main.0of2").agents.n < 40  # its own tiles only
        while time.monotonic() - t0 < SIBLING_SEEN_S + 5.0:
            k += 1
            s.step(epoch, k, n=40)
            st = s.probe.last_physics("main.0of2")
            if st.sumo_step == k and st.agents.n == 40:
                break
            time.sleep(0.2)
        st = s.probe.last_physics("main.0of2")
        assert st.agents.n == 40 and st.counters["shard_siblings_unseen"] == 1 and st.counters["shards_alive"] == 1
        assert time.monotonic() - t0 >= SIBLING_SEEN_S - 1.0, "taken over before the siblings had a chance"
    finally:
        assert s.close() == 0, s.daemon.tail()
