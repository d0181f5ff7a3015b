"""Two-way coupling on the SUMO side: which vehicles physics owns, and their states written back.

A physics-authoritative vehicle takes from SUMO only its intent (route, lane choice, target
speed from car following and signals); its physical pose and speed go back into SUMO
before SUMO's next step, so every other vehicle's car following, lane changing and
junction logic sees where it really is (README, "Two-way coupling"; SPEC.md 3.7).

Write-back, per vehicle, before ``simulationStep`` of step k+1, from the physics state that
ends step k:

- ``vehicle.moveTo(lane, pos)`` on SUMO's own lane of step k, at SUMO's lane position plus
  the physical body's offset along the path (``d_lon``). ``moveTo`` takes effect before
  SUMO's movement phase, so step k+1 is SUMO's own model run from the physical state.
  (``moveToXY`` is applied after the movement phase: one step of lag, sumo#11091.)
- ``vehicle.setPreviousSpeed(speed)`` with the measured speed (not one implied by the move).
- A position beyond the lane's ends (the body is behind SUMO's sample across a lane
  boundary, or ahead into the next lane) is kept on the lane, ``LANE_END_MARGIN_M`` inside
  its end (counted ``clamped``): ``moveToXY`` there acts after the movement phase, a step
  late, and in a filled grid its late moves made SUMO report collisions and teleport cars.
- On a junction's internal lane only the speed is written (counted ``internal``):
  ``moveTo`` onto internal lanes made SUMO count the move along the whole route (implied
  speeds of 10^4 m/s) and picked wrong internal lanes (sumo#15282).

libsumo has no batched setters: everything is computed with numpy over all vehicles and
only the calls themselves loop.
"""

from __future__ import annotations

import fnmatch
import logging
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from protocol.codec import DecodeLimits, decode
from protocol.errors import ProtocolError
from protocol.keys import Keys
from protocol.messages import AgentFlag, PhysicsFeedback
from runtime.config import CouplingConfig
from runtime.zones import DetailZones
from runtime.queues import LatestPerKey

log = logging.getLogger("sumo_side.coupling")

#: [m] an along-path offset smaller than this is not written (SUMO's pose is the physical one)
MOVE_MIN_M = 0.01
#: [m] a lane position this close to a lane's ends is kept inside it (SUMO refuses pos > length)
LANE_END_MARGIN_M = 0.01
#: [m/s] a physical speed at or below this is a stopped vehicle (``stopped`` counter)
STOPPED_SPEED = 0.1
#: [m] resolution and range of the intent-gap histogram (p50 / p95 / max in the stats)
GAP_BIN_M = 0.001
GAP_RANGE_M = 20.0
#: feedback senders held at once (one per physics shard of the coupling instance)
MAX_FEEDERS = 64


@dataclass
class FeedbackStats:
    """What the write-back did (SUMO side ``stats()``, ``summary.json``)."""

    applied_steps: int = 0  # steps whose states were written back
    late_steps: int = 0  # steps with two-way vehicles but no state in time: SUMO kept its own motion
    moved: int = 0  # moveTo calls (vehicle-steps)
    clamped: int = 0  # positions beyond a lane's end, kept on it
    internal: int = 0  # vehicle-steps on junction lanes: speed only
    speeds: int = 0  # setPreviousSpeed calls
    unknown: int = 0  # states of vehicles SUMO no longer has (arrived meanwhile)
    stopped: int = 0  # vehicle-steps written back at a standstill
    feedback_s: float = 0.0  # [s] wall time spent writing back


