"""The receiver's step-order rule (protocol.order, SPEC 3.1.1): epochs, replays, jumps."""

from __future__ import annotations

import dataclasses

from protocol import decode, encode
from protocol.golden_vectors import EPOCH, valid_messages
from protocol.order import EPOCH_SKEW_S, JUMP_SLACK_STEPS, MAX_STEP_RATE_HZ, NS_PER_S, StepOrder, Verdict

T0 = EPOCH + 60 * NS_PER_S  # [ns] the receiver's wall clock: one minute into the golden run


class Clocks:
    def __init__(self) -> None:
        self.wall_ns, self.mono_s = T0, 100.0

    def order(self) -> StepOrder:
        return StepOrder(wall_ns=lambda: self.wall_ns, mono_s=lambda: self.mono_s)


def test_epoch_travels_in_steps_and_static_data():
    for name in ("step", "static"):
        msg = valid_messages()[name]
        assert decode(encode(msg)).epoch == EPOCH
    # a 1.3 sender has none: 0
    assert decode(encode(dataclasses.replace(valid_messages()["step"], epoch=0))).epoch == 0


def test_steps_of_one_incarnation_go_forward_and_replays_are_counted():
    c = Clocks()
    o = c.order()
    assert o.judge(EPOCH, 500) is Verdict.FIRST and o.missed == 500  # joined late: 500 steps missed
    for k in range(501, 505):
        assert o.judge(EPOCH, k) is Verdict.NEXT
    assert o.judge(EPOCH, 504) is Verdict.DUPLICATE  # a lockstep re-send
    for _ in range(5):  # the red team's replay: a step of 4.5 s before, five times
        assert o.judge(EPOCH, 459) is Verdict.REPLAY
    assert o.judge(EPOCH, 505) is Verdict.NEXT
    assert o.counters == {"duplicate_steps": 1, "replayed_steps": 5, "step_jumps": 0}
    assert o.step == 505 and o.epoch == EPOCH


def test_absurd_jumps_are_refused_and_the_bound_grows_with_the_wall_clock():
    c = Clocks()
    o = c.order()
    o.judge(EPOCH, 10)
    assert o.judge(EPOCH, 2**62) is Verdict.JUMP  # the huge index
    assert o.judge(EPOCH, 10 + JUMP_SLACK_STEPS + 1) is Verdict.JUMP
    c.mono_s += 1.0  # a second later a SUMO side may have made MAX_STEP_RATE_HZ more
    assert o.judge(EPOCH, 10 + JUMP_SLACK_STEPS + MAX_STEP_RATE_HZ) is Verdict.NEXT
    assert o.counters["step_jumps"] == 2
    # the first step of an incarnation: at most what a SUMO side makes since its epoch
    fresh = Clocks().order()
    assert fresh.judge(EPOCH, JUMP_SLACK_STEPS + MAX_STEP_RATE_HZ * int(60 + EPOCH_SKEW_S) + 10) is Verdict.JUMP


def test_a_newer_epoch_is_a_restart_an_older_one_a_replay_a_future_one_refused():
    c = Clocks()
    o = c.order()
    o.judge(EPOCH, 300)
    newer = EPOCH + 30 * NS_PER_S
    assert o.judge(newer, 0) is Verdict.RESTART and o.restarts == 1 and o.missed == 0
    assert o.judge(newer, 1) is Verdict.NEXT
    assert o.judge(EPOCH, 301) is Verdict.REPLAY  # the old incarnation's steps: replays now
    future = T0 + int((EPOCH_SKEW_S + 60) * NS_PER_S)
    assert o.judge(future, 0) is Verdict.JUMP  # would outrank every real restart
    assert o.epoch == newer and o.step == 1
    # restarted and joined late: the first step tells how many were missed
    later = EPOCH + 50 * NS_PER_S
    assert o.judge(later, 166) is Verdict.RESTART and o.missed == 166


def test_senders_without_epoch_keep_the_old_rule():
    o = Clocks().order()
    assert o.judge(0, 40) is Verdict.FIRST
    assert o.judge(0, 41) is Verdict.NEXT
    assert o.judge(0, 3) is Verdict.RESTART  # a lower index from a 1.3 sender: its restart
    assert o.judge(EPOCH, 0) is Verdict.RESTART  # an upgraded sender
    assert o.judge(0, 5) is Verdict.REPLAY  # and then no going back to steps without epoch
