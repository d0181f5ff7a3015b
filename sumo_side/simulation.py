"""SUMO through libsumo (or TraCI for sumo-gui): start, step, read all agents as arrays.

Reading follows SUMO's advice for speed: every vehicle and person is subscribed ONCE
when it departs, and each step reads all results with one
``getAllSubscriptionResults()`` per domain, turned into numpy columns. No per-variable
getter runs per agent per step. Persons riding a vehicle report the vehicle's pose
and are flagged INSIDE_VEHICLE.

The vehicles' read takes a C fast path (``sumo_side._fastread``) when it is built: the same
columns, filled in one pass over the results. On anything it does not expect it steps
aside and the Python code below runs. ``SUMOCO_PURE_READ=1`` in the environment forces the
Python path; ``FAST_READ`` tells which is active.
"""

from __future__ import annotations

import itertools
import logging
import operator
import os
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from protocol.errors import ConfigError, SumocoError
from protocol.messages import (
    VCLASS_TO_AGENT_CLASS,
    AgentClass,
    AgentFlag,
    StaticData,
    TrafficLights,
    VType,
)
from runtime.native import optional_extension
from sumo_side.config import SumoConfig
from sumo_side.lanes import LaneGraph, build_static, tls_link_table
from sumo_side.tables import TlsTable, VTypeTable
from sumo_side.lookahead import MODE_LANES, MODE_NONE, MODE_STRAIGHT

log = logging.getLogger(__name__)

# Variable ids are the same numbers in libsumo and traci.constants.
import libsumo as _C  # noqa: E402  (constants only; the API module may be traci)

V_POS, V_ANGLE, V_SPEED = _C.VAR_POSITION, _C.VAR_ANGLE, _C.VAR_SPEED
V_SIGNALS, V_LANE, V_LANEPOS, V_TYPE = _C.VAR_SIGNALS, _C.VAR_LANE_ID, _C.VAR_LANEPOSITION, _C.VAR_TYPE
V_VEHICLE = _C.VAR_VEHICLE
V_ROUTE = _C.VAR_ROUTE_ID
TL_STATE, TL_PHASE, TL_NEXT = _C.TL_RED_YELLOW_GREEN_STATE, _C.TL_CURRENT_PHASE, _C.TL_NEXT_SWITCH
TL_PROGRAM = _C.TL_CURRENT_PROGRAM

# Each subscribed variable costs ~0.5 us per vehicle per step in getAllSubscriptionResults
# (measured: 2,500 vehicles, 9 variables 6.4 ms, 7 variables 5.0 ms). So the acceleration
# is derived from consecutive speeds. The type id is subscribed: nothing else tells of a
# vehicle.setType. The route id is the one route variable subscribed: every reroute
# (changeTarget, a rerouting device, a rerouter) gives the vehicle a new one
# ("!<veh>!var#<n>"), so it detects route changes; the edges and the route index are read
# only for vehicles whose lane or route changed (the index moves only with a new lane).
VEHICLE_VARS = (V_POS, V_ANGLE, V_SPEED, V_SIGNALS, V_LANE, V_LANEPOS, V_TYPE, V_ROUTE)
PERSON_VARS = (V_POS, V_ANGLE, V_SPEED, V_LANE, V_LANEPOS, V_TYPE, V_VEHICLE)
_VEHICLE_ROW = operator.itemgetter(V_POS, V_ANGLE, V_SPEED, V_SIGNALS, V_LANEPOS, V_LANE, V_TYPE, V_ROUTE)
_chain = itertools.chain.from_iterable
_PERSON_ROW = operator.itemgetter(V_POS, V_ANGLE, V_SPEED, V_LANEPOS, V_LANE, V_TYPE, V_VEHICLE)
TLS_VARS = (TL_STATE, TL_PHASE, TL_NEXT, TL_PROGRAM)


# The C vehicle read, configured with ``_VEHICLE_ROW``'s variables; None when it is not
# built or SUMOCO_PURE_READ is set.
_fast = optional_extension("sumo_side._fastread", "SUMOCO_PURE_READ")
if _fast is not None:
    _fast.configure((V_POS, V_ANGLE, V_SPEED, V_SIGNALS, V_LANEPOS, V_LANE, V_TYPE, V_ROUTE))
#: True when the vehicles are read through the C fast path (``sumo_side._fastread``).
FAST_READ: bool = _fast is not None
#: [m] beyond speed x step length, a position change this large is a jump (flag JUMPED);
#: larger than one lane width so that SUMO's instant lane changes stay ordinary motion.
JUMP_MARGIN_M = 5.0
#: [m] the same for a walking person (no lane changes): SUMO's pedestrian model moves a
#: person from a walking area onto a crossing 1-3 m at once (3.2 m in one 0.1 s step at
#: 1.1 m/s); unflagged, every engine following it slid the body across, and the step counted
#: as tracking error
PERSON_JUMP_MARGIN_M = 0.5
#: [s] ``next`` of a traffic light that has no switch scheduled (SPEC.md: |next| <= 1e9)
NO_SWITCH_S = 1e9


