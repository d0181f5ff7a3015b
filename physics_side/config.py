"""Typed configuration of the physics side: ``[physics]``, ``[control.paper]``, ``[control.default]``.

Every knob has its unit; ``load_physics_config`` reads the tables of a run config (see
``runtime.config``), and ``check_rates`` validates the control / MuJoCo step ratio once
at start-up. The SUMO step length is not configured: every step message carries its own,
and the daemon simulates up to each step's end time (``ticks_to``), whatever its length.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from protocol.errors import ConfigError
from runtime.config import from_dict, section
from runtime.zones import REGION_FIELDS

PRESETS = ("paper", "default", "kinematic")
MIN_STEP_S = 0.001  # [s] shortest SUMO step length the physics side follows
MAX_STEP_S = 10.0  # [s] longest (beyond ~1 s tracking degrades: see physics_side/README.md)
MAX_CONTROL_DT_S = 0.05  # [s] longest control period that still steers a car at city speeds
MAX_TIMESTEP_S = 0.01  # [s] longest MuJoCo step: cars roll over at the friction limit above it
CLOCK_TOLERANCE_S = 1e-12  # [s] float rounding allowed when a period is checked against a limit
RATIO_TOLERANCE = 1e-6  # [1] relative: a clock ratio this close to a whole number is one
MAX_BUSY_POLL_MS = 10_000.0  # [ms] the longest busy-poll window accepted (seconds typed as ms would spin for hours)
SUGGESTED_SUBSTEPS = 8  # [1] a timestep error suggests the control period over 1..this substeps ...
MIN_SUGGESTED_TIMESTEP_S = 1e-4  # [s] ... that are at least this long
TICK_ROUNDING = 1e-9  # [ticks] half a tick rounds up in spite of float error in the times
TYPES = ("passenger", "taxi", "bus", "bicycle", "pedestrian", "other")


@dataclass(frozen=True)
class PhysicsConfig:
    """``[physics]``: world, rates, pools, robustness."""

    instance: str = "main"  # physics instance name in the keys (several can follow one run)
    follow_next_run: bool = False  # stay up after a run's final step and follow the next run of the same id
    control_hz: float = 50.0  # [Hz] control tick rate (one tick = controllers + substeps)
    timestep_s: float = 0.005  # [s] MuJoCo integration step (implicitfast)
    sumo_step_s: float = 0.1  # [s] SUMO step length for offline tools (experiments, benches); the daemon follows each message's
    state_every: int = 1  # [ticks] publish PhysicsState every k control ticks
    preset: Literal["paper", "default", "kinematic"] = "default"  # for every type not in `presets`
    presets: dict[str, str] = field(default_factory=dict)  # per type, e.g. {pedestrian="kinematic"}
    all_wheel_drive: tuple[str, ...] = ()  # car-like types driven on all four wheels
    divergence_m: float = 6.0  # [m] front-bumper distance to the SUMO pose that forces a placement
    sideways_jump_m: float = 1.0  # [m] a slow agent whose SUMO pose moves sideways more than this (and than max_side_speed x the step) in one step is placed (0 = off)
    sideways_slide_m: float = 0.5  # [m] a slow agent this far off a SUMO pose that slides sideways (lane change in a queue) is placed
    max_side_speed: float = 3.0  # [m/s] SUMO sideways motion up to this is extrapolated (continuous lane change); faster is a hop
    sideways_jump_speed: float = 5.0  # [m/s] "slow" for sideways_jump_m (SUMO's instant lane changes in queues)
    flip_deg: float = 60.0  # [deg] |roll| or |pitch| beyond which an agent is placed upright again
    stall: tuple[str, ...] = ()  # faults: "ID@FROM-TO" holds agent ID stopped in physics from SUMO time FROM to TO [s]
    brake_failure: tuple[str, ...] = ()  # faults: "ID@FROM-TO": agent ID has neither drive nor brakes then (coasts)
    contact_guard: bool = True  # carry (show kinematic, on SUMO's poses) a pair of agents about to touch where SUMO has a gap
    carry_infeasible: bool = True  # show a vehicle kinematic (SUMO's pose) through a manoeuvre it cannot drive (U-turns, tight corners for its size)
    reference: Literal["auto", "interpolate", "extrapolate"] = "auto"  # interpolate: physics runs one SUMO step behind, between the last two samples (SUMO's own motion); extrapolate: ahead of the newest sample; auto: interpolate steps longer than interpolate_above_s
    interpolate_above_s: float = 0.15  # [s] reference = "auto" interpolates SUMO steps longer than this
    max_extrapolation_steps: float = 3.0  # [SUMO steps] reference extrapolation limit past the newest step (scales with the step length)
    stop_decel: float = 3.0  # [m/s^2] deceleration of the safe stop when the SUMO side is gone
    shards: int = 2  # parallel MuJoCo simulations (agents in different shards never touch)
    threads: int = 0  # worker threads for the shards, 0 = one per shard
    processes: int | str = 1  # shard processes of this instance under one supervisor (N or "auto"; --processes)
    process_restarts: int = 3  # [restarts] of one shard process within 300 s before its supervisor gives up (exit 3)
    # Parked slots sleep but are not free: MuJoCo's step still walks every tree (~4 us per
    # parked car slot per 20 ms tick), so pools start small and grow by half their size;
    # `expect` sizes a large run up front.
    initial_slots: dict[str, int] = field(
        default_factory=lambda: {"passenger": 16, "taxi": 4, "bus": 4, "bicycle": 4, "pedestrian": 8}
    )  # [slots per shard] pre-allocated parked slots per type (its default size bucket)
    pool_chunk: int = 8  # [slots] a pool that runs out grows by at least this many per shard
    lod_radius_m: float = 0.0  # [m] level of detail: full physics within this of every ego, kinematic beyond (0 = off)
    lod_regions: tuple[tuple[float, ...], ...] = ()  # [[x, y, r], ...] [m] regions that always run full physics
    shard_tile_m: float = 250.0  # [m] tile edge of the spatial partition between shard processes (--shard i/k)
    shard_halo_m: float = 30.0  # [m] an agent keeps its shard this far beyond the shard's tiles
    expect: dict[str, int] = field(default_factory=dict)  # [agents] at once per type, e.g. {passenger = 3000}: pools sized up front
    step_queue: int = 64  # [messages] bounded FIFO of received SUMO steps
    step_queue_mb: float = 64.0  # [MiB] byte bound of that FIFO (full: the oldest step is dropped)
    # [ms] latency-sensitive runs: after each step, spin up to this long for the next one
    # instead of sleeping until Zenoh's callback wakes the loop (~50 us less per step, a core
    # busy while it spins; 0 = off). Steps then come from a ring of step_queue messages.
    busy_poll_ms: float = 0.0
    log_every_s: float = 1.0  # [s] status line period (wall clock)

    def validate(self) -> None:
        from physics_side.faults import parse_stall
        from protocol.keys import check_chunk

        for i, spec in enumerate(self.stall):
            parse_stall(spec, f"physics.stall[{i}]")
        for i, spec in enumerate(self.brake_failure):
            parse_stall(spec, f"physics.brake_failure[{i}]")

        try:
            check_chunk(self.instance, "physics.instance")
        except Exception as e:
            raise ConfigError(str(e)) from None
        if self.control_hz <= 0 or self.timestep_s <= 0 or self.sumo_step_s <= 0:
            raise ConfigError("physics: control_hz, timestep_s and sumo_step_s must be > 0")
        if self.state_every < 1:
            raise ConfigError(f"physics.state_every: expected >= 1, got {self.state_every}")
        for k, v in self.presets.items():
            if k not in TYPES:
                raise ConfigError(f"physics.presets.{k}: unknown agent type (expected one of {', '.join(TYPES)})")
            if v not in PRESETS:
                raise ConfigError(f"physics.presets.{k}: expected one of {list(PRESETS)}, got {v!r}")
        for k in self.all_wheel_drive:
            if k not in ("passenger", "taxi", "bus"):
                raise ConfigError(f"physics.all_wheel_drive: {k!r} is not a four-wheel type (passenger, taxi, bus)")
        for k, v in self.initial_slots.items():
            if k not in TYPES[:-1]:
                raise ConfigError(f"physics.initial_slots.{k}: unknown agent type")
            if v < 0:
                raise ConfigError(f"physics.initial_slots.{k}: expected >= 0, got {v}")
        if self.shard_tile_m <= 0 or not 0 <= self.shard_halo_m < self.shard_tile_m:
            raise ConfigError("physics: need shard_tile_m > 0 and 0 <= shard_halo_m < shard_tile_m [m]")
        if self.lod_radius_m < 0:
            raise ConfigError(f"physics.lod_radius_m: expected >= 0, got {self.lod_radius_m}")
        for i, r in enumerate(self.lod_regions):
            if len(r) != REGION_FIELDS or r[2] <= 0:
                raise ConfigError(f"physics.lod_regions[{i}]: expected [x, y, radius] with radius > 0 [m], got {list(r)}")
        for k, v in self.expect.items():
            if k not in TYPES[:-1]:
                raise ConfigError(f"physics.expect.{k}: unknown agent type (expected one of {', '.join(TYPES[:-1])})")
            if v < 0:
                raise ConfigError(f"physics.expect.{k}: expected >= 0, got {v}")
        if self.shards < 1 or self.threads < 0:
            raise ConfigError("physics: shards must be >= 1 and threads >= 0")
        if isinstance(self.processes, str) and self.processes != "auto" or isinstance(self.processes, int) and (
                self.processes < 1):
            raise ConfigError(f"physics.processes: expected a number >= 1 or \"auto\", got {self.processes!r}")
        if self.process_restarts < 0:
            raise ConfigError(f"physics.process_restarts: expected >= 0, got {self.process_restarts}")
        if self.pool_chunk < 1 or self.step_queue < 1:
            raise ConfigError("physics: pool_chunk and step_queue must be >= 1")
        if self.step_queue_mb <= 0:
            raise ConfigError(f"physics.step_queue_mb: expected > 0 MiB, got {self.step_queue_mb}")
        if not 0.0 <= self.busy_poll_ms <= MAX_BUSY_POLL_MS:
            raise ConfigError(f"physics.busy_poll_ms: expected 0 (off) to {MAX_BUSY_POLL_MS:g} ms, "
                              f"got {self.busy_poll_ms}")
        if self.divergence_m <= 0 or self.stop_decel <= 0:
            raise ConfigError("physics: divergence_m and stop_decel must be > 0")
        if self.max_extrapolation_steps < 1.0:
            raise ConfigError(f"physics.max_extrapolation_steps: expected >= 1, got {self.max_extrapolation_steps}")

    def preset_for(self, type_name: str) -> str:
        return self.presets.get(type_name, self.preset)

    @property
    def control_dt(self) -> float:
        """Control period [s]."""
        return 1.0 / self.control_hz


@dataclass(frozen=True)
class PaperControl:
    """``[control.paper]``: the seed's controller, Sumonity section 3.3 (defaults = paper)."""

    k1: float = 15.0  # [1/m] P gain on the position error along the path -> u1
    k2: float = 1.0  # [s/m] P gain on the speed error -> u2; u_in = (u1 + u2) / 2
    lad_min: float = 7.0  # [m] minimum look-ahead distance
    lad_max: float = 10.0  # [m] maximum look-ahead distance
    k_lad: float = 1.0  # [s] LAD = v_ref * k_lad between the limits (must be >= 1)
    k_steer: float = 0.05  # [1/deg] P_steer = delta_ref[deg] * k_steer, clipped to +-1 (of max steer)
    lookahead: Literal["message", "path"] = "path"  # recomputed on path_xy with these LADs, or la_x/la_y as sent
    # The seed's code divides TraCI's speed [m/s] by 3.6 before the LAD rule, so at city speeds
    # LAD = LAD_min: that is what the paper's Figs. 8-9 show (1.0 = the formula as printed).
    lad_speed_divisor: float = 3.6  # [1]
    # u_in is a pedal command in [-1, 1]: + = fraction of the model's max drive torque,
    # - = fraction of its max brake torque (the paper's Unity car took a normalised input).
    ped_omega: float = 3.0  # [rad/s] pedestrian position-loop natural frequency
    ped_zeta: float = 0.7  # [1] pedestrian position-loop damping ratio

    def validate(self) -> None:
        if self.lad_min <= 0 or self.lad_max < self.lad_min:
            raise ConfigError("control.paper: need 0 < lad_min <= lad_max")
        if self.lad_speed_divisor <= 0:
            raise ConfigError(f"control.paper.lad_speed_divisor: expected > 0, got {self.lad_speed_divisor}")
        if self.k_lad < 1.0:
            raise ConfigError(f"control.paper.k_lad: the paper requires >= 1, got {self.k_lad}")


