"""Bayesian road profile: the exact Gaussian posterior of a GMRF prior and every pass's AP, incrementally.

Model (per route, on the global grid ``x_i = i · spacing_m``)
------------------------------------------------------------
* Prior: Gaussian random walk (thesis eq. 4.8) of order 1 — increments ``R_i − R_{i−1} ~ N(0, 1/τ)``
  per grid step — or of order 2 (second differences ``~ N(0, 1/τ)``), plus a vanishing ridge
  ``ridge · I`` that makes the level proper (the data fix it; the absolute level is unobservable
  anyway, segments are drift-controlled on the edge). In the thesis's parametrisation
  ``τ₁ = τ · spacing_m²``.
* Likelihood: each segment observes the profile directly, ``y = R[lo:hi] + e`` with
  ``e ~ N(0, D C D)``, ``D = diag(sigma)`` and ``C`` the AR(1) correlation ``ρ^|i−j|``; ``C⁻¹`` is
  tridiagonal, so a segment adds a tridiagonal block ``Hᵀ R⁻¹ H`` to the precision and ``Hᵀ R⁻¹ y``
  to the information vector: O(segment length), exact, order-independent. ``retract`` recomputes
  the same contribution from the segment (a deterministic function of it) and subtracts it.
  A segment that carries the edge's own error model (:attr:`ApSegment.error_model`, derived from the
  inverse's noise transfer: :mod:`edge.error_model`) uses it instead: ``R⁻¹ = D⁻¹ T D⁻¹`` with ``T``
  its banded Toeplitz precision (order p ≤ 8), so the contribution is a (p + 1)-band, still O(m p)
  and exactly retractable. The drift nuisance below reads every segment through the same model.
* τ: fixed when given; otherwise learnt by empirical Bayes (type-II maximum likelihood) at
  snapshot time. The score equation of the marginal likelihood is the EM fixed point
  ``τ = rank / (μᵀAμ + tr(A Σ))`` (``A`` the difference-operator precision), whose trace needs
  only the band of ``Σ`` the selected inverse gives; it is solved by secant iteration on log τ,
  warm-started from the previous τ, to a relative tolerance ``tau_tol``.

Posterior
---------
Only covered stretches are solved: runs of points covered by at least one segment, merged across
gaps of at most ``max_gap_m`` (interpolated by the prior, with wider bands). Each such block's
precision ``τ A + ridge I + Q_data`` is factorised by a banded Cholesky (LAPACK ``pbtrf``); the
mean is a banded solve, the marginal variances come from the selected inverse (Takahashi
recursion on the banded factor, O(P b²)), and posterior draws are ``μ + L⁻ᵀ z``. Points outside
every block are NaN. Blocks are solved independently; the random walk's coupling across a gap
longer than ``max_gap_m`` is weak and ignored. The result is cached per route until the next
update or retract touching it.

Per-pass drift (optional, ``drift_knot_m``)
-------------------------------------------
Each pass also carries its own drift (what the edge's drift control leaves of twice-integrated
sensor noise, independent from pass to pass): a nuisance of the posterior on a lattice of knots
every ``drift_knot_m``, marginalised exactly by eliminating the profile (:mod:`.pass_drift`), its
level learnt from the evidence (or fixed by ``drift_sd_m``). Two short passes leave the level
uncertain over an order of magnitude, and a level far above what the passes' error suggests lets the
drifts take the road's long waves: the mean is taken at the level a half-normal prior scaled to the
passes' stated error and the evidence support (MAP), the band at the larger of that and the
evidence's maximum (type-II ML), so the prior never narrows the band. It moves the mean (each
pass's drift is estimated, not averaged in) and widens the band at wavelengths above about
``2 · drift_knot_m`` by what the unknown drifts leave in the fused profile. Its information is
assembled at snapshot time from the held segments, so segment updates and retractions cost what
they did and a retraction is exact by construction.

What neither covers (errors at 0.5–50 m beyond the white model's, calibration error in between)
is measured from the passes' disagreement by :mod:`.long_wave`, which the cloud applies to the
exported band.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_solve_banded, cholesky_banded

from shared.jit import kernel
from shared.schema import SIGMA_SCALE, ApSegment

from cloud.road.banded import draw_into, selected_inverse
from cloud.road.mean_profile import ProfileSnapshot
from cloud.road.pass_drift import (DRIFT_PRIOR_SCALE, DriftPosterior, drift_system, eliminate, learn_drift_variance,
                                   stated_error_sd)

log = logging.getLogger(__name__)

_Z95 = 1.959963984540054
_DIFF = {1: np.array([-1.0, 1.0]), 2: np.array([1.0, -2.0, 1.0])}
TAU_BOUNDS = (1.0, 1.0e16)
"""Range τ is learnt within (1/m²): increment sd between 1 m and 10 nm per grid step."""


def iso8608_tau(spacing_m: float, gd0_m3: float = 64e-6, order: int = 1) -> float:
    """Precision of the order-``order`` differences of an ISO 8608 profile (w = 2) on ``spacing_m``.

    For ``Gd(n) = Gd0 (n/n0)⁻²`` the increment over Δ has variance ``2π² Gd0 n0² Δ`` and the
    second difference ``4π² Gd0 n0² Δ``. The default ``Gd0`` is class B's geometric mean; used as
    the starting value when τ is learnt.
    """
    var = (2.0 if order == 1 else 4.0) * math.pi**2 * gd0_m3 * 0.1**2 * spacing_m
    return 1.0 / var


def difference_precision(n: int, order: int) -> np.ndarray:
    """``DᵀD`` of the order-``order`` difference operator on ``n`` points, lower banded (order + 1, n)."""
    c = _DIFF[order]
    band = np.zeros((order + 1, n))
    rows = n - order
    if rows <= 0:
        return band
    for p in range(order + 1):
        for q in range(p + 1):
            band[p - q, q : q + rows] += c[p] * c[q]
    return band


def segment_information(values: np.ndarray, sigma: np.ndarray, rho: float
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One segment's ``Hᵀ R⁻¹ H`` (diagonal, sub-diagonal) and ``Hᵀ R⁻¹ y`` on its own points.

    ``R = D C D`` with ``D = diag(sigma)`` (m) and ``C_ij = ρ^|i−j|``; ``C⁻¹`` is tridiagonal with
    diagonal ``(1, 1 + ρ², …, 1 + ρ², 1) / (1 − ρ²)`` and off-diagonal ``−ρ / (1 − ρ²)``.
    """
    inv = 1.0 / sigma
    m = values.size
    if rho == 0.0 or m == 1:
        diag = inv * inv
        off = np.zeros(max(m - 1, 0))
        return diag, off, diag * values
    g = 1.0 / (1.0 - rho * rho)
    c = np.full(m, (1.0 + rho * rho) * g)
    c[0] = c[-1] = g
    diag = c * inv * inv
    off = (-rho * g) * inv[:-1] * inv[1:]
    rhs = diag * values
    rhs[:-1] += off * values[1:]
    rhs[1:] += off * values[:-1]
    return diag, off, rhs


