"""A logger's irregular timestamps onto the nominal uniform grid, cut at gaps, anti-aliased.

Logger clocks stamp samples with jitter (a phone's sensor thread is scheduled, not clocked) and
drop samples now and then. The edge's inverse needs a uniform step, so each contiguous run of
samples (no step longer than ``max_gap_steps`` nominal steps) is interpolated by a cubic spline on
its own timestamps — exact for the band the logger resolved — onto a uniform grid at an integer
multiple ``m`` of the nominal rate at or above the logger's mean rate, then low-passed and
decimated by ``m`` (zero-phase Kaiser FIR, cut-off at 0.9 of the nominal Nyquist) so nothing
above it folds back. A run whose steps scatter beyond ``max_jitter`` (rms, relative to the median step) or whose
mean rate is below the nominal one is refused with an error: such timestamps are not jitter but a
broken or mislabelled stream, and upsampling cannot restore a band the logger never sampled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.signal import firwin


class ResampleError(ValueError):
    """Timestamps that cannot be resampled honestly; the message is one line."""


@dataclass(frozen=True)
class ResampleSettings:
    """``max_gap_steps``: a step longer than this many nominal steps is a gap (runs are cut there);
    ``max_jitter``: largest rms deviation of a run's steps from its median step, relative;
    ``min_rate_ratio``: the logger's mean rate must reach this share of the nominal rate;
    ``min_run_s``: shorter runs are dropped (counted as gaps)."""

    max_gap_steps: float = 3.0
    max_jitter: float = 0.5
    min_rate_ratio: float = 0.98
    min_run_s: float = 1.0

    def __post_init__(self):
        for k in ("max_gap_steps", "max_jitter", "min_rate_ratio", "min_run_s"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"ResampleSettings.{k}: must be a positive finite number, got {v!r}")
        if self.max_gap_steps <= 1.0:
            raise ValueError(f"ResampleSettings.max_gap_steps: must exceed 1, got {self.max_gap_steps!r}")


class Run(NamedTuple):
    """One contiguous run on the nominal grid: ``t`` (s, uniform) and each signal resampled."""

    t: np.ndarray
    signals: dict[str, np.ndarray]


def runs(t: np.ndarray, gap_s: float) -> list[tuple[int, int]]:
    """Index ranges ``[a, b)`` of ``t`` with no step longer than ``gap_s``."""
    cut = np.flatnonzero(np.diff(t) > gap_s) + 1
    edges = np.concatenate(([0], cut, [len(t)]))
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def resample(t: np.ndarray, signals: dict[str, np.ndarray], rate_hz: float,
             settings: ResampleSettings = ResampleSettings()) -> tuple[list[Run], float]:
    """Resample ``signals`` (each (n,), sampled at the increasing times ``t``, s) to ``rate_hz``.

    Returns the runs and the seconds lost to gaps (the gaps themselves plus runs too short to keep).
    Raises `ResampleError` when a run's timestamps scatter beyond the settings' tolerance or its
    mean rate is below the nominal one.
    """
    t = np.asarray(t, float)
    dt = 1.0 / rate_hz
    out: list[Run] = []
    lost = 0.0
    pieces = runs(t, settings.max_gap_steps * dt)
    for (a, b), nxt in zip(pieces, [*pieces[1:], None]):
        if nxt is not None:
            lost += float(t[nxt[0]] - t[b - 1])
        span = float(t[b - 1] - t[a]) if b - a > 1 else 0.0
        if span < settings.min_run_s:
            lost += span
            continue
        steps = np.diff(t[a:b])
        med = float(np.median(steps))
        jitter = float(np.sqrt(np.mean((steps / med - 1.0) ** 2)))
        if jitter > settings.max_jitter:
            raise ResampleError(f"timestamps between {t[a]:.3f} s and {t[b - 1]:.3f} s scatter by {jitter:.0%} "
                                f"rms of the median step (tolerance {settings.max_jitter:.0%})")
        rate = (b - a - 1) / span
        if rate < settings.min_rate_ratio * rate_hz:
            raise ResampleError(f"the logger samples at {rate:.4g} Hz between {t[a]:.3f} s and {t[b - 1]:.3f} s, "
                                f"below the nominal sample_rate_hz {rate_hz:g}")
        # A logger a few per cent above the nominal rate resolves nothing the nominal grid cannot
        # hold but a sliver below its Nyquist: no decimation then.
        m = max(1, math.ceil(rate / rate_hz - 0.05))
        fine_dt = dt / m
        # The uniform grid starts on a multiple of the nominal step so that runs share one clock.
        t0 = math.ceil(t[a] / dt - 1e-9) * dt
        n_out = int(math.floor((t[b - 1] - t0) / dt + 1e-9)) + 1
        fine = t0 + np.arange((n_out - 1) * m + 1) * fine_dt
        res = {}
        for name, y in signals.items():
            y_fine = CubicSpline(t[a:b], np.asarray(y[a:b], float))(fine)
            if m > 1:
                y_fine = _lowpass(y_fine, m)[::m]
            res[name] = y_fine[:n_out]
        out.append(Run(t0 + np.arange(n_out) * dt, res))
    return out, lost


def _lowpass(y: np.ndarray, m: int) -> np.ndarray:
    """Zero-phase linear-phase FIR low-pass to 0.9 of the Nyquist of ``y`` decimated by ``m``
    (Kaiser window, β = 8: ~80 dB stop band), reflected at the ends so a run's edges do not sag."""
    taps = firwin(64 * m + 1, 0.9 / m, window=("kaiser", 8.0))
    half = len(taps) // 2
    ext = np.pad(y, half, mode="reflect") if len(y) > half else np.pad(y, half, mode="edge")
    return np.convolve(ext, taps, mode="valid")
