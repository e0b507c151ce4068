"""A short rail bridge's stiffness from a calibrated batch of carriage runs (thesis §3.5–3.6): the
bogie's moving-reference deflection per unit wheel load, and the damage indicators D1/D2 (eq. 3.24)
against a healthy batch.

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
:func:`cloud.bridge.mril.damage_indicators` does. On a short span the unloaded profile relative to
the supports' line is as large as the deflection, so reading the mean AP per unit load with the
profile left in (``unseparated``, as the thesis does) dilutes D.

Across independent batches (different runs, as the thesis's) the per-batch slope is noisy: its
lever arm is the wheel load's small spread. The batch mean of the AP per unit load is not, and the
profile is common to every batch on the track, so :func:`damage_from_batch_means` takes the change
of that mean between the healthy and the current batch and only the scale from the healthy batch's
slope. That change is only profile-free if the two batches' chainages agree to a millimetre or two,
and each batch's calibrated speeds share an error of about a centimetre at the span, so the current
batch is first registered to the healthy one on the wheels' time-synchronous difference beside the
span (:func:`difference_shift`). The healthy regression line is taken relative to the supports
after its low-pass, as the batch-mean lines it is combined with are (chorded before it, its ends
would carry the track's deflection beside the span). What is left of the regression's scale is a
bias common to a track's batches, not noise (pooling the healthy line over every batch of the track,
:func:`pooled_healthy`, does not remove it), so the pooled line is reported, not used; the design
drawings give the scale instead where they are trusted (:func:`design_scale`).

The AP comes from the carriage inverse (all four channels) or from the 2-DOF bogie half-car of
App. A.3 (the leading bogie's two channels). The half-car ignores the body's force through the
secondary suspension; the body's response to the track depends on its mass, so the half-car's AP
error is correlated with the wheel load and the regression's slope is biased (it can even have the
wrong sign): the half-car cannot separate the profile this way. The two wheels' time-synchronous
difference is free of that force (it acts at the bogie's centre), so on the difference
(:attr:`BogieInfluence.difference`, the matrix method for J⁰ — the thesis's own reading for both
models, eq. 3.16–3.23) the half-car and the carriage give the same line, and the half-car is read
that way (one bogie's two channels and the calibrated run properties). The third reading,
``leading_bogie`` (:func:`leading_bogie_ap`), keeps the half-car's data (the leading bogie's two
channels) and models the body's force: the carriage's body, driven by the leading bogie and by a
trailing bogie simulated over the AP the leading wheels found. Every inverse here runs at the batch
calibration's Newmark γ (:data:`cloud.rail.carriage_inverse.INVERSE_GAMMA`), the one its properties were
fitted under.

Each run's calibrated speed is off by a little (centimetres of chainage at a span far into the
record), and the load regression turns the profile's slope times that into the line's scale by
chance correlation with the loads, so the reading is sensitive to the smallest change of a batch's
calibration. :func:`registered_runs` reads each run's speed error off its wheels' difference beside
the span first; :func:`run_aps` / :func:`influence_of_aps` split :func:`bogie_influence` so that the
reading can be redone on resampled or re-drawn runs (:func:`resampled_runs`,
:func:`calibration_draw`) for its own sd without re-running the inverses.

The deflection follows each wheel's dynamic contact force, not its static load. The dynamic force
follows the run's masses and speed, so across a batch it correlates with the static load, and each
run's chord through the supports takes the track's deflection there under it (the track deflects
more under a wheel than a short span does): the static-load regression takes both into the line's
scale. :func:`dynamic_wheel_forces` (the carriage model over the AP it found) and
:func:`static_equivalent` with :func:`ap_compliance` take both out, and the regression then finds
the static line of track and span. But that line is track and span together: the track's own
compliance varies along the span (its ballast and sub-ballast field), and no load regression can
separate its chorded share from the span's (both scale with the load). Read with the dynamic forces,
a reading carries that share in full, where in the static-load reading the dynamic shares of the
regression and of the batch means partly cancel it; and on the pipeline's AP the calibration adds
errors that follow the load. So ``dynamic`` is reported beside ours (``driveby reproduce rail``), not
used: a regression scale carries the track's share; the design drawings' scale
(:func:`design_scale`) does not.

(The thesis's matrix method, eq. 3.16–3.23, applied to b·W̄ of the two wheels, is available as
:func:`cloud.bridge.mril.mril_two_axle`; on our simulated batches its indicators read further from
the truth than those of J itself.)

Needs variation of the wheel load across the batch (passengers: mv's class sd ~10 %). Pure
functions on arrays.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np
from scipy import linalg
from scipy.signal import butter, sosfiltfilt

from shared.dynamics.forward import ap_response, channels_from_ap, trapezoid_rate
from shared.dynamics.inverse import InverseStream, build_inverse
from shared.dynamics.newmark import newmark_constants
from shared.fe.beam import contact_matrix, influence_line, stiffness_matrix
from shared.fe.design import design_beam
from shared.vehicles import GRAVITY
from shared.vehicles.bogie import BogieHalfCar
from shared.vehicles.carriage import Carriage

from cloud.bridge.mril import MrIl, damage_indicators
from cloud.rail.calibration import FIXED, BatchFit
from cloud.rail.carriage_inverse import INVERSE_GAMMA
from cloud.rail.fundamental import chord_windows, difference_mril, registered_fundamental
from cloud.rail.records import RailRun

GRID_M = 0.05
APPROACH_M = 10.0  # AP kept either side of the span, m
#: Shortest wavelength kept in J, m. The regression's noise is short-waved and the span's vibration
#: (~14 Hz at 30 m/s: ~2 m) rides on the line; a 10 m span's static line has nothing below ~5 m.
#: The thesis low-passes its mean MR-IL too (FIR, §3.5.3) before reading the mid-span ordinate.
MIN_WAVELENGTH_M = 4.0
#: Track used to register two batches' chainage on the wheels' difference (:func:`difference_shift`),
#: m before and after the span (less where a batch's runs do not cover it); the last
#: ``REGISTER_EDGE_M`` of each end are left out (the filters' end effects), and waves longer than
#: ``REGISTER_MAX_WAVELENGTH_M`` (the inverses' drift) are removed first.
REGISTER_BEFORE_M = 40.0
REGISTER_AFTER_M = 20.0
REGISTER_EDGE_M = 2.0
REGISTER_MAX_WAVELENGTH_M = 20.0
REGISTER_ITERATIONS = 3


@dataclasses.dataclass(frozen=True, eq=False)
class BogieInfluence:
    """The leading bogie's deflection per unit wheel load on the span (m/N, positive down) and what
    went into it."""

    mril: MrIl  # x_m from the first support
    wheel_load_n: np.ndarray  # (n_runs,) static wheel load of each run, N
    intercept_m: np.ndarray  # (2, K) a_i(x): the profile (relative to the supports' line), m
    #: The thesis's reading (profile not separated): −½ Σ_i mean_r(y_r,i / W_r), m/N — for comparison.
    unseparated: MrIl | None = None
    #: J⁰ by the matrix method on the wheels' time-synchronous AP difference (:func:`cloud.rail.fundamental.difference_mril`).
    difference: MrIl | None = None
    #: The same from the batch mean of the difference per unit load (profile left in), m/N.
    difference_unseparated: MrIl | None = None
    #: The batch-mean AP line −½ Σ_i mean_r y_r,i (profile and load both in), m — and of the
    #: difference, by the matrix method: what :func:`damage_from_batch_means` compares.
    mean_line: MrIl | None = None
    difference_mean: MrIl | None = None
    #: The batch-mean AP line over the span and its approaches (x from the first support), m.
    approach_line: MrIl | None = None
    #: The batch mean of the wheels' time-synchronous AP difference −(y_1 − y_2) over the span and its
    #: approaches, at wheel 1's chainage x (from the first support), m, neither filtered nor chorded:
    #: what registers two batches' chainage (:func:`damage_from_batch_means`) and, shifted, what the
    #: registered J⁰ is read from.
    difference_line: MrIl | None = None
    wheelbase_m: float | None = None  # the leading bogie's wheel spacing 2·Lb the difference is taken over
    #: The track's compliance at the supports fitted with the dynamic wheel forces (:func:`static_equivalent`;
    #: m/N, up per unit downward force; None: the runs carry no forces, the static load regression).
    track_compliance_m_per_n: float | None = None


def _leading_bogie_ap(run: RailRun, est, globals_: dict[str, float], class_mean: dict[str, float],
                      model: str) -> tuple[np.ndarray, np.ndarray, float, float, np.ndarray | None]:
    """AP (n, 2) under the leading bogie's two wheels, their offsets ahead of the body's centre of
    gravity (m), the run's speed (m/s), its static wheel load (N) and (``carriage`` only, else None)
    the two wheels' dynamic contact forces (n, 2; :func:`dynamic_wheel_forces`), under the run's
    calibration.

    ``carriage``: the 6-DOF carriage inverse from all four channels (App. B.2). ``bogie_half_car``:
    the 2-DOF bogie half-car of App. A.3 (Table 3.5: the bogie's mass, inertia, primary suspension
    and half wheelbase) from the leading bogie's two channels alone — the body's load through the
    secondary suspension is not modelled, as in the thesis's test of a simpler model.
    """
    car = Carriage(**{**{k: class_mean[k] for k in FIXED}, **globals_, **est.mean})
    load = GRAVITY * (car.mv / 4 + car.mb / 2 + car.mw)
    force = None
    if model == "carriage":
        ap = InverseStream(build_inverse(car.system(), run.dt, gamma=INVERSE_GAMMA)).update(run.channels)
        force = dynamic_wheel_forces(car, ap, run.dt)[:, :2]
        ap = ap[:, :2]
    elif model == "bogie_half_car":
        bogie = BogieHalfCar(ms=car.mb, Is=car.Ib, K1=car.kp, K2=car.kp, C1=car.cp, C2=car.cp, D1=car.Lb, D2=car.Lb)
        ap = InverseStream(build_inverse(bogie.system(), run.dt, gamma=INVERSE_GAMMA)).update(np.asarray(run.channels)[:, :2])
    elif model == "leading_bogie":
        ap = leading_bogie_ap(car, np.asarray(run.channels, dtype=float)[:, :2], run.dt)
    else:
        raise ValueError(f"bogie_influence: unknown model {model!r} ({', '.join(MODELS)})")
    return ap, car.wheel_offsets_m()[:2], car.v, load, force


#: The inverses :func:`bogie_influence` can read the AP with.
MODELS = ("carriage", "bogie_half_car", "leading_bogie")
#: Passes of :func:`leading_bogie_ap`: the fixed point has converged after two (a third changes
#: nothing); what remains of its error against the four-channel inverse is mostly the start transient.
LEADING_BOGIE_PASSES = 2


def leading_bogie_ap(car: Carriage, z: np.ndarray, dt: float, passes: int = LEADING_BOGIE_PASSES) -> np.ndarray:
    """AP (n, 2) under the leading bogie's two wheels from that bogie's two channels alone
    (``z`` (n, 2): acceleration, pitch rate at step ``dt``), the body's force modelled.

    The bogie half-car (App. A.3) leaves out the body's force through the secondary suspension; it
    is ks/(2·kp) ≈ 0.18 of the body's motion at the pivot, which rings at the body's ~1 Hz modes and
    depends on the run's mv, Iv and v: its AP error on the span is of the order of the deflection and
    correlates with the wheel load, so neither the load regression nor the batch means survive it.
    Here the body is the carriage's,
    under the run's calibrated properties, driven by both bogies; the trailing bogie, 2·Lv behind on
    the same rail, runs over the AP the leading wheels found 2·Lv/v earlier. A fixed point: start
    with the trailing bogie's channels a delayed copy of the leading one's, invert the carriage
    (App. B.2) for the leading wheels' AP, simulate the trailing bogie (and the body) over that AP
    delayed (Newmark, the inverse's γ) for its channels, and repeat ``passes`` times. Before the
    trailing wheels reach the first sample's chainage (2·Lv/v) their AP is unknown and held at the
    leading wheels' first value: a body transient that decays over the approach (~2 s).
    """
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
        zz[:, 2:] = channels_from_ap(system, y, c)[:, 2:]
    return InverseStream(inverse).update(zz)[:, :2]


#: The dynamic wheel forces are low-passed to waves longer than this, m: the AP's noise, twice
#: differentiated for the wheelset's inertia, is short-waved (unfiltered, it swamps the dynamic part),
#: and J itself keeps nothing shorter than :data:`MIN_WAVELENGTH_M`.
FORCE_MIN_WAVELENGTH_M = 2.0


def dynamic_wheel_forces(car: Carriage, ap: np.ndarray, dt: float) -> np.ndarray:
    """(n, 4) each wheel's contact force on the rail less its static load (N, pressing down), of the
    carriage ``car`` (wheels following the rail) over the AP ``ap`` (n, 4; m, up) at step ``dt``:
    the carriage simulated over the AP (Newmark at the inverse's γ, from static equilibrium on its
    first sample) and each wheelset's force balance, mw·ÿ + kp·(y − bogie point) + cp·(ẏ − its rate),
    low-passed (:data:`FORCE_MIN_WAVELENGTH_M` at the run's speed). The AP the carriage inverse found is
    the profile the measured body and bogies responded to, so this is the force the track felt."""
    s = car.system()
    ap = np.asarray(ap, dtype=float)
    ydot = trapezoid_rate(ap, 0.0, dt)
    state = ap_response(s, ap, newmark_constants(dt, INVERSE_GAMMA))
    yddot = np.gradient(np.gradient(ap, dt, axis=0), dt, axis=0)
    force = car.mw * yddot + s.kc * (ap - state.u @ s.G) + s.cc * (ydot - state.v @ s.G)
    cutoff_hz = car.v / FORCE_MIN_WAVELENGTH_M
    if cutoff_hz < 0.5 / dt:
        force = sosfiltfilt(butter(4, cutoff_hz * 2.0 * dt, output="sos"), force, axis=0)
    return force


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
    # (The runs' own chainage shifts, RunEstimate.shift_m, are not applied here: each batch is registered
    # on the wheels' difference beside the span below, and the per-run shifts add nothing to that.)
    return influence_of_aps(run_aps(runs, fit, class_mean, model), start_m, span_m)


@dataclasses.dataclass(frozen=True, eq=False)
class RunAp:
    """One run's AP under the leading bogie's two wheels and what keys it to the track."""

    pass_id: str
    ap_m: np.ndarray  # (n, 2) at step dt_s from the run's first sample
    dt_s: float
    x0_m: float  # chainage of the body's centre of gravity at the first sample (the log's)
    offsets_m: np.ndarray  # (2,) the two wheels ahead of the body's centre of gravity
    speed_mps: float  # calibrated
    wheel_load_n: float  # calibrated static wheel load
    #: (n, 2) the two wheels' contact forces less the static load, N (:func:`dynamic_wheel_forces`;
    #: None: not modelled, the load regression takes the static load alone).
    dynamic_force_n: np.ndarray | None = None


def run_aps(runs: Sequence[RailRun], fit: BatchFit, class_mean: dict[str, float], model: str) -> list[RunAp]:
    """Each run's AP under its calibrated properties (:func:`_leading_bogie_ap`): the expensive half of
    :func:`bogie_influence`; :func:`influence_of_aps` is the rest."""
    out = []
    for run, est in zip(runs, fit.runs):
        ap, off, v, load, force = _leading_bogie_ap(run, est, fit.globals_, class_mean, model)
        out.append(RunAp(run.pass_id, ap, run.dt, run.x0_m, np.asarray(off, dtype=float), v, load, force))
    return out


def influence_of_aps(aps: Sequence[RunAp], start_m: float, span_m: float, dynamic: bool = False) -> BogieInfluence:
    """:func:`bogie_influence` from the runs' APs (:func:`run_aps`). ``dynamic``: each wheel's AP on the
    span first taken to what the static load alone would give (:func:`static_equivalent`, with the
    compliance of :func:`ap_compliance`) from the runs' dynamic wheel forces (every run must carry them);
    the wheels' difference (J⁰) is left as it is."""
    if len(aps) < 3:
        raise ValueError("bogie_influence: needs at least three runs (a slope over wheel loads)")
    a, b = start_m, start_m + span_m
    x = np.arange(a - APPROACH_M, b + APPROACH_M + 1e-9, GRID_M)
    # The registration window: as much of REGISTER_BEFORE_M/AFTER_M as every run covers (whole grid steps).
    front = [r.x0_m + r.offsets_m[0] for r in aps]
    end = [r.x0_m + (len(r.ap_m) - 1) * r.dt_s * r.speed_mps + r.offsets_m[0] for r in aps]
    before = GRID_M * np.floor(min(REGISTER_BEFORE_M, a - max(front) - 0.5) / GRID_M)
    after = GRID_M * np.floor(min(REGISTER_AFTER_M, min(end) - b - 0.5) / GRID_M)
    if before < APPROACH_M or after < APPROACH_M:
        raise ValueError(f"bogie_influence: the runs cover less than {APPROACH_M:g} m either side of the span")
    xr = a + np.arange(-round(before / GRID_M), round((b - a + after) / GRID_M) + 1) * GRID_M
    Y, W, DIFF, DX, FD = [], [], [], [], []
    M_span = c = None
    if dynamic and any(r.dynamic_force_n is None for r in aps):
        raise ValueError("bogie_influence: dynamic needs every run's dynamic wheel forces (the carriage model's)")
    for r in aps:
        ap, off, v, load = r.ap_m, r.offsets_m, r.speed_mps, r.wheel_load_n
        t = np.arange(len(ap)) * r.dt_s
        if c is None:  # the difference's grid: a whole number c of steps per wheelbase
            c = max(1, int(round((off[0] - off[1]) / GRID_M)))
            h = (off[0] - off[1]) / c
            M_span = int(np.floor(span_m / h + 1e-9)) + 1
            xd = a + h * np.arange(M_span + c)
        # Both wheels at one instant, wheel 1 at xd (wheel 2 a wheelbase behind); the line through
        # its means beyond the ends (both wheels off the span, before and after) removes the drift.
        wheels = ap[:, 0] - ap[:, 1]
        dd = np.interp((xd - r.x0_m - off[0]) / v, t, wheels)
        e0, e1 = (np.interp((xe - r.x0_m - off[0]) / v, t, wheels).mean() for xe in chord_windows(xd))
        DIFF.append(dd - (e0 + (e1 - e0) * (xd - a) / (xd[-1] - a)))
        DX.append(np.interp((xr - r.x0_m - off[0]) / v, t, wheels))
        ys, fs = [], []
        for i in (0, 1):
            ti = (x - r.x0_m - off[i]) / v
            if ti[0] < 0 or ti[-1] > t[-1]:
                raise ValueError(f"bogie_influence: run {r.pass_id} does not cover the span with both wheels")
            y = np.interp(ti, t, ap[:, i])
            ya, yb = np.interp(a, x, y), np.interp(b, x, y)
            ys.append(y - (ya + (yb - ya) * (x - a) / (b - a)))
            if dynamic:
                fs.append(np.interp(ti, t, r.dynamic_force_n[:, i]))
        Y.append(ys)
        W.append(load)
        FD.append(fs)
    Y, W = np.asarray(Y), np.asarray(W)
    Wc = W - W.mean()
    if np.sum(Wc**2) <= (1e-3 * W.mean()) ** 2 * len(W):
        raise ValueError("bogie_influence: the runs' wheel loads hardly differ; the profile cannot be separated")
    compliance = None
    if dynamic:  # the AP under the static loads alone
        compliance = ap_compliance(aps, a, before)
        Y = static_equivalent(Y, W, np.asarray(FD), x, a, b, compliance)
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
    return BogieInfluence(MrIl(x[on] - a, J[on], len(aps)), W, intercept[:, on],
                          MrIl(x[on] - a, J_unseparated[on], len(aps)), difference_mril(xd - a, g, M_span, c, len(aps), min_wavelength_m=MIN_WAVELENGTH_M),
                          difference_mril(xd - a, g_unseparated, M_span, c, len(aps), min_wavelength_m=MIN_WAVELENGTH_M),
                          MrIl(x[on] - a, J_mean[on], len(aps)),
                          difference_mril(xd - a, -DIFF.mean(axis=0), M_span, c, len(aps), min_wavelength_m=MIN_WAVELENGTH_M),
                          MrIl(x - a, J_mean, len(aps)), MrIl(xr - a, -np.mean(DX, axis=0), len(aps)), h * c,
                          track_compliance_m_per_n=compliance)


def static_equivalent(Y: np.ndarray, W: np.ndarray, dynamic: np.ndarray, x: np.ndarray, a: float, b: float,
                      compliance: float) -> np.ndarray:
    """The runs' chorded APs ``Y`` (runs, 2, K; on the grid ``x``, each relative to its line through
    its values at the supports ``a``, ``b``) as they would be under the static wheel loads ``W`` (runs,)
    alone, given each wheel's dynamic force there (``dynamic`` (runs, 2, K), N; :func:`dynamic_wheel_forces`)
    and the AP's compliance ``compliance`` under a wheel force beside the span (m/N, up per unit
    downward force; :func:`ap_compliance`).

    Under a wheel force F = W + ΔF the deflection under the wheel at x is b(x)·F(x) (b: track and
    bridge, the neighbouring wheel's share included) and the chord through the supports takes T·F
    there (T: the compliance beside the span; the span deflects nothing at its supports), so

        y_r(x) = a(x) + b(x)·F_r(x) + T·(ΔF_r(x) − ℓ_r(x))        (ℓ_r: ΔF_r's line through the supports)

    with b the static regression's deflection per unit load (for ΔF = 0 this is that regression). b by
    least squares over the runs at each x and wheel, and the runs' APs returned as a(x) + b(x)·W_r +
    residual: the static-load regression, the batch means and the registration downstream are
    unchanged. Why: the dynamic force follows the run's masses and speed, not its load alone, so it
    correlates with the static load across a batch, and T·ΔF at the supports (the track deflects more
    under a wheel than a short span does) is as large as the span's share: the static-load regression
    takes both into the line's scale. Taking out the dynamic force alone removes part of that, with T
    all of it."""
    F = W[:, None, None] + dynamic
    # ΔF less its chord (W's chord is W: the static load cancels).
    fa = np.stack([[np.interp(a, x, f) for f in run] for run in dynamic])
    fb = np.stack([[np.interp(b, x, f) for f in run] for run in dynamic])
    phi = dynamic - (fa[..., None] + (fb - fa)[..., None] * (x - a) / (b - a))
    Y = Y - compliance * phi
    Fc = F - F.mean(axis=0)
    slope = np.sum(Fc * (Y - Y.mean(axis=0)), axis=0) / np.sum(Fc**2, axis=0)
    return Y - slope * dynamic


#: :func:`ap_compliance` keeps waves between these lengths, m: longer ones carry the inverse's drift and
#: the static loads' deflection (a constant per run), shorter ones its noise.
COMPLIANCE_BAND_M = (2.0, 10.0)


def ap_compliance(aps: Sequence[RunAp], start_m: float, before_m: float) -> float:
    """The AP's compliance under a wheel force beside the span, m/N (up per unit downward force): the
    slope of the runs' AP on their dynamic wheel forces (:attr:`RunAp.dynamic_force_n`) over the
    ``before_m`` of track before the span (the last :data:`REGISTER_EDGE_M` left out), both band-passed
    (:data:`COMPLIANCE_BAND_M`), across the runs at each chainage (the profile is common to them), both
    wheels and every chainage pooled. Only the dynamic force can show it: a static load's deflection is
    a constant per run, which the drift's removal takes with it.

    It is the track's compliance plus what the inverse adds: the AP is the bogie's point plus the
    primary suspension's deflection, so a calibrated kp off by δ puts (1/kp_cal − 1/kp)·ΔF_primary
    into the AP, which acts the same way (a per-cent error of kp is of the order of the track's own
    compliance). So on the inverse's AP under calibrated properties it reads the track's compliance
    less well than under the true ones."""
    a = start_m
    x = np.arange(a - before_m, a - REGISTER_EDGE_M, GRID_M)
    k = int(round(0.5 * COMPLIANCE_BAND_M[1] / GRID_M))  # the filters' ends, left out
    if len(x) < 4 * k:
        raise ValueError(f"ap_compliance: {before_m:g} m before the span is too short (at least "
                         f"{4 * k * GRID_M + REGISTER_EDGE_M:g} m)")
    band = (butter(2, GRID_M / (0.5 * COMPLIANCE_BAND_M[1]), btype="high", output="sos"),
            butter(4, GRID_M / (0.5 * COMPLIANCE_BAND_M[0]), output="sos"))
    Y, F = [], []
    for r in aps:
        t = np.arange(len(r.ap_m)) * r.dt_s
        for i in (0, 1):
            ti = (x - r.x0_m - r.offsets_m[i]) / r.speed_mps
            Y.append(np.interp(ti, t, r.ap_m[:, i]))
            F.append(np.interp(ti, t, r.dynamic_force_n[:, i]))
    Y, F = (np.asarray(v).reshape(len(aps), 2, len(x)) for v in (Y, F))
    Y, F = (sosfiltfilt(band[1], sosfiltfilt(band[0], v, axis=-1), axis=-1) for v in (Y, F))
    Y, F = Y[..., k:-k], F[..., k:-k]
    Yc, Fc = Y - Y.mean(axis=0), F - F.mean(axis=0)
    # Each run's chainage error δ_r leaves δ_r·p'(x) (the profile's slope: far larger than the signal) in
    # both; its share is taken out of each run first (what registered_runs would do, here on the
    # compliance's band).
    g = np.gradient(Y.mean(axis=0), GRID_M, axis=-1)
    gg = float(np.sum(g**2))
    if gg > 0.0:
        Yc = Yc - np.einsum("rik,ik->r", Yc, g)[:, None, None] * g / gg
        Fc = Fc - np.einsum("rik,ik->r", Fc, g)[:, None, None] * g / gg
    sff = float(np.sum(Fc**2))
    return float(np.sum(Yc * Fc)) / sff if sff > 0.0 else 0.0


def registered_runs(aps: Sequence[RunAp], start_m: float, span_m: float,
                    iterations: int = REGISTER_ITERATIONS, reference: MrIl | None = None) -> list[RunAp]:
    """``aps`` with each run's speed corrected so that its wheels' time-synchronous difference beside
    the span lines up with the batch's mean (the runs' mean shift at mid-span unchanged: registering
    the batch as a whole is :func:`difference_shift`'s).

    Why: a run's calibrated speed is off by ε_r (a few hundredths of a per cent), which puts its AP
    ε_r·(x − x_r) off in chainage at x (x_r: where its record starts): centimetres at a span far into
    the record. The unloaded profile's slope times that is a few per cent of the deflection per run,
    and the load regression over the batch's small load spread turns its chance correlation with the
    loads into the line's scale, many times larger. The profile is the same for every run, so each
    run's ε_r is read off the wheels' difference over the registration window
    (:data:`REGISTER_BEFORE_M`/``AFTER_M``, the span and the wheelbase after it left out), where the
    body's force cannot move it: Gauss–Newton on
    c_r(x − ε_r·(x − x_r)) against the batch mean, the mean re-formed from the registered runs each
    step (band as in :func:`difference_shift`). ``reference``: another batch's
    :attr:`BogieInfluence.difference_line` (the healthy batch's, registered) to register every run to
    instead, its mean shift included (so that the batch-to-batch registration has ~nothing left)."""
    a, b = start_m, start_m + span_m
    x1 = np.array([r.x0_m + r.offsets_m[0] for r in aps])  # wheel 1 at each record's first sample
    end = [r.x0_m + (len(r.ap_m) - 1) * r.dt_s * r.speed_mps + r.offsets_m[0] for r in aps]
    before = GRID_M * np.floor(min(REGISTER_BEFORE_M, a - x1.max() - 0.5) / GRID_M)
    after = GRID_M * np.floor(min(REGISTER_AFTER_M, min(end) - b - 0.5) / GRID_M)
    if before < APPROACH_M or after < APPROACH_M:
        raise ValueError(f"registered_runs: the runs cover less than {APPROACH_M:g} m either side of the span")
    x = a + np.arange(-round(before / GRID_M), round((b - a + after) / GRID_M) + 1) * GRID_M
    wb = float(aps[0].offsets_m[0] - aps[0].offsets_m[1])
    sos_lo = butter(4, GRID_M / (0.5 * MIN_WAVELENGTH_M), output="sos")
    sos_hi = butter(2, GRID_M / (0.5 * REGISTER_MAX_WAVELENGTH_M), output="sos")
    lines = []
    for r in aps:
        t = np.arange(len(r.ap_m)) * r.dt_s
        y = sosfiltfilt(sos_lo, np.interp((x - r.x0_m - r.offsets_m[0]) / r.speed_mps, t, r.ap_m[:, 0] - r.ap_m[:, 1]))
        lines.append(y - sosfiltfilt(sos_hi, y))
    lines = np.asarray(lines)
    off = ((x < a - 1.0) | (x > b + wb + 1.0)) & (x > x[0] + REGISTER_EDGE_M) & (x < x[-1] - REGISTER_EDGE_M)
    mid = 0.5 * (a + b)
    if reference is not None:  # another batch's difference_line: −(y_1 − y_2), x from the first support
        y = sosfiltfilt(sos_lo, np.interp(x - a, reference.x_m, -reference.J))
        ref_line = y - sosfiltfilt(sos_hi, y)
    eps = np.zeros(len(aps))
    for _ in range(iterations):
        shifted = np.array([np.interp(x - e * (x - xr), x, line) for e, xr, line in zip(eps, x1, lines)])
        ref = shifted.mean(axis=0) if reference is None else ref_line
        for i in range(len(aps)):
            slope = np.gradient(0.5 * (ref + shifted[i]), x)[off] * (x[off] - x1[i])
            eps[i] += float(slope @ (shifted[i] - ref)[off]) / float(slope @ slope)
        if reference is None:  # the batch's mean shift at mid-span is the batch registration's
            eps -= np.mean(eps * (mid - x1)) / (mid - x1)
    return [dataclasses.replace(r, speed_mps=r.speed_mps * (1.0 + e)) for r, e in zip(aps, eps)]


def calibration_sds(fit: BatchFit, class_mean: dict[str, float], class_std: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """Each run's calibration uncertainty as the reading feels it, from the fit's 95 % intervals: the
    sd of its log speed with the bogie spacing's share taken out (that one moves every run alike:
    the registrations absorb it; :func:`cloud.rail.calibration.calibrate_batch` adds it to every
    run's interval) and the sd of its static wheel load (N, from mv's). The mass's interval carries
    the held globals' error too, common to every run and batch, so the load's is an upper bound."""
    lv = class_std["Lv"] / class_mean["Lv"]
    z = 2.0 * 1.959963984540054
    speed = np.array([math.sqrt(max(math.log(e.hi95["v"] / e.lo95["v"]) ** 2 / z**2 - lv**2, 0.0)) for e in fit.runs])
    load = np.array([GRAVITY * e.mean["mv"] / 4 * math.log(e.hi95["mv"] / e.lo95["mv"]) / z for e in fit.runs])
    return speed, load


def resampled_runs(aps: Sequence[RunAp], rng: np.random.Generator) -> list[RunAp]:
    """A bootstrap batch: as many runs drawn from ``aps`` with replacement (the batch's own noise)."""
    return [aps[i] for i in rng.integers(0, len(aps), len(aps))]


def calibration_draw(aps: Sequence[RunAp], rng: np.random.Generator, speed_log_sd: np.ndarray,
                     load_sd_n: np.ndarray) -> list[RunAp]:
    """``aps`` with each run's speed and wheel load drawn from its calibration's uncertainty
    (:func:`calibration_sds`), independently per run. (The carriage inverse's AP depends on the
    run's mv and Iv too; that is left out: drawn per run at their marginal sd, they move the
    carriage's readings through AP and load together by a fraction of a point.)"""
    return [dataclasses.replace(r, speed_mps=r.speed_mps * math.exp(rng.normal() * sv), wheel_load_n=r.wheel_load_n + rng.normal() * sw)
            for r, sv, sw in zip(aps, speed_log_sd, load_sd_n)]


def damage_from_batch_means(healthy: BogieInfluence, current: BogieInfluence, fundamental: bool = False,
                            register: bool = True):
    """D1/D2 (eq. 3.24) of ``current`` against ``healthy`` when the two batches are different runs
    over the same track: the batch means Ȳ = p + W̄·J share the unloaded profile p, which the
    healthy batch's separated line J_H gives (p = Ȳ_H − W̄_H·J_H), so

        J_D = (Ȳ_D − p) / W̄_D = (Ȳ_D − Ȳ_H) / W̄_D + J_H · W̄_H / W̄_D.

    The regression alone (:attr:`BogieInfluence.mril`) is noisy across independent batches (its
    lever arm is the wheel load's small spread); here it only sets the scale. (Differencing the batch
    means of Y/W instead, J_H + mean_D(Y/W) − mean_H(Y/W), leaves p·(mean_D(1/W) − mean_H(1/W)): a
    per cent or so of p between independent batches, and p relative to the supports' chord is as
    large as the deflection — about a point of D.)

    ``register``: first shift the current batch's chainage onto the healthy batch's
    (:func:`difference_shift`): each batch's calibrated speeds share an error (the carriage's bogie
    spacing is known only so well), a few millimetres to a centimetre at the span, and the unloaded
    profile's slope times a centimetre is a few per cent of the deflection. The shift is read off the
    wheels' time-synchronous difference on the approaches, which the body's force cannot move (it acts
    at the bogie's centre) — unlike the batch-mean AP lines, whose long-wave errors differ between
    batches. Both readings are registered by it (only the wheels' difference is needed, so the bogie
    half-car's data register themselves).
    ``fundamental``: the same on the wheels' difference (J⁰, free of a force at the bogie centre):
    J⁰ of each batch mean by the matrix method from the registered difference line, the healthy
    batch's regression J⁰ for the scale."""
    ref = healthy.difference if fundamental else healthy.mril
    w_h, w_c = float(np.mean(healthy.wheel_load_n)), float(np.mean(current.wheel_load_n))
    lines = (healthy.difference_line, current.difference_line)
    delta = 0.0
    if register:
        if None in lines or healthy.wheelbase_m is None:
            raise ValueError("damage_from_batch_means: registering needs both batches' difference lines")
        delta = difference_shift(*lines, float(healthy.mril.x_m[-1]), healthy.wheelbase_m)
    if fundamental:
        if None in lines:
            c_J, h_J = current.difference_mean.J, healthy.difference_mean.J
        else:
            c_J, h_J = (registered_fundamental(line, shift, float(healthy.mril.x_m[-1]), healthy.wheelbase_m,
                                               grid_m=GRID_M, min_wavelength_m=MIN_WAVELENGTH_M)
                        for line, shift in ((current.difference_line, delta), (healthy.difference_line, 0.0)))
    elif healthy.approach_line is not None and current.approach_line is not None:
        c_J, h_J = _on_span(current.approach_line, ref.x_m, delta), _on_span(healthy.approach_line, ref.x_m, 0.0)
        # The scale line as the batch-mean lines are: relative to the supports after the low-pass
        # (chorded only before it, its ends are off zero by the track's deflection beside the span
        # smeared in, and mixing the two conventions reads D low).
        ref = _on_span(ref, ref.x_m, 0.0, as_line=True)
    else:
        c_J, h_J = current.mean_line.J, healthy.mean_line.J
    readable_line(ref, "damage_from_batch_means: the healthy line (the scale)")
    line = readable_line(MrIl(ref.x_m, (c_J - h_J) / w_c + ref.J * w_h / w_c, current.mril.n_passes),
                         "damage_from_batch_means: the current batch's line")
    return damage_indicators(ref, line)


def readable_line(line: MrIl, what: str) -> MrIl:
    """``line`` (a deflection per unit load on the span, positive down) if D can be read from it, else
    a ValueError naming ``what``: its area and its mid-span ordinate must both be positive. D = 100·(1 −
    IL_H/IL_D) divides by them, so a line near zero or of the wrong sign reads any D at all. That is what
    an AP whose errors follow the wheel load more than the deflection does gives (e.g. ``leading_bogie``
    where its on-span error varies between runs more than the deflection does over their loads). Not a
    test of accuracy: a wrong but positive line passes."""
    area, mid = line.area, line.midspan()
    if not (area > 0.0 and mid > 0.0):
        raise ValueError(f"{what} is not a deflection (area {area * 1e9:.3g} µm·m/kN, mid-span "
                         f"{mid * 1e9:.3g} µm/kN; both must be positive; likely an AP whose errors follow the "
                         f"wheel load more than the deflection does): D not read")
    return line


def pooled_healthy(healthy: BogieInfluence, batches: Sequence[BogieInfluence], weights=None) -> BogieInfluence:
    """``healthy`` with its deflection per unit load (:attr:`BogieInfluence.mril`) and its J⁰
    (:attr:`BogieInfluence.difference`) estimated from every batch over the same track, not from
    its own load regression alone. Each batch b's regression J_b and the change of its batch mean
    give the healthy line whatever the damage (only the unloaded profile p is assumed common):

        Ȳ_b = p + W̄_b·J_b,  Ȳ_H = p + W̄_H·J_H  ⇒  J_H = (W̄_b·J_b − (Ȳ_b − Ȳ_H)) / W̄_H,

    and these (:func:`healthy_estimates`) are averaged with ``weights`` (per batch, or per batch and
    line: (J, J⁰)), by default Σ(W − W̄_b)²/W̄_b² (the regression's precision; its noise dominates the
    batch means', and weights from each estimate's own bootstrap and calibration-draw variance read
    about the same). Each batch is registered to ``healthy`` first, as in
    :func:`damage_from_batch_means`; ``batches`` may include ``healthy`` (its own regression).
    Pooling cuts the regression's noise by about the square root of the number of batches, but not a
    bias every batch's regression shares (module docstring); on the wheels' difference (J⁰) both are
    larger. The lines are relative to the supports after the low-pass, as
    :func:`damage_from_batch_means` reads them."""
    if not batches:
        raise ValueError("pooled_healthy: needs at least one batch")
    estimates = healthy_estimates(healthy, batches)
    if weights is None:
        weights = [float(np.sum((b.wheel_load_n - np.mean(b.wheel_load_n)) ** 2)) / float(np.mean(b.wheel_load_n)) ** 2
                   for b in batches]
    w = np.asarray(weights, dtype=float)
    w = np.repeat(w[:, None], 2, axis=1) if w.ndim == 1 else w
    if w.shape != (len(batches), 2) or not np.all(w >= 0) or not np.all(w.sum(axis=0) > 0):
        raise ValueError("pooled_healthy: weights must be (n_batches,) or (n_batches, 2), non-negative, not all zero")
    J = sum(wb * e[0] for wb, e in zip(w[:, 0], estimates)) / w[:, 0].sum()
    J0 = sum(wb * e[1] for wb, e in zip(w[:, 1], estimates)) / w[:, 1].sum()
    return dataclasses.replace(healthy, mril=MrIl(healthy.mril.x_m, J, healthy.mril.n_passes),
                               difference=MrIl(healthy.difference.x_m, J0, healthy.difference.n_passes))


def healthy_estimates(healthy: BogieInfluence, batches: Sequence[BogieInfluence]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each batch's estimate of ``healthy``'s line, (J on ``healthy.mril.x_m``, J⁰ on
    ``healthy.difference.x_m``): (W̄_b·J_b − (Ȳ_b − Ȳ_H))/W̄_H, the batch registered to ``healthy``
    first (:func:`pooled_healthy`)."""
    span, wb = float(healthy.mril.x_m[-1]), healthy.wheelbase_m
    if healthy.difference_line is None or healthy.approach_line is None or wb is None:
        raise ValueError("pooled_healthy: needs the batches' approach and difference lines")
    x, xd = healthy.mril.x_m, healthy.difference.x_m
    w_h = float(np.mean(healthy.wheel_load_n))
    h_J, h_0 = _on_span(healthy.approach_line, x, 0.0), registered_fundamental(healthy.difference_line, 0.0, span, wb, grid_m=GRID_M, min_wavelength_m=MIN_WAVELENGTH_M)
    out = []
    for b in batches:
        w_b = float(np.mean(b.wheel_load_n))
        delta = 0.0 if b is healthy else difference_shift(healthy.difference_line, b.difference_line, span, wb)
        J = (w_b * _on_span(b.mril, x, delta) - (_on_span(b.approach_line, x, delta) - h_J)) / w_h
        d0 = np.interp(xd - delta, b.difference.x_m, b.difference.J)
        J0 = (w_b * d0 - (registered_fundamental(b.difference_line, delta, span, wb, grid_m=GRID_M, min_wavelength_m=MIN_WAVELENGTH_M) - h_0)) / w_h
        out.append((J, J0))
    return out


def design_scale(bridge, healthy: BogieInfluence) -> BogieInfluence:
    """``healthy`` with its deflection per unit load (:attr:`BogieInfluence.mril`, J⁰ + J¹ of the
    leading bogie's two equal loads) and its J⁰ (:attr:`BogieInfluence.difference`) replaced by the
    design span's static lines (the registry's E·I, span; :func:`shared.fe.design.design_beam`),
    chorded and low-passed as the data's are: the scale :func:`damage_from_batch_means` takes from the
    healthy batch's load regression, from the drawings instead. The regression's scale is the
    reading's largest error once the batches are registered (its lever arm is the loads' small
    spread, and AP errors that follow the load — calibration, dynamic wheel loads — bias it even on
    the true AP; the dynamic loads' share can be taken out, :func:`static_equivalent`, but the
    track's own compliance along the span cannot: module docstring); the drawings' is as good as the
    design is of the healthy span (on our simulated spans their element scatter averages out; on a
    real bridge the design can be tens of per cent off, which moves D by as many per cent of D).
    ``bridge``: :class:`shared.registry.Bridge`."""
    beam = design_beam(bridge)
    x, span, wb = healthy.approach_line.x_m, float(healthy.mril.x_m[-1]), float(healthy.wheelbase_m)
    n1, n2 = contact_matrix(beam, np.clip(x, 0.0, span)), contact_matrix(beam, np.clip(x - wb, 0.0, span))
    J = np.einsum("ij,ji->i", n1, linalg.solve(stiffness_matrix(beam), (n1 + n2).T, assume_a="pos"))
    J = _lowpassed(MrIl(x, J * ((x >= 0.0) & (x <= span)), 0))
    on = (x >= -1e-9) & (x <= span + 1e-9)
    xs, J = x[on], J[on]
    xd = healthy.difference.x_m
    J0 = _lowpassed(MrIl(xd, influence_line(beam, np.clip(xd, 0.0, span)), 0))
    return dataclasses.replace(healthy, mril=MrIl(xs, J - (J[0] + (J[-1] - J[0]) * xs / span), 0),
                               difference=MrIl(xd, J0, 0))


def _lowpassed(line: MrIl) -> np.ndarray:
    h = float(line.x_m[1] - line.x_m[0])
    return sosfiltfilt(butter(4, h / (0.5 * MIN_WAVELENGTH_M), output="sos"), line.J)


def difference_shift(healthy: MrIl, current: MrIl, span_m: float, wheelbase_m: float) -> float:
    """The chainage shift δ (m) at mid-span of ``current``'s batch-mean wheel difference against
    ``healthy``'s (``current(x − δ) ≈ healthy(x)``), from the track either side of the span: where
    neither wheel is on the span, the difference is the unloaded profile's p(x) − p(x − 2·Lb) plus
    the track's, so the two batches differ by the shift times its slope, plus drift and noise. The
    shift grows along the track (it is a speed error: δ(x) = δ + ε·(x − x_mid)), so a stretch ε is
    fitted with it; waves beyond :data:`REGISTER_MAX_WAVELENGTH_M` (drift) and below
    :data:`MIN_WAVELENGTH_M` are filtered out of both lines first. Gauss–Newton
    (:data:`REGISTER_ITERATIONS` steps, ``current`` resampled at the shifted chainage each time) on
    the two lines' mean slope: the healthy line's slope alone is a noisy regressor, which pulls a
    single step's δ towards zero."""
    def band(y: np.ndarray, h: float) -> np.ndarray:
        y = sosfiltfilt(butter(4, h / (0.5 * MIN_WAVELENGTH_M), output="sos"), y)
        return y - sosfiltfilt(butter(2, h / (0.5 * REGISTER_MAX_WAVELENGTH_M), output="sos"), y)

    # Both lines on the same stretch of grid before filtering, so the filters' end effects match.
    x = healthy.x_m
    x = x[(x >= current.x_m[0] - 1e-9) & (x <= current.x_m[-1] + 1e-9)]
    step = float(x[1] - x[0])
    h = band(np.interp(x, healthy.x_m, healthy.J), step)
    off = ((x < -1.0) | (x > span_m + wheelbase_m + 1.0)) & (x > x[0] + REGISTER_EDGE_M) & (x < x[-1] - REGISTER_EDGE_M)
    shift, stretch = 0.0, 0.0
    for _ in range(REGISTER_ITERATIONS):
        c = band(np.interp(x - shift - stretch * (x - 0.5 * span_m), current.x_m, current.J), step)
        slope = np.gradient(0.5 * (h + c), x)
        X = np.stack([slope, (x - 0.5 * span_m) * slope], axis=1)[off]
        d_shift, d_stretch = np.linalg.lstsq(X, (c - h)[off], rcond=None)[0]
        shift, stretch = shift + float(d_shift), stretch + float(d_stretch)
    return shift


def _on_span(line: MrIl, x_span: np.ndarray, shift: float, as_line: bool = False):
    """``line`` on the span read at x − ``shift`` (Ȳ_D(x) ≈ Ȳ_H(x + δ)), relative to its values at the
    supports again (as an :class:`MrIl` with ``as_line``)."""
    y = np.interp(x_span - shift, line.x_m, line.J)
    y = y - (y[0] + (y[-1] - y[0]) * x_span / x_span[-1])
    return MrIl(x_span, y, line.n_passes) if as_line else y
