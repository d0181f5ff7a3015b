"""Footprint geometry of the contact rules (``physics_side.policies.footprints``): closed forms."""

from __future__ import annotations

import math

import numpy as np

from physics_side.policies.footprints import (centre, footprint_gap, footprints_overlap, gap_floor, near_pairs,
                                             overlaps_any)


def test_near_pairs_and_footprint_gaps_match_a_brute_force_check():
    rng = np.random.default_rng(4)
    x, y, r = rng.uniform(0, 60, 300), rng.uniform(0, 20, 300), rng.uniform(0.2, 4.0, 300)
    i, j = near_pairs(x, y, r)
    d = np.hypot(x[:, None] - x, y[:, None] - y) < r[:, None] + r
    want = {(a, b) for a, b in zip(*np.nonzero(np.triu(d, 1)))}
    assert set(zip(i.tolist(), j.tolist())) == want and len(i) == len(want)
    # two 4 x 2 m boxes side by side 0.5 m apart, end to end 1 m apart, crossing (overlap)
    g = footprint_gap(0.0, 0.0, 0.0, 4.0, 2.0, np.array([0.0, 5.0, 1.0]), np.array([2.5, 0.0, 1.0]),
                      np.array([0.0, 0.0, math.pi / 2]), 4.0, 2.0)
    assert np.allclose(g[:2], [0.5, 1.0]) and g[2] < 0


def test_near_pairs_of_fewer_than_two_discs_is_empty_and_zero_radii_meet_only_on_the_spot():
    i, j = near_pairs(np.array([1.0]), np.array([2.0]), np.array([1.0]))
    assert len(i) == len(j) == 0
    i, j = near_pairs(np.array([0.0, 0.0, 5.0]), np.array([0.0, 0.0, 0.0]), np.zeros(3))
    assert len(i) == 0  # touching discs of radius 0 do not overlap (strict)


def test_a_rotated_box_gap_is_its_corner_distance_along_the_separating_axis():
    # a 2 x 2 m box turned 45 deg reaches sqrt(2) m along x: 3 m away its gap to a 2 x 2 box is 3 - 1 - sqrt 2
    g = footprint_gap(0.0, 0.0, 0.0, 2.0, 2.0, 3.0, 0.0, math.pi / 4, 2.0, 2.0)
    assert abs(float(g) - (3.0 - 1.0 - math.sqrt(2.0))) < 1e-12


def test_overlap_with_a_margin_grows_both_boxes():
    # 0.5 m apart side by side: apart without a margin, overlapping with 0.3 m each
    assert not footprints_overlap(0.0, 0.0, 0.0, 4.0, 2.0, 0.0, 2.5, 0.0, 4.0, 2.0)
    assert footprints_overlap(0.0, 0.0, 0.0, 4.0, 2.0, 0.0, 2.5, 0.0, 4.0, 2.0, margin=0.3)
    assert not footprints_overlap(0.0, 0.0, 0.0, 4.0, 2.0, 0.0, 2.5, 0.0, 4.0, 2.0, margin=0.2)


def test_centre_is_half_a_length_behind_the_bumper_and_overlaps_any_checks_a_mask():
    cx, cy = centre(np.array([10.0, 0.0]), np.array([0.0, 4.0]), np.array([0.0, math.pi / 2]), np.array([4.0, 2.0]))
    assert np.allclose(cx, [8.0, 0.0]) and np.allclose(cy, [0.0, 3.0])
    x, y, yaw = np.array([0.0, 3.0, 30.0]), np.zeros(3), np.zeros(3)
    L, W = np.full(3, 4.0), np.full(3, 2.0)
    assert overlaps_any(0, x, y, yaw, L, W, np.array([False, True, True]))
    assert not overlaps_any(0, x, y, yaw, L, W, np.array([False, False, True]))
    assert not overlaps_any(0, x, y, yaw, L, W, np.zeros(3, bool))


def test_gap_floor_never_exceeds_the_separating_axis_gap():
    """The contact guard prunes pairs with ``gap_floor``: it must be a lower bound of
    ``footprint_gap`` for every pair of rectangles, or the guard would miss a near pair."""
    rng = np.random.default_rng(11)
    n = 400
    x, y = rng.uniform(-15, 15, n), rng.uniform(-15, 15, n)
    yaw = rng.uniform(-np.pi, np.pi, n)
    length, width = rng.uniform(0.5, 18.0, n), rng.uniform(0.4, 2.6, n)
    i, j = np.triu_indices(n, 1)
    exact = footprint_gap(x[i], y[i], yaw[i], length[i], width[i], x[j], y[j], yaw[j], length[j], width[j])
    floor = gap_floor(x, y, i, j, 0.5 * np.maximum(length, width), 0.5 * np.hypot(length, width))
    assert np.all(floor <= exact + 1e-9), float(np.max(floor - exact))
    # and it prunes: most of these pairs are far apart
    assert np.mean(floor > 0.1) > 0.5
