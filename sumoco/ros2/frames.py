"""SUMO's frame -> the ROS frame, in one place (no ROS import: tests and docs read it alone).

The ROS fixed frame (``map`` by default) is ENU: x east, y north, z up, metres, with the
**same x/y as SUMO's network** (the ``.net.xml`` coordinates, i.e. after SUMO's
``netOffset``; projected coordinates are ``map − net.offset``, the offset is in the static
data and logged at start). Nothing is shifted, so a pose in ROS and a position in SUMO are
the same numbers.

The conventions (REP 103 / REP 105):

- **heading**: SUMO's ``angle`` is degrees clockwise from north; a ROS yaw is radians
  counter-clockwise from east (the x axis): ``yaw = radians(90 − angle)``, wrapped to
  (−pi, pi]. Orientation quaternion: ``(0, 0, sin(yaw/2), cos(yaw/2))``.
- **reference point**: SUMO places an agent at its *front-bumper centre*; ROS tools expect
  the body centre (``base_link`` at the middle of the footprint). ``centre = front −
  length/2 · (cos yaw, sin yaw)`` with the agent's own ``length`` (the step row's; for an
  ego before SUMO reports it, ``[ros2] ego_length_m``). The same rule holds for every agent
  (persons too). Poses sit on the ground (z = 0); marker boxes are lifted by half their
  height.
- the inverse (ROS -> SUMO, for egos): ``front = centre + length/2 · (cos yaw, sin yaw)``,
  ``angle = (90 − degrees(yaw)) mod 360``.

Every function is vectorised: scalars or numpy arrays in, the same shape out.
"""

from __future__ import annotations

import numpy as np

from protocol.frames import centre_to_front, front_to_centre, sumo_angle_to_yaw, yaw_to_sumo_angle


def sumo_to_ros(x, y, angle_deg, length):
    """SUMO front-bumper centre [m] and angle [deg cw from north] -> ROS body centre (cx, cy)
    [m] and yaw [rad ccw from east, (−pi, pi]]."""
    yaw = sumo_angle_to_yaw(angle_deg)
    cx, cy = front_to_centre(np.asarray(x, np.float64), np.asarray(y, np.float64), yaw, length)
    return cx, cy, yaw


def ros_to_sumo(cx, cy, yaw, length):
    """ROS body centre [m] and yaw [rad ccw from east] -> SUMO front-bumper centre (x, y) [m]
    and angle [deg cw from north, [0, 360)]."""
    yaw = np.asarray(yaw, np.float64)
    x, y = centre_to_front(np.asarray(cx, np.float64), np.asarray(cy, np.float64), yaw, length)
    return x, y, yaw_to_sumo_angle(yaw)


def yaw_to_quaternion(yaw):
    """Yaw [rad] -> the (z, w) components of the quaternion (x = y = 0)."""
    half = 0.5 * np.asarray(yaw, np.float64)
    return np.sin(half), np.cos(half)


def quaternion_to_yaw(qx, qy, qz, qw):
    """Yaw [rad, (−pi, pi]] of a quaternion (x, y, z, w); any roll and pitch are dropped."""
    return np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def stamp_of(t_s: float) -> tuple[int, int]:
    """Simulation time [s] -> (sec, nanosec) of a ``builtin_interfaces/Time`` (rounded to 1 ns)."""
    sec, nsec = divmod(int(round(float(t_s) * 1e9)), 1_000_000_000)
    return sec, nsec
