"""The edge's chainage: odometry anchored on GNSS — affine over a pass, bounded over a long drive."""

from __future__ import annotations

import numpy as np
import pytest

from edge.chainage import ChainageTracker
from simfleet.sim import gnss_and_odometry


def _drive(duration_s: float, dt: float, v: float, seed: int, bias_sd=2.0, jitter_sd=0.05, speed_sd=0.02):
    rng = np.random.default_rng(seed)
    x_true = 3.0 + v * np.arange(0.0, duration_s, dt)
    gnss, bias, scale_err = gnss_and_odometry(x_true, rng, bias_sd, jitter_sd, speed_sd)
    return x_true, gnss, np.full(x_true.size, v * (1 + scale_err)), bias, scale_err


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_over_a_pass_the_chainage_error_is_a_shift_and_a_stretch(seed):
    """What the cloud's alignment can remove exactly: x_rep − x_true = b + ε·(x − x₀) to ~1 cm."""
    dt, v = 0.002, 20.0
    x_true, gnss, speed, bias, scale_err = _drive(11.0, dt, v, seed)
    x_rep = ChainageTracker(dt).update(gnss, speed)
    err = x_rep - x_true
    A = np.stack([np.ones_like(x_true), x_true - x_true[0]], axis=1)
    (b, eps), *_ = np.linalg.lstsq(A, err, rcond=None)
    assert np.max(np.abs(err - A @ (b, eps))) < 0.015
    assert b == pytest.approx(gnss[0] - x_true[0], abs=0.01)  # anchored on the first GNSS fix
    assert eps == pytest.approx(scale_err, abs=1e-3)  # the odometer's scale error, nearly all of it
    assert np.all(np.diff(x_rep) > 0)  # never runs backwards


def test_over_a_long_drive_gnss_wins_and_the_odometer_scale_is_learnt():
    dt, v = 0.05, 15.0
    x_true, gnss, speed, bias, scale_err = _drive(4 * 3600.0, dt, v, seed=4, jitter_sd=0.5, speed_sd=0.03)
    tracker = ChainageTracker(dt)
    x_rep = tracker.update(gnss, speed)
    err = x_rep - x_true
    # Bounded: a critically damped type-2 loop peaks at Δv·τ/e for a speed error Δv (pure odometry
    # would grow as Δv·t, here ~2 km); the price of keeping a pass affine is this slow pull.
    dv = v * abs(scale_err) / (1 + scale_err)
    assert np.max(np.abs(err - bias)) < 1.1 * dv * tracker_tau(tracker) / np.e + 1.0
    assert np.abs(err[-1000:] - bias).max() < 0.3  # converged onto GNSS (its bias is all it has)
    assert tracker.scale * (1 + scale_err) == pytest.approx(1.0, abs=2e-4)


def tracker_tau(t: ChainageTracker) -> float:
    return float(np.sqrt(t.dt / t.k_scale))


def test_streaming_in_chunks_equals_one_shot():
    dt = 0.002
    _, gnss, speed, _, _ = _drive(6.0, dt, 18.0, seed=3)
    one = ChainageTracker(dt).update(gnss, speed)
    t = ChainageTracker(dt)
    chunks = np.split(np.arange(gnss.size), [7, 500, 1234, 2000])
    many = np.concatenate([t.update(gnss[c], speed[c]) for c in chunks])
    np.testing.assert_allclose(many, one, rtol=0, atol=1e-9)


def test_rejects_non_positive_time_constants():
    with pytest.raises(ValueError):
        ChainageTracker(0.002, tau_s=0.0)