class SumoFailed(SumocoError):
    """libsumo / TraCI reported an error during the run (the message is SUMO's)."""


@dataclass
class Snapshot:
    """Every agent after one SUMO step, one numpy column per field (vehicles, then persons)."""

    time: float
    ids: list[str]
    x: np.ndarray
    y: np.ndarray
    angle: np.ndarray
    speed: np.ndarray
    accel: np.ndarray
    signals: np.ndarray
    lane: np.ndarray
    """Lane index into the lane graph, -1 when none [int64]."""
    lane_pos: np.ndarray
    vtype: np.ndarray
    flags: np.ndarray
    mode: np.ndarray
    """Look-ahead mode per agent (``lookahead.MODE_*``)."""
    n_vehicles: int
    tls: TrafficLights
    departed: int = 0
    arrived: list[str] = field(default_factory=list)
    teleports: int = 0
    prev_index: np.ndarray | None = None
    """Row of each agent in the previous snapshot (-1: new), for per-agent state."""
    serial: int = 0
    """Snapshot counter of this SumoSim (consecutive snapshots differ by one)."""
    route_changed: np.ndarray | None = None
    """True for vehicles whose route changed in this step (rerouted), bool per agent."""

    @property
    def n(self) -> int:
        return len(self.ids)

    def is_vehicle(self) -> np.ndarray:
        v = np.zeros(self.n, bool)
        v[: self.n_vehicles] = True
        return v


def _empty_f(n: int = 0) -> np.ndarray:
    return np.zeros(n, np.float64)


@dataclass(frozen=True)
class _Events:
    """What SUMO reports of the last step besides the agents' variables."""

    new: set[str]
    """Vehicles and persons that departed."""
    departed: int
    arrived: list[str]
    teleported: set[str]
    """Vehicles that started or ended a teleport."""
    teleports: int
    """Teleports that started."""


@dataclass(frozen=True)
class _Columns:
    """One kind of agent (vehicles or persons) as read in one step, one column per variable."""

    ids: list[str]
    xy: np.ndarray
    """Positions, shape (n, 2) [m]."""
    angle: np.ndarray
    """[deg], SUMO's."""
    speed: np.ndarray
    """[m/s]"""
    lane_pos: np.ndarray
    """[m]"""
    lane: np.ndarray
    """Lane index, -1 when none [int64]."""
    vtype: np.ndarray
    """vType index [int64]."""
    signals: np.ndarray
    """SUMO's signal bits [int64] (0 for persons)."""
    route: list[str]
    """Route id per vehicle (empty for persons)."""
    riding: np.ndarray
    """True for a person inside a vehicle (empty for vehicles)."""

    @staticmethod
    def none() -> "_Columns":
        i64 = np.zeros(0, np.int64)
        return _Columns([], np.zeros((0, 2)), _empty_f(), _empty_f(), _empty_f(), i64, i64, i64, [],
                        np.zeros(0, bool))


@dataclass(frozen=True)
class _Previous:
    """The previous snapshot, as far as the next one's derived quantities need it."""

    ids: list[str] = field(default_factory=list)
    speed: np.ndarray = field(default_factory=_empty_f)
    time: float = -1.0
    """[s] (-1: no snapshot yet)"""
    xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    route: np.ndarray = field(default_factory=lambda: np.zeros(0, object))
    """Route id per vehicle row (object array)."""


