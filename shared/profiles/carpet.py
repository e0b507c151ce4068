"""The 3-D 'carpet': correlated ISO 8608 lanes and the wander lane draw (thesis §4.2, §4.3.5).

Model
-----
The thesis builds the carpet from eleven alternative 2-D profiles giving "a varied but correlated
excitation", one of which each vehicle follows, chosen from a truncated Normal distribution of
lateral position (Blab and Litzka, 1995). It gives no cross-lane statistics, so the carpet is
modelled here as the road surface seen by eleven parallel tracks of an *isotropic* rough surface:

* Each lane is an ISO 8608 random-phase profile with exactly the amplitudes of
  :func:`~shared.profiles.iso8608.iso8608_profile`, so every lane on its own is a valid class
  profile.
* At each harmonic ``n`` the lanes' phases are the arguments of a complex Gaussian vector whose
  lateral correlation is that of an isotropic surface whose tracks have the ISO PSD ∝ n^−2: its 2-D
  spectrum ∝ |κ|^−3, and the cross-spectrum of two tracks ``Δy`` apart is
  ``Gd(n) · x K₁(x)``, ``x = 2π n |Δy|`` (a Matérn-1 correlation across the road with length
  ``1 / (2π n)``). The lane-to-lane coherence is a monotone function of, and close to, ``x K₁(x)``.

So long waves are shared by all lanes, while waves shorter than about five times the lateral
separation (``x K₁(x) = ½`` at ``n Δy ≈ 0.2``) differ between lanes, and correlation falls with
lateral separation. Unlike "shared component + independent lane noise", this needs no extra
parameter: the lateral scale follows from the ISO spectrum and the lane spacing alone. The defaults
put the lanes 0.1 m apart (a 1 m band across the wheel path) and give the lateral wander a standard
deviation of 3 lanes (0.3 m). The thesis states neither value; both are assumptions to revisit.
"""

from __future__ import annotations

import dataclasses
import math
import operator

import numpy as np
from numpy.typing import ArrayLike

from .iso8608 import (
    TYRE_WINDOW_M,
    RoadProfile,
    finite_float,
    harmonic_grid,
    positive_float,
    synthesise,
    tyre_average,
)

N_LANES = 11
"""Number of lanes in the thesis carpet."""

LANE_SPACING_M = 0.1
"""Default lateral distance between adjacent lanes (m)."""

SD_LANES = 3.0
"""Default standard deviation of the lateral wander, in lanes (0.3 m at the default spacing)."""

# Added to the diagonal of the lateral correlation before factorising: at the lowest wavenumbers
# the lanes are coherent to ~1e-5, and the nugget keeps the Cholesky factor well defined.
_NUGGET = 1e-9

# Harmonics handled per batch of lateral factorisations (bounds memory to a few MB).
_BATCH = 2048


