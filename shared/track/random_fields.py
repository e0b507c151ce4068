"""Random fields along a track: support stiffness variation and the rail's vertical irregularity."""

from __future__ import annotations

import math

import numpy as np

#: German track spectrum, low-disturbance (vertical): S(Ω) = A·Ωc² / ((Ω² + Ωr²)(Ω² + Ωc²)),
#: one-sided in m²/(rad/m), Ω the angular wavenumber (rad/m). Widely used for ballasted track.
GERMAN_LOW = dict(A=4.032e-7, omega_c=0.8246, omega_r=0.0206)
GERMAN_HIGH = dict(A=10.80e-7, omega_c=0.8246, omega_r=0.0206)


def stiffness_factors(
    n: int, spacing_m: float, sd: float, correlation_m: float, rng: np.random.Generator
) -> np.ndarray:
    """Log-normal multipliers (mean 1) of a support stiffness at ``n`` sleepers ``spacing_m`` apart.

    The log factor is a stationary Gaussian process with exponential covariance
    sd²·exp(−|Δx|/correlation_m) (an Ornstein–Uhlenbeck process, sampled exactly in O(n) on the
    regular sleeper grid); ``sd`` is the standard deviation of the log factor (≈ relative sd).
    """
    if n < 1 or not (spacing_m > 0 and correlation_m > 0 and sd >= 0):
        raise ValueError("stiffness_factors: need n >= 1, spacing_m > 0, correlation_m > 0, sd >= 0")
    rho = math.exp(-spacing_m / correlation_m)
    eps = rng.standard_normal(n)
    g = np.empty(n)
    g[0] = eps[0]
    innovation = math.sqrt(1.0 - rho * rho)
    for k in range(1, n):
        g[k] = rho * g[k - 1] + innovation * eps[k]
    return np.exp(sd * g - 0.5 * sd * sd)


class RailIrregularity:
    """A vertical rail irregularity r(x) (m, up positive) as a sum of cosines with random phases.

    The German spectrum (``GERMAN_LOW`` by default) between wavelengths ``min_wavelength_m`` and
    ``max_wavelength_m``, ``n_waves`` log-spaced harmonics; ``scale`` multiplies the amplitude
    (0 gives a smooth rail).
    """

    def __init__(self, seed: int, min_wavelength_m: float = 1.0, max_wavelength_m: float = 80.0,
                 n_waves: int = 300, spectrum: dict | None = None, scale: float = 1.0):
        if not (0 < min_wavelength_m < max_wavelength_m) or n_waves < 1 or scale < 0:
            raise ValueError("RailIrregularity: need 0 < min_wavelength_m < max_wavelength_m, n_waves >= 1, scale >= 0")
        p = GERMAN_LOW if spectrum is None else spectrum
        rng = np.random.default_rng(seed)
        omega = np.geomspace(2 * np.pi / max_wavelength_m, 2 * np.pi / min_wavelength_m, n_waves)
        psd = p["A"] * p["omega_c"] ** 2 / ((omega**2 + p["omega_r"] ** 2) * (omega**2 + p["omega_c"] ** 2))
        self.omega = omega
        self.amplitude = scale * np.sqrt(2.0 * psd * np.gradient(omega))
        self.phase = rng.uniform(0.0, 2 * np.pi, n_waves)

    def elevation(self, x_m: np.ndarray) -> np.ndarray:
        x = np.asarray(x_m, dtype=float)
        return (self.amplitude * np.cos(self.omega * x[..., None] + self.phase)).sum(-1)

    def slope(self, x_m: np.ndarray) -> np.ndarray:
        x = np.asarray(x_m, dtype=float)
        return (-self.amplitude * self.omega * np.sin(self.omega * x[..., None] + self.phase)).sum(-1)
