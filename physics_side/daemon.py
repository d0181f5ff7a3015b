"""The physics side daemon: SUMO steps in, physics state out, over Zenoh.

``PhysicsDaemon`` is a thin orchestrator (like dm_control's ``Environment.step``): it
receives its Zenoh session, keys and a ``Fleet`` (world + controllers) from outside and
runs, per control tick: apply the latest SUMO step -> controllers -> MuJoCo substeps ->
publish. Timing:

- ``lockstep``: every step is processed in order; the daemon simulates up to the step's
  end time (``ticks_to``: any step length, 0.05 s steps at 50 Hz get 3, 2, 3, ... ticks),
  publishes, then acknowledges the step on ``Keys.ack`` (the SUMO side waits for it before
  the next step). The step length comes from each message; nothing needs to match it.
- ``realtime``: control ticks are paced by the wall clock; each tick uses the newest
  step received (older queued steps are skipped).

Liveliness: the daemon declares ``Keys.physics_alive`` and watches ``Keys.sumo_alive``.
When the SUMO side disappears every agent brakes to rest (mode STOPPING) and the daemon
waits; when it returns, the next step resynchronises the agent set (a step index that
goes backwards, e.g. a restarted SUMO at step 0, is a resync too).

Zenoh callbacks run on Zenoh's threads; they only append to bounded deques and set an
event. MuJoCo runs on the main thread only.
"""

from __future__ import annotations

import collections
import logging
import math
import faulthandler
import signal
import threading
import time
from dataclasses import replace

import numpy as np
import zenoh

from physics_side.config import PhysicsSettings, Rates, check_rates, load_physics_config, parse_expect, ticks_to
from physics_side.fleet import Fleet
from physics_side.cameras import ViewerCameras
from physics_side.lod import DetailSplit, DetailZones
from physics_side.shard import ShardFilter, parse_shard, shard_instance, shard_of_instance, subset
from physics_side.models import TYPE_NAMES
from physics_side.world import PhysicsWorld
from protocol.codec import decode_as, encode
from protocol.errors import ConfigError, ProtocolError
from protocol.keys import Keys
from protocol.messages import PhysicsAgents, PhysicsState, StaticData, StepAck, StepMessage
from protocol.order import StepOrder, Verdict
from protocol.tables import StaticTracker
from runtime.config import RunConfig
from runtime.queues import DropOldest
from runtime.transport import RingPoll, Wake

log = logging.getLogger("physics")

REJECT_LOG_PERIOD_S = 2.0  # [s] at most one log line per period about rejected messages
STATIC_QUERY_PERIOD_S = 1.0  # [s] at most one static-data query per period while a step's version is unknown
IDLE_WAIT_S = 0.05  # [s] wait for messages when there is nothing to simulate
REST_SPEED = 0.05  # [m/s] below this every stopping agent counts as at rest
SHUTDOWN_DUMP_S = 5.0  # [s] a shutdown longer than this dumps every thread's stack to stderr (the log)
OVERRUN_S = 0.25  # [s] realtime pacing this far behind the wall clock skips ahead (counted as an overrun)
DURATION_TOLERANCE_S = 1e-6  # [s] float rounding of SUMO times when the run's duration is checked
SIBLING_END_STEPS = 2.0  # [SUMO steps] a sibling shard that leaves this close to the run's end finished it
#: [s] after its first step a shard has seen every running sibling's liveliness token (peers
#: link to each other by gossip within ~2 s); a sibling never seen by then is taken as not
#: running and its tiles as this shard's: in peer mode a shard hears a sibling leave only over
#: a direct link, so without one it would never take over that sibling's agents
SIBLING_SEEN_S = 10.0
# Bounds of what Zenoh's threads hand over between two turns of the loop (oldest dropped)
ALIVE_EVENTS = 64  # [events] SUMO-side liveliness changes
SHARD_EVENTS = 256  # [events] sibling shards' liveliness changes
RATE_CACHE = 16  # [step lengths] checked clock ratios kept (a few per run at most)
MIB = 1 << 20  # [bytes]
MS_PER_S = 1e3
MIN_ELAPSED_S = 1e-9  # [s] a status line's period divides as at least this


