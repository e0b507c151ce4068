"""Batch self-calibration of a carriage's run properties (thesis §3.4): body mass ``mv``, pitch inertia
``Iv`` and speed ``v`` of every run of a batch, the global properties known (to ~5 %).

Every run of the batch crossed the same track, so under the right run properties the apparent
profiles (AP) of all runs and all four wheels agree in space. The thesis searches the 3·n_b run
properties by Cross-Entropy with restarts (:func:`cross_entropy_batch`, the reference here). Ours
(:func:`calibrate_batch`) is Bayesian:

    −log p(θ | data) = ‖B AP(θ) − c(θ)‖² / (2σ²) + ½ Σ_r ‖(θ_r − μ_r) / s‖² + ½ ‖(θ_g − μ_g) / s_g‖²,

θ_r = log(mv, Iv, v) of run r, θ_g the log global properties (below); B maps a run's AP under wheel i onto a common chainage grid
(x = x0 + v·t + offset_i) and removes a cubic (the inverse's integrators turn noise into slow drift,
and the absolute level is unobservable); c(θ) is the consensus, the mean of all runs' and wheels'
mapped APs (the track profile profiled out, as in :mod:`cloud.calibration`); the prior is the
class (mean, sd) of ``mv`` and ``Iv`` from the registry and the run's GNSS speed with its relative
error.

One consensus for all four wheels makes the speed identifiable in absolute terms: the same
rail bump reaches wheel 3 2·Lv/v after wheel 1, whatever the GNSS says (so the speed is as good as
the bogie spacing Lv is known; its class sd is added to the speed's interval). Each run's speed is
started from a grid search of its own wheels' agreement (:func:`_speed_from_wheels`).

Beyond the thesis, the carriage's global properties (``mb, Ib, kp, cp, ks, cs``, common to every
run) are calibrated with the batch, their class sd (~5 %) as the prior: with them fixed at the class
means, the run masses absorb the global errors (a 7 % error in ``ks`` moves every ``mv`` ~7 %),
while the batch — different masses and speeds over one track — identifies them; the class means of
``mv`` and ``Iv`` (known for a route, as in the thesis's blind test) pin the common scale.

Gauss–Newton with Levenberg damping on all 3·n_b + 6 unknowns at once (the normal matrix of the
profiled consensus has a closed form from per-run blocks, :func:`calibrate_batch`), in stages of
decreasing shortest wavelength; σ² is re-estimated from the residual with its along-track
correlation; the Gauss–Newton Hessian at the optimum gives Laplace 95 % intervals, with the global
properties' uncertainty marginalised.

Pure functions on arrays: no I/O, no transport.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Sequence

import numpy as np
from scipy.signal import butter, sosfiltfilt

from shared.vehicles.carriage import Carriage

RUN_NAMES = ("mv", "Iv", "v")
#: Global properties calibrated with the batch (their class sd is the prior); the wheelset mass does
#: not enter the wheels-on-rail model and the lengths are known from drawings.
GLOBAL_FIT = ("mb", "Ib", "kp", "cp", "ks", "cs")
FIXED = ("mw", "Lb", "Lv")
#: Shortest wavelength compared in each stage, m (continuation: long waves first, where the misfit is
#: smooth in every property, then sharper). Below 2 m there is mostly noise and sleeper-scale detail.
STAGES_M = (16.0, 6.0, 2.0)
MAX_WAVELENGTH_M = 60.0
GRID_M = 0.1  # comparison grid spacing, m
EDGE_M = 1.5  # margin kept from the wheels' coverage (trial speeds move it), m
FD_LOG_STEP = 1e-3
Z95 = 1.959963984540054


@dataclasses.dataclass(frozen=True)
class RailRun:
    """One run's measured bogie channels (n, 4) in ``bogie1_acc, bogie1_pitch_rate, bogie2_acc,
    bogie2_pitch_rate`` order at step ``dt`` (s), its reported speed (m/s) and the chainage of the
    body's centre of gravity at the first sample (m)."""

    pass_id: str
    channels: np.ndarray
    dt: float
    speed_mps: float
    x0_m: float = 0.0

    def __post_init__(self) -> None:
        z = np.asarray(self.channels)
        if z.ndim != 2 or z.shape[1] != 4 or len(z) < 16:
            raise ValueError(f"RailRun {self.pass_id}: channels must be (n >= 16, 4), got {z.shape}")
        if not (self.dt > 0 and self.speed_mps > 0 and math.isfinite(self.x0_m)):
            raise ValueError(f"RailRun {self.pass_id}: need dt > 0, speed_mps > 0 and a finite x0_m")


