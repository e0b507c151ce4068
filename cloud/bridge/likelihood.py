"""Bridge stiffness and vehicle weights from passes' APs: the model of a pass and its likelihood.

Model of one pass p (vehicle v, speed v_p) over the window, in AP units (m, up positive)::

    ρ_p(x) = AP_p(x) − consensus(x) = μ(x) + s_p(x) − W_v · (1 + φ_p(x)) · J(x; θ) − W_v·ε_p(x) + e_p(x)

* ``J(x; θ)`` (m/N) — the deflection under a unit wheel load at x (the moving-reference
  influence line), zero off the span; for a simply supported span ``J = Σ_z G_z(x)/EI_z``
  (unit-load theorem, :func:`shared.fe.beam.compliance_kernel`), linear in the compliances.
  Every J is carried in a cubic B-spline basis with knots at the element nodes
  (:class:`~cloud.bridge.basis.SpanBasis`, relative error < 2e-4), ``J = Σ_j a_j ψ_j``.
* ``1 + φ_p`` — the dynamic wheel load over the static one, from the vehicle's calibrated ratios
  (:class:`~cloud.bridge.passdata.VehicleFilter`) driven over the fleet's consensus road and its own
  deflection — not the pass's own AP, whose noise it would carry
  (:func:`~cloud.bridge.passdata.road_load_factor`); on a bridge entrance it
  swings by ±10 %, so it is part of the model, not of the noise.
* ``ε_p`` — the bridge's own dynamics (:mod:`cloud.bridge.dynamic`), zero in the quasi-static model.
* ``s_p(x)`` — on a smooth deck (where the consensus is taken as 0 on the span) the consensus'
  drift-control trend shows as a step of up to millimetres at the supports; it differs between
  passes by a few per cent, so each pass has its own cubic on the span (``{1, ξ, ξ², ξ³}``,
  values and slopes at both supports), projected out of its likelihood. A quadratic would leave an
  antisymmetric error that reads as a stiffness gradient along the span (of about ±6 %).
* ``μ(x)`` — on a rough deck the consensus holds the fleet-mean deflection: a common unknown
  shape on the span (basis ``{ψ_j}``), estimated with the rest.
* the fleet-common calibration error δ_c (:mod:`cloud.bridge.vehicle_error`): one coefficient per
  calibration quantity shared by every pass, its columns the pass's AP distortion less the
  consensus'; carried as further coordinates of μ with their own prior (``mu_precision``).
* ``W_v`` — the vehicle's static wheel load (N), prior ``N(W̄, s_W²)`` from its class: W̄ fixes the
  scale between loads and compliances (thesis §4.5.5).

AP errors are far from white (twice-integrated sensor noise), so each pass is compared in the
measured-channel domain (:mod:`cloud.bridge.whitening`): everything above goes through the vehicle's
forward model F_p (:meth:`~cloud.bridge.passdata.VehicleFilter.whiten`), where sensor noise is white;
F_p annihilates offsets, slopes and (to O(ω²)) the drift-control trend. The result is band-limited
to ``BAND_HZ`` and decimated (the model is trusted, and the deflection's information lives,
below ~10 Hz), then prewhitened by an AR model of the pass's own residual on the approach, whose
level — read in the band of the pass's element directions, as they would see it on new data —
gives the pass's noise sd. At 2 % sensor noise one pass pins the global compliance to ≈ 27 % (1σ),
so the information grows as 27 %/√passes.

Inference: the weights enter linearly given J, so they are integrated out analytically, vehicle by
vehicle (a pass shares W_v with the vehicle's other passes). What remains is a smooth
log-posterior in the stiffness parameters and μ, maximised by Newton's method; the Laplace
approximation gives 95 % intervals and the evidence (:mod:`cloud.bridge.posterior`). Integrating W
(rather than maximising over it) matters: the joint mode over (θ, W) is biased by ≈ s_W²/W̄² ≈ 1 % in
the global scale.

All data reduce to small per-vehicle sufficient statistics (:class:`VehicleStats`), so a fit costs
O(vehicles × basis²), independent of the record lengths.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from cloud.bridge.basis import MU_PRIOR_SD_M
from cloud.bridge.whitening import WhitenedPass

# ---------------------------------------------------------------------------------------------
# Sufficient statistics


@dataclasses.dataclass(frozen=True, eq=False)
class VehicleStats:
    """Sums over one vehicle's passes of the products of its whitened columns.

    With ``h = Ψa + δ`` (δ: the dynamic correction column, zero when quasi-static)::

        A = ΣΨᵀΨ, e = ΣΨᵀδ, f = Σδᵀδ, Pw = ΣΨᵀw, Pb = ΣΨᵀB, dw = Σδᵀw, db = ΣBᵀδ,
        Bw = ΣBᵀw, BB = ΣBᵀB, ww = Σwᵀw, n = number of points, passes = number of passes.
    """

    vehicle_id: str
    A: np.ndarray
    e: np.ndarray
    f: float
    Pw: np.ndarray
    Pb: np.ndarray
    dw: float
    db: np.ndarray
    Bw: np.ndarray
    BB: np.ndarray
    ww: float
    n: int
    passes: int
    mu_precision: np.ndarray | None = None  # prior precision of μ (see :class:`~cloud.bridge.whitening.WhitenedPass`)

    @classmethod
    def of_pass(cls, wp: WhitenedPass, delta: np.ndarray | None = None) -> "VehicleStats":
        P, B, w = wp.Psi, wp.B, wp.w
        d = np.zeros(w.size) if delta is None else np.asarray(delta, dtype=float)
        return cls(wp.vehicle_id, P.T @ P, P.T @ d, float(d @ d), P.T @ w, P.T @ B, float(d @ w), B.T @ d,
                   B.T @ w, B.T @ B, float(w @ w), int(w.size), 1, wp.mu_precision)

    def __add__(self, other: "VehicleStats") -> "VehicleStats":
        if other.vehicle_id != self.vehicle_id:
            raise ValueError("VehicleStats: adding statistics of different vehicles")
        return VehicleStats(self.vehicle_id, self.A + other.A, self.e + other.e, self.f + other.f,
                            self.Pw + other.Pw, self.Pb + other.Pb, self.dw + other.dw, self.db + other.db,
                            self.Bw + other.Bw, self.BB + other.BB, self.ww + other.ww, self.n + other.n,
                            self.passes + other.passes, self.mu_precision)


def vehicle_stats(passes: Sequence[WhitenedPass], deltas: dict[str, np.ndarray] | None = None) -> list[VehicleStats]:
    """Per-vehicle sums of :meth:`VehicleStats.of_pass` (``deltas``: pass_id → whitened δ column)."""
    out: dict[str, VehicleStats] = {}
    for wp in passes:
        s = VehicleStats.of_pass(wp, None if deltas is None else deltas.get(wp.pass_id))
        out[wp.vehicle_id] = out[wp.vehicle_id] + s if wp.vehicle_id in out else s
    return list(out.values())


@dataclasses.dataclass(frozen=True, eq=False)
class Stacked:
    """:class:`VehicleStats` of all vehicles stacked along a leading axis, with each one's weight prior."""

    ids: tuple[str, ...]
    A: np.ndarray
    e: np.ndarray
    f: np.ndarray
    Pw: np.ndarray
    Pb: np.ndarray
    dw: np.ndarray
    db: np.ndarray
    Bw: np.ndarray
    BB: np.ndarray
    ww: np.ndarray
    w_mean: np.ndarray  # prior mean wheel load per vehicle, N
    w_sd: np.ndarray  # prior sd, N
    n: int
    passes: int
    q_mu: np.ndarray | None = None  # prior precision of every μ coordinate (default 1/MU_PRIOR_SD_M²)

    @classmethod
    def of(cls, stats: Sequence[VehicleStats], prior: Callable[[str], tuple[float, float]]) -> "Stacked":
        if not stats:
            raise ValueError("no passes")
        pri = np.array([prior(s.vehicle_id) for s in stats], dtype=float)
        st = lambda name: np.array([getattr(s, name) for s in stats])  # noqa: E731
        nm = np.shape(stats[0].Bw)[0]
        q = stats[0].mu_precision
        q = np.full(nm, 1.0 / MU_PRIOR_SD_M**2) if q is None else np.asarray(q, dtype=float)
        if q.shape != (nm,):
            raise ValueError(f"mu_precision: {q.shape} for {nm} common nuisance columns")
        return cls(tuple(s.vehicle_id for s in stats), st("A"), st("e"), st("f"), st("Pw"), st("Pb"), st("dw"),
                   st("db"), st("Bw"), st("BB"), st("ww"), pri[:, 0], pri[:, 1], int(sum(s.n for s in stats)),
                   int(sum(s.passes for s in stats)), q)