class PhysicsDaemon:
    """Runs the physics side on an open Zenoh session (see module docstring)."""

    def __init__(
        self, session: zenoh.Session, keys: Keys, fleet: Fleet, settings: PhysicsSettings, run: RunConfig,
        shard: ShardFilter | None = None,
    ):
        """``shard``: simulate only this shard's agents (``--shard i/k``); None = all."""
        self.session = session
        self.shard = shard
        zones = DetailZones.from_config(settings.physics.lod_radius_m, settings.physics.lod_regions)
        # far agents extrapolate as far as the fleet's reference does (steps of 0.1 s assumed
        # until the first step tells the step length)
        self.detail = None if zones is None else DetailSplit(
            zones, settings.physics.max_extrapolation_steps * settings.physics.sumo_step_s)
        self.cameras = ViewerCameras()  # viewer cameras: interest points of the detail zones
        self._shard_events: collections.deque[tuple[str, bool]] = collections.deque(maxlen=SHARD_EVENTS)
        self.keys = keys
        self.fleet = fleet
        self.settings = settings
        self.cfg = settings.physics
        self.run_cfg = run
        self.lockstep = run.timing == "lockstep"
        self.rates = fleet.rates
        self._limits = run.decode_limits
        # Bounded in messages and bytes (SPEC 5.1): full -> the oldest step is dropped, counted.
        self._steps: DropOldest[bytes] = DropOldest(self.cfg.step_queue, int(self.cfg.step_queue_mb * MIB))
        # vType table between steps (protocol 1.2 sends it only when it changes); a static
        # reply lands here from a Zenoh thread, newest only
        self._tables = StaticTracker()
        self._static_replies: collections.deque[bytes] = collections.deque(maxlen=1)
        self._static_asked = -math.inf
        self._alive_events: collections.deque[bool] = collections.deque(maxlen=ALIVE_EVENTS)
        self._wake = Wake()  # (a C-level lock: cheaper than Event after an idle wait)
        self._poll: RingPoll | None = None  # physics.busy_poll_ms: the step subscriber's ring
        self._stop = threading.Event()
        self.counters: dict[str, int] = {"rejected": 0, "dropped_steps": 0, "acks": 0, "states": 0,
                                         "static_queries": 0}
        self.sumo_present = False
        self._seen_sumo = False
        self._resync = False
        self._last_step = -1
        # which incarnation of the run it follows; steps of an older one, or out of order, or
        # too far ahead are refused and counted (SPEC 3.1.1)
        self.order = StepOrder()
        self._run_over = False  # the followed incarnation sent its final step: no ticks, no states
        self._rate_cache: dict[float, Rates] = {}
        self._reject_log_t = 0.0
        self._reject_since_log = 0
        self._status = _Status()
        self.time = 0.0  # [s] physics time aligned with SUMO time
        self._declared: list = []
        self._finished = False
        self._begin: float | None = None  # [s] SUMO time before the first step applied
        self._siblings_seen: set[int] = set()  # sibling shards whose liveliness token came
        self._first_step_at: float | None = None  # monotonic [s] of the first step (shards)
        self._siblings_checked = False

    # ------------------------------------------------------------------ zenoh plumbing

    def _on_step(self, sample: zenoh.Sample) -> None:
        self._steps.put(sample.payload.to_bytes())
        self.counters["dropped_steps"] = self._steps.dropped + self._steps.refused
        self._wake.set()

    def _on_alive(self, sample: zenoh.Sample) -> None:
        self._alive_events.append(sample.kind == zenoh.SampleKind.PUT)
        self._wake.set()

    def _on_peer_alive(self, sample: zenoh.Sample) -> None:
        self._shard_events.append((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))
        self._wake.set()

    def start(self) -> "PhysicsDaemon":
        s = self.session
        cc = zenoh.CongestionControl.BLOCK if self.lockstep else zenoh.CongestionControl.DROP
        self._pub_state = s.declare_publisher(self.keys.physics_state, congestion_control=cc)
        self._pub_ack = s.declare_publisher(self.keys.ack, congestion_control=zenoh.CongestionControl.BLOCK)
        self._pub_feedback = s.declare_publisher(self.keys.feedback, congestion_control=zenoh.CongestionControl.BLOCK)
        if self.cfg.busy_poll_ms > 0:  # steps from a ring the loop polls (``_idle``), no wake-up per step
            self._poll = RingPoll(s, self.keys.step, self.cfg.step_queue, self.cfg.busy_poll_ms / MS_PER_S,
                                  self._on_step)
            self._sub_step = self._poll
            log.info("steps busy-polled for up to %g ms after each acknowledgement", self.cfg.busy_poll_ms)
        else:
            self._sub_step = s.declare_subscriber(self.keys.step, self._on_step)
        self._sub_alive = s.liveliness().declare_subscriber(self.keys.sumo_alive, self._on_alive, history=True)
        self._token = s.liveliness().declare_token(self.keys.physics_alive)
        self._declared = [self._token, self._sub_alive, self._sub_step, self._pub_ack, self._pub_state,
                          self._pub_feedback]
        if self.detail is not None:
            self._declared += [s.declare_subscriber(self.keys.viewer_camera_all, self.cameras.on_camera),
                               s.liveliness().declare_subscriber(self.keys.viewer_alive_all, self.cameras.on_alive)]
        if self.shard is not None:  # sibling shards: a lost one's tiles go to the survivors
            self._declared.append(s.liveliness().declare_subscriber(
                self.keys.physics_alive_all, self._on_peer_alive, history=True))
        log.info(
            "physics %s/%s: %s, preset %s%s, control %g Hz, %d substeps of %g s, %d shard(s)",
            self.keys.run, self.keys.physics, self.run_cfg.timing, self.cfg.preset,
            f" {self.cfg.presets}" if self.cfg.presets else "", self.cfg.control_hz, self.rates.substeps,
            self.cfg.timestep_s, self.fleet.world.shards,
        )
        return self

    def close(self) -> None:
        for d in self._declared:
            try:
                d.undeclare()
            except Exception:  # already gone with the session
                pass
        self._declared = []

    def stop(self) -> None:
        """Ask the run loop to return (thread- and signal-safe)."""
        self._stop.set()
        self._wake.set()

    # ------------------------------------------------------------------ messages

    def _reject(self, why: str, counter: str = "rejected") -> None:
        """Count a refused message (in ``counter``) and log it, at most once per REJECT_LOG_PERIOD_S."""
        if counter in self.counters:
            self.counters[counter] += 1
        self._reject_since_log += 1
        now = time.monotonic()
        if now - self._reject_log_t >= REJECT_LOG_PERIOD_S:
            log.warning("rejected %d message(s); latest: %s", self._reject_since_log, why)
            self._reject_log_t = now
            self._reject_since_log = 0

    def _on_static_reply(self, reply) -> None:
        if reply.ok is not None:
            self._static_replies.append(reply.ok.payload.to_bytes())

    def _resolve_vtypes(self, msg: StepMessage) -> StepMessage:
        """Fill in the vType table; query the static data when this step's version is unknown."""
        while self._static_replies:
            try:
                self._tables.on_static(decode_as(self._static_replies.popleft(), StaticData))
            except ProtocolError as e:
                self._reject(f"static data: {e}")
        msg = self._tables.resolve(msg)
        now = time.monotonic()
        if self._tables.stale and now - self._static_asked >= STATIC_QUERY_PERIOD_S:
            log.info("step %d refers to static version %d: querying the static data", msg.step, msg.static_version)
            self._ask_static()
        return msg

    def _ask_static(self) -> None:
        """One static-data query; the reply comes on Zenoh's thread (the loop never waits)."""
        self._static_asked = time.monotonic()
        self.counters["static_queries"] += 1
        try:
            self.session.get(self.keys.static, self._on_static_reply, timeout=STATIC_QUERY_PERIOD_S)
        except Exception as e:  # a closing session; the next stale step asks again
            log.debug("static query failed: %s", e)

    def _decode(self, data: bytes) -> StepMessage | None:
        try:
            msg = decode_as(data, StepMessage, self._limits)
        except ProtocolError as e:
            self._reject(str(e))
            return None
        if msg.epoch > (self.order.epoch or 0):
            # a newer incarnation numbers its static versions afresh: forget the old tables
            # (an older epoch is refused in _apply and leaves them alone)
            self._tables = StaticTracker()
        msg = self._resolve_vtypes(msg)
        rates = self._rate_cache.get(msg.step_length)
        if rates is None:
            try:
                rates = check_rates(msg.step_length, self.cfg.control_hz, self.cfg.timestep_s)
            except ConfigError as e:
                self._reject(f"step {msg.step}: {e}")
                return None
            if len(self._rate_cache) >= RATE_CACHE:
                self._rate_cache.clear()
            log.info("SUMO step length %g s: %.3g control ticks of %g s per step",
                     msg.step_length, msg.step_length / rates.control_dt, rates.control_dt)
            self._rate_cache[msg.step_length] = rates
        return msg

    def _handle_alive(self) -> None:
        while self._alive_events:
            up = self._alive_events.popleft()
            if up and not self.sumo_present:
                log.info("SUMO side is up%s", " again: resynchronising" if self._seen_sumo else "")
                self._resync = self._seen_sumo
                self._seen_sumo = True
                self.sumo_present = True
            elif not up and self.sumo_present:
                log.warning("SUMO side is gone: bringing %d agents to a safe stop", self.fleet.n)
                self.sumo_present = False
                self.fleet.begin_stop()

    def _handle_shards(self) -> None:
        mine = shard_of_instance(self.keys.physics)
        while self._shard_events:
            key, up = self._shard_events.popleft()
            other = shard_of_instance(Keys.instance_of(key))
            if mine is None or other is None or other[0] != mine[0] or other[2] != mine[2]:
                continue
            if up:
                self._siblings_seen.add(other[1])
            if not up and self._duration_done(self.time + SIBLING_END_STEPS * self.fleet.step_length):
                continue  # a sibling that finished the run's last step leaves: nothing to take over
            if self.shard.set_alive(other[1], up):
                log.warning("shard %d/%d %s: %d of %d shards alive (%s)", other[1], other[2],
                            "is back" if up else "is gone, taking over its tiles", len(self.shard.living),
                            self.shard.count, ", ".join(map(str, self.shard.living)))
        if mine is not None:
            self._check_siblings_seen(mine)

    def _check_siblings_seen(self, mine: tuple[str, int, int]) -> None:
        """Once, SIBLING_SEEN_S after the first step: siblings never seen are not running."""
        now = time.monotonic()
        if self._first_step_at is None:
            self._first_step_at = now
        if self._siblings_checked or now - self._first_step_at < SIBLING_SEEN_S:
            return
        self._siblings_checked = True
        unseen = [i for i in self.shard.living if i != mine[1] and i not in self._siblings_seen]
        for i in unseen:
            self.shard.set_alive(i, False)
        self.counters["shard_siblings_unseen"] = len(unseen)
        if unseen:
            log.warning("shard(s) %s of %d never seen %g s after the first step (no liveliness token: not "
                        "running, or no direct link to this shard): taking over their tiles; peers of one run "
                        "must all link to each other (gossip on, or connect every shard to every other, or a router)",
                        ", ".join(map(str, unseen)), self.shard.count, SIBLING_SEEN_S)

    def handle_step(self, payload: bytes) -> StepMessage | None:
        """One step as it arrives on ``Keys.step``: decoded, its vTypes resolved, applied to the
        fleet. Returns it, or None when it was rejected (counted) or a duplicate."""
        msg = self._decode(payload)
        if msg is None or not self._apply(msg):
            return None
        return msg

    def _apply(self, msg: StepMessage) -> bool:
        """Apply one step; False if it was a duplicate and ignored, or refused (SPEC 3.1.1)."""
        verdict = self.order.judge(msg.epoch, msg.step)  # first: a refused step changes nothing
        if verdict is Verdict.DUPLICATE:
            return False  # a lockstep re-send of the step it has
        if not verdict.accepted:
            # counted by the order rule (replayed_steps, step_jumps), not as malformed
            self._reject(f"step {msg.step} of epoch {msg.epoch} ({verdict.value}): {self.order.why}", counter="")
            return False
        if self.shard is not None:
            self._handle_shards()
            # every size of the step gets a pool (compiled in the background): taking over a
            # lost shard's agents then spawns them without a compile on this thread
            self.fleet.reserve(msg.agents, msg.vtypes)
            msg = replace(msg, agents=subset(msg.agents, self.shard.rows(msg.agents)))
        if self.detail is not None:  # agents outside every detail zone never enter MuJoCo
            self.detail.points = self.cameras.points()
            msg = self.detail.apply(msg)
        resync = self._resync
        restart = verdict is Verdict.RESTART
        if restart:
            log.warning("SUMO side restarted: epoch %d, first step %d%s: resetting the fleet", msg.epoch, msg.step,
                        f" ({msg.step} steps missed)" if msg.step else "")
            resync = True
        elif verdict is Verdict.FIRST and msg.step:
            log.info("joined epoch %d at step %d (%d steps missed)", msg.epoch, msg.step, msg.step)
        # Physics time only moves forward, one control period per tick: in lockstep it stays
        # within dt/2 of SUMO's step end; in realtime the wall clock paces it and a step may
        # arrive a tick early or late (then the reference is extrapolated from it by the
        # difference). Setting it back to each step's time made two states share one time.
        # It jumps (forward) when physics is behind, and restarts after a resync or when it
        # ran further ahead than the extrapolation limit (a stalled SUMO side).
        # Interpolating, physics covers (previous step, this step]: it starts a step length back.
        start = msg.time - (msg.step_length if self.fleet.interpolates(msg.step_length) else 0.0)
        ahead = self.time - start
        limit = self.cfg.max_extrapolation_steps * msg.step_length
        fresh = resync or ahead < -self.fleet.dt or ahead > limit
        try:
            stats = self.fleet.apply_step(msg, resync=resync, tau=0.0 if fresh else ahead, restart=restart)
        except (ValueError, IndexError, KeyError) as e:
            self._reject(f"step {msg.step}: {type(e).__name__}: {e}")
            return False
        if resync or self._begin is None:
            # Durations count from the scenario's begin (SUMO time before the first step).
            self._begin = msg.time - msg.step_length
        self._resync = False
        self._run_over = False
        self._last_step = msg.step
        if fresh:
            self.time = start
        self.fleet.rates = self._rate_cache[msg.step_length]
        if stats.spawned or stats.parked:
            log.debug("step %d: +%d -%d agents (%d)", msg.step, stats.spawned, stats.parked, self.fleet.n)
        return True

    # ------------------------------------------------------------------ tick

    def _tick(self) -> None:
        t0 = time.perf_counter()
        m0 = self.fleet.world.mujoco_s
        self.fleet.tick()
        self.time += self.fleet.dt
        if self.fleet.tick_count % self.cfg.state_every == 0:
            self._publish_state()
        self._status.tick(time.perf_counter() - t0, self.fleet.world.mujoco_s - m0)

    def all_counters(self) -> dict[str, int]:
        c = dict(self.fleet.world.counters)
        c.update(self.fleet.counters)
        c.update(self.counters)
        c.update(self.order.counters)
        c["sumo_restarts"] = self.order.restarts
        c.update(self.fleet.mode_counts())
        if self.detail is not None:
            c["kinematic"] = c.get("kinematic", 0) + self.detail.far.n
            c["lod_far"] = self.detail.far.n
            c["viewer_cameras"] = len(self.cameras)
            c["rejected_cameras"] = self.cameras.rejected + self.cameras.refused
            c["evicted_cameras"] = self.cameras.evicted
        if self.shard is not None:
            c["shards_alive"] = len(self.shard.living)
            c["shard_takeovers"] = self.shard.takeovers
        return c

    def snapshot(self) -> PhysicsAgents:
        """Every agent as the next state message publishes it: the fleet's, then those outside
        every detail zone (mode KINEMATIC)."""
        near = self.fleet.snapshot()
        return near if self.detail is None else self.detail.snapshot(near, self.time)

    def _publish_state(self) -> None:
        msg = PhysicsState(
            run=self.keys.run, tick=self.fleet.tick_count, time=self.time, sumo_step=self._last_step,
            agents=self.snapshot(), counters=self.all_counters(),
        )
        self._pub_state.put(encode(msg))
        self.counters["states"] += 1

    def _ack(self, step: int) -> None:
        fb = self.fleet.two_way
        if fb:  # two-way coupling: the physical states SUMO writes back, before the ack (SPEC 3.8)
            self._pub_feedback.put(encode(self.fleet.feedback(self.keys.run, step, self.time)))
            self.counters["feedback"] = self.counters.get("feedback", 0) + 1
        self._pub_ack.put(encode(StepAck(self.keys.run, step, self.fleet.tick_count, feedback=fb)))
        self.counters["acks"] += 1

    def _at_rest(self) -> bool:
        if self.fleet.n == 0:
            return True
        snap_speed = self.fleet.world.observe(self.fleet.slots).speed
        return bool(np.all(np.abs(snap_speed) < REST_SPEED))

    def _duration_done(self, sumo_time: float | None = None) -> bool:
        """The run's duration has passed since the begin time (at ``sumo_time``, default now)."""
        d = self.run_cfg.duration_s
        t = self.time if sumo_time is None else sumo_time
        return bool(d) and self._begin is not None and t - self._begin >= d - DURATION_TOLERANCE_S

    # ------------------------------------------------------------------ loops

    def run(self, max_wall_s: float | None = None) -> int:
        """Run until stopped (signal, ``stop()``), the run's duration, or ``max_wall_s``."""
        t_end = None if max_wall_s is None else time.monotonic() + max_wall_s
        next_tick = time.monotonic()
        while not self._stop.is_set():
            if t_end is not None and time.monotonic() > t_end:
                break
            self._handle_alive()
            self._status.maybe_log(self.fleet, self.all_counters)  # counted only when it logs: a step waits behind this
            if self._poll is not None:
                self._poll.pull()
            if self._run_over and not self._steps:
                # after the final step (following the next run): nothing to simulate or publish
                # until a step of a new incarnation arrives
                self._idle()
                next_tick = time.monotonic()
                continue
            if (not self.sumo_present and self.fleet.stopping and self.fleet.n and not self._at_rest()
                    and not self._steps):
                # SUMO gone: keep simulating at the control rate until every agent is at rest
                # (steps that came before it left go first: the final one ends the run)
                next_tick = self._pace(next_tick)
                self._tick()
                continue
            if self.lockstep:
                if not self._steps:
                    self._idle()
                    continue
                msg = self.handle_step(self._steps.get())
                if msg is None:
                    continue
                end = msg.time + msg.step_length - self.fleet.lag
                for _ in range(ticks_to(self.time, end, self.fleet.dt)):
                    self._tick()
                self._ack(msg.step)
                if self._poll is not None:
                    self._poll.arm()  # the next step is due once SUMO has stepped
                # The SUMO side ends on the same step: it marks it final, and it applies the
                # same duration rule to the same SUMO time.
                if (msg.final and not self.cfg.follow_next_run) or self._duration_done(msg.time):
                    log.info("last step %d at t=%.1f s (%s)", msg.step, msg.time,
                             "marked final" if msg.final else f"duration {self.run_cfg.duration_s:g} s")
                    break
                if msg.final:
                    self._end_of_run(msg)
                elif not self.sumo_present:
                    self.fleet.begin_stop()  # a step that came before SUMO left: stop after it
            else:
                newest = None
                while self._steps:
                    m = self._decode(self._steps.get())
                    if m is not None:
                        newest = m
                if newest is not None and self._apply(newest):
                    self._ack(newest.step)
                    if newest.final and not self.cfg.follow_next_run:
                        log.info("last step %d at t=%.1f s (marked final)", newest.step, newest.time)
                        break
                    if newest.final:
                        self._end_of_run(newest)
                        continue
                    if not self.sumo_present:
                        self.fleet.begin_stop()  # a step that came before SUMO left: stop after it
                if self.fleet.ref is None and not self.fleet.n:
                    self._idle()
                    next_tick = time.monotonic()
                    continue
                next_tick = self._pace(next_tick)
                self._tick()
                if self._duration_done():
                    log.info("duration %.1f s reached", self.run_cfg.duration_s)
                    break
        self._status.maybe_log(self.fleet, self.all_counters(), force=True)
        return 0

    def _idle(self) -> None:
        """Wait (at most IDLE_WAIT_S) for a message: woken by a callback, or polling the step
        ring (``physics.busy_poll_ms``: spinning within its window after an ack)."""
        if self._poll is not None:
            self._poll.wait(self._stop, IDLE_WAIT_S, self._wake)
        else:
            self._wake.wait(IDLE_WAIT_S)
        self._wake.clear()

    def _end_of_run(self, msg: StepMessage) -> None:
        """The followed incarnation's final step while following the next run: one last state,
        then no ticks and no states until a new incarnation's step (SPEC 3.1)."""
        self._publish_state()
        self._run_over = True
        log.info("last step %d at t=%.1f s (marked final): waiting for the next run", msg.step, msg.time)

    def _pace(self, next_tick: float) -> float:
        """Sleep until the next control tick (wall clock); skip ahead when far behind."""
        now = time.monotonic()
        if next_tick > now:
            # wake early for messages only in realtime; steps are applied at tick boundaries
            self._stop.wait(next_tick - now)
        elif now - next_tick > OVERRUN_S:
            self._status.overruns += 1
            next_tick = now
        return next_tick + self.fleet.dt


