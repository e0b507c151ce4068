"""Whole drives → passes (edge.trip) on simulated network drives: nothing but steady driving on one
route, in its direction, enters a pass; every cut is counted; the match lands on the true route."""

import numpy as np
import pytest

from edge.trip import REASONS, TripError, TripSettings, split_trip
from edge.mapmatch import build_network
from shared.drivelog import DriveLog
from simfleet.network import TRIPS, NetworkScenario, logger_rotation, geometries, route_surfaces, simulate_trip
from simfleet.scenarios import TABLE_4_1

SC = NetworkScenario("t", "test", fleet_mean=tuple(TABLE_4_1["mean"].items()),
                     fleet_std=tuple(TABLE_4_1["std"].items()))
SETTINGS = TripSettings()


@pytest.fixture(scope="module")
def world():
    geoms = geometries()
    surfaces = route_surfaces(geoms, "A", 0)
    net = build_network(geoms)
    trips = []
    for i in range(len(TRIPS)):
        log, truth = simulate_trip(SC, TRIPS[i], geoms, surfaces, dict(TABLE_4_1["mean"]), f"veh-{i + 1:04d}", i,
                                   1000 + i, dict(TABLE_4_1["mean"]))
        trips.append((log, truth, split_trip(log, net, SETTINGS)))
    return net, trips


def _truth_at(truth, t):
    k = np.searchsorted(truth["t"], t)
    k = np.clip(k, 0, len(truth["t"]) - 1)
    # Pass samples sit on the nominal grid, truth on the logger's jittered stamps: nearest within a step.
    prev = np.clip(k - 1, 0, None)
    k = np.where(np.abs(truth["t"][prev] - t) < np.abs(truth["t"][k] - t), prev, k)
    assert np.max(np.abs(truth["t"][k] - t)) < 2.5 / SC.sample_rate_hz
    return k


def test_passes_are_ordinary_single_route_logs(world):
    _, trips = world
    n = 0
    for _, _, res in trips:
        for p in res.passes:
            assert isinstance(p, DriveLog) and p.is_pass and not p.has_positions
            assert set(p.channels) == {"body_acc"} and p.meta.route_id in {"R1", "R2", "R3", "R4"}
            assert np.all(np.diff(p.chainage) > 0)  # in the route's direction
            n += 1
    assert n >= 10


def test_no_stop_braking_turn_or_wrong_route_enters_a_pass(world):
    """Fails if a braking or accelerating stretch, a stop, or a sample of another route is fused."""
    _, trips = world
    for _, truth, res in trips:
        for p in res.passes:
            k = _truth_at(truth, p.t)
            # 0.1 m/s² above the threshold: the fused acceleration's own error on steady stretches.
            assert np.max(np.abs(truth["long_acc"][k])) <= SETTINGS.max_long_acc_mps2 + 0.1, p.meta.pass_id
            assert np.min(truth["speed"][k]) >= SETTINGS.min_speed_mps, p.meta.pass_id
            assert {truth["route"][i] for i in k} == {p.meta.route_id}, p.meta.pass_id


def test_braking_and_stops_happen_and_are_counted(world):
    _, trips = world
    for log, truth, res in trips:
        assert set(res.cut_s) == set(REASONS)
        assert np.min(truth["speed"]) == 0.0 and np.min(truth["long_acc"]) < -2.0  # the world has them
        # A stop or braking on a route driven against its chainage is counted under that reason first.
        assert res.cut_s["slow"] + res.cut_s["against_chainage"] > 0
        assert res.cut_s["long_acc"] + res.cut_s["against_chainage"] > 0 and res.cut_s["settling"] > 0
        # The simulated IMU gap (0.6 s) is cut; a jittered neighbour step may add up to two steps.
        assert SC.imu_gap_s - 0.01 <= res.cut_s["imu_gap"] <= SC.imu_gap_s + 3 / SC.sample_rate_hz
        kept = sum(len(p) for p in res.passes) / SC.sample_rate_hz
        span = float(log.t[-1] - log.t[0])
        assert kept + sum(res.cut_s.values()) == pytest.approx(span, abs=0.5)  # every second accounted for
    assert sum(r.cut_s["slow"] for *_, r in trips) > 0 and sum(r.cut_s["long_acc"] for *_, r in trips) > 0


def test_passes_against_chainage_are_rejected(world):
    _, trips = world
    log, truth, res = trips[2]  # R3 and R2 driven against their chainage, then R4 along it
    assert {p.meta.route_id for p in res.passes} == {"R4"}
    against = sum(truth["speed"][i] > 0 for i in range(len(truth["t"])) if truth["route"][i] in ("R3", "R2"))
    assert res.cut_s["against_chainage"] > 0.5 * against / SC.sample_rate_hz


def test_map_matching_error(world):
    """Chainage vs truth over all pass samples: GNSS error is absolute (metres), never a drift."""
    _, trips = world
    err = []
    for _, truth, res in trips:
        for p in res.passes:
            k = _truth_at(truth, p.t)
            err.append(p.chainage - truth["chainage"][k])
    e = np.abs(np.concatenate(err))
    # The simulated fixes err by 1.2 m (slow wander) and 0.7 m (white) per axis: the along-track
    # error cannot beat the wander's ~0.8 m median, and must not exceed a few of its sigmas.
    assert np.median(e) < 2.0 and np.percentile(e, 95) < 4.0, (np.median(e), np.percentile(e, 95))


def test_logger_orientation_is_found(world):
    _, trips = world
    R = logger_rotation(*SC.tilt_deg)  # logger ← vehicle
    for _, _, res in trips:
        f = res.frame
        assert np.degrees(np.arccos(f.up @ R[:, 2])) < 0.5  # the vertical: body_acc loses < 4e-5 of itself
        assert np.degrees(np.arccos(f.forward @ R[:, 0])) < 6.0  # heading: only the fusion's input


def test_drive_without_positions_is_refused(world):
    net, trips = world
    log = trips[0][0]
    bare = DriveLog(log.meta, log.t, None, None, {}, True, None, None, None, log.imu)
    with pytest.raises(TripError, match="no lat/lon"):
        split_trip(bare, net)
