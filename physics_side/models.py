"""MuJoCo models of every agent type, built with ``MjSpec`` (pools of them: ``layout``).

Every agent is one kinematic tree rooted at a body named ``agent``:

- **car-like** (passenger, taxi, bus): freejoint chassis, four sphere wheels; the front
  wheels have a steer hinge (z) and a spin hinge (y) in one body, the rear wheels a spin
  hinge. Steering: one position servo per front wheel, so the controller can set Ackermann
  angles. Drive: one motor on a fixed tendon over the driven spin joints with
  coefficients summing to 1, i.e. an open differential whose ``ctrl`` is the total wheel
  torque [N*m]. Brakes: ``dof_frictionloss`` [N*m] of the spin joints, written every
  control tick (Coulomb friction never pushes backwards, unlike reverse torque, which
  flips cars: see FIELD-NOTES).
- **bicycle**: freejoint frame+rider, a steered front wheel, a driven rear wheel, and a
  *roll stabiliser*: a motor on a site transmission that applies a torque about the
  frame's longitudinal axis. The controller drives it with a PD law towards the
  steady-turn lean angle ``atan(v * yaw_rate / g)``, so the bicycle leans into curves like
  a rider would and never falls over; it stands in for the rider's balancing.
- **pedestrian**: a box (SUMO's footprint) on two world-aligned slide joints (x, y) and a yaw hinge,
  moved by three motors with bounded force/torque; no wheels, no gravity load.

Sizes: every agent gets its SUMO length and width (from its vType, sent per agent): a
model *family* per vClass (``VCLASS_FAMILY``: car, taxi, van, truck, bus, tram,
motorcycle, bicycle, pedestrian) builds the body, wheelbase, mass and actuators for the
size, quantised to a 4 % geometric grid (one pool per family and grid size, within 2 %
of SUMO's length and width); the physics side reports the
model's own front bumper. Wheels are spheres (one contact each, the cheapest collision
pair) because the ground is a plane.

Collision filter bits (contype / conaffinity):
ground 1/0, wheels 0/1 (ground only), chassis 2/3 (ground, chassis, pedestrians), bicycle
and motorcycle frames 2/2 (not the ground: a frame box as wide as the handlebars scraped the
road at ~40 deg of lean in SUMO's tight turns and counted as a collision), pedestrians 4/2
(chassis only; SUMO lets pedestrians overlap each other).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from types import MappingProxyType

import mujoco
import numpy as np

from physics_side.control import G
from protocol.messages import AgentClass

# Kinds of model layout, for the world's index tables.
KIND_CAR = 0
KIND_BIKE = 1
KIND_PED = 2
CAR_WHEELS = ("fl", "fr", "rl", "rr")  # a car's wheels, in the order of its brake columns (``layout``)
N_WHEELS = {KIND_CAR: len(CAR_WHEELS), KIND_BIKE: 2, KIND_PED: 0}

#: Agent types by name (config keys) -> AgentClass.
TYPE_NAMES: dict[str, AgentClass] = {
    "passenger": AgentClass.PASSENGER,
    "taxi": AgentClass.TAXI,
    "bus": AgentClass.BUS,
    "bicycle": AgentClass.BICYCLE,
    "pedestrian": AgentClass.PEDESTRIAN,
}

GROUND_FRICTION = (1.0, 0.005, 0.0001)  # sliding, torsional, rolling
CAR_TYRE_MU = 1.3  # [1] tyre-road friction of cars, taxis, vans and bicycles
# Agent bodies (chassis, frames, pedestrians) touch softly: a time constant of 0.1 s
# instead of 0.02 s, so an overlap (a placement next to a lagging neighbour, a crash)
# pushes the agents apart at a few m/s^2 instead of exploding; wheels keep the stiff
# default against the ground.
BODY_CONTACT = dict(solref=[0.1, 1.0], solimp=[0.9, 0.95, 0.01, 0.5, 2.0])
# Collision filter bits (contype / conaffinity, see the module docstring)
GROUND_BIT = 1
BODY_BIT = 2  # chassis and two-wheeler frames
PED_BIT = 4
CONDIM_SLIDING = 3  # contact dimensions: the normal and sliding friction (no torsion, no rolling)
SOLID_SPHERE_INERTIA = 0.4  # [1] a solid sphere's spin inertia / (m r^2): 2/5
STEER_ARMATURE = 0.05  # [kg*m^2 per kg of wheel] a steer hinge's armature
BIKE_TYRE_HALF_WIDTH = 0.03  # [m] half-thickness of a two-wheeler's ellipsoid wheel
WHEEL_RGBA = (0.1, 0.1, 0.1, 1.0)  # colours in MuJoCo's own renderer
CHASSIS_RGBA = (0.6, 0.6, 0.7, 1.0)
PED_RGBA = (0.8, 0.5, 0.3, 1.0)
PED_YAW_DAMPING = 2.0  # [N*m*s/rad] a pedestrian's yaw hinge
PED_YAW_ARMATURE = 1.0  # [kg*m^2]
PED_YAW_TORQUE_MAX = 150.0  # [N*m] its yaw motor's limit (``control.PED_YAW_MAX`` commands within it)
# Rest pose (``rest_pose``): one agent settled on flat ground for REST_SETTLE_S, its wheels
# braked and a two-wheeler held upright by a stiff roll PD
REST_SETTLE_S = 1.0  # [s]
REST_BRAKE = 50.0  # [N*m] per spin joint
REST_ROLL_KP = 2000.0  # [N*m/rad]
REST_ROLL_KD = 200.0  # [N*m*s/rad]


@dataclass(frozen=True)
class AgentSpec:
    """Physical parameters of one model size (all SI units)."""

    name: str
    """Pool name, e.g. ``car_5x1.8`` (unique per family and size)."""
    kind: int
    """KIND_CAR, KIND_BIKE or KIND_PED."""
    cls: AgentClass
    length: float
    """Overall length [m]; the body origin is at its middle."""
    width: float
    """Overall width [m]."""
    height: float
    """Body height [m]."""
    mass: float
    """Chassis (plus rider) mass [kg], wheels excluded."""
    com_height: float = 0.55
    """Centre of mass above the ground [m]."""
    wheelbase: float = 0.0
    """Distance front to rear axle [m] (0 for pedestrians)."""
    track: float = 0.0
    """Distance between left and right wheel centres [m] (0 for single track)."""
    wheel_radius: float = 0.3
    """[m]."""
    wheel_mass: float = 20.0
    """Per wheel [kg]."""
    clearance: float = 0.25
    """Chassis box bottom above the ground [m]."""
    max_steer_deg: float = 35.0
    """Road-wheel steering limit [deg]."""
    rear_steer_deg: float = 0.0
    """Rear-axle steering limit [deg]; 0: a fixed rear axle. Long vehicles steer both axles
    so that the body lies on SUMO's chord between its front and back on the lane."""
    max_drive: float = 2500.0
    """Total drive torque limit [N*m] (pedestrians: force [N])."""
    max_brake: float = 5000.0
    """Total brake torque limit [N*m]."""
    awd: bool = False
    """All-wheel drive (default rear-wheel drive)."""
    steer_kp: float = 3000.0
    """Steering servo stiffness [N*m/rad]."""
    steer_kv: float = 150.0
    """Steering servo damping [N*m*s/rad]."""
    stab_max: float = 1500.0
    """Bicycle roll stabiliser torque limit [N*m]."""
    ped_max_force: float = 300.0
    """Pedestrian planar force limit [N] (~0.4 g for 70 kg)."""
    brake_front: float = 0.6
    """Share of brake torque on the front axle."""
    tyre_mu: float = 1.0
    """Tyre-road sliding friction [1]."""
    traction_control: bool = False
    """A spinning driven wheel is braked (heavy vehicles' ASR: ``world.traction_control``)."""

    @property
    def front_offset(self) -> float:
        """Body origin -> front bumper along the heading [m]."""
        return 0.5 * self.length

    @property
    def rear_axle(self) -> float:
        """Body origin -> rear axle along the heading [m] (negative = behind)."""
        return -0.5 * self.wheelbase

    @property
    def wheel_inertia(self) -> float:
        """Spin inertia of one sphere wheel [kg*m^2]."""
        return SOLID_SPHERE_INERTIA * self.wheel_mass * self.wheel_radius**2

    @property
    def n_wheels(self) -> int:
        return N_WHEELS[self.kind]

    @property
    def total_mass(self) -> float:
        return self.mass + self.n_wheels * self.wheel_mass

    @property
    def drive_grip(self) -> float:
        """Force the driven wheels of a vehicle carry when pulling away [N]: tyre mu times the
        driven axles' load. The axles sit symmetric about the body, so a rear axle (a
        two-wheeler's rear wheel) carries half the weight at rest, plus the load that
        accelerating moves onto it (COM height / wheelbase): at the grip limit
        ``a = mu g / 2 / (1 - mu h / L)``. Infinite for pedestrians."""
        if self.kind == KIND_PED:
            return math.inf
        if self.awd:
            return self.tyre_mu * G * self.total_mass
        share = min(0.5 / max(1.0 - self.tyre_mu * self.com_height / self.wheelbase, 0.5), 1.0)
        return self.tyre_mu * G * self.total_mass * share

    @property
    def roll_stiffness(self) -> float:
        """Gravity's toppling moment per radian of lean about the ground line [N*m/rad]
        (total mass * g * COM height, small angles): a roll stabiliser must be stiffer."""
        h = (self.mass * self.com_height + self.n_wheels * self.wheel_mass * self.wheel_radius) / self.total_mass
        return self.total_mass * G * h

    @property
    def effective_mass(self) -> float:
        """Mass seen by the drive: body plus wheel spin inertia / r^2 [kg]."""
        if self.kind == KIND_PED:
            return self.mass
        return self.total_mass + self.n_wheels * self.wheel_inertia / self.wheel_radius**2


