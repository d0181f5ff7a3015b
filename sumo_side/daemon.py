"""The SUMO side daemon: step SUMO, publish one message per step, serve static data.

``SumoDaemon`` receives everything it uses (Zenoh session, keys, a started ``SumoSim``,
configs, clock) so tests can drive it with a loopback session; ``cli_main`` is the only
place that reads files and command-line arguments.

Per step (main thread only; libsumo is not thread-safe):

1. drain ego poses (``EgoInbox``: the newest poses only, each refused by its length when too big) and apply them (``moveToXY``);
2. ``simulationStep`` (timed as ``sumo_ms``);
3. read all agents, look-ahead points and paths, encode, publish (``bridge_ms``);
4. pace: wall-clock deadlines ``t0 + (k+1) * step_length`` (realtime) or wait for the
   acknowledgement of step k from every physics instance listed in
   ``[sumo] lockstep_instances`` (lockstep; bounded by ``[run] lockstep_timeout_s``).

Lockstep is pipelined: steps 1-3 of step k+1 run while the physics side works on step k,
and step k+1 goes out as soon as step k is acknowledged (the SUMO side and the physics
side are separate processes, so SUMO's step and the physics ticks overlap in wall clock).
No step is published before the acknowledgements of the one before it (SPEC.md 3.4).
While an ego vehicle is active the next step is computed only after the
acknowledgements, so that the poses received meanwhile move the ego in it.

Zenoh callbacks never touch SUMO: the static-data queryable replies with bytes encoded
once at start, the ack callback only enqueues payloads for the main loop.
"""

from __future__ import annotations

import collections
import gc
import json
import logging
import re
import math
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import zenoh

from protocol.codec import decode, encode
from protocol.errors import ConfigError, ProtocolError, SumocoError
from protocol.keys import Keys
from protocol.messages import EgoPose, StepAck, SumoStatus
from protocol.order import new_epoch
from sumo_side.bridge import Bridge
from sumo_side.config import SumoConfig, sumo_config_from
from sumo_side.coupling import SumoCoupling
from sumo_side.ego import EgoManager
from sumo_side.mapmesh import MapService
from sumo_side.simulation import SumoSim
from runtime.queues import LatestPerKey
from runtime.config import CommonConfig, CouplingConfig, RunConfig, apply_cli, load_common, replace

log = logging.getLogger("sumo_side")

STATIC_REENCODE_PERIOD_S = 1.0  # [s] at most one re-encoding of the static data per period


#: An acknowledgement is ~40 bytes; bigger payloads on an ack key are refused unread [bytes].
MAX_ACK_BYTES = 1024
#: An ego pose is ~100 bytes (a vType name of 1,024 characters at most): bigger payloads on an
#: ego key are refused by their length, before they are copied or decoded [bytes].
MAX_EGO_BYTES = 4096
#: Ego poses waiting for the main loop (newest kept: one pose per ego is applied per step) [poses]
EGO_INBOX = 256


class EgoInbox:
    """Ego poses from Zenoh's threads to the main loop: the newest ``size`` (key, payload),
    each at most ``max_bytes`` (a bigger one is counted in ``oversized`` and never copied).
    Held payloads are bounded by ``size`` x ``max_bytes`` (1 MiB), whatever a sender puts."""

    def __init__(self, size: int = EGO_INBOX, max_bytes: int = MAX_EGO_BYTES) -> None:
        self._q: collections.deque[tuple[str, bytes]] = collections.deque(maxlen=size)
        self.max_bytes = max_bytes
        self.oversized = 0
        self.dropped = 0  # the oldest pose made room for a newer one

    def on_sample(self, sample: zenoh.Sample) -> None:
        if len(sample.payload) > self.max_bytes:
            self.oversized += 1
            return
        if len(self._q) == self._q.maxlen:
            self.dropped += 1
        self._q.append((str(sample.key_expr), sample.payload.to_bytes()))

    def try_recv(self) -> tuple[str, bytes] | None:
        try:
            return self._q.popleft()
        except IndexError:
            return None


