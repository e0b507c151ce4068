"""Zero-phase low-pass filters of a rail run's records, compiled: scipy's ``sosfiltfilt`` arithmetic
on the closed-form sections of a fourth-order Butterworth filter, along columns (a run's channels) or
rows (APs mapped to chainage), and a run's channels low-passed at a wavelength."""

from __future__ import annotations

import math

import numpy as np

from shared.jit import kernel

from cloud.rail.records import RailRun

#: :func:`sosfiltfilt_rows` transposes this many rows at a time into a work array that stays in cache.
FILTER_BLOCK_ROWS = 32


def lowpass_channels(run: RailRun, min_wavelength_m: float = 2.0) -> np.ndarray:
    """The channels without wavelengths shorter than ``min_wavelength_m`` at the run's reported speed
    (zero phase). A linear filter commutes with the linear inverse only away from the record's start
    (:class:`cloud.rail.mapping.Mapper`): :func:`cloud.rail.calibration.calibrate_batch` uses this only
    against aliasing before decimating."""
    z = np.asarray(run.channels, dtype=float)
    nyq = 0.5 / run.dt
    fc = run.speed_mps / min_wavelength_m
    if fc < 0.9 * nyq:
        z = sosfiltfilt_columns(butter4_sos(fc / nyq), np.ascontiguousarray(z))
    return z


@kernel
def sosfiltfilt_columns(sos, x):
    """``scipy.signal.sosfiltfilt(sos, x, axis=0)`` with its defaults (odd extension of 3·(2·sections
    + 1) samples, each pass started in the steady state of its first sample), for sections without
    zero coefficients: the same arithmetic, to rounding. scipy's is mostly Python overhead, a
    noticeable share of a batch calibration, which calls it once per run and stage."""
    n, nch = x.shape
    edge = 3 * (2 * sos.shape[0] + 1)
    if n <= edge:
        raise ValueError("sosfiltfilt_columns: the record is shorter than the filter's padding")
    ext = np.empty((n + 2 * edge, nch))  # channels side by side: independent recursions interleave
    ext[edge:edge + n] = x
    _filtfilt_extended(sos, ext, edge)
    return ext[edge:edge + n].copy()


@kernel
def sosfiltfilt_rows(sos, x):
    """:func:`sosfiltfilt_columns` along the last axis of ``x`` (rows, n): the same numbers. The mapper
    filters ~200–300 mapped rows a call; a block of rows at a time is transposed into a work array
    that stays in cache (faster than numpy's transposes around :func:`sosfiltfilt_columns`)."""
    nch, n = x.shape
    edge = 3 * (2 * sos.shape[0] + 1)
    if n <= edge:
        raise ValueError("sosfiltfilt_rows: the record is shorter than the filter's padding")
    out = np.empty_like(x)
    for c0 in range(0, nch, FILTER_BLOCK_ROWS):
        c1 = min(nch, c0 + FILTER_BLOCK_ROWS)
        ext = np.empty((n + 2 * edge, c1 - c0))
        for ch in range(c0, c1):
            for k in range(n):
                ext[edge + k, ch - c0] = x[ch, k]
        _filtfilt_extended(sos, ext, edge)
        for ch in range(c0, c1):
            for k in range(n):
                out[ch, k] = ext[edge + k, ch - c0]
    return out


@kernel
def _filtfilt_extended(sos, ext, edge):
    """In place on ``ext`` (n + 2·edge, nch), the record in the middle rows: the odd extensions,
    then the forward and backward passes of every section (scipy's sosfiltfilt arithmetic)."""
    m, nch = ext.shape
    n = m - 2 * edge
    ns = sos.shape[0]
    # sosfilt_zi: each section's lfilter_zi (the 2x2 solve of its companion form), scaled by the
    # DC gain of the sections before it
    zi = np.empty((ns, 2))
    scale = 1.0
    for q in range(ns):
        b0, b1, b2, a1, a2 = sos[q, 0] / sos[q, 3], sos[q, 1] / sos[q, 3], sos[q, 2] / sos[q, 3], \
            sos[q, 4] / sos[q, 3], sos[q, 5] / sos[q, 3]
        r1, r2 = b1 - a1 * b0, b2 - a2 * b0
        # (I - A) zi = B with A = companion(a).T: [[1 + a1, -1], [a2, 1]]
        z0 = (r1 + r2) / (1.0 + a1 + a2)
        zi[q, 0] = scale * z0
        zi[q, 1] = scale * (r2 - a2 * z0)
        scale *= (b0 + b1 + b2) / (1.0 + a1 + a2)
    for k in range(edge):
        for ch in range(nch):
            ext[k, ch] = 2.0 * ext[edge, ch] - ext[2 * edge - k, ch]
            ext[n + edge + k, ch] = 2.0 * ext[n + edge - 1, ch] - ext[n + edge - 2 - k, ch]
    st0 = np.empty((ns, nch))
    st1 = np.empty((ns, nch))
    for direction in range(2):
        first = 0 if direction == 0 else m - 1
        for q in range(ns):
            for ch in range(nch):
                st0[q, ch] = zi[q, 0] * ext[first, ch]
                st1[q, ch] = zi[q, 1] * ext[first, ch]
        for kk in range(m):
            k = kk if direction == 0 else m - 1 - kk
            row = ext[k]
            # section by section over a whole row: the channels' recursions are independent, so
            # the inner loop vectorises (channel by channel through both sections it cannot)
            for q in range(ns):
                b0, b1, b2, a1, a2 = sos[q, 0], sos[q, 1], sos[q, 2], sos[q, 4], sos[q, 5]
                s0 = st0[q]
                s1 = st1[q]
                for ch in range(nch):
                    v = row[ch]
                    out = b0 * v + s0[ch]
                    s0[ch] = b1 * v - a1 * out + s1[ch]
                    s1[ch] = b2 * v - a2 * out
                    row[ch] = out


def butter4_sos(wn: float) -> np.ndarray:
    """``scipy.signal.butter(4, wn, output="sos")`` in closed form (same sections, same order, to
    ~1e-13 relative): the bilinear transform of the prewarped analog poles. scipy's design is slow
    for a batch calibration, which designs one per run and stage."""
    warped = 4.0 * math.tan(math.pi * wn / 2.0)  # scipy's prewarp at fs = 2
    pa = warped * np.exp(1j * np.pi * np.array([5.0, 7.0]) / 8.0)  # one pole of each conjugate pair
    pd = (4.0 + pa) / (4.0 - pa)
    gain = warped**4 / float(np.real(np.prod(4.0 - pa) * np.prod(4.0 - np.conj(pa))))
    sos = np.zeros((2, 6))
    for row, i in enumerate(np.argsort(np.abs(pd))):  # scipy's "nearest" pairing: nearest the unit circle last
        sos[row] = (1.0, 2.0, 1.0, 1.0, -2.0 * pd[i].real, abs(pd[i]) ** 2)
    sos[0, :3] *= gain
    return sos
