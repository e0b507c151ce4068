"""Fleet self-calibration, the vehicle step: a vehicle's identifiable ratios given the consensus.

Only ratios are identifiable (divide the equations of motion by the body mass): the AP depends on
``K/M, k/M, c/M, m/M`` of a quarter-car, not on ``M``. So each model is parametrised by its
reference mass, held at the class mean, and the ratios of every other mass, stiffness and damping
to it; lengths (axle positions) stay absolute.

The step runs in the cloud but needs no raw data: a segment's AP under a known calibration is a
lossless encoding of the vehicle's measured channels (the inverse is exactly invertible), so the
AP the vehicle *would* have produced under candidate parameters θ is

    AP_θ = inverse_θ( forward_θ0( AP_θ0 ) )

computed in the time domain at the pass's speed. Fitting θ to the consensus (leave-this-vehicle-
out) in a band of wavelengths the vehicle resolves, under the class prior, is a small nonlinear
least-squares problem; its Laplace approximation gives 95 % intervals.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import butter, sosfiltfilt

from shared.dynamics.forward import measured_channels
from shared.dynamics.inverse import InverseStream, build_inverse
from shared.dynamics.newmark import integrate, newmark_constants
from shared.vehicles import MODELS, vehicle_from_params

#: model → (reference mass, absolute length parameters)
REFERENCE = {
    "sprung_mass": ("m", ()),
    "quarter_car": ("M", ()),
    "half_car": ("ms", ("D1", "D2")),
    "bogie_half_car": ("ms", ("D1", "D2")),
}

REMAP_DT = 0.002  # s: the time grid of the remap (the logger rate; the filter barely depends on it)
BAND_M = (1.0, 30.0)  # wavelengths compared: resolved by every pass, free of drift-control effects


def calibration_names(model: str) -> list[str]:
    """The identifiable quantities of a model, e.g. ``['m/M', 'K/M', 'k/M', 'c/M']``."""
    ref, lengths = REFERENCE[model]
    names = []
    for p in MODELS[model].param_names():
        if p == ref:
            continue
        names.append(p if p in lengths else f"{p}/{ref}")
    return names


def to_calibration(model: str, params: dict[str, float]) -> dict[str, float]:
    ref, lengths = REFERENCE[model]
    return {n: (params[n] if "/" not in n else params[n.split("/")[0]] / params[ref])
            for n in calibration_names(model)}


def from_calibration(model: str, cal: dict[str, float], ref_value: float) -> dict[str, float]:
    ref, _ = REFERENCE[model]
    params = {ref: ref_value}
    for n, v in cal.items():
        params[n.split("/")[0]] = v * ref_value if "/" in n else v
    return params


def class_prior(model: str, mean: dict[str, float], std: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """Prior on the log of each calibration quantity (delta method from the class's mean/std)."""
    ref, _ = REFERENCE[model]
    mu, sd = [], []
    for n in calibration_names(model):
        if "/" in n:
            p = n.split("/")[0]
            mu.append(math.log(mean[p] / mean[ref]))
            cv = math.hypot(std[p] / mean[p], std[ref] / mean[ref])
        else:
            mu.append(math.log(mean[n]))
            cv = std[n] / mean[n]
        sd.append(max(cv, 1e-3))
    return np.array(mu), np.array(sd)


@dataclasses.dataclass(frozen=True)
class PassAp:
    """One pass's AP under known parameters, per contact, on the route grid (NaN: no data)."""

    start_index: int
    spacing_m: float
    values: np.ndarray  # (n_points, n_contacts)
    speed_mps: float


@dataclasses.dataclass(frozen=True)
class VehicleFit:
    names: list[str]
    mean: np.ndarray  # calibration quantities (ratios, lengths)
    lo95: np.ndarray
    hi95: np.ndarray
    params: dict[str, float]  # full parameter set (reference mass at the class mean)
    residual_m: float  # rms band-passed misfit to the consensus
    n_points: int


def _band(spacing_m: float):
    lo, hi = BAND_M
    return butter(2, [1.0 / hi, 1.0 / lo], btype="band", fs=1.0 / spacing_m, output="sos")


def _forward_channels(model: str, params: dict, ap_t: np.ndarray) -> np.ndarray:
    system = vehicle_from_params(model, params).system()
    c = newmark_constants(REMAP_DT)
    force = (ap_t * system.kc) @ system.G.T
    u0 = np.linalg.solve(system.K, system.G @ (system.kc * ap_t[0]))
    return measured_channels(system, integrate(system.M, system.C, system.K, force, c, u0=u0))


class PassRemap:
    """One pass prepared for the vehicle step, in acceleration space.

    The vehicle's measured channels are reconstructed from its AP (forward model under the
    parameters the AP was computed with); candidate parameters θ are scored by how well the
    forward model under θ, driven by the consensus profile, predicts those channels. Sensor noise
    is white in this space, so least squares here weights every wavelength as the data do
    (the likelihood of thesis eq. 4.1 with the consensus in place of the unknown profile).
    """

    WARMUP_S = 2.0  # both signals start from an assumed rest state: skip the transient

    def __init__(self, model: str, params0: dict, ap: PassAp, consensus: np.ndarray, offsets_m=None):
        self.model = model
        n_points, n_contacts = ap.values.shape
        x = (ap.start_index + np.arange(n_points)) * ap.spacing_m
        valid = np.all(np.isfinite(ap.values), axis=1) & np.all(np.isfinite(consensus), axis=1)
        x0, x1 = x[valid][0], x[valid][-1]
        xt = np.arange(x0, x1, ap.speed_mps * REMAP_DT)
        vals = np.where(np.isfinite(ap.values), ap.values, 0.0)
        cons = np.where(np.isfinite(consensus), consensus, 0.0)
        ap_t = np.stack([np.interp(xt, x, vals[:, i]) for i in range(n_contacts)], axis=1)
        self.profile_t = np.stack([np.interp(xt, x, cons[:, i]) for i in range(n_contacts)], axis=1)
        self.z = _forward_channels(model, params0, ap_t)
        self.skip = int(self.WARMUP_S / REMAP_DT)
        self.n = max(self.z.shape[0] - self.skip, 0)
        self.scale = np.std(self.z[self.skip:], axis=0) + 1e-12  # channels in comparable units

    def residual(self, params: dict) -> np.ndarray:
        pred = _forward_channels(self.model, params, self.profile_t)
        return ((pred - self.z)[self.skip:] / self.scale).ravel()


def fit_vehicle(model: str, params0: dict, passes: list[tuple[PassAp, np.ndarray]],
                prior: tuple[np.ndarray, np.ndarray], ref_value: float) -> VehicleFit:
    """The vehicle step. ``passes``: (AP under ``params0``, leave-one-out consensus on the same
    grid slice, shape (n_points, n_contacts)). Returns ratios with 95 % intervals."""
    names = calibration_names(model)
    offsets = vehicle_from_params(model, params0).system().offsets_m
    remaps = [PassRemap(model, params0, ap, cons, offsets) for ap, cons in passes]
    mu, sd = prior
    theta0 = np.log(np.array([to_calibration(model, params0)[n] for n in names]))
    n_res = sum(r.n * r.z.shape[1] for r in remaps)
    n_eff = float(max(n_res, 1))  # white residuals: every sample counts
    state = {"sigma": None}

    def data_res(theta):
        params = from_calibration(model, dict(zip(names, np.exp(theta))), ref_value)
        return np.concatenate([r.residual(params) for r in remaps])

    r0 = data_res(theta0)
    state["sigma"] = max(float(np.sqrt(np.mean(r0**2))), 1e-9)

    def fun(theta):
        w = math.sqrt(n_eff / n_res) / state["sigma"]
        return np.concatenate([w * data_res(theta), (theta - mu) / sd])

    for _ in range(2):  # re-estimate the misfit scale once at the optimum (empirical Bayes)
        sol = least_squares(fun, theta0, x_scale=np.maximum(sd, 0.01), diff_step=1e-4, max_nfev=200)
        theta0 = sol.x
        rr = data_res(theta0)
        state["sigma"] = max(float(np.sqrt(np.mean(rr**2))), 1e-9)
    sol = least_squares(fun, theta0, x_scale=np.maximum(sd, 0.01), diff_step=1e-4, max_nfev=50)
    J = sol.jac
    try:
        cov = np.linalg.inv(J.T @ J)
        se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        se = sd.copy()
    mean = np.exp(sol.x)
    params = from_calibration(model, dict(zip(names, mean)), ref_value)
    return VehicleFit(names, mean, np.exp(sol.x - 1.96 * se), np.exp(sol.x + 1.96 * se), params,
                      float(np.sqrt(np.mean(data_res(sol.x) ** 2))), n_res)
