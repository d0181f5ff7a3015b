"""Zenoh key expressions of a sumoco run, all under ``<root>/<run>/``.

| key                         | who puts          | what                                  |
|-----------------------------|-------------------|---------------------------------------|
| <root>/<run>/sumo/step      | SUMO side         | StepMessage, one per SUMO step        |
| <root>/<run>/sumo/static    | SUMO side (query) | StaticData, answered to `get`         |
| <root>/<run>/sumo/map       | SUMO side (query) | the network as glTF (SPEC 9)          |
| <root>/<run>/sumo/alive     | SUMO side         | liveliness token                      |
| <root>/<run>/sumo/status    | SUMO side (query) | counters (steps, rejected, ego drift) |
| <root>/<run>/physics/<inst>/state | physics side | PhysicsState, per control tick     |
| <root>/<run>/physics/<inst>/ack   | physics side | StepAck (lockstep)                 |
| <root>/<run>/physics/<inst>/feedback | physics side | PhysicsFeedback (two-way coupling) |
| <root>/<run>/physics/<inst>/alive | physics side | liveliness token                   |
| <root>/<run>/ego/<id>       | outside clients   | EgoPose of ego vehicle <id>           |
| <root>/<run>/viewer/<role>/<client>/camera | viewers, renderers | CameraPose (LOD interest point) |
| <root>/<run>/viewer/<role>/<client>/alive  | viewers, renderers | liveliness token of that camera |

``<inst>`` names one physics process ("main" by default): several can follow the same SUMO
run side by side (the demo runs the ``paper`` and ``default`` presets at once) or split
the agents between them (shards). Every liveliness token: ``<root>/<run>/**/alive``
(``*`` matches one chunk only). ``<role>`` in a camera key is the publisher's certificate
role (``viewer``, ``renderer-<ego>``; "viewer" without the secure profile), so that access
control can let each role put only its own cameras; ``<client>`` tells cameras apart.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from protocol.errors import ProtocolError

_CHUNK = re.compile(r"^[A-Za-z0-9_.\-]+$")


def check_chunk(value: str, what: str) -> str:
    """A key chunk must be non-empty and free of Zenoh wildcards and separators."""
    if not _CHUNK.match(value or ""):
        raise ProtocolError(
            f"expected letters, digits, '_', '-' or '.', got {value!r}", what
        )
    return value


@dataclass(frozen=True)
class Keys:
    """Key expressions for one run under one root."""

    root: str = "sumoco"
    run: str = "default"
    physics: str = "main"  # physics instance name used by physics_state / ack / physics_alive

    def __post_init__(self) -> None:
        for part in self.root.split("/"):
            check_chunk(part, "root")
        check_chunk(self.run, "run")
        check_chunk(self.physics, "physics instance")

    @property
    def base(self) -> str:
        return f"{self.root}/{self.run}"

    @property
    def step(self) -> str:
        return f"{self.base}/sumo/step"

    @property
    def static(self) -> str:
        return f"{self.base}/sumo/static"

    @property
    def sumo_map(self) -> str:
        """The road network as glTF (SPEC 9), answered next to the static data."""
        return f"{self.base}/sumo/map"

    @property
    def sumo_status(self) -> str:
        return f"{self.base}/sumo/status"

    @property
    def sumo_alive(self) -> str:
        return f"{self.base}/sumo/alive"

    @property
    def physics_state(self) -> str:
        return f"{self.base}/physics/{self.physics}/state"

    @property
    def ack(self) -> str:
        return f"{self.base}/physics/{self.physics}/ack"

    @property
    def physics_alive(self) -> str:
        return f"{self.base}/physics/{self.physics}/alive"

    @property
    def feedback(self) -> str:
        """Physical states of physics-authoritative vehicles, per SUMO step (two-way coupling)."""
        return f"{self.base}/physics/{self.physics}/feedback"

    # Wildcards over every physics instance (the SUMO side collects acks with these).
    @property
    def physics_state_all(self) -> str:
        return f"{self.base}/physics/*/state"

    @property
    def ack_all(self) -> str:
        return f"{self.base}/physics/*/ack"

    @property
    def feedback_all(self) -> str:
        return f"{self.base}/physics/*/feedback"

    @property
    def physics_alive_all(self) -> str:
        return f"{self.base}/physics/*/alive"

    @staticmethod
    def instance_of(key: str) -> str:
        """Physics instance name in a ``.../physics/<inst>/...`` key."""
        parts = str(key).split("/")
        return parts[parts.index("physics") + 1] if "physics" in parts[:-1] else ""

    def ego(self, ego_id: str) -> str:
        return f"{self.base}/ego/{check_chunk(ego_id, 'ego id')}"

    @property
    def ego_all(self) -> str:
        return f"{self.base}/ego/*"

    def viewer_camera(self, role: str, client: str) -> str:
        """Camera of viewer ``client`` connected with certificate role ``role``."""
        return f"{self.base}/viewer/{check_chunk(role, 'viewer role')}/{check_chunk(client, 'viewer client id')}/camera"

    def viewer_alive(self, role: str, client: str) -> str:
        """Liveliness token of that camera: its DELETE retires the camera at once."""
        return f"{self.base}/viewer/{check_chunk(role, 'viewer role')}/{check_chunk(client, 'viewer client id')}/alive"

    @property
    def viewer_camera_all(self) -> str:
        return f"{self.base}/viewer/*/*/camera"

    @property
    def viewer_alive_all(self) -> str:
        return f"{self.base}/viewer/*/*/alive"

    @staticmethod
    def viewer_of(key: str) -> str:
        """``<role>/<client>`` of a ``.../viewer/<role>/<client>/...`` key ("" if none)."""
        parts = str(key).split("/")
        if len(parts) >= 4 and parts[-4] == "viewer":
            return f"{parts[-3]}/{parts[-2]}"
        return ""

    @property
    def everything(self) -> str:
        return f"{self.base}/**"
