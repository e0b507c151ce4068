"""A short rail bridge's stiffness from a calibrated batch of carriage runs (thesis §3.5–3.6, issue #6
item 6): the bogie's moving-reference deflection per unit wheel load, and the damage indicators
D1/D2 (eq. 3.24) against a healthy batch.

On the span, the AP under a wheel is the rail's unloaded profile plus the deflection of track and
bridge under the carriage. The profile is the same for every run, the deflection scales with the
run's wheel load W_r = g·(mv/4 + mb/2 + mw) (the batch calibration's masses), so across the runs of
a batch, at each chainage,

    y_r,i(x) = a_i(x) + W_r · b_i(x)        (i = the leading bogie's two wheels)

and the slope b_i (least squares over runs) is the deflection per unit wheel load with the profile
gone. Each run's AP is first taken relative to the line through its values at the two supports
(the thesis's drift removal by the zero deflection at the supports, which also removes the track's
own settlement there). J(x) = −½(b_1 + b_2) is the leading bogie's influence per unit wheel load
(J⁰(x) + J¹(x, x ∓ 2·Lb) in the thesis's notation); D1 and D2 compare its mid-span ordinate and its
area over the span with the healthy batch's, as :func:`cloud.bridge.mril.damage_indicators` does.

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

from shared.dynamics.inverse import InverseStream, build_inverse
from shared.vehicles import GRAVITY
from shared.vehicles.carriage import Carriage

from .bridge.mril import MrIl
from .rail_calibration import FIXED, BatchFit, RailRun

GRID_M = 0.05
APPROACH_M = 10.0  # AP kept either side of the span, m


@dataclasses.dataclass(frozen=True, eq=False)
class BogieInfluence:
    """The leading bogie's deflection per unit wheel load on the span (m/N, positive down) and what
    went into it."""

    mril: MrIl  # x_m from the first support
    wheel_load_n: np.ndarray  # (n_runs,) static wheel load of each run, N
    intercept_m: np.ndarray  # (2, K) a_i(x): the profile (relative to the supports' line), m


def bogie_influence(runs: Sequence[RailRun], fit: BatchFit, class_mean: dict[str, float], start_m: float,
                    span_m: float) -> BogieInfluence:
    """J(x) of a batch over the span [start_m, start_m + span_m] (route chainage, m), with each run
    inverted under its calibrated properties (``fit``; ``class_mean`` supplies the fixed lengths
    and wheelset mass)."""
    if len(runs) != len(fit.runs) or any(r.pass_id != e.pass_id for r, e in zip(runs, fit.runs)):
        raise ValueError("bogie_influence: the fit must be of these runs, in order")
    if len(runs) < 3:
        raise ValueError("bogie_influence: needs at least three runs (a slope over wheel loads)")
    a, b = start_m, start_m + span_m
    x = np.arange(a - APPROACH_M, b + APPROACH_M + 1e-9, GRID_M)
    Y, W = [], []
    for run, est in zip(runs, fit.runs):
        car = Carriage(**{k: class_mean[k] for k in FIXED}, **fit.globals_, **est.mean)
        ap = InverseStream(build_inverse(car.system(), run.dt)).update(run.channels)
        t = np.arange(len(ap)) * run.dt
        off = car.wheel_offsets_m()
        ys = []
        for i in (0, 1):
            ti = (x - run.x0_m - off[i]) / car.v
            if ti[0] < 0 or ti[-1] > t[-1]:
                raise ValueError(f"bogie_influence: run {run.pass_id} does not cover the span with both wheels")
            y = np.interp(ti, t, ap[:, i])
            ya, yb = np.interp(a, x, y), np.interp(b, x, y)
            ys.append(y - (ya + (yb - ya) * (x - a) / (b - a)))
        Y.append(ys)
        W.append(GRAVITY * (car.mv / 4 + car.mb / 2 + car.mw))
    Y, W = np.asarray(Y), np.asarray(W)
    Wc = W - W.mean()
    if np.sum(Wc**2) <= (1e-3 * W.mean()) ** 2 * len(W):
        raise ValueError("bogie_influence: the runs' wheel loads hardly differ; the profile cannot be separated")
    slope = np.einsum("r,rik->ik", Wc, Y - Y.mean(axis=0)) / np.sum(Wc**2)
    intercept = Y.mean(axis=0) - slope * W.mean()
    on = (x >= a - 1e-9) & (x <= b + 1e-9)
    J = -0.5 * (slope[0] + slope[1])
    return BogieInfluence(MrIl(x[on] - a, J[on], len(runs)), W, intercept[:, on])