@dataclasses.dataclass(frozen=True)
class RunEstimate:
    pass_id: str
    mean: dict[str, float]
    lo95: dict[str, float]
    hi95: dict[str, float]


@dataclasses.dataclass(frozen=True)
class BatchFit:
    runs: list[RunEstimate]
    globals_: dict[str, float]  # the batch's estimate of the carriage's global properties
    grid_m: np.ndarray  # the comparison window, m
    consensus_m: np.ndarray  # the batch's AP on it (cubic removed), m
    sigma_m: float  # residual sd per grid point, m
    correlation: float  # residual correlation factor (information per point ÷ this)
    iterations: int
    seconds: float

    def rows(self, vehicle_id: str) -> list[dict]:
        """``vehicles.parquet`` rows (interfaces.md §3): one per run and property, with ``pass_id``."""
        return [{"vehicle_id": vehicle_id, "param": k, "mean": r.mean[k], "lo95": r.lo95[k], "hi95": r.hi95[k],
                 "pass_id": r.pass_id} for r in self.runs for k in RUN_NAMES]


def _lowpass(run: RailRun, min_wavelength_m: float = 2.0) -> np.ndarray:
    """The channels without wavelengths shorter than ``MIN_WAVELENGTH_M`` at the run's reported speed
    (zero phase; a linear filter commutes with the linear inverse, so this is the AP's low-pass)."""
    z = np.asarray(run.channels, dtype=float)
    nyq = 0.5 / run.dt
    fc = run.speed_mps / min_wavelength_m
    if fc < 0.9 * nyq:
        z = sosfiltfilt(butter(4, fc / nyq, output="sos"), z, axis=0)
    return z


def _window(runs: Sequence[RailRun], offsets: np.ndarray, window_m: tuple[float, float] | None,
            speed_slack: float) -> np.ndarray:
    """The common grid every wheel of every run covers at any speed within ``speed_slack`` (relative)."""
    lo = max(r.x0_m + offsets.max() for r in runs) + EDGE_M
    hi = min(r.x0_m + offsets.min() + r.speed_mps * (1 - speed_slack) * (len(r.channels) - 1) * r.dt
             for r in runs) - EDGE_M
    if window_m is not None:
        lo, hi = max(lo, window_m[0]), min(hi, window_m[1])
    if hi - lo < 20.0:
        raise ValueError(f"the runs share only [{lo:.1f}, {hi:.1f}] m of track: too short a window to calibrate")
    return np.arange(lo, hi, GRID_M)


class _Mapper:
    """B: a run's AP (time) → its four wheels on the grid, a cubic removed from each (the unknown
    level and the integrators' slow drift of sensor noise)."""

    def __init__(self, grid: np.ndarray):
        self.grid = grid
        X = np.stack([((grid - grid.mean()) / np.ptp(grid)) ** k for k in range(4)], axis=1)
        self.basis, _ = np.linalg.qr(X)

    def detrend(self, a: np.ndarray) -> np.ndarray:
        return a - (a @ self.basis) @ self.basis.T

    def map(self, ap: np.ndarray, dt: float, x0: float, v: float, offsets: np.ndarray) -> np.ndarray:
        t = np.arange(len(ap)) * dt
        out = np.empty((4, self.grid.size))
        ti = (self.grid[None, :] - x0 - offsets[:, None]) / v  # when wheel i passes each grid point
        for i in range(4):
            out[i] = np.interp(ti[i], t, ap[:, i])
        return self.detrend(out)


def _aps(base: dict[str, float], trials: Sequence[dict[str, float]], z: np.ndarray, dt: float) -> np.ndarray:
    """APs (T, n, 4) of one run's channels under each trial (the inverse of
    :mod:`shared.dynamics.inverse`, batched over trials)."""
    from .reference.cross_entropy import population_aps

    return population_aps("carriage", [{**base, **t} for t in trials], z, dt)[0]