@kernel
def _accumulate(q, b, cover, passes, lo, values_q, scale, offset, sigma_q, sigma_ref, sigma_scale, rho, sign,
                is_pass):
    """Add ``sign`` times a segment's :func:`segment_information` to the route's sums from index ``lo``.

    The segment comes as its wire codes, decoded point by point as :attr:`ApSegment.values` and
    :attr:`ApSegment.sigma` decode them (``offset + scale·q``; ``sigma_ref · sigma_scale[−q]``),
    and the arithmetic is :func:`segment_information`'s, in the same order: the result is
    bit-identical, without the temporaries (this is the cloud's per-segment cost). ``cover`` (and
    ``passes`` if ``is_pass``) move by ``sign``.
    """
    m = values_q.size
    step = int(sign)
    if rho == 0.0 or m == 1:
        for i in range(m):
            inv = 1.0 / (sigma_ref * sigma_scale[-np.int64(sigma_q[i])])
            d = inv * inv
            q[0, lo + i] += sign * d
            b[lo + i] += sign * (d * (offset + scale * np.float64(values_q[i])))
    else:
        g = 1.0 / (1.0 - rho * rho)
        c_mid = (1.0 + rho * rho) * g
        c_off = -rho * g
        off_prev = 0.0
        v_prev = 0.0
        v = offset + scale * np.float64(values_q[0])
        inv_next = 1.0 / (sigma_ref * sigma_scale[-np.int64(sigma_q[0])])
        for i in range(m):
            inv = inv_next
            d = (g if i == 0 or i == m - 1 else c_mid) * inv * inv
            r = d * v
            off = 0.0  # Q[i + 1, i]
            v_next = 0.0
            if i + 1 < m:
                v_next = offset + scale * np.float64(values_q[i + 1])
                inv_next = 1.0 / (sigma_ref * sigma_scale[-np.int64(sigma_q[i + 1])])
                off = c_off * inv * inv_next
                r += off * v_next
                q[1, lo + i] += sign * off
            if i > 0:
                r += off_prev * v_prev
            q[0, lo + i] += sign * d
            b[lo + i] += sign * r
            off_prev, v_prev, v = off, v, v_next
    for i in range(lo, lo + m):
        cover[i] += step
        if is_pass:
            passes[i] += step


