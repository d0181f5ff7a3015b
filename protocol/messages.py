"""Message types of the sumoco wire protocol (see SPEC.md for the byte layout).

Every positional field is in SUMO's network frame unless it says otherwise:
x east [m], y north [m], positions at the *front-bumper centre* of a vehicle, angles in
degrees clockwise from north (SUMO's convention). ``protocol.frames`` converts to the
MuJoCo world frame in one place.

Per-agent data is columnar: one numpy array per field, all of the same length ``n``,
so both sides work on whole arrays and the codec moves raw little-endian buffers.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

#: Protocol version (major, minor). A different major is rejected by the decoder.
SCHEMA_VERSION: tuple[int, int] = (1, 4)  # 1.1: StaticData.tls_links; 1.2: anchored positions, static version;
# 1.3: two-way coupling (AgentFlag.PHYSICS_AUTHORITY, PhysicsFeedback); 1.4: run incarnations (epoch)


class AgentClass(IntEnum):
    """Agent class on the wire: which physical model an agent needs."""

    PASSENGER = 0
    TAXI = 1
    BUS = 2
    BICYCLE = 3
    PEDESTRIAN = 4
    OTHER = 5  # any other SUMO vClass; its name travels in the vtype table


#: SUMO vClass name -> agent class. Classes not listed map to OTHER.
VCLASS_TO_AGENT_CLASS: dict[str, AgentClass] = {
    "passenger": AgentClass.PASSENGER,
    "private": AgentClass.PASSENGER,
    "evehicle": AgentClass.PASSENGER,
    "taxi": AgentClass.TAXI,
    "bus": AgentClass.BUS,
    "coach": AgentClass.BUS,
    "bicycle": AgentClass.BICYCLE,
    "pedestrian": AgentClass.PEDESTRIAN,
}


class AgentFlag(IntEnum):
    """Bits of the per-agent ``flags`` field."""

    INSIDE_VEHICLE = 1  # a person riding a vehicle (its pose is the vehicle's)
    EGO = 2  # the externally controlled ego vehicle
    JUMPED = 4  # teleported or moved by moveToXY this step: do not track, place
    NEW = 8  # departed (entered the network) this step
    PHYSICS_AUTHORITY = 16  # two-way coupling: physics owns this vehicle's motion, SUMO follows it


class AgentMode(IntEnum):
    """How the physics side drives an agent (``PhysicsAgents.mode``)."""

    PHYSICAL = 0  # forces and torques through contact (PID + pure pursuit)
    KINEMATIC = 1  # placed at its interpolated SUMO pose (the paper's direct representation)
    EXTERNAL = 2  # the ego: placed where the outside engine says
    STOPPING = 3  # SUMO side gone: braking to a safe stop


def _f32(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)


@dataclass(frozen=True)
class AgentBatch:
    """All agents of one SUMO step, one array per field (length ``n``).

    ``path_offsets`` (uint32, n+1) and ``path_xy`` (float64, (m, 2)) hold each agent's
    path ahead: agent i's polyline is ``path_xy[path_offsets[i]:path_offsets[i+1]]``,
    starting at its front bumper. Both are empty when the sender omits paths. Every
    position here is absolute and float64; the codec sends look-ahead points and paths
    as float32 offsets from the agent's (x, y) (SPEC.md 3.1).
    """

    ids: list[str]
    """Agent id (SUMO vehicle or person id)."""
    cls: np.ndarray
    """Agent class, ``AgentClass`` [uint8]."""
    vtype: np.ndarray
    """Index into ``StepMessage.vtypes`` [uint16]."""
    x: np.ndarray
    """Front-bumper centre x (east) [m, float64]."""
    y: np.ndarray
    """Front-bumper centre y (north) [m, float64]."""
    angle: np.ndarray
    """Heading [deg clockwise from north, float32]."""
    speed: np.ndarray
    """Speed [m/s, float32]."""
    accel: np.ndarray
    """Longitudinal acceleration [m/s^2, float32]."""
    signals: np.ndarray
    """SUMO signal bitmask (blinkers, brake light, ...) [uint16]."""
    la_x: np.ndarray
    """Look-ahead point x [m, float64] (LAD along the path ahead from the SUMO pose)."""
    la_y: np.ndarray
    """Look-ahead point y [m, float64]."""
    length: np.ndarray
    """Length [m, float32]."""
    width: np.ndarray
    """Width [m, float32]."""
    lane: np.ndarray
    """Index into ``StaticData.lanes`` or -1 when not on a lane [int32]."""
    flags: np.ndarray
    """``AgentFlag`` bits [uint8]."""
    path_offsets: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint32))
    """Start of each agent's path in ``path_xy``, length n+1, or empty [uint32]."""
    path_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float64))
    """Path-ahead vertices (x, y) [m, float64, shape (m, 2)]."""

    @property
    def n(self) -> int:
        return len(self.ids)

    @classmethod
    def empty(cls) -> "AgentBatch":
        z = np.zeros(0)
        return cls(
            ids=[], cls=z.astype(np.uint8), vtype=z.astype(np.uint16), x=z.copy(), y=z.copy(),
            angle=_f32(z), speed=_f32(z), accel=_f32(z), signals=z.astype(np.uint16),
            la_x=z.copy(), la_y=z.copy(), length=_f32(z), width=_f32(z),
            lane=z.astype(np.int32), flags=z.astype(np.uint8),
        )

    def path(self, i: int) -> np.ndarray:
        """Path-ahead polyline of agent ``i`` as an (k, 2) array (empty if omitted)."""
        if len(self.path_offsets) == 0:
            return np.zeros((0, 2), np.float64)
        return self.path_xy[self.path_offsets[i] : self.path_offsets[i + 1]]


