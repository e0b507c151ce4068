"""Sensor corruption: accelerometer/gyro noise (thesis eq. 2.34–2.35) and GNSS chainage errors."""

from __future__ import annotations

import math

import numpy as np


def _nonnegative(name: str, value: object) -> float:
    """``value`` as a finite float >= 0, or ValueError naming ``name``."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be a finite number >= 0, got {value!r}") from None
    if not (math.isfinite(x) and x >= 0):
        raise ValueError(f"{name}: must be a finite number >= 0, got {value!r}")
    return x


def add_noise(signal: np.ndarray, pct: float, rng: np.random.Generator) -> np.ndarray:
    """Signal plus white Gaussian noise whose std is ``pct`` % of the signal's std (eq. 2.34–2.35).

    Note the convention: ``pct`` is a percentage of the *std*. The thesis's "1 % noise (SNR = 100)"
    is 1 % in *power*, i.e. a noise std of 10 % of the signal's; our scenarios' 1 % is 1 % of the
    std (a decision, kept; see the thesis notes).

    A 1-D ``signal`` is one channel; for an (n_samples, n_channels) array each column gets noise
    scaled by its own std, so channels of different units (m/s², rad/s) keep their own level.
    """
    signal = np.asarray(signal, dtype=float)
    pct = _nonnegative("noise pct", pct)
    return signal + (pct / 100.0) * np.std(signal, axis=0) * rng.standard_normal(signal.shape)


def snr_db(pct: float) -> float:
    """The signal-to-noise ratio of eq. (2.35), dB, that a noise level of ``pct`` % corresponds to.

    SNR = 10·log10(var(A) / E²) with E = pct/100·std(A), i.e. −20·log10(pct/100); inf for 0 %.
    """
    pct = _nonnegative("noise pct", pct)
    if pct == 0.0:
        return math.inf
    return -20.0 * math.log10(pct / 100.0)


def gnss_chainage(
    true_chainage_m: np.ndarray,
    rng: np.random.Generator,
    bias_sd_m: float = 0.0,
    jitter_sd_m: float = 0.0,
    speed_error_sd: float = 0.0,
) -> tuple[np.ndarray, float, float]:
    """Chainage as a GNSS/odometry receiver would report it.

    The reported chainage is shifted by a per-pass bias (sd ``bias_sd_m``), stretched by a per-pass
    relative speed (odometry scale) error (sd ``speed_error_sd``, e.g. 0.02 for 2 %) about the start
    of the pass, and carries white jitter (sd ``jitter_sd_m``). Returns (reported, bias, scale error).
    """
    x = np.asarray(true_chainage_m, dtype=float)
    bias_sd_m = _nonnegative("bias_sd_m", bias_sd_m)
    jitter_sd_m = _nonnegative("jitter_sd_m", jitter_sd_m)
    speed_error_sd = _nonnegative("speed_error_sd", speed_error_sd)
    bias = float(rng.normal(0.0, bias_sd_m)) if bias_sd_m > 0 else 0.0
    scale_err = float(rng.normal(0.0, speed_error_sd)) if speed_error_sd > 0 else 0.0
    reported = x[0] + bias + (1.0 + scale_err) * (x - x[0])
    if jitter_sd_m > 0:
        reported = reported + rng.normal(0.0, jitter_sd_m, x.shape)
    return reported, bias, scale_err
