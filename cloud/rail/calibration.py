"""Batch self-calibration of a carriage's run properties (thesis §3.4): body mass ``mv``, pitch inertia
``Iv`` and speed ``v`` of every run of a batch, the global properties known (to ~5 %).

Every run of the batch crossed the same track, so under the right run properties the apparent
profiles (AP) of all runs and all four wheels agree in space. The thesis searches the 3·n_b run
properties by Cross-Entropy with restarts (:func:`cloud.reference.rail_cross_entropy.cross_entropy_batch`,
kept to measure against). Ours (:func:`calibrate_batch`) is Bayesian:

    −log p(θ | data) = ‖B AP(θ) − c(θ)‖² / (2σ²) + ½ Σ_r ‖(θ_r − μ_r) / s‖² + ½ ‖(θ_g − μ_g) / s_g‖²,

θ_r = log(mv, Iv, v) of run r, θ_g the log global properties (below); B maps a run's AP under wheel i onto a common chainage grid
(x = x0 + v·t + offset_i) and removes a cubic (the inverse's integrators turn noise into slow drift,
and the absolute level is unobservable); c(θ) is the consensus, the mean of all runs' and wheels'
mapped APs (the track profile profiled out, as in :mod:`cloud.road.calibration`); the prior is the
class (mean, sd) of ``mv`` and ``Iv`` from the registry and the run's GNSS speed with its relative
error.

One consensus for all four wheels makes the speed identifiable against the carriage's lengths:
the same rail bump reaches wheel 3 2·Lv/v after wheel 1, whatever the GNSS says. The lengths
(:data:`LENGTH_FIT`) are calibrated with the batch under their class prior: a carriage whose bogie
spacing is off its class mean would otherwise put every run's speed off by as much. The wheels'
delays fix the ratios of the speeds and lengths; their common scale only stretches the consensus.
The data do see that scale a little — on a wave longer than the wheelbase a bogie's pitch is the
rail's slope and its vertical velocity v times that slope, so the accelerometer against the gyro
reads the speed — but roughly (the misfit along the scale is bumpy at the noise's level, and
Gauss–Newton's local curvature there claims a precision the misfit does not have), and it rests on
the two sensors' relative scale factors, which no log calibrates. So the scale is placed by the
anchors alone (:func:`_anchored_scale`): the GNSS speeds, whose per-run errors average out over
the batch, and the lengths' class prior; the last stage holds the lengths there, and every speed's
95 % interval carries that scale's sd (:func:`_anchor_sd`). Each run's speed is started from a
grid search of its own wheels' agreement relative to the class's lengths
(:func:`_speed_from_wheels`), the common scale from the batch mean of those against the GNSS.

Beyond the thesis, the carriage's global properties (``mb, Ib, kp, cp, ks, cs``, common to every
run) are calibrated with the batch, their class sd (~5 %) as the prior: with them fixed at the class
means, the run masses absorb the global errors (an error in ``ks`` moves every ``mv`` by about as
much), while the batch — different masses and speeds over one track — identifies them; the class means of
``mv`` and ``Iv`` (known for a route, as in the thesis's blind test) pin the common scale.

Records need not start at rest. The inverse starts the body at rest, right for a record that
starts in static equilibrium (a logger switched on at a standstill; our simulator's runs) and wrong
for one that starts mid-motion: the body's free oscillation then rides every AP, and on Table 3.1's
suspension it decays slowly (bounce 1.16 Hz, pitch 1.4 Hz, ζ ≈ 0.07–0.08: e-folding in ~2 s, 60 m
at 30 m/s), so no start-up window a 150 m record can spare removes it. Given θ the AP is
affine in the body's initial state (:data:`~cloud.rail.carriage_inverse.BODY0_NAMES`), so each run
carries it as a nuisance with a weak prior, its Jacobian columns exact from the same forward-mode pass. A free state costs
information when the record did start at rest, so before the last
stage each run's fitted state is tested against rest (Wald χ², 4 dof, :data:`REST_CHI2`) and held
at rest where consistent — a spike-and-slab prior decided per run. A mid-motion record's first
chainage comes from the log (GNSS speed × time: decimetres off after half a second), so each run
also carries a chainage shift (prior sd ``position_sd_m``). The shift is tested the same way
(against the log's chainage, :data:`SHIFT_CHI2`) and held at zero where consistent: held where the
middle stage left it instead (centimetres), the last stage's speeds would take up its error.

Gauss–Newton with Levenberg damping on all 8·n_b + 8 unknowns at once (the normal matrix of the
profiled consensus has a closed form from per-run blocks, :func:`calibrate_batch`), in stages of
decreasing shortest wavelength; σ² is re-estimated from the residual with its along-track
correlation; the 95 % intervals are the Gauss–Newton sandwich at the optimum, H⁻¹ (JᵀΣJ/σ⁴ + prior)
H⁻¹ with Σ the noise's covariance along the track and between a run's wheels as the residual shows
it (:func:`noise_information`; the Hessian alone would take the noise as white), with the global
properties' uncertainty marginalised.

Cost (the thesis's CE needs thousands of batch evaluations; this needs tens): the early stages see
no short waves, so their channels are decimated to ~20 samples per period of the stage's cut-off
and compared on a coarser grid; the Jacobian is exact, the AP's derivatives in the 8 inverse
parameters and the body's initial state carried through the inverse's recursion in forward mode
(:func:`~cloud.rail.carriage_inverse.carriage_aps_sensitivities`: one pass per run at a few inverses'
cost, where finite differences need one per parameter and are only good to their step; the state's
columns are skipped once every run is held at rest), the speed's and shift's columns finite
differences of the mapping alone; it is refreshed every third accepted step, with chord steps (1
inverse per run) in between; samples past what the window needs are not inverted; every trial of
every run is one compiled inverse call (:func:`~cloud.rail.carriage_inverse.carriage_aps_runs`) and one
interpolation (:meth:`~cloud.rail.mapping.Mapper.map_runs`); the stage's low-pass is a compiled
zero-phase filter of the mapped rows in space (:func:`~cloud.rail.filters.sosfiltfilt_rows`; on the
channels before the inverse it biases the masses, :class:`~cloud.rail.mapping.Mapper`).
``python -m benchmarks rail`` times it.

Pure functions on arrays: no I/O, no transport.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Sequence

import numpy as np
import scipy.fft


from cloud.rail.carriage_inverse import (BODY0_NAMES, INVERSE_NAMES, N_SENS, carriage_aps_runs,
                                         carriage_aps_sensitivities)
from cloud.rail.filters import lowpass_channels
from cloud.rail.mapping import EDGE_M, GRID_M, Mapper, window
from cloud.rail.records import RailRun

RUN_NAMES = ("mv", "Iv", "v")
#: Global properties of the inverse calibrated with the batch (their class sd is the prior): the
#: columns of :data:`~cloud.rail.carriage_inverse.INVERSE_NAMES` after the run's own two.
GLOBAL_FIT = ("mb", "Ib", "kp", "cp", "ks", "cs")
#: The carriage's lengths, calibrated with the batch too (their class sd is the prior): the bogie
#: spacing sets every run's speed scale (a bump reaches wheel 3 2·Lv/v after wheel 1), so a
#: carriage whose Lv is off its class mean would put every speed off by as much, and the GNSS
#: speeds' per-run errors, averaged over the batch, are what anchors it.
LENGTH_FIT = ("Lb", "Lv")
#: Not passed to the inverse as a calibrated column: the wheelset mass does not enter the
#: wheels-on-rail model; the lengths are arguments of the inverse, not columns of θ.
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
#: A decimated stage's channels are low-passed (against aliasing) at its shortest wavelength ÷ this:
#: the decimated rate's Nyquist is at ÷ 10 and the stage's own low-pass is in space
#: (:class:`~cloud.rail.mapping.Mapper`).
ANTIALIAS_FACTOR = 4.0
MAX_WAVELENGTH_M = 60.0
SPEED_SEARCH_M = 6.0  # shortest wavelength of the speed's grid search (:func:`_speed_from_wheels`), m
SPEED_STEP = 0.01  # its step in log speed
FD_LOG_STEP = 1e-3  # the lengths' Jacobian columns through the inverse: a one-sided difference, log length
#: The stages before the last stop on steps below this (log): they only bring the last one into its
#: basin, which it then converges from to ``tol`` (the stage's optimum is not the last stage's).
STAGE_TOL_LOG = 1e-3
#: A Jacobian's runs are differentiated and mapped this many at a time (a few MB of work arrays
#: that stay in cache and are reused, instead of ~40 MB fresh pages per Jacobian).
JACOBIAN_CHUNK_RUNS = 8
#: The last stage's Jacobian may be this far (log, every coordinate) from the optimum: the Laplace
#: intervals then use it instead of a fresh one at the end: J moves about a per cent over such a
#: step, the intervals' widths much less.
LAPLACE_REUSE_LOG = 0.01
Z95 = 1.959963984540054
#: :func:`noise_information` keeps the wavenumbers up to the last where the residual's power times
#: the Jacobian's is above this fraction of its peak: beyond the stage's low-pass both are down at
#: the leakage floor of their ends, and the products' cost is in proportion to the bins kept.
NOISE_BAND_FLOOR = 1e-6


@dataclasses.dataclass(frozen=True)
class RunEstimate:
    pass_id: str
    mean: dict[str, float]
    lo95: dict[str, float]
    hi95: dict[str, float]
    #: :func:`calibrate_batch`: whether the record was found to start at rest (the body's initial
    #: state then held at rest), and the Wald statistic of its fitted initial state (χ², 4 dof).
    started_at_rest: bool | None = None
    rest_wald: float | None = None
    #: :func:`calibrate_batch`: the record's fitted chainage shift (m): its first sample was at
    #: ``x0_m + shift_m``. Fitted jointly with the speed, so whoever keys the run in chainage with
    #: the calibrated speed must add it (without it, a batch's runs sat 4–5 cm apart at the span).
    shift_m: float = 0.0


@dataclasses.dataclass(frozen=True)
class BatchFit:
    runs: list[RunEstimate]
    globals_: dict[str, float]  # the batch's estimate of the carriage's global properties (GLOBAL_FIT + LENGTH_FIT)
    grid_m: np.ndarray  # the comparison window, m
    consensus_m: np.ndarray  # the batch's AP on it (cubic removed), m
    sigma_m: float  # residual sd per grid point, m
    correlation: float  # residual correlation factor (information per point ÷ this)
    iterations: int
    seconds: float
    #: The global properties' posterior covariance of their logs (:data:`GLOBAL_FIT` + :data:`LENGTH_FIT` order), marginal
    #: over the runs: what a later batch that holds these globals carries into its intervals
    #: (``calibrate_batch(held_globals_cov=…)``).
    globals_log_cov: np.ndarray | None = None

    def rows(self, vehicle_id: str) -> list[dict]:
        """``vehicles.parquet`` rows (interfaces.md §3): one per run and property, with ``pass_id``."""
        return [{"vehicle_id": vehicle_id, "param": k, "mean": r.mean[k], "lo95": r.lo95[k], "hi95": r.hi95[k],
                 "pass_id": r.pass_id} for r in self.runs for k in RUN_NAMES]


#: :func:`calibrate_batch` carries the initial state in these units (m, rad, m/s, rad/s): as many
#: times its typical posterior sd as a log unit is the masses', so the step tolerance means the same
#: for both (in mm and mm/s the state's steps never fall below it and the stages run out of
#: iterations). Its prior sd (same units as SI): weak, beyond a body's motion on a track.
BODY0_UNIT = np.array([1e-2, 1e-3, 1e-1, 1e-2])
BODY0_PRIOR_SD = np.array([0.05, 0.01, 0.2, 0.05])
#: A run's unknowns in :func:`calibrate_batch`: log mv, log Iv, log v, the chainage shift of its
#: record (m) and its body's initial state (BODY0_UNIT), in this order.
N_LOCAL = len(RUN_NAMES) + 1 + len(BODY0_NAMES)
_I_SHIFT, _I_BODY = len(RUN_NAMES), len(RUN_NAMES) + 1
CHAINAGE_GAUGE_SD_M = 1e-3  # the runs' mean shift is held to the logs' (:func:`calibrate_batch`), m
#: The shift's Jacobian column: a central difference of the mapping with this step, m — about a
#: sample's length at speed, over which the linear interpolation's kinks average out (at 1 mm the
#: column jumps from kink to kink and Gauss–Newton crawls), a fraction of a per cent off for the 2 m
#: waves.
SHIFT_FD_M = 0.03
#: A run whose fitted initial state is within this of rest (Wald χ², 4 dof: the 99.9 % quantile) is
#: held at rest (to ``REST_SD``, m, rad, m/s, rad/s: a tight prior, rest as the logger saw it).
REST_CHI2 = 18.4668
REST_SD = 1e-7
#: A run whose fitted chainage shift is within this of zero (Wald χ², 1 dof, 99.9 %) keeps the
#: log's chainage (module docstring).
SHIFT_CHI2 = 10.8276


def wheel_offsets(Lb: float, Lv: float) -> np.ndarray:
    """The carriage's wheel positions ahead of the body's centre of gravity (m; wheel 1 leads), as
    :meth:`shared.vehicles.carriage.Carriage.wheel_offsets_m`."""
    return np.array([Lv + Lb, Lv - Lb, -Lv + Lb, -Lv - Lb])


def _speed_from_wheels(runs: Sequence[RailRun], stage: dict, theta: np.ndarray, fixed: dict[str, float],
                       offsets: np.ndarray, mapper: "Mapper", slack: float) -> np.ndarray:
    """log(v / reported v) of each run at which its own four wheels agree best (global grid search).

    A bump reaches wheel 3 2·Lv/v after wheel 1: the run's speed follows from its own data,
    whatever the class parameters' errors (which affect the wheels alike). A cheap global search
    (one inverse per run, then mapping only) that starts Gauss–Newton in the right basin whatever
    the GNSS error (the misfit in a speed is oscillatory beyond a shift of a short wavelength).
    ``stage``: the runs' channels for :data:`SPEED_SEARCH_M` (``calibrate_batch``), ``mapper`` its
    low-pass.

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