# --------------------------------------------------------------------------- families
# Each family's parameters (``AgentSpec`` fields, SI units as documented there); those that
# scale with the SUMO size are ratios applied in its builder below.

# Cars: wheelbase ~0.6 of the length, front overhang = rear overhang (symmetric body).
# Tyres mu 1.3 (``CAR_TYRE_MU``, good tyres on dry asphalt, the upper end): SUMO drives
# junction turns at up to ~10 m/s^2 of lateral acceleration; with mu 1.0 cars ran 1-1.5 m wide.
CAR_HEIGHT = 1.5  # [m]
CAR_MASS = 1300.0  # [kg] of a car of CAR_AREA footprint; heavier in proportion to its footprint
CAR_AREA = 9.0  # [m^2]
CAR_WHEELBASE_SHARE = 0.6  # [1] of the length
CAR_TRACK_INSET = 0.25  # [m] track = width - this
CAR_WHEEL_RADIUS = 0.32  # [m]

# Heavy vehicles (bus, coach, truck, tram): 0.5 m wheels, high COM, ~3.5 m/s^2 drive, ~9 m/s^2 brakes.
HEAVY_WHEEL_RADIUS = 0.5  # [m]
HEAVY_TRACK_INSET = 0.4  # [m] track = width - this ...
HEAVY_MIN_TRACK = 1.2  # [m] ... but at least this
# SUMO's coach accelerates at 2.0 m/s^2 (bus 1.2, truck 1.3): ~2 m/s^2 of drive left a coach
# ~6 m behind after every start, so the drive keeps a margin over the fastest
HEAVY_DRIVE_ACCEL = 3.5  # [m/s^2]
HEAVY_DRIVE_MARGIN = 1.3  # [1] drive torque over accel * mass * wheel radius
HEAVY_BRAKE_DECEL = 9.0  # [m/s^2]
HEAVY_BRAKE_MARGIN = 1.2  # [1] brake torque over decel * mass * wheel radius
HEAVY = MappingProxyType(dict(
    com_height=1.0,  # [m]
    tyre_mu=1.0,  # [1]
    wheel_mass=120.0,  # [kg]
    clearance=0.35,  # [m]
    # [deg] city buses and trucks cut their front wheels ~50 deg (a 12 m bus turns within ~11 m)
    max_steer_deg=50.0,
    # [deg] SUMO puts a long body on the chord between its front and back positions on the lane,
    # whatever the turn's radius; a rigid 12-16 m body on a fixed rear axle cuts ~3 m inside
    # a 10 m junction turn (into the next lane) or cannot make it at all. Steering the rear
    # axle too (as articulated buses, trailers and bogies effectively do) keeps it on the chord.
    rear_steer_deg=40.0,
    traction_control=True,
    steer_kp=20_000.0,  # [N*m/rad]
    steer_kv=1_500.0,  # [N*m*s/rad]
))
BUS_MASS = 11_000.0  # [kg] of a BUS_LENGTH bus; heavier in proportion to its length
BUS_LENGTH = 12.0  # [m]
BUS_HEIGHT = 3.0  # [m]
BUS_WHEELBASE_SHARE = 0.5  # [1] of the length
# trucks (SUMO: 7.1 x 2.4 m), trailers as one rigid 16.5 m body, ~12 t per 7 m
TRUCK_MASS = 12_000.0  # [kg] of a TRUCK_LENGTH truck; heavier in proportion to its length
TRUCK_LENGTH = 7.1  # [m]
TRUCK_HEIGHT = 3.4  # [m]
TRUCK_WHEELBASE_SHARE = 0.55  # [1] of the length
TRAM_MASS = 1_300.0  # [kg per m of length] of a TRAM_WIDTH tram; heavier in proportion to its footprint
TRAM_WIDTH = 2.65  # [m]
TRAM_HEIGHT = 3.3  # [m]
TRAM_WHEELBASE_SHARE = 0.45  # [1] of the length