class Authority:
    """Which vehicles are physics-authoritative: by vType, class and id decided once per
    vehicle and kept by row; by zone (``authority = "zones"``) decided every step, with the
    level of detail's hysteresis, from the vehicle's SUMO position."""

    def __init__(self, cfg: CouplingConfig) -> None:
        self.cfg = cfg
        self._by_vtype = np.zeros(0, bool)
        self._vtypes_version = -1
        self._prev = np.zeros(0, bool)  # per row of the previous snapshot: selected by type/class/id
        self._zones = (DetailZones.from_config(cfg.zone_radius_m, cfg.zone_regions)
                       if cfg.authority == "zones" else None)
        self._in_zone = np.zeros(0, bool)  # per row of the previous snapshot: inside a zone

    def _vtype_rule(self, vtypes) -> np.ndarray:
        """Per vType index: physics-authoritative by ``authority``, ``classes`` or ``types``."""
        if vtypes.version != self._vtypes_version:
            cfg = self.cfg
            self._by_vtype = np.array(
                [cfg.authority == "physics" or t.vclass in cfg.classes or t.id in cfg.types
                 for t in vtypes.types], bool)
            self._vtypes_version = vtypes.version
        return self._by_vtype

    def _by_id(self, ids: list[str], rows: np.ndarray) -> np.ndarray:
        pats = self.cfg.ids
        return np.array([any(fnmatch.fnmatchcase(ids[r], p) for p in pats) for r in rows], bool)

    def flags(self, snap, vtypes, ego_flags: np.ndarray | None = None) -> np.ndarray:
        """``AgentFlag.PHYSICS_AUTHORITY`` per agent of ``snap`` (uint8): vehicles only,
        never an ego (``ego_flags``: the ego manager's flags of this step); ``vtypes``: the
        SUMO side's ``VTypeTable`` (``types``, ``version``)."""
        n, nv = snap.n, snap.n_vehicles
        out = np.zeros(n, np.uint8)
        keep = np.zeros(n, bool)
        if self.cfg.two_way and nv:
            by_type = self._vtype_rule(vtypes)
            auth = by_type[snap.vtype[:nv]] if len(by_type) else np.zeros(nv, bool)
            if self.cfg.ids:
                # id patterns are matched once per vehicle, at its first step, and kept by row
                prev = snap.prev_index
                known = np.zeros(nv, bool) if prev is None else prev[:nv] >= 0
                if known.any():
                    auth[known] |= self._prev[prev[:nv][known]]
                new = np.flatnonzero(~known)
                if len(new):
                    auth[new] |= self._by_id(snap.ids, new)
            self._prev = np.zeros(n, bool)
            self._prev[:nv] = auth
            ego = np.zeros(nv, bool) if ego_flags is None else (ego_flags[:nv] & AgentFlag.EGO) != 0
            if self._zones is not None:
                auth = auth | self._zone_rule(snap, ego)
            keep[:nv] = auth & ~ego
        else:
            self._prev = keep
        out[keep] = AgentFlag.PHYSICS_AUTHORITY
        return out

    def _zone_rule(self, snap, ego: np.ndarray) -> np.ndarray:
        """Vehicles inside a level-of-detail zone this step (hysteresis on the previous one)."""
        nv = len(ego)
        prev = snap.prev_index
        was = None
        if prev is not None and len(self._in_zone):
            p = prev[:nv]
            was = np.where(p >= 0, self._in_zone[np.clip(p, 0, len(self._in_zone) - 1)], False)
        inside = self._zones.full(snap.x[:nv], snap.y[:nv], ego, was)
        self._in_zone = np.zeros(snap.n, bool)
        self._in_zone[:nv] = inside
        return inside