def _wheelbase_from_wheels(runs: Sequence[RailRun], stage: dict, theta: np.ndarray, fixed: dict[str, float],
                           log_speeds: np.ndarray, mapper: "Mapper", slack: float) -> float:
    """log(Lb / class Lb) at which every run's four wheels agree best at its speed ``log_speeds``
    (log of the reported), Lv at the class's (global grid search, as :func:`_speed_from_wheels`):
    a wheelbase off its class mean by more than a short wave's basin would start Gauss–Newton
    where the wheels' delays are matched wrongly (the speed search relative to the class's Lv
    finds v/Lv whatever the wheelbase; this finds Lb/Lv)."""
    n = len(runs)
    aps = carriage_aps_runs(np.repeat(theta[None], n, axis=0), np.arange(n), fixed["Lb"], fixed["Lv"],
                            stage["z"], stage["lengths"], stage["dts"])[:, None]
    v = np.array([r.speed_mps for r in runs]) * np.exp(log_speeds)
    x0 = np.array([r.x0_m for r in runs])
    steps = np.linspace(-slack, slack, int(round(2 * slack / SPEED_STEP)) + 1)
    cost = []
    for s in steps:
        A = mapper.map_runs(aps, stage["dts"], x0, v[:, None], stage["lengths"],
                            wheel_offsets(fixed["Lb"] * math.exp(s), fixed["Lv"]))[:, 0, 0]  # (n, 4, K)
        cost.append(float(((A - A.mean(axis=1, keepdims=True)) ** 2).sum()))
    return float(steps[int(np.argmin(cost))])