# Delivery vans (SUMO: 6.5 x 2.16 m): taller, heavier, COM 0.8 m
VAN_MASS = 3500.0  # [kg] of a VAN_LENGTH x VAN_WIDTH van; heavier in proportion to its footprint
VAN_LENGTH = 6.5  # [m]
VAN_WIDTH = 2.16  # [m]
VAN_WHEELBASE_SHARE = 0.55  # [1] of the length
VAN_WHEEL_RADIUS = 0.36  # [m]
VAN_TOTAL_MASS = 3800.0  # [kg] the drive and brake torques are sized for (with wheels)
VAN_DRIVE_ACCEL = 3.0  # [m/s^2]
VAN_BRAKE_DECEL = 9.0  # [m/s^2]
VAN = MappingProxyType(dict(
    height=2.5,  # [m]
    com_height=0.8,  # [m]
    wheel_radius=VAN_WHEEL_RADIUS,
    wheel_mass=30.0,  # [kg]
    steer_kp=8000.0,  # [N*m/rad]
    steer_kv=400.0,  # [N*m*s/rad]
))

# Bicycles with their rider. COM 1 m high over a 1 m wheelbase: beyond ~4.9 m/s^2 a bicycle
# lifts a wheel, so drive (~3 m/s^2) and brakes (~4.5 m/s^2) stay below that. Braking unloads
# the rear wheel: with half the brake there it locked at full braking and the bicycle swung
# 26 deg off its lane on a straight. 65 % in front (75 % ran bicycles braking in junction
# turns wide: p95 0.22 -> 0.29 m on a random network). Tyres as cars': SUMO's bicycles take
# junction turns like cars.
BIKE_WHEELBASE_SHARE = 0.62  # [1] of the length
BICYCLE = MappingProxyType(dict(
    height=1.7,  # [m]
    mass=85.0,  # [kg] frame and rider
    com_height=1.0,  # [m]
    wheel_radius=0.34,  # [m]
    wheel_mass=2.0,  # [kg]
    clearance=0.3,  # [m]
    max_steer_deg=35.0,  # [deg]
    max_drive=100.0,  # [N*m]
    max_brake=130.0,  # [N*m]
    brake_front=0.65,  # [1]
    steer_kp=300.0,  # [N*m/rad]
    steer_kv=15.0,  # [N*m*s/rad]
    stab_max=1500.0,  # [N*m]
    tyre_mu=CAR_TYRE_MU,
))

