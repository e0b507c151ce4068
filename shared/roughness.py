"""International Roughness Index (ASTM E1926, Sayers 1995): the Golden Car at 80 km/h over a profile.

The quarter-car is driven, as in the standard's reference program, by the slope of the profile
after a 250 mm moving average, with the input held constant over each grid step. Its exact
discrete-time recursion ``z ← ST z + PR · slope`` uses ``ST = expm(A Δt)`` and
``PR = A⁻¹ (ST − I) B`` with ``Δt = Δx / V``. In this slope form the states are the distance
derivatives of ``(z_s, ż_s, z_u, ż_u)``, so ``z[0] − z[2] = (ż_s − ż_u) / V`` is the suspension
rate divided by the speed, and the IRI is its average absolute value (m/m, reported in m/km).

Initialisation follows the standard: both masses start moving along the profile's average slope
over its first 11 m (``z = (s, 0, s, 0)``, the steady state on a ramp), which is also why a
linear profile has an IRI of exactly zero.

Segments (:func:`iri_segments`) are taken from one continuous run of the quarter-car over the
whole finite stretch, so every segment but the first has the *preceding profile as its run-up*;
only the first segment of a stretch (and the first after a gap of NaNs) starts from the 11 m
initialisation. Each grid step is credited to the segment containing the midpoint of the car's
travel during that step (the centre of the 250 mm averaging base).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

from .jit import kernel


class GoldenCar(NamedTuple):
    """Quarter-car parameters per unit sprung mass (ASTM E1926).

    k1 = kt/ms (1/s²), k2 = ks/ms (1/s²), c = cs/ms (1/s), mu = mu/ms (–).
    """

    k1: float = 653.0
    k2: float = 63.3
    c: float = 6.0
    mu: float = 0.15


GOLDEN_CAR = GoldenCar()
IRI_SPEED_MPS = 80.0 / 3.6
"""Simulation speed of the IRI (m/s)."""
SMOOTHING_BASE_M = 0.25
"""Base length of the moving average applied to the profile (m)."""
INIT_LENGTH_M = 11.0
"""Length over which the initial slope is taken (m)."""

def golden_car_matrices(car: GoldenCar = GOLDEN_CAR) -> tuple[np.ndarray, np.ndarray]:
    """Continuous-time ``(A, B)`` of the quarter-car, state ``(z_s, ż_s, z_u, ż_u)``, input road height.

    Returns
    -------
    A : numpy.ndarray (4, 4)
        System matrix (1/s, 1/s²).
    B : numpy.ndarray (4,)
        Input vector (1/s²).
    """
    k1, k2, c, mu = car
    A = np.array([
        [0.0, 1.0, 0.0, 0.0],
        [-k2, -c, k2, c],
        [0.0, 0.0, 0.0, 1.0],
        [k2 / mu, c / mu, -(k1 + k2) / mu, -c / mu],
    ])
    B = np.array([0.0, 0.0, 0.0, k1 / mu])
    return A, B


@functools.lru_cache(maxsize=32)
def transition(spacing_m: float, speed_mps: float = IRI_SPEED_MPS,
               car: GoldenCar = GOLDEN_CAR) -> tuple[np.ndarray, np.ndarray]:
    """The standard's exact state transition over one grid step: ``(ST (4, 4), PR (4,))``."""
    from scipy.linalg import expm  # only here: keeps import of the module light

    A, B = golden_car_matrices(car)
    ST = expm(A * (spacing_m / speed_mps))
    PR = np.linalg.solve(A, (ST - np.eye(4)) @ B)
    ST.flags.writeable = False
    PR.flags.writeable = False
    return ST, PR


@kernel
def _iri_kernel(y, base, i11, dx, ST, PR, seg_of_step, sums, counts):
    """Accumulate ``|z0 − z2|`` per segment for every row of ``y`` (rows × points).

    Runs of finite values are simulated independently, each initialised from its first 11 m
    slope; step ``i`` takes the slope ``(y[i + base] − y[i]) / (base dx)`` and is credited to
    segment ``seg_of_step[i]`` (skipped when negative). ``sums`` and ``counts`` are (rows, n_seg).
    """
    n_rows, n = y.shape
    inv_base = 1.0 / (base * dx)
    for r in range(n_rows):
        j = 0
        while j < n:
            if not math.isfinite(y[r, j]):
                j += 1
                continue
            e = j
            while e < n and math.isfinite(y[r, e]):
                e += 1
            m = e - j
            if m > base:
                i1 = min(i11, m - 1)
                s0 = (y[r, j + i1] - y[r, j]) / (i1 * dx)
                z0 = s0
                z1 = 0.0
                z2 = s0
                z3 = 0.0
                for i in range(j, e - base):
                    u = (y[r, i + base] - y[r, i]) * inv_base
                    n0 = ST[0, 0] * z0 + ST[0, 1] * z1 + ST[0, 2] * z2 + ST[0, 3] * z3 + PR[0] * u
                    n1 = ST[1, 0] * z0 + ST[1, 1] * z1 + ST[1, 2] * z2 + ST[1, 3] * z3 + PR[1] * u
                    n2 = ST[2, 0] * z0 + ST[2, 1] * z1 + ST[2, 2] * z2 + ST[2, 3] * z3 + PR[2] * u
                    n3 = ST[3, 0] * z0 + ST[3, 1] * z1 + ST[3, 2] * z2 + ST[3, 3] * z3 + PR[3] * u
                    z0, z1, z2, z3 = n0, n1, n2, n3
                    k = seg_of_step[i]
                    if k >= 0:
                        sums[r, k] += abs(z0 - z2)
                        counts[r, k] += 1
            j = e


