"""Road elevation on a chainage grid, ISO 8608 random profiles, the tyre filter (thesis §2.2.2)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from types import MappingProxyType

import numpy as np
from numpy.typing import ArrayLike

N0 = 0.1
"""ISO 8608 reference spatial frequency n0 (cycles/m)."""

WAVINESS = 2.0
"""ISO 8608 waviness exponent w of the displacement PSD."""

ISO8608_GD0: Mapping[str, float] = MappingProxyType(
    {"A": 16e-6, "B": 64e-6, "C": 256e-6, "D": 1024e-6, "E": 4096e-6}
)
"""Geometric-mean displacement PSD Gd(n0) per road class (m³/cycle, i.e. m²/(cycle/m))."""

TYRE_WINDOW_M = 0.24
"""Length of the moving-average tyre-contact filter of thesis §2.2.2 (m)."""

# Relative slack when checking that a query lies on the grid, so that x = end_m computed
# in a slightly different order of operations is not rejected for a rounding error.
_RANGE_RTOL = 1e-9


@dataclasses.dataclass(frozen=True, eq=False)
class RoadProfile:
    """Elevation on the regular chainage grid ``start_m + i * spacing_m``, ``i = 0 … N−1``.

    Parameters
    ----------
    start_m : float
        Chainage of the first sample (m).
    spacing_m : float
        Grid spacing (m), > 0.
    elevation_m : numpy.ndarray
        Elevations (m), 1-D with at least two finite values. Stored as a read-only float64 copy.

    Between samples the profile is the linear interpolant of the samples; :meth:`at` and
    :meth:`slope` evaluate exactly that function and its derivative.
    """

    start_m: float
    spacing_m: float
    elevation_m: np.ndarray

    def __post_init__(self) -> None:
        start = finite_float(self.start_m, "start_m")
        spacing = positive_float(self.spacing_m, "spacing_m")
        y = np.array(self.elevation_m, dtype=np.float64)
        if y.ndim != 1:
            raise ValueError(f"elevation_m must be 1-D, got shape {y.shape}")
        if y.size < 2:
            raise ValueError(f"elevation_m needs at least 2 points, got {y.size}")
        if not np.all(np.isfinite(y)):
            raise ValueError("elevation_m must be finite (found NaN or inf)")
        y.flags.writeable = False
        object.__setattr__(self, "start_m", start)
        object.__setattr__(self, "spacing_m", spacing)
        object.__setattr__(self, "elevation_m", y)

    @property
    def n_points(self) -> int:
        """Number of grid points."""
        return self.elevation_m.size

    @property
    def end_m(self) -> float:
        """Chainage of the last sample (m)."""
        return self.start_m + (self.n_points - 1) * self.spacing_m

    @property
    def chainage_m(self) -> np.ndarray:
        """Chainage of every sample (m), shape ``(n_points,)``."""
        return self.start_m + self.spacing_m * np.arange(self.n_points)

    def at(self, x: ArrayLike) -> np.ndarray:
        """Elevation (m) at chainage ``x`` (m) by linear interpolation; same shape as ``x``.

        Raises
        ------
        ValueError
            If any ``x`` lies outside ``[start_m, end_m]`` or is not finite.
        """
        s = self._local_coordinate(x)
        i = np.clip(np.floor(s).astype(np.intp), 0, self.n_points - 2)
        t = s - i
        y = self.elevation_m
        return (1.0 - t) * y[i] + t * y[i + 1]

    def slope(self, x: ArrayLike) -> np.ndarray:
        """Gradient dy/dx (m/m) of the linear interpolant at chainage ``x`` (m); shaped like ``x``.

        The interpolant is piecewise linear, so its slope is constant on each grid interval; at an
        interior grid point the slope of the interval to the right is returned (at ``end_m``, that
        of the last interval).

        Raises
        ------
        ValueError
            If any ``x`` lies outside ``[start_m, end_m]`` or is not finite.
        """
        s = self._local_coordinate(x)
        i = np.clip(np.floor(s).astype(np.intp), 0, self.n_points - 2)
        y = self.elevation_m
        return (y[i + 1] - y[i]) / self.spacing_m

    def resampled(self, spacing_m: float) -> RoadProfile:
        """The profile resampled to ``spacing_m`` (m) from the same start, by linear interpolation.

        The new grid stops at the last point not beyond ``end_m``. No anti-alias filtering is done:
        when coarsening, apply :func:`tyre_filter` (or another low-pass) first if that matters.
        """
        spacing = positive_float(spacing_m, "spacing_m")
        n = int(math.floor((self.end_m - self.start_m) / spacing * (1.0 + _RANGE_RTOL))) + 1
        if n < 2:
            raise ValueError(
                f"spacing_m={spacing} is longer than the profile ({self.end_m - self.start_m} m)"
            )
        x = np.minimum(self.start_m + spacing * np.arange(n), self.end_m)
        return RoadProfile(self.start_m, spacing, self.at(x))

    def _local_coordinate(self, x: ArrayLike) -> np.ndarray:
        """``(x − start_m) / spacing_m`` clipped onto the grid, after checking the range."""
        x = np.asarray(x, dtype=np.float64)
        slack = _RANGE_RTOL * max(self.spacing_m, abs(self.start_m), abs(self.end_m))
        inside = (x >= self.start_m - slack) & (x <= self.end_m + slack)
        if not np.all(inside):
            bad = x[~inside] if x.ndim else x
            raise ValueError(
                f"x must lie in [{self.start_m}, {self.end_m}] m (the profile's range); "
                f"got {np.ravel(bad)[0]}"
            )
        return np.clip((x - self.start_m) / self.spacing_m, 0.0, self.n_points - 1.0)


def iso8608_psd(n: ArrayLike, road_class: str) -> np.ndarray:
    """ISO 8608 displacement PSD ``Gd(n) = Gd(n0) · (n / n0)^(−w)`` with n0 = 0.1 cycles/m, w = 2.

    Parameters
    ----------
    n : array_like
        Spatial frequency (cycles/m), > 0.
    road_class : str
        ISO 8608 class ``"A"`` … ``"E"`` (case-insensitive); Gd(n0) is the geometric class mean.

    Returns
    -------
    numpy.ndarray
        One-sided PSD (m³/cycle, i.e. m² per cycle/m), same shape as ``n``.
    """
    gd0 = ISO8608_GD0[_road_class(road_class)]
    n = np.asarray(n, dtype=np.float64)
    if not np.all(np.isfinite(n) & (n > 0)):
        raise ValueError("n (spatial frequency, cycles/m) must be finite and > 0")
    return gd0 * (n / N0) ** (-WAVINESS)


def iso8608_profile(
    length_m: float,
    spacing_m: float = 0.01,
    road_class: str = "A",
    seed: int | np.random.SeedSequence | np.random.Generator = 0,
    n_min: float = 0.01,
    n_max: float | None = None,
) -> RoadProfile:
    """A random ISO 8608 road profile by spectral synthesis with random phases.

    The profile is ``y(x) = Σ_k A_k cos(2π n_k x + φ_k)`` with ``A_k = sqrt(2 Gd(n_k) Δn)``, the
    ``φ_k`` independent and uniform on [0, 2π), and ``n_k`` the harmonics ``k Δn`` with
    ``n_min ≤ n_k ≤ n_max`` (summed with one inverse real FFT). ``Δn`` is at most ``n_min`` and at
    most ``1 / length_m``: a record longer than the profile is synthesised when needed, so that the
    lowest requested wavenumber is present even in a short profile.

    Parameters
    ----------
    length_m : float
        Profile length (m), ≥ ``spacing_m``. The grid is ``0, spacing_m, …`` up to the last point
        not beyond ``length_m``.
    spacing_m : float
        Grid spacing (m), > 0.
    road_class : str
        ISO 8608 class ``"A"`` … ``"E"``.
    seed : int, SeedSequence or Generator
        Passed to :func:`numpy.random.default_rng`; equal seeds give identical profiles.
    n_min : float
        Lowest spatial frequency generated (cycles/m), > 0.
    n_max : float, optional
        Highest spatial frequency generated (cycles/m); defaults to the Nyquist frequency
        ``1 / (2 spacing_m)`` (the Nyquist harmonic itself is left out: its phase is lost).

    Returns
    -------
    RoadProfile
        Elevations (m) starting at chainage 0.
    """
    grid = harmonic_grid(length_m, spacing_m, n_min, n_max, road_class)
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0.0, 2.0 * np.pi, grid.amplitude.size)
    y = synthesise(grid, np.exp(1j * phase))
    return RoadProfile(0.0, grid.spacing_m, y)


def tyre_filter(profile: RoadProfile, window_m: float = TYRE_WINDOW_M) -> RoadProfile:
    """Centred moving average over ``window_m`` (m) for the tyre contact patch (thesis §2.2.2).

    The window spans ``k = round(window_m / spacing_m)`` grid intervals. For even ``k`` it is the
    trapezoid-rule mean over ``k + 1`` points (half weight at both ends), i.e. the exact mean of
    the linear interpolant over ``k · spacing_m``; for odd ``k`` it is the plain mean of ``k``
    points. Either way the filter has its first zero at wavelength ``k · spacing_m`` (0.24 m for
    the default window when the spacing divides it), and the result is on the same grid.

    At the ends the profile is extended point-symmetrically about its first and last samples
    (``y[−j] = 2 y[0] − y[j]``), so constants and straight lines are reproduced exactly right up to
    the ends; within half a window of an end the short-wavelength attenuation is weaker.

    Raises
    ------
    ValueError
        If the window is shorter than half a grid spacing, or longer than the profile.
    """
    y = tyre_average(profile.elevation_m, profile.spacing_m, window_m)
    return RoadProfile(profile.start_m, profile.spacing_m, y)


@dataclasses.dataclass(frozen=True)
class HarmonicGrid:
    """Where the spectral synthesis puts its harmonics, and with what amplitude."""

    n_points: int  # samples returned
    spacing_m: float
    n_fft: int  # length of the synthesised periodic record (samples)
    index: np.ndarray  # rfft bins carrying power
    wavenumber: np.ndarray  # their spatial frequencies (cycles/m)
    amplitude: np.ndarray  # |rfft coefficient| for each, so irfft gives A_k cos(...)


def harmonic_grid(
    length_m: float, spacing_m: float, n_min: float, n_max: float | None, road_class: str
) -> HarmonicGrid:
    """Validate the synthesis inputs and lay out the harmonics (amplitudes for ``road_class``)."""
    road_class = _road_class(road_class)
    length = positive_float(length_m, "length_m")
    spacing = positive_float(spacing_m, "spacing_m")
    if length < spacing:
        raise ValueError(f"length_m={length} must be at least spacing_m={spacing}")
    nyquist = 0.5 / spacing
    lo = positive_float(n_min, "n_min")
    hi = nyquist if n_max is None else positive_float(n_max, "n_max")
    if hi > nyquist * (1.0 + _RANGE_RTOL):
        raise ValueError(f"n_max={hi} cycles/m exceeds the Nyquist frequency {nyquist} of the grid")
    if lo >= hi:
        raise ValueError(f"n_min={lo} must be below n_max={hi} cycles/m")
    n_points = int(math.floor(length / spacing * (1.0 + _RANGE_RTOL))) + 1
    n_fft = max(n_points, math.ceil(1.0 / (lo * spacing) - _RANGE_RTOL))
    n_fft += n_fft % 2
    dn = 1.0 / (n_fft * spacing)
    k = np.arange(1, n_fft // 2)  # DC and Nyquist bins excluded
    n = k * dn
    keep = (n >= lo * (1.0 - _RANGE_RTOL)) & (n <= hi * (1.0 + _RANGE_RTOL))
    index, n = k[keep], n[keep]
    # irfft(c)[j] = (2/N) |c_k| cos(2π k j / N + arg c_k) for 0 < k < N/2, and A_k² = 2 Gd Δn.
    amplitude = n_fft * np.sqrt(0.5 * iso8608_psd(n, road_class) * dn)
    return HarmonicGrid(n_points, spacing, n_fft, index, n, amplitude)


def synthesise(grid: HarmonicGrid, phasor: np.ndarray) -> np.ndarray:
    """Sum the harmonics with unit ``phasor`` (…, n_harmonics); returns (…, n_points) elevations."""
    coeffs = np.zeros(phasor.shape[:-1] + (grid.n_fft // 2 + 1,), dtype=np.complex128)
    coeffs[..., grid.index] = grid.amplitude * phasor
    return np.fft.irfft(coeffs, n=grid.n_fft, axis=-1)[..., : grid.n_points]


def tyre_average(y: np.ndarray, spacing_m: float, window_m: float) -> np.ndarray:
    """Tyre filter of :func:`tyre_filter` along the last axis of ``y`` (samples every ``spacing_m``)."""
    window = positive_float(window_m, "window_m")
    k = int(round(window / spacing_m))
    if k < 1:
        raise ValueError(f"window_m={window} is shorter than the grid spacing {spacing_m} m")
    if k % 2 == 0:
        half = k // 2
        weights = np.ones(k + 1)
        weights[[0, -1]] = 0.5
    else:
        half = (k - 1) // 2
        weights = np.ones(k)
    weights /= k
    n = y.shape[-1]
    if half >= n:
        raise ValueError(f"window_m={window} is longer than the profile ({(n - 1) * spacing_m} m)")
    if half == 0:
        return y.copy()
    first, last = y[..., :1], y[..., -1:]
    left = 2.0 * first - y[..., half:0:-1]
    right = 2.0 * last - y[..., -2 : -half - 2 : -1]
    padded = np.concatenate([left, y, right], axis=-1)
    return np.lib.stride_tricks.sliding_window_view(padded, weights.size, axis=-1) @ weights


def _road_class(road_class: str) -> str:
    """The canonical (upper-case) ISO 8608 class letter, or ValueError."""
    key = road_class.upper() if isinstance(road_class, str) else None
    if key not in ISO8608_GD0:
        raise ValueError(f"road_class must be one of {', '.join(ISO8608_GD0)}; got {road_class!r}")
    return key


def finite_float(value: float, name: str) -> float:
    """``value`` as a finite float, or ValueError naming the argument ``name``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    return v


def positive_float(value: float, name: str) -> float:
    """``value`` as a finite float > 0, or ValueError naming the argument ``name``."""
    v = finite_float(value, name)
    if v <= 0.0:
        raise ValueError(f"{name} must be > 0, got {v}")
    return v
