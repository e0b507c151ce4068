"""Per-pass drift as a nuisance of the profile posterior, marginalised exactly.

Model
-----
Each pass ``p`` (one vehicle, one pass, one axle) measures ``y_p = R + d_p + e_p`` on the points it
covers: the road, its own drift, and the error the white/AR(1) likelihood describes. The drift is
what the edge's ±150 m drift control leaves of twice-integrated sensor noise: smooth, independent
from pass to pass, tens to hundreds of metres long. It is modelled on a global lattice of knots
every ``knot_m`` metres by linear hat functions, ``d_p(x) = Σ_j β_pj φ_j(x)``, with independent
coefficients ``β_pj ~ N(0, s²)`` over the knots the pass touches (offset and drift of the pass
included). The hats resolve wavelengths down to about ``2 · knot_m``; shorter ones stay with the
white likelihood and the excess-scatter term of :mod:`.long_wave`.

Exact marginalisation (information form)
----------------------------------------
With ``A_RR`` the banded precision of the profile (prior + data), the nuisance adds the blocks
``A_Rβ = Σ_p H_pᵀ R_p⁻¹ B_p`` and ``A_ββ = blockdiag(B_pᵀ R_p⁻¹ B_p) + I/s²`` and the information
``b_β = B_pᵀ R_p⁻¹ y_p``; every term is a sum over segments, assembled here from the held segments
(so a retracted segment is simply absent, and a segment update costs what it did). Eliminating R:

* ``W = A_RR⁻¹ A_Rβ`` (banded solves, one per coefficient),
* ``C(s²) = C₀ + I/s²`` with ``C₀ = B ᵀR⁻¹B − A_βR W`` (the information the data give on β once R
  is free), ``r = b_β − A_βR A_RR⁻¹ b_R``,
* ``β | y ~ N(C⁻¹ r, C⁻¹)``, and ``R | y`` has mean ``A_RR⁻¹ b_R − W μ_β`` and covariance
  ``A_RR⁻¹ + W C⁻¹ Wᵀ``: the banded posterior's band plus ``diag(W C⁻¹ Wᵀ)``.

With ``C₀ = V Λ Vᵀ`` (once per snapshot), every ``s²`` costs O(K): the drift level is learnt by
type-II maximum likelihood, maximising the part of the log evidence that depends on it,
``ℓ(s²) = ½ Σ_k ρ_k² / (λ_k + 1/s²) − ½ Σ_k log(1 + s² λ_k)``, ``ρ = Vᵀ r``. With no drift in the
data the maximum is at ``s² = 0`` and the nuisance vanishes exactly.

Cost (at snapshot, per block of P points and K = Σ_p knots_p coefficients): O(P b K) for ``W``,
O(K³) for the eigendecomposition and O(P K²) for the band: linear in the route length for a fixed
fleet, but growing with the passes held (K ∝ passes). Segment updates and retractions do not touch
any of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.linalg import cho_solve_banded
from scipy.optimize import minimize_scalar

from shared.schema import ApSegment

#: Range the drift sd is learnt within (m); below the lower end the drift is taken as absent.
DRIFT_SD_BOUNDS_M = (1e-7, 1e-2)


def pass_key(seg: ApSegment) -> tuple[str, str, int]:
    """The drift belongs to one vehicle's pass under one axle."""
    return (seg.vehicle_id, seg.pass_id, seg.axle)