# Motorcycles and mopeds: heavier, lower single-track vehicles. SUMO's motorcycle accelerates
# at 6 and decelerates at 10 m/s^2 (moped 1.1 / 7): with 4 / 6 m/s^2 they overshot SUMO's
# stops by ~6 m. ~8 m/s^2 of drive and ~12 m/s^2 of braking; a stoppie needs g * wheelbase /
# 2 / COM ~ 13. At 10 m/s^2 the rear keeps ~12 % of the load: 85 % front on mu 1.2 tyres
# locked the rear from 9.8 m/s^2, which slid sideways and the motorcycle fell; 90 % front on
# mu 1.3 keeps both wheels rolling to ~10.9 m/s^2 (95 % stopped ~1 m longer where SUMO stops
# it in a turn).
MOTO_WHEELBASE_SHARE = 0.65  # [1] of the length
MOTO_WHEEL_RADIUS = 0.32  # [m]
MOTO_TOTAL_MASS = 280.0  # [kg] with rider and wheels: the drive and brake torques are sized for it
MOTO_DRIVE_ACCEL = 8.0  # [m/s^2]
MOTO_BRAKE_DECEL = 12.0  # [m/s^2]
MOTORCYCLE = MappingProxyType(dict(
    height=1.5,  # [m]
    mass=260.0,  # [kg] frame and rider
    com_height=0.55,  # [m]
    wheel_radius=MOTO_WHEEL_RADIUS,
    wheel_mass=10.0,  # [kg]
    clearance=0.3,  # [m]
    max_steer_deg=35.0,  # [deg]
    brake_front=0.9,  # [1]
    tyre_mu=CAR_TYRE_MU,
    steer_kp=800.0,  # [N*m/rad]
    steer_kv=40.0,  # [N*m*s/rad]
    stab_max=4000.0,  # [N*m]
))

# Pedestrians: SUMO's footprint, no wheels, a bounded planar force.
PEDESTRIAN = MappingProxyType(dict(
    height=1.75,  # [m]
    mass=70.0,  # [kg]
    com_height=0.95,  # [m]
    wheel_radius=0.0,
    wheel_mass=0.0,
    max_drive=300.0,  # [N]
    max_brake=0.0,
    ped_max_force=300.0,  # [N] (~0.4 g)
))


def _car(cls: AgentClass, length: float, width: float, name: str = "", **kw) -> AgentSpec:
    """A car-like model of a SUMO size; ``kw``: other ``AgentSpec`` fields (other families)."""
    kw.setdefault("tyre_mu", CAR_TYRE_MU)
    return AgentSpec(
        name=name or f"{cls.name.lower()}_{length:g}", kind=KIND_CAR, cls=cls, length=length, width=width,
        height=kw.pop("height", CAR_HEIGHT), mass=kw.pop("mass", CAR_MASS * length * width / CAR_AREA),
        wheelbase=kw.pop("wheelbase", CAR_WHEELBASE_SHARE * length), track=kw.pop("track", width - CAR_TRACK_INSET),
        wheel_radius=kw.pop("wheel_radius", CAR_WHEEL_RADIUS), **kw,
    )


def _van(length: float, width: float, name: str) -> AgentSpec:
    return _car(
        AgentClass.PASSENGER, length, width, name=name, mass=VAN_MASS * length * width / (VAN_LENGTH * VAN_WIDTH),
        wheelbase=VAN_WHEELBASE_SHARE * length, max_drive=VAN_DRIVE_ACCEL * VAN_TOTAL_MASS * VAN_WHEEL_RADIUS,
        max_brake=VAN_BRAKE_DECEL * VAN_TOTAL_MASS * VAN_WHEEL_RADIUS, **VAN,
    )