def _speed_from_wheels(run: RailRun, z: np.ndarray, params: dict[str, float], offsets: np.ndarray,
                       mapper: "_Mapper", slack: float) -> float:
    """log(v / reported v) at which the run's own four wheels agree best (global grid search).

    A bump reaches wheel 3 2·Lv/v after wheel 1: the run's speed follows from its own data,
    whatever the class parameters' errors (which affect the wheels alike). A cheap global search
    (mapping only, no inverse per step) that starts Gauss–Newton in the right basin whatever the
    GNSS error (the misfit in a speed is oscillatory beyond a shift of a short wavelength).
    """
    ap = _aps(params, [{"mv": params["mv"], "Iv": params["Iv"], "v": run.speed_mps}], z, run.dt)[0]
    steps = np.linspace(-slack, slack, int(round(2 * slack / 2.5e-4)) + 1)
    cost = []
    for s in steps:
        A = mapper.map(ap, run.dt, run.x0_m, run.speed_mps * math.exp(s), offsets)
        cost.append(float(((A - A.mean(axis=0)) ** 2).sum()))
    return float(steps[int(np.argmin(cost))])


def _gauss_newton(evaluate, normal_equations, x, mu, P, max_iter, tol):
    """Levenberg-damped Gauss–Newton on ‖e(x)‖²/(2σ²) + ½‖x − μ‖²_P, σ² re-estimated each step."""
    e, D, A = evaluate(x, True)
    lam = 1e-3
    kappa = _correlation_factor(e)
    sigma2 = float((e**2).mean()) * kappa
    it = 0
    for it in range(1, max_iter + 1):

        def neglogpost(e, x):
            return 0.5 * float((e**2).sum()) / sigma2 + 0.5 * float((((x - mu) ** 2) * P).sum())

        JtJ, Jte = normal_equations(e, D)
        H = JtJ / sigma2 + np.diag(P)
        grad = Jte / sigma2 + (x - mu) * P
        f0 = neglogpost(e, x)
        while True:
            step = np.clip(np.linalg.solve(H + lam * np.diag(np.diag(H)), -grad), -0.2, 0.2)
            e_new, _, _ = evaluate(x + step, False)
            if neglogpost(e_new, x + step) <= f0:
                lam = max(lam / 3, 1e-7)
                break
            lam *= 10
            if lam > 1e6:
                step = np.zeros_like(step)
                break
        x = x + step
        e, D, A = evaluate(x, True)
        kappa = _correlation_factor(e)
        sigma2 = float((e**2).mean()) * kappa
        if np.abs(step).max() < tol or lam > 1e6:
            break
    return x, e, D, A, sigma2, kappa, it


def _correlation_factor(e: np.ndarray) -> float:
    """1 + 2 Σ ρ_k of the residual along the grid (up to its first zero): grid points per
    independent piece of information."""
    flat = e.reshape(-1, e.shape[-1])
    f = np.fft.rfft(flat, 2 * flat.shape[1], axis=1)
    ac = np.fft.irfft(np.abs(f) ** 2, axis=1)[:, : flat.shape[1]].sum(axis=0)
    rho = ac / ac[0]
    cut = int(np.argmax(rho <= 0)) if np.any(rho <= 0) else len(rho)
    return float(max(1.0, 1.0 + 2.0 * rho[1:cut].sum()))


