"""Fleet calibration by Cross-Entropy optimisation with injections: the thesis's method (§2.4, Fig. 2.5).

Every vehicle of a fleet drove over the same profile, so under its true parameters each vehicle's
apparent profile (AP) is the same. The thesis searches the parameters of the *whole fleet* at once:

* a population of trial solutions, each a parameter vector for every vehicle, is drawn from
  independent normal distributions (mean μ, sd σ per parameter and vehicle);
* each trial is scored by eq. (2.32)–(2.33): the APs of all vehicles under the trial's parameters
  (inverse Newmark-β) are compared on a common chainage grid, and the objective is the sum over
  vehicles, axles and grid points of the squared difference between a vehicle's AP and the fleet
  mean AP of that axle;
* the best 10 % (the elite) give the next μ and σ, with smoothing;
* when the search has converged, an *injection* (Botev and Kroese, 2004) restarts it from the best
  solution with widened sds: the first two injections reset σ to its initial value, later ones
  to σ₀·2/n for the n-th injection (inverse proportion to the number of injections, continuous at
  n = 2, as in Casero et al., 2014);
* the search stops when an injection no longer improves the best objective, or after the last
  allowed injection, or at the generation budget.

Two things the thesis leaves implicit are made explicit here. A logger switched on while driving
does not know the vehicle's initial state, so each AP carries an offset and a linear drift from the
neutral integrators of the inverse (and a short transient, skipped): each AP is detrended (its
least-squares line removed) on the common window before comparison, which removes the same linear
part of the true profile from every vehicle and so cannot bias the agreement. And vehicles may
drive at different speeds: APs are compared on a chainage grid, each contact at its own offset
(for a half-car, the trial axle spacing moves axle positions, which is what makes D1, D2
identifiable at all).

Only ratios are identifiable (divide the equations of motion by the body mass): the objective is
flat along each vehicle's mass scale, so absolute values wander while ratios converge — exactly
what the thesis reports (Tables 2.3, 2.5, 2.6).

Evaluating a trial runs the inverse of every vehicle under new parameters;
:func:`cloud.batched_inverse.inverse_runs` runs the readable inverse step of
:mod:`shared.dynamics.inverse` for a whole population in one compiled call, without compiling a
state-space model per trial.
"""

from __future__ import annotations

import logging
import math
import time
from typing import NamedTuple, Sequence

import numpy as np

from shared.dynamics.newmark import newmark_constants
from shared.vehicles import MODELS, vehicle_from_params

from ..batched_inverse import inverse_runs

log = logging.getLogger(__name__)

ELITE_FRACTION = 0.10  # thesis §2.4: "the 10% best of the trial vehicle property sets"


# ---------------------------------------------------------------------------------------------
# The inverse for a population of parameter sets