@dataclass(frozen=True)
class DefaultControl:
    """``[control.default]``: our controller (front-bumper referenced, feed-forward, damped)."""

    lateral: Literal["stanley", "pursuit"] = "stanley"  # front-bumper Stanley or front-axle pure pursuit
    k_cross: float = 4.0  # [1/s] Stanley cross-track gain: bumper heading correction atan(k e / v)
    v_soft: float = 1.0  # [m/s] Stanley low-speed softening
    max_correction_deg: float = 15.0  # [deg] cross-track correction limit (angle of approach to the path)
    preview_s: float = 0.05  # [s] path heading/curvature taken this far ahead (steering servo lag)
    k_yaw: float = 0.05  # [s] yaw-rate damping: steer -= k_yaw * (r - r_ref) (rad per rad/s)
    lad_min: float = 4.0  # [m] pure pursuit: minimum look-ahead distance (lateral = "pursuit")
    lad_max: float = 10.0  # [m] pure pursuit: maximum look-ahead distance
    k_lad: float = 0.6  # [s] pure pursuit: LAD = v * k_lad between the limits
    mean_speed_lead: float = 0.5  # [SUMO steps] the extrapolated speed profile is taken this much ahead: SUMO's speed is the mean over the step before its sample (0 = off)
    pos_omega: float = 2.5  # [rad/s] along-path position loop natural frequency
    pos_zeta: float = 1.0  # [1] along-path position loop damping ratio (critically damped)
    brake_omega: float = 4.0  # [rad/s] natural frequency of the loop where it brakes harder than the pos_omega one (ahead of SUMO or faster); <= pos_omega: off
    k_int: float = 0.5  # [1/s^3] gain on the integral of the along-path error (cornering drag, slopes)
    int_limit: float = 1.0  # [m/s^2] integral term clamp
    accel_max: float = 6.0  # [m/s^2] commanded acceleration limit
    decel_max: float = 11.0  # [m/s^2] commanded deceleration limit (SUMO's motorcycles brake at 10)
    hold_speed: float = 0.2  # [m/s] below this reference speed a stopped agent holds its brakes
    hold_brake: float = 0.3  # [1] hold brake as a fraction of max brake torque
    creep_back_m: float = 0.15  # [m] a vehicle standing this far past its standing reference rolls back to it (0 = never)
    creep_speed: float = 0.5  # [m/s] the fastest such a roll back goes
    ped_omega: float = 6.0  # [rad/s] pedestrian position-loop natural frequency
    ped_zeta: float = 1.0  # [1] pedestrian position-loop damping ratio
    bike_roll_kp: float = 1500.0  # [N*m/rad] roll stabiliser stiffness of SUMO's default bicycle (every preset; other two-wheelers in proportion to their m g h)
    bike_roll_kd: float = 250.0  # [N*m*s/rad] roll stabiliser damping (the same)

    def validate(self) -> None:
        if self.pos_omega <= 0 or self.pos_zeta <= 0:
            raise ConfigError("control.default: pos_omega and pos_zeta must be > 0")
        if self.lad_min <= 0 or self.lad_max < self.lad_min:
            raise ConfigError("control.default: need 0 < lad_min <= lad_max")


