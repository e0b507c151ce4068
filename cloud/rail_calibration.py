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

Cost (the thesis's CE needs thousands of batch evaluations; this needs tens): the early stages see
no short waves, so their channels are decimated to ~20 samples per period of the stage's cut-off
and compared on a coarser grid; the finite-difference Jacobian (9 inverses per run) is refreshed
every third accepted step, with chord steps (1 inverse per run) in between; samples past what the
window needs are not inverted; and every trial of every run is one compiled inverse call
(:func:`carriage_aps_runs`) and one interpolation (:meth:`_Mapper.map_runs`).

Pure functions on arrays: no I/O, no transport.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Sequence

import numpy as np
from numba import njit
from scipy.signal import sosfiltfilt

from shared.vehicles.carriage import Carriage

from .batched_inverse import inverse_runs

RUN_NAMES = ("mv", "Iv", "v")
#: Global properties calibrated with the batch (their class sd is the prior); the wheelset mass does
#: not enter the wheels-on-rail model and the lengths are known from drawings.
GLOBAL_FIT = ("mb", "Ib", "kp", "cp", "ks", "cs")
FIXED = ("mw", "Lb", "Lv")
#: Shortest wavelength compared in each stage, m (continuation: long waves first, where the misfit is
#: smooth in every property, then sharper). Below 2 m there is mostly noise and sleeper-scale detail.
STAGES_M = (16.0, 6.0, 2.0)
#: A stage's comparison grid has about this many points per its shortest wavelength (a stage
#: without short waves needs fewer), at a multiple of GRID_M.
POINTS_PER_WAVELENGTH = 20
#: A stage's channels are decimated (after its low-pass) to at least this many samples per period of
#: its cut-off v/λ_min: the early stages need no 500 Hz inverse. The last stage keeps the logger's rate
#: unless :func:`calibrate_batch` is told otherwise.
SAMPLES_PER_CUTOFF = 20
MAX_WAVELENGTH_M = 60.0
GRID_M = 0.1  # finest comparison grid spacing, m
SPEED_SEARCH_M = 6.0  # shortest wavelength of the speed's grid search (:func:`_speed_from_wheels`), m
SPEED_STEP = 0.01  # its step in log speed
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
    #: The global properties' posterior covariance of their logs (:data:`GLOBAL_FIT` order), marginal
    #: over the runs: what a later batch that holds these globals carries into its intervals
    #: (``calibrate_batch(held_globals_cov=…)``).
    globals_log_cov: np.ndarray | None = None

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
        z = sosfiltfilt(_butter4_sos(fc / nyq), z, axis=0)
    return z


def _butter4_sos(wn: float) -> np.ndarray:
    """``scipy.signal.butter(4, wn, output="sos")`` in closed form (same sections, same order, to
    ~1e-13 relative): the bilinear transform of the prewarped analog poles. scipy's design took
    ~0.3 ms a call — 6 % of a production batch calibration, which designs one per run and stage."""
    warped = 4.0 * math.tan(math.pi * wn / 2.0)  # scipy's prewarp at fs = 2
    pa = warped * np.exp(1j * np.pi * np.array([5.0, 7.0]) / 8.0)  # one pole of each conjugate pair
    pd = (4.0 + pa) / (4.0 - pa)
    gain = warped**4 / float(np.real(np.prod(4.0 - pa) * np.prod(4.0 - np.conj(pa))))
    sos = np.zeros((2, 6))
    for row, i in enumerate(np.argsort(np.abs(pd))):  # scipy's "nearest" pairing: nearest the unit circle last
        sos[row] = (1.0, 2.0, 1.0, 1.0, -2.0 * pd[i].real, abs(pd[i]) ** 2)
    sos[0, :3] *= gain
    return sos


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

    def map_runs(self, aps: np.ndarray, dts: np.ndarray, x0: np.ndarray, speeds: np.ndarray, lengths: np.ndarray,
                 offsets: np.ndarray) -> np.ndarray:
        """(R, T, N, 4) APs of R runs (the first ``lengths[r]`` samples at step ``dts[r]``, from
        ``x0[r]``), each mapped at each of its run's speeds ``speeds`` (R, S): (R, T, S, 4, K), by
        linear interpolation, each query clipped to its record (:func:`_map_kernel`)."""
        R, T, N, nw = aps.shape
        out = np.empty((R, T, speeds.shape[1], nw, len(self.grid)))
        _map_kernel(aps, np.asarray(dts, dtype=float), np.asarray(x0, dtype=float), np.asarray(speeds, dtype=float),
                    np.asarray(lengths, dtype=np.int64), np.asarray(offsets, dtype=float), self.grid, out)
        return self.detrend(out)


@njit(cache=True)
def _map_kernel(aps, dts, x0, speeds, lengths, offsets, grid, out):
    """out[r, t, s, i, k] = AP of run r, trial t, wheel i at chainage grid[k] at speed speeds[r, s]:
    linear interpolation between the bracketing samples, computed (the samples are uniform in time),
    not searched. What ``np.interp`` over the records laid end to end gave (to rounding; the end to
    end abscissae lost ~1e-11 to their offsets), without its (R, T, 4, N) abscissa array: a 50-run
    Jacobian mapping (and its detrend) 0.04 → 0.017 s. CE's evaluations share it."""
    R, T = aps.shape[0], aps.shape[1]
    for r in range(R):
        top = lengths[r] - 1
        for s in range(speeds.shape[1]):
            for i in range(aps.shape[3]):
                for k in range(grid.shape[0]):
                    u = (grid[k] - x0[r] - offsets[i]) / speeds[r, s] / dts[r]
                    u = min(max(u, 0.0), float(top))
                    j = min(int(u), top - 1)
                    f = u - j
                    for t in range(T):
                        a0 = aps[r, t, j, i]
                        out[r, t, s, i, k] = a0 + (aps[r, t, j + 1, i] - a0) * f


#: The carriage's parameters the inverse depends on, in the order of :func:`carriage_aps`' columns.
INVERSE_NAMES = ("mv", "Iv", "mb", "Ib", "kp", "cp", "ks", "cs")
#: Newmark γ of the calibration's inverse. Not the edge's 0.8: its numerical damping (~(γ − ½)·ω·Δt/2,
#: +0.013 on the bogies' ~7 Hz bounce, ζ 0.06) is read as a lower cp relative to the masses, and
#: cp's prior then pulls the batch's common mass scale up: mv +1.5 % on average beyond what the
#: priors explain (six quick seeds and the blind test's healthy batches: common mv error −0.3…+5.0 %
#: at 0.8, −1.4…+3.5 % at 0.5, against −1.7…+1.6 % the class priors alone give; the blind
#: test's mv coverage 0.62/0.12 → 0.92/0.54 on profiles 1/2, median |mv error| 2.4 → 1.9 %; on the
#: benchmark's rail-track batch, whose prior error the bias happened to offset, 0.80 → 0.99 %, Iv
#: 0.44 → 0.79 %). ``tests/test_rail_calibration.py`` checks the common error over seeds.
INVERSE_GAMMA = 0.5
_MEASURED = np.arange(2, 6)  # the channels (RailRun order) measure the bogies' DOFs: acc, rate, acc, rate
_IS_ACC = np.array([True, False, True, False])
_FREE = np.arange(2)  # the body's bounce and pitch


def carriage_aps_runs(theta: np.ndarray, run_of: np.ndarray, Lb: float, Lv: float, z: np.ndarray,
                      lengths: np.ndarray, dts: np.ndarray) -> np.ndarray:
    """APs (T, N, 4) under T parameter sets ``theta`` (T, 8) in :data:`INVERSE_NAMES` order, trial t
    on run ``run_of[t]``'s channels ``z`` (R, N, 4) (the first ``lengths[r]`` samples, step
    ``dts[r]``; the rest of its AP is zero). Same result as :func:`cloud.reference.cross_entropy.
    population_aps` per run; the carriage's matrices are assembled in array form — M, C, K are
    linear in the parameters (:meth:`shared.vehicles.carriage.Carriage._body_bogie`) — and the whole
    batch is one compiled call, instead of a ``Carriage`` per trial and a call per run."""
    from shared.dynamics.newmark import newmark_constants

    theta = np.asarray(theta, dtype=float)
    run_of = np.asarray(run_of, dtype=np.int64)
    dts = np.asarray(dts, dtype=float)
    T = len(theta)
    mv, Iv, mb, Ib, kp, cp, ks, cs = theta.T
    s1 = np.array([1.0, Lv, -1.0, 0.0, 0.0, 0.0])
    s2 = np.array([1.0, -Lv, 0.0, 0.0, -1.0, 0.0])
    sec = np.outer(s1, s1) + np.outer(s2, s2)
    G = np.zeros((6, 4))
    G[2, 0], G[3, 0], G[2, 1], G[3, 1] = 1.0, Lb, 1.0, -Lb
    G[4, 2], G[5, 2], G[4, 3], G[5, 3] = 1.0, Lb, 1.0, -Lb
    prim = G @ G.T
    K = ks[:, None, None] * sec + kp[:, None, None] * prim
    C = cs[:, None, None] * sec + cp[:, None, None] * prim
    M = np.zeros((T, 6, 6))
    for j, m in enumerate((mv, Iv, mb, Ib, mb, Ib)):
        M[:, j, j] = m
    c = newmark_constants(float(dts.min()), INVERSE_GAMMA)
    dt = dts[run_of][:, None, None]
    S = np.concatenate([M[:, :, :2] + c.gamma * dt * C[:, :, :2] + c.beta * dt * dt * K[:, :, :2],
                        np.broadcast_to(-G, (T, 6, 4))], axis=2)
    out = np.zeros((T, 4, z.shape[1]))  # wheel-major: what the mapping reads in one piece
    # the four contacts are the primary suspensions (kp, cp)
    inverse_runs(np.ascontiguousarray(np.linalg.inv(S)), M, C, K, np.repeat(kp[:, None], 4, axis=1),
                 np.repeat(cp[:, None], 4, axis=1), _MEASURED, _IS_ACC, _FREE, run_of,
                 np.ascontiguousarray(z, dtype=np.float64), np.asarray(lengths, dtype=np.int64), dts, c.gamma, c.beta,
                 out)
    return out.transpose(0, 2, 1)


def carriage_aps(theta: np.ndarray, Lb: float, Lv: float, z: np.ndarray, dt: float) -> np.ndarray:
    """APs (T, n, 4) of one run's channels ``z`` (n, 4) under T parameter sets (:func:`carriage_aps_runs`)."""
    z = np.asarray(z, dtype=float)
    return carriage_aps_runs(theta, np.zeros(len(theta), dtype=np.int64), Lb, Lv, z[None], np.array([len(z)]),
                             np.array([dt]))


def _speed_from_wheels(runs: Sequence[RailRun], stage: dict, theta: np.ndarray, fixed: dict[str, float],
                       offsets: np.ndarray, mapper: "_Mapper", slack: float) -> np.ndarray:
    """log(v / reported v) of each run at which its own four wheels agree best (global grid search).

    A bump reaches wheel 3 2·Lv/v after wheel 1: the run's speed follows from its own data,
    whatever the class parameters' errors (which affect the wheels alike). A cheap global search
    (one inverse per run, then mapping only) that starts Gauss–Newton in the right basin whatever
    the GNSS error (the misfit in a speed is oscillatory beyond a shift of a short wavelength).
    ``stage``: the runs' channels low-passed to :data:`SPEED_SEARCH_M` (``calibrate_batch``).

    A wrong speed s moves wheel 3's AP against wheel 1's by ~2·Lv·s (~19 m·s), so the misfit's
    shortest period in s is ~λ_min/19 m (~0.3 at 6 m): steps of 0.01 resolve it, and the stages
    of Gauss–Newton refine from there (the first, at 16 m, has a basin of ~±0.2).
    """
    n = len(runs)
    aps = carriage_aps_runs(np.repeat(theta[None], n, axis=0), np.arange(n), fixed["Lb"], fixed["Lv"],
                            stage["z"], stage["lengths"], stage["dts"])[:, None]
    steps = np.linspace(-slack, slack, int(round(2 * slack / SPEED_STEP)) + 1)
    v = np.array([r.speed_mps for r in runs])
    A = mapper.map_runs(aps, stage["dts"], np.array([r.x0_m for r in runs]), v[:, None] * np.exp(steps),
                        stage["lengths"], offsets)[:, 0]  # (n, S, 4, K)
    cost = ((A - A.mean(axis=2, keepdims=True)) ** 2).sum(axis=(2, 3))
    return steps[np.argmin(cost, axis=1)]


def _gauss_newton(evaluate, normal_equations, x, mu, P, max_iter, tol, jacobian_every=1):
    """Levenberg-damped Gauss–Newton on ‖e(x)‖²/(2σ²) + ½‖x − μ‖²_P, σ² re-estimated each step.

    ``jacobian_every``: the Jacobian (finite differences: 9 inverses per run) is refreshed after
    every so many accepted steps and reused in between (chord steps: one inverse per run each,
    the damping's descent test unchanged), ending on a refreshed one whenever the loop stops early.
    """
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
        e_new = A_new = None
        while True:
            step = np.clip(np.linalg.solve(H + lam * np.diag(np.diag(H)), -grad), -0.2, 0.2)
            e_new, _, A_new = evaluate(x + step, False)
            if neglogpost(e_new, x + step) <= f0:
                lam = max(lam / 3, 1e-7)
                break
            lam *= 10
            if lam > 1e6:
                step = np.zeros_like(step)
                break
        x = x + step
        done = np.abs(step).max() < tol or lam > 1e6 or it == max_iter
        if it % jacobian_every == 0 or done:
            e, D, A = evaluate(x, True)
        elif lam <= 1e6:
            e, A = e_new, A_new
        kappa = _correlation_factor(e)
        sigma2 = float((e**2).mean()) * kappa
        if done:
            break
    return x, e, D, A, sigma2, kappa, it


def _correlation_factor(e: np.ndarray) -> float:
    """1 + 2 Σ ρ_k of the residual along the grid (up to its first zero): grid points per
    independent piece of information."""
    flat = e.reshape(-1, e.shape[-1])
    flat = flat[:: max(1, len(flat) // 64)]  # ~64 rows estimate it as well as all, at a fraction of the FFTs
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
    jacobian_every: int = 3,
    final_decimation: int = 1,
    stages_m: Sequence[float] = STAGES_M,
    held_globals_cov: np.ndarray | None = None,
) -> BatchFit:
    """Run properties of every run of a batch, and the carriage's global properties (module docstring).

    ``prior_mean``/``prior_sd``: the carriage class of the registry (all Table 3.1 names; ``v`` is
    not used: each run's reported speed is its prior, with relative sd ``speed_rel_sd``).
    ``window_m``: restrict the comparison to this chainage range (e.g. off a bridge). Returns the
    run estimates with 95 % intervals (the global properties' uncertainty marginalised).
    ``jacobian_every``: refresh the finite-difference Jacobian after every so many accepted steps
    (:func:`_gauss_newton`); ``final_decimation``: the last stage's channels at every so many
    samples (1: the logger's rate; at 2 the inverse's own discretisation error grew enough to move
    mv by ~1.4 points on a 4-run, 100 m batch);
    ``stages_m``: the stages' shortest wavelengths (m).
    ``held_globals_cov``: when ``prior_sd`` holds the global properties (sd 0: another batch's
    estimate, :attr:`BatchFit.globals_`), that estimate's log covariance (:attr:`BatchFit.
    globals_log_cov`): the fit still holds them, but the intervals carry their uncertainty — the
    Laplace covariance given the globals plus their error propagated through the runs' sensitivity
    to them (the full matrix: the globals' errors are strongly correlated along the common mass
    scale). On the batch the covariance came from, this is exactly the free fit's marginal interval.
    Without it a held global's error is shared by every run's interval unseen (the blind test's
    damaged batches: mv/Iv coverage 0.00–0.58 with the healthy batch's globals).
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
    slack = 4 * speed_rel_sd
    grid = _window(runs, offsets, window_m, speed_slack=slack)
    # Samples past the last the window can need (trailing wheel, slowest trial speed) are not
    # inverted: the inverse is causal, and the low-pass is applied to the whole record first.
    keep = [min(len(r.channels), int(math.ceil((grid[-1] + EDGE_M - r.x0_m - offsets.min())
                                              / (r.speed_mps * (1 - slack)) / r.dt)) + 2) for r in runs]
    mapper = stage = None
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

    x0s = np.array([r.x0_m for r in runs])
    h = math.exp(FD_LOG_STEP)

    def evaluate(x, with_jac):
        """Residual e (n, 4, K), Jacobian blocks D (n, 3 + n_g, 4, K) and the mapped APs A."""
        loc, glob = unpack(x)
        p = np.exp(loc)  # (n, 3): mv, Iv, v
        theta = np.column_stack([p[:, :2], np.broadcast_to(np.exp(glob), (n, n_g))])  # INVERSE_NAMES order
        T = 1
        if with_jac:  # trial 0 as is, then each of mv, Iv and the globals stepped in turn
            T = 1 + theta.shape[1]
            theta = np.repeat(theta[:, None], T, axis=1)
            theta[:, 1:] *= 1.0 + (h - 1.0) * np.eye(T - 1)
        aps = carriage_aps_runs(theta.reshape(n * T, -1), np.repeat(np.arange(n), T), fixed["Lb"], fixed["Lv"],
                                stage["z"], stage["lengths"], stage["dts"]).reshape(n, T, -1, 4)
        mapped = mapper.map_runs(aps, stage["dts"], x0s, p[:, 2:3], stage["lengths"], offsets)[:, :, 0]
        A = mapped[:, 0]  # (n, 4, K)
        e = A - A.mean(axis=(0, 1))
        if not with_jac:
            return e, None, A
        faster = mapper.map_runs(aps[:, :1], stage["dts"], x0s, p[:, 2:3] * h, stage["lengths"], offsets)[:, 0, 0]
        D = np.empty((n, 3 + n_g) + A.shape[1:])  # written in place: ~20 MB a Jacobian at 50 runs
        np.subtract(mapped[:, 1:3], A[:, None], out=D[:, :2])
        np.subtract(faster, A, out=D[:, 2])
        np.subtract(mapped[:, 3:], A[:, None], out=D[:, 3:])
        D /= FD_LOG_STEP
        return e, D, A

    def normal_equations(e, D):
        """JᵀJ and Jᵀe of the profiled consensus residual (J = ∂e/∂x), from the per-run blocks."""
        # Products over (wheel, grid point) as batched matrix products (BLAS), not einsum loops.
        Dl, Dg = D[:, :3], D[:, 3:]
        g = Dl.sum(axis=2)  # (n, 3, K)
        Dgc = Dg - Dg.mean(axis=(0, 2), keepdims=True)  # global columns, consensus removed
        Fl = Dl.reshape(n, 3, -1)
        Fg = Dgc.reshape(n, n_g, -1)
        JtJ = np.zeros((n_par, n_par))
        Hl = Fl @ Fl.transpose(0, 2, 1)
        for r in range(n):
            JtJ[3 * r:3 * r + 3, 3 * r:3 * r + 3] = Hl[r]
        g2 = g.reshape(3 * n, -1)
        JtJ[: 3 * n, : 3 * n] -= (g2 @ g2.T) / N
        cross = (Fl @ Fg.transpose(0, 2, 1)).reshape(3 * n, n_g)
        JtJ[: 3 * n, 3 * n:] = cross
        JtJ[3 * n:, : 3 * n] = cross.T
        JtJ[3 * n:, 3 * n:] = (Fg @ Fg.transpose(0, 2, 1)).sum(axis=0)
        ev = e.reshape(n, -1, 1)
        Jte = np.concatenate([(Fl @ ev).ravel(), (Dg.reshape(n, n_g, -1) @ ev).sum(axis=0).ravel()])
        return JtJ, Jte

    staged = {}

    def stage_channels(min_wavelength, decimation=None):
        """The runs' channels low-passed for a stage, trimmed and decimated, stacked (R, N, 4) with
        their lengths and steps (kept: the speed search and the 6 m stage ask for the same)."""
        if (min_wavelength, decimation) not in staged:
            staged[min_wavelength, decimation] = _stage_channels(min_wavelength, decimation)
        return staged[min_wavelength, decimation]

    def _stage_channels(min_wavelength, decimation):
        chans = []
        for r, k in zip(runs, keep):
            q = decimation or max(1, int(1.0 / (r.dt * SAMPLES_PER_CUTOFF * r.speed_mps / min_wavelength)))
            chans.append((_lowpass(r, min_wavelength)[:k:q], r.dt * q))
        lengths = np.array([len(c[0]) for c in chans])
        z = np.zeros((n, lengths.max(), 4))
        for r, c in enumerate(chans):
            z[r, : lengths[r]] = c[0]
        return {"z": z, "lengths": lengths, "dts": np.array([c[1] for c in chans])}

    def mapper_for(min_wavelength):
        return _Mapper(grid[:: max(1, int(round(min_wavelength / POINTS_PER_WAVELENGTH / GRID_M)))])

    x = mu.copy()
    theta0 = np.array([prior_mean[k] for k in INVERSE_NAMES])
    x[2: 3 * n: 3] += _speed_from_wheels(runs, stage_channels(SPEED_SEARCH_M), theta0, fixed, offsets,
                                         mapper_for(SPEED_SEARCH_M), slack)
    it = 0
    for i_stage, min_wavelength in enumerate(stages_m):
        last = i_stage == len(stages_m) - 1
        mapper = mapper_for(min_wavelength)
        stage = stage_channels(min_wavelength, final_decimation if last else None)
        x, e, D, A, sigma2, kappa, n_it = _gauss_newton(evaluate, normal_equations, x, mu, P,
                                                         max_iter if last else 8, tol, jacobian_every)
        it += n_it
    JtJ, _ = normal_equations(e, D)
    H = JtJ / sigma2 + np.diag(P)
    cov = np.linalg.inv(H)
    if held_globals_cov is not None:
        # The runs' estimates given the held globals, plus the held values' error propagated through
        # their sensitivity to them: Σ_loc = H_ll⁻¹ + S Σ_g Sᵀ with S = −H_ll⁻¹ H_lg.
        c_ll = np.linalg.inv(H[: 3 * n, : 3 * n])
        S = -c_ll @ H[: 3 * n, 3 * n:]
        cov[: 3 * n, : 3 * n] = c_ll + S @ np.asarray(held_globals_cov, dtype=float) @ S.T
    sd = np.sqrt(np.diag(cov))
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
    return BatchFit(estimates, globals_fit, mapper.grid, A.mean(axis=(0, 1)), math.sqrt(sigma2 / kappa), kappa, it,
                    time.perf_counter() - t_start, cov[3 * n:, 3 * n:].copy())


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
    slack = 4 * speed_rel_sd
    grid = _window(runs, offsets, window_m, speed_slack=slack)
    mapper = _Mapper(grid)
    # The same primitives as ours: channels trimmed to what the window needs, every trial of a run
    # inverted in one compiled call and mapped in one interpolation.
    zs = [_lowpass(r, STAGES_M[-1])[: int(math.ceil((grid[-1] + EDGE_M - r.x0_m - offsets.min())
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
