"""Sensor corruption: the noise model of thesis eq. (2.34)–(2.35) and GNSS chainage errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.sensors import add_noise, gnss_chainage, snr_db

N = 200_000  # samples: the sample std of the noise is then within ~0.5 % (3 sd) of its true value


def channel(n: int = N, seed: int = 0) -> np.ndarray:
    """A non-white, offset test signal (the noise level must follow its std, not its RMS)."""
    t = np.arange(n) / 500.0
    rng = np.random.default_rng(seed)
    tones = 0.8 * np.sin(2 * np.pi * 1.7 * t) + 0.3 * np.sin(2 * np.pi * 11.0 * t + 0.4)
    return 3.0 + tones + 0.05 * rng.standard_normal(n)


# --- add_noise ---------------------------------------------------------------------------------


@pytest.mark.parametrize("pct", [0.5, 1.0, 2.0, 5.0, 10.0])
def test_noise_std_is_pct_of_the_channel_std(pct):
    signal = channel()
    noise = add_noise(signal, pct, np.random.default_rng(1)) - signal
    assert np.std(noise) / np.std(signal) == pytest.approx(pct / 100.0, rel=0.02)
    assert abs(np.mean(noise)) < 5 * np.std(noise) / math.sqrt(N)  # zero mean
    lag1 = np.corrcoef(noise[:-1], noise[1:])[0, 1]
    assert abs(lag1) < 5 / math.sqrt(N)  # white
    kurtosis = np.mean((noise - noise.mean()) ** 4) / np.var(noise) ** 2
    assert kurtosis == pytest.approx(3.0, abs=0.1)  # Gaussian


def test_noise_level_follows_eq_2_35():
    """10·log10(var(A)/E²) measured on the noisy signal equals snr_db(pct)."""
    signal = channel()
    for pct in (1.0, 3.0):
        noise = add_noise(signal, pct, np.random.default_rng(2)) - signal
        measured = 10 * np.log10(np.var(signal) / np.var(noise))
        assert measured == pytest.approx(snr_db(pct), abs=0.1)


def test_each_channel_of_a_2d_signal_gets_noise_scaled_by_its_own_std():
    acc = channel()  # m/s²
    pitch_rate = 1e-3 * channel(seed=5)  # rad/s: a thousand times smaller
    signal = np.column_stack([acc, pitch_rate])
    noise = add_noise(signal, 2.0, np.random.default_rng(3)) - signal
    ratio = np.std(noise, axis=0) / np.std(signal, axis=0)
    np.testing.assert_allclose(ratio, [0.02, 0.02], rtol=0.02)
    assert abs(np.corrcoef(noise.T)[0, 1]) < 5 / math.sqrt(N)  # independent between channels


def test_zero_noise_leaves_the_signal_unchanged():
    signal = channel(1000)
    out = add_noise(signal, 0.0, np.random.default_rng(4))
    np.testing.assert_array_equal(out, signal)
    assert out is not signal


def test_noise_is_reproducible_from_the_seed():
    signal = channel(5000)
    a = add_noise(signal, 2.0, np.random.default_rng(42))
    b = add_noise(signal, 2.0, np.random.default_rng(42))
    c = add_noise(signal, 2.0, np.random.default_rng(43))
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-3


def test_noise_does_not_modify_its_input():
    signal = channel(1000)
    before = signal.copy()
    add_noise(signal, 5.0, np.random.default_rng(0))
    np.testing.assert_array_equal(signal, before)


@pytest.mark.parametrize("pct", [-1.0, -1e-9, math.nan, math.inf, -math.inf, "two", None, [1.0]])
def test_invalid_noise_pct_is_rejected(pct):
    with pytest.raises(ValueError, match="noise pct"):
        add_noise(channel(100), pct, np.random.default_rng(0))


# --- snr_db ------------------------------------------------------------------------------------


def test_snr_db_values():
    assert snr_db(1.0) == pytest.approx(40.0)
    assert snr_db(10.0) == pytest.approx(20.0)
    assert snr_db(100.0) == pytest.approx(0.0)
    assert snr_db(2.0) == pytest.approx(10 * math.log10(1 / 0.02**2))
    assert snr_db(0.0) == math.inf  # noise-free
    assert snr_db(1.0) > snr_db(2.0) > snr_db(5.0)  # more noise, lower SNR


@pytest.mark.parametrize("pct", [-1.0, math.nan, math.inf, "x"])
def test_snr_db_rejects_invalid_pct(pct):
    with pytest.raises(ValueError):
        snr_db(pct)


# --- gnss_chainage -----------------------------------------------------------------------------


def true_chainage(n: int = 2000, x0: float = 12.0, step: float = 0.04) -> np.ndarray:
    return x0 + step * np.arange(n)


def test_gnss_without_errors_reports_the_truth():
    x = true_chainage()
    reported, bias, scale = gnss_chainage(x, np.random.default_rng(0))
    np.testing.assert_array_equal(reported, x)
    assert bias == 0.0 and scale == 0.0


def test_gnss_bias_and_scale_are_what_the_reported_chainage_carries():
    x = true_chainage()
    reported, bias, scale = gnss_chainage(x, np.random.default_rng(1), bias_sd_m=2.0, speed_error_sd=0.02)
    np.testing.assert_allclose(reported, x[0] + bias + (1 + scale) * (x - x[0]), rtol=0, atol=1e-12)
    assert bias != 0.0 and scale != 0.0


def test_gnss_bias_and_scale_statistics_over_many_passes():
    x = true_chainage(50)
    rng = np.random.default_rng(7)
    draws = np.array([gnss_chainage(x, rng, bias_sd_m=2.0, speed_error_sd=0.02)[1:] for _ in range(4000)])
    bias, scale = draws.T
    # 4000 passes: the sample sd is within ~3.4 % (3 sd) of the true value, the mean within 3 sd/√n
    assert np.std(bias) == pytest.approx(2.0, rel=0.04)
    assert np.std(scale) == pytest.approx(0.02, rel=0.04)
    assert abs(np.mean(bias)) < 3 * 2.0 / math.sqrt(4000)
    assert abs(np.mean(scale)) < 3 * 0.02 / math.sqrt(4000)
    assert abs(np.corrcoef(bias, scale)[0, 1]) < 3 / math.sqrt(4000)


def test_gnss_jitter_is_white_with_the_given_sd():
    x = true_chainage(N)
    reported, bias, scale = gnss_chainage(x, np.random.default_rng(3), jitter_sd_m=0.05)
    assert bias == 0.0 and scale == 0.0
    jitter = reported - x
    assert np.std(jitter) == pytest.approx(0.05, rel=0.02)
    assert abs(np.mean(jitter)) < 5 * 0.05 / math.sqrt(N)
    assert abs(np.corrcoef(jitter[:-1], jitter[1:])[0, 1]) < 5 / math.sqrt(N)


def test_gnss_is_reproducible_from_the_seed():
    x = true_chainage()
    kw = dict(bias_sd_m=2.0, jitter_sd_m=0.05, speed_error_sd=0.02)
    a = gnss_chainage(x, np.random.default_rng(9), **kw)
    b = gnss_chainage(x, np.random.default_rng(9), **kw)
    c = gnss_chainage(x, np.random.default_rng(10), **kw)
    np.testing.assert_array_equal(a[0], b[0])
    assert a[1:] == b[1:]
    assert a[1] != c[1]


@pytest.mark.parametrize("name", ["bias_sd_m", "jitter_sd_m", "speed_error_sd"])
@pytest.mark.parametrize("value", [-0.1, math.nan, math.inf])
def test_gnss_rejects_invalid_error_levels(name, value):
    with pytest.raises(ValueError, match=name):
        gnss_chainage(true_chainage(), np.random.default_rng(0), **{name: value})
