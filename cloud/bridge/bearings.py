"""Rotational-spring bearings (thesis §4.4): the restraint the data can see, and how Krot is read from it.

What a fleet's passes determine about a span on springs is its *effective* stiffness — the area of
its influence line, read mostly from the bridge's own vibration (:mod:`cloud.bridge.dynamic`) —
and hardly anything else: a stiffer beam on softer bearings and a softer beam on stiffer ones give
the same deflections and the same first frequency. Measured on ``bearing-1e9`` (30 self-calibrated
passes, 2 % noise, the dynamic likelihood maximised over a uniform level g at each log10 Krot κ):
the maximum log-likelihood varies by 0.3 along the whole ridge from pinned bearings with a 16 %
stiffer beam (κ ≤ 8) to κ = 9.25 with a 12 % softer one. Krot is therefore only identifiable with a
prior on the beam's stiffness: the as-built tolerance, ``g ~ N(0, AS_BUILT_SD²)`` — the same
tolerance the damage hypotheses carry (:class:`~cloud.bridge.hypotheses.HypothesisSettings`).

Nor is the effective stiffness itself always determined. A nearly clamped span (``bearing-1e12``:
4.6× the pinned span's area, first mode 9.5 Hz, outside the band the vehicles feel) deflects so
little that 30 passes only bound it from below: at g = 0 the dynamic log-likelihood is within 2 of
its best everywhere from κ = 10 to 13 (effective 2.2–4.7×), and falls by 12 at κ = 9. Reading the
effective level first and then walking along its iso-effective line turns that flat likelihood into
a sharp, wrong κ = 10.0 ± 0.1. So κ is read where the tolerance prior
puts the beam, not along a ridge: at each κ node the dynamic log-likelihood at g = 0, ±2σ (a
parabola in g; one more level where the likelihood pulls the beam outside that range), integrated
over g against the tolerance prior, on a grid of one log10 Krot shared by both supports (the data
do not separate the supports either). Its mode is where the per-element fit is linearised.

The prior is uniform in the restraint fraction r = (A_pinned − A(κ)) / (A_pinned − A_clamped) of
the design span (A: influence-line area), not in κ: it saturates at both ends, where decades of
Krot all mean "pinned" or "fixed" — uniform in κ (thesis eq. 4.23 over an interval), a flat
likelihood over κ = 11…13 gathers two decades of prior mass and drags a measured 10^10 upwards.
The grid runs from 10^6 (r < 0.001: pinned) to 10^13 (r > 0.998: clamped). Where the data do not
exclude a limit — the integrated likelihood at the grid's end within the 95 % likelihood-ratio
threshold of its maximum — the interval is reported one-sided: (lower 5 % quantile, grid top),
read "Krot ≥ 10^lo, effectively fixed" (:func:`krot_reading`), or (grid bottom, upper 95 %
quantile) for an effectively pinned span.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from cloud.bridge.excess import LEVEL_GRID, dynamic_deltas
from cloud.bridge.hypotheses import Kernels
from cloud.bridge.likelihood import Stacked, WeightPrior, marginal_loglik_batch, vehicle_stats
from cloud.bridge.setup import Setup
from cloud.bridge.stiffness import design_influence
from cloud.bridge.whitening import WhitenedPass

#: as-built tolerance of the global stiffness (log sd) — HypothesisSettings.tolerance_sd
AS_BUILT_SD = 0.02
#: log10 Krot (N·m/rad) where the dynamic likelihood is evaluated: dense where the restraint
#: changes the span (K·L/EI ≈ 1 at ≈ 9.3 for the thesis bridge), sparse where it does not
KAPPA_NODES = (6.0, 7.0, 8.0, 8.5, 9.0, 9.25, 9.5, 9.75, 10.0, 10.5, 11.0, 12.0, 13.0)
KAPPA_FINE_STEP = 0.02
#: the levels g (log EI ratio, in as-built sds) evaluated at every κ node before any refinement
G_OFFSETS_SD = (-2.0, 0.0, 2.0)
#: the data "do not exclude" a limit (fixed or pinned) when the log-likelihood there is within this
#: of its maximum: the 95 % likelihood-ratio threshold, χ²₁(0.95)/2
LR_THRESHOLD = 1.92
#: sd (log10) with which the per-element fit holds Krot at the grid posterior's mode
HOLD_SD = 0.05
#: the one-sided bound's probability (a 95 % bound: the 5 % quantile)
ONE_SIDED_P = 0.05


@dataclasses.dataclass(frozen=True, eq=False)
class KrotPosterior:
    """Posterior of one shared log10 Krot, the beam's level integrated against the tolerance.

    ``kappa``/``log_post``: fine grid and its log posterior (normalised); ``g_mean``: posterior
    mean of the uniform log level given κ on that grid; ``effective_log``/``effective_sd``: the
    posterior's effective log level (pinned-equivalent) and its sd; ``effective_logs``: the
    effective log level at (κ, g_mean(κ)); ``evaluations``: (κ, g) → the dynamic log-likelihood;
    ``fixed_open``/``pinned_open``: the data do not exclude a clamped / pinned span (the grid's
    top / bottom); ``node_loglik``: κ node → log-likelihood integrated over the beam's level.
    """

    kappa: np.ndarray
    log_post: np.ndarray
    g_mean: np.ndarray
    effective_log: float
    effective_sd: float
    effective_logs: np.ndarray
    evaluations: dict[tuple[float, float], float]
    fixed_open: bool = False
    pinned_open: bool = False
    node_loglik: dict | None = None

    @property
    def probabilities(self) -> np.ndarray:
        p = np.exp(self.log_post - self.log_post.max())
        return p / p.sum()

    def quantile(self, q: float) -> float:
        c = np.cumsum(self.probabilities)
        return float(self.kappa[min(np.searchsorted(c, q), c.size - 1)])

    def summary(self) -> tuple[float, float, float]:
        """(mean, lo95, hi95) of log10 Krot; one-sided where the data do not exclude a limit:
        (5 % quantile, grid top) when a clamped span is not excluded, (grid bottom, 95 % quantile)
        when a pinned one is not, the whole grid if neither is."""
        mean = float(self.probabilities @ self.kappa)
        fixed, pinned = self.fixed_open, self.pinned_open
        if fixed and pinned:
            return mean, float(self.kappa[0]), float(self.kappa[-1])
        if fixed:
            return mean, self.quantile(ONE_SIDED_P), float(self.kappa[-1])
        if pinned:
            return mean, float(self.kappa[0]), self.quantile(1.0 - ONE_SIDED_P)
        return mean, self.quantile(0.025), self.quantile(0.975)

    @property
    def mode(self) -> int:
        return int(np.argmax(self.log_post))


def krot_reading(lo95: float, hi95: float) -> str:
    """How to read a reported (lo95, hi95) of log10 Krot (:meth:`KrotPosterior.summary`)."""
    top, bottom = KAPPA_NODES[-1] - 0.5 * KAPPA_FINE_STEP, KAPPA_NODES[0] + 0.5 * KAPPA_FINE_STEP
    if hi95 >= top and lo95 <= bottom:
        return "not identified"
    if hi95 >= top:
        return f"effectively fixed: Krot ≥ 10^{lo95:.1f} (lower bound)"
    if lo95 <= bottom:
        return f"effectively pinned: Krot ≤ 10^{hi95:.1f} (upper bound)"
    return "measured"


def _log_area_table(setup: Setup, kappa: np.ndarray) -> np.ndarray:
    """log ∫J dx of the uniform design span with both springs at 10^κ (g = 0): the pinned span's J
    with the closed-form rank-2 restraint update (:meth:`~cloud.bridge.hypotheses.Kernels.bearings`)
    — one FE solve for the whole table instead of one per κ."""
    kern = Kernels.of(setup)
    return np.log(kern.bearings(np.ones_like(kappa), 10.0**kappa) @ setup.basis.integrals)


def _parabola_marginal(gs: Sequence[float], ys: Sequence[float], sd: float) -> tuple[float, float, float]:
    """∫ exp(parabola through (gs, ys)) · N(g; 0, sd²) dg, as (log of it, mean of g, sd of g)."""
    g1 = float(np.median(gs))
    c2, c1, c0 = np.polyfit(np.asarray(gs) - g1, ys, 2)
    c2 = min(c2, 0.0)  # a convex bend is noise on a flat likelihood: keep the slope only
    A = -c2 + 0.5 / sd**2
    B = c1 - g1 / sd**2
    C = c0 - 0.5 * g1**2 / sd**2 - 0.5 * math.log(2 * math.pi * sd**2)
    return C + B * B / (4 * A) + 0.5 * math.log(math.pi / A), g1 + B / (2 * A), math.sqrt(0.5 / A)


def krot_posterior(passes: Sequence[WhitenedPass], setup: Setup, weight_prior: WeightPrior, model,
                  cache: dict | None = None, as_built_sd: float = AS_BUILT_SD) -> KrotPosterior:
    """The grid posterior of log10 Krot (shared by both supports) — see the module docstring."""
    cache = {} if cache is None else cache
    ne = model.n_elements
    table_k = np.arange(min(KAPPA_NODES) - 4.0, max(KAPPA_NODES) + 4.0 + 1e-9, 0.05)
    table = _log_area_table(setup, table_k)
    log_area = lambda k: np.interp(k, table_k, table)  # noqa: E731 — monotone in κ
    slope = lambda k: np.interp(k, table_k, np.gradient(table, table_k))  # noqa: E731
    log_area_d = math.log(float(model.basis.integrals @ model.basis.coefficients(design_influence(model))))

    def log_eff(g, k):  # uniform beam: J(g, κ) = e^{−g}·J(0, κ − g/ln 10)
        return log_area_d - (-g + log_area(k - g / math.log(10.0)))

    ev: dict[tuple[float, float], float] = {}  # (κ, g) → dynamic log-likelihood

    def loglik(k: float, g: float) -> float:
        key = (round(k, 6), round(round(g / LEVEL_GRID) * LEVEL_GRID, 6))
        if key not in ev:
            lin = np.array(model.prior_mean(), dtype=float)
            lin[:ne] = key[1]
            lin[ne:] = key[0]
            d = dynamic_deltas(passes, setup, lin, cache)
            S = Stacked.of(vehicle_stats(passes, d), weight_prior)
            ev[key] = float(marginal_loglik_batch(S, model.a(lin)[None, :])[0])
        return ev[key]

    nodes = np.array(KAPPA_NODES)
    marg, gmean, gsd = np.empty(nodes.size), np.empty(nodes.size), np.empty(nodes.size)
    reach = max(abs(o) for o in G_OFFSETS_SD) * as_built_sd
    for j, k in enumerate(KAPPA_NODES):
        gs = [o * as_built_sd for o in G_OFFSETS_SD]
        ys = [loglik(k, g) for g in gs]
        for _ in range(3):  # where the likelihood pulls the beam out of ±2σ, add the level it pulls to
            marg[j], gmean[j], gsd[j] = _parabola_marginal(gs, ys, as_built_sd)
            if abs(gmean[j]) <= reach + LEVEL_GRID or any(abs(g - gmean[j]) < 2 * LEVEL_GRID for g in gs):
                break
            g_new = round(round(gmean[j] / LEVEL_GRID) * LEVEL_GRID, 6)
            gs, ys = gs + [g_new], ys + [loglik(k, g_new)]
            near = np.argsort(np.abs(np.array(gs) - g_new))[:3]
            gs, ys = [gs[i] for i in near], [ys[i] for i in near]
        marg[j], gmean[j], gsd[j] = _parabola_marginal(gs, ys, as_built_sd)
    # On a fine grid (interpolated between the nodes), under a prior uniform in the restraint
    # fraction r(κ) = (A_pinned − A(κ)) / (A_pinned − A_clamped) of the design span: uniform in
    # what the bearings do to the span, so that it saturates at both ends (a flat likelihood over
    # κ = 11…13 does not gather the mass of two decades that all mean "fixed").
    kap = np.arange(KAPPA_NODES[0], KAPPA_NODES[-1] + 1e-9, KAPPA_FINE_STEP)
    area = np.exp(table)
    restraint = (area[0] - np.interp(kap, table_k, area)) / (area[0] - area[-1])
    log_prior = np.log(np.maximum(np.gradient(restraint, kap), 1e-300))
    log_post = np.interp(kap, nodes, marg) + log_prior
    log_post -= log_post.max() + math.log(np.sum(np.exp(log_post - log_post.max())))
    g_mean = np.interp(kap, nodes, gmean)
    # One-sided where the data do not exclude the limit: the likelihood (integrated over the
    # beam's level) at the grid's end within the 95 % likelihood-ratio threshold of its maximum.
    near_top = marg[-1] >= marg.max() - LR_THRESHOLD
    near_bottom = marg[0] >= marg.max() - LR_THRESHOLD
    # The effective level the posterior implies (what the per-element fit is recentred on).
    p = np.exp(log_post)
    le = log_eff(g_mean, kap)
    dg = 1.0 + slope(kap - g_mean / math.log(10.0)) / math.log(10.0)  # ∂ log eff / ∂g
    within = (np.interp(kap, nodes, gsd) * dg) ** 2
    e_mean = float(p @ le)
    e_sd = math.sqrt(float(p @ ((le - e_mean) ** 2 + within)))
    return KrotPosterior(kap, log_post, g_mean, e_mean, e_sd, le, ev, bool(near_top), bool(near_bottom),
                        dict(zip(KAPPA_NODES, marg.tolist())))
