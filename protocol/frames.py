"""The one place where SUMO's frame meets the MuJoCo world frame.

SUMO: x east, y north [m]; a vehicle's position is its *front-bumper centre*; its angle
is in degrees *clockwise from north*.
MuJoCo world: x east, y north, z up [m]; yaw in radians *counter-clockwise from east*;
a body's origin is wherever its model puts it (physics_side uses the body centre).

All functions are vectorised: scalars or numpy arrays in, the same shape out.
"""

from __future__ import annotations

import numpy as np


def sumo_angle_to_yaw(angle_deg):
    """SUMO angle [deg cw from north] -> yaw [rad ccw from east], wrapped to (-pi, pi]."""
    return wrap_pi(np.deg2rad(90.0 - np.asarray(angle_deg, dtype=np.float64)))


def yaw_to_sumo_angle(yaw_rad):
    """Yaw [rad ccw from east] -> SUMO angle [deg cw from north] in [0, 360)."""
    return np.mod(90.0 - np.rad2deg(np.asarray(yaw_rad, dtype=np.float64)), 360.0)


_TWO_PI = 2.0 * np.pi
_INV_TWO_PI = 1.0 / _TWO_PI


def wrap_pi(a):
    """Wrap angles [rad] to (-pi, pi]. (ceil instead of np.mod: the hot paths call it ~10
    times per tick over every agent, and float mod is twice as slow.)"""
    a = np.asarray(a, dtype=np.float64)
    return a - _TWO_PI * np.ceil((a - np.pi) * _INV_TWO_PI)


def front_to_centre(x, y, yaw, length):
    """Front-bumper centre -> body centre, moving back half a length along the heading."""
    h = 0.5 * np.asarray(length, dtype=np.float64)
    return x - h * np.cos(yaw), y - h * np.sin(yaw)


def centre_to_front(x, y, yaw, length):
    """Body centre -> front-bumper centre."""
    h = 0.5 * np.asarray(length, dtype=np.float64)
    return x + h * np.cos(yaw), y + h * np.sin(yaw)


def along_across(dx, dy, yaw):
    """Split a displacement into components along the heading (+ ahead) and across it (+ left)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return dx * c + dy * s, -dx * s + dy * c