def _heavy(cls: AgentClass, length: float, width: float, name: str, mass: float, height: float,
           wheelbase: float) -> AgentSpec:
    """Bus, coach, truck, tram (``HEAVY``)."""
    return _car(
        cls, length, width, name=name, height=height, mass=mass, wheelbase=wheelbase,
        track=max(width - HEAVY_TRACK_INSET, HEAVY_MIN_TRACK), wheel_radius=HEAVY_WHEEL_RADIUS,
        max_drive=HEAVY_DRIVE_ACCEL * mass * HEAVY_WHEEL_RADIUS * HEAVY_DRIVE_MARGIN,
        max_brake=HEAVY_BRAKE_DECEL * mass * HEAVY_WHEEL_RADIUS * HEAVY_BRAKE_MARGIN, **HEAVY,
    )


def _bus(length: float, width: float = 2.5, name: str = "") -> AgentSpec:
    return _heavy(AgentClass.BUS, length, width, name or f"bus_{length:g}", BUS_MASS * length / BUS_LENGTH,
                  BUS_HEIGHT, BUS_WHEELBASE_SHARE * length)


def _truck(length: float, width: float, name: str) -> AgentSpec:
    return _heavy(AgentClass.BUS, length, width, name, TRUCK_MASS * length / TRUCK_LENGTH, TRUCK_HEIGHT,
                  TRUCK_WHEELBASE_SHARE * length)


def _tram(length: float, width: float, name: str) -> AgentSpec:
    return _heavy(AgentClass.BUS, length, width, name, TRAM_MASS * length * width / TRAM_WIDTH, TRAM_HEIGHT,
                  TRAM_WHEELBASE_SHARE * length)


def _bike(length: float, width: float = 0.65, name: str = "") -> AgentSpec:
    return AgentSpec(
        name=name or f"bicycle_{length:g}", kind=KIND_BIKE, cls=AgentClass.BICYCLE, length=length,
        width=width, wheelbase=BIKE_WHEELBASE_SHARE * length, **BICYCLE,
    )


def _moto(length: float, width: float, name: str) -> AgentSpec:
    """Motorcycle / moped (``MOTORCYCLE``)."""
    return AgentSpec(
        name=name, kind=KIND_BIKE, cls=AgentClass.BICYCLE, length=length, width=width,
        wheelbase=MOTO_WHEELBASE_SHARE * length, max_drive=MOTO_DRIVE_ACCEL * MOTO_TOTAL_MASS * MOTO_WHEEL_RADIUS,
        max_brake=MOTO_BRAKE_DECEL * MOTO_TOTAL_MASS * MOTO_WHEEL_RADIUS, **MOTORCYCLE,
    )


def _ped(length: float = 0.3, width: float = 0.5, name: str = "pedestrian_0.3") -> AgentSpec:
    return AgentSpec(name=name, kind=KIND_PED, cls=AgentClass.PEDESTRIAN, length=length, width=width, **PEDESTRIAN)


# --------------------------------------------------------------------------- sizes

#: Model families: how an agent drives (body proportions, mass, drive, steering); the
#: size comes from its SUMO vType. Each builds an ``AgentSpec`` from length and width [m].
FAMILIES: dict[str, object] = {
    "car": lambda L, W, n: _car(AgentClass.PASSENGER, L, W, name=n),
    "taxi": lambda L, W, n: _car(AgentClass.TAXI, L, W, name=n),
    "van": _van,
    "bus": _bus,
    "truck": _truck,
    "tram": _tram,
    "motorcycle": _moto,
    "bicycle": _bike,
    "pedestrian": _ped,
}

#: SUMO vClass -> model family (every vClass in SUMO's documentation; others by size).
VCLASS_FAMILY: dict[str, str] = {
    "passenger": "car", "private": "car", "evehicle": "car", "emergency": "car", "authority": "car",
    "vip": "car", "hov": "car", "custom1": "car", "custom2": "car", "taxi": "taxi",
    "delivery": "van", "army": "truck", "truck": "truck", "trailer": "truck",
    "bus": "bus", "coach": "bus", "tram": "tram", "rail_urban": "tram", "rail": "tram",
    "rail_electric": "tram", "rail_fast": "tram", "cable_car": "tram", "subway": "tram",
    "motorcycle": "motorcycle", "moped": "motorcycle", "bicycle": "bicycle", "scooter": "bicycle",
    "e_scooter": "bicycle", "pedestrian": "pedestrian", "wheelchair": "pedestrian",
}

#: Family of each wire class when the vClass is unknown.
CLASS_FAMILY: dict[AgentClass, str] = {
    AgentClass.PASSENGER: "car", AgentClass.TAXI: "taxi", AgentClass.BUS: "bus",
    AgentClass.BICYCLE: "bicycle", AgentClass.PEDESTRIAN: "pedestrian",
}

