"""Egos driven from ROS 2: ``PoseStamped`` (and optionally ``Odometry``) -> ``EgoPose`` on Zenoh.

The node feeds SUMO exactly as every other ego client does (SPEC 3.5): one ego message
per pose on ``<root>/<run>/ego/<id>``; the SUMO side applies the newest each step, holds
the ego when poses pause (``[sumo] ego_hold_s``), removes it after ``ego_timeout_s``,
and enforces ``ego_max`` / ``ego_max_per_client``. Here each pose is checked first; a bad
one (wrong ``frame_id``, a non-finite or out-of-range value, a zero quaternion) is refused
with a logged error naming the field and counted, and the node keeps running.

Conversion (``frames``): the ROS pose is the body centre; SUMO gets the front-bumper centre
``length/2`` ahead along the yaw, with the ego's length as SUMO reports it in the steps
(until then ``[ros2] ego_length_m``). Speed: ``Odometry.twist.twist.linear.x`` when an
odometry message came within the last second, else the displacement between the last two
poses along the heading over their stamps' difference (0 for the first pose).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field

from protocol.codec import encode
from protocol.errors import ProtocolError
from protocol.messages import EgoPose
from sumoco.ros2.frames import quaternion_to_yaw, ros_to_sumo

log = logging.getLogger(__name__)

MAX_ABS_XY_M = 1e8  # [m] SPEC 5 bound of positions
MAX_SPEED_MPS = 200.0  # [m/s] SPEC 5 bound of an ego's speed
ODOM_FRESH_S = 1.0  # [s] an odometry speed is used this long after it came
LOG_FIRST = 20  # errors logged one by one, then every LOG_EVERY-th


@dataclass
class EgoStats:
    received: int = 0
    forwarded: int = 0
    rejected: int = 0
    thinned: int = 0
    errors: dict[str, int] = field(default_factory=dict)  # reason -> count


class EgoInput:
    """One ego: checks ROS poses and puts ego messages through ``put(bytes)``.

    Called from the ROS executor's thread; ``put`` must not block (a Zenoh publisher with
    congestion control *drop*)."""

    def __init__(self, ego_id: str, put, frame_id: str, length_m: float, max_hz: float) -> None:
        self.id, self._put, self.frame_id = ego_id, put, frame_id
        self.length_m = length_m  # replaced by SUMO's own length once a step carries the ego
        self.min_period_s = 1.0 / max_hz
        self.stats = EgoStats()
        self._lock = threading.Lock()
        self._prev: tuple[float, float, float] | None = None  # (stamp, cx, cy)
        self._odom_speed: tuple[float, float] | None = None  # (monotonic time, speed)
        self._last_put = -math.inf

    def _refuse(self, reason: str, detail: str) -> None:
        st = self.stats
        st.rejected += 1
        st.errors[reason] = st.errors.get(reason, 0) + 1
        if st.rejected <= LOG_FIRST or st.rejected % 1000 == 0:
            log.error("ego %r: refused a pose (%d refused so far): %s", self.id, st.rejected, detail)

    def on_pose(self, msg) -> None:
        """``geometry_msgs/PoseStamped``."""
        self._pose(msg.header, msg.pose, None)

    def on_odometry(self, msg) -> None:
        """``nav_msgs/Odometry``: its pose drives the ego too, its twist gives the speed."""
        v = msg.twist.twist.linear.x
        if math.isfinite(v):
            with self._lock:
                self._odom_speed = (time.monotonic(), float(v))
        self._pose(msg.header, msg.pose.pose, float(v))

    def _pose(self, header, pose, speed: float | None) -> None:
        self.stats.received += 1
        try:
            ego = self._check(header, pose, speed)
        except ProtocolError as e:
            self._refuse(e.field if hasattr(e, "field") else "pose", str(e))
            return
        if ego is None:
            return
        self._put(encode(ego))
        self.stats.forwarded += 1

    def _check(self, header, pose, speed: float | None) -> EgoPose | None:
        if header.frame_id != self.frame_id:
            raise ProtocolError(f"expected frame_id {self.frame_id!r} (the fixed frame), got {header.frame_id!r}; "
                                f"transform the pose into {self.frame_id!r} first", "header.frame_id")
        p, q = pose.position, pose.orientation
        for name, v in (("x", p.x), ("y", p.y), ("z", p.z)):
            if not math.isfinite(v):
                raise ProtocolError(f"expected a finite number, got {v}", f"pose.position.{name}")
        if abs(p.x) > MAX_ABS_XY_M or abs(p.y) > MAX_ABS_XY_M:
            raise ProtocolError(f"expected |x|, |y| <= {MAX_ABS_XY_M:g} m, got ({p.x:g}, {p.y:g})", "pose.position")
        norm = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)
        if not math.isfinite(norm) or norm < 1e-6:
            raise ProtocolError(f"expected a unit quaternion, got ({q.x}, {q.y}, {q.z}, {q.w})", "pose.orientation")
        stamp = header.stamp.sec + 1e-9 * header.stamp.nanosec
        now = time.monotonic()
        with self._lock:
            if now - self._last_put < self.min_period_s:
                self.stats.thinned += 1
                return None
            yaw = float(quaternion_to_yaw(q.x / norm, q.y / norm, q.z / norm, q.w / norm))
            if speed is None:
                odo = self._odom_speed
                if odo is not None and now - odo[0] <= ODOM_FRESH_S:
                    speed = odo[1]
                elif self._prev is not None and 0.0 < stamp - self._prev[0] <= 1.0:
                    dx, dy = p.x - self._prev[1], p.y - self._prev[2]
                    speed = (dx * math.cos(yaw) + dy * math.sin(yaw)) / (stamp - self._prev[0])
                else:
                    speed = 0.0
            if not math.isfinite(speed) or abs(speed) > MAX_SPEED_MPS:
                raise ProtocolError(f"expected |speed| <= {MAX_SPEED_MPS:g} m/s, got {speed:g}", "speed")
            self._prev = (stamp, p.x, p.y)
            self._last_put = now
        x, y, angle = ros_to_sumo(p.x, p.y, yaw, self.length_m)
        return EgoPose(id=self.id, x=float(x), y=float(y), angle=float(angle), speed=float(speed), time=stamp)
