"""Ego vehicles: poses from an outside engine applied to SUMO every step.

Each step, before ``simulationStep``, every known ego is placed with
``vehicle.moveToXY(id, "", -1, x, y, angle, keepRoute)`` and given its speed, so SUMO's
traffic sees it where the outside engine drives it (followers brake for it, junctions
yield to it). An ego missing in SUMO is created first (a one-edge route on the edge
nearest the pose, its vType from the pose or the config).

When poses pause, the ego stays where it was last put: for ``ego_hold_s`` with its
last speed, then standing (speed 0); after ``ego_timeout_s`` without a pose it is removed
(with a log line) and created again as soon as poses resume.

How many egos: at most ``[sumo] ego_max`` at once, and at most ``ego_max_per_client`` of
one client, where the client of an ego is what its id says: ``<client>.<name>`` counts
against ``<client>`` (``unity1.car``, ``unity1.trailer``), an id without a dot is a client
of its own. A pose for one ego more is refused before it reaches SUMO (``admit``, counted
in ``ego_refused`` and ``ego_refused_client``); an ego already in keeps being driven, and a
removed one frees its place. Ids are chosen by the sender: against a hostile sender the
total cap is the bound, and the secure profile's access control lets each renderer
certificate put its own ego key only.

Drift is the distance between the requested pose and the pose SUMO reports after the
step; with keepRoute=2 it is normally zero, larger values mean SUMO could not put the ego
where asked (e.g. blocked insertion or no road nearby).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from protocol.messages import AgentFlag, EgoPose
from sumo_side.config import SumoConfig

log = logging.getLogger(__name__)

#: Drift above this is counted as an event [m].
DRIFT_EVENT_M = 0.5


@dataclass
class _Ego:
    id: str
    pose: EgoPose
    received: float  # clock() when the newest pose arrived [s]
    in_sumo: bool = False
    requested: tuple[float, float] | None = None  # pose asked for this step
    requested_prev: tuple[float, float] | None = None  # pose asked for in the step before
    jumped: bool = False  # created or jumped this step


class EgoManager:
    """Owns every ego vehicle; call ``offer`` per received pose, ``apply`` before each
    SUMO step, ``after_step`` after reading."""

    def __init__(self, api, cfg: SumoConfig, clock: Callable[[], float] = time.monotonic) -> None:
        self.api = api
        self.cfg = cfg
        self.clock = clock
        self.egos: dict[str, _Ego] = {}
        self.counters = {
            "ego_poses": 0,
            "ego_created": 0,
            "ego_removed": 0,
            "ego_errors": 0,
            "ego_drift_events": 0,
            "ego_refused": 0,  # poses for one ego more than [sumo] ego_max
            "ego_refused_client": 0,  # poses for one ego more than its client's ego_max_per_client
        }
        self.drift_last_m = 0.0
        self.drift_max_m = 0.0
        self._drift_sum = 0.0
        self._drift_n = 0
        self._last_error_log = -math.inf
        self._route_serial = 0  # route ids must be unique for the whole run

    # ------------------------------------------------------------------ input

    def accepts(self, ego_id: str) -> bool:
        return self.cfg.ego_id in ("*", ego_id)

    @staticmethod
    def client_of(ego_id: str) -> str:
        """The client an ego counts against: the id up to its first "." (the whole id without one)."""
        return ego_id.split(".", 1)[0]

    def admit(self, ego_id: str) -> str:
        """"" when a pose for ``ego_id`` may be offered, else why not (counted): a known ego
        always may; a new one only within ``ego_max`` and its client's ``ego_max_per_client``."""
        if ego_id in self.egos:
            return ""
        if len(self.egos) >= self.cfg.ego_max:
            self.counters["ego_refused"] += 1
            return (f"{len(self.egos)} egos already, the most [sumo] ego_max allows; "
                    f"ego {ego_id!r} not added")
        client = self.client_of(ego_id)
        n = sum(1 for other in self.egos if self.client_of(other) == client)
        if n >= self.cfg.ego_max_per_client:
            self.counters["ego_refused_client"] += 1
            return (f"client {client!r} has {n} egos already, the most [sumo] ego_max_per_client allows; "
                    f"ego {ego_id!r} not added")
        return ""

    def offer(self, pose: EgoPose) -> None:
        """Newest pose of an ego (poses of one ego arrive in order; the last one wins)."""
        now = self.clock()
        e = self.egos.get(pose.id)
        if e is None:
            self.egos[pose.id] = _Ego(pose.id, pose, now)
        else:
            e.pose, e.received = pose, now
        self.counters["ego_poses"] += 1

    @property
    def drift_mean_m(self) -> float:
        return self._drift_sum / self._drift_n if self._drift_n else 0.0

    @property
    def drift_samples(self) -> int:
        """Steps in which an ego's position in SUMO was compared with its requested pose."""
        return self._drift_n

    def active_ids(self) -> list[str]:
        return [e.id for e in self.egos.values() if e.in_sumo]

    # ------------------------------------------------------------------ before the step

    def apply(self) -> None:
        now = self.clock()
        for e in list(self.egos.values()):
            age = now - e.received
            e.jumped = False
            e.requested = None
            if age > self.cfg.ego_timeout_s:
                self._remove(e, f"no pose for {age:.1f} s (timeout {self.cfg.ego_timeout_s:g} s)")
                del self.egos[e.id]
                continue
            p = e.pose
            speed = p.speed if age <= self.cfg.ego_hold_s else 0.0
            if not e.in_sumo and not self._create(e):
                continue
            prev = e.requested_prev
            try:
                self.api.vehicle.moveToXY(e.id, "", -1, p.x, p.y, p.angle, self.cfg.ego_keep_route)
                self.api.vehicle.setSpeed(e.id, max(float(speed), 0.0))
            except Exception as exc:  # TraCIException: vehicle gone or pose not mappable
                self._error(f"ego {e.id!r}: moveToXY({p.x:.2f}, {p.y:.2f}) failed: {exc}")
                if not self._exists(e.id):
                    e.in_sumo = False
                continue
            e.requested = (p.x, p.y)
            if prev is not None and math.hypot(p.x - prev[0], p.y - prev[1]) > self.cfg.ego_jump_m:
                e.jumped = True
            e.requested_prev = (p.x, p.y)

    def _exists(self, ego_id: str) -> bool:
        """In the network, or added and waiting for insertion."""
        try:
            pending = self.api.simulation.getPendingVehicles()
        except Exception:
            pending = ()
        return ego_id in self.api.vehicle.getIDList() or ego_id in pending

    def _create(self, e: _Ego) -> bool:
        api = self.api
        p = e.pose
        vtype = p.vtype or self.cfg.ego_vtype or "DEFAULT_VEHTYPE"
        try:
            vclass = api.vehicletype.getVehicleClass(vtype)
        except Exception:
            self._error(f"ego {e.id!r}: unknown vType {vtype!r}; pose ignored")
            return False
        edge = self._edge_near(p.x, p.y, vclass)
        if edge is None:
            self._error(f"ego {e.id!r}: no edge for vClass {vclass!r} in the network")
            return False
        self._route_serial += 1
        route_id = f"!sumoco_ego!{e.id}!{self._route_serial}"
        try:
            api.route.add(route_id, [edge])
            api.vehicle.add(e.id, route_id, typeID=vtype, depart="now", departSpeed="0")
            # The outside engine drives: no SUMO speed checks, no SUMO lane changes.
            api.vehicle.setSpeedMode(e.id, 0)
            api.vehicle.setLaneChangeMode(e.id, 0)
        except Exception as exc:
            self._error(f"ego {e.id!r}: cannot add it to SUMO: {exc}")
            return False
        e.in_sumo = True
        e.jumped = True
        self.counters["ego_created"] += 1
        log.info("ego %r created at (%.1f, %.1f) on edge %s with vType %s", e.id, p.x, p.y, edge, vtype)
        return True

    def _edge_near(self, x: float, y: float, vclass: str) -> str | None:
        api = self.api
        try:
            edge, _, _ = api.simulation.convertRoad(x, y, False, vclass)
        except Exception:
            edge = ""
        if edge and not edge.startswith(":"):
            return edge
        if edge.startswith(":"):
            # Inside a junction: take an edge leaving it (a route cannot start on an internal edge).
            try:
                junction = api.edge.getToJunction(edge) if hasattr(api.edge, "getToJunction") else ""
                outgoing = api.junction.getOutgoingEdges(junction) if junction else ()
                for cand in outgoing:
                    if not cand.startswith(":"):
                        return cand
            except Exception:
                pass
        for cand in api.edge.getIDList():
            if not cand.startswith(":"):
                return cand
        return None

    def _remove(self, e: _Ego, why: str) -> None:
        if e.in_sumo:
            try:
                # libsumo raises in the next simulationStep for a removed vehicle that
                # still has a subscription: drop it first.
                self.api.vehicle.unsubscribe(e.id)
                self.api.vehicle.remove(e.id)
            except Exception as exc:
                log.debug("removing ego %r: %s", e.id, exc)
            self.counters["ego_removed"] += 1
        e.in_sumo = False
        log.warning("ego %r removed from SUMO: %s", e.id, why)

    def _error(self, text: str) -> None:
        self.counters["ego_errors"] += 1
        now = self.clock()
        if now - self._last_error_log >= 1.0:  # rate-limited: poses come at 20+ Hz
            log.warning("%s", text)
            self._last_error_log = now

    # ------------------------------------------------------------------ after the step

    def after_step(self, ids: list[str], x: np.ndarray, y: np.ndarray, arrived: list[str]) -> np.ndarray:
        """Per-agent EGO/JUMPED flags for this step; measures drift; notices removed egos."""
        flags = np.zeros(len(ids), np.uint8)
        if not self.egos:
            return flags
        gone = set(arrived)
        for e in self.egos.values():
            if e.id in gone:
                e.in_sumo = False  # SUMO ended its route or removed it: re-created next step
            if not e.in_sumo:
                continue
            try:
                i = ids.index(e.id)
            except ValueError:
                continue  # added but not inserted yet
            flags[i] |= AgentFlag.EGO
            if e.jumped:
                flags[i] |= AgentFlag.JUMPED
            if e.requested is not None:
                d = math.hypot(float(x[i]) - e.requested[0], float(y[i]) - e.requested[1])
                self.drift_last_m = d
                self.drift_max_m = max(self.drift_max_m, d)
                self._drift_sum += d
                self._drift_n += 1
                if d > DRIFT_EVENT_M:
                    self.counters["ego_drift_events"] += 1
        return flags

    def close(self) -> None:
        """Remove every ego from SUMO (daemon shutdown)."""
        for e in self.egos.values():
            if e.in_sumo:
                try:
                    self.api.vehicle.unsubscribe(e.id)
                    self.api.vehicle.remove(e.id)
                except Exception as exc:  # SUMO already closed or the ego gone
                    log.debug("removing ego %r at close: %s", e.id, exc)
        self.egos.clear()