@dataclass(frozen=True)
class TrafficLights:
    """State of every traffic-light program in one step."""

    ids: list[str]
    """Traffic-light (junction program) id."""
    state: list[str]
    """Full per-link state string, SUMO letters (``rRyYgGuos``), one char per link."""
    phase: np.ndarray
    """Current phase index [int32]."""
    next_switch: np.ndarray
    """Time until the next phase switch [s, float32]."""
    program: list[str] | None = None
    """Active program id per light (since 1.2; None from 1.1 senders)."""

    @classmethod
    def empty(cls) -> "TrafficLights":
        return cls([], [], np.zeros(0, np.int32), np.zeros(0, np.float32), [])


@dataclass(frozen=True)
class VType:
    """A SUMO vehicle type as referenced by ``AgentBatch.vtype``."""

    id: str
    """SUMO vType id."""
    vclass: str
    """SUMO vClass name (``passenger``, ``bus``, ``truck`` ...)."""


@dataclass(frozen=True)
class StepMessage:
    """Everything the SUMO side publishes for one simulation step."""

    run: str
    """Run id (same for every message of one run)."""
    step: int
    """Step index, 0-based, increasing by one per SUMO step."""
    time: float
    """SUMO simulation time after this step [s]."""
    step_length: float
    """SUMO step length [s]."""
    agents: AgentBatch
    tls: TrafficLights
    vtypes: list[VType] | None
    """The vehicle-type table ``agents.vtype`` indexes, or None when this message does not
    carry it (since 1.2 it travels only when it changes: it is then the table of static
    version ``static_version``, also served by the static-data queryable)."""
    static_version: int = 0
    """Version of the static tables (vtypes, tls links) this step refers to; it changes
    whenever one of them changes (since 1.2; 0 from 1.1 senders)."""
    final: bool = False
    """The run's last step: the SUMO side publishes nothing after it (lockstep peers
    acknowledge it and leave)."""
    epoch: int = 0
    """Incarnation of the run: the SUMO side's start time [ns since the Unix epoch], the same
    in every step of one SUMO process (since 1.4; 0 from older senders). ``protocol.order``."""