@dataclasses.dataclass(frozen=True, eq=False)
class Carpet:
    """Elevations of parallel lanes on one chainage grid ``start_m + i * spacing_m``.

    Parameters
    ----------
    start_m : float
        Chainage of the first sample (m).
    spacing_m : float
        Grid spacing (m), > 0.
    offsets_m : numpy.ndarray
        Lateral offset of each lane (m), strictly increasing, shape ``(n_lanes,)``.
    elevation_m : numpy.ndarray
        Elevations (m), shape ``(n_lanes, n_points)``, finite, ``n_points ≥ 2``.

    Arrays are stored as read-only float64 copies. Lane ``i`` is ``elevation_m[i]``.
    """

    start_m: float
    spacing_m: float
    offsets_m: np.ndarray
    elevation_m: np.ndarray

    def __post_init__(self) -> None:
        start = finite_float(self.start_m, "start_m")
        spacing = positive_float(self.spacing_m, "spacing_m")
        offsets = np.array(self.offsets_m, dtype=np.float64)
        y = np.array(self.elevation_m, dtype=np.float64)
        if offsets.ndim != 1 or offsets.size < 1:
            raise ValueError(f"offsets_m must be 1-D and non-empty, got shape {offsets.shape}")
        if not np.all(np.isfinite(offsets)) or np.any(np.diff(offsets) <= 0):
            raise ValueError("offsets_m must be finite and strictly increasing")
        if y.ndim != 2 or y.shape[0] != offsets.size:
            raise ValueError(
                f"elevation_m must have shape (n_lanes={offsets.size}, n_points), got {y.shape}"
            )
        if y.shape[1] < 2:
            raise ValueError(f"elevation_m needs at least 2 points per lane, got {y.shape[1]}")
        if not np.all(np.isfinite(y)):
            raise ValueError("elevation_m must be finite (found NaN or inf)")
        offsets.flags.writeable = False
        y.flags.writeable = False
        object.__setattr__(self, "start_m", start)
        object.__setattr__(self, "spacing_m", spacing)
        object.__setattr__(self, "offsets_m", offsets)
        object.__setattr__(self, "elevation_m", y)

    @property
    def n_lanes(self) -> int:
        """Number of lanes."""
        return self.offsets_m.size

    @property
    def end_m(self) -> float:
        """Chainage of the last sample (m)."""
        return self.start_m + (self.elevation_m.shape[1] - 1) * self.spacing_m

    @property
    def lanes(self) -> tuple[RoadProfile, ...]:
        """Every lane as a :class:`RoadProfile`, in order of offset."""
        return tuple(self.lane(i) for i in range(self.n_lanes))

    def lane(self, index: int) -> RoadProfile:
        """Lane ``index`` (0 … n_lanes − 1) as a :class:`RoadProfile`."""
        i = operator.index(index)
        if not 0 <= i < self.n_lanes:
            raise ValueError(f"lane index must be in 0..{self.n_lanes - 1}, got {i}")
        return RoadProfile(self.start_m, self.spacing_m, self.elevation_m[i])

    def mean_profile(self, weights: ArrayLike) -> RoadProfile:
        """Weighted mean over lanes; the fleet-mean profile for ``weights = lane_probabilities()``.

        Parameters
        ----------
        weights : array_like
            Non-negative weight per lane, shape ``(n_lanes,)``, not all zero; normalised here.
        """
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (self.n_lanes,):
            raise ValueError(f"weights must have shape ({self.n_lanes},), got {w.shape}")
        if not np.all(np.isfinite(w) & (w >= 0)) or w.sum() <= 0:
            raise ValueError("weights must be finite, non-negative and not all zero")
        return RoadProfile(self.start_m, self.spacing_m, (w / w.sum()) @ self.elevation_m)

    def tyre_filtered(self, window_m: float = TYRE_WINDOW_M) -> Carpet:
        """Every lane put through :func:`~shared.profiles.iso8608.tyre_filter` (same grid)."""
        y = tyre_average(self.elevation_m, self.spacing_m, window_m)
        return Carpet(self.start_m, self.spacing_m, self.offsets_m, y)


