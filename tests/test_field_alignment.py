"""Centring the passes' alignment maps when passes are partial (field drives cut at stops and turns):
a short pass far from chainage 0 must not move the fleet's frame by its ill-determined stretch."""

import numpy as np

from cloud.road.alignment import Alignment, centred


def test_a_short_pass_far_down_the_route_leaves_the_frame_where_the_passes_are():
    # Two passes over the whole 600 m route, already in the true frame, and a 110 m pass at 430–540 m
    # whose stretch came out at +0.5 % (a short pass's stretch is poorly known): exact at its middle,
    # 0.28 m off at its ends — but 2.4 m off if its line is carried to chainage 0.
    als = [Alignment(0.0, 0.0, 0.0, 1.0), Alignment(0.0, 0.0, 5.0, 1.0), Alignment(-0.005 * 55.0, 0.005, 430.0, 1.0)]
    extents = [(0.0, 600.0), (5.0, 600.0), (430.0, 540.0)]
    x = np.linspace(0.0, 600.0, 61)
    moved = [np.max(np.abs(c.true_to_reported(x) - a.true_to_reported(x))) for a, c in zip(als, centred(als, extents))]
    # The full passes' frames move by what the short pass's stretch tilts the route's mean line (a
    # few cm where the passes are), not by its extrapolated offset.
    assert max(moved[:2]) < 0.1, moved
    # Without the extents the maps are averaged at chainage 0, and every pass moves by ~0.8 m.
    moved_at_origin = [np.max(np.abs(c.true_to_reported(x) - a.true_to_reported(x))) for a, c in zip(als, centred(als))]
    assert min(moved_at_origin[:2]) > 0.5, moved_at_origin


def test_passes_spanning_the_same_stretch_centre_as_before():
    rng = np.random.default_rng(1)
    als = [Alignment(float(b), float(e), 0.0, 1.0) for b, e in zip(rng.normal(0, 2, 5), rng.normal(0, 0.01, 5))]
    extents = [(0.0, 500.0)] * 5
    for a, b in zip(centred(als), centred(als, extents)):
        assert abs(a.shift_m - b.shift_m) < 1e-9 and abs(a.stretch - b.stretch) < 1e-12
