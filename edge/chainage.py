"""Time → chainage on the vehicle: dead reckoning on speed, pulled gently towards GNSS."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _fuse(gnss, speed, dt, gain, x0):
    out = np.empty(gnss.size)
    x = x0
    for k in range(gnss.size):
        x += speed[k] * dt
        x += gain * (gnss[k] - x)
        out[k] = x
    return out


class ChainageTracker:
    """Complementary filter: chainage advances with speed and relaxes to GNSS with time constant
    ``tau_s``, so GNSS jitter cannot make chainage run backwards while a constant GNSS bias is kept
    (the cloud aligns passes against the consensus to remove it).
    """

    def __init__(self, dt: float, tau_s: float = 2.0):
        self.dt = dt
        self.gain = min(dt / tau_s, 1.0)
        self._x: float | None = None

    def update(self, gnss_m: np.ndarray, speed_mps: np.ndarray) -> np.ndarray:
        gnss_m = np.asarray(gnss_m, float)
        speed = np.asarray(speed_mps, float)
        if gnss_m.size == 0:
            return gnss_m.copy()
        if self._x is None:
            self._x = float(gnss_m[0] - speed[0] * self.dt)  # so the first sample lands on GNSS
        out = _fuse(gnss_m, speed, self.dt, self.gain, self._x)
        self._x = float(out[-1])
        return out
