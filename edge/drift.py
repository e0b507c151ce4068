"""Drift control of the apparent profile: remove a long-wavelength local linear trend.

Twice-integrated sensor noise and the unknown initial velocity make the AP wander at long
wavelengths. A local linear regression with triangular weights over ±``half_width`` grid points
removes that wander (a constant offset and a linear drift exactly, at every point including the
ends of a pass) while leaving wavelengths much shorter than the half-width intact: the trend's
transfer is sinc²-like, 2 % at a wavelength of half_width/1.5.
"""

from __future__ import annotations

import numpy as np

from shared.jit import kernel


@kernel
def local_linear_trend(values, valid, half_width):
    """Trend of ``values`` (NaN-free where ``valid``) at every index, from valid points only."""
    n = values.size
    out = np.zeros(n)
    for i in range(n):
        lo = max(0, i - half_width)
        hi = min(n, i + half_width + 1)
        s0 = s1 = s2 = t0 = t1 = 0.0
        for j in range(lo, hi):
            if not valid[j]:
                continue
            d = float(j - i)
            w = 1.0 - abs(d) / (half_width + 1.0)
            s0 += w
            s1 += w * d
            s2 += w * d * d
            t0 += w * values[j]
            t1 += w * d * values[j]
        det = s0 * s2 - s1 * s1
        if s0 <= 0.0:
            out[i] = 0.0
        elif det <= 1e-12 * s0 * s0:
            out[i] = t0 / s0
        else:
            out[i] = (s2 * t0 - s1 * t1) / det  # intercept of the weighted line at d = 0
    return out


@kernel
def _lattice_trend(values, valid, half_width, step):
    n = values.size
    # The lattice samples the mean of the valid values over one step around each of its points, not
    # the single value there: sampled at every step (1 m), road roughness shorter than the step
    # would alias into the trend (0.02–0.04 mm on a class A road, the same for every pass whose
    # lattice falls alike); the step means leave the trend within ~1 µm of the full local fit.
    cs = np.zeros(n + 1)
    cn = np.zeros(n + 1)
    for i in range(n):
        cs[i + 1] = cs[i] + (values[i] if valid[i] else 0.0)
        cn[i + 1] = cn[i] + (1.0 if valid[i] else 0.0)
    half = step // 2
    m = (n - 1) // step + 1
    nodes = np.empty(m + 1, dtype=np.int64)
    for k in range(m):
        nodes[k] = k * step
    count = m
    if nodes[m - 1] != n - 1:
        nodes[m] = n - 1
        count = m + 1
    at = np.empty(count)
    for k in range(count):
        i = nodes[k]
        lo = max(0, i - half_width)
        hi = min(n - 1, i + half_width)
        s0 = s1 = s2 = t0 = t1 = 0.0
        j = ((lo + step - 1) // step) * step  # the lattice points j ≡ 0 (mod step) in the window
        while j <= hi:
            a = max(j - half, lo)
            b = min(j + step - half, hi + 1)
            c = cn[b] - cn[a]
            if c > 0:
                y = (cs[b] - cs[a]) / c
                d = float(j - i)
                w = (1.0 - abs(d) / (half_width + 1.0)) * (c / step)  # a part-valid step counts in part
                s0 += w
                s1 += w * d
                s2 += w * d * d
                t0 += w * y
                t1 += w * d * y
            j += step
        det = s0 * s2 - s1 * s1
        if s0 <= 0.0:
            at[k] = 0.0
        elif det <= 1e-12 * s0 * s0:
            at[k] = t0 / s0
        else:
            at[k] = (s2 * t0 - s1 * t1) / det
    out = np.empty(n)
    for k in range(count - 1):
        a, b = nodes[k], nodes[k + 1]
        for i in range(a, b + 1):
            f = (i - a) / (b - a)
            out[i] = (1.0 - f) * at[k] + f * at[k + 1]
    if count == 1:
        out[0] = at[0]
    return out


def drift_trend(values: np.ndarray, valid: np.ndarray, half_width: int, step: int | None = None) -> np.ndarray:
    """:func:`local_linear_trend` evaluated on a lattice of every ``step``-th point (from the means of
    the valid points over one step around the points of the same lattice) and interpolated linearly
    between: the trend varies over ~half_width, so a lattice of ~half_width/150 loses nothing that
    matters and costs ~step² less."""
    if step is None:
        step = max(1, half_width // 150)
    if step <= 1 or values.size <= 2 * step:
        return local_linear_trend(values, valid, half_width)
    return _lattice_trend(values, valid, half_width, step)
