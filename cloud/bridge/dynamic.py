"""Fits of the bridge's stiffness with its own dynamics: the moving-force excess (:mod:`cloud.bridge.excess`)
in the per-element posterior.

ε moves with the stiffness level — in amplitude and, above all, in phase (f1 ∝ √EI) — and that is
most of the information on the global stiffness at these speeds (:mod:`cloud.bridge.information`:
at 2 % noise one pass's quasi-static part carries ~5 % of its Fisher information on the level). The
global level ĝ comes from the profile likelihood with ε recomputed at every level
(:func:`profile_global_level`: ε is far from linear over the level's prior range). Without
``sensitivities`` the per-element posterior is fitted with ε at ĝ and recentred on it
(:func:`recentre`): it then sees the dynamics through the level alone. With them (the estimator's
default, :attr:`~cloud.bridge.estimator.BridgeSettings.dynamic_sensitivities`) ε is linearised in
every element's θ about ĝ, ``ε_p(θ) ≈ ε_p(θ₀) + ∂ε_p/∂θ·(θ − θ₀)``
(:func:`~cloud.bridge.excess.dynamic_sensitivities`, kept on the level grid in the estimator's
cache), so the per-element fit reads the dynamics itself: the element directions, which the
quasi-static part barely sees at the span's ends, get their share of the bridge's vibration. The fit
is linearised once; relinearising at the per-element estimate moves the largest element error by
less than a tenth of a point.

A span on rotational-spring bearings is fitted on its Krot grid posterior
(:mod:`cloud.bridge.bearings`, :func:`fit_bearings_dynamic`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from cloud.bridge.bearings import HOLD_SD, krot_posterior
from cloud.bridge.excess import LEVEL_GRID, dynamic_deltas, dynamic_sensitivities, extended_passes
from cloud.bridge.likelihood import Stacked, WeightPrior, marginal_loglik_batch, vehicle_stats
from cloud.bridge.posterior import ElementPosterior, fit_elements, fit_elements_per_scale, mix_scales
from cloud.bridge.setup import Setup
from cloud.bridge.stiffness import LinearisedDynamicModel, StiffnessPrior
from cloud.bridge.whitening import WhitenedPass

#: The per-element fit keeps an earlier linearisation level while ĝ is within this (log ratio) of it:
#: the linearised ε follows the level itself to second order, and computing every pass's ∂ε afresh
#: at each step of ĝ on the level grid would cost ~4× the excess, while linearising that far off ĝ moves
#: no element by more than a small fraction of its sd.
LINEARISATION_TOL = 0.01


@dataclasses.dataclass(frozen=True, eq=False)
class GlobalLevel:
    """The global stiffness level by the profile likelihood of the dynamic model.

    ``log_ratio`` g (EI = EI_design·e^g along the whole span) maximises the weight- and
    nuisance-marginal likelihood with the dynamic excess recomputed *at* g — so the information
    in the bridge's own vibration (its frequency ∝ √EI: the phase of the excess moves with g) is
    used, not only the quasi-static amplitude. ``sd`` from the curvature of the log-likelihood
    (flat prior in g); ``evaluations`` the levels tried: g → log-likelihood.
    """

    log_ratio: float
    sd: float
    evaluations: dict[float, float]

    @property
    def ratio(self) -> float:
        return math.exp(self.log_ratio)


def _uniform_linearisation(model, g: float, post: ElementPosterior | None) -> np.ndarray:
    lin = np.array(model.prior_mean(), dtype=float)
    lin[: model.n_elements] = g
    if post is not None and model.n > model.n_elements:  # bearings: at the current estimate
        lin[model.n_elements :] = post.params[model.n_elements :]
    return lin


def profile_global_level(passes: Sequence[WhitenedPass], setup: Setup, weight_prior: WeightPrior, model,
                         start: float = 0.0, cache: dict | None = None, post: ElementPosterior | None = None,
                         step: float = 0.04, max_evaluations: int = 14) -> GlobalLevel:
    """Maximise log p(data | g) over the uniform level g (weights and μ integrated exactly,
    :func:`~cloud.bridge.likelihood.marginal_loglik_batch`), the dynamic excess at every g.

    Successive parabolas through the three best levels (spacing ``step`` at first, then the
    parabola's own scale), until the vertex lies inside the bracket within 1e-3.
    """
    cache = {} if cache is None else cache
    ev: dict[float, float] = {}

    def loglik(g: float) -> float:
        g = round(round(float(g) / LEVEL_GRID) * LEVEL_GRID, 6)
        if g not in ev:
            lin = _uniform_linearisation(model, g, post)
            d = dynamic_deltas(passes, setup, lin, cache)
            S = Stacked.of(vehicle_stats(passes, d), weight_prior)
            ev[g] = float(marginal_loglik_batch(S, model.a(lin)[None, :])[0])
        return ev[g]

    g0 = float(start)
    for g in (g0 - step, g0, g0 + step):
        loglik(g)
    vertex, curv = g0, float("nan")
    for _ in range(max_evaluations):  # bounded: a level already on the grid adds no evaluation
        gs = sorted(ev, key=lambda k: -ev[k])[:3]
        gs.sort()
        x, y = np.array(gs), np.array([ev[k] for k in gs])
        c2, c1, _ = np.polyfit(x - x[1], y, 2)
        if c2 >= 0:  # not concave yet: walk uphill
            best = max(ev, key=ev.get)
            if best == max(ev):
                loglik(best + step)
            elif best == min(ev):
                loglik(best - step)
            else:
                loglik(best + 0.5 * step)
            continue
        curv = -2.0 * c2
        vertex = float(x[1] - c1 / (2 * c2))
        vertex = float(np.clip(vertex, x[0] - 2 * step, x[-1] + 2 * step))
        on_grid = round(round(vertex / LEVEL_GRID) * LEVEL_GRID, 6)
        if on_grid in ev:  # the vertex's grid level is known already: nothing finer to learn
            break
        loglik(vertex)
        step = max(min(step, 2.0 / math.sqrt(curv)), 2 * LEVEL_GRID)
    sd = 1.0 / math.sqrt(curv) if curv > 0 else float("nan")
    return GlobalLevel(vertex, sd, dict(ev))


@dataclasses.dataclass(frozen=True, eq=False)
class DynamicFit:
    """The dynamic fit and its history: ``history[i]`` is the posterior after outer iteration i
    (``history[0]`` is quasi-static); ``deltas`` the whitened corrections used by ``posterior``;
    ``level`` the profile-likelihood global level the per-element posterior was recentred on."""

    posterior: ElementPosterior
    history: tuple[ElementPosterior, ...]
    deltas: dict[str, np.ndarray]
    scale: float = 1.0  # the uniform stiffness ratio the dynamic excess was computed at
    linearisation: np.ndarray | None = None  # the full parameter vector it was computed at
    level: GlobalLevel | None = None
    #: with sensitivities: each pass's whitened ∂ε/∂θ at ``linearisation`` (:func:`dynamic_sensitivities`)
    sensitivities: dict[str, np.ndarray] | None = None


def recentre(post: ElementPosterior, model, level: GlobalLevel) -> ElementPosterior:
    """Condition the per-element posterior on the profile-likelihood global level.

    The per-element fit sees the dynamic excess at a fixed level, so it uses the quasi-static
    information on the global stiffness only; the profile likelihood has it all. In the Gaussian
    posterior, move θ along its covariance so that the effective level (log of the area ratio,
    linearised: γᵀθ) equals ĝ, and shrink its variance along that direction to the profile's.
    """
    n = post.theta.size
    wint = model.basis.integrals
    par = np.array(post.params, dtype=float)
    a, Ja, _ = model.a_jac(par)
    gam = -(wint @ Ja[:, :n]) / float(wint @ a)  # ∂ log(effective ratio)/∂θ
    C = post.cov
    Cg = C @ gam
    V = float(gam @ Cg)
    if not (V > 0 and np.isfinite(level.sd)):
        return post
    g_now = math.log(post.effective_ratio)
    T = min(level.sd**2, V)
    theta = post.theta + Cg / V * (level.log_ratio - g_now)
    cov = C - (1.0 - T / V) * np.outer(Cg, Cg) / V
    params = par.copy()
    params[:n] = theta
    # The loads follow the stiffness (the data fix W/EI): rescale them with the level.
    k = math.exp(level.log_ratio - g_now)
    weights = {v: (m * k, s_ * k) for v, (m, s_) in post.weights.items()}
    return dataclasses.replace(post, theta=theta, cov=cov, params=params, weights=weights,
                               effective_ratio=float(level.ratio),
                               effective_ratio_sd=float(level.ratio * math.sqrt(T)))


def fit_elements_dynamic(passes: Sequence[WhitenedPass], setup: Setup, weight_prior: WeightPrior,
                         prior: StiffnessPrior = StiffnessPrior(), iterations: int = 6,
                         start: float | None = None, model=None, tol: float = 1e-3,
                         cache: dict | None = None, sensitivities: bool = False,
                         linearise_at: float | None = None) -> DynamicFit:
    """Per-element posterior with the moving-force dynamics.

    ε depends on the stiffness mainly through its global level (f1 ∝ √EI), and strongly: both
    its amplitude and its phase move with the level, and that is where about half of the
    information on the global stiffness lies (the Cramér–Rao bound, :mod:`cloud.bridge.information`).
    So the global level ĝ is found first by the profile likelihood with ε recomputed at every
    level (:func:`profile_global_level`, from ``start``, a ratio). With ``sensitivities``
    each pass's ε is then linearised in every element's θ about ĝ
    (:class:`~cloud.bridge.stiffness.LinearisedDynamicModel`; relinearised about the estimate it moved the
    largest element error by < 0.1 point), so the per-element fit reads the dynamics itself; without,
    it is fitted with ε fixed at ĝ and recentred on ĝ (:func:`recentre`). ``model``: an
    :class:`~cloud.bridge.stiffness.ElementModel` (default, simply supported) or a
    :class:`~cloud.bridge.stiffness.BearingElementModel` (ε at the level only, :mod:`cloud.bridge.bearings`);
    the departure scales are weighted by the linearised fits' own evidence (the model the estimate comes
    from). ``cache``: see :func:`dynamic_deltas`; ``linearise_at``: the uniform level (log ratio) of an
    earlier fit's linearisation, kept while within :data:`LINEARISATION_TOL` of ĝ (a live estimator's
    cache then holds every earlier pass's ∂ε there). ``iterations``/``tol`` bound the bearings' alternation
    between level and Krot. ``deltas`` of the result are ε at ĝ (what the hypotheses use).
    """
    model = model or setup.model(prior)
    if model.n > model.n_elements:  # bearings: fitted on the Krot grid posterior
        return fit_bearings_dynamic(passes, setup, weight_prior, model, cache=cache, start=start)
    cache = {} if cache is None else cache
    qs = fit_elements(vehicle_stats(passes), model, weight_prior)
    g = math.log(start) if start else 0.0
    level = profile_global_level(passes, setup, weight_prior, model, start=g, cache=cache)
    g_lin = round(level.log_ratio / LEVEL_GRID) * LEVEL_GRID
    if sensitivities and linearise_at is not None and abs(linearise_at - level.log_ratio) < LINEARISATION_TOL:
        g_lin = linearise_at  # the linearised model follows the level itself: keep the passes' cached ∂ε
    lin = _uniform_linearisation(model, g_lin, None)
    deltas = dynamic_deltas(passes, setup, lin, cache)
    fits = fit_elements_per_scale(vehicle_stats(passes, deltas), model, weight_prior, theta0=lin)
    if not sensitivities:
        # Each departure scale's fit is recentred on the level before they are mixed: the mixture's
        # covariance carries the spread between the fits, which is not the level's uncertainty.
        final = mix_scales([recentre(f, model, level) for f in fits], model.prior)
        return DynamicFit(final, (qs, mix_scales(fits, model.prior)), deltas, level.ratio, lin, level)
    sens = dynamic_sensitivities(passes, setup, lin, cache)
    lmodel = LinearisedDynamicModel(model.basis, model.ei_design, model.kernel, model.prior, np.array(lin))
    lfits = fit_elements_per_scale(vehicle_stats(extended_passes(passes, sens), deltas), lmodel, weight_prior,
                                   theta0=lin)
    post = mix_scales(lfits, model.prior)
    return DynamicFit(post, (qs, post), deltas, level.ratio, lin, level, sens)


def fit_bearings_dynamic(passes: Sequence[WhitenedPass], setup: Setup, weight_prior: WeightPrior, model,
                         cache: dict | None = None, start: float | None = None):
    """The bearing model's dynamic fit (same contract as :func:`fit_elements_dynamic`):
    the Krot grid posterior, the per-element fit linearised at its mode with Krot held there
    (:data:`HOLD_SD`), recentred on the effective level there; Krot and the effective ratio
    reported from the whole grid posterior (Krot one-sided where the data leave a limit open)."""
    cache = {} if cache is None else cache
    ne = model.n_elements
    qs = fit_elements(vehicle_stats(passes), model, weight_prior)
    kp = krot_posterior(passes, setup, weight_prior, model, cache=cache)  # (``start`` is not needed)
    i = kp.mode
    k_hat = float(kp.kappa[i])
    mean, lo, hi = kp.summary()
    lin = np.array(model.prior_mean(), dtype=float)
    lin[:ne] = round(round(float(kp.g_mean[i]) / LEVEL_GRID) * LEVEL_GRID, 6)
    lin[ne:] = k_hat
    deltas = dynamic_deltas(passes, setup, lin, cache)
    # Krot held at the mode (the fit is conditional on it; its uncertainty is the grid posterior's):
    # a loose hold lets the two supports split and the elements absorb the difference.
    held = dataclasses.replace(model, krot_prior=(k_hat, HOLD_SD))
    post = fit_elements(vehicle_stats(passes, deltas), held, weight_prior, theta0=lin)
    # Recentred on the effective level at the linearisation (the posterior's mean over κ would
    # pull the elements towards a restraint they are not fitted with).
    level = GlobalLevel(float(kp.effective_logs[i]), kp.effective_sd, {})
    final = recentre(post, held, level)
    # The effective stiffness and Krot are reported from the whole grid posterior (the elements are
    # conditional on its mode): for a nearly clamped span the effective ratio is as uncertain as Krot.
    eff = math.exp(kp.effective_log)
    final = dataclasses.replace(final, krot=((mean, lo, hi),) * 2, effective_ratio=eff,
                                effective_ratio_sd=eff * kp.effective_sd)
    return DynamicFit(final, (qs, post), deltas, math.exp(float(lin[0])), lin, level)
