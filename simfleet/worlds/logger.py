"""A data logger's sensor chain: anti-alias FIR at the simulation rate, decimation to the logged rate, noise.

The logger samples the continuous response on its own clock (a phase the simulation does not
choose to suit the road), low-passes it with a linear-phase Kaiser FIR whose group delay it
compensates in the time stamps (as loggers that align channels do), keeps every ``R``-th sample,
and adds white sensor noise (:func:`shared.sensors.add_noise`, the project's noise contract).
Speed comes from an odometer with a per-run scale error, and chainage is integrated from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import firwin, kaiserord, oaconvolve

#: The FIR's cut-off and transition width as fractions of the logged rate: −6 dB at 0.4 fs, the
#: stop band starting at the logged Nyquist frequency (0.5 fs), flat to 0.3 fs.
CUTOFF_OF_FS = 0.4
WIDTH_OF_FS = 0.2
#: Stop-band attenuation and pass-band ripple of the Kaiser design, dB (ripple 10^(−60/20) = 1e-3).
ATTENUATION_DB = 60.0


@dataclass(frozen=True)
class AntiAlias:
    """The anti-alias filter of a logger sampling at ``fs_hz`` behind a simulation ``oversample`` × faster."""

    fs_hz: float
    oversample: int

    def __post_init__(self) -> None:
        if not (self.fs_hz > 0 and isinstance(self.oversample, int) and self.oversample >= 2):
            raise ValueError(f"AntiAlias: fs_hz > 0 and an integer oversample >= 2 required, got "
                             f"{self.fs_hz!r}, {self.oversample!r}")

    @property
    def taps(self) -> np.ndarray:
        fs_sim = self.fs_hz * self.oversample
        n, beta = kaiserord(ATTENUATION_DB, WIDTH_OF_FS * self.fs_hz / (0.5 * fs_sim))
        n += 1 - n % 2  # odd length: an integer group delay, compensated exactly
        return firwin(n, CUTOFF_OF_FS * self.fs_hz, window=("kaiser", beta), fs=fs_sim)

    def sample(self, signal: np.ndarray, first: int) -> np.ndarray:
        """Filter ``signal`` (simulation rate, (n,) or (n, channels)) and keep samples ``first``,
        ``first + oversample``, …; the filter is centred on each kept sample (delay compensated)."""
        h = self.taps
        x = np.asarray(signal, dtype=float)
        h2 = h if x.ndim == 1 else h[:, None]
        y = oaconvolve(x, h2, mode="same", axes=0)
        return y[first::self.oversample]


def odometer(true_speed: np.ndarray, scale_error: float) -> np.ndarray:
    """Reported speed: the true speed stretched by the run's odometer scale error."""
    return np.asarray(true_speed, float) * (1.0 + scale_error)


def integrated_chainage(start_m: float, speed_mps: np.ndarray, dt_s: float) -> np.ndarray:
    """Chainage by trapezoidal integration of the reported speed from ``start_m`` at the first sample."""
    v = np.asarray(speed_mps, float)
    steps = 0.5 * (v[1:] + v[:-1]) * dt_s
    return start_m + np.concatenate([[0.0], np.cumsum(steps)])
