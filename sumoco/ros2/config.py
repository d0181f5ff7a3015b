"""``[ros2]``: the ROS 2 bridge's settings (``sumoco ros2``, ``sumoco export rosbag2``).

Every knob with its unit; an unknown key or a wrong type is a ``ConfigError`` (runtime.config).
Command-line flags of ``sumoco ros2`` override these.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

from protocol.errors import ConfigError

#: A ROS 2 name token: letters, digits and underscores, not starting with a digit.
_ROS_TOKEN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass(frozen=True)
class Ros2Config:
    source: Literal["physics", "sumo"] = "physics"  # where poses come from: a physics instance or SUMO's samples
    instance: str = ""  # physics instance whose states are used ("": the first one that publishes)
    rate_hz: float = 10.0  # [Hz of simulated time] agents, poses and odometry at most this often; 0 = every message
    frame_id: str = "map"  # the fixed frame (ENU, SUMO's network x/y in metres)
    prefix: str = "/sumoco"  # topic prefix: <prefix>/agents, <prefix>/poses, <prefix>/map, ...
    odometry: tuple[str, ...] = ()  # agent ids published as nav_msgs/Odometry on <prefix>/odom/<id>
    egos: tuple[str, ...] = ()  # ego ids driven from ROS 2: <prefix>/ego/<id>/pose (+ .../odom)
    ego_length_m: float = 5.0  # [m] body length of an ego until SUMO reports its own (SUMO's default car)
    ego_max_hz: float = 100.0  # [Hz, wall clock] poses forwarded per ego at most; faster ones are dropped (counted)
    domain_id: int | None = None  # ROS_DOMAIN_ID (none: the environment's, else 0)
    localhost_only: bool = True  # DDS discovery on loopback only (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST)
    queue: int = 2  # [messages] per Zenoh key between the transport and the publishing thread; full: newest wins

    def validate(self) -> None:
        if self.rate_hz < 0:
            raise ConfigError(f"ros2.rate_hz: expected >= 0 (0 = every message), got {self.rate_hz:g}")
        if not _ROS_TOKEN.match(self.frame_id):
            raise ConfigError(f"ros2.frame_id: expected a ROS name (letters, digits, _), got {self.frame_id!r}")
        parts = self.prefix.strip("/").split("/")
        if not self.prefix.startswith("/") or not all(_ROS_TOKEN.match(p) for p in parts):
            raise ConfigError(f"ros2.prefix: expected an absolute ROS namespace such as '/sumoco', got {self.prefix!r}")
        if self.ego_length_m <= 0 or self.ego_max_hz <= 0:
            raise ConfigError(f"ros2.ego_length_m / ego_max_hz: expected > 0, got {self.ego_length_m:g} and "
                              f"{self.ego_max_hz:g}")
        if self.domain_id is not None and not 0 <= self.domain_id <= 232:
            raise ConfigError(f"ros2.domain_id: expected 0..232, got {self.domain_id}")
        if self.queue < 1:
            raise ConfigError(f"ros2.queue: expected >= 1, got {self.queue}")
        names: dict[str, str] = {}
        for agent in (*self.odometry, *self.egos):
            name = ros_name(agent)
            if names.setdefault(name, agent) != agent:
                raise ConfigError(f"ros2: ids {names[name]!r} and {agent!r} both become the ROS name {name!r}; "
                                  f"rename one")

    def topic(self, *parts: str) -> str:
        return "/".join([self.prefix.rstrip("/"), *parts])


def ros_name(agent_id: str) -> str:
    """An agent id as a ROS name token: every character other than a letter, digit or '_'
    becomes '_', and a leading digit gets an '_' before it (``veh.1-a`` -> ``veh_1_a``)."""
    name = re.sub(r"[^A-Za-z0-9_]", "_", agent_id) or "_"
    return "_" + name if name[0].isdigit() else name
