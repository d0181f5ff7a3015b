"""``[sumo]`` table of a run config: everything the SUMO side daemon needs besides
``[run]`` and ``[zenoh]`` (those come from ``runtime.config.load_common``).

Every knob has its unit in the comment; unknown keys and wrong types are ConfigErrors
naming the file and key (``runtime.config.section``). Paths resolve against the TOML file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from protocol.errors import ConfigError
from runtime.config import load_toml, section


@dataclass(frozen=True)
class SumoConfig:
    sumocfg: Path | None = None  # SUMO scenario (.sumocfg), relative to the TOML file
    step_length_s: float = 0.0  # [s] 0: the scenario's own step length; > 0 replaces it (logged)
    begin_s: float | None = None  # [s] start SUMO at this time instead of the scenario's begin
    gui: bool = False  # sumo-gui through TraCI instead of embedded libsumo (needs a display)
    extra_args: tuple[str, ...] = ()  # further SUMO command-line options, verbatim
    lanechange_duration_s: float = 3.0  # [s] continuous lane changes when the scenario sets neither lanechange.duration nor lateral-resolution (0 = SUMO's one-step hop)

    # Look-ahead distance (paper 3.3.2): LAD = lad_min if v < lad_min else min(v*k_lad, lad_max)
    lad_min_m: float = 7.0  # [m] LAD_min
    lad_max_m: float = 10.0  # [m] LAD_max
    k_lad_s: float = 1.0  # [s] k_LAD, multiplies the speed in m/s (the paper: 1, must be >= 1)

    path_ahead: bool = True  # publish each agent's path-ahead polyline
    path_margin_m: float = 15.0  # [m] path length beyond LAD_max (physics looks ahead from its own pose)
    persons: bool = True  # publish persons (walking and riding) as pedestrian agents
    traffic_lights: bool = True  # publish traffic-light states

    ego_id: str = "ego"  # id of the ego vehicle an outside engine drives (poses on ego/<id>)
    ego_vtype: str = ""  # SUMO vType for a new ego when the pose does not name one ('' = SUMO default)
    ego_keep_route: int = 2  # moveToXY keepRoute bits (2: exact pose, may leave the road)
    ego_hold_s: float = 0.3  # [s] after the last pose the ego is dead-reckoned this long, then held stopped
    ego_timeout_s: float = 30.0  # [s] without poses the ego is removed (re-added when poses resume)
    ego_jump_m: float = 5.0  # [m] a pose further than this from the previous one flags the ego JUMPED
    ego_max: int = 8  # [vehicles] most egos at once (ego_id "*" takes any id); poses for more are rejected
    ego_max_per_client: int = 4  # [vehicles] most egos of one client at once: an id "<client>.<name>" counts against <client>, an id without "." is a client of its own; more are rejected
    max_peer_keys: int = 256  # [keys] ack / physics-liveliness keys held at once (newest per key; more refused)

    lockstep_instances: tuple[str, ...] = ("main",)  # physics instances whose acks lockstep waits for
    lockstep_start_timeout_s: float = 60.0  # [s] lockstep: wait this long for them to come up before step 0
    max_lag_s: float = 1.0  # [s] realtime: when this far behind the wall clock, re-anchor (no catch-up burst)
    status_period_s: float = 1.0  # [s] wall time between INFO status lines

    def validate(self) -> None:
        if self.step_length_s != 0 and not 0.001 <= self.step_length_s <= 10.0:
            raise ConfigError(
                f"sumo.step_length_s: expected 0 (the scenario's own) or 0.001..10 s, got {self.step_length_s}"
            )
        if self.begin_s is not None and self.begin_s < 0:
            raise ConfigError(f"sumo.begin_s: expected >= 0 s, got {self.begin_s}")
        if not 0.0 <= self.lanechange_duration_s <= 30.0:
            raise ConfigError(f"sumo.lanechange_duration_s: expected 0..30 s, got {self.lanechange_duration_s}")
        if self.lad_min_m <= 0 or self.lad_max_m < self.lad_min_m:
            raise ConfigError(
                f"sumo.lad_min_m/lad_max_m: expected 0 < lad_min_m <= lad_max_m, "
                f"got {self.lad_min_m} and {self.lad_max_m}"
            )
        if self.k_lad_s <= 0:
            raise ConfigError(f"sumo.k_lad_s: expected > 0, got {self.k_lad_s}")
        if self.path_margin_m < 0:
            raise ConfigError(f"sumo.path_margin_m: expected >= 0, got {self.path_margin_m}")
        if self.ego_hold_s < 0 or self.ego_timeout_s <= 0:
            raise ConfigError("sumo.ego_hold_s / ego_timeout_s: expected >= 0 and > 0")
        if self.ego_max < 1 or self.max_peer_keys < 1:
            raise ConfigError(f"sumo.ego_max / max_peer_keys: expected >= 1, got {self.ego_max} and {self.max_peer_keys}")
        if self.ego_max_per_client < 1:
            raise ConfigError(f"sumo.ego_max_per_client: expected >= 1, got {self.ego_max_per_client}")
        if self.status_period_s <= 0:
            raise ConfigError(f"sumo.status_period_s: expected > 0, got {self.status_period_s}")
        if not self.lockstep_instances:
            raise ConfigError("sumo.lockstep_instances: expected at least one physics instance")

    @property
    def path_length_m(self) -> float:
        """Length of the published path ahead [m]."""
        return self.lad_max_m + self.path_margin_m


def sumo_config_from(data: dict, base: Path | None, file: str = "") -> SumoConfig:
    """Typed ``[sumo]`` view of already-loaded TOML tables."""
    return section(data, "sumo", SumoConfig, base, file)


def load_sumo_config(path: str | Path) -> SumoConfig:
    """Read the ``[sumo]`` table of a TOML file (defaults for missing keys)."""
    data, base = load_toml(path)
    return sumo_config_from(data, base, str(path))
