"""Sensor corruption: accelerometer/gyro noise (thesis eq. 2.34–2.35) and GNSS chainage errors."""

from __future__ import annotations

import numpy as np


def add_noise(signal: np.ndarray, pct: float, rng: np.random.Generator) -> np.ndarray:
    """Signal plus white Gaussian noise whose std is ``pct`` % of the signal's std (eq. 2.34–2.35)."""
    signal = np.asarray(signal, dtype=float)
    if pct < 0 or not np.isfinite(pct):
        raise ValueError(f"noise pct: must be a finite percentage >= 0, got {pct!r}")
    return signal + (pct / 100.0) * np.std(signal) * rng.standard_normal(signal.shape)


def snr_db(pct: float) -> float:
    """The signal-to-noise ratio of eq. (2.35) that a noise level of ``pct`` % corresponds to."""
    return float(10.0 * np.log10(1.0 / (pct / 100.0) ** 2))


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
    bias = float(rng.normal(0.0, bias_sd_m)) if bias_sd_m > 0 else 0.0
    scale_err = float(rng.normal(0.0, speed_error_sd)) if speed_error_sd > 0 else 0.0
    reported = x[0] + bias + (1.0 + scale_err) * (x - x[0])
    if jitter_sd_m > 0:
        reported = reported + rng.normal(0.0, jitter_sd_m, x.shape)
    return reported, bias, scale_err