def _smoothing_base(spacing_m: float) -> int:
    return max(1, int(round(SMOOTHING_BASE_M / spacing_m)))


def _check_spacing(spacing_m: float) -> float:
    spacing_m = float(spacing_m)
    if not (math.isfinite(spacing_m) and spacing_m > 0.0):
        raise ValueError(f"spacing_m must be finite and > 0, got {spacing_m}")
    return spacing_m


def iri(profile_m: np.ndarray, spacing_m: float, *, speed_mps: float = IRI_SPEED_MPS,
        car: GoldenCar = GOLDEN_CAR) -> float:
    """IRI of a whole stretch (m/km).

    Parameters
    ----------
    profile_m : array (n,)
        Profile elevations (m) on a regular grid, finite, covering more than the 250 mm base.
    spacing_m : float
        Grid spacing (m).

    Returns
    -------
    float
        Average absolute suspension rate / speed over all steps, in m/km.
    """
    spacing_m = _check_spacing(spacing_m)
    y = np.ascontiguousarray(profile_m, dtype=np.float64)
    if y.ndim != 1:
        raise ValueError(f"profile_m must be 1-D, got shape {y.shape}")
    if not np.all(np.isfinite(y)):
        raise ValueError("profile_m must be finite (use iri_segments for stretches with gaps)")
    base = _smoothing_base(spacing_m)
    if y.size <= base:
        raise ValueError(f"profile needs more than {base} points for a {SMOOTHING_BASE_M} m base")
    ST, PR = transition(spacing_m, float(speed_mps), car)
    sums = np.zeros((1, 1))
    counts = np.zeros((1, 1), dtype=np.int64)
    i11 = max(1, int(round(INIT_LENGTH_M / spacing_m)))
    _iri_kernel(y[None, :], base, i11, spacing_m, ST, PR, np.zeros(y.size, dtype=np.int64), sums, counts)
    return 1000.0 * float(sums[0, 0]) / int(counts[0, 0])


def iri_segments(chainage_m: np.ndarray, profile_m: np.ndarray, length_m: float, *,
                 min_coverage: float = 0.5, speed_mps: float = IRI_SPEED_MPS,
                 car: GoldenCar = GOLDEN_CAR) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IRI of consecutive segments ``[k L, (k + 1) L)`` of chainage, clipped to the profile's extent.

    Parameters
    ----------
    chainage_m : array (n,)
        Regular, increasing chainage grid (m).
    profile_m : array (n,) or (n_profiles, n)
        Elevations (m); NaN marks points without a profile. Several rows (e.g. posterior draws)
        are processed independently in one call.
    length_m : float
        Nominal segment length (m), e.g. 10 or 100.
    min_coverage : float
        A segment's IRI is NaN unless the quarter-car's steps cover at least this fraction of it.

    Returns
    -------
    start_m, end_m : numpy.ndarray (n_seg,)
        Segment bounds (m); consecutive segments share their bounds and together span
        ``[chainage_m[0], chainage_m[-1]]``.
    iri : numpy.ndarray (n_seg,) or (n_profiles, n_seg)
        IRI (m/km) per segment (and per profile).

    Notes
    -----
    The car runs continuously over each finite stretch, so a segment's run-up is the profile
    before it; the first segment of a stretch starts from the standard's 11 m initialisation.
    """
    x = np.asarray(chainage_m, dtype=np.float64)
    y = np.asarray(profile_m, dtype=np.float64)
    single = y.ndim == 1
    y2 = np.ascontiguousarray(y[None, :] if single else y)
    if x.ndim != 1 or y2.ndim != 2 or y2.shape[1] != x.size:
        raise ValueError(f"chainage_m (n,) and profile_m (n,) or (rows, n) must agree, got {x.shape}, {y.shape}")
    if x.size < 2:
        raise ValueError("need at least two points")
    dx = _check_spacing((x[-1] - x[0]) / (x.size - 1))
    if not np.allclose(np.diff(x), dx, rtol=1e-6, atol=1e-9):
        raise ValueError("chainage_m must be a regular grid")
    length_m = float(length_m)
    if not (math.isfinite(length_m) and length_m > 0):
        raise ValueError(f"length_m must be finite and > 0, got {length_m}")
    base = _smoothing_base(dx)
    first = math.floor(x[0] / length_m + 1e-9)
    last = max(first, math.ceil(x[-1] / length_m - 1e-9) - 1)
    edges = np.arange(first, last + 2) * length_m
    edges[0], edges[-1] = x[0], x[-1]
    start, end = edges[:-1].copy(), edges[1:].copy()
    # Step i moves the car across the centre of the base [x_i, x_i + base dx]; credit it there.
    mid = x + 0.5 * base * dx
    seg = np.floor(mid / length_m + 1e-12).astype(np.int64) - first
    seg[(seg < 0) | (seg >= start.size) | (mid > x[-1])] = -1
    ST, PR = transition(dx, float(speed_mps), car)
    sums = np.zeros((y2.shape[0], start.size))
    counts = np.zeros((y2.shape[0], start.size), dtype=np.int64)
    i11 = max(1, int(round(INIT_LENGTH_M / dx)))
    _iri_kernel(y2, base, i11, dx, ST, PR, seg, sums, counts)
    enough = counts * dx >= min_coverage * (end - start)[None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(enough & (counts > 0), 1000.0 * sums / np.maximum(counts, 1), np.nan)
    return start, end, out[0] if single else out