#: SUMO's default size of each wire class (length, width) [m]: the pre-allocated pools'.
DEFAULT_SIZE: dict[AgentClass, tuple[float, float]] = {
    AgentClass.PASSENGER: (5.0, 1.8), AgentClass.TAXI: (5.0, 1.8), AgentClass.BUS: (12.0, 2.5),
    AgentClass.BICYCLE: (1.6, 0.65), AgentClass.PEDESTRIAN: (0.215, 0.478),
}

SIZE_RATIO = 1.04  # a size is the nearest of a geometric grid: length and width within 2 % of SUMO's
SIZE_TOLERANCE = 0.05  # an existing pool this close in length and width is used instead of a new one
_SIZE_BASE = 5.0  # [m] a grid point (SUMO's default car length)
_SIZE_MIN = 0.05  # [m] sizes below this are taken as this (the grid is logarithmic)
_SIZE_DECIMALS = 3  # a grid size is rounded to mm (stable pool names)
TRUCK_FROM_LENGTH = 7.5  # [m] an agent of unknown family this long or longer drives as a truck ...
BICYCLE_UP_TO_LENGTH = 2.5  # [m] ... this short or shorter as a bicycle, else as a car


def family_for(cls: AgentClass | int, vclass: str, length: float) -> str:
    """Model family of an agent: by wire class, for OTHER by vClass, else by length."""
    f = CLASS_FAMILY.get(AgentClass(int(cls))) or VCLASS_FAMILY.get(vclass)
    if f is not None:
        return f
    if length >= TRUCK_FROM_LENGTH:
        return "truck"
    if length <= BICYCLE_UP_TO_LENGTH:
        return "bicycle"
    return "car"


def _grid(x: float) -> int:
    return int(round(math.log(max(float(x), _SIZE_MIN) / _SIZE_BASE) / math.log(SIZE_RATIO)))


def size_key(family: str, length: float, width: float) -> tuple[str, int, int]:
    """Pool key of a family at a size: (family, length step, width step) on the size grid."""
    if family not in FAMILIES:
        raise ValueError(f"unknown model family {family!r} (expected one of {', '.join(FAMILIES)})")
    return family, _grid(length), _grid(width)


@functools.lru_cache(maxsize=None)
def spec_for_key(key: tuple[str, int, int]) -> AgentSpec:
    """The model of a pool key (cached: one spec per family and grid size)."""
    family, li, wi = key
    L = round(_SIZE_BASE * SIZE_RATIO**li, _SIZE_DECIMALS)
    W = round(_SIZE_BASE * SIZE_RATIO**wi, _SIZE_DECIMALS)
    return FAMILIES[family](L, W, f"{family}_{L:g}x{W:g}")


def spec_for_size(family: str, length: float, width: float) -> AgentSpec:
    """The model of a family nearest to a SUMO size (length, width [m])."""
    return spec_for_key(size_key(family, length, width))


def default_key(cls: AgentClass) -> tuple[str, int, int]:
    """Pool key of a wire class at SUMO's default size (the pre-allocated pools)."""
    return size_key(CLASS_FAMILY[AgentClass(cls)], *DEFAULT_SIZE[AgentClass(cls)])


def default_spec(cls: AgentClass) -> AgentSpec:
    return spec_for_key(default_key(cls))


# --------------------------------------------------------------------------- templates


def _box_inertia(m: float, a: float, b: float, c: float) -> list[float]:
    return [m * (b * b + c * c) / 12.0, m * (a * a + c * c) / 12.0, m * (a * a + b * b) / 12.0]


def _wheel(parent, name: str, pos, spec: AgentSpec, steer: bool):
    w = parent.add_body(name=f"w{name}", pos=list(pos))
    if steer:
        lim = math.radians(spec.rear_steer_deg if name.startswith("r") else spec.max_steer_deg)
        w.add_joint(
            name=f"steer_{name}", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1],
            range=[-lim, lim], limited=mujoco.mjtLimited.mjLIMITED_TRUE,
            armature=STEER_ARMATURE * spec.wheel_mass, damping=0.0,
        )
    w.add_joint(name=f"spin_{name}", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 1, 0])
    if spec.kind == KIND_BIKE:
        # A thin ellipsoid: when the bicycle leans, the contact stays in the wheel plane
        # (a sphere's contact would slide under the hub and shift the lean equilibrium).
        shape = dict(type=mujoco.mjtGeom.mjGEOM_ELLIPSOID, size=[spec.wheel_radius, BIKE_TYRE_HALF_WIDTH, spec.wheel_radius])
    else:
        shape = dict(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[spec.wheel_radius, 0, 0])
    w.add_geom(
        name=f"g{name}", **shape, mass=spec.wheel_mass, contype=0, conaffinity=GROUND_BIT, condim=CONDIM_SLIDING,
        friction=[spec.tyre_mu, *GROUND_FRICTION[1:]], rgba=list(WHEEL_RGBA),
    )


