"""The accelerometer's along-track bias, once per drive (edge.trip.imu_bias), and the simulated
drives' consistency that an estimate of it relies on (simfleet.network.speed_profile)."""

import math

import numpy as np

from edge.trip import TripSettings, imu_bias
from simfleet.network import local_to_latlon, speed_profile

FS = 200.0


def _drive(seed: int, bias: float, leak: float):
    """A drive along a straight road with two stops, its GNSS at 5 Hz with a wandering error, and an
    IMU whose longitudinal axis reads ``bias`` plus ``leak`` of a lateral acceleration (one turn)."""
    rng = np.random.default_rng(seed)
    s, v, a = speed_profile(900.0, [300.0, 600.0], 13.0, 1.5, 2.5, 4.0, 1.0 / FS, brake_at=150.0)
    t = np.arange(len(s)) / FS
    lat_acc = np.where((t > 20.0) & (t < 22.0), 3.0, 0.0)  # a bend's lateral acceleration
    long_acc = a + bias + leak * lat_acc + rng.normal(0.0, 0.02, len(t))
    fix = np.arange(0, len(t), int(FS / 5))
    tau, sd = 30.0, 1.2
    phi = math.exp(-0.2 / tau)
    w = np.zeros((len(fix), 2))
    w[0] = rng.normal(0.0, sd, 2)
    for i in range(1, len(fix)):
        w[i] = phi * w[i - 1] + math.sqrt(1 - phi * phi) * rng.normal(0.0, sd, 2)
    e = w + rng.normal(0.0, 0.7, w.shape)
    la, lo = local_to_latlon(s[fix] + e[:, 0], e[:, 1])
    return t, long_acc, lat_acc, t[fix], la, lo


def test_the_simulated_speed_changes_only_by_what_the_accelerometer_sees():
    # A speed that drops to zero at a stop line without a deceleration would read as a bias to any
    # estimate that integrates the IMU between stops.
    s, v, a = speed_profile(600.0, [200.0, 400.0], 13.0, 1.5, 2.5, 4.0, 1.0 / 800.0, brake_at=100.0)
    assert np.max(np.abs(np.diff(v) - a[1:] / 800.0)) < 0.005  # m/s: clipping at rest, one step
    assert abs(v[-1] - v[0] - np.sum(a[1:]) / 800.0) < 0.02


def test_the_drives_bias_is_known_to_millimetres_per_second_squared_and_its_stated_sigma_covers():
    errs, within = [], []
    for seed in range(6):
        b = 0.02 * (seed - 2.5) / 2.5
        t, la, lt, tf, lat, lon = _drive(seed, b, 0.03)
        est = imu_bias([(t, la, lt)], tf, lat, lon, TripSettings())
        assert est is not None
        errs.append(est.bias_mps2 - b)
        within.append(abs(est.bias_mps2 - b) <= 1.96 * est.bias_sd_mps2)
    # A stretch's own fixes leave a bias to ~1e-2 m/s² (a bend of decimetres in a 20 s pass); the
    # whole drive's speed (minutes, two stops) pins it to a few mm/s².
    assert np.sqrt(np.mean(np.square(errs))) < 0.004, errs
    assert all(within), (errs, within)
