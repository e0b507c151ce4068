"""The bridge's own dynamics in the pass model: a moving-force correction to the quasi-static kernel.

At 15–22 m/s a 20 m span (f1 ≈ 4.2 Hz) is crossed in about four of its periods, and the deflection
under the wheel differs from the static ``W·J(x)`` by several per cent, oscillating with x and with
a speed-dependent phase; averaged over a fleet's speeds it is a bias of a few per cent in the
global stiffness, and along the span it masquerades as stiffness variations.

Model: the wheel is a moving force ``W·(1 + φ_p(x))`` (the pass's measured dynamic wheel load,
:class:`~cloud.bridge.passdata.VehicleFilter`) on the FE beam with the current stiffness estimate,
integrated from rest (:func:`shared.fe.beam.moving_load_deflection`, Newmark trapezoidal rule).
Its deflection under the force, per newton of static load, minus the quasi-static
``(1 + φ_p)·J`` is the pass's dynamic excess ``ε_p(x)``; the estimator adds it to the load term
(``h_p = (1 + φ_p)·J(θ) + ε_p``). ε moves with the stiffness level — in amplitude and, above
all, in phase (f1 ∝ √EI) — and that is most of the information on the global stiffness at these
speeds (:mod:`cloud.bridge.information`: at 2 % noise one pass's quasi-static part carries ~5 % of
its Fisher information on the level). So the level is estimated by the profile likelihood with ε
recomputed at every level (:func:`profile_global_level`), and the per-element posterior is fitted
with ε at that level and recentred on it (:func:`recentre`). Measured on 30 self-calibrated passes
at 2 % noise (``driveby reproduce bridge``): the global level's sd falls from ~5 % (ε fixed) to
~2 % (the Cramér–Rao bound is 0.7 %). This is a simplification of the coupled vehicle–bridge
system the data came from (``shared.vbi``): the coupling enters only through the measured wheel
load. Measured (``tests/test_bridge_dynamic.py``): with the coupled simulation's actual wheel
load the moving force reproduces its deflection to < 1 %.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from shared.fe.beam import Beam, BeamSystem, assemble, influence_line, moving_load_deflection

from .passdata import PassData, Window
from .static import (ElementPosterior, Setup, Stacked, StiffnessPrior, WeightPrior, WhitenedPass, design_beam,
                     fit_elements, fit_elements_per_scale, marginal_loglik_batch, mix_scales, vehicle_stats)

SUBSTEPS = 2  # beam time steps per grid point
#: The dynamic excess is computed at global levels on this grid (log ratio): a live estimator's
#: later updates then find most levels' excesses of earlier passes in its cache. Half a grid step
#: moves ε by far less than its own uncertainty (the level's sd is ~2 % at 30 passes).
LEVEL_GRID = 0.0025


def dynamic_excess(beam: Beam, p: PassData, substeps: int = SUBSTEPS, system: BeamSystem | None = None,
                   influence: np.ndarray | None = None) -> np.ndarray:
    """ε_p on the window (m/N, positive in the load's direction; zero off the span).

    ``system`` (:func:`~shared.fe.beam.assemble` of ``beam``) and ``influence`` (J on the
    window's span points) may be passed in to share them between passes.
    """
    w: Window = p.window
    on = w.on_span
    xs = np.clip(w.x[on], 0.0, beam.span_m)
    J = influence_line(beam, xs) if influence is None else influence
    lf = p.load_factor[on]
    dt = w.spacing_m / (p.speed_mps * substeps)
    n_steps = int(np.ceil(beam.span_m / (p.speed_mps * dt))) + 2
    x_t = np.arange(n_steps) * p.speed_mps * dt
    force = -np.interp(x_t, xs, lf, left=1.0, right=1.0)  # per newton of static wheel load, up positive
    force[x_t > beam.span_m] = 0.0
    u = -moving_load_deflection(beam, x_t, force, dt, system=system)  # compliance sign
    out = np.zeros(w.n)
    out[on] = np.interp(xs, x_t, u) - lf * J
    return out


def dynamic_deltas(passes: Sequence[WhitenedPass], setup: Setup, params: np.ndarray,
                   cache: dict | None = None) -> dict[str, np.ndarray]:
    """Every pass's whitened dynamic excess at the stiffness ``params`` (θ, then log10 Krot if any).

    ``cache``: a dict kept by the caller; the (unwhitened) excess of a pass at the same parameters
    is then computed once (a live estimator keeps it across updates).
    """
    ne = setup.bridge.n_elements
    key = tuple(np.round(np.asarray(params, dtype=float), 9))
    beam = system = J = None
    out = {}
    for wp in passes:
        ck = (wp.vehicle_id, wp.pass_id, key)
        excess = None if cache is None else cache.get(ck)
        if excess is None:
            if beam is None:
                theta = np.asarray(params[:ne], dtype=float)
                krot = None
                if len(params) > ne:
                    k = 10.0 ** np.asarray(params[ne:], dtype=float)
                    krot = (float(k[0]), float(k[-1]))
                beam = design_beam(setup.bridge, ei_factor=np.exp(theta), krot=krot)
                system = assemble(beam)
                J = influence_line(beam, setup.basis.x)
            excess = dynamic_excess(beam, wp.data, system=system, influence=J)
            if cache is not None:
                cache[ck] = excess
        out[wp.pass_id] = wp.whiten_extra(excess)
    return out


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
    :func:`~cloud.bridge.static.marginal_loglik_batch`), the dynamic excess at every g.

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
                         cache: dict | None = None) -> DynamicFit:
    """Per-element posterior with the moving-force dynamics.

    ε depends on the stiffness mainly through its global level (f1 ∝ √EI), and strongly: both
    its amplitude and its phase move with the level, and that is where about half of the
    information on the global stiffness lies (the Cramér–Rao bound, :mod:`cloud.bridge.information`).
    So the global level ĝ is found first by the profile likelihood with ε recomputed at every
    level (:func:`profile_global_level`, from ``start``, a ratio); the per-element posterior is
    then fitted with ε at ĝ and recentred on ĝ (:func:`recentre`). ``model``: an
    :class:`~cloud.bridge.static.ElementModel` (default, simply supported) or a
    :class:`~cloud.bridge.static.BearingElementModel`; ``cache``: see :func:`dynamic_deltas`.
    ``iterations``/``tol`` bound the bearings' alternation between level and Krot.
    """
    model = model or setup.model(prior)
    if model.n > model.n_elements:  # bearings: Krot is read along the effective-stiffness ridge
        from .bearings import fit_bearings_dynamic

        return fit_bearings_dynamic(passes, setup, weight_prior, model, cache=cache, start=start)
    cache = {} if cache is None else cache
    qs = fit_elements(vehicle_stats(passes), model, weight_prior)
    history = [qs]
    g = math.log(start) if start else 0.0
    post = qs if model.n > model.n_elements else None
    for _ in range(max(1, iterations if post is not None else 1)):
        level = profile_global_level(passes, setup, weight_prior, model, start=g, cache=cache, post=post)
        lin = _uniform_linearisation(model, round(level.log_ratio / LEVEL_GRID) * LEVEL_GRID, post)
        deltas = dynamic_deltas(passes, setup, lin, cache)
        fits = fit_elements_per_scale(vehicle_stats(passes, deltas), model, weight_prior, theta0=lin)
        new = mix_scales(fits, model.prior)
        done = post is None or abs(level.log_ratio - g) < tol
        g, post = level.log_ratio, new
        if done:
            break
    history.append(post)
    # Each departure scale's fit is recentred on the level before they are mixed: the mixture's
    # covariance carries the spread between the fits, which is not the level's uncertainty.
    final = (mix_scales([recentre(f, model, level) for f in fits], model.prior)
             if model.n == model.n_elements else post)
    return DynamicFit(final, tuple(history), deltas, level.ratio, lin, level)
