"""The drive's accelerometer bias with the standstills the IMU itself sees (edge.trip.imu_bias,
edge.trip.rest_samples): standing, the speed is zero exactly, and across a short IMU gap it goes on."""

import math

import numpy as np

from edge.trip import TripSettings, imu_bias, rest_samples
from simfleet.network import local_to_latlon, speed_profile

FS = 200.0


def _drive(seed: int, bias: float, leak: float):
    """A straight drive with two stops, split by a 0.6 s IMU gap: per run (time, longitudinal and
    lateral acceleration, vertical specific force), the GNSS fixes (5 Hz, wandering), the true speed."""
    rng = np.random.default_rng(seed)
    s, v, a = speed_profile(900.0, [300.0, 600.0], 13.0, 1.5, 2.5, 4.0, 1.0 / FS, brake_at=150.0)
    t = np.arange(len(s)) / FS
    lat_acc = np.where((t > 20.0) & (t < 22.0), 3.0, 0.0)  # a bend's lateral acceleration
    long_acc = a + bias + leak * lat_acc + rng.normal(0.0, 0.02, len(t))
    # The road shakes the body in proportion to the speed; standing, only the sensor's noise is left.
    vertical = 0.05 * v * rng.normal(0.0, 1.0, len(t)) + rng.normal(0.0, 0.005, len(t))
    fix = np.arange(0, len(t), int(FS / 5))
    phi = math.exp(-0.2 / 30.0)
    w = np.zeros((len(fix), 2))
    w[0] = rng.normal(0.0, 1.2, 2)
    for i in range(1, len(fix)):
        w[i] = phi * w[i - 1] + math.sqrt(1 - phi * phi) * rng.normal(0.0, 1.2, 2)
    e = w + rng.normal(0.0, 0.7, w.shape)
    la, lo = local_to_latlon(s[fix] + e[:, 0], e[:, 1])
    cut = np.searchsorted(t, 0.5 * t[-1])
    keep = [slice(0, cut), slice(cut + int(0.6 * FS), len(t))]
    runs = [(t[k], long_acc[k], lat_acc[k], vertical[k]) for k in keep]
    return runs, t[fix], la, lo, (t, v)


def test_rest_samples_are_standing():
    runs, *_, (t, v) = _drive(0, 0.01, 0.0)
    for tr, la, _, vert in runs:
        rest = rest_samples(vert, la, int(FS))
        assert len(rest) >= 1
        assert np.all(np.interp(tr[rest], t, v) == 0.0), np.interp(tr[rest], t, v)


def test_the_standstills_pin_the_drives_bias_and_its_sigma_still_covers():
    errs = {"gnss": [], "rests": []}
    within = []
    for seed in range(6):
        b = 0.02 * (seed - 2.5) / 2.5
        runs, tf, lat, lon, _ = _drive(seed, b, 0.03)
        three = [(tr, la, lt) for tr, la, lt, _ in runs]
        rests = [rest_samples(vert, la, int(FS)) for _, la, _, vert in runs]
        alone = imu_bias(three, tf, lat, lon, TripSettings())
        est = imu_bias(three, tf, lat, lon, TripSettings(), rests)
        errs["gnss"].append(alone.bias_mps2 - b)
        errs["rests"].append(est.bias_mps2 - b)
        within.append(abs(est.bias_mps2 - b) <= 1.96 * est.bias_sd_mps2)
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in errs.items()}
    assert rms["rests"] < rms["gnss"], rms
    assert all(within), (errs, within)
