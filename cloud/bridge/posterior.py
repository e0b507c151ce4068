"""The Laplace posterior of a span's element stiffnesses, with μ, the vehicles' wheel loads and the prior's
departure scale integrated out."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import numpy as np

from cloud.bridge.likelihood import Stacked, VehicleStats, WeightPrior, marginal_loglik
from cloud.bridge.stiffness import BearingElementModel, ElementModel, StiffnessPrior, design_influence


@dataclasses.dataclass(frozen=True, eq=False)
class ElementPosterior:
    """Laplace posterior of the element stiffnesses (and the vehicles' wheel loads).

    ``theta``/``cov``: mode and covariance of log(EI/EI_design) per element; ``weights``: vehicle →
    (mean, sd) of its static wheel load, N; ``log_evidence``: Laplace approximation of
    log p(data) under the prior (nuisance μ integrated); ``chi2_per_point``: mean squared
    whitened residual at the mode (≈ 1 when the noise model is right; the covariance is widened by
    it when above 1). ``effective_ratio``: area under the design influence line over the area
    under the estimated one — the well-determined global stiffness (the ends of a span barely
    affect any deflection, so a plain mean over elements is dominated by prior-driven elements);
    with bearings it includes their restraint (relative to the pinned design span).
    ``krot``: bearings' log10 Krot (mean, lo95, hi95) per support, when modelled.
    """

    theta: np.ndarray
    cov: np.ndarray
    ei_design: float
    element_bounds: np.ndarray
    weights: dict[str, tuple[float, float]]
    mu: np.ndarray
    log_evidence: float
    chi2_per_point: float
    n_passes: int
    n_vehicles: int
    iterations: int
    effective_ratio: float = float("nan")
    effective_ratio_sd: float = float("nan")
    krot: tuple[tuple[float, float, float], ...] | None = None  # per support: log10 Krot (mean, lo95, hi95)
    params: np.ndarray | None = None
    #: the departure scale τ of the stiffness prior
    #: (:attr:`~cloud.bridge.stiffness.StiffnessPrior.scales`): its posterior weight per τ (empty: fixed at 1)
    scale_weights: tuple[tuple[float, float], ...] = ()

    @property
    def departure_scale(self) -> float:
        """Posterior mean of log τ, as τ (1.0 when τ was fixed)."""
        if not self.scale_weights:
            return 1.0
        return float(math.exp(sum(w * math.log(t) for t, w in self.scale_weights)))

    @property
    def sd(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    @property
    def ei_mean(self) -> np.ndarray:
        """Posterior mean of EI per element (log-normal), N·m²."""
        return self.ei_design * np.exp(self.theta + 0.5 * self.sd**2)

    @property
    def ei_lo95(self) -> np.ndarray:
        return self.ei_design * np.exp(self.theta - 1.96 * self.sd)

    @property
    def ei_hi95(self) -> np.ndarray:
        return self.ei_design * np.exp(self.theta + 1.96 * self.sd)

    @property
    def stiffness_ratio(self) -> np.ndarray:
        """EI_mean / EI_design per element."""
        return self.ei_mean / self.ei_design

    def mean_ratio(self) -> tuple[float, float]:
        """Span-mean stiffness ratio exp(mean θ) and the sd of mean θ (≈ relative sd)."""
        n = self.theta.size
        return float(np.exp(self.theta.mean())), float(math.sqrt(np.sum(self.cov) / n**2))

    def rows(self, bridge_id: str) -> list[dict]:
        """Rows of ``bridge_elements.parquet`` (interfaces.md §3)."""
        return [dict(bridge_id=bridge_id, element=i + 1, x_start_m=float(b[0]), x_end_m=float(b[1]),
                     EI_mean=float(m), EI_lo95=float(lo), EI_hi95=float(hi), stiffness_ratio=float(r))
                for i, (b, m, lo, hi, r) in enumerate(zip(self.element_bounds, self.ei_mean, self.ei_lo95,
                                                          self.ei_hi95, self.stiffness_ratio))]


def _newton(fun: Callable[[np.ndarray], tuple[float, np.ndarray, np.ndarray]], x0: np.ndarray,
            max_iter: int = 60, tol: float = 1e-9, max_step: float = 0.5,
            max_step_dims: int = 0) -> tuple[np.ndarray, int]:
    """Maximise ``fun`` (value, gradient, Hessian) by damped Newton steps with backtracking.

    Steps are shortened so that none of the first ``max_step_dims`` coordinates moves by more
    than ``max_step`` (log-stiffness: a factor e^0.5 per iteration at most).
    """
    x = x0.copy()
    val, g, H = fun(x)
    for it in range(1, max_iter + 1):
        damp = 0.0
        scale = np.maximum(np.abs(np.diag(H)), 1e-12)
        while True:
            Hd = -H + damp * np.diag(scale)
            try:
                L = np.linalg.cholesky(Hd)
                break
            except np.linalg.LinAlgError:
                damp = max(2 * damp, 1e-6)
        step = np.linalg.solve(L.T, np.linalg.solve(L, g))
        big = np.max(np.abs(step[:max_step_dims])) if max_step_dims else 0.0
        t = min(1.0, max_step / big) if big > 0 else 1.0
        while True:
            cand = x + t * step
            with np.errstate(all="ignore"):
                v2, g2, H2 = fun(cand)
            if (np.isfinite(v2) and v2 >= val - 1e-10 * abs(val)) or t < 1e-8:
                break
            t *= 0.5
        if not np.isfinite(v2):
            return x, it
        x, decrease = cand, v2 - val
        val, g, H = v2, g2, H2
        if abs(decrease) < tol * max(1.0, abs(val)) and float(g @ step) < 1e-6:
            return x, it
    return x, max_iter


def fit_elements(stats: Sequence[VehicleStats], model: "ElementModel | BearingElementModel",
                 weight_prior: WeightPrior, theta0: np.ndarray | None = None) -> ElementPosterior:
    """Laplace posterior of the model's parameters (θ = log EI/EI_design per element, and
    log10 Krot for bearings) with μ and the vehicles' weights integrated out; with
    :attr:`~cloud.bridge.stiffness.StiffnessPrior.scales`, the prior's departure scale integrated out too
    (:func:`fit_elements_per_scale`, :func:`mix_scales`)."""
    return mix_scales(fit_elements_per_scale(stats, model, weight_prior, theta0), model.prior)


def fit_elements_per_scale(stats: Sequence[VehicleStats], model: "ElementModel | BearingElementModel",
                           weight_prior: WeightPrior, theta0: np.ndarray | None = None) -> list[ElementPosterior]:
    """One Laplace posterior per departure scale τ of :attr:`~cloud.bridge.stiffness.StiffnessPrior.scales`
    (one, at the prior as it stands, when there are none). A fit costs milliseconds: the data are reduced to
    per-vehicle statistics once."""
    S = Stacked.of(stats, weight_prior)
    scales = model.prior.scales
    if not scales:
        return [_fit_elements(S, model, theta0)]
    return [_fit_elements(S, dataclasses.replace(model, prior=model.prior.scaled(t)), theta0) for t in scales]


def mix_scales(fits: Sequence[ElementPosterior], prior: StiffnessPrior) -> ElementPosterior:
    """The posterior with the departure scale τ integrated out: the fits at each τ of
    ``prior.scales`` weighted by evidence × hyperprior (log τ ~ N(0, ``scale_sd``²) on the grid),
    moment-matched in θ — the mean, and a covariance that includes the spread between the fits
    (the bands widen when the data cannot tell the scales apart). The other fields are the most
    probable τ's; the result's ``log_evidence`` is the mixture's."""
    if len(fits) == 1:
        return fits[0]
    scales = np.asarray(prior.scales, dtype=float)
    log_z = np.array([f.log_evidence for f in fits], dtype=float)
    log_h = -0.5 * (np.log(scales) / prior.scale_sd) ** 2 if prior.scale_sd else np.zeros(scales.size)
    log_h -= np.log(np.sum(np.exp(log_h)))
    lp = log_z + log_h
    w = np.exp(lp - lp.max())
    log_ev = float(lp.max() + math.log(w.sum()))
    w /= w.sum()
    best = fits[int(np.argmax(w))]
    thetas = np.array([f.theta for f in fits])
    theta = w @ thetas
    dev = thetas - theta
    cov = np.einsum("k,kij->ij", w, np.array([f.cov for f in fits])) + (dev.T * w) @ dev
    params = np.array(best.params, dtype=float)
    params[: theta.size] = theta
    effs = np.array([f.effective_ratio for f in fits])
    eff = float(w @ effs)
    eff_sd = float(math.sqrt(w @ (np.array([f.effective_ratio_sd for f in fits]) ** 2 + (effs - eff) ** 2)))
    return dataclasses.replace(best, theta=theta, cov=cov, params=params, log_evidence=log_ev,
                               effective_ratio=eff, effective_ratio_sd=eff_sd,
                               scale_weights=tuple((float(t), float(v)) for t, v in zip(scales, w)))