@dataclass(frozen=True)
class ControlConfig:
    paper: PaperControl = field(default_factory=PaperControl)
    default: DefaultControl = field(default_factory=DefaultControl)


@dataclass(frozen=True)
class PhysicsSettings:
    """Everything the physics side reads from a run config."""

    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    control: ControlConfig = field(default_factory=ControlConfig)


def load_physics_config(data: dict[str, Any], base: Path | None = None, file: str = "") -> PhysicsSettings:
    """Typed ``[physics]`` and ``[control.*]`` tables; raises ConfigError naming the key."""
    phys = section(data, "physics", PhysicsConfig, base, file)
    ctl = data.get("control", {})
    if not isinstance(ctl, dict):
        raise ConfigError(f"{file}: control: expected a table")
    unknown = sorted(set(ctl) - {"paper", "default"})
    if unknown:
        raise ConfigError(f"{file}: control.{unknown[0]}: unknown table (expected paper, default)")
    try:
        paper = from_dict(PaperControl, _table(ctl, "paper"), "control.paper", base)
        default = from_dict(DefaultControl, _table(ctl, "default"), "control.default", base)
    except ConfigError as e:
        raise ConfigError(f"{file}: {e}" if file else str(e)) from None
    settings = PhysicsSettings(phys, ControlConfig(paper, default))
    check_rates(phys.sumo_step_s, phys.control_hz, phys.timestep_s)
    return settings