class FeedbackWriter:
    """Writes the physical states of step k into SUMO before its step k+1."""

    def __init__(self, api, lane_ids: list[str], lane_lengths: np.ndarray, pos_factor: np.ndarray,
                 internal: np.ndarray | None = None) -> None:
        self.api = api
        self.lane_ids = lane_ids
        self.internal = np.zeros(len(lane_ids), bool) if internal is None else np.asarray(internal, bool)
        self.lane_lengths = np.asarray(lane_lengths, np.float64)
        self.pos_factor = np.asarray(pos_factor, np.float64)
        self.stats = FeedbackStats()

    def apply(self, fb: PhysicsFeedback, rows: np.ndarray, lane: np.ndarray, lane_pos: np.ndarray) -> None:
        """Write ``fb`` back; ``rows[i]`` is the row of ``fb.ids[i]`` in SUMO's snapshot of
        ``fb.step`` (-1: gone), whose ``lane`` / ``lane_pos`` columns are given."""
        t0 = time.perf_counter()
        st = self.stats
        ok = rows >= 0
        st.unknown += int((~ok).sum())
        idx = np.flatnonzero(ok)
        r = rows[idx]
        ln = lane[r]
        on_lane = ln >= 0
        # along-path metres -> lane-position units of SUMO (junction lanes may differ)
        factor = np.where(on_lane, self.pos_factor[np.maximum(ln, 0)], 1.0)
        pos = lane_pos[r] + fb.d_lon[idx].astype(np.float64) / factor
        length = np.where(on_lane, self.lane_lengths[np.maximum(ln, 0)], 0.0)
        junction = on_lane & self.internal[np.maximum(ln, 0)]
        hi = np.maximum(length - LANE_END_MARGIN_M, 0.0)
        clamped = on_lane & ~junction & ((pos < 0.0) | (pos > hi))
        pos = np.clip(pos, 0.0, hi)
        move = on_lane & ~junction & (np.abs(fb.d_lon[idx]) >= MOVE_MIN_M)
        v = self.api.vehicle
        ids = fb.ids
        speed = fb.speed.astype(np.float64)
        for j in np.flatnonzero(move):
            v.moveTo(ids[idx[j]], self.lane_ids[ln[j]], float(pos[j]))
        for i in idx:
            v.setPreviousSpeed(ids[i], float(speed[i]))
        st.moved += int(move.sum())
        st.clamped += int((clamped & move).sum())
        st.internal += int(junction.sum())
        st.speeds += len(idx)
        st.stopped += int((speed[idx] <= STOPPED_SPEED).sum())
        st.applied_steps += 1
        st.feedback_s += time.perf_counter() - t0


class GapHistogram:
    """Bounded distribution of the intent gap [m]: fixed bins, exact maximum."""

    def __init__(self) -> None:
        self.counts = np.zeros(int(GAP_RANGE_M / GAP_BIN_M) + 1, np.int64)
        self.max = 0.0

    def add(self, gap: np.ndarray) -> None:
        if len(gap):
            self.max = max(self.max, float(gap.max()))
            np.add.at(self.counts, np.minimum((gap / GAP_BIN_M).astype(np.int64), len(self.counts) - 1), 1)

    def quantile(self, q: float) -> float:
        total = int(self.counts.sum())
        if not total:
            return 0.0
        i = int(np.searchsorted(np.cumsum(self.counts), q * total))
        return round(min((i + 0.5) * GAP_BIN_M, self.max), 4)

    def summary(self) -> dict[str, float]:
        return {"p50": self.quantile(0.5), "p95": self.quantile(0.95), "max": round(self.max, 4),
                "samples": int(self.counts.sum())}


