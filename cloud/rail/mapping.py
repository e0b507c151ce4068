"""A rail run's AP from time to chainage: the comparison grid every run of a batch covers
(:func:`window`) and the mapping of every run's four wheels onto it, low-passed in space and
detrended (:class:`Mapper`)."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from shared.jit import kernel

from cloud.rail.filters import butter4_sos, sosfiltfilt_rows
from cloud.rail.records import RailRun

GRID_M = 0.1  # finest comparison grid spacing, m
EDGE_M = 1.5  # margin kept from the wheels' coverage (trial speeds move it), m


def window(runs: Sequence[RailRun], offsets: np.ndarray, window_m: tuple[float, float] | None,
           speed_slack: float) -> np.ndarray:
    """The common grid every wheel of every run covers at any speed within ``speed_slack`` (relative)."""
    lo = max(r.x0_m + offsets.max() for r in runs) + EDGE_M
    hi = min(r.x0_m + offsets.min() + r.speed_mps * (1 - speed_slack) * (len(r.channels) - 1) * r.dt
             for r in runs) - EDGE_M
    if window_m is not None:
        lo, hi = max(lo, window_m[0]), min(hi, window_m[1])
    if hi - lo < 20.0:
        raise ValueError(f"the runs share only [{lo:.1f}, {hi:.1f}] m of track: too short a window to calibrate")
    return np.arange(lo, hi, GRID_M)


class Mapper:
    """B: a run's AP (time) → its four wheels on the grid, low-passed there (no wavelengths shorter
    than ``min_wavelength_m``, zero phase) and a cubic removed from each (the unknown level and the
    integrators' slow drift of sensor noise).

    The low-pass is applied to the mapped AP, in space, not to the channels before the inverse: a
    filter commutes with the linear inverse only away from the record's start, where the channels'
    filter makes an edge error that the inverse's lightly damped body modes then carry for seconds
    (most of a window). That error depends on each run's mv, so it biases the masses — not a common
    scale but an over-dispersion (calibrated mv regressed on the truth has a slope above 1), by an
    amount that depends on the track near the record's start. On the grid the filter's edges are the
    same for every run and wheel, so the truth stays exact."""

    def __init__(self, grid: np.ndarray, min_wavelength_m: float | None = None):
        self.grid = grid
        X = np.stack([((grid - grid.mean()) / np.ptp(grid)) ** k for k in range(4)], axis=1)
        self.basis, _ = np.linalg.qr(X)
        wn = 2.0 * (grid[1] - grid[0]) / min_wavelength_m if min_wavelength_m else 1.0
        self.sos = butter4_sos(wn) if wn < 0.9 else None

    def lowpass(self, a: np.ndarray) -> np.ndarray:
        """``a`` (..., K) without wavelengths shorter than the mapper's (zero phase, along the grid)."""
        if self.sos is None:
            return a
        return sosfiltfilt_rows(self.sos, np.ascontiguousarray(a).reshape(-1, a.shape[-1])).reshape(a.shape)

    def detrend(self, a: np.ndarray) -> np.ndarray:
        """``a`` (..., K) less its least-squares cubic along the grid."""
        return a - (a @ self.basis) @ self.basis.T

    def map_runs(self, aps: np.ndarray, dts: np.ndarray, x0: np.ndarray, speeds: np.ndarray, lengths: np.ndarray,
                 offsets: np.ndarray) -> np.ndarray:
        """(R, T, N, 4) APs of R runs (the first ``lengths[r]`` samples at step ``dts[r]``, from
        ``x0[r]``), each mapped at each of its run's speeds ``speeds`` (R, S): (R, T, S, 4, K), by
        linear interpolation, each query clipped to its record (:func:`_map_kernel`)."""
        return self.finish(self.interpolate(aps, dts, x0, speeds, lengths, offsets))

    def interpolate(self, aps: np.ndarray, dts: np.ndarray, x0: np.ndarray, speeds: np.ndarray,
                    lengths: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """:meth:`map_runs` before its low-pass and detrend: the records read at the grid."""
        R, T, N, nw = aps.shape
        out = np.empty((R, T, speeds.shape[1], nw, len(self.grid)))
        _map_kernel(aps, np.asarray(dts, dtype=float), np.asarray(x0, dtype=float), np.asarray(speeds, dtype=float),
                    np.asarray(lengths, dtype=np.int64), np.asarray(offsets, dtype=float), self.grid, out)
        return out

    def finish(self, a: np.ndarray) -> np.ndarray:
        """The low-pass and detrend of :meth:`map_runs` on values read at the grid (both linear:
        the derivative of a mapped AP is the finished derivative of its reading)."""
        return self.detrend(self.lowpass(a))


@kernel
def _map_kernel(aps, dts, x0, speeds, lengths, offsets, grid, out):
    """out[r, t, s, i, k] = AP of run r, trial t, wheel i at chainage grid[k] at speed speeds[r, s]:
    linear interpolation between the bracketing samples, computed (the samples are uniform in time),
    not searched. What ``np.interp`` over the records laid end to end gave (to rounding; the end to
    end abscissae lost ~1e-11 to their offsets), without its (R, T, 4, N) abscissa array: a 50-run
    Jacobian mapping (and its detrend) 0.04 → 0.017 s. CE's evaluations share it."""
    R, T = aps.shape[0], aps.shape[1]
    for r in range(R):
        top = lengths[r] - 1
        for s in range(speeds.shape[1]):
            for i in range(aps.shape[3]):
                for k in range(grid.shape[0]):
                    u = (grid[k] - x0[r] - offsets[i]) / speeds[r, s] / dts[r]
                    u = min(max(u, 0.0), float(top))
                    j = min(int(u), top - 1)
                    f = u - j
                    for t in range(T):
                        a0 = aps[r, t, j, i]
                        out[r, t, s, i, k] = a0 + (aps[r, t, j + 1, i] - a0) * f