class LockstepTimeout(SumocoError):
    """No acknowledgement from a physics instance within ``lockstep_timeout_s``."""


class HotLoopGC:
    """Keep Python's cyclic garbage collector out of the per-step hot path.

    Each step creates thousands of short-lived dicts (libsumo's subscription results),
    which triggers generation-0/1/2 collections in the middle of reading; measured at
    2,500 vehicles that costs ~1.5 ms per step. Objects from start-up (lane graph, ...)
    are frozen out of collections, automatic collection is off during the loop and
    ``tick()`` collects explicitly once per status period (between steps).
    """

    def __init__(self) -> None:
        self.collect_ms = 0.0
        self._was_enabled = gc.isenabled()

    def __enter__(self) -> "HotLoopGC":
        gc.collect()
        gc.freeze()
        gc.disable()
        return self

    def tick(self) -> None:
        t0 = time.perf_counter()
        gc.collect()
        self.collect_ms = (time.perf_counter() - t0) * 1e3

    def __exit__(self, *exc) -> None:
        gc.unfreeze()
        if self._was_enabled:
            gc.enable()


@dataclass
class _Period:
    """Statistics of one status period."""

    t0: float
    steps: int = 0
    sumo_s: float = 0.0
    bridge_s: float = 0.0
    wait_s: float = 0.0


@dataclass
class Counters:
    steps: int = 0
    rejected: int = 0  # malformed or foreign incoming messages
    acks: int = 0
    lag_resets: int = 0  # realtime: SUMO fell behind the wall clock by more than max_lag_s
    rejoined: int = 0  # lockstep: awaited physics instances that left and came back
    strict_steps: int = 0  # lockstep: steps computed only after the previous step's acks (an ego was active)
    max_agents: int = 0
    static_versions: int = 0  # static data re-encoded for a new static version
    extra: dict = field(default_factory=dict)


