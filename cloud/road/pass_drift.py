"""Per-pass drift as a nuisance of the profile posterior, marginalised exactly and locally.

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

Joint system (information form)
-------------------------------
With ``A_RR`` the banded precision of the profile (prior + data), the nuisance adds the blocks
``A_Rβ = Σ_p H_pᵀ R_p⁻¹ B_p`` and ``A_ββ = blockdiag(B_pᵀ R_p⁻¹ B_p) + I/s²`` and the information
``b_β = B_pᵀ R_p⁻¹ y_p``; every term is a sum over segments, assembled here from the held segments
(so a retracted segment is simply absent, and a segment update costs what it did).

Local elimination (why it is cheap)
-----------------------------------
A knot touches the profile only within one knot spacing of itself, and the profile is a Markov
chain of order ``u`` (its precision's bandwidth). So ``u`` profile points at each knot
(*separators*) cut the route into chunks whose interior points couple only to the two separators
around them and to the drift coefficients of the (at most two) knots of that chunk. Eliminating
every chunk's interior (one banded solve per chunk with ``2u + 2·passes`` right-hand sides) is
exact and leaves a *reduced* system on (separators, β) that is banded when ordered by position:
bandwidth ≈ 2 · (passes at a point + u), size ≈ knots × (passes + u). Everything then follows
from that small banded system and the chunks:

* the log evidence's dependence on ``s²`` is ``ℓ(s²) = ½ b̃ᵀÃ(s²)⁻¹b̃ − ½ log|Ã(s²)| − ½ K log s²``
  less its ``s² → 0`` limit (the system with β removed), one banded factorisation of ``Ã`` per
  ``s²``; the level is learnt by type-II maximum likelihood (0 when no drift beats none), and with
  a half-normal prior on ``s`` (MAP) for the mean: few short passes leave ℓ flat over an order of
  magnitude; the band is taken at the larger of the two levels;
* ``μ_β`` from ``Ã``; the profile's mean ``A_RR⁻¹ b_R − A_RR⁻¹ A_Rβ μ_β`` (one banded solve);
* the variance the unknown drifts add: at a chunk's interior ``diag(G Σ̃_JJ Gᵀ) − diag(G_S Σ̃⁰_SS G_Sᵀ)``
  with ``G = A_II⁻¹ A_IJ`` and ``Σ̃`` (``Σ̃⁰``: β removed) the band of the reduced system's inverse
  (selected inverse); at a separator ``Σ̃_ss − Σ̃⁰_ss``;
* draws: ``β`` from the reduced system, then ``R = A_RR⁻¹ b_R − A_RR⁻¹ A_Rβ β + L⁻ᵀ z``.

Cost per snapshot, for P points and n passes at a point: O(P · n) for the chunk solves and
O(P · n²) for the band, O(knots · n³) per ``s²`` tried: linear in the route length (eliminating
the profile against all K knots of all passes at once would be O(P · K) in memory and O(P · K²) in time).
Segment updates and retractions do not touch any of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.linalg import LinAlgError, cho_solve_banded, cholesky_banded
from scipy.optimize import minimize_scalar

from shared.jit import kernel
from shared.schema import ApSegment

from cloud.road.banded import band_cholesky, band_solve, draw_into, selected_inverse

#: Range the drift sd is learnt within (m); below the lower end the drift is taken as absent.
DRIFT_SD_BOUNDS_M = (1e-7, 1e-2)
#: Tolerance of the learnt log drift variance (the score equation's residual).
SCORE_TOL = 1e-11
#: Scale of the drift sd's half-normal prior in units of the passes' stated error sd (the edge's
#: error model's marginal sd per point, ``r · sigma``): a weakly informative prior that ties the level
#: to the noise the passes state. With two short passes the evidence alone is flat over an order of
#: magnitude and can peak on a far shoulder, where the drifts trade against the road's long waves (and
#: the trends the edges removed over the passes' differing stretches) and take them out of the mean;
#: where the passes' disagreement demands a larger level, the evidence outweighs the prior. The
#: scale is a modelling choice, not a bound the edge states: the band is held at the evidence's own
#: level when that is larger (:meth:`DriftPosterior.set_level`).
DRIFT_PRIOR_SCALE = 3.0


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
    A_bb: sp.csr_matrix  # (K, K): Σ BᵀR⁻¹B, the prior not included
    b_b: np.ndarray  # (K,)
    knot: np.ndarray  # (K,) global knot index of each column
    passes: list[tuple]  # pass keys, in column order
    offsets: list[int]  # first column of each pass


def drift_system(segments: list[ApSegment], a: int, e: int, size: int, spacing_m: float, knot_m: float,
                 info) -> DriftSystem:
    """Assemble ``A_Rβ``, ``BᵀR⁻¹B`` and ``BᵀR⁻¹y`` over block ``[a, e)`` from the held segments.

    ``info(segment, m) -> (q, rhs)`` is the likelihood's information on the segment's first ``m``
    points, ``q[d, t] = (R⁻¹)[t + d, t]`` (lower banded) and ``rhs = R⁻¹ y``: exactly what the
    estimator adds for the segment (its AR(1) form, or the edge's banded error model), so the
    nuisance sees the error model the profile does — a different one would make the joint system
    inconsistent (not even positive definite where a pass's drift and the road are confounded). Segments are clipped to the route's ``size`` points as the
    estimator clips them. Blocks are solved independently, so a pass cut by an uncovered gap
    longer than the estimator's ``max_gap_m`` has independent coefficients on either side.
    """
    spans: dict[tuple, list[int]] = {}
    parts = []
    # In a fixed order (pass, then position), not the order they arrived in: the sums below are then
    # the same floating-point sums whatever the run's history (arrivals, retractions, re-sends).
    for s in sorted(segments, key=lambda s: (pass_key(s), s.start_index, s.end_index)):
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
    P = e - a
    if not parts:
        return DriftSystem(sp.csr_matrix((P, 0)), sp.csr_matrix((0, 0)), np.zeros(0), np.zeros(0, np.int64), [], [])
    passes = sorted(spans)
    offsets, knots, K = [], [], 0
    for key in passes:
        offsets.append(K)
        knots.append(np.arange(spans[key][0], spans[key][1] + 1))
        K += spans[key][1] - spans[key][0] + 1
    col0 = {key: off - spans[key][0] for key, off in zip(passes, offsets)}
    # The passes' observations stacked (one row per segment point): row t observes grid point g[t]
    # through the hats of knots c[t], c[t] + 1 (column indices) with weights 1 − w[t], w[t]; Q is
    # block-diagonal, one banded block per segment (rows seg_lo[t] .. seg_hi[t] − 1).
    g, c, w, qs, rhs, seg_lo, seg_hi = [], [], [], [], [], [], []
    t0 = 0
    for s, lo, hi, k, wk, key in parts:
        m = hi - lo
        q, rh = info(s, m)
        g.append(np.arange(lo - a, hi - a))
        c.append(k + col0[key])
        w.append(wk)
        qs.append(q)
        rhs.append(rh)
        seg_lo.append(np.full(m, t0))
        seg_hi.append(np.full(m, t0 + m))
        t0 += m
    nq = max(q.shape[0] for q in qs)
    q = np.zeros((nq, t0))
    t0 = 0
    for qq in qs:
        q[: qq.shape[0], t0 : t0 + qq.shape[1]] = qq
        t0 += qq.shape[1]
    cat = np.concatenate
    r_rb, c_rb, v_rb, r_bb, c_bb, v_bb, b_b = _assemble(cat(g), cat(c), cat(w), q, cat(rhs), cat(seg_lo),
                                                        cat(seg_hi), K)
    A_Rb = sp.csr_matrix((v_rb, (r_rb, c_rb)), shape=(P, K))
    A_bb = sp.csr_matrix((v_bb, (r_bb, c_bb)), shape=(K, K))
    return DriftSystem(A_Rb, A_bb, b_b, cat(knots).astype(np.int64), passes, offsets)


@kernel
def _assemble(g, c, w, q, rhs, seg_lo, seg_hi, K):
    """``A_Rβ`` and ``BᵀQB`` (COO triplets, duplicates to be summed) and ``BᵀQy`` from the stacked rows.

    ``q[d, t] = Q[t + d, t]`` within a segment. Row t of ``QB`` couples to the hats of the rows
    within the band around it, whose left knots lie within ``Δ`` of ``c[t]``: its columns are
    ``c[t] − Δ .. c[t] + 1 + Δ``.
    """
    n = g.size
    nq = q.shape[0]
    delta = 0
    for t in range(n):
        for d in range(1, nq):
            if t + d < seg_hi[t] and q[d, t] != 0.0:
                delta = max(delta, c[t + d] - c[t])
    width = 2 * delta + 2
    qb = np.zeros((n, width))
    for t in range(n):
        qb[t, delta] += q[0, t] * (1.0 - w[t])
        qb[t, delta + 1] += q[0, t] * w[t]
        for d in range(1, nq):
            if t + d < seg_hi[t]:
                v = q[d, t]
                j = c[t + d] - c[t] + delta
                qb[t, j] += v * (1.0 - w[t + d])
                qb[t, j + 1] += v * w[t + d]
            if t - d >= seg_lo[t]:
                v = q[d, t - d]
                j = c[t - d] - c[t] + delta
                qb[t, j] += v * (1.0 - w[t - d])
                qb[t, j + 1] += v * w[t - d]
    nnz = 0
    for t in range(n):
        for j in range(width):
            if qb[t, j] != 0.0:
                nnz += 1
    rows = np.empty(nnz, dtype=np.int64)
    cols = np.empty(nnz, dtype=np.int64)
    vals = np.empty(nnz)
    brow = np.empty(2 * nnz, dtype=np.int64)
    bcol = np.empty(2 * nnz, dtype=np.int64)
    bval = np.zeros(2 * nnz)
    b_b = np.zeros(K)
    k = 0
    for t in range(n):
        for j in range(width):
            v = qb[t, j]
            if v == 0.0:
                continue
            rows[k] = g[t]
            cols[k] = c[t] - delta + j
            vals[k] = v
            # BᵀQB: row t's hats (c[t] with 1 − w, c[t] + 1 with w) against QB's column
            brow[2 * k] = c[t]
            bcol[2 * k] = cols[k]
            bval[2 * k] = (1.0 - w[t]) * v
            brow[2 * k + 1] = c[t] + 1
            bcol[2 * k + 1] = cols[k]
            bval[2 * k + 1] = w[t] * v
            k += 1
        b_b[c[t]] += (1.0 - w[t]) * rhs[t]
        b_b[c[t] + 1] += w[t] * rhs[t]
    keep = bval != 0.0  # a structural zero between two passes would couple them in the ordering
    return rows, cols, vals, brow[keep], bcol[keep], bval[keep], b_b


# -- the reduced (separators, β) system ------------------------------------------------------------


def _to_band(r: np.ndarray, c: np.ndarray, v: np.ndarray, n: int) -> np.ndarray:
    """Lower banded storage ``band[d, j] = A[j + d, j]`` of a symmetric matrix given as full COO
    triplets (duplicates summed); the bandwidth is the structural one, explicit zeros included."""
    low = r >= c
    r, c, v = r[low], c[low], v[low]
    bw = int((r - c).max()) if r.size else 0
    band = np.bincount((r - c) * n + c, weights=v, minlength=(bw + 1) * n).reshape(bw + 1, n)
    return band


def _band_block(S: np.ndarray, J: np.ndarray) -> np.ndarray:
    """``Σ[J, J]`` (dense) from the band ``S[d, i] = Σ[i, i + d]`` of a symmetric matrix."""
    d = np.abs(J[:, None] - J[None, :])
    return S[d, np.minimum(J[:, None], J[None, :])]


@kernel
def _chunk_rhs(ab, indptr, indices, data, b, i0, i1, around, betas):
    """``[A_IS, A_Iβ, b_I]`` (dense, (i1 − i0, |S| + |β| + 1)) of interior points ``[i0, i1)``:
    ``A_IS`` from the banded ``ab`` (lower, ``ab[d, j] = A[j + d, j]``) against the separator points
    ``around``, ``A_Iβ`` from the CSR arrays of ``A_Rβ`` against the sorted columns ``betas``."""
    u = ab.shape[0] - 1
    nS, nB = around.size, betas.size
    out = np.zeros((i1 - i0, nS + nB + 1))
    for c in range(nS):
        j = around[c]
        for i in range(max(i0, j - u), min(i1, j + u + 1)):
            out[i - i0, c] = ab[abs(i - j), min(i, j)]
    for i in range(i0, i1):
        for q in range(indptr[i], indptr[i + 1]):
            out[i - i0, nS + np.searchsorted(betas, indices[q])] += data[q]
        out[i - i0, nS + nB] = b[i]
    return out


@dataclass
class _Chunk:
    start: int  # interior points [start, stop) of the block
    stop: int
    factor: np.ndarray  # banded Cholesky factor of A_II
    sep_points: np.ndarray  # block indices of the separator points around it
    betas: np.ndarray  # columns of A_Rβ it couples to
    J: np.ndarray  # reduced indices of (sep_points, betas)
    J0: np.ndarray  # reduced-without-β indices of sep_points


@dataclass
class DriftPosterior:
    """Eliminated nuisance of one block: what the profile's mean, band and draws need."""

    size: int  # points of the block
    factor_RR: np.ndarray | None = None  # banded Cholesky factor of A_RR (the block's, drift-free)
    A_Rb: sp.csr_matrix | None = None
    ab: np.ndarray | None = None  # A_RR, lower banded
    b: np.ndarray | None = None  # b_R
    red: np.ndarray = field(default_factory=lambda: np.zeros((1, 0)))  # reduced precision, no prior
    b_red: np.ndarray = field(default_factory=lambda: np.zeros(0))
    beta_idx: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # reduced index of each β
    sep_red: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # reduced index of sep points
    sep_points: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # their block indices
    chunks: list[_Chunk] = field(default_factory=list)
    quad0: float = 0.0  # b̃_Sᵀ Ã_SS⁻¹ b̃_S (β removed)
    logdet0: float = 0.0  # log |Ã_SS|
    cov0: np.ndarray = field(default_factory=lambda: np.zeros((1, 0)))  # band of Ã_SS⁻¹
    s2: float = 0.0  # drift variance per coefficient (m²) the mean is taken at
    spread_s2: float = 0.0  # ... and the band and the draws' spread (>= s2)
    factor_red: np.ndarray | None = None  # at spread_s2: banded factor of Ã(spread_s2)
    mean_red: np.ndarray | None = None  # at s2
    level_shift: np.ndarray | None = None  # the profile's mean at spread_s2 less that at s2 (None: equal)

    @property
    def n_beta(self) -> int:
        return int(self.beta_idx.size)

    @property
    def n_coefficients(self) -> int:
        """Standard normals one draw of the nuisance takes (the reduced system's size, and one for
        the level's own uncertainty when the band's level differs from the mean's)."""
        return int(self.b_red.size) + (self.level_shift is not None)

    def _factor(self, s2: float) -> np.ndarray:
        A = self.red.copy()
        A[0, self.beta_idx] += 1.0 / s2
        return cholesky_banded(A, lower=True, check_finite=False)

    def log_evidence(self, s2: float) -> float:
        """The part of the block's log marginal likelihood that depends on ``s2`` (m²), 0 at 0."""
        if s2 <= 0.0 or self.n_beta == 0:
            return 0.0
        try:
            cb = self._factor(s2)
        except LinAlgError:  # numerically singular: β and the road confounded at this level
            return -math.inf
        x = cho_solve_banded((cb, True), self.b_red, check_finite=False)
        logdet = 2.0 * float(np.sum(np.log(cb[0])))
        return (0.5 * (float(self.b_red @ x) - self.quad0) - 0.5 * (logdet - self.logdet0)
                - 0.5 * self.n_beta * math.log(s2))

    def em_statistic(self, s2: float) -> float:
        """``E[βᵀβ | y, s2] = μ_βᵀμ_β + tr Σ_ββ`` (m²) at drift variance ``s2``: the evidence's score is
        ``(E[βᵀβ] / s2 − K) / (2 s2)``, zero where ``s2 = E[βᵀβ] / K`` (the EM fixed point)."""
        if self.n_beta == 0:
            return 0.0
        cb = self._factor(s2)
        mb = cho_solve_banded((cb, True), self.b_red, check_finite=False)[self.beta_idx]
        return float(mb @ mb) + float(selected_inverse(cb)[0, self.beta_idx].sum())

    def set_level(self, s2: float, spread_s2: float | None = None) -> None:
        """Fix the drift variance (m²): factorise the reduced system and take its mean at ``s2`` and
        its band (and the draws' spread about that mean) at ``spread_s2`` (default ``s2``; never below
        it). Two levels where the level itself is uncertain: the mean at the better supported one, the
        band at the larger, which holds what the drifts might be at either."""
        self.s2 = float(s2) if self.n_beta else 0.0
        self.spread_s2 = max(self.s2, float(spread_s2)) if self.n_beta and spread_s2 is not None else self.s2
        self.mean_red = self.level_shift = None
        if self.s2 > 0.0:
            self.mean_red = cho_solve_banded((self._factor(self.s2), True), self.b_red, check_finite=False)
        if self.spread_s2 > 0.0:
            self.factor_red = self._factor(self.spread_s2)
        if self.spread_s2 > self.s2:
            # The mean the band's level would give differs from the mean's by this shift; the band
            # holds it too (its square is added to the variance, a draw moves along it by a standard
            # normal), so that it covers what the drifts leave at either level.
            at_spread = cho_solve_banded((self.factor_red, True), self.b_red, check_finite=False)[self.beta_idx]
            self.level_shift = self._shift(at_spread - self.mean_beta())

    def mean_beta(self) -> np.ndarray:
        if self.s2 <= 0.0:
            return np.zeros(self.n_beta)
        return self.mean_red[self.beta_idx]

    def _shift(self, beta: np.ndarray) -> np.ndarray:
        """``−A_RR⁻¹ A_Rβ β`` for coefficient vectors ``beta`` (K,) or (K, n)."""
        return -cho_solve_banded((self.factor_RR, True), self.A_Rb @ beta, check_finite=False)

    def profile_shift(self) -> np.ndarray:
        """What the drift's posterior mean removes from the drift-free mean: ``−A_RR⁻¹ A_Rβ μ_β``."""
        if self.s2 <= 0.0:
            return np.zeros(self.size)
        return self._shift(self.mean_beta())

    def profile_variance(self) -> np.ndarray:
        """``diag(W C⁻¹ Wᵀ)`` (m²), ``W = A_RR⁻¹ A_Rβ``: the variance the unknown drifts add to each
        point, as the joint posterior's marginal less the drift-free one, chunk by chunk (at the band's
        level), plus the square of the mean's shift between the two levels when they differ."""
        out = np.zeros(self.size)
        if self.spread_s2 <= 0.0:
            return out
        cov = selected_inverse(self.factor_red)  # at the band's level
        out[self.sep_points] = cov[0, self.sep_red] - self.cov0[0, np.arange(self.sep_points.size)]
        for ch in self.chunks:
            G = self._chunk_solve(ch)[:, :-1]
            nS = ch.sep_points.size
            GS = G[:, :nS]
            out[ch.start : ch.stop] = (np.einsum("ij,ij->i", G @ _band_block(cov, ch.J), G)
                                       - np.einsum("ij,ij->i", GS @ _band_block(self.cov0, ch.J0), GS))
        out = np.maximum(out, 0.0)
        return out if self.level_shift is None else out + self.level_shift**2

    def draw_shift(self, z: np.ndarray) -> np.ndarray:
        """``−A_RR⁻¹ A_Rβ β`` for draws of β from its marginal posterior, one per row of the standard
        normals ``z`` (n, :attr:`n_coefficients`): the reduced system is drawn whole, β taken from it."""
        if self.spread_s2 <= 0.0:
            return np.zeros((z.shape[0], self.size))
        n = self.b_red.size
        x = np.array(z[:, :n], dtype=np.float64, order="C")
        draw_into(self.factor_red, self.mean_red if self.s2 > 0.0 else np.zeros(n), x)
        out = self._shift(np.ascontiguousarray(x[:, self.beta_idx].T)).T
        if self.level_shift is not None:
            out += z[:, n : n + 1] * self.level_shift
        return out

    def _chunk_solve(self, ch: _Chunk) -> np.ndarray:
        """``A_II⁻¹ [A_IS, A_Iβ, b_I]`` of one chunk (its last column the information's)."""
        return band_solve(ch.factor, self._chunk_rhs(ch))

    def _chunk_rhs(self, ch: _Chunk) -> np.ndarray:
        A = self.A_Rb
        return _chunk_rhs(self.ab, A.indptr, A.indices, A.data, self.b, ch.start, ch.stop, ch.sep_points, ch.betas)


def _separators(P: int, u: int, first: int, knot_pts: float) -> list[int]:
    """Starts of the ``u``-point separators: the grid points at the knots, each chunk between two
    keeping at least one interior point (knots closer than ``u + 1`` points are skipped)."""
    out, nxt = [], 1
    for k in range(math.ceil(first / knot_pts), math.floor((first + P - 1) / knot_pts) + 1):
        s = int(round(k * knot_pts)) - first
        if s >= nxt and s + u <= P - 1:
            out.append(s)
            nxt = s + u + 1
    return out


def eliminate(ab: np.ndarray, cb: np.ndarray, b: np.ndarray, system: DriftSystem, knot_pts: float,
              first: int) -> DriftPosterior:
    """Eliminate the profile chunk by chunk into the reduced (separators, β) system.

    ``ab``: the block's profile precision ``A_RR`` (lower banded, prior + data), ``cb`` its banded
    Cholesky factor, ``b`` its information vector; ``knot_pts``: the knot spacing in grid steps;
    ``first``: the global grid index of the block's first point.
    """
    P = ab.shape[1]
    K = system.b_b.size
    if K == 0:
        return DriftPosterior(P)
    u = ab.shape[0] - 1
    seps = _separators(P, u, first, knot_pts)
    sep_points = np.array([s + d for s in seps for d in range(u)], dtype=np.int64)
    bounds = [0] + [x for s in seps for x in (s, s + u)] + [P]
    spans = [(bounds[i], bounds[i + 1]) for i in range(0, len(bounds), 2)]
    # Reduced unknowns ordered by position (separator points, then the knots there): banded.
    pos = np.concatenate([sep_points.astype(float), system.knot * knot_pts - first])
    kind = np.concatenate([np.zeros(sep_points.size), np.ones(K)])
    order = np.lexsort((np.arange(pos.size), kind, pos))
    red_of = np.empty(pos.size, dtype=np.int64)
    red_of[order] = np.arange(pos.size)
    sep_red, beta_idx = red_of[: sep_points.size], red_of[sep_points.size :]
    point_red = np.full(P, -1, dtype=np.int64)
    point_red[sep_points] = sep_red
    n = pos.size
    rows, cols, vals = [], [], []

    def add(J_r, J_c, M):
        rows.append(np.repeat(J_r, J_c.size))
        cols.append(np.tile(J_c, J_r.size))
        vals.append(M.ravel())

    b_red = np.zeros(n)
    b_red[sep_red] = b[sep_points]
    b_red[beta_idx] += system.b_b
    if sep_points.size:  # direct couplings of the separators: among themselves and to β
        for d in range(u + 1):  # A[i + d, i] between separator points (within one, or neighbours)
            i = sep_points[sep_points + d < P]
            i = i[point_red[i + d] >= 0]
            for r, c in ((point_red[i + d], point_red[i]), (point_red[i], point_red[i + d]))[: 1 if d == 0 else 2]:
                rows.append(r), cols.append(c), vals.append(ab[d, i])
        Sb = system.A_Rb[sep_points].tocoo()
        for r, c in ((sep_red[Sb.row], beta_idx[Sb.col]), (beta_idx[Sb.col], sep_red[Sb.row])):
            rows.append(r), cols.append(c), vals.append(Sb.data)
    bb = system.A_bb.tocoo()
    rows.append(beta_idx[bb.row]), cols.append(beta_idx[bb.col]), vals.append(bb.data)
    post = DriftPosterior(P, cb, system.A_Rb, ab, b)
    sep_pos0 = np.full(P, -1, dtype=np.int64)  # index among the separator points (system without β)
    sep_pos0[sep_points] = np.arange(sep_points.size)
    for i0, i1 in spans:
        if i1 <= i0:
            continue
        around = np.array([j for j in range(i0 - u, i0) if j >= 0] + [j for j in range(i1, i1 + u) if j < P],
                          dtype=np.int64)
        betas = np.unique(system.A_Rb.indices[system.A_Rb.indptr[i0] : system.A_Rb.indptr[i1]])
        ch = _Chunk(i0, i1, band_cholesky(ab[:, i0:i1]), around, betas,
                    np.concatenate([point_red[around], beta_idx[betas]]), sep_pos0[around])
        post.chunks.append(ch)
        M = post._chunk_rhs(ch)
        X = band_solve(ch.factor, M.copy())
        nJ = ch.J.size
        add(ch.J, ch.J, -(M[:, :nJ].T @ X[:, :nJ]))
        np.subtract.at(b_red, ch.J, M[:, :nJ].T @ X[:, nJ])
    r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    post.red = _to_band(r, c, v, n)
    post.b_red, post.beta_idx, post.sep_red, post.sep_points = b_red, beta_idx, sep_red, sep_points
    if sep_points.size:  # the same system without β: the evidence's reference and the drift-free band
        keep = (r < n) & np.isin(r, sep_red) & np.isin(c, sep_red)
        to0 = np.full(n, -1, dtype=np.int64)
        to0[sep_red] = np.arange(sep_red.size)  # sep_red is increasing: positions keep their order
        cb0 = cholesky_banded(_to_band(to0[r[keep]], to0[c[keep]], v[keep], sep_red.size), lower=True,
                              check_finite=False)
        x0 = cho_solve_banded((cb0, True), b_red[sep_red], check_finite=False)
        post.quad0 = float(b_red[sep_red] @ x0)
        post.logdet0 = 2.0 * float(np.sum(np.log(cb0[0])))
        post.cov0 = selected_inverse(cb0)
    return post


def log_evidence(s2: float, posts: list[DriftPosterior]) -> float:
    """The part of the log marginal likelihood that depends on the drift variance ``s2`` (m²)."""
    return sum(d.log_evidence(s2) for d in posts)


def stated_error_sd(segments: list[ApSegment]) -> float:
    """The median over the points of ``segments`` of the error sd their passes state (m): the edge's
    error model's marginal sd ``r · sigma``, or ``sigma`` where a segment carries no model."""
    if not segments:
        return 0.0
    sd = [s.sigma * (float(s.error_model[0]) if s.error_model.size else 1.0) for s in segments]
    return float(np.median(np.concatenate(sd)))


def log_prior(s2: float, prior_sd: float | None) -> float:
    """Log density (up to a constant) of the drift sd's half-normal prior of scale ``prior_sd`` (m) at
    variance ``s2`` (m²); 0 (flat: maximum likelihood) when ``prior_sd`` is None."""
    return 0.0 if prior_sd is None else -0.5 * s2 / prior_sd**2


def learn_drift_variance(posts: list[DriftPosterior], bounds_m=DRIFT_SD_BOUNDS_M, tol: float = SCORE_TOL,
                         prior_sd: float | None = None) -> float:
    """Type-II ML (MAP with ``prior_sd``) drift variance (m²) over all blocks of a route; 0 when the
    lower bound wins.

    ``prior_sd``: scale (m) of a half-normal prior on the drift sd (:func:`log_prior`). With many
    passes the evidence is sharp and the prior moves the level little; with two short passes it is
    flat over an order of magnitude, and the prior keeps the level where the passes' disagreement
    and the error they state put it rather than on a far shoulder.

    A function of the held data alone, to well below anything it moves: a fixed grid brackets the
    maximum (ℓ can have a flat shoulder), Brent's method on ℓ finds it to ~1e-4 in log s², and the
    score equation (the EM fixed point ``log s² = log(E[βᵀβ] / K)``) polishes it by secant steps to
    ``tol`` in log s² — a comparison of evidence values stops resolving the maximum at ~1e-6 (their
    rounding against ℓ's curvature), and where it stops would depend on the rounding of the sums,
    i.e. on the order segments arrived in.
    """
    if not any(d.n_beta for d in posts):
        return 0.0
    lo, hi = 2.0 * math.log(bounds_m[0]), 2.0 * math.log(bounds_m[1])
    def objective(u):
        return log_evidence(math.exp(u), posts) + log_prior(math.exp(u), prior_sd)

    grid = np.linspace(lo, hi, 25)  # ℓ can have a flat shoulder: bracket on a grid, then refine
    vals = [objective(u) for u in grid]
    i = int(np.argmax(vals))
    if vals[i] <= 0.0:  # no s² beats no drift at all
        return 0.0
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    res = minimize_scalar(lambda u: -objective(u), bounds=(a, b), method="bounded", options={"xatol": 1e-4})
    u = res.x if -res.fun >= vals[i] else grid[i]
    if u <= lo + 1e-9:
        return 0.0
    return math.exp(_polish(u, posts, a, b, tol, prior_sd))


def _polish(u: float, posts: list[DriftPosterior], a: float, b: float, tol: float, prior_sd: float | None = None,
            max_iter: int = 30) -> float:
    """The root of ``h(u) = log(Σ E[βᵀβ] / (Σ K + s²/s₀²)) − u``, ``s² = eᵘ`` (the prior's term only
    with a scale ``s₀ = prior_sd``), near ``u`` within ``[a, b]`` (secant steps after one EM step);
    ``u`` unchanged if the steps leave the bracket or do not converge."""
    K = sum(d.n_beta for d in posts)

    def h(v):
        st = sum(d.em_statistic(math.exp(v)) for d in posts)
        k = K + (0.0 if prior_sd is None else math.exp(v) / prior_sd**2)
        return math.log(st / k) - v if st > 0.0 else -math.inf

    try:
        u0, h0 = u, h(u)
        if abs(h0) <= tol:
            return u0
        u1 = u0 + h0
        for _ in range(max_iter):
            if not (a <= u1 <= b):
                break
            h1 = h(u1)
            if abs(h1) <= tol:
                return u1
            step = h1 if h1 == h0 else -h1 * (u1 - u0) / (h1 - h0)
            if not math.isfinite(step):
                break
            u0, h0, u1 = u1, h1, u1 + step
    except LinAlgError:
        pass
    return u