def carpet_profile(
    length_m: float,
    spacing_m: float = 0.01,
    road_class: str = "A",
    seed: int | np.random.SeedSequence | np.random.Generator = 0,
    n_lanes: int = N_LANES,
    lane_spacing_m: float = LANE_SPACING_M,
    n_min: float = 0.01,
    n_max: float | None = None,
) -> Carpet:
    """A random carpet of ``n_lanes`` laterally correlated ISO 8608 lanes (model: module doc).

    Parameters
    ----------
    length_m, spacing_m, road_class, n_min, n_max
        As for :func:`~shared.profiles.iso8608.iso8608_profile` (m, m, class letter, cycles/m,
        cycles/m); every lane has the same harmonic amplitudes as that 2-D profile.
    seed : int, SeedSequence or Generator
        Passed to :func:`numpy.random.default_rng`; equal seeds give identical carpets.
    n_lanes : int
        Number of lanes, ≥ 1.
    lane_spacing_m : float
        Lateral distance between adjacent lanes (m), > 0. Lanes are centred on offset 0.

    Returns
    -------
    Carpet
        Starting at chainage 0, offsets ``(i − (n_lanes − 1) / 2) · lane_spacing_m``.
    """
    grid = harmonic_grid(length_m, spacing_m, n_min, n_max, road_class)
    n_lanes = _lane_count(n_lanes)
    offsets = (np.arange(n_lanes) - 0.5 * (n_lanes - 1)) * positive_float(
        lane_spacing_m, "lane_spacing_m"
    )
    rng = np.random.default_rng(seed)
    xi = rng.standard_normal((grid.wavenumber.size, n_lanes, 2)) @ np.array([1.0, 1j])
    z = np.empty_like(xi)
    separation = np.abs(offsets[:, None] - offsets[None, :])
    for lo in range(0, grid.wavenumber.size, _BATCH):
        batch = slice(lo, lo + _BATCH)
        chol = np.linalg.cholesky(lateral_correlation(grid.wavenumber[batch], separation))
        z[batch] = (chol @ xi[batch, :, None])[..., 0]
    magnitude = np.abs(z)
    phasor = np.where(magnitude > 0, z / np.where(magnitude > 0, magnitude, 1.0), 1.0)
    y = synthesise(grid, phasor.T)
    return Carpet(0.0, grid.spacing_m, offsets, y)


def lane_probabilities(n_lanes: int = N_LANES, sd_lanes: float = SD_LANES) -> np.ndarray:
    """Probability of each lane under lateral wander, shape ``(n_lanes,)``, summing to 1.

    The lateral position ``u`` (in lanes) is Normal with mean at the middle lane ``(n_lanes − 1)/2``
    and standard deviation ``sd_lanes``, truncated to ``[−0.5, n_lanes − 0.5]``; the lane is the
    nearest one to ``u``. Hence ``P(i) ∝ Φ((i + ½ − c)/sd) − Φ((i − ½ − c)/sd)``.
    """
    n = _lane_count(n_lanes)
    sd = positive_float(sd_lanes, "sd_lanes")
    centre = 0.5 * (n - 1)
    edges = (np.arange(n + 1) - 0.5 - centre) / (sd * math.sqrt(2.0))
    cdf = 0.5 * np.array([math.erf(e) for e in edges])
    p = np.diff(cdf)
    return p / p.sum()


def draw_lane(
    rng: np.random.Generator,
    n_lanes: int = N_LANES,
    sd_lanes: float = SD_LANES,
    size: int | tuple[int, ...] | None = None,
) -> int | np.ndarray:
    """Draw lane indices (0 … n_lanes − 1) from the truncated Normal of :func:`lane_probabilities`.

    Returns an ``int`` when ``size`` is None, else an integer array of shape ``size``.
    """
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    p = lane_probabilities(n_lanes, sd_lanes)
    lane = rng.choice(p.size, size=size, p=p)
    return int(lane) if size is None else lane


def lateral_correlation(wavenumber: np.ndarray, separation: np.ndarray) -> np.ndarray:
    """Matérn-1 lateral correlation ``x K₁(x)``, ``x = 2π n Δy``: (harmonics, lanes, lanes)."""
    from scipy.special import k1  # lazy: keeps scipy out of the import of the package

    x = 2.0 * np.pi * wavenumber[:, None, None] * separation[None]
    positive = x > 0
    safe = np.where(positive, x, 1.0)
    r = np.where(positive, safe * k1(safe), 1.0)
    return r + _NUGGET * np.eye(separation.shape[0])


def _lane_count(n_lanes: int) -> int:
    if isinstance(n_lanes, bool) or not isinstance(n_lanes, (int, np.integer)) or n_lanes < 1:
        raise ValueError(f"n_lanes must be an integer ≥ 1, got {n_lanes!r}")
    return int(n_lanes)