def _table(data: dict, name: str) -> dict:
    raw = data.get(name, {})
    if not isinstance(raw, dict):
        raise ConfigError(f"control.{name}: expected a table, got {type(raw).__name__}")
    return raw


def _ratio(big: float, small: float) -> int | None:
    """``big / small`` if it is a whole number (to 1e-6 relative), else None."""
    r = big / small
    n = round(r)
    return n if n >= 1 and abs(r - n) <= RATIO_TOLERANCE * max(1.0, r) else None


@dataclass(frozen=True)
class Rates:
    """Whole-number ratios between the three clocks."""

    ticks_per_step: int
    """Control ticks per SUMO step of ``sumo_step_s`` (rounded, >= 1; offline tools only: the
    daemon counts ticks by time with ``ticks_to``, so any step length works)."""
    substeps: int
    """MuJoCo steps per control tick."""
    control_dt: float
    """[s]."""


def check_rates(sumo_step_s: float, control_hz: float, timestep_s: float) -> Rates:
    """Check the control period is a whole number of MuJoCo steps, and the SUMO step length is sane.

    Like dm_control's ``compute_n_steps``: raises ConfigError naming the number to change.
    The SUMO step need not be a multiple of the control period: ``ticks_to`` spreads ticks
    over steps by time (0.05 s steps at 50 Hz: 3, 2, 3, 2 ... ticks).
    """
    if sumo_step_s <= 0 or control_hz <= 0 or timestep_s <= 0:
        raise ConfigError("rates: sumo_step_s, control_hz and timestep_s must be > 0")
    dt = 1.0 / control_hz
    substeps = _ratio(dt, timestep_s)
    if substeps is None:
        ok = [f"{dt / n:g}" for n in range(1, SUGGESTED_SUBSTEPS + 1) if dt / n >= MIN_SUGGESTED_TIMESTEP_S]
        raise ConfigError(
            f"physics.timestep_s = {timestep_s:g} s does not divide the control period "
            f"1/control_hz = {dt:g} s; change physics.timestep_s to one of {', '.join(ok)} "
            f"(or change physics.control_hz)"
        )
    if not MIN_STEP_S <= sumo_step_s <= MAX_STEP_S:
        raise ConfigError(
            f"the SUMO step length {sumo_step_s:g} s is outside {MIN_STEP_S:g}..{MAX_STEP_S:g} s; "
            f"run SUMO with a step length in that range"
        )
    if dt > MAX_CONTROL_DT_S + CLOCK_TOLERANCE_S:
        raise ConfigError(
            f"physics.control_hz = {control_hz:g} Hz is too slow to steer a car (control period "
            f"{dt:g} s > {MAX_CONTROL_DT_S:g} s); change physics.control_hz to 50"
        )
    if timestep_s > MAX_TIMESTEP_S + CLOCK_TOLERANCE_S:
        raise ConfigError(
            f"physics.timestep_s = {timestep_s:g} s is too coarse: cars roll over at the friction "
            f"limit above {MAX_TIMESTEP_S:g} s; change physics.timestep_s to 0.005"
        )
    return Rates(ticks_per_step=max(1, round(sumo_step_s / dt)), substeps=substeps, control_dt=dt)