def segment_band_information(values: np.ndarray, sigma: np.ndarray, error_model: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray]:
    """A segment's ``Hᵀ R⁻¹ H`` (lower banded, (p + 1, m)) and ``Hᵀ R⁻¹ y`` under the edge's error
    model ``[r, c₀, …, c_p]`` (:attr:`ApSegment.error_model`): ``R⁻¹ = D⁻¹ T D⁻¹`` with
    ``D = diag(r · sigma)`` and ``T`` the banded Toeplitz matrix ``c_{|i−j|}``. The reference for
    :func:`_accumulate_band`."""
    inv = 1.0 / (error_model[0] * sigma)
    band = error_model[1:]
    m = values.size
    q = np.zeros((band.size, m))
    rhs = np.zeros(m)
    for d in range(band.size):
        if d >= m:
            break
        w = band[d] * inv[: m - d] * inv[d:]
        q[d, : m - d] = w
        rhs[: m - d] += w * values[d:]
        if d > 0:
            rhs[d:] += w * values[: m - d]
    return q, rhs


def error_band_shares(error_model: np.ndarray, widths: list[int]) -> np.ndarray:
    """Variance, per unit ``sigma``², of each moving-average band of a segment's error (bands as
    :mod:`.long_wave` cuts them: ``MA_{w_j} − MA_{w_{j+1}}``, the last ``MA_{w_last}``; odd widths in
    grid points). Empty ``error_model`` (white): ``1/w_j − 1/w_{j+1}`` and ``1/w_last``. With the
    edge's model ``[r, c₀, …]``: ``r² (1/π) ∫₀^π |H_j(ω)|² / P(ω) dω``, ``P`` the band's symbol."""
    if error_model.size == 0:
        out = [1.0 / a - 1.0 / b for a, b in zip(widths[:-1], widths[1:])]
        return np.array(out + [1.0 / widths[-1]])
    key = (error_model.tobytes(), tuple(widths))
    hit = _SHARES.get(key)
    if hit is not None:
        return hit
    if len(_SHARES) > 4096:
        _SHARES.clear()
    _SHARES[key] = out = _model_shares(error_model, widths)
    return out


_SHARES: dict = {}


def _model_shares(error_model: np.ndarray, widths: list[int]) -> np.ndarray:
    w = np.linspace(1e-6, math.pi, 16385)
    sym = np.full(w.size, error_model[1])
    for k in range(2, error_model.size):
        sym += 2.0 * error_model[k] * np.cos((k - 1) * w)
    ma = [np.sin(a * w / 2) / (a * np.sin(w / 2)) for a in widths]  # a centred mean of a points
    gains = [ma[j] - ma[j + 1] for j in range(len(widths) - 1)] + [ma[-1]]
    return np.array([error_model[0] ** 2 * np.trapezoid(g * g / sym, w) / math.pi for g in gains])


