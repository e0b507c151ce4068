"""Rotational-spring bearings (thesis §4.4): the restraint the data can see, and how Krot is read from it.

What a fleet's passes determine about a span on springs is its *effective* stiffness — the area of
its influence line, read mostly from the bridge's own vibration (:mod:`cloud.bridge.dynamic`) —
and hardly anything else: a stiffer beam on softer bearings and a softer beam on stiffer ones give
the same deflections and the same first frequency. Measured on ``bearing-1e9`` (30 self-calibrated
passes, 2 % noise, the dynamic likelihood maximised over a uniform level g at each log10 Krot κ):
the maximum log-likelihood varies by 0.3 along the whole ridge from pinned bearings with a 16 %
stiffer beam (κ ≤ 8) to κ = 9.25 with a 12 % softer one, while the effective ratio on it stays
within 1.157–1.171 (truth 1.166). Krot is therefore only identifiable with a prior on the beam's
stiffness: the as-built tolerance, ``g ~ N(0, AS_BUILT_SD²)`` — the same tolerance the damage
hypotheses carry (:class:`~cloud.bridge.hypotheses.HypothesisSettings`). A bearing restraint and a
uniform stiffness change cannot be told apart by these data; with this prior the restraint takes
what the tolerance does not allow the beam.

The search (:func:`bearing_ridge`): the effective level by the 1-D dynamic profile at the prior's
κ (then again at the ridge's mode while that moves: a stiff pinned beam does not vibrate like a
clamped one of the same area, so the level read at the wrong κ is biased), then along the iso-effective line g_r(κ) (uniform beam: J(g, κ) = e^{−g}·J(0, κ − g/ln 10), so
g_r is a 1-D root on a table of the pinned-to-clamped areas) the dynamic log-likelihood at a few
κ, each integrated over g against the tolerance prior, times the κ prior: a grid posterior of
one log10 Krot shared by both supports (the data do not separate the supports either). Its mode
is where the per-element fit is linearised; its quantiles are the reported Krot — for a nearly
clamped span the upper one is the grid's top: read it as a lower bound.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from .static import Setup, Stacked, WeightPrior, WhitenedPass, fit_elements, marginal_loglik_batch, vehicle_stats

#: as-built tolerance of the global stiffness (log sd) — HypothesisSettings.tolerance_sd
AS_BUILT_SD = 0.02
#: log10 Krot (N·m/rad) where the dynamic likelihood is evaluated along the ridge: dense where the
#: restraint changes the span (K·L/EI ≈ 1 at ≈ 9.3 for the thesis bridge), sparse where it does not
KAPPA_NODES = (6.0, 7.0, 8.0, 8.5, 9.0, 9.25, 9.5, 10.0, 10.5, 11.0, 12.0, 13.0)
KAPPA_FINE_STEP = 0.02
#: the effective level is re-profiled at the ridge's mode until the mode moves less than this
MODE_TOLERANCE = 0.5
MAX_ROUNDS = 2


@dataclasses.dataclass(frozen=True, eq=False)
class BearingRidge:
    """Posterior of one shared log10 Krot from the dynamic likelihood along the iso-effective line.

    ``kappa``/``log_post``: fine grid and its log posterior (normalised); ``g_mean``: posterior
    mean of the uniform log level given κ on that grid; ``effective_log``/``effective_sd``: the
    posterior's effective log level (pinned-equivalent) and its sd; ``evaluations``: (κ, g) → the
    dynamic log-likelihood.
    """

    kappa: np.ndarray
    log_post: np.ndarray
    g_mean: np.ndarray
    effective_log: float
    effective_sd: float
    effective_logs: np.ndarray  # the effective log level at (κ, g_mean(κ)) on the grid
    evaluations: dict[tuple[float, float], float]

    @property
    def probabilities(self) -> np.ndarray:
        p = np.exp(self.log_post - self.log_post.max())
        return p / p.sum()

    def summary(self) -> tuple[float, float, float]:
        """(mean, lo95, hi95) of log10 Krot."""
        p = self.probabilities
        c = np.cumsum(p)
        lo = float(self.kappa[np.searchsorted(c, 0.025)])
        hi = float(self.kappa[min(np.searchsorted(c, 0.975), c.size - 1)])
        return float(p @ self.kappa), lo, hi

    @property
    def mode(self) -> int:
        return int(np.argmax(self.log_post))


def _log_area_table(setup: Setup, kappa: np.ndarray) -> np.ndarray:
    """log ∫J dx of the uniform design span with both springs at 10^κ (g = 0): the pinned span's J
    with the closed-form rank-2 restraint update (:meth:`~cloud.bridge.hypotheses.Kernels.bearings`)
    — one FE solve for the whole table instead of one per κ."""
    from .hypotheses import Kernels

    kern = Kernels.of(setup)
    return np.log(kern.bearings(np.ones_like(kappa), 10.0**kappa) @ setup.basis.integrals)


def bearing_ridge(passes: Sequence[WhitenedPass], setup: Setup, weight_prior: WeightPrior, model,
                  cache: dict | None = None, start_effective: float = 1.0,
                  as_built_sd: float = AS_BUILT_SD) -> BearingRidge:
    """The grid posterior of log10 Krot (shared by both supports) — see the module docstring.
    ``start_effective``: the effective ratio to start the effective-level search from (e.g. the
    quasi-static fit's: a stiff restraint doubles it, further than the search walks from 1)."""
    from .dynamic import LEVEL_GRID, dynamic_deltas, profile_global_level

    cache = {} if cache is None else cache
    ne = model.n_elements
    kap0 = float(model.prior_mean()[ne])
    table_k = np.arange(min(KAPPA_NODES) - 4.0, max(KAPPA_NODES) + 4.0 + 1e-9, 0.05)
    table = _log_area_table(setup, table_k)
    log_area = lambda k: np.interp(k, table_k, table)  # noqa: E731 — monotone in κ
    slope = lambda k: np.interp(k, table_k, np.gradient(table, table_k))  # noqa: E731
    log_area_d = math.log(float(model.basis.integrals @ model.basis.coefficients(_design_J(model))))

    def log_eff(g, k):
        return log_area_d - (-g + log_area(k - g / math.log(10.0)))

    def g_at(k, target):  # log_eff increases with g at fixed κ: bisection
        lo, hi = -2.0, 2.0
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if log_eff(mid, k) < target else (lo, mid)
        return 0.5 * (lo + hi)

    kap = np.arange(KAPPA_NODES[0], KAPPA_NODES[-1] + 1e-9, KAPPA_FINE_STEP)
    nodes = np.array(KAPPA_NODES)
    k_mean, k_sd = model.krot_prior
    # 1. The effective level: the 1-D dynamic profile at a fixed κ (the prior's, then the ridge's
    #    mode: far from the truth the profile's level is biased — a stiffer pinned beam does not
    #    vibrate like a clamped one — so it is repeated at the mode until the mode stays put).
    kap_p, g_start = kap0, g_at(kap0, math.log(max(start_effective, 1e-3)))
    ev: dict[tuple[float, float], float] = {}  # (κ, g) → dynamic log-likelihood
    for _ in range(MAX_ROUNDS):
        at = dataclasses.replace(model, krot_prior=(kap_p, model.krot_prior[1]))
        level = profile_global_level(passes, setup, weight_prior, at, start=g_start, cache=cache, post=None)
        eff_log = float(log_eff(level.log_ratio, kap_p))
        d_eff = 1.0 + float(slope(kap_p - level.log_ratio / math.log(10.0))) / math.log(10.0)
        eff_sd = (level.sd if np.isfinite(level.sd) else 0.05) * d_eff
        # 2. At each κ node the dynamic log-likelihood at three levels about the ridge (a parabola in
        #    g: where the span's vibration is out of the band, e.g. nearly clamped, it is flat and the
        #    tolerance decides), integrated over g against the tolerance prior N(0, as_built_sd²).
        marg, gmean, gsd = np.empty(nodes.size), np.empty(nodes.size), np.empty(nodes.size)
        for j, k in enumerate(KAPPA_NODES):
            gr = g_at(k, eff_log)
            dg = 1.0 + float(slope(k - gr / math.log(10.0))) / math.log(10.0)  # ∂ log eff / ∂g
            step = float(np.clip(eff_sd / dg, 2 * LEVEL_GRID, 0.1))
            gs = [round(round((gr + o * step) / LEVEL_GRID) * LEVEL_GRID, 6) for o in (-1, 0, 1)]
            ys = []
            for g in gs:
                key = (round(k, 6), g)
                if key not in ev:
                    lin = np.array(model.prior_mean(), dtype=float)
                    lin[:ne] = g
                    lin[ne:] = k
                    d = dynamic_deltas(passes, setup, lin, cache)
                    S = Stacked.of(vehicle_stats(passes, d), weight_prior)
                    ev[key] = float(marginal_loglik_batch(S, model.a(lin)[None, :])[0])
                ys.append(ev[key])
            g1 = gs[1]
            c2, c1, c0 = np.polyfit(np.array(gs) - g1, ys, 2)
            c2 = min(c2, 0.0)  # a convex bend is noise on a flat likelihood: keep the slope only
            A = -c2 + 0.5 / as_built_sd**2
            B = c1 - g1 / as_built_sd**2
            C = c0 - 0.5 * g1**2 / as_built_sd**2 - 0.5 * math.log(2 * math.pi * as_built_sd**2)
            marg[j] = C + B * B / (4 * A) + 0.5 * math.log(math.pi / A)
            gmean[j] = g1 + B / (2 * A)
            gsd[j] = math.sqrt(0.5 / A)
        # 3. On a fine grid (interpolated between the nodes), times the κ prior.
        log_post = np.interp(kap, nodes, marg) - 0.5 * ((kap - k_mean) / k_sd) ** 2
        log_post -= log_post.max() + math.log(np.sum(np.exp(log_post - log_post.max())))
        g_mean = np.interp(kap, nodes, gmean)
        mode = float(kap[np.argmax(log_post)])
        if abs(mode - kap_p) <= MODE_TOLERANCE:
            break
        kap_p = round(mode / 0.05) * 0.05
        g_start = g_at(kap_p, eff_log)
    # The effective level the posterior implies (what the per-element fit is recentred on).
    p = np.exp(log_post)
    le = log_eff(g_mean, kap)
    dg = 1.0 + slope(kap - g_mean / math.log(10.0)) / math.log(10.0)
    within = (np.interp(kap, nodes, gsd) * dg) ** 2
    e_mean = float(p @ le)
    e_sd = math.sqrt(float(p @ ((le - e_mean) ** 2 + within)))
    return BearingRidge(kap, log_post, g_mean, e_mean, e_sd, le, ev)


def _design_J(model) -> np.ndarray:
    from .static import design_influence

    return design_influence(model)


def fit_bearings_dynamic(passes: Sequence[WhitenedPass], setup: Setup, weight_prior: WeightPrior, model,
                         cache: dict | None = None, start: float | None = None):
    """The bearing model's dynamic fit (same contract as :func:`~cloud.bridge.dynamic.fit_elements_dynamic`):
    the Krot ridge posterior, the per-element fit linearised at its mode with Krot held there by a
    prior of the ridge's width, recentred on the effective level; Krot reported from the ridge."""
    from .dynamic import LEVEL_GRID, DynamicFit, GlobalLevel, dynamic_deltas, recentre

    cache = {} if cache is None else cache
    ne = model.n_elements
    qs = fit_elements(vehicle_stats(passes), model, weight_prior)
    eff0 = qs.effective_ratio if np.isfinite(qs.effective_ratio) else 1.0
    ridge = bearing_ridge(passes, setup, weight_prior, model, cache=cache, start_effective=eff0)
    # (``start`` is not used: the quasi-static fit's effective ratio is a better start for a restraint.)
    i = ridge.mode
    k_hat = float(ridge.kappa[i])
    mean, lo, hi = ridge.summary()
    lin = np.array(model.prior_mean(), dtype=float)
    lin[:ne] = round(round(float(ridge.g_mean[i]) / LEVEL_GRID) * LEVEL_GRID, 6)
    lin[ne:] = k_hat
    deltas = dynamic_deltas(passes, setup, lin, cache)
    held = dataclasses.replace(model, krot_prior=(k_hat, max(0.25 * (hi - lo), 0.05)))
    post = fit_elements(vehicle_stats(passes, deltas), held, weight_prior, theta0=lin)
    # Recentred on the effective level at the linearisation (the posterior's mean over κ would
    # pull the elements towards a restraint they are not fitted with).
    level = GlobalLevel(float(ridge.effective_logs[i]), ridge.effective_sd, {})
    final = recentre(post, held, level)
    final = dataclasses.replace(final, krot=((mean, lo, hi),) * 2)
    return DynamicFit(final, (qs, post), deltas, math.exp(float(lin[0])), lin, level)