def ticks_to(t_now: float, t_end: float, dt: float) -> int:
    """Control ticks of ``dt`` [s] that bring physics time ``t_now`` nearest to ``t_end`` [s].

    Physics time then stays within dt/2 of SUMO's step end for any step length: a step
    shorter than ``dt`` gets a tick every few steps, a longer one several.
    """
    return max(0, int(math.floor((t_end - t_now) / dt + 0.5 + TICK_ROUNDING)))


__all__ = [
    "ControlConfig", "DefaultControl", "PaperControl", "PhysicsConfig", "PhysicsSettings",
    "MAX_STEP_S", "MIN_STEP_S", "PRESETS", "Rates", "TYPES", "check_rates", "load_physics_config", "ticks_to",
]


def parse_expect(text: str) -> dict[str, int]:
    """``--expect``: ``N`` (passenger cars) or ``type=N,type=N`` -> agents per type."""
    out: dict[str, int] = {}
    for part in (p.strip() for p in text.split(",") if p.strip()):
        name, _, num = part.rpartition("=")
        name = name.strip() or "passenger"
        if name not in TYPES[:-1]:
            raise ConfigError(f"--expect: unknown agent type {name!r} (expected one of {', '.join(TYPES[:-1])})")
        try:
            n = int(num)
        except ValueError:
            raise ConfigError(f"--expect: expected a whole number of agents for {name}, got {num!r}") from None
        if n < 0:
            raise ConfigError(f"--expect: expected >= 0 agents for {name}, got {n}")
        out[name] = n
    return out