@dataclasses.dataclass(frozen=True)
class WeightPrior:
    """Prior of static wheel loads: ``(mean, sd)`` N per vehicle, by default the class's."""

    mean_n: float
    sd_n: float
    per_vehicle: tuple[tuple[str, float, float], ...] = ()
    #: the class's log-sd of each calibration quantity, (name, sd): the scale of the fleet-common
    #: calibration error (:class:`~cloud.bridge.estimator.BridgeSettings`); empty: not known
    class_log_sd: tuple[tuple[str, float], ...] = ()

    def __call__(self, vehicle_id: str) -> tuple[float, float]:
        for vid, m, s in self.per_vehicle:
            if vid == vehicle_id:
                return m, s
        return self.mean_n, self.sd_n


# ---------------------------------------------------------------------------------------------
# The weight-marginalised log-likelihood in basis coefficients a and nuisance μ


class Terms(dict):
    """Value, gradients and Hessian blocks of the marginal log-likelihood (a dict for brevity)."""


def marginal_loglik(S: Stacked, a: np.ndarray, mu: np.ndarray, derivatives: bool = True) -> Terms:
    """log p(data | a, μ) with every vehicle's wheel load integrated over its prior.

    Per vehicle, with λ = hᵀh + 1/s², g = hᵀρ, u = W̄/s² − g, m = u/λ (the weight's conditional
    posterior mean, N) and 1/λ its variance::

        ℓ = −½‖ρ‖² + ½u²/λ − ½W̄²/s² − ½ log(λ s²)

    Returns ``value``, ``m``, ``var`` and, with ``derivatives``, ``ga``, ``gm`` (gradients) and
    ``Haa``, ``Hmm``, ``Hma`` (Hessian blocks), all summed over vehicles.
    """
    inv_s2 = 1.0 / S.w_sd**2
    r = S.A @ a + S.e  # (V, nb)
    lam = r @ a + S.e @ a + S.f + inv_s2
    q = S.Pw - S.Pb @ mu  # (V, nb)
    t = np.einsum("vbm,b->vm", S.Pb, a) + S.db  # (V, nm)
    g = q @ a + S.dw - S.db @ mu
    u = S.w_mean * inv_s2 - g
    m = u / lam
    rr = S.ww - 2.0 * (S.Bw @ mu) + np.einsum("m,vmn,n->v", mu, S.BB, mu)
    val = float(np.sum(-0.5 * rr + 0.5 * u * m - 0.5 * S.w_mean**2 * inv_s2 - 0.5 * np.log(lam / inv_s2)))
    out = Terms(value=val, m=m, var=1.0 / lam)
    if not derivatives:
        return out
    ew2 = m * m + 1.0 / lam  # E[W²]
    out["ga"] = np.sum(-m[:, None] * q - ew2[:, None] * r, axis=0)
    out["gm"] = np.sum(S.Bw - np.einsum("vmn,n->vm", S.BB, mu) + m[:, None] * t, axis=0)
    k = q + 2.0 * m[:, None] * r  # (V, nb)
    out["Haa"] = (np.einsum("vi,vj,v->ij", k, k, 1.0 / lam) + 2.0 * np.einsum("vi,vj,v->ij", r, r, 1.0 / lam**2)
                  - np.einsum("v,vij->ij", ew2, S.A))
    out["Hmm"] = -S.BB.sum(axis=0) + np.einsum("vi,vj,v->ij", t, t, 1.0 / lam)
    out["Hma"] = -np.einsum("vm,vb,v->mb", t, k, 1.0 / lam) + np.einsum("v,vbm->mb", m, S.Pb)
    # dm/da and dm/dμ, for the weights' uncertainty propagation.
    out["dm_da"] = -k / lam[:, None]
    out["dm_dmu"] = t / lam[:, None]
    return out


