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

Measured (30 fleet-calibrated passes, 2 % noise, smooth deck; ``driveby reproduce bridge`` cases):
the largest element error falls from 10.5–10.8 to 8.5–8.7 points (healthy, global5, global10)
and the global estimates do not move (< 0.2 points). Most of the element error left is not of
this first-order form (projecting these directions out entirely changes it by < 1 point): at 30
passes it is within the posterior's bands and the information limit (the Cramér–Rao element sd
with the GMRF prior is 3–9 %).

A vehicle's passes share its δ; treating them as independent discards a little of the information
that repeated passes of one vehicle carry about its own δ (none with one pass each).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import numpy as np

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
    from cloud.calibration import calibration_names, class_prior

    vc = site.vehicle_class(model)
    _, sd = class_prior(model, dict(vc.mean), dict(vc.std))
    return dict(zip(calibration_names(model), (float(s) for s in sd)))


def fit_log_sd(fit) -> dict[str, float]:
    """Log-sd of the calibration quantities from a calibrator's :class:`~cloud.calibration.VehicleFit`
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
