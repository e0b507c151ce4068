"""A carriage's run properties by Cross-Entropy with restarts: the thesis's batch calibration (§3.4.1),
kept to measure :func:`cloud.rail.calibration.calibrate_batch` against."""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Sequence

import numpy as np

from shared.vehicles.carriage import Carriage

from cloud.rail.calibration import FIXED, GLOBAL_FIT, RUN_NAMES, STAGES_M, RunEstimate
from cloud.rail.carriage_inverse import INVERSE_NAMES, carriage_aps
from cloud.rail.filters import lowpass_channels
from cloud.rail.mapping import EDGE_M, Mapper, window
from cloud.rail.records import RailRun


@dataclasses.dataclass(frozen=True)
class CrossEntropyResult:
    runs: list[RunEstimate]  # the best trial; lo95/hi95 are the last elite's 2.5/97.5 % quantiles
    best_objective: float  # eq. (3.11), m²
    initial_objective: float  # at the class means and the reported speeds
    generations: int
    restarts: int
    evaluations: int  # trial vectors scored
    seconds: float


def cross_entropy_batch(
    runs: Sequence[RailRun],
    prior_mean: dict[str, float],
    prior_sd: dict[str, float],
    rng: np.random.Generator,
    speed_rel_sd: float = 0.02,
    window_m: tuple[float, float] | None = None,
    population: int = 60,
    elite_fraction: float = 0.10,
    alpha: float = 0.7,
    max_generations: int = 200,
    restarts: int = 3,
    sd_tol: float = 0.02,
    patience: int = 8,
    time_budget_s: float | None = None,
) -> CrossEntropyResult:
    """The thesis's batch calibration: Cross-Entropy over the 3·n_b run properties (mv, Iv, v of
    every run), global properties held at the class means, objective eq. (3.11)–(3.12) — the squared
    differences of each run's AP under each axle from the batch mean AP of that axle, on a common
    chainage grid (each run mapped to space with its own trial speed, as the thesis converts to a
    reference speed). Trials are drawn from independent normals (initial mean: class means and the
    reported speed; initial sd: class sd and the GNSS error), the best 10 % give the next mean and sd
    (smoothed by ``alpha``), and a restart keeps the mean but resets the sd (Botev and Kroese, 2004)
    when the sd has collapsed (max σ/σ₀ < ``sd_tol``) or the best has not improved for ``patience``
    generations. The comparison grid and cubic removal are those of :func:`cloud.rail.calibration.calibrate_batch`; the
    low-pass (the same 2 m) is on the channels, once per run, although its edge error over-disperses
    the masses (:class:`cloud.rail.mapping.Mapper`): in space it would filter every trial of every run, and slow the
    reference for an accuracy it does not reach anyway.
    """
    t0 = time.perf_counter()
    runs = list(runs)
    n = len(runs)
    if n < 2:
        raise ValueError("cross_entropy_batch: a batch needs at least two runs")
    base = {k: float(prior_mean[k]) for k in GLOBAL_FIT + FIXED}
    offsets = Carriage(**base, mv=1.0, Iv=1.0, v=1.0).wheel_offsets_m()
    slack = 4 * speed_rel_sd
    grid = window(runs, offsets, window_m, speed_slack=slack)
    mapper = Mapper(grid)
    # The same primitives as ours: channels trimmed to what the window needs, every trial of a run
    # inverted in one compiled call and mapped in one interpolation.
    zs = [lowpass_channels(r, STAGES_M[-1])[: int(math.ceil((grid[-1] + EDGE_M - r.x0_m - offsets.min())
                                                     / (r.speed_mps * (1 - slack)) / r.dt)) + 2] for r in runs]
    theta_g = np.array([base[k] for k in INVERSE_NAMES[2:]])
    mu0 = np.array([[prior_mean["mv"], prior_mean["Iv"], r.speed_mps] for r in runs])
    sd0 = np.array([[prior_sd["mv"], prior_sd["Iv"], speed_rel_sd * r.speed_mps] for r in runs])
    floor = 0.2 * mu0

    def evaluate(thetas: np.ndarray) -> np.ndarray:  # (T, n, 3) → (T,)
        T = len(thetas)
        A = np.empty((T, n, 4, grid.size))
        for r, run in enumerate(runs):
            theta = np.column_stack([thetas[:, r, :2], np.broadcast_to(theta_g, (T, len(theta_g)))])
            aps = carriage_aps(theta, base["Lb"], base["Lv"], zs[r], run.dt)
            m = len(zs[r])
            A[:, r] = mapper.map_runs(aps[:, None], np.full(T, run.dt), np.full(T, run.x0_m), thetas[:, r, 2:3],
                                      np.full(T, m), offsets)[:, 0, 0]
        dev = A - A.mean(axis=1, keepdims=True)  # eq. (3.12): the batch mean under each axle
        return np.einsum("trik,trik->t", dev, dev)

    n_elite = max(2, int(math.ceil(elite_fraction * population)))
    mu, sd = mu0.copy(), sd0.copy()
    best_theta = mu0.copy()
    best = initial = float(evaluate(mu0[None])[0])
    evaluations, gen, n_restarts, stale = 1, 0, 0, 0
    elite = mu0[None]
    while gen < max_generations:
        if time_budget_s is not None and time.perf_counter() - t0 > time_budget_s:
            break
        gen += 1
        thetas = mu[None] + sd[None] * rng.standard_normal((population,) + mu.shape)
        thetas = np.maximum(thetas, floor[None])
        f = evaluate(thetas)
        evaluations += population
        order = np.argsort(f)
        elite = thetas[order[:n_elite]]
        if f[order[0]] < best * (1 - 1e-6):
            best, best_theta, stale = float(f[order[0]]), thetas[order[0]].copy(), 0
        else:
            stale += 1
        mu = alpha * elite.mean(axis=0) + (1 - alpha) * mu
        sd = alpha * elite.std(axis=0) + (1 - alpha) * sd
        if np.max(sd / sd0) < sd_tol or stale >= patience:
            if n_restarts >= restarts:
                break
            n_restarts += 1
            mu, sd, stale = best_theta.copy(), sd0.copy(), 0
    lo = np.quantile(elite, 0.025, axis=0)
    hi = np.quantile(elite, 0.975, axis=0)
    estimates = [RunEstimate(run.pass_id, dict(zip(RUN_NAMES, map(float, best_theta[r]))),
                             dict(zip(RUN_NAMES, map(float, lo[r]))), dict(zip(RUN_NAMES, map(float, hi[r]))))
                 for r, run in enumerate(runs)]
    return CrossEntropyResult(estimates, best, initial, gen, n_restarts, evaluations, time.perf_counter() - t0)