class _Status:
    """Once-per-second INFO status line."""

    def __init__(self) -> None:
        self.t0 = time.monotonic()
        self.ticks = 0
        self.tick_s = 0.0
        self.mujoco_s = 0.0
        self.overruns = 0

    def tick(self, dt: float, mj: float) -> None:
        self.ticks += 1
        self.tick_s += dt
        self.mujoco_s += mj

    def maybe_log(self, fleet: Fleet, counters, force: bool = False, period: float = 1.0) -> None:
        """``counters``: a dict, or a function returning one (called only when logging)."""
        now = time.monotonic()
        el = now - self.t0
        if el < period and not force:
            return
        if callable(counters):
            counters = counters()
        if self.ticks or force:
            n = max(self.ticks, 1)
            log.info(
                "%.0f ticks/s | agents %d (phys %d kin %d ext %d stop %d) | tick %.2f ms (mujoco %.2f, "
                "overhead %.2f) | step %d | collisions %d placements %d rejected %d%s",
                self.ticks / max(el, MIN_ELAPSED_S), fleet.n, counters.get("physical", 0),
                counters.get("kinematic", 0), counters.get("external", 0), counters.get("stopping", 0),
                MS_PER_S * self.tick_s / n, MS_PER_S * self.mujoco_s / n, MS_PER_S * (self.tick_s - self.mujoco_s) / n,
                fleet.sumo_step,
                counters.get("collisions", 0), counters.get("placements", 0), counters.get("rejected", 0),
                f" | overruns {self.overruns}" if self.overruns else "",
            )
        self.t0 = now
        self.ticks = 0
        self.tick_s = 0.0
        self.mujoco_s = 0.0


