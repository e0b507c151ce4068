"""The vehicle's calibration error as a nuisance of the bridge likelihood.

Each pass is compared in the measured-channel domain through the vehicle's forward model F(q̂) at
its *calibrated* quantities q̂ (ratios such as k/M, c/M): the model holds ``F(q̂)[·]`` of what the
vehicle drove over, the data ``F(q)[·]`` at the true q. The difference,
``Σ_k ∂F/∂log q_k [road − W·h] · δ_k`` with δ = log q − log q̂, is a signal-shaped error: mostly
the vehicle's response to the road before the bridge ringing on into the span (in whitened units
it is several times the noise along a few directions for a 4 % error), a little the deflection
itself. So δ is carried per pass as a Gaussian nuisance with the calibration's uncertainty,
``δ ~ N(0, diag(sd²))``, linearised at the consensus road, the design load term and the
class-mean wheel load, and integrated out exactly: the pass's noise covariance becomes
``I + C Σ Cᵀ`` (C: whitened sensitivity columns, rows × K), and every whitened column is mapped by
``(I + C Σ Cᵀ)^(-1/2)`` (a rank-K correction).

Integrated out, it lowers the largest element error on fleet-calibrated passes and leaves the
global estimate where it is (docs/results.md).

**The fleet-common part.** Fleet self-calibration fixes the vehicles relative to each other; their
common mode is pinned only by the class prior, so the fleet-mean error is about as large as the
calibration error itself: almost all of a quantity's rms log error is the fleet mean. Every pass then
mis-inverts the road in the same way, the consensus carries the same error, and the difference
between them is the AP error ringing on past the bridge entrance into the span — where a smooth
deck's consensus is known to be flat — with the same sign in every pass: it does not average out.
The per-pass model above cannot see it (its columns are the pass's response to the road, which
an error shared by the consensus mostly cancels). So the estimator also carries one common δ_c
per quantity, shared by all passes, as coordinates of the common nuisance μ with prior log-sd
σ_class/√N (the class prior's mean is that of N vehicles drawn from it; ``BridgeSettings``),
marginalised jointly with the stiffness (exact: the columns join the state; the hypotheses see the
same marginal likelihood). Its columns are ``u_p − 1_off·ū`` in the AP domain
(:func:`~cloud.bridge.whitening.common_calibration_columns`): the pass's AP distortion
(:func:`ap_distortion`) less the consensus' (the fleet mean, where the consensus is used).
Carried, it removes false crack alarms on healthy spans and reads the common error itself
(docs/results.md). It needs alias-free APs (the edge's ``EdgeConfig.antialias``): linearly
gridded, the inverse's noise up to 250 Hz folds into the band, several times the sensor noise in
the measured channel, coloured like the vehicle's transfer, and the common columns fit it
(``tests/test_bridge_common_calibration.py``).

A vehicle's passes share its δ; treating them as independent discards a little of the information
that repeated passes of one vehicle carry about its own δ (none with one pass each).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import numpy as np

from shared.dynamics.transfer import newmark_transfer
from shared.vehicles import vehicle_from_params
from shared.vehicles.calibration import calibration_names, class_prior

#: finite-difference step in the log calibration quantities
FD_STEP = 1e-3


def perturbed_params(params: Mapping[str, float], name: str, step: float) -> dict:
    """``params`` with the calibration quantity ``name`` ('k/M': k scaled, M fixed; 'D1': itself)
    multiplied by e^step."""
    p = dict(params)
    key = name.split("/")[0]
    if key not in p:
        raise ValueError(f"calibration quantity {name!r}: no parameter {key!r} in {sorted(p)}")
    p[key] = p[key] * math.exp(step)
    return p


def class_log_sd(site, model: str) -> dict[str, float]:
    """Log-sd of every calibration quantity under the vehicle class prior (an uncalibrated vehicle)."""
    vc = site.vehicle_class(model)
    _, sd = class_prior(model, dict(vc.mean), dict(vc.std))
    return dict(zip(calibration_names(model), (float(s) for s in sd)))


def fit_log_sd(fit) -> dict[str, float]:
    """Log-sd of the calibration quantities from a calibrator's :class:`~cloud.road.calibration.VehicleFit`
    (its 95 % interval on the quantity, taken as log-normal)."""
    lo, hi = np.asarray(fit.lo95, dtype=float), np.asarray(fit.hi95, dtype=float)
    sd = np.log(np.maximum(hi, 1e-300) / np.maximum(lo, 1e-300)) / (2 * 1.959964)
    return {n: float(s) for n, s in zip(fit.names, sd)}


@dataclasses.dataclass(frozen=True, eq=False)
class CalibrationMarginal:
    """The map ``v ↦ (I + C Σ Cᵀ)^(-1/2) v`` of one pass's whitened values, as an orthonormal basis
    ``V`` (rows × K) and the factors ``shrink`` = (1 + s)^(-1/2) − 1 along its columns; ``logdet``
    = log det(I + C Σ Cᵀ)."""

    V: np.ndarray
    shrink: np.ndarray
    logdet: float

    @classmethod
    def of(cls, C: np.ndarray, sd: np.ndarray) -> "CalibrationMarginal":
        C = np.asarray(C, dtype=float) * np.asarray(sd, dtype=float)[None, :]
        Q, R = np.linalg.qr(C)
        s, U = np.linalg.eigh(R @ R.T)
        s = np.maximum(s, 0.0)
        return cls(Q @ U, 1.0 / np.sqrt(1.0 + s) - 1.0, float(np.sum(np.log1p(s))))

    def __call__(self, v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, dtype=float)
        one = v.ndim == 1
        m = v[:, None] if one else v
        out = m + self.V @ (self.shrink[:, None] * (self.V.T @ m))
        return out[:, 0] if one else out


def ap_distortion(p, profile: np.ndarray, names) -> np.ndarray:
    """How the pass's AP of ``profile`` moves per unit of each calibration error δ_k (window grid,
    (n, K), m per log unit): the edge inverted the channel ``F(q)[profile]`` with the calibrated
    ``q̂`` = q·e^{−δ}, so ``AP ≈ profile + Σ_k δ_k·F(q̂)⁻¹ ∂F/∂log q_k [profile]``
    (:func:`distortion_of` at the pass's parameters, speed and grid).

    This is what a consensus built from every pass's AP carries when all passes share one
    calibration error (:class:`~cloud.bridge.estimator.BridgeSettings` ``common_calibration``):
    the AP error rings on past any abrupt change of the profile, into the span of a smooth deck.
    """
    return distortion_of(p.model, p.params, p.speed_mps, p.window.spacing_m, profile, names)


def distortion_of(model: str, params: Mapping[str, float], speed_mps: float, spacing_m: float,
                  profile: np.ndarray, names) -> np.ndarray:
    """``F(q̂)⁻¹ ∂F/∂log q_k [profile]`` (n, K) for a vehicle ``model`` at ``params`` driven at
    ``speed_mps`` over ``profile`` sampled every ``spacing_m``.

    Computed as the ratio of the forward model's discrete transfer functions
    (:func:`~shared.dynamics.transfer.newmark_transfer` with the trapezoidal rule of
    :class:`~cloud.bridge.passdata.VehicleFilter`), applied by FFT with zero padding: it is causal
    and stable (the channel's zeros — e.g. the suspension's k + c·s — are in the left half-plane),
    and zero at 0 Hz.
    """
    profile = np.asarray(profile, dtype=float)
    n = profile.size
    dt = spacing_m / speed_mps
    nfft = 1 << int(math.ceil(math.log2(3 * n)))
    f = np.fft.rfftfreq(nfft, dt)
    H0 = newmark_transfer(vehicle_from_params(model, dict(params)).system(), f, dt, 0.5, 0.25)[:, 0, 0]
    X = np.fft.rfft(profile - profile[0], nfft)
    ok = np.abs(H0) > 1e-12 * np.max(np.abs(H0))
    out = np.empty((n, len(names)))
    for k, name in enumerate(names):
        moved = vehicle_from_params(model, perturbed_params(params, name, FD_STEP)).system()
        Hk = newmark_transfer(moved, f, dt, 0.5, 0.25)[:, 0, 0]
        ratio = np.where(ok, (Hk - H0) / (FD_STEP * np.where(ok, H0, 1.0)), 0.0)
        out[:, k] = np.fft.irfft(ratio * X, nfft)[:n]
    return out