def population_aps(model: str, trials: Sequence[dict[str, float]], channels: np.ndarray, dt: float,
                   gamma: float = 0.8, beta: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """APs (T, n_samples, n_contacts) of one vehicle's ``channels`` under each trial parameter set.

    Also returns the contact offsets (T, n_contacts) ahead of the centre of gravity, m.
    """
    c = newmark_constants(dt, gamma, beta)
    systems = [vehicle_from_params(model, p).system() for p in trials]
    s0 = systems[0]
    measured = [ch.dof for ch in s0.channels]
    free = np.array([i for i in range(s0.n_dof) if i not in measured], dtype=np.int64)
    M = np.stack([s.M for s in systems])
    C = np.stack([s.C for s in systems])
    K = np.stack([s.K for s in systems])
    G = np.stack([s.G for s in systems])
    S = np.concatenate([M[:, :, free] + c.gamma * dt * C[:, :, free] + c.beta * dt * dt * K[:, :, free], -G], axis=2)
    Sinv = np.ascontiguousarray(np.linalg.inv(S))
    kc = np.stack([s.kc for s in systems])
    cc = np.stack([s.cc for s in systems])
    dof = np.array(measured, dtype=np.int64)
    is_acc = np.array([ch.kind == "acc" for ch in s0.channels])
    z = np.ascontiguousarray(channels, dtype=np.float64).reshape(1, len(channels), -1)  # one run
    out = np.empty((len(systems), s0.n_contacts, z.shape[1]))
    inverse_runs(Sinv, M, C, K, kc, cc, dof, is_acc, free, np.zeros(len(systems), dtype=np.int64), z,
                 np.array([z.shape[1]], dtype=np.int64), np.array([float(dt)]), c.gamma, c.beta, out)
    return out.transpose(0, 2, 1), np.stack([s.offsets_m for s in systems])


# ---------------------------------------------------------------------------------------------
# The objective (eq. 2.32–2.33)


class _Window(NamedTuple):
    x: np.ndarray  # common chainage grid of the centre of gravity's frame, m
    basis: np.ndarray  # (K, 2) orthonormal basis of {1, x} on the grid, for detrending


def _window(channels_list, dt, speeds, x0, spacing_m, skip_s, margin_m) -> _Window:
    lo = max(x + v * skip_s for x, v in zip(x0, speeds)) + margin_m
    hi = min(x + v * (len(z) - 1) * dt for x, v, z in zip(x0, speeds, channels_list)) - margin_m
    if hi - lo < 10 * spacing_m:
        raise ValueError(f"the vehicles' records share only [{lo:.2f}, {hi:.2f}] m: too short a common window")
    x = np.arange(lo, hi, spacing_m)
    X = np.stack([np.ones_like(x), x - x.mean()], axis=1)
    q, _ = np.linalg.qr(X)
    return _Window(x, q)


def fleet_aps(model: str, fleet_trials: Sequence[Sequence[dict[str, float]]], channels_list, dt: float,
              speeds, x0, window: _Window, detrend: bool = True) -> np.ndarray:
    """APs of every trial and vehicle on the common grid: (T, n_vehicles, n_contacts, K).

    ``fleet_trials[i]`` holds the T trial parameter sets of vehicle i.
    """
    n_veh = len(channels_list)
    T = len(fleet_trials[0])
    out = None
    for i in range(n_veh):
        ap, offsets = population_aps(model, fleet_trials[i], channels_list[i], dt)
        x_cg = x0[i] + speeds[i] * dt * np.arange(ap.shape[1])
        if out is None:
            out = np.empty((T, n_veh, ap.shape[2], window.x.size))
        for t in range(T):
            for c in range(ap.shape[2]):
                # the contact passes chainage x when the centre of gravity is at x − offset
                out[t, i, c] = np.interp(window.x - offsets[t, c], x_cg, ap[t, :, c])
    if detrend:
        out -= (out @ window.basis) @ window.basis.T
    return out


def objective(aps: np.ndarray) -> np.ndarray:
    """Eq. (2.32): Σ over vehicles, axles and points of (AP − fleet mean AP of that axle)², per trial (m²)."""
    dev = aps - aps.mean(axis=1, keepdims=True)
    return np.einsum("tick,tick->t", dev, dev)


# ---------------------------------------------------------------------------------------------
# Cross-Entropy with injections


def _as_list(x, n: int, what: str) -> list[dict[str, float]]:
    if isinstance(x, dict):
        return [dict(x) for _ in range(n)]
    x = [dict(p) for p in x]
    if len(x) != n:
        raise ValueError(f"{what}: expected one dict per vehicle ({n}), got {len(x)}")
    return x


def _draw(mu: np.ndarray, sd: np.ndarray, n: int, rng: np.random.Generator, floor: np.ndarray) -> np.ndarray:
    """``n`` draws of N(μ, σ²) truncated to positive values (redrawn), each (len(μ),)."""
    x = mu + sd * rng.standard_normal((n, mu.size))
    for _ in range(50):
        bad = x <= floor
        if not bad.any():
            break
        x[bad] = (mu + sd * rng.standard_normal((n, mu.size)))[bad]
    return np.maximum(x, floor)


def injection_sd(n_injection: int, sd0: np.ndarray) -> np.ndarray:
    """σ after the n-th injection: σ₀ for the first two, then σ₀·2/n (inverse proportion to n)."""
    return sd0 if n_injection <= 2 else sd0 * (2.0 / n_injection)


def cross_entropy_fleet(
    model: str,
    channels_list: Sequence[np.ndarray],
    dt: float,
    init_params: dict[str, float] | Sequence[dict[str, float]],
    init_sd: dict[str, float] | Sequence[dict[str, float]],
    rng: np.random.Generator,
    *,
    speeds: Sequence[float] | None = None,
    x0: Sequence[float] | None = None,
    spacing_m: float | None = None,
    population: int = 100,
    elite_fraction: float = ELITE_FRACTION,
    alpha: float = 0.7,
    beta: float = 0.8,
    q: int = 5,
    max_generations: int = 400,
    max_injections: int = 6,
    sd_tol: float = 1e-3,
    patience: int = 30,
    improve_tol: float = 1e-3,
    skip_s: float = 1.0,
    margin_m: float | None = None,
    detrend: bool = True,
    time_budget_s: float | None = None,
) -> tuple[list[dict[str, float]], list[dict]]:
    """Calibrate a fleet of one vehicle model by Cross-Entropy on the agreement of its APs (§2.4).

    Parameters
    ----------
    model : str
        Vehicle model (``"sprung_mass"``, ``"quarter_car"``, ``"half_car"``, …).
    channels_list : sequence of arrays (n_samples_i, n_channels)
        Each vehicle's measured channels (``system.channels`` order), sampled every ``dt`` s.
    init_params, init_sd : dict or one dict per vehicle
        Initial mean and sd of every parameter (SI units). A parameter with sd 0 is held fixed.
    rng : numpy.random.Generator
    speeds, x0 : sequences, optional
        Each vehicle's constant speed (m/s) and the chainage of its centre of gravity at the first
        sample (m). Default: every vehicle at 1 m/s from 0, i.e. compared sample by sample, as in the
        thesis where all vehicles drive alike.
    spacing_m : float, optional
        Grid spacing of the comparison (m); default the smallest distance travelled per sample.
    population, elite_fraction : int, float
        Trials per generation and the elite's share (thesis: 10 %).
    alpha, beta, q : float, float, int
        Smoothing of the mean (μ ← α μ_elite + (1−α) μ) and dynamic smoothing of the sd
        (β_t = β − β (1 − 1/t)^q, t the generation within the current phase).
    max_generations, max_injections : int
        Budget of generations, and of injections.
    sd_tol, patience, improve_tol : float, int, float
        A phase has converged when every σ/σ₀ < ``sd_tol`` or the best objective has not improved
        by a relative ``improve_tol`` for ``patience`` generations. The search stops when a phase
        that followed an injection improved the best by less than ``improve_tol`` (relative), after
        at least two injections, or when the injections are used up.
    skip_s, margin_m : float
        Transient skipped at each record's start (s) and margin kept from the common window's ends
        for axle offsets (m; default 1.5 × the largest initial offset).
    detrend : bool
        Remove each AP's least-squares line on the window (the unknown initial state's drift).
    time_budget_s : float, optional
        Stop after this much wall time.

    Returns
    -------
    params_list : list of dict
        The best trial found: each vehicle's full parameter set.
    history : list of dict
        Per generation: ``generation``, ``phase``, ``injections``, ``best`` and ``elite_mean``
        objective (m²), ``max_rel_sd`` (max σ/σ₀ over free parameters), ``evaluations``, ``seconds``.
    """
    if model not in MODELS:
        raise ValueError(f"model: unknown {model!r}")
    n_veh = len(channels_list)
    if n_veh < 2:
        raise ValueError("cross_entropy_fleet: a fleet needs at least two vehicles")
    names = list(MODELS[model].param_names())
    init_params = _as_list(init_params, n_veh, "init_params")
    init_sd = _as_list(init_sd, n_veh, "init_sd")
    offsets = np.concatenate([vehicle_from_params(model, p).system().offsets_m for p in init_params])
    if speeds is None and np.any(offsets != 0):
        raise ValueError(f"{model}: contacts away from the centre of gravity need each vehicle's speed (speeds=)")
    speeds = [1.0] * n_veh if speeds is None else [float(v) for v in speeds]
    x0 = [0.0] * n_veh if x0 is None else [float(x) for x in x0]
    if spacing_m is None:
        spacing_m = min(speeds) * dt
    if margin_m is None:  # room for the axles, whose trial positions vary
        margin_m = 1.5 * float(np.max(np.abs(offsets))) + spacing_m
    window = _window(channels_list, dt, speeds, x0, spacing_m, skip_s, margin_m)

    mu0 = np.array([[p[n] for n in names] for p in init_params], dtype=float)  # (n_veh, n_par)
    sd0 = np.array([[s.get(n, 0.0) for n in names] for s in init_sd], dtype=float)
    free = sd0 > 0
    mu, sd = mu0.copy(), sd0.copy()
    floor = 1e-3 * np.abs(mu0) + 1e-12
    n_elite = max(2, int(math.ceil(elite_fraction * population)))

    def evaluate(thetas: np.ndarray) -> np.ndarray:
        trials = [[dict(zip(names, thetas[t, i])) for t in range(len(thetas))] for i in range(n_veh)]
        return objective(fleet_aps(model, trials, channels_list, dt, speeds, x0, window, detrend))

    best_theta = mu0.copy()
    best = float(evaluate(mu0[None])[0])
    history: list[dict] = []
    t_start = time.perf_counter()
    evaluations = 1
    injections = 0
    phase_gen = 0
    phase_start_best = best
    last_improve_gen = 0
    gen = 0
    while gen < max_generations:
        gen += 1
        phase_gen += 1
        draws = _draw(mu[free], sd[free], population, rng, floor[free])
        thetas = np.repeat(mu[None], population, axis=0)
        thetas[:, free] = draws
        scores = evaluate(thetas)
        evaluations += population
        order = np.argsort(scores)
        elite = thetas[order[:n_elite]]
        if scores[order[0]] < best * (1.0 - improve_tol):
            last_improve_gen = phase_gen
        if scores[order[0]] < best:
            best, best_theta = float(scores[order[0]]), thetas[order[0]].copy()
        mu = alpha * elite.mean(axis=0) + (1.0 - alpha) * mu
        b_t = beta - beta * (1.0 - 1.0 / phase_gen) ** q
        sd = np.where(free, b_t * elite.std(axis=0) + (1.0 - b_t) * sd, 0.0)
        rel = float(np.max(sd[free] / sd0[free]))
        history.append({"generation": gen, "phase": injections, "injections": injections, "best": best,
                        "elite_mean": float(np.mean(scores[order[:n_elite]])), "max_rel_sd": rel,
                        "evaluations": evaluations, "seconds": time.perf_counter() - t_start})
        if time_budget_s is not None and time.perf_counter() - t_start > time_budget_s:
            log.info("cross-entropy: time budget reached at generation %d", gen)
            break
        converged = rel < sd_tol or phase_gen - last_improve_gen >= patience
        if not converged:
            continue
        gained = (phase_start_best - best) / phase_start_best if phase_start_best > 0 else 0.0
        if injections >= max_injections or (injections >= 2 and gained < improve_tol):
            log.info("cross-entropy: stopped after %d generations, %d injections (last gain %.2e)",
                     gen, injections, gained)
            break
        injections += 1
        mu = best_theta.copy()
        sd = np.where(free, injection_sd(injections, sd0), 0.0)
        phase_gen, last_improve_gen, phase_start_best = 0, 0, best
    params = [dict(zip(names, map(float, best_theta[i]))) for i in range(n_veh)]
    return params, history
