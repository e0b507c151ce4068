"""A short rail bridge's stiffness from a calibrated batch of carriage runs (thesis §3.5–3.6, issue #6
item 6): the bogie's moving-reference deflection per unit wheel load, and the damage indicators
D1/D2 (eq. 3.24) against a healthy batch.

On the span, the AP under a wheel is the rail's unloaded profile plus the deflection of track and
bridge under the carriage. The profile is the same for every run, the deflection scales with the
run's wheel load W_r = g·(mv/4 + mb/2 + mw) (the batch calibration's masses), so across the runs of
a batch, at each chainage,

    y_r,i(x) = a_i(x) + W_r · b_i(x)        (i = the leading bogie's two wheels)

and the slope b_i (least squares over runs) is the deflection per unit wheel load with the profile
gone. Each run's AP is first taken relative to the line through its values at the two supports (the
thesis's drift removal by the zero deflection at the supports, which also removes the track's own
settlement there). J(x) = −½(b_1 + b_2), low-passed (:data:`MIN_WAVELENGTH_M`), is the leading
bogie's influence per unit wheel load (J⁰(x) + J¹(x, x ∓ 2·Lb) in the thesis's notation); D1 and D2
compare its mid-span ordinate and its area over the span with the healthy batch's, as
:func:`cloud.bridge.mril.damage_indicators` does. On a 10 m span the unloaded profile relative to
the supports' line is as large as the deflection (~0.5 mm mid-span in our blind-test worlds), so
reading the mean AP per unit load with the profile left in (``unseparated``, as the thesis does)
dilutes D by about half.

Across independent batches (different runs, as the thesis's) the per-batch slope is noisy — its
lever arm is the wheel load's ~7 % spread (25 runs against 25: ±20 points in D). The batch mean
of the AP per unit load is not, and the profile is common to every batch on the track, so
:func:`damage_from_batch_means` takes the change of that mean between the healthy and the current
batch and only the scale from the healthy batch's slope.

The AP comes from the carriage inverse (all four channels) or from the 2-DOF bogie half-car of
App. A.3 (the leading bogie's two channels). The half-car ignores the body's force through the
secondary suspension; the body's response to the track depends on its mass, so the half-car's AP
error is correlated with the wheel load and the regression's slope is biased (on our batches it
even has the wrong sign): the half-car cannot separate the profile this way. The two wheels'
time-synchronous difference is free of that force (it acts at the bogie's centre), so on the
difference (:attr:`BogieInfluence.difference`, the matrix method for J⁰) the half-car and the
carriage give the same line — but one difference of two noisy wheels is too noisy for ±3 points.
The third reading, ``leading_bogie`` (:func:`leading_bogie_ap`), keeps the half-car's data (the
leading bogie's two channels) and models the body's force: the carriage's body, driven by the
leading bogie and by a trailing bogie simulated over the AP the leading wheels found. Every
inverse here runs at the batch calibration's Newmark γ (:data:`cloud.rail_calibration.
INVERSE_GAMMA`), the one its properties were fitted under.

(The thesis's matrix method, eq. 3.16–3.23, applied to b·W̄ of the two wheels, is available as
:func:`cloud.bridge.mril.mril_two_axle`; on our simulated blind-test batches its indicators were
further from the truth than those of J itself — see the report of issue #6.)

Needs variation of the wheel load across the batch (passengers: mv's class sd ~10 %). Pure
functions on arrays.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np
from scipy.signal import butter, sosfiltfilt

from shared.dynamics.inverse import InverseStream, build_inverse
from shared.vehicles import GRAVITY
from shared.vehicles.bogie import BogieHalfCar
from shared.vehicles.carriage import Carriage

from .bridge.mril import MrIl
from .rail_calibration import FIXED, INVERSE_GAMMA, BatchFit, RailRun

GRID_M = 0.05
APPROACH_M = 10.0  # AP kept either side of the span, m
#: Shortest wavelength kept in J, m. The regression's noise is short-waved and the span's vibration
#: (~14 Hz at 30 m/s: ~2 m) rides on the line; a 10 m span's static line has nothing below ~5 m.
#: The thesis low-passes its mean MR-IL too (FIR, §3.5.3) before reading the mid-span ordinate.
MIN_WAVELENGTH_M = 4.0


@dataclasses.dataclass(frozen=True, eq=False)
class BogieInfluence:
    """The leading bogie's deflection per unit wheel load on the span (m/N, positive down) and what
    went into it."""

    mril: MrIl  # x_m from the first support
    wheel_load_n: np.ndarray  # (n_runs,) static wheel load of each run, N
    intercept_m: np.ndarray  # (2, K) a_i(x): the profile (relative to the supports' line), m
    #: The thesis's reading (profile not separated): −½ Σ_i mean_r(y_r,i / W_r), m/N — for comparison.
    unseparated: MrIl | None = None
    #: J⁰ by the matrix method on the wheels' time-synchronous AP difference (:func:`_difference_mril`).
    difference: MrIl | None = None
    #: The same from the batch mean of the difference per unit load (profile left in), m/N.
    difference_unseparated: MrIl | None = None
    #: The batch-mean AP line −½ Σ_i mean_r y_r,i (profile and load both in), m — and of the
    #: difference, by the matrix method: what :func:`damage_from_batch_means` compares.
    mean_line: MrIl | None = None
    difference_mean: MrIl | None = None
    #: The batch-mean AP line over the span and its approaches (x from the first support), m: what
    #: registers two batches' chainage off the bridge (:func:`damage_from_batch_means`).
    approach_line: MrIl | None = None


def _leading_bogie_ap(run: RailRun, est, globals_: dict[str, float], class_mean: dict[str, float],
                      model: str) -> tuple[np.ndarray, np.ndarray, float, float]:
    """AP (n, 2) under the leading bogie's two wheels, their offsets ahead of the body's centre of
    gravity (m), the run's speed (m/s) and its static wheel load (N), under the run's calibration.

    ``carriage``: the 6-DOF carriage inverse from all four channels (App. B.2). ``bogie_half_car``:
    the 2-DOF bogie half-car of App. A.3 (Table 3.5: the bogie's mass, inertia, primary suspension
    and half wheelbase) from the leading bogie's two channels alone — the body's load through the
    secondary suspension is not modelled, as in the thesis's test of a simpler model.
    """
    car = Carriage(**{k: class_mean[k] for k in FIXED}, **globals_, **est.mean)
    load = GRAVITY * (car.mv / 4 + car.mb / 2 + car.mw)
    if model == "carriage":
        ap = InverseStream(build_inverse(car.system(), run.dt, gamma=INVERSE_GAMMA)).update(run.channels)[:, :2]
    elif model == "bogie_half_car":
        bogie = BogieHalfCar(ms=car.mb, Is=car.Ib, K1=car.kp, K2=car.kp, C1=car.cp, C2=car.cp, D1=car.Lb, D2=car.Lb)
        ap = InverseStream(build_inverse(bogie.system(), run.dt, gamma=INVERSE_GAMMA)).update(np.asarray(run.channels)[:, :2])
    elif model == "leading_bogie":
        ap = leading_bogie_ap(car, np.asarray(run.channels, dtype=float)[:, :2], run.dt)
    else:
        raise ValueError(f"bogie_influence: unknown model {model!r} ({', '.join(MODELS)})")
    return ap, car.wheel_offsets_m()[:2], car.v, load


#: The inverses :func:`bogie_influence` can read the AP with.
MODELS = ("carriage", "bogie_half_car", "leading_bogie")
#: Passes of :func:`leading_bogie_ap` (measured on the blind test's healthy batches, profiles 1/2, 12
#: runs each, rms AP error on the span, relative to the supports' chord, against the four-channel
#: inverse: 0.08/0.11 mm with the trailing bogie a plain delayed copy, 0.034/0.047 after one pass,
#: 0.025/0.043 after two, no change after three; the bogie half-car's is 0.27/0.31 mm; about half
#: of what remains is the start transient, 0.016/0.025 mm with the trailing bogie's true channels
#: over the first 2·Lv/v).
LEADING_BOGIE_PASSES = 2


def leading_bogie_ap(car: Carriage, z: np.ndarray, dt: float, passes: int = LEADING_BOGIE_PASSES) -> np.ndarray:
    """AP (n, 2) under the leading bogie's two wheels from that bogie's two channels alone
    (``z`` (n, 2): acceleration, pitch rate at step ``dt``), the body's force modelled.

    The bogie half-car (App. A.3) leaves out the body's force through the secondary suspension; it
    is ks/(2·kp) ≈ 0.18 of the body's motion at the pivot, which rings at the body's ~1 Hz modes and
    depends on the run's mv, Iv and v: on the blind test's batches its AP is off by 0.27 mm rms on
    the span (the deflection is ~0.5 mm) and the error correlates with the wheel load (ρ ≈ ±0.6),
    so neither the load regression nor the batch means survive it. Here the body is the carriage's,
    under the run's calibrated properties, driven by both bogies; the trailing bogie, 2·Lv behind on
    the same rail, runs over the AP the leading wheels found 2·Lv/v earlier. A fixed point: start
    with the trailing bogie's channels a delayed copy of the leading one's, invert the carriage
    (App. B.2) for the leading wheels' AP, simulate the trailing bogie (and the body) over that AP
    delayed (Newmark, the inverse's γ) for its channels, and repeat ``passes`` times. Before the
    trailing wheels reach the first sample's chainage (2·Lv/v) their AP is unknown and held at the
    leading wheels' first value: a body transient that decays over the approach (~2 s).
    """
    from shared.dynamics.forward import measured_channels, trapezoid_rate
    from shared.dynamics.newmark import integrate

    system = car.system()
    n = len(z)
    t = np.arange(n) * dt
    lag = 2.0 * car.Lv / car.v
    zz = np.zeros((n, 4))
    zz[:, :2] = z
    for j in (0, 1):
        zz[:, 2 + j] = np.interp(t - lag, t, z[:, j], left=0.0)
    inverse = build_inverse(system, dt, gamma=INVERSE_GAMMA)
    c = inverse.constants  # the forward step the inverse inverts
    for _ in range(passes):
        ap = InverseStream(inverse).update(zz)
        y = np.empty((n, 4))
        y[:, :2] = ap[:, :2]
        for j in (0, 1):
            y[:, 2 + j] = np.interp(t - lag, t, ap[:, j], left=ap[0, j])
        force = (y * system.kc + trapezoid_rate(y, np.zeros(4), dt) * system.cc) @ system.G.T
        state = integrate(system.M, system.C, system.K, force, c,
                          u0=np.linalg.solve(system.K, system.G @ (system.kc * y[0])))
        zz[:, 2:] = measured_channels(system, state)[:, 2:]
    return InverseStream(inverse).update(zz)[:, :2]


def bogie_influence(runs: Sequence[RailRun], fit: BatchFit, class_mean: dict[str, float], start_m: float,
                    span_m: float, model: str = "carriage") -> BogieInfluence:
    """J(x) of a batch over the span [start_m, start_m + span_m] (route chainage, m), with each run
    inverted under its calibrated properties (``fit``; ``class_mean`` supplies the fixed lengths
    and wheelset mass); ``model``: the inverse giving the AP, ``carriage`` or ``bogie_half_car``
    (:func:`_leading_bogie_ap`). The wheel loads are the calibrated ones either way."""
    if len(runs) != len(fit.runs) or any(r.pass_id != e.pass_id for r, e in zip(runs, fit.runs)):
        raise ValueError("bogie_influence: the fit must be of these runs, in order")
    if len(runs) < 3:
        raise ValueError("bogie_influence: needs at least three runs (a slope over wheel loads)")
    if model not in MODELS:
        raise ValueError(f"bogie_influence: unknown model {model!r} ({', '.join(MODELS)})")
    a, b = start_m, start_m + span_m
    x = np.arange(a - APPROACH_M, b + APPROACH_M + 1e-9, GRID_M)
    Y, W, DIFF = [], [], []
    M_span = c = None
    for run, est in zip(runs, fit.runs):
        ap, off, v, load = _leading_bogie_ap(run, est, fit.globals_, class_mean, model)
        t = np.arange(len(ap)) * run.dt
        if c is None:  # the difference's grid: a whole number c of steps per wheelbase
            c = max(1, int(round((off[0] - off[1]) / GRID_M)))
            h = (off[0] - off[1]) / c
            M_span = int(np.floor(span_m / h + 1e-9)) + 1
            xd = a + h * np.arange(M_span + c)
        # Both wheels at one instant, wheel 1 at xd (wheel 2 a wheelbase behind); the line through
        # the ends (both wheels off the span, before and after) removes the run's drift.
        dd = np.interp((xd - run.x0_m - off[0]) / v, t, ap[:, 0] - ap[:, 1])
        DIFF.append(dd - (dd[0] + (dd[-1] - dd[0]) * (xd - a) / (xd[-1] - a)))
        ys = []
        for i in (0, 1):
            ti = (x - run.x0_m - off[i]) / v
            if ti[0] < 0 or ti[-1] > t[-1]:
                raise ValueError(f"bogie_influence: run {run.pass_id} does not cover the span with both wheels")
            y = np.interp(ti, t, ap[:, i])
            ya, yb = np.interp(a, x, y), np.interp(b, x, y)
            ys.append(y - (ya + (yb - ya) * (x - a) / (b - a)))
        Y.append(ys)
        W.append(load)
    Y, W = np.asarray(Y), np.asarray(W)
    Wc = W - W.mean()
    if np.sum(Wc**2) <= (1e-3 * W.mean()) ** 2 * len(W):
        raise ValueError("bogie_influence: the runs' wheel loads hardly differ; the profile cannot be separated")
    slope = np.einsum("r,rik->ik", Wc, Y - Y.mean(axis=0)) / np.sum(Wc**2)
    intercept = Y.mean(axis=0) - slope * W.mean()
    on = (x >= a - 1e-9) & (x <= b + 1e-9)
    sos = butter(4, GRID_M / (0.5 * MIN_WAVELENGTH_M), output="sos")  # zero phase, over span and approaches
    J = sosfiltfilt(sos, -0.5 * (slope[0] + slope[1]))
    J_unseparated = sosfiltfilt(sos, -0.5 * (Y / W[:, None, None]).mean(axis=0).sum(axis=0))
    DIFF = np.asarray(DIFF)
    g = -np.einsum("r,rk->k", Wc, DIFF - DIFF.mean(axis=0)) / np.sum(Wc**2)
    g_unseparated = -(DIFF / W[:, None]).mean(axis=0)
    J_mean = sosfiltfilt(sos, -0.5 * Y.mean(axis=0).sum(axis=0))
    return BogieInfluence(MrIl(x[on] - a, J[on], len(runs)), W, intercept[:, on],
                          MrIl(x[on] - a, J_unseparated[on], len(runs)), _difference_mril(xd - a, g, M_span, c, len(runs)),
                          _difference_mril(xd - a, g_unseparated, M_span, c, len(runs)),
                          MrIl(x[on] - a, J_mean[on], len(runs)),
                          _difference_mril(xd - a, -DIFF.mean(axis=0), M_span, c, len(runs)),
                          MrIl(x - a, J_mean, len(runs)))


def damage_from_batch_means(healthy: BogieInfluence, current: BogieInfluence, fundamental: bool = False,
                            register: bool = True):
    """D1/D2 (eq. 3.24) of ``current`` against ``healthy`` when the two batches are different runs
    over the same track: the batch means Ȳ = p + W̄·J share the unloaded profile p, which the
    healthy batch's separated line J_H gives (p = Ȳ_H − W̄_H·J_H), so

        J_D = (Ȳ_D − p) / W̄_D = (Ȳ_D − Ȳ_H) / W̄_D + J_H · W̄_H / W̄_D.

    The regression alone (:attr:`BogieInfluence.mril`) is noisy across independent batches (its
    lever arm is the wheel load's ~7 % spread); here it only sets the scale. (Differencing the batch
    means of Y/W instead, J_H + mean_D(Y/W) − mean_H(Y/W), leaves p·(mean_D(1/W) − mean_H(1/W)):
    ~1 % of p between independent batches, and p relative to the supports' chord is as large as
    the deflection — about a point of D.) ``register``: first align the current batch's chainage to
    the healthy batch's on the approaches (:func:`_shift`; on the blind test's profile 1 this
    took the largest error over its six states from 1.8 to 1.7 points and the mean from 1.2 to 0.8,
    shifts of −11…+1 mm).
    ``fundamental``: the same on the wheels' difference (J⁰, free of a force at the bogie centre),
    not registered (registered by the same shift, profile 1's largest error went from 5.4 to 5.0
    points but state 2's from 0.5 to 4.0: no better)."""
    from .bridge.mril import damage_indicators

    ref, h, c = ((healthy.difference, healthy.difference_mean, current.difference_mean) if fundamental
                 else (healthy.mril, healthy.mean_line, current.mean_line))
    w_h, w_c = float(np.mean(healthy.wheel_load_n)), float(np.mean(current.wheel_load_n))
    c_J, h_J = c.J, h.J
    if not fundamental and register and healthy.approach_line is not None and current.approach_line is not None:
        delta = _shift(healthy.approach_line, current.approach_line, float(healthy.mril.x_m[-1]))
        c_J, h_J = _on_span(current.approach_line, ref.x_m, delta), _on_span(healthy.approach_line, ref.x_m, 0.0)
    return damage_indicators(ref, MrIl(ref.x_m, (c_J - h_J) / w_c + ref.J * w_h / w_c, current.mril.n_passes))


def _shift(healthy: MrIl, current: MrIl, span_m: float) -> float:
    """The chainage shift δ (m) of ``current``'s batch-mean line against ``healthy``'s, from the
    approaches (off the span). Each batch's calibrated speeds carry a common error of ~0.01 % (a
    centimetre 130 m on), and the unloaded profile's slope times a centimetre is a few per cent of
    the span's deflection: a point or two of D. Off the span the two batch means differ by that
    shift (δ·Ȳ_H'), a line (the chords) and the loads' difference times the track's compliance."""
    x = healthy.x_m
    off = (x < -1.0) | (x > span_m + 1.0)
    X = np.stack([np.gradient(healthy.J, x), np.ones_like(x), x], axis=1)[off]
    return float(np.linalg.lstsq(X, (current.J - healthy.J)[off], rcond=None)[0][0])


def _on_span(line: MrIl, x_span: np.ndarray, shift: float) -> np.ndarray:
    """``line`` on the span read at x − ``shift`` (Ȳ_D(x) ≈ Ȳ_H(x + δ)), relative to its values at the
    supports again."""
    y = np.interp(x_span - shift, line.x_m, line.J)
    return y - (y[0] + (y[-1] - y[0]) * x_span / x_span[-1])


def _difference_mril(x_m: np.ndarray, g: np.ndarray, M: int, c: int, n_runs: int) -> MrIl:
    """J⁰ on the span from g_k = J⁰_k − J⁰_(k−c), the slope over wheel loads of the two wheels'
    time-synchronous AP difference (eq. 3.16 with equal axle loads W: W·(δ_A − δ_B) = W²·(J⁰_k −
    J⁰_(k−c)); Betti removes the cross terms, the regression the profile's difference).

    Least squares with J⁰ = 0 off the span (the matrix method, eq. 3.17–3.23, for unit loads), then
    the low-pass of :data:`MIN_WAVELENGTH_M`. Why the difference: a body's force through the secondary
    suspension acts at the bogie's centre and moves both wheels' AP alike at each instant — the
    error of the bogie half-car (module docstring) cancels; a uniform track compliance cancels too.
    """
    K = M + c
    A = np.zeros((K, M))
    A[np.arange(M), np.arange(M)] = 1.0
    A[np.arange(c, K), np.arange(K - c)] = -1.0
    J = np.linalg.lstsq(A, g, rcond=None)[0]
    J -= J[0] + (J[-1] - J[0]) * np.arange(M) / (M - 1)  # relative to the supports, as the AP chords
    h = x_m[1] - x_m[0]
    J = sosfiltfilt(butter(4, h / (0.5 * MIN_WAVELENGTH_M), output="sos"), J)
    return MrIl(x_m[:M], J, n_runs)