def marginal_loglik_batch(S: Stacked, a: np.ndarray, delta_scale: np.ndarray | None = None,
                          chunk: int = 512) -> np.ndarray:
    """log p(data | a) for a batch of coefficient vectors ``a`` (K, n_b): weights *and* μ integrated.

    μ has the prior N(0, diag(1/S.q_mu)) and enters the weight-marginal log-likelihood
    quadratically, so its integral is exact. ``delta_scale`` (K,) multiplies the dynamic
    correction column of every pass (ε scales with the compliance). Returns (K,).
    """
    a = np.atleast_2d(np.asarray(a, dtype=float))
    K = a.shape[0]
    ds = np.ones(K) if delta_scale is None else np.asarray(delta_scale, dtype=float)
    nm = S.Bw.shape[1]
    q_mu = S.q_mu
    inv_s2 = 1.0 / S.w_sd**2
    out = np.empty(K)
    for lo in range(0, K, chunk):
        ak, dk = a[lo : lo + chunk], ds[lo : lo + chunk]
        Aa = np.matmul(ak[None], S.A)  # (V, k, nb), batched BLAS
        lam = (np.sum(Aa * ak[None], axis=2).T + 2 * dk[:, None] * (ak @ S.e.T) + dk[:, None] ** 2 * S.f[None, :]
               + inv_s2[None, :])  # (k, V)
        t = np.matmul(ak[None], S.Pb).transpose(1, 0, 2) + dk[:, None, None] * S.db[None, :, :]  # (k, V, nm)
        u0 = S.w_mean * inv_s2 - (ak @ S.Pw.T) - dk[:, None] * S.dw[None, :]  # (k, V)
        H = S.BB.sum(axis=0)[None] - np.matmul(t.transpose(0, 2, 1) / lam[:, None, :], t) + np.diag(q_mu)[None]
        b = S.Bw.sum(axis=0)[None] + np.matmul((u0 / lam)[:, None, :], t)[:, 0, :]
        c0 = np.sum(-0.5 * S.ww[None] + 0.5 * u0**2 / lam - 0.5 * S.w_mean[None] ** 2 * inv_s2[None]
                    - 0.5 * np.log(lam / inv_s2[None]), axis=1)
        sol = np.linalg.solve(H, b[:, :, None])[:, :, 0]
        _, logdet = np.linalg.slogdet(H)
        out[lo : lo + chunk] = (c0 + 0.5 * np.einsum("km,km->k", b, sol) - 0.5 * logdet
                                + 0.5 * float(np.sum(np.log(q_mu))))
    return out