def hat_weights(start: int, m: int, spacing_m: float, knot_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Left knot index ``k`` (int) and right weight ``w`` of grid points ``start .. start + m − 1``:
    ``φ_k = 1 − w``, ``φ_{k+1} = w``."""
    u = (start + np.arange(m)) * (spacing_m / knot_m)
    k = np.floor(u + 1e-9).astype(np.int64)
    w = np.clip(u - k, 0.0, 1.0)
    return k, w


@dataclass
class DriftSystem:
    """The nuisance's information for one block of grid points ``[a, e)``."""

    A_Rb: sp.csr_matrix  # (P_block, K)
    A_bb: np.ndarray  # (K, K): Σ B ᵀR⁻¹B, the prior not included
    b_b: np.ndarray  # (K,)
    passes: list[tuple]  # pass keys, in column order
    offsets: list[int]  # first column of each pass


def drift_system(segments: list[ApSegment], a: int, e: int, size: int, spacing_m: float, knot_m: float,
                 info) -> DriftSystem:
    """Assemble ``A_Rβ``, ``BᵀR⁻¹B`` and ``BᵀR⁻¹y`` over block ``[a, e)`` from the held segments.

    ``info(values, sigma) -> (diag, off, rhs)`` is the likelihood's per-segment information
    (:func:`.gmrf_profile.segment_information` at the estimator's ρ), so the nuisance sees exactly
    the error model the profile does. Segments are clipped to the route's ``size`` points as the
    estimator clips them. Blocks are solved independently, so a pass cut by an uncovered gap
    longer than the estimator's ``max_gap_m`` has independent coefficients on either side.
    """
    spans: dict[tuple, list[int]] = {}
    parts = []
    for s in segments:
        lo, hi = max(s.start_index, a), min(s.end_index, size, e)
        if hi <= lo or s.start_index < a:  # a segment lies in one block (blocks are covered runs)
            continue
        k, w = hat_weights(lo, hi - lo, spacing_m, knot_m)
        key = pass_key(s)
        k0, k1 = int(k[0]), int(k[-1]) + 1
        if key in spans:
            spans[key][0] = min(spans[key][0], k0)
            spans[key][1] = max(spans[key][1], k1)
        else:
            spans[key] = [k0, k1]
        parts.append((s, lo, hi, k, w, key))
    passes = sorted(spans)
    offsets, K = [], 0
    for key in passes:
        offsets.append(K)
        K += spans[key][1] - spans[key][0] + 1
    col0 = {key: off - spans[key][0] for key, off in zip(passes, offsets)}
    # The passes' observations stacked (one row per segment point): B maps coefficients to rows,
    # Q is block-diagonal (one tridiagonal block per segment) and row t observes grid point g[t].
    P = e - a
    rows, cols, vals, qrows, qcols, qvals, g, rhs_all = [], [], [], [], [], [], [], []
    t0 = 0
    for s, lo, hi, k, w, key in parts:
        m = hi - lo
        diag, off, rhs = info(s.values[:m], s.sigma[:m])
        t = t0 + np.arange(m)
        c = k + col0[key]
        rows += [t, t]
        cols += [c, c + 1]
        vals += [1.0 - w, w]
        qrows += [t, t[:-1], t[1:]]
        qcols += [t, t[1:], t[:-1]]
        qvals += [diag, off, off]
        g.append(np.arange(lo - a, hi - a))
        rhs_all.append(rhs)
        t0 += m
    if not parts:
        return DriftSystem(sp.csr_matrix((P, 0)), np.zeros((0, 0)), np.zeros(0), [], [])
    cat = np.concatenate
    B = sp.csr_matrix((cat(vals), (cat(rows), cat(cols))), shape=(t0, K))
    Q = sp.csr_matrix((cat(qvals), (cat(qrows), cat(qcols))), shape=(t0, t0))
    H = sp.csr_matrix((np.ones(t0), (np.arange(t0), cat(g))), shape=(t0, P))
    QB = (Q @ B).tocsc()
    A_Rb = (H.T @ QB).tocsr()
    A_bb = (B.T @ QB).toarray()
    b_b = B.T @ cat(rhs_all)
    return DriftSystem(A_Rb, A_bb, b_b, passes, offsets)


@dataclass
class DriftPosterior:
    """Eliminated nuisance of one block: what the profile's mean, band and draws need."""

    W: np.ndarray  # (P_block, K) = A_RR⁻¹ A_Rβ
    lam: np.ndarray  # (K,) eigenvalues of C₀ (clipped ≥ 0)
    V: np.ndarray  # (K, K) its eigenvectors
    rho: np.ndarray  # (K,) Vᵀ r
    s2: float = 0.0  # drift variance per coefficient (m²)

    def mean_beta(self) -> np.ndarray:
        if self.s2 <= 0.0:
            return np.zeros(self.lam.size)
        return self.V @ (self.rho / (self.lam + 1.0 / self.s2))

    def profile_shift(self) -> np.ndarray:
        """What the drift's posterior mean removes from the drift-free mean: ``−W μ_β``."""
        return -(self.W @ self.mean_beta())

    def profile_variance(self) -> np.ndarray:
        """``diag(W C⁻¹ Wᵀ)``: the variance the unknown drifts add to each point (m²)."""
        if self.s2 <= 0.0:
            return np.zeros(self.W.shape[0])
        F = self.W @ self.V
        return (F * F) @ (1.0 / (self.lam + 1.0 / self.s2))

    def draw_shift(self, z: np.ndarray) -> np.ndarray:
        """``−W β`` for draws ``β = μ_β + V diag(1/√(λ + 1/s²)) z`` of the nuisance (rows of z)."""
        if self.s2 <= 0.0:
            return np.zeros((z.shape[0], self.W.shape[0]))
        beta = self.mean_beta()[None, :] + (z / np.sqrt(self.lam + 1.0 / self.s2)) @ self.V.T
        return -(beta @ self.W.T)


def eliminate(cb: np.ndarray, mean0: np.ndarray, system: DriftSystem) -> DriftPosterior:
    """Eliminate R from the joint system: ``W``, and ``C₀``, ``r`` in their eigenbasis."""
    K = system.b_b.size
    if K == 0:
        return DriftPosterior(np.zeros((mean0.size, 0)), np.zeros(0), np.zeros((0, 0)), np.zeros(0))
    W = cho_solve_banded((cb, True), system.A_Rb.toarray(), check_finite=False)
    C0 = system.A_bb - system.A_Rb.T @ W
    r = system.b_b - system.A_Rb.T @ mean0
    C0 = 0.5 * (C0 + C0.T)
    lam, V = np.linalg.eigh(C0)
    return DriftPosterior(W, np.clip(lam, 0.0, None), V, V.T @ r)


def log_evidence(s2: float, posts: list[DriftPosterior]) -> float:
    """The part of the log marginal likelihood that depends on the drift variance ``s2`` (m²)."""
    if s2 <= 0.0:
        return 0.0
    out = 0.0
    for d in posts:
        out += 0.5 * float(np.sum(d.rho**2 / (d.lam + 1.0 / s2))) - 0.5 * float(np.sum(np.log1p(s2 * d.lam)))
    return out


def learn_drift_variance(posts: list[DriftPosterior], bounds_m=DRIFT_SD_BOUNDS_M) -> float:
    """Type-II ML drift variance (m²) over all blocks of a route; 0 when the lower bound wins."""
    if not any(d.lam.size for d in posts):
        return 0.0
    lo, hi = 2.0 * math.log(bounds_m[0]), 2.0 * math.log(bounds_m[1])
    grid = np.linspace(lo, hi, 25)  # ℓ can have a flat shoulder: bracket on a grid, then refine
    vals = [log_evidence(math.exp(u), posts) for u in grid]
    i = int(np.argmax(vals))
    if vals[i] <= 0.0:  # no s² beats no drift at all
        return 0.0
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    res = minimize_scalar(lambda u: -log_evidence(math.exp(u), posts), bounds=(a, b), method="bounded",
                          options={"xatol": 1e-4})
    u = res.x if -res.fun >= vals[i] else grid[i]
    return 0.0 if u <= lo + 1e-9 else math.exp(u)