def _chassis(b, spec: AgentSpec) -> None:
    r = spec.wheel_radius
    h = spec.height - spec.clearance
    b.add_geom(
        name="chassis", type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[spec.length / 2, spec.width / 2, h / 2],
        pos=[0, 0, spec.clearance + h / 2 - r], density=0.0, contype=BODY_BIT,
        conaffinity=BODY_BIT if spec.kind == KIND_BIKE else BODY_BIT | GROUND_BIT,
        condim=CONDIM_SLIDING, rgba=list(CHASSIS_RGBA), **BODY_CONTACT,
    )
    # Explicit inertia: the COM height matters for load transfer and roll-over, and a
    # uniform box would put it too high.
    b.explicitinertial = True
    b.mass = spec.mass
    b.ipos = [0.0, 0.0, spec.com_height - r]
    b.inertia = _box_inertia(spec.mass, spec.length, spec.width, h)


def driven_wheels(spec: AgentSpec) -> tuple[str, ...]:
    """The wheels a car's drive tendon turns (sharing its torque equally): all four or the rear two."""
    return CAR_WHEELS if spec.awd else CAR_WHEELS[2:]


def car_template(spec: AgentSpec) -> mujoco.MjSpec:
    """Four-wheel Ackermann vehicle; body origin at the footprint centre, axle height."""
    s = mujoco.MjSpec()
    s.compiler.degree = False
    r = spec.wheel_radius
    b = s.worldbody.add_body(name="agent", pos=[0, 0, r])
    b.add_freejoint(name="free")
    _chassis(b, spec)
    xf, xr, y = spec.wheelbase / 2, -spec.wheelbase / 2, spec.track / 2
    _wheel(b, "fl", (xf, y, 0), spec, True)
    _wheel(b, "fr", (xf, -y, 0), spec, True)
    rear = spec.rear_steer_deg > 0
    _wheel(b, "rl", (xr, y, 0), spec, rear)
    _wheel(b, "rr", (xr, -y, 0), spec, rear)
    for w in ("fl", "fr"):
        a = s.add_actuator(name=f"steer_{w}", target=f"steer_{w}", trntype=mujoco.mjtTrn.mjTRN_JOINT)
        a.set_to_position(kp=spec.steer_kp, kv=spec.steer_kv)
    t = s.add_tendon(name="drive")
    driven = driven_wheels(spec)
    for w in driven:
        t.wrap_joint(f"spin_{w}", 1.0 / len(driven))
    a = s.add_actuator(name="drive", target="drive", trntype=mujoco.mjtTrn.mjTRN_TENDON)
    a.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
    a.ctrlrange = [-spec.max_drive, spec.max_drive]
    if rear:  # after the drive: the first three actuators of every car stay (steer, steer, drive)
        for w in ("rl", "rr"):
            a = s.add_actuator(name=f"steer_{w}", target=f"steer_{w}", trntype=mujoco.mjtTrn.mjTRN_JOINT)
            a.set_to_position(kp=spec.steer_kp, kv=spec.steer_kv)
    return s


def bike_template(spec: AgentSpec) -> mujoco.MjSpec:
    """Single-track vehicle with a roll stabiliser (see module docstring)."""
    s = mujoco.MjSpec()
    s.compiler.degree = False
    r = spec.wheel_radius
    b = s.worldbody.add_body(name="agent", pos=[0, 0, r])
    b.add_freejoint(name="free")
    _chassis(b, spec)
    b.add_site(name="stab", pos=[0, 0, 0])
    _wheel(b, "f", (spec.wheelbase / 2, 0, 0), spec, True)
    _wheel(b, "r", (-spec.wheelbase / 2, 0, 0), spec, False)
    a = s.add_actuator(name="steer", target="steer_f", trntype=mujoco.mjtTrn.mjTRN_JOINT)
    a.set_to_position(kp=spec.steer_kp, kv=spec.steer_kv)
    a = s.add_actuator(name="drive", target="spin_r", trntype=mujoco.mjtTrn.mjTRN_JOINT)
    a.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
    a.ctrlrange = [-spec.max_drive, spec.max_drive]
    a = s.add_actuator(name="stab", target="stab", trntype=mujoco.mjtTrn.mjTRN_SITE)
    a.gear = [0, 0, 0, 1, 0, 0]  # torque about the frame's x (forward) axis
    a.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
    a.ctrlrange = [-spec.stab_max, spec.stab_max]
    return s