def calibrate_batch(
    runs: Sequence[RailRun],
    prior_mean: dict[str, float],
    prior_sd: dict[str, float],
    speed_rel_sd: float = 0.02,
    window_m: tuple[float, float] | None = None,
    max_iter: int = 30,
    tol: float = 1e-5,
) -> BatchFit:
    """Run properties of every run of a batch, and the carriage's global properties (module docstring).

    ``prior_mean``/``prior_sd``: the carriage class of the registry (all Table 3.1 names; ``v`` is
    not used: each run's reported speed is its prior, with relative sd ``speed_rel_sd``).
    ``window_m``: restrict the comparison to this chainage range (e.g. off a bridge). Returns the
    run estimates with 95 % intervals (the global properties' uncertainty marginalised).
    """
    t_start = time.perf_counter()
    runs = list(runs)
    n = len(runs)
    if n < 2:
        raise ValueError("calibrate_batch: a batch needs at least two runs")
    for k in ("mv", "Iv") + GLOBAL_FIT + FIXED:
        if not (prior_mean.get(k, 0) > 0 and prior_sd.get(k, -1) >= 0):
            raise ValueError(f"calibrate_batch: the class needs a positive mean and an sd of {k}")
    fixed = {k: float(prior_mean[k]) for k in FIXED}
    offsets = Carriage(**fixed, **{k: prior_mean[k] for k in GLOBAL_FIT}, mv=1.0, Iv=1.0, v=1.0).wheel_offsets_m()
    grid = _window(runs, offsets, window_m, speed_slack=4 * speed_rel_sd)
    mapper = _Mapper(grid)
    zs: list[np.ndarray] = []
    n_g = len(GLOBAL_FIT)
    mu_loc = np.array([[math.log(prior_mean["mv"]), math.log(prior_mean["Iv"]), math.log(r.speed_mps)] for r in runs])
    s_loc = np.array([prior_sd["mv"] / prior_mean["mv"], prior_sd["Iv"] / prior_mean["Iv"], speed_rel_sd])
    mu_g = np.log([prior_mean[k] for k in GLOBAL_FIT])
    s_g = np.array([max(prior_sd[k] / prior_mean[k], 1e-4) for k in GLOBAL_FIT])
    mu = np.concatenate([mu_loc.ravel(), mu_g])
    P = np.concatenate([np.tile(1.0 / s_loc**2, n), 1.0 / s_g**2])
    n_par = 3 * n + n_g
    N = 4 * n

    def unpack(x):
        return x[: 3 * n].reshape(n, 3), x[3 * n:]

    def run_model(r, loc, glob, with_jac):
        mv, iv, v = np.exp(loc)
        base = {**fixed, **dict(zip(GLOBAL_FIT, np.exp(glob)))}
        trials = [{"mv": mv, "Iv": iv, "v": v}]
        if with_jac:
            h = math.exp(FD_LOG_STEP)
            trials += [{"mv": mv * h, "Iv": iv, "v": v}, {"mv": mv, "Iv": iv * h, "v": v}]
            for k in GLOBAL_FIT:  # a global's step, with the others at base
                trials.append({"mv": mv, "Iv": iv, "v": v, k: base[k] * h})
        run = runs[r]
        aps = _aps(base, trials, zs[r], run.dt)
        A = mapper.map(aps[0], run.dt, run.x0_m, v, offsets)
        if not with_jac:
            return A, None
        h = math.exp(FD_LOG_STEP)
        D = np.empty((3 + n_g,) + A.shape)
        D[0] = (mapper.map(aps[1], run.dt, run.x0_m, v, offsets) - A) / FD_LOG_STEP
        D[1] = (mapper.map(aps[2], run.dt, run.x0_m, v, offsets) - A) / FD_LOG_STEP
        D[2] = (mapper.map(aps[0], run.dt, run.x0_m, v * h, offsets) - A) / FD_LOG_STEP
        for j, k in enumerate(GLOBAL_FIT):
            D[3 + j] = (mapper.map(aps[3 + j], run.dt, run.x0_m, v, offsets) - A) / FD_LOG_STEP
        return A, D

    def evaluate(x, with_jac):
        loc, glob = unpack(x)
        out = [run_model(r, loc[r], glob, with_jac) for r in range(n)]
        A = np.stack([o[0] for o in out])  # (n, 4, K)
        e = A - A.mean(axis=(0, 1))
        D = np.stack([o[1] for o in out]) if with_jac else None  # (n, 3 + n_g, 4, K)
        return e, D, A

    def normal_equations(e, D):
        """JᵀJ and Jᵀe of the profiled consensus residual (J = ∂e/∂x), from the per-run blocks."""
        Dl, Dg = D[:, :3], D[:, 3:]
        g = Dl.sum(axis=2)  # (n, 3, K)
        Dgc = Dg - Dg.mean(axis=(0, 2), keepdims=True)  # global columns, consensus removed
        JtJ = np.zeros((n_par, n_par))
        Hl = np.einsum("rjik,rlik->rjl", Dl, Dl)
        for r in range(n):
            JtJ[3 * r:3 * r + 3, 3 * r:3 * r + 3] = Hl[r]
        JtJ[: 3 * n, : 3 * n] -= np.einsum("rjk,slk->rjsl", g, g).reshape(3 * n, 3 * n) / N
        cross = np.einsum("rjik,rlik->rjl", Dl, Dgc).reshape(3 * n, n_g)
        JtJ[: 3 * n, 3 * n:] = cross
        JtJ[3 * n:, : 3 * n] = cross.T
        JtJ[3 * n:, 3 * n:] = np.einsum("rjik,rlik->jl", Dgc, Dgc)
        Jte = np.concatenate([np.einsum("rjik,rik->rj", Dl, e).ravel(), np.einsum("rjik,rik->j", Dg, e)])
        return JtJ, Jte

    x = mu.copy()
    x[2: 3 * n: 3] += [_speed_from_wheels(r, z, {**fixed, **{k: prior_mean[k] for k in GLOBAL_FIT + ("mv", "Iv")}},
                                          offsets, mapper, 4 * speed_rel_sd)
                       for r, z in zip(runs, (_lowpass(r, STAGES_M[-1]) for r in runs))]
    it = 0
    for stage, min_wavelength in enumerate(STAGES_M):
        zs[:] = [_lowpass(r, min_wavelength) for r in runs]
        x, e, D, A, sigma2, kappa, n_it = _gauss_newton(evaluate, normal_equations, x, mu, P,
                                                         max_iter if stage == len(STAGES_M) - 1 else 8, tol)
        it += n_it
    JtJ, _ = normal_equations(e, D)
    sd = np.sqrt(np.diag(np.linalg.inv(JtJ / sigma2 + np.diag(P))))
    loc, glob = unpack(x)
    sd_loc = sd[: 3 * n].reshape(n, 3)
    # The speed is measured against the bogie spacing 2·Lv (module docstring): its relative error
    # moves every run's speed alike, outside the data's reach.
    sd_loc[:, 2] = np.hypot(sd_loc[:, 2], prior_sd["Lv"] / prior_mean["Lv"])
    estimates = []
    for r, run in enumerate(runs):
        mean = {k: float(math.exp(loc[r, j])) for j, k in enumerate(RUN_NAMES)}
        lo = {k: float(math.exp(loc[r, j] - Z95 * sd_loc[r, j])) for j, k in enumerate(RUN_NAMES)}
        hi = {k: float(math.exp(loc[r, j] + Z95 * sd_loc[r, j])) for j, k in enumerate(RUN_NAMES)}
        estimates.append(RunEstimate(run.pass_id, mean, lo, hi))
    globals_fit = {k: float(math.exp(glob[j])) for j, k in enumerate(GLOBAL_FIT)}
    return BatchFit(estimates, globals_fit, grid, A.mean(axis=(0, 1)), math.sqrt(sigma2 / kappa), kappa, it,
                    time.perf_counter() - t_start)


