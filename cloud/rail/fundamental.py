"""J⁰, the span's fundamental influence line, from a bogie's two wheels by the matrix method (thesis
§3.5.2, eq. 3.16–3.23, for the bogie half-car of App. A.3): the batch's time-synchronous AP
difference of the leading bogie's two wheels, g_k = J⁰_k − J⁰_(k−c) per unit wheel load (c = the
wheelbase in grid steps),
inverted with J⁰ = 0 off the span. What :mod:`cloud.rail.bridge` reads the bogie half-car's D1/D2 from.

Why J⁰ in a smooth basis (:func:`smooth_operator`), not grid point by grid point. With J⁰ free at
every grid point (the thesis's least squares, :func:`difference_pinv`) the equations split into c
independent chains, one per residue class mod c (J⁰_r, J⁰_(r+c), …: ~4 unknowns on a 10 m span with
a 2.5 m wheelbase), and J⁰ along each is a running sum of g, so each chain carries its own random walk
of g's noise. The low-pass afterwards smooths J⁰ across the chains but keeps its mean, so D2 (the area,
a sum of those sums) collects every chain's walk in full, so the area's sd is about twice the
mid-span ordinate's. A static deflection line under
a unit load is smooth (a 10 m span's has nothing below ~5 m even with the 5 % per-element E·I scatter),
so J⁰ is taken as its first :data:`FUNDAMENTAL_MODES` sine modes on the span (both support conditions
built in) and fitted to g by least squares: the chains must agree, and g's noise averages across them.
On the blind test this halves or better the sd of the half-car's D1 and D2 without moving their mean;
what is left of the errors is a common scale per profile (errors ∝ D), not this estimator's noise
(docs/results.md).

Pure functions on arrays.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy.signal import butter, sosfiltfilt

from cloud.bridge.mril import MrIl

#: The wheels' difference is taken relative to the line through its means over this much track
#: beyond each end (both wheels off the span), m, not through its two end samples: the end samples'
#: noise tilts the line, which the matrix method turns into an error of J⁰'s area.
DIFFERENCE_CHORD_WINDOW_M = 2.5
#: Sine modes J⁰ is fitted in (:func:`smooth_operator`); ``None`` in :func:`difference_mril`: the
#: thesis's grid-point least squares (:func:`difference_pinv`). 10 on a 10.2 m span: the shortest mode's
#: wavelength (2 m) is below the reading's low-pass (4 m), so the basis presumes no more smoothness than
#: the low-pass imposes anyway. Noise-free, on FE beams with 5 % element scatter, the area (mid-span)
#: against the low-passed line: 3 modes +3.0 % (+2.6–2.9 %), 6 modes +0.3 % (0.0 %), 10 modes −0.5 %
#: (−0.4 %), 14 −0.6 % (the rest is the low-pass's ends, not truncation) — and a relative bias common to
#: every batch cancels in D (global damage scales J⁰). 6 and 10 read the same sd on the blind test; 10
#: for the argument from the low-pass.
FUNDAMENTAL_MODES = 10


def registered_fundamental(line: MrIl, shift: float, span_m: float, wheelbase_m: float, *, grid_m: float,
                           min_wavelength_m: float, modes: int | None = FUNDAMENTAL_MODES) -> np.ndarray:
    """J⁰ on the span (the grid of :func:`cloud.rail.bridge.bogie_influence`'s ``difference``: whole
    steps of about ``grid_m`` per wheelbase) from a batch-mean wheel difference line read at x −
    ``shift``: relative to the line through its means beyond the ends (both wheels off the span;
    :func:`chord_windows`), then the matrix method (:func:`difference_mril`, low-passed at
    ``min_wavelength_m``; ``modes`` as there)."""
    c = max(1, int(round(wheelbase_m / grid_m)))
    h = wheelbase_m / c
    M = int(np.floor(span_m / h + 1e-9)) + 1
    xd = h * np.arange(M + c)
    g = np.interp(xd - shift, line.x_m, line.J)
    e0, e1 = (np.interp(xe - shift, line.x_m, line.J).mean() for xe in chord_windows(xd))
    g = g - (e0 + (e1 - e0) * xd / xd[-1])
    return difference_mril(xd, g, M, c, line.n_passes, min_wavelength_m=min_wavelength_m, modes=modes).J


def chord_windows(xd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The grid points over which the wheels' difference is anchored: :data:`DIFFERENCE_CHORD_WINDOW_M`
    of track before the grid ``xd``'s first point and after its last (both wheels off the span)."""
    h = float(xd[1] - xd[0])
    steps = h * np.arange(int(round(DIFFERENCE_CHORD_WINDOW_M / h)) + 1)
    return xd[0] - steps, xd[-1] + steps