def build_fleet(settings: PhysicsSettings, realtime: bool = False) -> Fleet:
    """World (pools sized up front) + fleet for a config. ``realtime``: switch to a model
    grown in the background as soon as it is ready (lockstep: when a pool runs out)."""
    cfg = settings.physics
    rates = check_rates(cfg.sumo_step_s, cfg.control_hz, cfg.timestep_s)
    initial = {TYPE_NAMES[k]: v for k, v in cfg.initial_slots.items()}
    expect = {TYPE_NAMES[k]: v for k, v in cfg.expect.items()}
    awd = frozenset(TYPE_NAMES[k] for k in cfg.all_wheel_drive)
    world = PhysicsWorld(
        cfg.timestep_s, rates.substeps, shards=cfg.shards, threads=cfg.threads, initial=initial,
        pool_chunk=cfg.pool_chunk, awd=awd, expect=expect, adopt_early=realtime,
    )
    return Fleet(world, settings, rates)


def cli_main(args) -> int:
    """``sumoco physics --config X.toml [--preset P] [--instance I] [--listen ...] [--timing ...]``."""
    from runtime.config import apply_cli, load_common
    from runtime.hotpath import freeze_startup_objects, tune_allocator
    from runtime.transport import open_session

    if not args.config:
        raise ConfigError("sumoco physics: --config is required")
    common, data, base = load_common(args.config)
    common = apply_cli(common, args)
    settings = load_physics_config(data, base, str(args.config))
    phys = settings.physics
    if getattr(args, "preset", None):
        if args.preset not in ("paper", "default", "kinematic"):
            raise ConfigError(f"--preset: expected paper, default or kinematic, got {args.preset!r}")
        phys = replace(phys, preset=args.preset, presets={})
    if getattr(args, "instance", None):
        phys = replace(phys, instance=args.instance)
    if getattr(args, "expect", None):
        phys = replace(phys, expect=parse_expect(args.expect))
    shard = None
    if getattr(args, "shard", None):
        i, k = parse_shard(args.shard)
        shard = ShardFilter(i, k, phys.shard_tile_m, phys.shard_halo_m)
        phys = replace(phys, instance=shard_instance(phys.instance, i, k))
    settings = replace(settings, physics=phys)
    keys = Keys(common.zenoh.root, common.run.id, phys.instance)
    fleet = build_fleet(settings, realtime=common.run.timing == "realtime")
    # two-way coupling: is this the instance SUMO follows ([coupling] instance, or the default preset's)?
    fleet.two_way = common.coupling.follows(phys.instance, phys.preset)
    if fleet.two_way:
        log.info("two-way coupling: %s drives the physics-authoritative vehicles; SUMO follows it", phys.instance)
    tune_allocator()
    freeze_startup_objects()
    old = {}
    try:
        with open_session(common.zenoh, role="physics") as session:
            daemon = PhysicsDaemon(session, keys, fleet, settings, common.run, shard=shard).start()

            def _handler(signum, frame):
                log.info("signal %d: shutting down", signum)
                daemon.stop()

            for sig in (signal.SIGTERM, signal.SIGINT):
                old[sig] = signal.signal(sig, _handler)
            try:
                return daemon.run()
            finally:
                # A shutdown that hangs leaves every thread's stack in the log (stderr)
                faulthandler.dump_traceback_later(SHUTDOWN_DUMP_S, exit=False)
                daemon.close()
                fleet.world.close()
    finally:
        faulthandler.cancel_dump_traceback_later()
        # Restored only after the session closed: a SIGTERM during that shutdown (the run
        # already ended) must not kill the process with -15.
        for sig, h in old.items():
            signal.signal(sig, h)


__all__ = ["PhysicsDaemon", "build_fleet", "cli_main"]
