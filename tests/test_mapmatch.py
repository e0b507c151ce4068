"""Map matching (edge.mapmatch): the HMM follows a drive through a junction, refuses to force
off-network fixes onto a route, and marks fixes between two close parallel roads ambiguous."""

import numpy as np
import pytest

from edge.mapmatch import OFF, MatchSettings, build_network, match
from simfleet.network import local_to_latlon
from shared.geo import RouteGeometry


def line(points):
    e, n = np.array(points, float).T
    lat, lon = local_to_latlon(e, n)
    return RouteGeometry.from_latlon(np.column_stack([lat, lon]))


def fixes(points, sd, rng):
    p = np.array(points, float) + rng.normal(0.0, sd, (len(points), 2))
    return local_to_latlon(p[:, 0], p[:, 1])


def test_junctions_are_found():
    net = build_network({"A": line([(0, 0), (500, 0)]), "B": line([(500, 0), (500, 400)]),
                         "C": line([(250, -100), (250, 100)])})
    pairs = {(net.route_ids[j.a], net.route_ids[j.b]): (j.chainage_a, j.chainage_b) for j in net.junctions}
    assert pairs.keys() == {("A", "B"), ("A", "C")}
    assert pairs[("A", "B")] == pytest.approx((500.0, 0.0), abs=2.5)  # the 2 m scan step
    assert pairs[("A", "C")] == pytest.approx((250.0, 100.0), abs=2.5)


def test_drive_through_a_junction_follows_the_turn_not_the_crossing():
    rng = np.random.default_rng(1)
    net = build_network({"A": line([(0, 0), (500, 0)]), "B": line([(500, 0), (500, 400)]),
                         "C": line([(250, -100), (250, 100)])})
    # 12 m/s at 5 Hz: along A (crossing C at 250 m), then up B.
    s = np.arange(0.0, 800.0, 12.0 / 5)
    pts = [(x, 0.0) if x <= 500 else (500.0, x - 500) for x in s]
    lat, lon = fixes(pts, 1.5, rng)
    m = match(net, lat, lon, np.full(len(s), 1.5))
    truth = np.where(s <= 500, net.route_ids.index("A"), net.route_ids.index("B"))
    clear = np.abs(s - 500) > 15  # within a junction's reach either route is right
    assert np.all(m.route[clear] == truth[clear])
    expected = np.where(s <= 500, s, s - 500)
    assert np.median(np.abs(m.chainage[clear] - expected[clear])) < 1.5
    assert not m.ambiguous[clear & (np.abs(s - 250) > 15)].any()  # the crossing does not confuse it


def test_off_network_fixes_are_not_forced_onto_a_route():
    rng = np.random.default_rng(2)
    net = build_network({"A": line([(0, 0), (500, 0)])})
    s = np.arange(0.0, 400.0, 2.4)
    pts = [(x, 0.0) if x < 200 else (200.0, (x - 200)) for x in s]  # leaves along an unmapped road
    lat, lon = fixes(pts, 1.0, rng)
    m = match(net, lat, lon, np.full(len(s), 1.0))
    far = s > 200 + 40
    assert np.all(m.route[far] == OFF) and np.all(np.isnan(m.chainage[far]))
    assert np.all(m.route[s < 180] == 0)


def test_parallel_roads_closer_than_the_error_are_ambiguous():
    rng = np.random.default_rng(3)
    net = build_network({"A": line([(0, 0), (500, 0)]), "B": line([(0, 4), (500, 4)])})
    s = np.arange(0.0, 400.0, 2.4)
    lat, lon = fixes([(x, 2.0) for x in s], 3.0, rng)  # between them, 3 m error
    m = match(net, lat, lon, np.full(len(s), 3.0))
    assert m.ambiguous.mean() > 0.9


def test_settings_are_validated():
    with pytest.raises(ValueError, match="radius_m"):
        MatchSettings(radius_m=-1.0)
    with pytest.raises(ValueError, match="min_posterior"):
        MatchSettings(min_posterior=1.0)