@kernel
def _accumulate_band(q, b, cover, passes, lo, values_q, scale, offset, sigma_q, sigma_ref, sigma_scale, error_model,
                     sign, is_pass):
    """:func:`_accumulate` for a segment with its own error model (:func:`segment_band_information`):
    adds ``sign`` times ``D⁻¹ T D⁻¹`` to the rows ``0..p`` of ``q`` and its product with the values to
    ``b``, decoding the wire codes point by point. O(m p)."""
    m = values_q.size
    step = int(sign)
    r = error_model[0]
    p1 = error_model.size - 1
    for i in range(m):
        inv_i = 1.0 / (r * sigma_ref * sigma_scale[-np.int64(sigma_q[i])])
        v_i = offset + scale * np.float64(values_q[i])
        for d in range(min(p1, m - i)):
            j = i + d
            inv_j = 1.0 / (r * sigma_ref * sigma_scale[-np.int64(sigma_q[j])])
            w = error_model[1 + d] * inv_i * inv_j
            q[d, lo + i] += sign * w
            b[lo + i] += sign * (w * (offset + scale * np.float64(values_q[j])))
            if d > 0:
                b[lo + j] += sign * (w * v_i)
    for i in range(lo, lo + m):
        cover[i] += step
        if is_pass:
            passes[i] += step


# -- state ---------------------------------------------------------------------------------------


@dataclass
class _Block:
    start: int  # first grid index
    stop: int  # one past the last
    factor: np.ndarray  # lower banded Cholesky factor of the block's precision
    mean: np.ndarray  # posterior mean (drift marginalised when it is modelled)
    cov_band: np.ndarray  # S[d, i] = Σ[i, i + d] of the profile given the drifts
    mean0: np.ndarray | None = None  # the mean given zero drifts (A_RR⁻¹ b_R)
    drift: DriftPosterior | None = None
    precision: np.ndarray | None = None  # the block's A_RR, lower banded (what the drift eliminates)


@dataclass
class _Posterior:
    tau: float
    blocks: list[_Block]
    snapshot: ProfileSnapshot


class _Route:
    def __init__(self, n: int, tau: float):
        self.q = np.zeros((2, n))  # data precision, lower banded: q[0] diagonal, q[1, i] = Q[i+1, i]
        self.b = np.zeros(n)  # data information vector
        self.cover = np.zeros(n, dtype=np.int64)  # segments covering each point (any axle)
        self.passes = np.zeros(n, dtype=np.int64)  # axle-1 segments covering each point
        self.tau = tau
        self.drift_sd = 0.0  # learnt (or given) per-pass drift sd per knot coefficient (m): the band's
        self.drift_mean_sd = 0.0  # ... and the mean's (<= drift_sd)
        self.posterior: _Posterior | None = None