def check_sumocfg(path: Path) -> Path:
    """A readable, well-formed SUMO config, or a ConfigError naming the file and the problem."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise ConfigError(f"{p}: SUMO config file not found")
    try:
        root = ET.parse(p).getroot()
    except ET.ParseError as e:
        raise ConfigError(f"{p}: SUMO config is not well-formed XML ({e})") from None
    except OSError as e:
        raise ConfigError(f"{p}: SUMO config cannot be read ({e})") from None
    if root.tag not in ("configuration", "sumoConfiguration"):
        raise ConfigError(f"{p}: expected a SUMO <configuration> root element, got <{root.tag}>")
    return p.resolve()


#: SUMO options that decide how lateral motion looks: either one set means the scenario chose.
LATERAL_OPTIONS = ("lanechange.duration", "lateral-resolution")


def lane_change_args(sumocfg: Path, extra_args: tuple[str, ...], duration_s: float) -> list[str]:
    """``--lanechange.duration`` for a scenario that sets neither it nor the sublane model.

    SUMO's default lane change is a whole lane width in one step, which no physics vehicle
    can drive; a continuous one over ``duration_s`` [s] is. The scenario's own choice (in
    its .sumocfg or the run's extra arguments) stands; ``duration_s`` 0 keeps SUMO's default.
    """
    if duration_s <= 0:
        return []
    if any(a.lstrip("-").split("=")[0] in LATERAL_OPTIONS for a in extra_args):
        return []
    try:
        root = ET.parse(sumocfg).getroot()
    except (ET.ParseError, OSError):
        return []  # check_sumocfg reports it
    if any(el.tag in LATERAL_OPTIONS for el in root.iter()):
        return []
    log.info("the scenario sets neither lanechange.duration nor lateral-resolution: "
             "continuous lane changes over %g s (--lanechange.duration)", duration_s)
    return ["--lanechange.duration", f"{duration_s:g}"]


@dataclass(frozen=True)
class ScenarioOptions:
    """What a .sumocfg says about time and randomness (SUMO's defaults where it is silent)."""

    step_length_s: float = 1.0
    """SUMO's step length [s] (SUMO's default 1 s)."""
    seed: int | None = None
    """The scenario's random seed (None: SUMO's default)."""
    begin_s: float = 0.0
    """Begin time [s]."""
    end_s: float | None = None
    """End time [s] (None: until no traffic is left)."""


def _sumo_time(text: str | None) -> float | None:
    """A SUMO time value: seconds, or [[D:]H:]M:S."""
    if text is None:
        return None
    try:
        if ":" in text:
            secs = 0.0
            for part in text.split(":"):
                secs = secs * 60 + float(part)
            return secs if text.count(":") < 3 else None
        return float(text)
    except ValueError:
        return None


def scenario_options(path: Path) -> ScenarioOptions:
    """Step length, seed, begin and end as written in a .sumocfg (checked by ``check_sumocfg``)."""
    root = ET.parse(path).getroot()
    found = {el.tag: el.get("value") for el in root.iter() if el.get("value") is not None}
    seed = found.get("seed")
    end = _sumo_time(found.get("end"))
    return ScenarioOptions(
        step_length_s=_sumo_time(found.get("step-length")) or 1.0,
        seed=int(seed) if seed is not None and seed.strip().lstrip("-").isdigit() else None,
        begin_s=_sumo_time(found.get("begin")) or 0.0,
        end_s=end if end is not None and end >= 0 else None,
    )


def sumo_binary(gui: bool) -> str:
    try:
        from sumo_side.scenarios import find_sumo_binary

        return find_sumo_binary("sumo-gui" if gui else "sumo")
    except ConfigError:
        if gui:
            raise
        return "sumo"  # libsumo only needs argv[0] as a name


class SumoSim:
    """One running SUMO: libsumo embedded, or sumo-gui over TraCI (``cfg.gui``)."""

    def __init__(
        self,
        cfg: SumoConfig,
        sumocfg: Path | None = None,
        seed: int | None = None,
        run_id: str = "default",
        output_dir: Path | None = None,
    ) -> None:
        """``seed`` None keeps the scenario's own; ``output_dir`` receives SUMO's own outputs
        (tripinfos, detectors, its log) instead of the scenario's folder."""
        self.cfg = cfg
        path = sumocfg if sumocfg is not None else cfg.sumocfg
        if path is None:
            raise ConfigError(
                "no SUMO scenario: set [sumo] sumocfg in the config file or pass --sumocfg PATH"
            )
        self.sumocfg = Path(path)
        self.seed = None if seed is None else int(seed)
        self.run_id = run_id
        self.output_dir = None if output_dir is None else Path(output_dir)
        self.options = ScenarioOptions()
        self._dt = float(cfg.step_length_s) or 1.0
        self.api = None
        self.graph: LaneGraph | None = None
        self.static: StaticData | None = None
        self.vtypes: VTypeTable | None = None
        self.tls: TlsTable | None = None
        self.tls_ids: list[str] = []
        self.begin_time = 0.0
        self.end_time = -1.0
        self.counters = {"departed": 0, "arrived": 0, "teleports": 0, "persons_departed": 0}
        self._lane_index: dict[str, int] = {}  # lane id -> lane index, '' -> -1
        self._prev = _Previous()
        self._serial = 0

    # ------------------------------------------------------------------ life cycle

    def start(self) -> None:
        cfg = self.cfg
        path = check_sumocfg(self.sumocfg)
        self.sumocfg = path
        self.options = scenario_options(path)
        args = [sumo_binary(cfg.gui), "-c", str(path), "--no-step-log", "true"]
        # The scenario is the truth; the run replaces its step length, seed or begin only
        # when it says so, and the log names both values.
        if cfg.step_length_s > 0:
            args += ["--step-length", repr(float(cfg.step_length_s))]
        if self.seed is not None:
            args += ["--seed", str(self.seed)]
        if cfg.begin_s is not None:
            args += ["--begin", repr(float(cfg.begin_s))]
        # every vehicle gets SUMO's tripinfo device, so ``trips()`` reads its aggregate
        # (travel time, time loss) at the end without an output file. (Not through
        # --duration-log.statistics: that also prints SUMO's loading log on stdout, where
        # the benches write their JSON rows.) The device draws from SUMO's equipment random
        # stream only, so the traffic is the same with and without it.
        args += ["--device.tripinfo.probability", "1"]
        if self.output_dir is not None:
            # SUMO resolves output names against the config's folder and puts the prefix in
            # front of each name's last component, so a relative prefix moves every output
            # written next to the scenario (also detector files of additional files there and
            # the scenario's <log>) into the run's folder. (Outputs the scenario puts into
            # other folders stay relative to those.)
            self.output_dir.mkdir(parents=True, exist_ok=True)
            args += ["--output-prefix", os.path.relpath(self.output_dir.resolve(), path.parent) + os.sep]
        args += list(cfg.extra_args)
        args += lane_change_args(path, cfg.extra_args, cfg.lanechange_duration_s)
        if cfg.gui:
            if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
                raise ConfigError("--gui needs a display: DISPLAY is not set (run without --gui for embedded libsumo)")
            import traci as api

            args += ["--start", "--quit-on-end"]
        else:
            import libsumo as api
        log.info("starting SUMO (%s): %s", "sumo-gui via TraCI" if cfg.gui else "libsumo", " ".join(args))
        try:
            api.start(args)
        except Exception as e:  # libsumo.TraCIException, traci.FatalTraCIError, OSError
            raise ConfigError(f"{path}: SUMO could not load the scenario ({_exc_text(e)}); "
                              "SUMO's own messages are above") from None
        self.api = api
        # libsumo's SWIG function itself, without its Python wrapper (called per vehicle)
        self._vehicle_results = getattr(getattr(api, "_libsumo", None), "vehicle_getSubscriptionResults",
                                        api.vehicle.getSubscriptionResults)
        self._dt = float(api.simulation.getDeltaT())
        self._log_choices()
        try:
            self._after_start()
        except Exception:
            self.close()
            raise

    def _after_start(self) -> None:
        api = self.api
        self.graph = LaneGraph.from_sumo(api)
        self._lane_index = dict(self.graph.index)
        self._lane_index[""] = -1
        self.vtypes = VTypeTable(api)
        for t in api.vehicletype.getIDList():
            self.vtypes.add(t)
        self.tls_ids = list(api.trafficlight.getIDList()) if self.cfg.traffic_lights else []
        for t in self.tls_ids:
            api.trafficlight.subscribe(t, TLS_VARS)
        graph = self.graph
        self.tls = TlsTable(api, self.tls_ids, lambda ids: tls_link_table(api, graph, ids))
        # Agents already present (e.g. a loaded state) are subscribed now, the rest on departure.
        for v in api.vehicle.getIDList():
            self._subscribe_vehicle(v)
        if self.cfg.persons:
            for p in api.person.getIDList():
                api.person.subscribe(p, PERSON_VARS)
        self.begin_time = float(api.simulation.getTime())
        try:
            self.end_time = float(api.simulation.getEndTime())
        except Exception:  # older SUMO: no getEndTime
            self.end_time = -1.0
        net_file = self.net_file = self._net_file()
        self.static = build_static(
            api, self.graph, self.run_id, self.step_length, net_file,
            list(self.vtypes.types), self.vtypes.length.copy(), self.vtypes.width.copy(), self.tls_ids,
        )
        self._static_version = -1
        self.static_data()
        log.info(
            "SUMO scenario %s: %d lanes, %d junctions, %d traffic lights, %d vehicle types",
            self.sumocfg.name, self.graph.n, len(self.static.junctions.ids), len(self.tls_ids),
            len(self.vtypes.types),
        )

    @property
    def static_version(self) -> int:
        """Version of the vType table and the tls links (SPEC.md 3.2); both only grow."""
        return self.vtypes.version + self.tls.version

    def static_data(self) -> StaticData:
        """The static data of the current static version (rebuilt only after a change)."""
        v = self.static_version
        if v != self._static_version:
            vt, k = self.vtypes, len(self.vtypes.types)
            self.static = replace(
                self.static, vtypes=list(vt.types), vtype_length=vt.length[:k].copy(),
                vtype_width=vt.width[:k].copy(), tls_links=self.tls.links, version=v,
            )
            self._static_version = v
        return self.static

    def _log_choices(self) -> None:
        o, cfg = self.options, self.cfg
        if cfg.step_length_s > 0:
            log.info("step length %g s: [sumo] step_length_s replaces the scenario's %g s", self._dt, o.step_length_s)
        else:
            log.info("step length %g s (the scenario's)", self._dt)
        if self.seed is not None:
            log.info("seed %d: the run's seed replaces the scenario's %s", self.seed,
                     "SUMO default" if o.seed is None else o.seed)
        else:
            log.info("seed %s (the scenario's)", "SUMO default" if o.seed is None else o.seed)
        if cfg.begin_s is not None:
            log.info("begin %g s: [sumo] begin_s / --begin replaces the scenario's %g s", cfg.begin_s, o.begin_s)

    def _net_file(self) -> Path | None:
        try:
            value = self.api.simulation.getOption("net-file")
        except Exception:
            return None
        if not value:
            return None
        p = Path(value.split(",")[0])
        return p if p.is_absolute() else (self.sumocfg.parent / p)

    def close(self) -> None:
        if self.api is not None:
            try:
                self.api.close()
            except Exception as e:  # closing twice or after SUMO ended on its own
                log.debug("closing SUMO: %s", e)
            self.api = None

    def trips(self) -> dict:
        """SUMO's own account of the vehicles so far: trips ended (``trips_arrived``) with their
        mean travel time, time loss, waiting time and route length from the tripinfo device,
        vehicles inserted and still running, and ``vanished``: inserted vehicles that neither
        arrived nor are still running (removed by a collision or teleport rule, or lost)."""
        if self.api is None:
            return {}
        sim = self.api.simulation

        def num(key: str) -> float:
            try:
                return float(sim.getParameter("", key))
            except Exception:  # an older SUMO without the key
                return float("nan")

        inserted, running = num("stats.vehicles.inserted"), num("stats.vehicles.running")
        arrived = self.counters["arrived"]
        out = {
            "trips_arrived": arrived,
            "vehicles_inserted": int(inserted) if inserted == inserted else None,
            "vehicles_running_end": int(running) if running == running else None,
            "vanished": int(inserted - arrived - running) if inserted == inserted and running == running else None,
        }
        for name, key in (("travel_time_mean_s", "duration"), ("time_loss_mean_s", "timeLoss"),
                          ("waiting_time_mean_s", "waitingTime"), ("route_length_mean_m", "routeLength")):
            v = num(f"device.tripinfo.{key}")
            out[name] = round(v, 3) if v == v and arrived else None
        return out

    @property
    def step_length(self) -> float:
        """SUMO's step length [s] (``simulation.getDeltaT()`` once started)."""
        return self._dt

    def time(self) -> float:
        return float(self.api.simulation.getTime())

    def finished(self, duration_s: float, keep_empty: bool = False) -> str:
        """Why nothing is left to simulate ('' while there is): the run's duration (counted
        from the begin time), SUMO's end time, or no more traffic, whichever comes first.
        ``keep_empty``: an empty network does not end the run (an outside ego may come back)."""
        t = self.time()
        if duration_s > 0 and t >= self.begin_time + duration_s - 1e-9:
            return f"duration {duration_s:g} s reached"
        if self.end_time >= 0 and t >= self.end_time - 1e-9:
            return f"the scenario's end time {self.end_time:g} s reached"
        if not keep_empty and self.api.simulation.getMinExpectedNumber() <= 0:
            return "no traffic left in the scenario"
        return ""

    # ------------------------------------------------------------------ per step

    def _subscribe_vehicle(self, vid: str) -> None:
        self.api.vehicle.subscribe(vid, VEHICLE_VARS)

    def step(self) -> None:
        """SUMO's own step (timed separately as sumo_ms by the callers)."""
        try:
            self.api.simulationStep()
        except self.errors as e:
            raise SumoFailed(f"SUMO failed in the step after t={self._prev.time:g} s: {_exc_text(e)}") from None

    @property
    def errors(self) -> tuple[type[BaseException], ...]:
        """Exception types by which libsumo / TraCI report a failed call."""
        if self.cfg.gui:
            import traci

            return (traci.TraCIException, traci.FatalTraCIError)
        return (_C.TraCIException, _C.FatalTraCIError)

    def read(self) -> Snapshot:
        """Subscribe the agents that departed in the last step and read every agent."""
        try:
            return self._read()
        except self.errors as e:
            raise SumoFailed(f"SUMO failed while reading the step after t={self._prev.time:g} s: "
                             f"{_exc_text(e)}") from None

    def _read(self) -> Snapshot:
        # Reading, then what follows from the previous snapshot, then this one becomes the
        # previous one: the order matters (vType indices grow while reading, in SUMO's order).
        ev = self._take_events()
        now = float(self.api.simulation.getTime())
        veh, per = self._read_vehicles(), self._read_persons()
        ids = veh.ids + per.ids
        nv = len(veh.ids)
        xy = np.concatenate([veh.xy, per.xy])
        speed = np.concatenate([veh.speed, per.speed])
        vtype = np.concatenate([veh.vtype, per.vtype])
        route = np.array(veh.route, dtype=object)
        prev, prev_index = self._prev, self._align(ids)
        dt = now - prev.time if now > prev.time else self.step_length
        accel = _acceleration(speed, prev.speed, prev_index, dt)
        self.vtypes.collect(vtype)  # bounded table: drops types nobody uses any more
        jumped = _jumped(xy, speed, prev, prev_index, dt, _jump_margins(len(ids), nv, per.riding))
        route_changed = _route_changed(route, prev.route, prev_index, nv)
        self._prev = _Previous(ids=ids, speed=speed, time=now, xy=xy, route=route)
        self._serial += 1
        teleported = _members(ids, ev.teleported)
        if teleported is not None:
            accel[teleported] = 0.0  # SUMO, too, reports 0 when a teleport changes the speed
        return Snapshot(
            time=now,
            ids=ids,
            x=xy[:, 0].copy(),
            y=xy[:, 1].copy(),
            angle=np.concatenate([veh.angle, per.angle]),
            speed=speed,
            accel=accel,
            signals=np.concatenate([veh.signals, per.signals]),
            lane=np.concatenate([veh.lane, per.lane]),
            lane_pos=np.concatenate([veh.lane_pos, per.lane_pos]),
            vtype=vtype,
            flags=_flags(ids, nv, per.riding, jumped, _members(ids, ev.new), teleported),
            mode=_modes(len(ids), nv, per.riding),
            n_vehicles=nv,
            tls=self.read_tls(),
            departed=ev.departed,
            arrived=ev.arrived,
            teleports=ev.teleports,
            prev_index=prev_index,
            serial=self._serial,
            route_changed=route_changed,
        )

    def _take_events(self) -> _Events:
        """Departures (subscribed now), arrivals and teleports of the last step, counted."""
        api = self.api
        sim = api.simulation
        departed = sim.getDepartedIDList()
        for v in departed:
            self._subscribe_vehicle(v)
        p_departed: tuple = ()
        if self.cfg.persons:
            p_departed = sim.getDepartedPersonIDList()
            for p in p_departed:
                api.person.subscribe(p, PERSON_VARS)
        ev = _Events(
            new={*departed, *p_departed},
            departed=len(departed) + len(p_departed),
            arrived=list(sim.getArrivedIDList()),
            teleported=set(sim.getStartingTeleportIDList()) | set(sim.getEndingTeleportIDList()),
            teleports=sim.getStartingTeleportNumber(),
        )
        c = self.counters
        c["departed"] += len(departed)
        c["persons_departed"] += len(p_departed)
        c["arrived"] += len(ev.arrived)
        c["teleports"] += ev.teleports
        return ev

    def _read_vehicles(self) -> _Columns:
        """Every vehicle's subscribed variables as columns."""
        vids = list(self.api.vehicle.getIDList())
        if vids and _fast is not None:
            cols = self._read_vehicles_fast(vids)
            if cols is not None:
                return cols
        vids, values = self._vehicle_values(vids)
        nv = len(vids)
        if not nv:
            return _Columns.none()
        pos, angle, speed, sig, lpos, lanes, types, route = values
        num = np.array((angle, speed, sig, lpos), np.float64)
        return _Columns(
            ids=vids,
            xy=np.fromiter(_chain(pos), np.float64, 2 * nv).reshape(nv, 2),
            angle=num[0],
            speed=num[1],
            lane_pos=num[3],
            lane=_lookup(self._lane_index, lanes),
            vtype=self.vtypes.indices(types),  # every step, so that a vehicle.setType shows in its step
            signals=num[2].astype(np.int64),
            route=list(route),
            riding=np.zeros(0, bool),
        )

    def _read_vehicles_fast(self, vids: list[str]) -> _Columns | None:
        """``_read_vehicles`` through ``_fastread`` (None: it stepped aside, run the Python path).

        One ``getSubscriptionResults`` per vehicle, each dict read and dropped at once: at
        10,000 vehicles the Python path holds them all and walks them cache-cold (see
        ``_vehicle_values``). New vTypes are added in the vehicles' order, as there.
        """
        n = len(vids)
        f = np.empty(5 * n)  # x, y interleaved; angle; speed; lane position
        i = np.empty(3 * n, np.int64)  # signals; lane index; vType index
        vt = self.vtypes
        route = _fast.read_vehicles(self._vehicle_results, vids, self._lane_index, vt.index, vt.add, f, i)
        if route is None:
            return None
        return _Columns(
            ids=vids, xy=f[: 2 * n].reshape(n, 2), angle=f[2 * n : 3 * n], speed=f[3 * n : 4 * n],
            lane_pos=f[4 * n :], lane=i[n : 2 * n], vtype=i[2 * n :], signals=i[:n], route=route,
            riding=np.zeros(0, bool),
        )

    def _vehicle_values(self, vids: list[str]) -> tuple[list[str], tuple]:
        """The vehicles that have subscription results, and one tuple per ``_VEHICLE_ROW`` variable."""
        if not vids:
            return vids, ()
        # One ``getSubscriptionResults`` per vehicle, not ``getAllSubscriptionResults``:
        # libsumo copies the whole result map for the latter (measured at 10,000 vehicles:
        # 30 ms against 60-70 ms for the same dicts). The dicts are fresh and cache-cold:
        # one C-level pass (itemgetter) takes every variable out of each, ``zip`` makes the
        # columns (21 ms against 25 ms for one pass per variable).
        rows = list(map(self._vehicle_results, vids))
        try:
            return vids, tuple(zip(*map(_VEHICLE_ROW, rows)))
        except (KeyError, TypeError):
            # A vehicle without a subscription (an ego being removed) is left out, as
            # getAllSubscriptionResults would; one subscribed without some variable gets
            # them from getters.
            kept = [(v, r) for v, r in zip(vids, rows) if r]
            return [v for v, _ in kept], tuple(zip(*(self._vehicle_row(v, r) for v, r in kept)))

    def _read_persons(self) -> _Columns:
        """Every person's subscribed variables as columns (none unless ``cfg.persons``)."""
        api = self.api
        pids = list(api.person.getIDList()) if self.cfg.persons else []
        npers = len(pids)
        if not npers:
            return _Columns.none()
        prow = list(map(api.person.getSubscriptionResults, pids))
        try:
            pos, angle, speed, lpos, lanes, types, vehicle = zip(*map(_PERSON_ROW, prow))
        except (KeyError, TypeError):  # a person not subscribed (yet): subscribe and read it
            for p, r in zip(pids, prow):
                if not r or any(k not in r for k in PERSON_VARS):
                    api.person.subscribe(p, PERSON_VARS)
            prow = list(map(api.person.getSubscriptionResults, pids))
            pos, angle, speed, lpos, lanes, types, vehicle = zip(*map(_PERSON_ROW, prow))
        return _Columns(
            ids=pids,
            xy=np.array(pos, np.float64).reshape(npers, -1)[:, :2],
            angle=np.array(angle, np.float64),
            speed=np.array(speed, np.float64),
            lane_pos=np.array(lpos, np.float64),
            lane=_lookup(self._lane_index, lanes),
            vtype=self.vtypes.indices(list(types)),
            signals=np.zeros(npers, np.int64),
            route=[],
            riding=np.array([bool(v) for v in vehicle], bool),
        )

    def _vehicle_row(self, vid: str, r: dict | None) -> tuple:
        """One vehicle's ``_VEHICLE_ROW`` when its subscription lacks variables (getters)."""
        v = self.api.vehicle
        r = r or {}
        return (r.get(V_POS) or v.getPosition(vid), r[V_ANGLE] if V_ANGLE in r else v.getAngle(vid),
                r[V_SPEED] if V_SPEED in r else v.getSpeed(vid),
                r[V_SIGNALS] if V_SIGNALS in r else v.getSignals(vid),
                r[V_LANEPOS] if V_LANEPOS in r else v.getLanePosition(vid),
                r[V_LANE] if V_LANE in r else v.getLaneID(vid), r.get(V_TYPE) or v.getTypeID(vid),
                r[V_ROUTE] if V_ROUTE in r else v.getRouteID(vid))

    def _align(self, ids: list[str]) -> np.ndarray:
        """Row of each agent in the previous snapshot, -1 for agents new to it."""
        n = len(ids)
        prev = self._prev.ids
        if ids == prev:
            return np.arange(n)
        if not prev:
            return np.full(n, -1, np.int64)
        where = dict(zip(prev, range(len(prev))))
        return np.fromiter(map(where.get, ids, _repeat_minus_one(n)), np.int64, n)

    def read_tls(self) -> TrafficLights:
        if not self.tls_ids:
            return TrafficLights.empty()
        res = self.api.trafficlight.getAllSubscriptionResults()
        now = float(self.api.simulation.getTime())
        rows = [res[t] for t in self.tls_ids]
        programs = [r[TL_PROGRAM] for r in rows]
        if self.tls.update(programs):
            log.info("traffic-light links changed with a program switch (static version %d)", self.static_version)
        return TrafficLights(
            ids=list(self.tls_ids),
            state=[r[TL_STATE] for r in rows],
            phase=np.fromiter((r[TL_PHASE] for r in rows), np.int32, len(rows)),
            # A program without phases (old nets) reports ~1e15 s: "no switch scheduled" is
            # NO_SWITCH_S on the wire, inside the range receivers accept.
            next_switch=np.nan_to_num(
                np.clip(np.fromiter((r[TL_NEXT] - now for r in rows), np.float64, len(rows)), -NO_SWITCH_S, NO_SWITCH_S),
                nan=NO_SWITCH_S,
            ).astype(np.float32),
            program=programs,
        )

    def route_of(self, vehicle_id: str) -> tuple[tuple[str, ...], int]:
        """Route edges and route index of a vehicle (called only when its lane changes)."""
        veh = self.api.vehicle
        try:
            return tuple(veh.getRoute(vehicle_id)), int(veh.getRouteIndex(vehicle_id))
        except Exception:  # the vehicle left between read and resolve
            return (), -1


def _acceleration(speed: np.ndarray, prev_speed: np.ndarray, prev_index: np.ndarray, dt: float) -> np.ndarray:
    """Acceleration [m/s^2] from consecutive speeds; 0 in an agent's first step.

    SUMO defines it exactly so ((v - v_prev) / step length, checked against
    getAcceleration), and it saves a subscribed variable (~0.5 ms per step at 2,500 vehicles).
    """
    known = prev_index >= 0
    accel = np.zeros(len(speed))
    if known.any():
        accel[known] = (speed[known] - prev_speed[prev_index[known]]) / dt
    return accel


def _jump_margins(n: int, nv: int, riding: np.ndarray) -> np.ndarray:
    """[m] per agent: how far beyond its speed x step an agent may move before it jumped."""
    margin = np.full(n, JUMP_MARGIN_M)
    margin[nv:][~riding] = PERSON_JUMP_MARGIN_M
    return margin


def _jumped(xy: np.ndarray, speed: np.ndarray, prev: _Previous, prev_index: np.ndarray, dt: float,
            margin: np.ndarray) -> np.ndarray:
    """True for agents whose position change no motion explains.

    A person starting to wait at a stop far from where it walked, a stage change,
    moveToXY, a walker put onto a crossing: physics must place, not steer. A vehicle's
    margin covers SUMO's instant lane changes (one lane width).
    """
    known = prev_index >= 0
    jumped = np.zeros(len(xy), bool)
    if known.any() and len(prev.xy):
        pk = prev_index[known]
        moved = np.hypot(*(xy[known] - prev.xy[pk]).T)
        reach = np.maximum(speed[known], prev.speed[pk]) * dt + margin[known]
        jumped[known] = moved > reach
    return jumped


def _route_changed(route: np.ndarray, prev_route: np.ndarray, prev_index: np.ndarray, nv: int) -> np.ndarray:
    """True for vehicles (the first ``nv`` rows) with a new route id: rerouted.

    Object-array compare: one C loop, no Python per agent.
    """
    changed = np.zeros(len(prev_index), bool)
    if nv and len(prev_route):
        jv = prev_index[:nv]
        had = (jv >= 0) & (jv < len(prev_route))
        changed[:nv] = had & (route != prev_route[np.where(had, jv, 0)])
    return changed


def _members(ids: list[str], names: set[str]) -> np.ndarray | None:
    """True where ``ids`` is in ``names`` (None when ``names`` is empty: nothing to mark)."""
    if not names:
        return None
    return np.fromiter(map(names.__contains__, ids), bool, len(ids))


def _flags(ids: list[str], nv: int, riding: np.ndarray, jumped: np.ndarray, new: np.ndarray | None,
           teleported: np.ndarray | None) -> np.ndarray:
    """``AgentFlag`` bits per agent (persons follow the ``nv`` vehicles)."""
    flags = np.zeros(len(ids), np.uint8)
    flags[nv:][riding] = AgentFlag.INSIDE_VEHICLE
    flags[jumped] |= np.uint8(AgentFlag.JUMPED)
    if new is not None:
        flags[new] |= np.uint8(AgentFlag.NEW)
    if teleported is not None:
        flags[teleported] |= np.uint8(AgentFlag.JUMPED)
    return flags


def _modes(n: int, nv: int, riding: np.ndarray) -> np.ndarray:
    """Look-ahead mode per agent: vehicles follow lanes, walkers go straight, riders none."""
    mode = np.full(n, MODE_LANES, np.uint8)
    mode[nv:] = np.where(riding, MODE_NONE, MODE_STRAIGHT)
    return mode


def _lookup(table: dict[str, int], keys: tuple) -> np.ndarray:
    """``table[k]`` for every key as int64 (one C call); unknown keys give -1."""
    if len(keys) == 1:
        return np.array([table.get(keys[0], -1)], np.int64)
    try:
        return np.array(operator.itemgetter(*keys)(table), np.int64)
    except KeyError:
        return np.fromiter(map(table.get, keys, _repeat_minus_one(len(keys))), np.int64, len(keys))


def _repeat_minus_one(n: int):
    from itertools import repeat

    return repeat(-1, n)


def _exc_text(e: BaseException) -> str:
    """SUMO's message on one line (SUMO wraps long ones)."""
    text = str(e)
    if not text or text.startswith("<libsumo"):
        get = getattr(e, "getString", None)
        text = get() if callable(get) else type(e).__name__
    return " ".join(text.split())