@dataclass(frozen=True)
class EgoPose:
    """Pose of the externally driven ego vehicle, published by an outside engine."""

    id: str
    """Ego vehicle id in SUMO."""
    x: float
    """Front-bumper centre x [m]."""
    y: float
    """Front-bumper centre y [m]."""
    angle: float
    """Heading [deg clockwise from north]."""
    speed: float
    """Speed [m/s]."""
    time: float = 0.0
    """Sender's clock when the pose was taken [s] (informational)."""
    vtype: str = ""
    """SUMO vType for the ego when the SUMO side has to create it ('' = default)."""


@dataclass(frozen=True)
class CameraPose:
    """Where a viewer or renderer looks: an interest point for the physics level of detail."""

    id: str
    """Client id (equal to the last key chunk before ``camera``)."""
    x: float
    """Ground point the camera is centred on (orbit target), x [m]."""
    y: float
    """Ground point the camera is centred on, y [m]."""
    time: float = 0.0
    """Sender's clock [s] (informational)."""


@dataclass(frozen=True)
class PhysicsAgents:
    """Actual state of every agent in the physics world, one array per field."""

    ids: list[str]
    cls: np.ndarray
    """Agent class [uint8]."""
    mode: np.ndarray
    """``AgentMode`` [uint8]."""
    x: np.ndarray
    """Front-bumper centre x [m, float64]."""
    y: np.ndarray
    """Front-bumper centre y [m, float64]."""
    z: np.ndarray
    """Height of the body origin above the ground plane [m, float32]."""
    heading: np.ndarray
    """Heading [deg clockwise from north, float32]."""
    roll: np.ndarray
    """Roll [deg, positive = right side down, float32]."""
    pitch: np.ndarray
    """Pitch [deg, positive = nose up, float32]."""
    speed: np.ndarray
    """Forward speed [m/s, float32]."""
    steer: np.ndarray
    """Front-wheel steering angle [deg, positive = left, float32]."""
    drive: np.ndarray
    """Drive torque command [N*m, float32]."""
    brake: np.ndarray
    """Brake torque command [N*m, float32]."""
    err_lon: np.ndarray
    """Longitudinal tracking error at the front bumper, + = ahead of reference [m, float32]."""
    err_lat: np.ndarray
    """Lateral tracking error at the front bumper, + = left of reference [m, float32]."""

    @property
    def n(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class PhysicsState:
    """What the physics side publishes per control tick (or every k ticks)."""

    run: str
    tick: int
    """Control tick index, 0-based."""
    time: float
    """Physics simulation time [s]."""
    sumo_step: int
    """Index of the latest SUMO step applied (-1 before the first)."""
    agents: PhysicsAgents
    counters: dict[str, int]
    """Cumulative counters: collisions, placements, rejected, ..."""


@dataclass(frozen=True)
class StepAck:
    """Physics side acknowledges it has applied (and simulated through) a SUMO step."""

    run: str
    step: int
    """Acknowledged SUMO step index."""
    tick: int
    """Physics control tick at which the step was finished."""
    feedback: bool = False
    """Two-way coupling: this instance published the ``PhysicsFeedback`` of this step (since 1.3)."""


@dataclass(frozen=True)
class PhysicsFeedback:
    """Two-way coupling: the physical state of the physics-authoritative vehicles at the end
    of SUMO step ``step``, from the one physics instance SUMO follows (SPEC.md 3.8). The SUMO
    side writes it into SUMO before its step ``step + 1``."""

    run: str
    step: int
    """The SUMO step whose end this state is (the physics time equals that step's time)."""
    time: float
    """Physics time of the state [s]."""
    ids: list[str]
    x: np.ndarray
    """Front-bumper centre x [m, float64]."""
    y: np.ndarray
    """Front-bumper centre y [m, float64]."""
    heading: np.ndarray
    """Heading [deg clockwise from north, float32]."""
    speed: np.ndarray
    """Measured forward speed [m/s, float32]."""
    d_lon: np.ndarray
    """Front bumper's offset along the path from SUMO's sample of ``step`` [m, + = ahead, float32]."""
    d_lat: np.ndarray
    """Front bumper's offset across the path from SUMO's sample [m, + = left, float32]."""
    contact: np.ndarray
    """1 when the body touches another vehicle's body in physics (a collision) [uint8]."""

    @property
    def n(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class SumoStatus:
    """The SUMO side's counters, the reply on ``<root>/<run>/sumo/status`` (informational)."""

    counters: dict[str, float]
    """Counter name -> value (steps, rejected messages, acks, teleports, ...)."""


@dataclass(frozen=True)
class LaneTable:
    """All lanes of the network, internal (junction) lanes, crossings and walking areas included."""

    ids: list[str]
    edge: list[str]
    """Id of the edge the lane belongs to."""
    width: np.ndarray
    """Lane width [m, float32]."""
    length: np.ndarray
    """Lane length [m, float32]."""
    allow: list[list[str]]
    """SUMO vClass names allowed on the lane."""
    shape_offsets: np.ndarray
    """Start of each lane's centre line in ``shape_xy``, length n+1 [uint32]."""
    shape_xy: np.ndarray
    """Centre-line vertices [m, float64, shape (m, 2)]."""


@dataclass(frozen=True)
class JunctionTable:
    ids: list[str]
    shape_offsets: np.ndarray
    """Start of each junction's outline in ``shape_xy``, length n+1 [uint32]."""
    shape_xy: np.ndarray
    """Outline polygon vertices [m, float64, shape (m, 2)]."""


@dataclass(frozen=True)
class TlsLinks:
    """Which lanes each traffic-light link controls: row i is one character of a state string."""

    tls: np.ndarray
    """Index into ``StaticData.tls_ids`` [uint16]."""
    link: np.ndarray
    """Link index = position in that light's state string [uint16]."""
    from_lane: np.ndarray
    """Incoming lane, index into ``StaticData.lanes`` (-1 unknown) [int32]."""
    to_lane: np.ndarray
    """Outgoing lane [int32]."""
    via_lane: np.ndarray
    """Junction-internal lane the link drives through (-1 none) [int32]."""

    @classmethod
    def empty(cls) -> "TlsLinks":
        return cls(np.zeros(0, np.uint16), np.zeros(0, np.uint16), *(np.zeros(0, np.int32) for _ in range(3)))


@dataclass(frozen=True)
class StaticData:
    """Network, vehicle types and traffic-light links (queryable).

    The network never changes during a run; the vehicle-type table and the tls links may,
    and every change gives a new ``version`` (steps carry the version they refer to)."""

    run: str
    step_length: float
    """SUMO step length [s]."""
    net_offset: tuple[float, float]
    """netOffset of the SUMO network [m] (net = projected + offset)."""
    projection: str
    """proj4 parameter string of the network, '!' when not geo-referenced."""
    bounds: tuple[float, float, float, float]
    """Network boundary in net coordinates (xmin, ymin, xmax, ymax) [m]."""
    lanes: LaneTable
    junctions: JunctionTable
    vtypes: list[VType]
    """Vehicle-type table (``StepMessage.agents.vtype`` indexes it)."""
    vtype_length: np.ndarray
    """Length per ``vtypes`` entry [m, float32]."""
    vtype_width: np.ndarray
    """Width per ``vtypes`` entry [m, float32]."""
    tls_ids: list[str]
    """Traffic-light ids."""
    tls_links: TlsLinks = field(default_factory=TlsLinks.empty)
    """Lanes controlled by each traffic-light link (since 1.1; empty from 1.0 senders)."""
    version: int = 0
    """Static version: equals ``StepMessage.static_version`` of the steps it describes
    (since 1.2; 0 from older senders)."""
    epoch: int = 0
    """Incarnation that serves it: equals ``StepMessage.epoch`` of its steps (since 1.4)."""