class SumoDaemon:
    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        sim: SumoSim,
        cfg: SumoConfig,
        run: RunConfig,
        clock: Callable[[], float] = time.monotonic,
        pipeline: bool = True,
        coupling: CouplingConfig | None = None,
    ) -> None:
        """``pipeline``: in lockstep, compute step k+1 while the physics side works on step k
        (published only after its acknowledgements); False computes it after them.
        ``coupling``: who owns each vehicle's motion (``[coupling]``; default: SUMO, shadow mode)."""
        self.session = session
        self.keys = keys
        self.sim = sim
        self.cfg = cfg
        self.run_cfg = run
        self.clock = clock
        self.pipeline = pipeline
        # this incarnation of the run: in every step and in the static data (SPEC 3.1.1)
        self.epoch = new_epoch()
        self.bridge = Bridge(sim, cfg, run.id, self.epoch)
        self.ego = EgoManager(sim.api, cfg, clock)
        self.counters = Counters()
        self._egos = EgoInbox()  # ego poses, refused by length before they are copied (SPEC 5.1)
        self._stop = threading.Event()
        # Bounded hand-over from Zenoh's threads (SPEC 5.1): the newest ack and liveliness
        # change per key, at most [sumo] max_peer_keys keys (more are refused, counted).
        waited = [Keys(keys.root, keys.run, i) for i in cfg.lockstep_instances]
        self._acks: LatestPerKey[bytes] = LatestPerKey(cfg.max_peer_keys, frozenset(k.ack for k in waited))
        self._acked: dict[str, int] = {}
        self._alive_events: LatestPerKey[bool] = LatestPerKey(
            cfg.max_peer_keys, frozenset(k.physics_alive for k in waited))
        self._alive: set[str] = set()
        self._waited = list(cfg.lockstep_instances)  # shrinks when a physics shard is lost
        self._awaited = frozenset(cfg.lockstep_instances)  # the only instances whose acks and tokens are kept
        self._lost: dict[str, float] = {}  # awaited instances whose token went: clock() when
        self._last_reject_log = -math.inf
        self._limits = run.decode_limits  # acks and ego poses are small: any bound holds them
        # two-way coupling: physical states of physics-authoritative vehicles written back
        self.coupling = SumoCoupling(coupling or CouplingConfig(), sim, keys, self._limits, self._reject)
        self._static_bytes = encode(replace(sim.static_data(), epoch=self.epoch))
        self._static_version = sim.static_version
        self._static_encoded_at = -math.inf
        self.map = MapService(getattr(sim, "net_file", None), run.id)
        self.last_message = None  # the newest StepMessage (tests, status)
        self.end_reason = ""  # why the run ended ('' while running or when it failed)

    # ------------------------------------------------------------------ control

    def request_stop(self) -> None:
        """Stop after the current step (signal handlers, tests); thread-safe."""
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def _refresh_static(self, version: int) -> None:
        """Serve the static data of a new static version (re-encoded at most once per
        STATIC_REENCODE_PERIOD_S; a querier that gets an older version asks again)."""
        now = time.monotonic()
        if version == self._static_version or now - self._static_encoded_at < STATIC_REENCODE_PERIOD_S:
            return
        data = encode(replace(self.sim.static_data(), epoch=self.epoch))
        self._static_bytes = data  # one reference swap: the queryable thread reads either
        self._static_version = version
        self._static_encoded_at = now
        self.counters.static_versions += 1
        log.info("static version %d: %d vehicle types, %d tls links", version,
                 len(self.sim.static.vtypes), len(self.sim.static.tls_links.tls))

    # ------------------------------------------------------------------ Zenoh callbacks
    # These run on Zenoh's threads: no SUMO calls, no shared mutable state but the queue.

    def _on_static_query(self, query: zenoh.Query) -> None:
        try:
            query.reply(self.keys.static, self._static_bytes)
        except Exception as e:  # the querier may be gone already
            log.debug("static reply failed: %s", e)

    def _on_map_query(self, query: zenoh.Query) -> None:
        try:
            reply = self.map.reply(str(query.parameters))
            if reply is None:
                query.reply_err(f"map not ready: {self.map.error or 'still building, ask again'}".encode())
            else:
                query.reply(self.keys.sumo_map, reply)
        except Exception as e:  # the querier may be gone already
            log.debug("map reply failed: %s", e)

    def _on_status_query(self, query: zenoh.Query) -> None:
        # Counters for tests and operators (SPEC.md 3.6); read on Zenoh's thread, so copy.
        try:
            query.reply(self.keys.sumo_status, encode(SumoStatus(dict(self.stats()))))
        except Exception as e:  # the querier may be gone, or a dict changed size mid-copy
            log.debug("status reply failed: %s", e)

    def _on_ack(self, sample: zenoh.Sample) -> None:
        if len(sample.payload) > MAX_ACK_BYTES:  # an ack is ~40 bytes: do not even copy a big one
            self._acks.refused += 1
            return
        self._acks.put(str(sample.key_expr), sample.payload.to_bytes())

    def _on_alive(self, sample: zenoh.Sample) -> None:
        self._alive_events.put(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

    # ------------------------------------------------------------------ incoming

    def _reject(self, what: str, err: Exception | str) -> None:
        self.counters.rejected += 1
        now = self.clock()
        if now - self._last_reject_log >= 1.0:  # rate-limited: a broken sender repeats
            log.warning("rejected %s: %s (%d rejected so far)", what, err, self.counters.rejected)
            self._last_reject_log = now

    def _drain_ego(self, sub) -> None:
        while True:
            got = sub.try_recv()
            if got is None:
                return
            key, payload = got
            try:
                msg = decode(payload, self._limits)
            except ProtocolError as e:
                self._reject(f"message on {key}", e)
                continue
            if not isinstance(msg, EgoPose):
                self._reject(f"message on {key}", f"expected an ego pose, got {type(msg).__name__}")
                continue
            if key.rsplit("/", 1)[-1] != msg.id:
                self._reject(f"ego pose on {key}", f"id {msg.id!r} differs from the key")
                continue
            if not self.ego.accepts(msg.id):
                self._reject(f"ego pose on {key}", f"ego id {msg.id!r} is not [sumo] ego_id {self.cfg.ego_id!r}")
                continue
            # ego_id "*" takes any id: without caps, poses under many ids would each add a vehicle
            refused = self.ego.admit(msg.id)
            if refused:
                self._reject(f"ego pose on {key}", refused)
                continue
            self.ego.offer(msg)

    def _drain_acks(self, timeout: float = 0.0) -> None:
        """Take acks from the queue (blocking up to ``timeout`` for the first one)."""
        for key, payload in self._acks.drain(timeout).items():
            try:
                msg = decode(payload, self._limits)
                if not isinstance(msg, StepAck):
                    raise ProtocolError(f"expected an ack, got {type(msg).__name__}", "kind")
                if msg.run != self.run_cfg.id:
                    raise ProtocolError(f"expected run {self.run_cfg.id!r}, got {msg.run!r}", "run")
            except ProtocolError as e:
                self._reject(f"message on {key}", e)
            else:
                inst = Keys.instance_of(key)
                self.counters.acks += 1
                if msg.feedback:
                    self.coupling.announced(inst, msg.step)
                # kept for the instances lockstep waits for only: a flood of acks under new
                # instance names (each a remote declaration) leaves nothing behind
                if inst in self._awaited and msg.step > self._acked.get(inst, -1):
                    self._acked[inst] = msg.step

    def _update_alive(self) -> bool:
        """Apply liveliness changes; True when an awaited instance that had left is back."""
        back = False
        for key, up in self._alive_events.drain().items():
            inst = Keys.instance_of(key)
            if inst not in self._awaited:
                continue  # only the instances lockstep waits for are followed (bounded by the config)
            if up:
                self._alive.add(inst)
                if self._lost.pop(inst, None) is not None:
                    back = True
                    self.counters.rejoined += 1
                    log.info("lockstep: physics instance %r is back", inst)
                elif inst in self.cfg.lockstep_instances and inst not in self._waited and not self._stop.is_set():
                    # a lost shard restarted (``--processes``): it takes its tiles back, so wait for it again
                    self._waited.append(inst)
                    back = True
                    self.counters.rejoined += 1
                    log.info("lockstep: physics shard %r is back; waiting for %s", inst, ", ".join(self._waited))
            elif inst in self._alive:
                self._alive.discard(inst)
                if inst in self._waited and not self._stop.is_set():
                    siblings = [i for i in self._waited if i != inst and _shard_group(i) == _shard_group(inst)]
                    if _shard_group(inst) is not None and any(i in self._alive for i in siblings):
                        # a physics shard: its siblings take over its agents
                        self._waited.remove(inst)
                        log.warning("lockstep: physics shard %r left; waiting for %s from now on",
                                    inst, ", ".join(self._waited))
                        continue
                    # A restarted instance can take over where this one stopped: wait for it
                    # (bounded by lockstep_timeout_s) instead of ending the run at once.
                    self._lost[inst] = self.clock()
                    log.warning("lockstep: physics instance %r left (its liveliness token on %s disappeared); "
                                "waiting up to %g s ([run] lockstep_timeout_s) for it to come back",
                                inst, key, self.run_cfg.lockstep_timeout_s)
        return back

    def _wait_for_peers(self, publisher, ego_sub) -> None:
        """Lockstep: before step 0, wait until every instance is alive and subscribed."""
        wanted = set(self.cfg.lockstep_instances)
        timeout = self.cfg.lockstep_start_timeout_s
        t_end = self.clock() + timeout
        log.info("lockstep: waiting up to %g s for physics instance(s) %s", timeout, ", ".join(sorted(wanted)))
        while not self._stop.is_set():
            self._update_alive()
            if wanted <= self._alive and publisher.matching_status:
                log.info("lockstep: physics instance(s) %s are up", ", ".join(sorted(wanted)))
                return
            if self.clock() >= t_end:
                raise LockstepTimeout(
                    f"lockstep: physics instance(s) {', '.join(sorted(wanted - self._alive)) or '(subscriber)'} "
                    f"not up within {timeout:g} s ([sumo] lockstep_start_timeout_s); no liveliness "
                    f"token on {self.keys.physics_alive_all} or no subscriber on {self.keys.step}"
                )
            self._drain_ego(ego_sub)
            self._stop.wait(0.02)

    def _all_acked(self, step: int) -> bool:
        """Every awaited instance acknowledged ``step`` and every announced feedback of it is here."""
        return all(self._acked.get(i, -1) >= step for i in self._waited) and self.coupling.ready(step)

    # ------------------------------------------------------------------ main loop

    def run(self) -> int:
        """Run until done or stopped; returns the process exit code (0)."""
        keys, run = self.keys, self.run_cfg
        lockstep = run.timing == "lockstep"
        session = self.session
        queryable = session.declare_queryable(keys.static, self._on_static_query)
        status_q = session.declare_queryable(keys.sumo_status, self._on_status_query)
        map_q = session.declare_queryable(keys.sumo_map, self._on_map_query)
        token = session.liveliness().declare_token(keys.sumo_alive)
        publisher = session.declare_publisher(
            keys.step,
            congestion_control=zenoh.CongestionControl.BLOCK,  # SPEC: steps are never dropped
            express=True,  # one big message per step: send it now, do not batch
        )
        ego_decl = session.declare_subscriber(keys.ego_all, self._egos.on_sample)
        ego_sub = self._egos
        feedback_sub = self.coupling.declare(session)
        ack_sub = alive_sub = None
        if lockstep:
            ack_sub = session.declare_subscriber(keys.ack_all, self._on_ack)
            alive_sub = session.liveliness().declare_subscriber(
                keys.physics_alive_all, self._on_alive, history=True
            )
        log.info(
            "SUMO side up: run %r (epoch %d), %s timing, step %.3g s, publishing on %s, static on %s",
            run.id, self.epoch, run.timing, self.sim.step_length, keys.step, keys.static,
        )
        try:
            if lockstep:
                self._wait_for_peers(publisher, ego_sub)
            if not self._stop.is_set():
                with HotLoopGC() as hot_gc:
                    self._loop(publisher, ego_sub, lockstep, hot_gc)
        finally:
            for what, obj in (("ego subscriber", ego_decl), ("ack subscriber", ack_sub),
                              ("feedback subscriber", feedback_sub),
                              ("liveliness subscriber", alive_sub),
                              ("publisher", publisher), ("queryable", queryable),
                              ("status queryable", status_q), ("map queryable", map_q),
                              ("token", token)):
                if obj is None:
                    continue
                try:
                    obj.undeclare()
                except Exception as e:  # session already closed
                    log.debug("undeclaring %s: %s", what, e)
            self.ego.close()
            self._log_summary()
        return 0

    def _produce(self, k: int, ego_sub, period: "_Period") -> tuple:
        """Step ``k``: ego poses in, SUMO's step, read, bridge, encode (not yet published).
        Returns ``(msg, payload, snap, why)``; ``why`` is non-empty for the run's last step."""
        perf = time.perf_counter
        t_a = perf()
        self._drain_ego(ego_sub)
        self.ego.apply()
        self.coupling.write_back(k)  # physical states of step k-1, before SUMO moves (SPEC 3.8)
        t_b = perf()
        self.sim.step()
        t_c = perf()
        snap = self.sim.read()
        ego_flags = self.ego.after_step(snap.ids, snap.x, snap.y, snap.arrived)
        if self.coupling.active:
            ego_flags = ego_flags | self.coupling.flags(snap, self.sim.vtypes, ego_flags)
            self.coupling.remember(k, snap)
        # The last step is marked on the wire, so every peer ends on the same step. The
        # duration and SUMO's end time hold whatever egos do; only an empty network does not
        # end a run while an ego drives.
        why = self.sim.finished(self.run_cfg.duration_s, keep_empty=bool(self.ego.active_ids()))
        if not why and self._stop.is_set():
            why = "stop requested"
        msg = self.bridge.build(k, snap, ego_flags, final=bool(why))
        self._refresh_static(msg.static_version)
        payload = encode(msg)
        period.sumo_s += t_c - t_b
        period.bridge_s += (t_b - t_a) + (perf() - t_c)
        return msg, payload, snap, why

    def _loop(self, publisher, ego_sub, lockstep: bool, hot_gc: HotLoopGC) -> None:
        cfg = self.cfg
        dt = self.sim.step_length
        clock = self.clock
        perf = time.perf_counter
        anchor = clock()
        period = _Period(clock())
        k = 0
        pending = self._produce(0, ego_sub, period)
        while True:  # ends after publishing a final step (also on a stop request)
            msg, payload, snap, why = pending
            t_p = perf()
            publisher.put(payload)
            period.bridge_s += perf() - t_p
            self.last_message = msg
            c = self.counters
            c.steps += 1
            c.max_agents = max(c.max_agents, snap.n)
            period.steps += 1

            if why:
                self.end_reason = why
                log.info("run ends at t=%.1f s after %d steps: %s", snap.time, c.steps, why)
                if lockstep:
                    self._wait_for_final_acks(k)
                break
            if lockstep:
                # Pipelined lockstep: step k+1 is computed while the physics side works on
                # step k and published only after every acknowledgement of step k (SPEC 3.4).
                # Nothing the physics side sends feeds SUMO; ego poses do, so with an ego
                # the next step waits for the acknowledgement and the poses that came with it.
                # Two-way coupling: step k+1 starts from the physical states of step k.
                pipelined = self.pipeline and not self.ego.active_ids() and not self.coupling.active
                if pipelined:
                    pending = self._produce(k + 1, ego_sub, period)
                t_w = perf()
                self._wait_for_acks(k, ego_sub, publisher, payload)
                period.wait_s += perf() - t_w
                if not pipelined:
                    pending = self._produce(k + 1, ego_sub, period)
                    self.counters.strict_steps += 1
            else:
                t_w = perf()
                deadline = anchor + (k + 1) * dt
                now = clock()
                if now > deadline + cfg.max_lag_s:
                    c.lag_resets += 1
                    log.warning("SUMO side is %.2f s behind the wall clock: re-anchoring", now - deadline)
                    anchor = now - (k + 1) * dt
                elif deadline > now:
                    self._stop.wait(deadline - now)
                period.wait_s += perf() - t_w
                pending = self._produce(k + 1, ego_sub, period)
            k += 1
            if clock() - period.t0 >= cfg.status_period_s:
                hot_gc.tick()
                self._log_status(period, snap.n, hot_gc.collect_ms)
                period = _Period(clock())

    def _wait_for_final_acks(self, step: int) -> None:
        """Lockstep, last step: wait (bounded) until every instance acknowledged it or left."""
        timeout = self.run_cfg.lockstep_timeout_s
        t_end = self.clock() + timeout
        while True:
            self._drain_acks(timeout=0.02)
            self._update_alive()  # leaving after the last step is what peers are asked to do
            missing = [i for i in self._waited
                       if self._acked.get(i, -1) < step and i in self._alive]
            if not missing:
                return
            if self.clock() >= t_end:
                log.warning("lockstep: no acknowledgement of the last step %d from %s within %g s",
                            step, ", ".join(missing), timeout)
                return

    def _wait_for_acks(self, step: int, ego_sub, publisher, payload: bytes) -> None:
        timeout = self.run_cfg.lockstep_timeout_s
        t_end = self.clock() + timeout
        self._drain_acks()
        while not self._all_acked(step):
            if self._stop.is_set():
                return
            left = t_end - self.clock()
            if left <= 0:
                missing = [i for i in self._waited if self._acked.get(i, -1) < step]
                gone = [i for i in missing if i in self._lost]
                alive = [i for i in missing if i in self._alive]
                if gone:
                    why = f"{', '.join(gone)} left and did not come back"
                elif alive:
                    # its liveliness token is here, so the run id matches: it is stuck or refuses the step
                    why = (f"{', '.join(alive)} is alive but silent: stopped, overloaded, or rejecting "
                           f"this step (its log and the 'rejected' counter of its states say which)")
                else:
                    why = f"is the physics side running with the same run id {self.run_cfg.id!r}?"
                raise LockstepTimeout(
                    f"lockstep: no acknowledgement of step {step} from physics instance(s) "
                    f"{', '.join(missing)} within {timeout:g} s ([run] lockstep_timeout_s) on "
                    f"{self.keys.ack_all}; {why}")
            # Wake at least every 50 ms to keep ego poses flowing and notice stop requests.
            self._drain_acks(timeout=min(left, 0.05))
            self._drain_ego(ego_sub)
            if self._update_alive():
                # The returning instance subscribed after this step went out: send it again
                # (others ignore a step they already have) and give it a full timeout.
                log.info("lockstep: re-sending step %d", step)
                publisher.put(payload)
                t_end = self.clock() + timeout

    # ------------------------------------------------------------------ logging

    def _log_status(self, p: _Period, agents: int, gc_ms: float) -> None:
        el = max(self.clock() - p.t0, 1e-9)
        n = max(p.steps, 1)
        c = self.counters
        sc = self.sim.counters
        log.info(
            "step %d t=%.1f s | %.1f steps/s | %d agents | sumo %.2f ms bridge %.2f ms idle %.2f ms "
            "per step | rejected %d teleports %d egos %d drift %.2f m gc %.1f ms",
            c.steps, self.sim.time(), p.steps / el, agents, p.sumo_s / n * 1e3, p.bridge_s / n * 1e3,
            p.wait_s / n * 1e3, c.rejected, sc["teleports"], len(self.ego.active_ids()),
            self.ego.drift_last_m, gc_ms,
        )

    def stats(self) -> dict:
        c = self.counters
        return {
            "steps": c.steps,
            "max_agents": c.max_agents,
            "rejected": c.rejected,
            "acks": c.acks,
            "lag_resets": c.lag_resets,
            "rejoined": c.rejoined,
            "strict_steps": c.strict_steps,
            "acks_coalesced": self._acks.replaced,
            "peer_keys_refused": self._acks.refused + self._alive_events.refused,
            "ego_oversized": self._egos.oversized,
            "ego_inbox_dropped": self._egos.dropped,
            **self.sim.counters,
            **self.ego.counters,
            "ego_drift_max_m": round(self.ego.drift_max_m, 4),
            "ego_drift_mean_m": round(self.ego.drift_mean_m, 4),
            "lane_walks": self.bridge.planner.resolved,
            "static_version": self.sim.static_version,
            "epoch": self.epoch,
            "static_versions": c.static_versions,
            "vtypes_live": self.sim.vtypes.live,
            "vtypes_dropped": self.sim.vtypes.dropped,
            "vtypes_overflow": self.sim.vtypes.overflow,
            "tls_program_switches": self.sim.tls.switches,
            **(self.coupling.stats() if self.coupling.active else {}),
        }

    def _log_summary(self) -> None:
        log.info("SUMO side done: %s", ", ".join(f"{k}={v}" for k, v in self.stats().items()))


# ---------------------------------------------------------------------- command line


def load_configs(args) -> tuple[CommonConfig, SumoConfig]:
    """Common + [sumo] config from ``--config`` (or defaults) with CLI overrides applied."""
    if getattr(args, "config", None):
        common, data, base = load_common(args.config)
        scfg = sumo_config_from(data, base, str(args.config))
    else:
        common, scfg = CommonConfig(), SumoConfig()
    common = apply_cli(common, args)
    if getattr(args, "sumocfg", None):
        scfg = replace(scfg, sumocfg=Path(args.sumocfg).expanduser().resolve())
    if getattr(args, "gui", False):
        scfg = replace(scfg, gui=True)
    if getattr(args, "wait_for", None):
        scfg = replace(scfg, lockstep_instances=tuple(args.wait_for))
    if getattr(args, "begin", None) is not None:
        scfg = replace(scfg, begin_s=float(args.begin))
        scfg.validate()
    scfg = replace(scfg, extra_args=scfg.extra_args + common.coupling.sumo_args(scfg.extra_args))
    if scfg.sumocfg is None:
        where = f"{args.config}: " if getattr(args, "config", None) else ""
        raise ConfigError(f"{where}no SUMO scenario: set [sumo] sumocfg or pass --sumocfg PATH")
    return common, scfg


def cli_main(args) -> int:
    """``sumoco sumo``: start SUMO, open Zenoh, run until done or SIGINT/SIGTERM."""
    from runtime.hotpath import tune_allocator
    from runtime.transport import open_session

    common, scfg = load_configs(args)
    keys = Keys(common.zenoh.root, common.run.id)
    out = getattr(args, "output_dir", None)
    sim = SumoSim(scfg, seed=common.run.seed, run_id=common.run.id,
                  output_dir=Path(out).expanduser() if out else None)
    sim.start()  # a broken scenario fails here (ConfigError -> exit 2) before Zenoh opens
    tune_allocator()  # the loop's HotLoopGC freezes start-up objects
    session = None
    daemon = None
    previous = {}

    def on_signal(signum, _frame):
        log.info("signal %d: stopping after this step", signum)
        if daemon is not None:
            daemon.request_stop()

    try:
        session = open_session(common.zenoh, role="sumo")
        daemon = SumoDaemon(session, keys, sim, scfg, common.run, coupling=common.coupling)
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                previous[s] = signal.signal(s, on_signal)
        return daemon.run()
    finally:
        if daemon is not None and sim.output_dir is not None:
            # SUMO's trip account is read here, on the main thread: libsumo is not
            # thread-safe, and ``stats()`` also answers status queries on Zenoh's thread
            _write_stats(sim.output_dir, {**daemon.stats(), **sim.trips()})
        for s, h in previous.items():
            signal.signal(s, h)
        sim.close()
        if session is not None:
            session.close()


#: The SUMO side's final counters, beside SUMO's own outputs (``sumoco demo`` puts them in
#: summary.json as ``sumo_side``).
STATS_FILE = "sumoco_stats.json"


def _write_stats(folder: Path, stats: dict) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        (folder / STATS_FILE).write_text(json.dumps(stats, indent=1, sort_keys=True, default=float) + "\n")
    except OSError as e:  # the run's result does not depend on it: say so and go on
        log.warning("could not write %s: %s", folder / STATS_FILE, e)


_SHARD = re.compile(r"^(.+)\.\d+of(\d+)$")


def _shard_group(instance: str) -> tuple[str, str] | None:
    """(base, count) of a physics shard instance ``<base>.<i>of<k>`` (``--shard i/k``), else None."""
    m = _SHARD.match(instance)
    return (m[1], m[2]) if m else None