class GmrfProfile:
    """Exact incremental GMRF posterior of each route's profile (see the module docstring).

    Parameters
    ----------
    routes : dict
        Route id → length (m); each route's grid runs from chainage 0 to its length.
    spacing_m : float
        Grid spacing (m); only segments on this grid are accepted.
    tau : float, optional
        Prior precision of the order-``order`` differences per grid step (1/m²). ``None`` (default)
        learns it per route by empirical Bayes at snapshot time.
    order : {1, 2}
        Random walk order (1: eq. 4.8; 2: penalises curvature, pentadiagonal precision).
    rho : float
        Lag-one correlation of a segment's AP errors between neighbouring grid points, |ρ| < 1.
        :meth:`estimate_rho` measures it from residuals; :meth:`set_rho` changes it.
    ridge : float
        Prior precision of the level (1/m²); vanishing next to the data's.
    max_gap_m : float
        Uncovered gaps up to this length are bridged by the prior; longer ones split the route
        into independently solved blocks with NaN between them.
    tau_init : float, optional
        Starting value when τ is learnt (default :func:`iso8608_tau` for class B).
    tau_tol : float
        Relative tolerance on the learnt τ (each iteration is one factorisation of every block). Tight
        (1e-10: one iteration more than 1e-6 from a cold start), because τ is warm-started from the last
        snapshot's: at 1e-6 where it stopped depended on the run's history (snapshots taken on the way),
        which moved the mean by ~1e-7 of its sd — replays must give the same export.
    max_tau_iter : int
        Iterations allowed for learning τ before settling for the last value (with a warning).
    drift_knot_m : float or None
        Knot spacing (m) of each pass's drift nuisance (:mod:`.pass_drift`), e.g. 25; ``None``
        (default) leaves the drift out (the white/AR(1) model alone, the band's long-wave part then
        comes from :mod:`.long_wave`). Its snapshot cost is linear in the route length and grows
        with the passes *at a point*, n, as O(P · n²) (it is eliminated chunk by chunk between the
        knots): 10 km with 2 passes ~0.5–1 s, 200 m with 30 passes ~0.1–0.2 s on a loaded 2-core machine.
    drift_sd_m : float, optional
        Prior sd of each drift coefficient (m); ``None`` (default) learns it per route at snapshot
        time (0 when the data show no drift): the mean's level by MAP, the band's by type-II maximum
        likelihood or the MAP level, whichever is larger (:mod:`.pass_drift`).
    """

    def __init__(self, routes: dict[str, float], spacing_m: float = 0.05, tau: float | None = None, *,
                 order: int = 1, rho: float = 0.0, ridge: float = 1e-6, max_gap_m: float = 1.0,
                 tau_init: float | None = None, tau_tol: float = 1e-10, max_tau_iter: int = 60,
                 drift_knot_m: float | None = None, drift_sd_m: float | None = None):
        if order not in _DIFF:
            raise ValueError(f"order must be 1 or 2, got {order}")
        if not (spacing_m > 0 and math.isfinite(spacing_m)):
            raise ValueError(f"spacing_m must be finite and > 0, got {spacing_m}")
        if tau is not None and not (tau > 0 and math.isfinite(tau)):
            raise ValueError(f"tau must be finite and > 0, got {tau}")
        if not (ridge > 0 and math.isfinite(ridge)):
            raise ValueError(f"ridge must be finite and > 0, got {ridge}")
        if drift_knot_m is not None and not (drift_knot_m >= spacing_m and math.isfinite(drift_knot_m)):
            raise ValueError(f"drift_knot_m must be finite and >= spacing_m, got {drift_knot_m}")
        if drift_sd_m is not None and not (drift_sd_m >= 0 and math.isfinite(drift_sd_m)):
            raise ValueError(f"drift_sd_m must be finite and >= 0, got {drift_sd_m}")
        self.drift_knot_m = None if drift_knot_m is None else float(drift_knot_m)
        self.drift_sd_m = None if drift_sd_m is None else float(drift_sd_m)
        self.spacing_m = float(spacing_m)
        self.order = order
        self.learn_tau = tau is None
        self.ridge = float(ridge)
        self.max_gap = max(0, int(math.floor(max_gap_m / spacing_m + 1e-9)))
        self.tau_tol = float(tau_tol)
        self.max_tau_iter = max(1, int(max_tau_iter))
        self.rho = self._check_rho(rho)
        t0 = float(tau) if tau is not None else float(tau_init or iso8608_tau(spacing_m, order=order))
        self.routes = {rid: _Route(int(round(length / spacing_m)) + 1, t0) for rid, length in routes.items()}
        self.segments: dict[tuple, ApSegment] = {}  # identity → the segment whose information is in

    @staticmethod
    def _check_rho(rho: float) -> float:
        rho = float(rho)
        if not (abs(rho) < 1.0):
            raise ValueError(f"rho must lie in (-1, 1), got {rho}")
        return rho

    # -- estimator interface ---------------------------------------------------------------------
    def accepts(self, seg: ApSegment) -> bool:
        return seg.route_id in self.routes and abs(seg.spacing_m - self.spacing_m) < 1e-12

    def update(self, seg: ApSegment) -> None:
        """Add a segment's information; a segment with the same identity replaces the earlier one."""
        key = seg.identity
        old = self.segments.get(key)
        if old is not None:
            self._apply(old, -1.0)
        if self._apply(seg, +1.0):
            self.segments[key] = seg
        else:
            self.segments.pop(key, None)

    def retract(self, seg: ApSegment) -> None:
        """Subtract exactly what :meth:`update` added for this segment's identity."""
        old = self.segments.pop(seg.identity, None)
        if old is None:
            log.warning("retract of a segment never added: %s", seg.identity)
            return
        self._apply(old, -1.0)

    def _apply(self, seg: ApSegment, sign: float) -> bool:
        route = self.routes.get(seg.route_id)
        if route is None:
            return False
        lo, hi = seg.start_index, min(seg.end_index, route.cover.size)
        if hi <= lo:
            return False
        m = hi - lo
        if seg.error_model.size:  # the edge's own (banded) error model
            rows = seg.error_model.size - 1
            if rows > route.q.shape[0]:  # widen the route's band (zero rows until a segment fills them)
                route.q = np.concatenate([route.q, np.zeros((rows - route.q.shape[0], route.q.shape[1]))])
            _accumulate_band(route.q, route.b, route.cover, route.passes, lo, seg.values_q[:m], seg.scale_m,
                             seg.offset_m, seg.sigma_q[:m], seg.sigma_ref_m, SIGMA_SCALE, seg.error_model, sign,
                             seg.axle == 1)
        else:
            _accumulate(route.q, route.b, route.cover, route.passes, lo, seg.values_q[:m], seg.scale_m, seg.offset_m,
                        seg.sigma_q[:m], seg.sigma_ref_m, SIGMA_SCALE, self.rho, sign, seg.axle == 1)
        route.posterior = None
        return True

    def snapshot(self, route_id: str | None = None) -> dict[str, ProfileSnapshot]:
        """Posterior mean, 95 % band (mean ± 1.96 sd) and pass count per grid point of each route."""
        return {rid: self._posterior(rid).snapshot for rid in self.routes if route_id in (None, rid)}

    # -- more than the interface -----------------------------------------------------------------
    @property
    def tau(self) -> dict[str, float]:
        """Current prior precision per route (1/m²): the given one, or the last learnt."""
        return {rid: r.tau for rid, r in self.routes.items()}

    @property
    def drift_sd(self) -> dict[str, float]:
        """Per-pass drift sd per knot coefficient (m) of each route's last posterior (0: none): the level
        its band and draws hold. The mean is taken at :attr:`drift_mean_sd`, the level a half-normal
        prior scaled to the passes' stated error and the evidence support, which is this level or less."""
        return {rid: r.drift_sd for rid, r in self.routes.items()}

    @property
    def drift_mean_sd(self) -> dict[str, float]:
        """Per-pass drift sd per knot coefficient (m) each route's last posterior mean is taken at."""
        return {rid: r.drift_mean_sd for rid, r in self.routes.items()}

    def sample(self, route_id: str, n: int, rng: np.random.Generator | int | None = None) -> np.ndarray:
        """``n`` draws from the posterior of a route's profile, shape (n, P), NaN outside covered blocks."""
        post = self._posterior(route_id)
        rng = np.random.default_rng(rng)
        n = int(n)
        out = np.empty((n, self.routes[route_id].cover.size))  # filled in place: draws are big
        done = 0
        for blk in post.blocks:
            out[:, done : blk.start] = np.nan
            for r in range(n):
                rng.standard_normal(out=out[r, blk.start : blk.stop])
            if blk.drift is None:
                draw_into(blk.factor, blk.mean, out[:, blk.start : blk.stop])
            else:  # R = A_RR⁻¹ b_R − W β + L⁻ᵀ z, β drawn from its marginal posterior
                draw_into(blk.factor, blk.mean0, out[:, blk.start : blk.stop])
                out[:, blk.start : blk.stop] += blk.drift.draw_shift(rng.standard_normal((n, blk.drift.n_coefficients)))
            done = blk.stop
        out[:, done:] = np.nan
        return out

    def information(self, route_id: str, tau: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The full route's precision (lower banded, (b + 1, P)) and information vector, prior included.

        ``tau`` defaults to the route's current τ. For checks and references, not the hot path.
        """
        route = self.routes[route_id]
        t = route.tau if tau is None else tau
        n = route.cover.size
        u = max(self.order, route.q.shape[0] - 1)
        ab = np.zeros((u + 1, n))
        ab[: self.order + 1] += t * difference_precision(n, self.order)
        ab[: route.q.shape[0]] += route.q
        ab[0] += self.ridge
        return ab, route.b.copy()

    def set_rho(self, rho: float) -> None:
        """Change the AR(1) error correlation and rebuild every contribution from the held segments."""
        rho = self._check_rho(rho)
        if rho == self.rho:
            return
        for route in self.routes.values():  # rebuild from exact zeros, not from rounding residue
            route.q[:] = 0.0
            route.b[:] = 0.0
            route.cover[:] = 0
            route.passes[:] = 0
            route.posterior = None
        self.rho = rho
        for seg in self.segments.values():
            self._apply(seg, +1.0)

    def estimate_rho(self, route_id: str | None = None) -> float:
        """Pooled lag-one autocorrelation of the held segments' standardised residuals against the mean.

        Residuals include the posterior mean's own error, which is smooth, so with few passes this
        overestimates ρ; it is meant to be measured once with many passes and then set with
        :meth:`set_rho`. Returns 0 when there is nothing to measure.
        """
        num = den = 0.0
        means = {}
        for seg in self.segments.values():
            if route_id is not None and seg.route_id != route_id:
                continue
            if seg.route_id not in means:
                means[seg.route_id] = self.snapshot(seg.route_id)[seg.route_id].elevation_m
            mu = means[seg.route_id]
            lo, hi = seg.start_index, min(seg.end_index, mu.size)
            if hi - lo < 2:
                continue
            e = (seg.values[: hi - lo] - mu[lo:hi]) / seg.sigma[: hi - lo]
            e = e[np.isfinite(e)]
            e = e - e.mean()
            num += float(np.dot(e[:-1], e[1:]))
            den += float(np.dot(e, e))
        return num / den if den > 0 else 0.0

    # -- posterior ------------------------------------------------------------------------------
    def _blocks(self, route: _Route) -> list[tuple[int, int]]:
        covered = np.flatnonzero(route.cover > 0)
        if covered.size == 0:
            return []
        breaks = np.flatnonzero(np.diff(covered) > self.max_gap + 1)
        starts = np.concatenate([[covered[0]], covered[breaks + 1]])
        stops = np.concatenate([covered[breaks], [covered[-1]]]) + 1
        return list(zip(starts.tolist(), stops.tolist()))

    def _solve(self, route: _Route, spans: list[tuple[int, int]], tau: float) -> tuple[list[_Block], float, int]:
        """Factorise and solve every block at ``tau``; also return the EM statistic and the rank."""
        blocks, stat, rank = [], 0.0, 0
        u = max(self.order, route.q.shape[0] - 1)
        for a, e in spans:
            m = e - a
            A = difference_precision(m, self.order)
            ab = np.zeros((u + 1, m))
            ab[: self.order + 1] = tau * A
            ab[0] += route.q[0, a:e] + self.ridge
            for d in range(1, min(route.q.shape[0], m)):  # the coupling past the block is not ours
                ab[d, : m - d] += route.q[d, a : e - d]
            cb = cholesky_banded(ab, lower=True, check_finite=False)
            mean = cho_solve_banded((cb, True), route.b[a:e], check_finite=False)
            S = selected_inverse(cb)
            blocks.append(_Block(a, e, cb, mean, S, precision=ab))
            if m > self.order:
                # Sums, not np.dot: a long BLAS dot runs multi-threaded, and on a loaded machine its
                # thread hand-off costs milliseconds per call whatever the length, which makes the
                # snapshot superlinear in the route length.
                d = np.diff(mean, n=self.order)
                tr = float((A[0] * S[0]).sum()) + 2.0 * sum(float((A[k] * S[k]).sum()) for k in range(1, self.order + 1))
                stat += float((d * d).sum()) + tr
                rank += m - self.order
        return blocks, stat, rank

    def _learn_tau(self, route: _Route, spans: list[tuple[int, int]]) -> tuple[list[_Block], float]:
        """Solve the score equation ``log τ = log(rank / stat(τ))`` by secant steps on log τ."""
        lo, hi = math.log(TAU_BOUNDS[0]), math.log(TAU_BOUNDS[1])

        def em(u):
            blocks, stat, rank = self._solve(route, spans, math.exp(u))
            if rank == 0 or stat <= 0.0:
                return blocks, 0.0
            return blocks, min(max(math.log(rank / stat), lo), hi) - u

        u0 = min(max(math.log(route.tau), lo), hi)
        blocks, h0 = em(u0)
        if abs(h0) <= self.tau_tol:
            return blocks, math.exp(u0)
        u1, h1 = min(max(u0 + h0, lo), hi), h0  # one EM step, then secant on h(u) = EM(u) − u
        for _ in range(self.max_tau_iter):
            blocks, h1 = em(u1)
            if abs(h1) <= self.tau_tol or (u1 <= lo and h1 < 0) or (u1 >= hi and h1 > 0):
                return blocks, math.exp(u1)
            step = h1 if h1 == h0 else -h1 * (u1 - u0) / (h1 - h0)
            if not math.isfinite(step) or step * h1 <= 0:  # the secant points the wrong way: EM step
                step = h1
            step = min(max(step, -3.0), 3.0)
            u0, h0, u1 = u1, h1, min(max(u1 + step, lo), hi)
        log.warning("tau did not converge in %d iterations (last change %.2e)", self.max_tau_iter, h1)
        return blocks, math.exp(u1)

    def _segment_information(self, seg: ApSegment, m: int) -> tuple[np.ndarray, np.ndarray]:
        """A segment's ``Hᵀ R⁻¹ H`` (lower banded: row d holds ``Q[t + d, t]``) and ``Hᵀ R⁻¹ y`` on its
        first ``m`` points: what :meth:`_apply` adds (the edge's error model when it carries one)."""
        if seg.error_model.size:
            return segment_band_information(seg.values[:m], seg.sigma[:m], seg.error_model)
        diag, off, rhs = segment_information(seg.values[:m], seg.sigma[:m], self.rho)
        return np.stack([diag, np.append(off, 0.0)]), rhs

    def _marginalise_drift(self, route_id: str, route: _Route, blocks: list[_Block]) -> list[np.ndarray]:
        """Eliminate each block's per-pass drifts (learning their level); the drift variance per point.

        τ is the one learnt without the drifts: they live at wavelengths of twice the knot spacing
        and more, where the random walk's increments carry next to no weight.
        """
        zero = [np.zeros(blk.stop - blk.start) for blk in blocks]
        if self.drift_knot_m is None or not blocks:
            route.drift_sd = route.drift_mean_sd = 0.0
            return zero
        segs = [s for s in self.segments.values() if s.route_id == route_id]
        n = route.cover.size
        posts = []
        for blk in blocks:
            system = drift_system(segs, blk.start, blk.stop, n, self.spacing_m, self.drift_knot_m,
                                  self._segment_information)
            posts.append(eliminate(blk.precision, blk.factor, route.b[blk.start : blk.stop], system,
                                   self.drift_knot_m / self.spacing_m, blk.start))
        if self.drift_sd_m is not None:
            s2 = spread = self.drift_sd_m**2
        else:
            # The mean at the level the prior and the evidence support; the band at the larger of that
            # and the evidence's own maximum, so that a level the passes leave uncertain moves the
            # mean toward the better supported one without narrowing the band.
            s2 = learn_drift_variance(posts, prior_sd=DRIFT_PRIOR_SCALE * stated_error_sd(segs) or None)
            spread = max(s2, learn_drift_variance(posts))
        route.drift_sd = math.sqrt(spread)
        route.drift_mean_sd = math.sqrt(s2)
        out = []
        for blk, d in zip(blocks, posts):
            d.set_level(s2, spread)
            blk.mean0, blk.drift = blk.mean, d
            blk.mean = blk.mean0 + d.profile_shift()
            out.append(d.profile_variance())
        return out

    def _posterior(self, route_id: str) -> _Posterior:
        route = self.routes[route_id]
        if route.posterior is not None:
            return route.posterior
        spans = self._blocks(route)
        if self.learn_tau and spans:
            blocks, tau = self._learn_tau(route, spans)
            route.tau = tau
        else:
            blocks, _, _ = self._solve(route, spans, route.tau)
        var_drift = self._marginalise_drift(route_id, route, blocks)
        n = route.cover.size
        mean = np.full(n, np.nan)
        sd = np.full(n, np.nan)
        for blk, vd in zip(blocks, var_drift):
            mean[blk.start : blk.stop] = blk.mean
            sd[blk.start : blk.stop] = np.sqrt(blk.cov_band[0] + vd)
        x = np.arange(n) * self.spacing_m
        snap = ProfileSnapshot(route_id, x, mean, mean - _Z95 * sd, mean + _Z95 * sd, route.passes.copy())
        route.posterior = _Posterior(route.tau, blocks, snap)
        return route.posterior
