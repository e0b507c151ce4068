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

Three things the thesis leaves implicit are made explicit here. A logger switched on while driving
does not know the vehicle's initial state, so each AP carries an offset and a linear drift from the
neutral integrators of the inverse (and a short transient, skipped): each AP is detrended (its
least-squares line removed) on the common window before comparison, which removes the same linear
part of the true profile from every vehicle and so cannot bias the agreement. And vehicles may
drive at different speeds: APs are compared on a chainage grid, each contact at its own offset
(for a half-car, the trial axle spacing moves axle positions, which is what makes D1, D2
identifiable at all). And the APs are compared in the band where they carry the road: each
vehicle's channels are low-passed (zero-phase, in time) to wavelengths above ``lowpass_m`` (default
1 m), which for a linear inverse is the AP low-passed. The inverse differentiates a rate channel (a
half-car's pitch rate) and then the wheel's motion, so its noise gain grows as f² above the wheel
hop: on `road-hc` at 1 % noise (of each channel's sd, 500 Hz) the AP under the *true* parameters is
~140 mm rms of noise against a road of a few mm, nearly all at wavelengths under 0.5 m, and
resampling to the grid aliases it into every band. Point by point, eq. (2.32) then measures noise,
and is smallest for the parameters that amplify noise least (stiff tyres, light wheels: 1/700 of its
value at the truth for K_t × 3, m_u × 0.1), whatever the road says. Cut at 1 m (above every wheel
hop at these speeds) the objective at the truth is 7× its noise-free value, and moving off the
truth raises it: K_t × 1.3, m_u × 0.7, I_s × 0.9, D × 0.95 or K_s1 × 1.1 by 6–13×, a damper × 1.2
by 1.9×, K_t2 × 1.1 by 1.4×; cut at 0.5 m it is still 240× its noise-free value and still lower for
stiffer tyres (road-hc seed-0 logs). ``lowpass_m=None`` is eq. (2.32) on raw APs; what the search
reaches with and without the cut is in ``docs/results.md`` (``driveby reproduce road``).

Only ratios are identifiable (divide the equations of motion by the body mass): the objective is
flat along each vehicle's mass scale, so absolute values wander while ratios converge — exactly
what the thesis reports (Tables 2.3, 2.5, 2.6).

Evaluating a trial runs the inverse of every vehicle under new parameters;
:func:`shared.dynamics.population.population_aps` runs the readable inverse step of
:mod:`shared.dynamics.inverse` for a whole population in one compiled call, without compiling a
state-space model per trial.
"""

from __future__ import annotations

import logging
import math
import time
from typing import NamedTuple, Sequence

import numpy as np
from scipy.signal import butter, sosfiltfilt

from shared.dynamics.population import population_aps
from shared.vehicles import MODELS, vehicle_from_params

log = logging.getLogger(__name__)

ELITE_FRACTION = 0.10  # thesis §2.4: "the 10% best of the trial vehicle property sets"
#: Shortest wavelength compared (m): above every wheel hop at road speeds, below which the inverse's
#: noise gain (∝ f²) swamps the road at 1 % noise (module docstring).
LOWPASS_M = 1.0


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


def lowpass_channels(channels: np.ndarray, dt: float, speed: float, lowpass_m: float) -> np.ndarray:
    """One vehicle's ``channels`` (n_samples, n_channels) low-passed in time to wavelengths above
    ``lowpass_m`` at its ``speed`` (zero-phase 4th-order Butterworth, cutoff speed/lowpass_m Hz).

    The inverse is linear and time-invariant, so this is the AP low-passed (up to the start
    transient, which the comparison skips) — once per vehicle instead of once per trial, and
    without the aliasing that resampling an AP full of short-wave noise to the grid would add.
    """
    cutoff_hz = speed / lowpass_m
    if not 0.0 < cutoff_hz < 0.5 / dt:
        raise ValueError(f"lowpass_m: {lowpass_m} m at {speed:.3g} m/s is {cutoff_hz:.3g} Hz, "
                         f"not below the Nyquist frequency {0.5 / dt:.3g} Hz")
    return sosfiltfilt(butter(4, cutoff_hz, fs=1.0 / dt, output="sos"), np.asarray(channels, float), axis=0)


def _prepare(channels_list, dt, speeds, x0, spacing_m, skip_s, margin_m, lowpass_m):
    """(channels as compared, speeds, x0, window) for a fleet's records."""
    n_veh = len(channels_list)
    if speeds is None and lowpass_m is not None:
        raise ValueError("lowpass_m: a wavelength needs each vehicle's speed (speeds=), or lowpass_m=None")
    speeds = [1.0] * n_veh if speeds is None else [float(v) for v in speeds]
    x0 = [0.0] * n_veh if x0 is None else [float(x) for x in x0]
    if lowpass_m is not None:
        channels_list = [lowpass_channels(z, dt, v, lowpass_m) for z, v in zip(channels_list, speeds)]
    return channels_list, speeds, x0, _window(channels_list, dt, speeds, x0, spacing_m, skip_s, margin_m)


def fleet_objective(model: str, params_list: Sequence[dict[str, float]], channels_list, dt: float, *,
                    speeds: Sequence[float], x0: Sequence[float], spacing_m: float, margin_m: float,
                    skip_s: float = 1.0, detrend: bool = True, lowpass_m: float | None = LOWPASS_M) -> float:
    """Eq. (2.32) for one parameter set per vehicle, compared as :func:`cross_entropy_fleet` compares
    them with the same settings (pass it the same ``margin_m``): e.g. to tell a search that stopped
    short (its best above the objective at better parameters) from an objective whose minimum is off."""
    channels_list, speeds, x0, window = _prepare(channels_list, dt, speeds, x0, spacing_m, skip_s, margin_m,
                                                 lowpass_m)
    return float(objective(fleet_aps(model, [[dict(p)] for p in params_list], channels_list, dt, speeds, x0,
                                     window, detrend))[0])


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
    min_injections: int = 2,
    sd_tol: float = 1e-3,
    patience: int = 30,
    improve_tol: float = 1e-3,
    skip_s: float = 1.0,
    margin_m: float | None = None,
    detrend: bool = True,
    lowpass_m: float | None = LOWPASS_M,
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
        at least ``min_injections`` injections, or when the injections are used up.
    min_injections : int
        Injections before the search may stop for want of gain. The first two reset σ to σ₀, a
        restart that seldom beats the best at once; the later, narrower ones refine. The half-car
        fleet of `road-hc` (seed 0, 1 % noise, population 200) stopped after two with its best
        objective 4.1× the objective at the true parameters (averaged median error 8.5 %; noise-free
        24×, 8.6 %); allowed all six (``min_injections=6``; the 800-generation budget ended it at
        five), 1.04× (5.4 %; noise-free 2.0×, 5.2 %).
    skip_s, margin_m : float
        Transient skipped at each record's start (s) and margin kept from the common window's ends
        for axle offsets (m; default 1.5 × the largest initial offset).
    detrend : bool
        Remove each AP's least-squares line on the window (the unknown initial state's drift).
    lowpass_m : float or None
        Compare the APs at wavelengths above this (m): each vehicle's channels are low-passed in
        time at its speed (module docstring: the inverse's noise gain); None compares raw APs,
        eq. (2.32) literally.
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
    if min_injections < 0:
        raise ValueError(f"min_injections: must be >= 0, got {min_injections}")
    names = list(MODELS[model].param_names())
    init_params = _as_list(init_params, n_veh, "init_params")
    init_sd = _as_list(init_sd, n_veh, "init_sd")
    offsets = np.concatenate([vehicle_from_params(model, p).system().offsets_m for p in init_params])
    if speeds is None and np.any(offsets != 0):
        raise ValueError(f"{model}: contacts away from the centre of gravity need each vehicle's speed (speeds=)")
    if spacing_m is None:
        spacing_m = (1.0 if speeds is None else min(float(v) for v in speeds)) * dt
    if margin_m is None:  # room for the axles, whose trial positions vary
        margin_m = 1.5 * float(np.max(np.abs(offsets))) + spacing_m
    channels_list, speeds, x0, window = _prepare(channels_list, dt, speeds, x0, spacing_m, skip_s, margin_m,
                                                 lowpass_m)

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
        if injections >= max_injections or (injections >= min_injections and gained < improve_tol):
            log.info("cross-entropy: stopped after %d generations, %d injections (last gain %.2e)",
                     gen, injections, gained)
            break
        injections += 1
        mu = best_theta.copy()
        sd = np.where(free, injection_sd(injections, sd0), 0.0)
        phase_gen, last_improve_gen, phase_start_best = 0, 0, best
    params = [dict(zip(names, map(float, best_theta[i]))) for i in range(n_veh)]
    return params, history