class SumoCoupling:
    """The SUMO side of two-way coupling, driven by the daemon's main loop.

    Per step k: ``flags`` marks the physics-authoritative vehicles of SUMO's snapshot,
    ``remember`` keeps the snapshot's lanes for the write-back, and before step k+1
    ``write_back`` applies the newest feedback of every instance that sends it. Zenoh's
    thread only stores payloads (newest per sender); decoding happens on the main thread.
    """

    def __init__(self, cfg: CouplingConfig, sim, keys: Keys, limits: DecodeLimits,
                 reject: Callable[[str, object], None]) -> None:
        self.cfg = cfg
        self.active = cfg.two_way
        self.keys = keys
        self.limits = limits
        self.reject = reject
        self.authority = Authority(cfg)
        g = sim.graph
        self.writer = FeedbackWriter(sim.api, g.ids, g.lengths, g.pos_factor, g.internal)
        self._inbox: LatestPerKey[bytes] = LatestPerKey(MAX_FEEDERS)
        self._latest: dict[str, PhysicsFeedback] = {}
        self._expected: dict[str, int] = {}  # instance -> newest step whose ack announced feedback
        self._history: deque = deque(maxlen=cfg.feedback_steps + 2)  # (step, id -> row, lane, lane_pos)
        self.gap = GapHistogram()
        self.flagged_last = 0  # physics-authoritative vehicles in the newest snapshot

    def declare(self, session):
        """The feedback subscriber (None in shadow mode)."""
        if not self.active:
            return None
        return session.declare_subscriber(self.keys.feedback_all, self._on_sample)

    def _on_sample(self, sample) -> None:  # Zenoh's thread
        self._inbox.put(str(sample.key_expr), sample.payload.to_bytes())

    def announced(self, instance: str, step: int) -> None:
        """An acknowledgement of ``step`` from ``instance`` said it sent that step's feedback."""
        if step > self._expected.get(instance, -1):
            self._expected[instance] = step

    def _drain(self) -> None:
        for key, payload in self._inbox.drain().items():
            try:
                fb = decode(payload, self.limits)
                if not isinstance(fb, PhysicsFeedback):
                    raise ProtocolError(f"expected feedback, got {type(fb).__name__}", "kind")
                if fb.run != self.keys.run:
                    raise ProtocolError(f"expected run {self.keys.run!r}, got {fb.run!r}", "run")
            except ProtocolError as e:
                self.reject(f"message on {key}", e)
                continue
            self._latest[Keys.instance_of(key)] = fb

    def ready(self, step: int) -> bool:
        """Lockstep: every instance that announced feedback of ``step`` has delivered it."""
        if not self.active:
            return True
        self._drain()
        return all(i in self._latest and self._latest[i].step >= step
                   for i, s in self._expected.items() if s >= step)

    def flags(self, snap, vtypes, ego_flags: np.ndarray | None) -> np.ndarray:
        out = self.authority.flags(snap, vtypes, ego_flags)
        self.flagged_last = int(np.count_nonzero(out))
        return out

    def remember(self, step: int, snap) -> None:
        if self.active:
            nv = snap.n_vehicles
            self._history.append((step, {vid: i for i, vid in enumerate(snap.ids[:nv])},
                                  snap.lane, snap.lane_pos))

    def write_back(self, next_step: int) -> None:
        """Before SUMO's step ``next_step``: write the newest feedback of each instance back
        (in lockstep the one of ``next_step - 1``; in realtime at most ``feedback_steps`` old)."""
        if not self.active:
            return
        self._drain()
        oldest = next_step - 1 - self.cfg.feedback_steps
        applied = False
        for inst in list(self._latest):
            fb = self._latest.pop(inst)
            snap = next((h for h in self._history if h[0] == fb.step), None)
            if fb.step < oldest or snap is None:
                continue
            _, index, lane, lane_pos = snap
            rows = np.fromiter((index.get(i, -1) for i in fb.ids), np.int64, fb.n)
            self.writer.apply(fb, rows, lane, lane_pos)
            self.gap.add(np.hypot(fb.d_lon, fb.d_lat).astype(np.float64))
            applied = True
        if not applied and self.flagged_last:
            self.writer.stats.late_steps += 1

    def stats(self) -> dict:
        st = self.writer.stats
        return {
            "coupling_authoritative_last": self.flagged_last,
            "feedback_steps_applied": st.applied_steps,
            "feedback_late": st.late_steps,
            "feedback_moves": st.moved,
            "feedback_clamped": st.clamped,
            "feedback_internal": st.internal,
            "feedback_speeds": st.speeds,
            "feedback_unknown": st.unknown,
            "feedback_stopped": st.stopped,
            "feedback_ms": round(st.feedback_s * 1e3 / max(st.applied_steps, 1), 4),
            **{f"intent_gap_{k}_m" if k != "samples" else "intent_gap_samples": v
               for k, v in self.gap.summary().items()},
        }


__all__ = ["GapHistogram", "SumoCoupling", "Authority", "FeedbackStats", "FeedbackWriter", "LANE_END_MARGIN_M", "MOVE_MIN_M",
           "STOPPED_SPEED"]