@functools.lru_cache(maxsize=16)
def difference_pinv(M: int, c: int) -> np.ndarray:
    """The least-squares solution operator of the matrix method (g_k = J⁰_k − J⁰_(k−c), J⁰ = 0 off the
    span), (M, M + c): the same for every batch on a span, so formed once (the reading's draws call it
    hundreds of times)."""
    K = M + c
    A = np.zeros((K, M))
    A[np.arange(M), np.arange(M)] = 1.0
    A[np.arange(c, K), np.arange(K - c)] = -1.0
    P = np.linalg.pinv(A)
    P.flags.writeable = False
    return P


@functools.lru_cache(maxsize=16)
def smooth_operator(M: int, c: int, modes: int) -> np.ndarray:
    """The least-squares solution operator of the matrix method with J⁰ in the span's first ``modes``
    sine modes, J⁰_k = Σ_j θ_j·sin(j·π·k/(M − 1)) (zero at both supports and off the span), from g_k =
    J⁰_k − J⁰_(k−c) (k = 0 … M + c − 1) to J⁰ on the span's M grid points, (M, M + c)."""
    if not 1 <= modes <= (M - 1) // 2:
        raise ValueError(f"smooth_operator: modes must be 1..{(M - 1) // 2} for {M} grid points, got {modes}")
    k = np.arange(M + c)

    def basis(kk: np.ndarray) -> np.ndarray:
        on = (kk >= 0) & (kk <= M - 1)
        return np.sin(np.pi * np.outer(kk, np.arange(1, modes + 1)) / (M - 1)) * on[:, None]

    P = basis(k[:M]) @ np.linalg.pinv(basis(k) - basis(k - c))
    P.flags.writeable = False
    return P


def difference_mril(x_m: np.ndarray, g: np.ndarray, M: int, c: int, n_runs: int, *, min_wavelength_m: float,
                    modes: int | None = FUNDAMENTAL_MODES) -> MrIl:
    """J⁰ on the span from g_k = J⁰_k − J⁰_(k−c), the slope over wheel loads of the two wheels'
    time-synchronous AP difference (eq. 3.16 with equal axle loads W: W·(δ_A − δ_B) = W²·(J⁰_k −
    J⁰_(k−c)); Betti removes the cross terms, the regression the profile's difference).

    Least squares with J⁰ = 0 off the span (the matrix method, eq. 3.17–3.23, for unit loads) and J⁰
    in the span's first ``modes`` sine modes (:func:`smooth_operator`; ``None``: free at every grid
    point, :func:`difference_pinv`, the thesis's), then the low-pass of ``min_wavelength_m``. Why the
    difference: a body's force through the secondary suspension acts at the bogie's centre and moves
    both wheels' AP alike at each instant — the error of the bogie half-car (:mod:`cloud.rail.bridge`)
    cancels; a uniform track compliance cancels too.
    """
    J = (difference_pinv(M, c) if modes is None else smooth_operator(M, c, modes)) @ g
    J -= J[0] + (J[-1] - J[0]) * np.arange(M) / (M - 1)  # relative to the supports, as the AP chords
    h = x_m[1] - x_m[0]
    J = sosfiltfilt(butter(4, h / (0.5 * min_wavelength_m), output="sos"), J)
    return MrIl(x_m[:M], J, n_runs)