# ---------------------------------------------------------------------------------------------
# The thesis's reference: Cross-Entropy with restarts (§3.4.1)


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
    generations. The comparison grid, low-pass and cubic removal are those of :func:`calibrate_batch`.
    """
    t0 = time.perf_counter()
    runs = list(runs)
    n = len(runs)
    if n < 2:
        raise ValueError("cross_entropy_batch: a batch needs at least two runs")
    base = {k: float(prior_mean[k]) for k in GLOBAL_FIT + FIXED}
    offsets = Carriage(**base, mv=1.0, Iv=1.0, v=1.0).wheel_offsets_m()
    grid = _window(runs, offsets, window_m, speed_slack=4 * speed_rel_sd)
    mapper = _Mapper(grid)
    zs = [_lowpass(r, STAGES_M[-1]) for r in runs]
    mu0 = np.array([[prior_mean["mv"], prior_mean["Iv"], r.speed_mps] for r in runs])
    sd0 = np.array([[prior_sd["mv"], prior_sd["Iv"], speed_rel_sd * r.speed_mps] for r in runs])
    floor = 0.2 * mu0

    def evaluate(thetas: np.ndarray) -> np.ndarray:  # (T, n, 3) → (T,)
        T = len(thetas)
        A = np.empty((T, n, 4, grid.size))
        for r, run in enumerate(runs):
            trials = [{"mv": th[r, 0], "Iv": th[r, 1], "v": th[r, 2]} for th in thetas]
            aps = _aps(base, trials, zs[r], run.dt)
            for t in range(T):
                A[t, r] = mapper.map(aps[t], run.dt, run.x0_m, thetas[t, r, 2], offsets)
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