def _fit_elements(S: "Stacked", model, theta0: np.ndarray | None) -> ElementPosterior:
    """:func:`fit_elements` at the model's prior as it stands (τ fixed)."""
    npar, nm = model.n, S.Bw.shape[1]
    ne = model.n_elements
    Q, m0 = model.prior_precision(), model.prior_mean()
    q_mu = S.q_mu  # (nm,)

    def fun(z):
        par, mu = z[:npar], z[npar:]
        a, Ja, d2 = model.a_jac(par)
        T = marginal_loglik(S, a, mu)
        gp = Ja.T @ T["ga"]
        H_pp = Ja.T @ T["Haa"] @ Ja + np.diag(d2.T @ T["ga"]) - Q
        H_mp = T["Hma"] @ Ja
        g = np.r_[gp - Q @ (par - m0), T["gm"] - q_mu * mu]
        H = np.block([[H_pp, H_mp.T], [H_mp, T["Hmm"] - np.diag(q_mu)]])
        val = T["value"] - 0.5 * (par - m0) @ Q @ (par - m0) - 0.5 * mu @ (q_mu * mu)
        return val, g, H

    z0 = np.r_[m0, np.zeros(nm)]
    if theta0 is not None:
        z0[: len(theta0)] = theta0
    z, iters = _newton(fun, z0, max_step_dims=npar)
    val, g, H = fun(z)
    par, mu = z[:npar], z[npar:]
    a, Ja, _ = model.a_jac(par)
    T = marginal_loglik(S, a, mu)
    chi2 = _chi2(S, a, mu, T["m"])
    # Residuals a little larger than the noise model says (consensus noise, model error): widen.
    cov_full = np.linalg.inv(-H) * max(1.0, chi2)
    # Weights: conditional variance plus the propagated uncertainty of (θ, μ).
    J_w = np.hstack([T["dm_da"] @ Ja, T["dm_dmu"]])  # (V, npar + nm)
    var_w = T["var"] + np.einsum("vi,ij,vj->v", J_w, cov_full, J_w)
    weights = {vid: (float(m), float(math.sqrt(v))) for vid, m, v in zip(S.ids, T["m"], var_w)}
    # Laplace evidence with normalised Gaussian priors.
    _, logdet_H = np.linalg.slogdet(-H)
    _, logdet_Q = np.linalg.slogdet(Q)
    log_ev = (val + 0.5 * (npar + nm) * math.log(2 * math.pi) - 0.5 * logdet_H
              + 0.5 * logdet_Q - 0.5 * npar * math.log(2 * math.pi)
              + 0.5 * float(np.sum(np.log(q_mu))) - 0.5 * nm * math.log(2 * math.pi))
    edges = np.linspace(0.0, model.basis.window.span_m, ne + 1)
    bounds = np.column_stack([edges[:-1], edges[1:]])
    # Effective stiffness: area under the design influence line over the area under J (D2-like).
    wint = model.basis.integrals
    a_design = model.basis.coefficients(design_influence(model))
    nb = wint.size  # the load term's coefficients lead a (a linearised dynamic model appends its own)
    area = float(wint @ a[:nb])
    eff = float(wint @ a_design) / area
    geff = -eff / area * (wint @ Ja[:nb])
    eff_sd = float(math.sqrt(max(geff @ cov_full[:npar, :npar] @ geff, 0.0)))
    krot = None
    if npar > ne:
        kap = par[ne:]
        ksd = np.sqrt(np.diag(cov_full)[ne:npar])
        krot = tuple((float(k), float(k - 1.96 * s_), float(k + 1.96 * s_)) for k, s_ in zip(kap, ksd))
        if len(krot) == 1:
            krot = krot * 2
    return ElementPosterior(par[:ne], cov_full[:ne, :ne], model.ei_design, bounds, weights, mu, float(log_ev),
                            chi2, S.passes, len(S.ids), iters, eff, eff_sd, krot, par)


def _chi2(S: Stacked, a: np.ndarray, mu: np.ndarray, m: np.ndarray) -> float:
    """Mean squared whitened residual with every weight at its conditional mean."""
    # ‖ρ + W h‖² = ‖ρ‖² + 2W g + W² hᵀh
    rr = S.ww - 2.0 * (S.Bw @ mu) + np.einsum("m,vmn,n->v", mu, S.BB, mu)
    g = (S.Pw - S.Pb @ mu) @ a + S.dw - S.db @ mu
    hh = np.einsum("b,vbc,c->v", a, S.A, a) + 2 * S.e @ a + S.f
    return float(np.sum(rr + 2 * m * g + m * m * hh) / max(S.n, 1))
