"""Run incarnations and step order: which step a receiver takes (SPEC.md 3.1, "Epochs").

Every start of the SUMO side is one *incarnation* of a run, named by its ``epoch``: the
wall-clock start time of that process in nanoseconds since the Unix epoch, carried in every
step and in the static data. ``StepOrder`` is the receiver's rule, one verdict per step:

| verdict     | when                                                                  | receiver |
|-------------|-----------------------------------------------------------------------|----------|
| ``FIRST``   | the first step it sees (``missed`` > 0: it joined after step 0)        | apply |
| ``NEXT``    | same epoch, a higher step index within the jump bound                  | apply |
| ``RESTART`` | a newer epoch (a restarted SUMO side)                                  | reset, apply |
| ``DUPLICATE`` | same epoch, the step it has (a lockstep re-send)                     | ignore |
| ``REPLAY``  | same epoch and a lower step index, or an older epoch                   | reject, count |
| ``JUMP``    | a step index too far ahead (the bound below), or an epoch in the future | reject, count |

Jump bound: a SUMO side produces at most ``MAX_STEP_RATE_HZ`` steps per second of wall
clock, so a step index may exceed the last accepted one by at most ``JUMP_SLACK_STEPS`` plus
``MAX_STEP_RATE_HZ`` per second since that step was accepted, and (given its epoch, the
start time) the index itself is at most ``JUMP_SLACK_STEPS`` plus ``MAX_STEP_RATE_HZ`` per
second since the epoch began (clocks may differ by ``EPOCH_SKEW_S``). Steps without an
epoch (senders before 1.4, epoch 0) keep the old rule: a lower index is a restart.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from enum import Enum
from typing import Callable

NS_PER_S = 1_000_000_000
#: [steps/s of wall clock] more than any SUMO side publishes (an empty network's step ~0.1 ms)
MAX_STEP_RATE_HZ = 10_000
#: [steps] a jump always allowed on top of the rate (a receiver's own stalls, queue drops)
JUMP_SLACK_STEPS = 1_000
#: [s] how far the sender's clock may be ahead of the receiver's: an epoch further in the
#: future is refused (it would outrank every real restart)
EPOCH_SKEW_S = 300.0


def new_epoch(clock_ns: Callable[[], int] = time.time_ns) -> int:
    """The epoch of an incarnation starting now: wall-clock time [ns since the Unix epoch]."""
    return int(clock_ns())


class Verdict(Enum):
    FIRST = "first"
    NEXT = "next"
    RESTART = "restart"
    DUPLICATE = "duplicate"
    REPLAY = "replay"
    JUMP = "jump"

    @property
    def accepted(self) -> bool:
        return self in (Verdict.FIRST, Verdict.NEXT, Verdict.RESTART)


#: counter names of the refused verdicts (a receiver's counters)
COUNTER = {Verdict.DUPLICATE: "duplicate_steps", Verdict.REPLAY: "replayed_steps", Verdict.JUMP: "step_jumps"}


@dataclass
class StepOrder:
    """A receiver's view of the run's incarnation (see the module docstring)."""

    wall_ns: Callable[[], int] = time.time_ns
    """Wall clock [ns since the Unix epoch] (the epoch's clock)."""
    mono_s: Callable[[], float] = time.monotonic
    """Monotonic clock [s] (time since the last accepted step)."""
    epoch: int | None = None
    """Epoch of the incarnation followed (None before the first step)."""
    step: int = -1
    """Last accepted step index."""
    missed: int = 0
    """Steps of this incarnation before the first one received (a late join)."""
    restarts: int = 0
    counters: dict[str, int] = field(default_factory=lambda: {n: 0 for n in COUNTER.values()})
    why: str = ""
    """What the last refused verdict was about (for a log line)."""
    _accepted_at: float = 0.0

    def judge(self, epoch: int, step: int) -> Verdict:
        """The verdict for a step (see the table); accepted ones move the view forward,
        refused ones are counted in ``counters``."""
        v = self._verdict(int(epoch), int(step))
        if v.accepted:
            if v is not Verdict.NEXT:
                self.missed = step
                self.restarts += v is Verdict.RESTART
            self.epoch, self.step, self._accepted_at = int(epoch), int(step), self.mono_s()
        else:
            self.counters[COUNTER[v]] += 1
        return v

    def _verdict(self, epoch: int, step: int) -> Verdict:
        if epoch:
            since_epoch_s = (self.wall_ns() - epoch) / NS_PER_S
            if since_epoch_s < -EPOCH_SKEW_S:
                self.why = f"epoch {epoch} starts {-since_epoch_s:.0f} s in the future (> {EPOCH_SKEW_S:g} s)"
                return Verdict.JUMP
            bound = JUMP_SLACK_STEPS + MAX_STEP_RATE_HZ * max(0.0, since_epoch_s + EPOCH_SKEW_S)
            if step > bound:
                self.why = f"step {step} is more than a SUMO side makes {since_epoch_s:.0f} s after its epoch"
                return Verdict.JUMP
        if self.epoch is None:
            return Verdict.FIRST
        if epoch != self.epoch:
            if epoch > self.epoch or not self.epoch:
                return Verdict.RESTART
            self.why = f"epoch {epoch} is older than the current {self.epoch}"
            return Verdict.REPLAY
        if step == self.step:
            return Verdict.DUPLICATE
        if step < self.step:
            if not epoch:  # a sender without epochs: a lower index is its restart
                return Verdict.RESTART
            self.why = f"step {step} is behind step {self.step} of the same epoch"
            return Verdict.REPLAY
        ahead = JUMP_SLACK_STEPS + MAX_STEP_RATE_HZ * (self.mono_s() - self._accepted_at)
        if step - self.step > ahead:
            self.why = f"step {step} jumps {step - self.step} steps ahead of step {self.step} (> {ahead:.0f})"
            return Verdict.JUMP
        return Verdict.NEXT