def _gauss_newton(evaluate, normal_equations, x, mu, P, max_iter, tol, jacobian_every=1, final_jacobian=True,
                  max_step=0.2, Q=None):
    """Levenberg-damped Gauss–Newton on ‖e(x)‖²/(2σ²) + ½‖x − μ‖²_P, σ² re-estimated each step;
    converged when the damped step is below ``tol`` (log) in every coordinate (not taken), or
    after ``max_iter`` iterations.

    ``jacobian_every``: the Jacobian is refreshed after every so many accepted steps and reused in
    between (chord steps: one inverse per run each, the damping's descent test unchanged; JᵀJ is
    formed once per Jacobian). ``final_jacobian`` (the last stage): the returned D, which the Laplace
    intervals use, was taken within :data:`LAPLACE_REUSE_LOG` of the optimum in every coordinate
    — if the J at convergence is older, it is refreshed and the iteration goes on (a chord step's
    gradient is its J's, so its fixed point moves a little with J). Otherwise D is whichever was
    computed last. ``max_step``: a step's cap per coordinate (scalar or array); ``Q``: a dense prior
    precision added to ``diag(P)`` (the chainage gauge of :func:`calibrate_batch`).
    """
    if Q is None:
        Q = np.zeros((len(x), len(x)))
    e, D, A = evaluate(x, True)
    x_jac = x
    lam = 1e-3
    kappa = _correlation_factor(e)
    sigma2 = float((e**2).mean()) * kappa
    it = 0
    JtJ = None
    for it in range(1, max_iter + 1):

        def neglogpost(e, x):
            return 0.5 * float((e**2).sum()) / sigma2 + 0.5 * float((((x - mu) ** 2) * P).sum()) \
                + 0.5 * float((x - mu) @ Q @ (x - mu))

        JtJ, Jte = normal_equations(e, D, JtJ)
        H = JtJ / sigma2 + np.diag(P) + Q
        grad = Jte / sigma2 + (x - mu) * P + Q @ (x - mu)
        f0 = neglogpost(e, x)
        e_new = A_new = None
        while True:
            step = np.clip(np.linalg.solve(H + lam * np.diag(np.diag(H)), -grad), -max_step, max_step)
            if np.abs(step).max() < tol:  # converged: a step this small is not worth an evaluation
                step = None
                break
            e_new, _, A_new = evaluate(x + step, False)
            if neglogpost(e_new, x + step) <= f0:
                lam = max(lam / 3, 1e-7)
                break
            lam *= 10  # (a rejected step shrinks until it is below tol: then stop)
        if step is None:  # x stands (e, A are its own)
            if not (final_jacobian and np.abs(x - x_jac).max() > LAPLACE_REUSE_LOG):
                break
            # a chord step's gradient is the old J's: its fixed point moves with J; go on from a
            # J taken here (which the intervals then use)
            e, D, A = evaluate(x, True)
            x_jac, JtJ = x, None
            kappa = _correlation_factor(e)
            sigma2 = float((e**2).mean()) * kappa
            continue
        x = x + step
        done = it == max_iter
        if done:
            refresh = final_jacobian and np.abs(x - x_jac).max() > LAPLACE_REUSE_LOG
        else:
            refresh = it % jacobian_every == 0
        if refresh:
            e, D, A = evaluate(x, True)
            x_jac, JtJ = x, None
        else:
            e, A = e_new, A_new
        kappa = _correlation_factor(e)
        sigma2 = float((e**2).mean()) * kappa
        if done:
            break
    return x, e, D, A, sigma2, kappa, it


