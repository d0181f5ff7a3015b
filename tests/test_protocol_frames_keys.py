"""Frame conversions (closed form) and key expressions."""

from __future__ import annotations

import numpy as np
import pytest

from protocol import Keys, ProtocolError
from protocol.frames import (
    along_across, centre_to_front, front_to_centre, sumo_angle_to_yaw, wrap_pi, yaw_to_sumo_angle,
)


@pytest.mark.parametrize("angle,yaw", [(0, np.pi / 2), (90, 0.0), (180, -np.pi / 2), (270, np.pi)])
def test_sumo_angle_to_yaw(angle, yaw):
    assert float(wrap_pi(sumo_angle_to_yaw(angle) - yaw)) == pytest.approx(0, abs=1e-12)


def test_angle_round_trip_vectorised():
    a = np.linspace(0, 359.5, 720)
    np.testing.assert_allclose(yaw_to_sumo_angle(sumo_angle_to_yaw(a)), a, atol=1e-9)


def test_front_centre_round_trip_heading_north():
    yaw = sumo_angle_to_yaw(0.0)  # heading north
    cx, cy = front_to_centre(10.0, 20.0, yaw, 5.0)
    assert (cx, cy) == pytest.approx((10.0, 17.5))
    assert centre_to_front(cx, cy, yaw, 5.0) == pytest.approx((10.0, 20.0))


def test_along_across_signs():
    lon, lat = along_across(np.array([1.0, 0.0]), np.array([0.0, 1.0]), 0.0)
    np.testing.assert_allclose(lon, [1, 0], atol=1e-12)
    np.testing.assert_allclose(lat, [0, 1], atol=1e-12)


def test_keys_layout():
    k = Keys("sumoco", "demo")
    assert k.step == "sumoco/demo/sumo/step"
    assert k.static == "sumoco/demo/sumo/static"
    assert k.ack == "sumoco/demo/physics/main/ack"
    assert Keys("sumoco", "demo", "paper").physics_state == "sumoco/demo/physics/paper/state"
    assert k.ack_all == "sumoco/demo/physics/*/ack"
    assert Keys.instance_of("sumoco/demo/physics/paper/ack") == "paper"
    assert k.ego("ego") == "sumoco/demo/ego/ego"
    assert k.ego_all == "sumoco/demo/ego/*"


@pytest.mark.parametrize("bad", ["", "a*b", "x/y", "$", "a b"])
def test_bad_run_id_names_itself(bad):
    with pytest.raises(ProtocolError, match="run"):
        Keys("sumoco", bad)
