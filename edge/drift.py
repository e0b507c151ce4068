"""Drift control of the apparent profile: remove a long-wavelength local linear trend.

Twice-integrated sensor noise and the unknown initial velocity make the AP wander at long
wavelengths. A local linear regression with triangular weights over ±``half_width`` grid points
removes that wander (a constant offset and a linear drift exactly, at every point including the
ends of a pass) while leaving wavelengths much shorter than the half-width intact: the trend's
transfer is sinc²-like, 2 % at a wavelength of half_width/1.5.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
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