def ped_template(spec: AgentSpec) -> mujoco.MjSpec:
    """Planar pedestrian: slide x, slide y (world axes), yaw hinge, bounded motors."""
    s = mujoco.MjSpec()
    s.compiler.degree = False
    b = s.worldbody.add_body(name="agent", pos=[0, 0, 0])
    b.add_joint(name="px", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[1, 0, 0])
    b.add_joint(name="py", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 1, 0])
    b.add_joint(name="yaw", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1], damping=PED_YAW_DAMPING,
                armature=PED_YAW_ARMATURE)
    # SUMO's footprint (0.215 m deep, 0.478 m wide by default) as a box: a capsule of the
    # width's radius stood 0.13 m further out front and back, into passing buses at crossings
    b.add_geom(
        name="chassis", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.5 * spec.length, 0.5 * spec.width, 0.5 * spec.height],
        pos=[0, 0, 0.5 * spec.height], mass=spec.mass, contype=PED_BIT, conaffinity=BODY_BIT,
        condim=CONDIM_SLIDING, rgba=list(PED_RGBA), **BODY_CONTACT,
    )
    motors = (("fx", "px", spec.ped_max_force), ("fy", "py", spec.ped_max_force), ("tz", "yaw", PED_YAW_TORQUE_MAX))
    for name, j, lim in motors:
        a = s.add_actuator(name=name, target=j, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        a.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        a.ctrlrange = [-lim, lim]
    return s


def template(spec: AgentSpec) -> mujoco.MjSpec:
    return {KIND_CAR: car_template, KIND_BIKE: bike_template, KIND_PED: ped_template}[spec.kind](spec)


def set_world_options(s: mujoco.MjSpec, timestep: float) -> None:
    s.compiler.degree = False  # every angle in these specs is in radians
    s.option.timestep = timestep
    # implicitfast at 5 ms is stable at the friction limit (FIELD-NOTES); 20 ms rolled cars.
    s.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    s.option.enableflags |= int(mujoco.mjtEnableBit.mjENBL_SLEEP)
    # Island discovery costs ~15 % of a step with hundreds of independent cars and buys
    # nothing here (Newton converges in 1-2 iterations); sleeping still works per tree.
    s.option.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_ISLAND)


def add_ground(s: mujoco.MjSpec) -> None:
    s.worldbody.add_geom(
        name="ground", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1], contype=GROUND_BIT, conaffinity=0,
        friction=list(GROUND_FRICTION),
    )
    # One acceleration-stage sensor makes MuJoCo compute cfrc_ext (per-body contact
    # forces) in one O(ncon) pass; the world reads it to count agent-agent contacts.
    s.worldbody.add_site(name="probe")
    s.add_sensor(
        name="probe", type=mujoco.mjtSensor.mjSENS_FRAMELINACC,
        objtype=mujoco.mjtObj.mjOBJ_SITE, objname="probe",
    )


# --------------------------------------------------------------------------- rest pose


@dataclass(frozen=True)
class RestPose:
    """Settled pose of a template on flat ground (spawning there avoids a transient)."""

    z: float
    """Body origin height [m]."""
    pitch: float
    """[rad]."""


@functools.lru_cache(maxsize=None)
def rest_pose(spec: AgentSpec, timestep: float = 0.005) -> RestPose:
    """Settle one agent on the ground for 1 s and record its body height and pitch."""
    if spec.kind == KIND_PED:
        return RestPose(0.0, 0.0)
    s = mujoco.MjSpec()
    s.copy_during_attach = True
    set_world_options(s, timestep)
    s.option.enableflags &= ~int(mujoco.mjtEnableBit.mjENBL_SLEEP)
    add_ground(s)
    f = s.worldbody.add_frame(pos=[0, 0, 0])
    f.attach_body(template(spec).body("agent"), "a/")
    m = s.compile()
    d = mujoco.MjData(m)
    # Hold the wheels with the brakes so the settle does not roll.
    m.dof_frictionloss[6:] = REST_BRAKE  # (every dof after the freejoint's six)
    for _ in range(int(REST_SETTLE_S / timestep)):
        if spec.kind == KIND_BIKE:
            # keep the bike upright while it settles
            q = d.qpos[3:7]
            roll = math.atan2(2 * (q[0] * q[1] + q[2] * q[3]), 1 - 2 * (q[1] ** 2 + q[2] ** 2))
            d.ctrl[m.actuator("a/stab").id] = -REST_ROLL_KP * roll - REST_ROLL_KD * d.qvel[3]
        mujoco.mj_step(m, d)
    q = d.qpos[3:7]
    pitch = math.asin(max(-1.0, min(1.0, 2 * (q[0] * q[2] - q[3] * q[1]))))
    return RestPose(float(d.qpos[2]), float(pitch))


def with_awd(spec: AgentSpec, awd: bool) -> AgentSpec:
    return spec if spec.awd == awd else replace(spec, awd=awd, name=spec.name + ("_awd" if awd else ""))


__all__ = [
    "AgentSpec", "CLASS_FAMILY", "DEFAULT_SIZE", "FAMILIES", "KIND_BIKE", "KIND_CAR", "KIND_PED", "RestPose",
    "SIZE_RATIO", "SIZE_TOLERANCE", "TYPE_NAMES", "VCLASS_FAMILY", "add_ground", "default_key", "default_spec", "family_for",
    "rest_pose", "set_world_options", "size_key", "spec_for_key", "spec_for_size", "template", "with_awd",
]