def _anchor_sd(n: int, speed_rel_sd: float, length_log_sd: np.ndarray) -> float:
    """The log sd of the common scale of speeds and lengths that the anchors place: ``n`` GNSS
    speeds (relative sd ``speed_rel_sd`` each) and the lengths' class prior (log sds)."""
    return float((n / speed_rel_sd**2 + np.sum(1.0 / length_log_sd**2)) ** -0.5)


def _anchored_scale(log_v: np.ndarray, log_lengths: np.ndarray, log_v_reported: np.ndarray,
                    log_lengths_prior: np.ndarray, speed_rel_sd: float,
                    length_log_sd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``log_v`` (the runs' speeds) and ``log_lengths`` (Lb, Lv) moved together by the common log
    scale λ that the anchors alone place: the weighted mean of the reported speeds' and the class
    lengths' offsets from them (GNSS errors independent per run, sd ``speed_rel_sd``; the lengths'
    prior log sds ``length_log_sd``). Their ratios — what the wheels' delays measure — are kept."""
    w_v, w_l = 1.0 / speed_rel_sd**2, 1.0 / np.asarray(length_log_sd) ** 2
    lam = (w_v * np.sum(log_v_reported - log_v) + np.sum(w_l * (log_lengths_prior - log_lengths))) \
        / (w_v * len(log_v) + np.sum(w_l))
    return log_v + lam, log_lengths + lam


def _rate(aps: np.ndarray, lengths: np.ndarray, dts: np.ndarray) -> np.ndarray:
    """(R, N, 4) each run's AP rate in time (m/s), central differences within its first
    ``lengths[r]`` samples (one-sided at their ends; zero past them)."""
    out = np.zeros_like(aps)
    for r, (m, dt) in enumerate(zip(lengths, dts)):
        out[r, :m] = np.gradient(aps[r, :m], dt, axis=0)
    return out


def _correlation_factor(e: np.ndarray) -> float:
    """1 + 2 Σ ρ_k of the residual along the grid (up to its first zero): grid points per
    independent piece of information."""
    flat = e.reshape(-1, e.shape[-1])
    flat = flat[:: max(1, len(flat) // 64)]  # ~64 rows estimate it as well as all, at a fraction of the FFTs
    # zero-padded to a fast length (≥ 2K − 1: no wrap-around); the grids' lengths are often prime-ish
    f = np.fft.rfft(flat, scipy.fft.next_fast_len(2 * flat.shape[1], real=True), axis=1)
    ac = np.fft.irfft(np.abs(f) ** 2, axis=1)[:, : flat.shape[1]].sum(axis=0)
    rho = ac / ac[0]
    cut = int(np.argmax(rho <= 0)) if np.any(rho <= 0) else len(rho)
    return float(max(1.0, 1.0 + 2.0 * rho[1:cut].sum()))


def _residual_cross_spectrum(e: np.ndarray, nfft: int) -> np.ndarray:
    """The residual (n, 4, K) as a stationary noise along the grid, a run's four wheels together and
    the runs independent: the cross-periodogram (nf, 4, 4), S[f, w, v] = Σ_r ê_rw(f) ê_rv(f)* / (n·K)
    of the rows zero-padded to ``nfft`` ≥ 2K − 1 — the transform of the (biased) cross-covariances,
    so that (1/nfft) Σ_f â(f)ᴴ S(f) b̂(f) over the whole circle is aᵀ Σ b, Σ their block-Toeplitz
    covariance (positive semi-definite)."""
    n, _, K = e.shape
    Ef = np.fft.rfft(e, nfft, axis=-1)
    return np.einsum("rwf,rvf->fwv", Ef, Ef.conj()) / (n * K)


def _re_products(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Re Σ_i a[..., i, x] b[..., i, y] (complex, batched over the leading axes) as one real product."""
    return np.concatenate([a.real, -a.imag], axis=-2).swapaxes(-1, -2) @ np.concatenate([b.real, b.imag], axis=-2)


def noise_information(e: np.ndarray, D: np.ndarray, L: int, active: np.ndarray) -> np.ndarray:
    """Jᵀ Σ J (n·L + n_g square) of the profiled consensus residual — J as ``normal_equations`` of
    :func:`calibrate_batch` has it, ∂e_rw/∂x = D_rw − D̄ with D̄ the mean of every run's and wheel's
    rows — and Σ the noise's covariance as the residual ``e`` shows it (:func:`_residual_cross_spectrum`):
    the meat of the sandwich covariance H⁻¹ (JᵀΣJ/σ⁴ + prior) H⁻¹ of the estimate, which weighs
    every grid point alike. With Σ = σ² I it is σ² JᵀJ. Local coordinates not in ``active``: zero.
    Once per calibration.

    Run s's score in its local coordinate j, Σ_rw (D_rw − D̄)ᵀ ε_rw, is its own rows' D_swᵀ ε_sw
    less D̄_sjᵀ Σ_rw ε_rw (every run's noise): covariances of such pairs are the runs' own blocks,
    cross terms with that common sum and its variance — products of per-run spectra, never the
    (n·4·K)-row Jacobian."""
    n, n_cols, nw, K = D.shape
    n_g = n_cols - L
    k = len(active)
    N = n * nw
    nfft = scipy.fft.next_fast_len(2 * K - 1, real=True)
    S = _residual_cross_spectrum(e, nfft)
    Df = scipy.fft.rfft(D[:, np.r_[active, L:n_cols]], nfft, axis=-1)  # the columns in use (the FFT is half the cost)
    Lf, Gf = Df[:, :k], Df[:, k:]  # (n, k, 4, nf), (n, n_g, 4, nf)
    weight = np.einsum("fww->f", S).real * ((Lf.real**2 + Lf.imag**2).sum(axis=(0, 1, 2))
                                            + (Gf.real**2 + Gf.imag**2).sum(axis=(0, 1, 2)))
    nb = int(np.nonzero(weight > NOISE_BAND_FLOOR * weight.max())[0].max()) + 1
    wf = np.full(nb, 2.0 / nfft)  # the rfft's half circle: each bin stands for ±f but 0 and nfft/2
    wf[0] = 1.0 / nfft
    if nb == nfft // 2 + 1 and nfft % 2 == 0:
        wf[-1] = 1.0 / nfft
    S = S[:nb]
    # frequency and wheel together as the products' inner axis: (n, nb·4, columns)
    Lf = Lf[..., :nb].transpose(0, 3, 2, 1).reshape(n, nb * nw, k)
    Gf = Gf[..., :nb].transpose(0, 3, 2, 1).reshape(n, nb * nw, n_g)

    def apply_S(X):  # S(f) on each bin's four wheels: (n, nb·4, c) → the same
        Xf = X.reshape(X.shape[0], nb, nw, -1)
        return np.einsum("fwv,rfvc->rfwc", S, Xf, optimize=True).reshape(X.shape)

    wfw = np.repeat(wf, nw)[None, :, None]  # the weights on the inner axis
    Su = S.sum(axis=2)  # (nb, 4): S u, u the wheels' ones (D̄ is on every wheel alike)
    uSu = Su.sum(axis=1).real
    m_loc = Lf.reshape(n, nb, nw, k).sum(axis=2).transpose(1, 0, 2).reshape(nb, n * k) / N  # D̄, (nb, n·k)
    m_g = Gf.reshape(n, nb, nw, n_g).sum(axis=(0, 2)) / N  # (nb, n_g)
    t = (np.einsum("rfwk,fw->frk", Lf.reshape(n, nb, nw, k).conj(), Su) * wf[:, None, None]).reshape(nb, n * k)
    um = n * m_loc.conj() * (wf * uSu)[:, None]  # n m* uSu, weighted
    # local-local: each run's own block, less the cross terms with the common sum, plus its variance
    cross = _re_products(t, m_loc)  # Σ_f t_x m_y
    Mll = _re_products(um, m_loc) - cross - cross.T
    own = _re_products(Lf.conj() * wfw, apply_S(Lf))  # (n, k, k): Σ L_aᴴ S L_b
    for r in range(n):
        Mll[k * r:k * r + k, k * r:k * r + k] += own[r]
    # local-global: L_sjᴴ S G_sg − t_sj m_g − m_sj* Σ_r uᴴ S G_rg + n m_sj* uSu m_g
    SG = apply_S(Gf)
    lg_own = _re_products(Lf.conj() * wfw, SG).reshape(n * k, n_g)
    uSG = np.einsum("fw,rfwg->fg", Su.conj(), Gf.reshape(n, nb, nw, n_g))  # Σ_r uᴴ S G_rg
    Mlg = lg_own - _re_products(t, m_g) - _re_products(m_loc.conj() * wf[:, None], uSG) + _re_products(um, m_g)
    # global-global: every run's rows, D̄ removed
    Fg = (Gf.reshape(n, nb, nw, n_g) - m_g[None, :, None, :]).reshape(n, nb * nw, n_g)
    Mgg = _re_products((Fg.conj() * wfw).reshape(1, -1, n_g), apply_S(Fg).reshape(1, -1, n_g))[0]
    n_par = n * L + n_g
    loc_idx = (np.arange(n)[:, None] * L + active[None]).ravel()
    M = np.zeros((n_par, n_par))
    M[np.ix_(loc_idx, loc_idx)] = Mll
    M[loc_idx, n * L:] = Mlg
    M[n * L:, loc_idx] = Mlg.T
    M[n * L:, n * L:] = Mgg
    return M


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
    position_sd_m: float = 1.0,
) -> BatchFit:
    """Run properties of every run of a batch, and the carriage's global properties (module docstring).

    ``prior_mean``/``prior_sd``: the carriage class of the registry (all Table 3.1 names; ``v`` is
    not used: each run's reported speed is its prior, with relative sd ``speed_rel_sd``).
    ``window_m``: restrict the comparison to this chainage range (e.g. off a bridge). Returns the
    run estimates with 95 % intervals (the global properties' uncertainty marginalised).
    ``jacobian_every``: refresh the Jacobian after every so many accepted steps
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
    Without it a held global's error is shared by every run's interval unseen, and the intervals
    cover far too rarely.
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
    offsets = wheel_offsets(fixed["Lb"], fixed["Lv"])
    # The speeds' search range: the GNSS error and the bogie spacing's (which moves every speed alike)
    length_sd = prior_sd["Lv"] / prior_mean["Lv"]
    # The lengths are calibrated where the class leaves them looser than the batch's GNSS speeds
    # can place the common scale; declared tighter (design drawings), they are held at the class
    # means, and the scale is theirs.
    fit_lengths = max(length_sd, prior_sd["Lb"] / prior_mean["Lb"]) * math.sqrt(n) >= speed_rel_sd
    slack = max(4 * speed_rel_sd, 3 * math.hypot(speed_rel_sd, length_sd))
    # Trial lengths move the wheels: the window keeps clear of where the longest could put them.
    reach = offsets * (1 + 3 * length_sd) if fit_lengths else offsets
    grid = window(runs, reach, window_m, speed_slack=slack)
    # Samples past the last the window can need (trailing wheel, slowest trial speed) are not
    # inverted: the inverse is causal, and a decimated stage's anti-alias filter is applied to the
    # whole record first.
    keep = [min(len(r.channels), int(math.ceil((grid[-1] + EDGE_M - r.x0_m - reach.min())
                                              / (r.speed_mps * (1 - slack)) / r.dt)) + 2) for r in runs]
    mapper = stage = None
    n_i = len(GLOBAL_FIT)  # the globals of the inverse's θ; the lengths follow them in x
    n_g = n_i + len(LENGTH_FIT)
    L = N_LOCAL
    # per run (N_LOCAL): log mv, log Iv, log v, the record's chainage shift and the body's initial
    # state (nuisances: the first sample's chainage is the log's, the state a weak prior's)
    mu_loc = np.zeros((n, L))
    mu_loc[:, :3] = [[math.log(prior_mean["mv"]), math.log(prior_mean["Iv"]), math.log(r.speed_mps)] for r in runs]
    s_loc = np.concatenate([[prior_sd["mv"] / prior_mean["mv"], prior_sd["Iv"] / prior_mean["Iv"], speed_rel_sd,
                             position_sd_m], BODY0_PRIOR_SD / BODY0_UNIT])
    mu_g = np.log([prior_mean[k] for k in GLOBAL_FIT + LENGTH_FIT])
    s_g = np.array([max(prior_sd[k] / prior_mean[k], 1e-4) for k in GLOBAL_FIT + LENGTH_FIT])
    mu = np.concatenate([mu_loc.ravel(), mu_g])
    P = np.concatenate([np.tile(1.0 / s_loc**2, n), 1.0 / s_g**2])
    lengths_at = slice(L * n + n_i, None)
    if not fit_lengths:
        P[lengths_at] = 1.0 / REST_SD**2
    # a step's cap: the log coordinates' (the misfit is far from quadratic beyond); the initial
    # state enters linearly
    max_step = np.concatenate([np.tile(np.r_[np.full(3, 0.2), 1.0, np.full(len(BODY0_NAMES), np.inf)], n),
                               np.full(n_g, 0.2)])
    n_par = L * n + n_g
    N = 4 * n
    # The records' common shift is the chainage's gauge: the consensus follows it, so the data hardly
    # see it, but drifting it moves the window over the track (and the common mass error with it).
    # The logs' mean chainage defines it.
    gauge = np.zeros(n_par)
    gauge[_I_SHIFT: L * n: L] = 1.0 / n
    Q = np.outer(gauge, gauge) / CHAINAGE_GAUGE_SD_M**2

    def unpack(x):
        return x[: L * n].reshape(n, L), x[L * n:]

    x0s = np.array([r.x0_m for r in runs])
    h = math.exp(FD_LOG_STEP)

    def evaluate(x, with_jac):
        """Residual e (n, 4, K), Jacobian blocks D (n, L + n_g, 4, K) and the mapped APs A."""
        loc, glob = unpack(x)
        p = np.exp(loc[:, :3])  # (n, 3): mv, Iv, v
        body0 = loc[:, _I_BODY:] * BODY0_UNIT
        x0 = x0s + loc[:, _I_SHIFT]
        theta = np.column_stack([p[:, :2], np.broadcast_to(np.exp(glob[:n_i]), (n, n_i))])  # INVERSE_NAMES order
        Lb, Lv = np.exp(glob[n_i:])
        offsets = wheel_offsets(Lb, Lv)
        z, lengths, dts, N_t = stage["z"], stage["lengths"], stage["dts"], stage["z"].shape[1]
        if not with_jac:
            aps = carriage_aps_runs(theta, np.arange(n), Lb, Lv, z, lengths, dts,
                                    stage["work"][: n * N_t * 4].reshape(n, N_t, 4), body0=body0)
            A = mapper.map_runs(aps[:, None], dts, x0, p[:, 2:3], lengths, offsets)[:, 0, 0]
            return A - A.mean(axis=(0, 1)), None, A
        A = np.empty((n, 4, len(mapper.grid)))
        D = np.empty((n, L + n_g) + A.shape[1:])  # ~30 MB at 50 runs, written in place
        # The AP and its derivatives in mv, Iv, the initial state and the globals, exact
        # (carriage_aps_sensitivities), a chunk of runs at a time (a few MB of work array instead of
        # ~60); the speed's and the shift's columns by finite differences of the mapping (no
        # inverse). Columns of held coordinates (not in ``active``) are not computed.
        nb = len(BODY0_NAMES)
        with_body = _I_BODY in active
        rows = N_SENS if with_body else N_SENS - nb
        for r0 in range(0, n, JACOBIAN_CHUNK_RUNS):
            rs = slice(r0, min(n, r0 + JACOBIAN_CHUNK_RUNS))
            c = rs.stop - r0
            sens = carriage_aps_sensitivities(theta[rs], Lb, Lv, z[rs], lengths[rs], dts[rs],
                                              stage["work"][: c * N_t * 4 * N_SENS].reshape(c, N_t, N_SENS, 4),
                                              body0=body0[rs], body_derivatives=with_body)[:, :rows]
            args = (dts[rs], x0[rs])
            mapped = mapper.map_runs(sens, *args, p[rs, 2:3], lengths[rs], offsets)[:, :, 0]  # (c, rows, 4, K)
            A[rs] = mapped[:, 0]
            D[rs, :2] = mapped[:, 1:3]
            # The speed's and lengths' columns move where each sample lands on the grid: the AP's
            # slope there (its rate in time over the speed) times the move, analytic. (Finite
            # differences of the mapping would not cancel along the common scale of speeds and
            # lengths — which only stretches the consensus — and their error there read as
            # information the data do not have.)
            slope = mapper.interpolate(_rate(sens[:, 0], lengths[rs], dts[rs])[:, None], *args, p[rs, 2:3],
                                       lengths[rs], offsets)[:, 0, 0] / p[rs, 2, None, None]  # (c, 4, K)
            travel = mapper.grid[None, None] - x0[rs, None, None] - offsets[None, :, None]  # v·t, m
            D[rs, 2] = mapper.finish(-travel * slope)
            if _I_SHIFT in active:
                ahead, behind = (mapper.map_runs(sens[:, :1], dts[rs], x0[rs] + d, p[rs, 2:3], lengths[rs],
                                                 offsets)[:, 0, 0] for d in (SHIFT_FD_M, -SHIFT_FD_M))
                np.subtract(ahead, behind, out=D[rs, _I_SHIFT])
                D[rs, _I_SHIFT] /= 2 * SHIFT_FD_M
            if with_body:
                np.multiply(mapped[:, 9:9 + nb], BODY0_UNIT[:, None, None], out=D[rs, _I_BODY:_I_BODY + nb])
            D[rs, L:L + n_i] = mapped[:, 3:9]
            # The lengths' columns: the wheels' offsets move (analytic, as the speed's) and the
            # inverse's pitch terms change (a one-sided difference: one inverse per run and length).
            D[rs, L + n_i:] = 0.0
            for j, moved in enumerate((np.array([Lb, -Lb, Lb, -Lb]), np.array([Lv, Lv, -Lv, -Lv])) if fit_lengths else ()):
                trial = np.array([Lb, Lv])
                trial[j] *= h
                aps = carriage_aps_runs(theta[rs], np.arange(c), *trial, z[rs], lengths[rs], dts[rs],
                                        body0=body0[rs])
                inverse = mapper.map_runs(aps[:, None], *args, p[rs, 2:3], lengths[rs], offsets)[:, 0, 0]
                D[rs, L + n_i + j] = (inverse - A[rs]) / FD_LOG_STEP + mapper.finish(-moved[None, :, None] * slope)
        return A - A.mean(axis=(0, 1)), D, A

    def normal_equations(e, D, JtJ=None):
        """JᵀJ and Jᵀe of the profiled consensus residual (J = ∂e/∂x), from the per-run blocks
        (``JtJ``: the one already formed from this D), over the ``active`` local coordinates (the
        held ones' rows and columns zero: their prior holds them)."""
        # Products over (wheel, grid point) as batched matrix products (BLAS), not einsum loops.
        k = len(active)
        Dl, Dg = (D[:, :L] if k == L else D[:, active]), D[:, L:]
        Fl = Dl.reshape(n, k, -1)
        ev = e.reshape(n, -1, 1)
        loc_idx = (np.arange(n)[:, None] * L + active[None]).ravel()
        Jte = np.zeros(n_par)
        Jte[loc_idx] = (Fl @ ev).ravel()
        Jte[L * n:] = (Dg.reshape(n, n_g, -1) @ ev).sum(axis=0).ravel()
        if JtJ is not None:
            return JtJ, Jte
        g = Dl.sum(axis=2)  # (n, k, K)
        Dgc = Dg - Dg.mean(axis=(0, 2), keepdims=True)  # global columns, consensus removed
        Fg = Dgc.reshape(n, n_g, -1)
        g2 = g.reshape(k * n, -1)
        Jll = (g2 @ g2.T) / -N
        Hl = Fl @ Fl.transpose(0, 2, 1)
        for r in range(n):
            Jll[k * r:k * r + k, k * r:k * r + k] += Hl[r]
        JtJ = np.zeros((n_par, n_par))
        JtJ[np.ix_(loc_idx, loc_idx)] = Jll
        cross = (Fl @ Fg.transpose(0, 2, 1)).reshape(k * n, n_g)
        JtJ[loc_idx, L * n:] = cross
        JtJ[L * n:, loc_idx] = cross.T
        JtJ[L * n:, L * n:] = (Fg @ Fg.transpose(0, 2, 1)).sum(axis=0)
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
            # The stage's low-pass is the mapper's, in space (:class:`~cloud.rail.mapping.Mapper`); the
            # channels are filtered only against aliasing when decimated, well below the stage's cut-off.
            z = lowpass_channels(r, min_wavelength / ANTIALIAS_FACTOR) if q > 1 else np.asarray(r.channels, dtype=float)
            chans.append((z[:k:q], r.dt * q))
        lengths = np.array([len(c[0]) for c in chans])
        z = np.zeros((n, lengths.max(), 4))
        for r, c in enumerate(chans):
            z[r, : lengths[r]] = c[0]
        return {"z": z, "lengths": lengths, "dts": np.array([c[1] for c in chans]),
                "work": np.empty(max(4 * n, 4 * N_SENS * JACOBIAN_CHUNK_RUNS) * z.shape[1])}  # chord / Jacobian

    def mapper_for(min_wavelength):
        return Mapper(grid[:: max(1, int(round(min_wavelength / POINTS_PER_WAVELENGTH / GRID_M)))], min_wavelength)

    x = mu.copy()
    at_rest = None
    shift_held = np.zeros(n, dtype=bool)  # runs found to start at the log's chainage (held at zero)
    shift_idx = np.arange(n) * L + _I_SHIFT
    body = np.arange(n)[:, None] * L + _I_BODY + np.arange(len(BODY0_NAMES))[None]  # the runs' initial states
    theta0 = np.array([prior_mean[k] for k in INVERSE_NAMES])
    found = _speed_from_wheels(runs, stage_channels(SPEED_SEARCH_M), theta0, fixed, offsets,
                               mapper_for(SPEED_SEARCH_M), slack)
    # The wheels give each speed relative to the class's bogie spacing: v/Lv. The batch's mean of
    # log(found / reported) is minus the spacing's log error plus the GNSS errors' mean (sd
    # speed_rel_sd/√n): the lengths start at that scale's posterior mean under their class prior,
    # the speeds with them.
    scale = -float(np.mean(found)) * length_sd**2 / (length_sd**2 + speed_rel_sd**2 / n) if fit_lengths else 0.0
    x[2: L * n: L] += found + scale
    x[L * n + n_i:] += scale
    if fit_lengths:
        x[L * n + n_i] += _wheelbase_from_wheels(runs, stage_channels(SPEED_SEARCH_M), theta0, fixed, found,
                                                 mapper_for(SPEED_SEARCH_M), 3 * s_g[n_i])
    it = 0
    for i_stage, min_wavelength in enumerate(stages_m):
        last = i_stage == len(stages_m) - 1
        mapper = mapper_for(min_wavelength)
        stage = stage_channels(min_wavelength, final_decimation if last else None)
        if last and fit_lengths:
            # The common scale of speeds and lengths as the anchors alone place it (module
            # docstring), the ratios the data found kept; the last stage holds the lengths there.
            x[2: L * n: L], x[lengths_at] = _anchored_scale(x[2: L * n: L], x[lengths_at], mu[2: L * n: L],
                                                            mu_g[n_i:], speed_rel_sd, s_g[n_i:])
            mu[lengths_at] = x[lengths_at]
            P[lengths_at] = 1.0 / REST_SD**2
        # The wheelbase is held in the first stage where the wheels' agreement put it
        # (:func:`_wheelbase_from_wheels`): waves longer than the stage's shortest are long against
        # it (2·Lb), so the stage hardly sees it, and with the other globals still at the class means
        # the wheelbase takes up their misfit — a large batch's data outweigh its class prior and
        # walk it out of its basin.
        i_lb = L * n + n_i + LENGTH_FIT.index("Lb")
        if fit_lengths and not last:
            held_lb = i_stage == 0
            P[i_lb] = 1.0 / (REST_SD if held_lb else s_g[n_i + LENGTH_FIT.index("Lb")]) ** 2
            mu[i_lb] = x[i_lb] if held_lb else mu_g[n_i + LENGTH_FIT.index("Lb")]
        # The records' chainage shifts are fitted in the middle stages only. The first holds them
        # where the logs put them: with the run properties still at the class means its shifts take
        # up misfit (decimetre steps on exact chainages) and cost iterations, and its waves are long
        # against a chainage error anyway. The last holds them where the middle one left them
        # (centimetres): at 2 m the linear interpolation's kinks make the misfit rough in a shift
        # below a centimetre, and Gauss–Newton's shift steps are rejected over and over.
        hold_shift = len(stages_m) > 1 and (i_stage == 0 or (last and len(stages_m) > 2))
        P[_I_SHIFT: L * n: L] = 1.0 / np.where(hold_shift | shift_held, REST_SD, position_sd_m) ** 2
        mu[_I_SHIFT: L * n: L] = x[_I_SHIFT: L * n: L] if hold_shift else 0.0
        active = np.array([j for j in range(L) if not (hold_shift and j == _I_SHIFT)
                           and not (j >= _I_BODY and at_rest is not None and at_rest.all())])
        x, e, D, A, sigma2, kappa, n_it = _gauss_newton(evaluate, normal_equations, x, mu, P,
                                                         max_iter if last else 8,
                                                         tol if last else max(tol, STAGE_TOL_LOG), jacobian_every, last,
                                                         max_step, Q)
        it += n_it
        if i_stage == max(0, len(stages_m) - 2):
            # Did each run start at rest? Its body's fitted initial state against its marginal
            # covariance (a Wald statistic, χ² with 4 dof if it did), decided before the last stage
            # (which then runs once): a record consistent with rest is held at rest — the data then
            # carry the information a free start spends on the state (module docstring).
            JtJ, _ = normal_equations(e, D)
            cov = np.linalg.inv(JtJ / sigma2 + np.diag(P) + Q)
            wald = np.array([x[b] @ np.linalg.solve(cov[np.ix_(b, b)], x[b]) for b in body])
            at_rest = wald < REST_CHI2
            # Likewise each fitted shift against the log's chainage (only where this stage fitted it)
            if not hold_shift:
                shift_held = x[shift_idx] ** 2 / cov[shift_idx, shift_idx] < SHIFT_CHI2
            held = np.concatenate([body[at_rest].ravel(), shift_idx[shift_held]])
            # the posterior mean given the held states at rest (Gaussian conditioning at this
            # linearisation): the next stage starts where holding them moves the runs, not at a jump
            x = x - cov[:, held] @ np.linalg.solve(cov[np.ix_(held, held)], x[held])
            x[held] = 0.0
            P[body[at_rest].ravel()] = np.tile(1.0 / (REST_SD / BODY0_UNIT) ** 2, int(at_rest.sum()))
            P[shift_idx[shift_held]] = 1.0 / REST_SD**2
            mu[shift_idx[shift_held]] = 0.0
            if last and at_rest.any():  # a one-stage fit: go on from here
                if at_rest.all():
                    active = active[active < _I_BODY]
                x, e, D, A, sigma2, kappa, n_it = _gauss_newton(evaluate, normal_equations, x, mu, P, max_iter, tol,
                                                                 jacobian_every, True, max_step, Q)
                it += n_it
    JtJ, _ = normal_equations(e, D)
    H = JtJ / sigma2 + np.diag(P) + Q
    # The sandwich H⁻¹ (JᵀΣJ/σ⁴ + prior) H⁻¹, Σ the noise's covariance as the residual shows it
    # (:func:`noise_information`). H⁻¹ alone takes the noise as white with σ² scaled by the
    # residual's correlation factor: right on average over the grid, not for each coordinate, whose
    # signature sits where the (integrated, red) noise is stronger or weaker than that average.
    meat = noise_information(e, D, L, active) / sigma2**2 + np.diag(P) + Q
    H_inv = np.linalg.inv(H)
    cov = H_inv @ meat @ H_inv
    # The lengths were held at the anchored scale: their uncertainty is that scale's (the ratio of
    # the two the data fix far better), and it moves every speed alike. Held at the class means,
    # it is the class's: the bogie spacing's sd (the speeds are measured against it).
    if fit_lengths:
        anchor_sd = _anchor_sd(n, speed_rel_sd, s_g[n_i:])
        cov[lengths_at, lengths_at] = anchor_sd**2
    elif held_globals_cov is None:
        anchor_sd = float(s_g[-1])
        cov[lengths_at, lengths_at] = np.diag(s_g[n_i:] ** 2)
    else:  # held at another batch's estimate: its uncertainty
        anchor_sd = float(math.sqrt(np.asarray(held_globals_cov)[-1, -1]))
        cov[lengths_at, lengths_at] = np.asarray(held_globals_cov)[n_i:, n_i:]
    if held_globals_cov is not None:
        # The runs' estimates given the held globals, plus the held values' error propagated through
        # their sensitivity to them: Σ_loc = H_ll⁻¹ M_ll H_ll⁻¹ + S Σ_g Sᵀ with S = −H_ll⁻¹ H_lg.
        h_inv = np.linalg.inv(H[: L * n, : L * n])
        S = -h_inv @ H[: L * n, L * n:]
        cov[: L * n, : L * n] = h_inv @ meat[: L * n, : L * n] @ h_inv \
            + S @ np.asarray(held_globals_cov, dtype=float) @ S.T
    sd = np.sqrt(np.diag(cov))
    loc, glob = unpack(x)
    sd_loc = sd[: L * n].reshape(n, L)[:, :3].copy()
    sd_loc[:, 2] = np.hypot(sd_loc[:, 2], anchor_sd)
    estimates = []
    for r, run in enumerate(runs):
        mean = {k: float(math.exp(loc[r, j])) for j, k in enumerate(RUN_NAMES)}
        lo = {k: float(math.exp(loc[r, j] - Z95 * sd_loc[r, j])) for j, k in enumerate(RUN_NAMES)}
        hi = {k: float(math.exp(loc[r, j] + Z95 * sd_loc[r, j])) for j, k in enumerate(RUN_NAMES)}
        estimates.append(RunEstimate(run.pass_id, mean, lo, hi, bool(at_rest[r]), float(wald[r]),
                                     float(loc[r, _I_SHIFT])))
    globals_fit = {k: float(math.exp(glob[j])) for j, k in enumerate(GLOBAL_FIT + LENGTH_FIT)}
    return BatchFit(estimates, globals_fit, mapper.grid, A.mean(axis=(0, 1)), math.sqrt(sigma2 / kappa), kappa, it,
                    time.perf_counter() - t_start, cov[L * n:, L * n:].copy())
