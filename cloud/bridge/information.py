"""The information limit of a bridge scenario: Cramér–Rao bounds from the measured channel.

Whatever an estimator does with a fleet's passes, its error in the bridge's stiffness cannot beat
the Cramér–Rao bound of the data it is given. Here the bound is computed from our forward model of
what the vehicles measure: the coupled vehicle–bridge dynamics (:func:`shared.vbi.simulate_vbi`,
the moving quarter-car on the FE beam, bridge inertia and damping included), differentiated by
finite differences with respect to

* each element's log EI (θ_z, z = 1…n_e) — the per-element view;
* the global log EI (g: all θ_z equal) — ``∂/∂g = Σ_z ∂/∂θ_z``;
* a 3-parameter crack (location x_c m, depth ratio φ, global level g): θ = g + log crack factor
  (:func:`shared.fe.beam.crack_ei_factor`), by the chain rule through the element sensitivities;

and the nuisance log wheel load of each vehicle (all of its masses, stiffnesses and dampings
scaled together: the same dynamics, a different load — exactly what the off-bridge calibration
cannot see). Sensor noise is white in the measured channel with sd ``noise_pct`` % of the channel's
own sd (the simulator's and thesis's definition, eq. 2.34), so one pass contributes
``F_p = S_pᵀS_p / σ_p²``. Each vehicle's wheel load is marginalised with its class prior (relative
sd ``s_W``): the Schur complement ``F_θθ − F_θW (F_WW + 1/s_W²)⁻¹ F_Wθ`` per vehicle, summed.

The bound is local (at the scenario's true bridge) and covers the measured channel only — any
processing (AP inversion, band limits, drift control) can only lose information. Deck roughness
does not enter: the sensitivities are differences of simulations over the same surface, and the
approach is taken flat (the dynamic wheel load from roughness modulates the sensitivities by a few
per cent at most).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from shared.fe.beam import Beam, crack_ei_factor
from shared.vbi import simulate_vbi

#: finite-difference step in log EI and log wheel load
FD_STEP = 1e-3


@dataclasses.dataclass(frozen=True)
class PassCase:
    """What the bound needs of one pass: the vehicle (model, parameters, id), its speed (m/s) and
    its channel noise sd (m/s², or the channel's unit)."""

    vehicle_id: str
    model: str
    params: dict
    speed_mps: float
    noise_sd: float


@dataclasses.dataclass(frozen=True, eq=False)
class PassSensitivity:
    """Channel sensitivities of one pass: ``S`` (n, n_e) to each element's log EI and ``s_w`` (n,)
    to the log wheel load, divided by the pass's noise sd (so unit-variance noise)."""

    case: PassCase
    S: np.ndarray
    s_w: np.ndarray


def _run(beam: Beam, system, speed: float, start_m: float, pre_m: float, post_m: float,
         sample_rate_hz: float) -> np.ndarray:
    x0 = start_m - pre_m
    duration = (pre_m + beam.span_m + post_m) / speed
    flat = lambda x: np.zeros_like(np.asarray(x, dtype=float))  # noqa: E731
    resp = simulate_vbi(system, flat, flat, x0, speed, duration, 1.0 / sample_rate_hz, beam=beam,
                        bridge_start_m=start_m, gamma=0.5)
    return resp.channels[:, 0]


def pass_sensitivity(case: PassCase, beam: Beam, pre_m: float = 5.0, post_m: float = 25.0,
                     sample_rate_hz: float = 500.0, step: float = FD_STEP) -> PassSensitivity:
    """Finite-difference sensitivities of ``case``'s measured channel at the bridge ``beam``
    (its ``ei_factor`` is the linearisation point). The record runs from ``pre_m`` before the first
    support to ``post_m`` after the second (the bridge's free vibration after the vehicle left it
    no longer reaches the vehicle)."""
    from shared.vehicles import vehicle_from_params

    system = vehicle_from_params(case.model, dict(case.params)).system()
    start = pre_m  # route chainage of the first support
    base = _run(beam, system, case.speed_mps, start, pre_m, post_m, sample_rate_hz)
    n_e = beam.n_elements
    factor = beam.element_ei_factor()
    S = np.empty((base.size, n_e))
    for z in range(n_e):
        f = factor.copy()
        f[z] *= math.exp(step)
        S[:, z] = (_run(dataclasses.replace(beam, ei_factor=f), system, case.speed_mps, start, pre_m, post_m,
                        sample_rate_hz) - base) / step
    heavy = vehicle_from_params(case.model, {k: (v * math.exp(step) if k not in ("D1", "D2") else v)
                                             for k, v in case.params.items()}).system()
    s_w = (_run(beam, heavy, case.speed_mps, start, pre_m, post_m, sample_rate_hz) - base) / step
    return PassSensitivity(case, S / case.noise_sd, s_w / case.noise_sd)


@dataclasses.dataclass(frozen=True, eq=False)
class Information:
    """Fisher information of a fleet's passes in the element log-stiffnesses, wheel loads
    marginalised (``F``, n_e × n_e), and the bounds derived from it."""

    F: np.ndarray
    n_passes: int
    n_vehicles: int

    def global_sd(self) -> float:
        """CRB sd of the global log EI (≈ relative sd of the global stiffness)."""
        one = np.ones(self.F.shape[0])
        return float(1.0 / math.sqrt(one @ self.F @ one))

    def element_sd(self, prior_precision: np.ndarray | None = None) -> np.ndarray:
        """sd of each element's log EI: the CRB with 20 free elements, or — with the GMRF's
        ``prior_precision`` — the Bayesian (van Trees) bound of the regularised problem."""
        F = self.F if prior_precision is None else self.F + prior_precision
        return np.sqrt(np.diag(np.linalg.pinv(F)))

    def crack_sd(self, n_elements: int, span_m: float, depth_m: float, crack_x_m: float,
                 phi: float) -> np.ndarray:
        """CRB sd of (x_c m, φ, g) of a crack at (``crack_x_m``, ``phi``) (φ > 0: at φ = 0 the
        location is not identifiable)."""
        T = crack_jacobian(n_elements, span_m, depth_m, crack_x_m, phi)
        Fc = T.T @ self.F @ T
        return np.sqrt(np.diag(np.linalg.inv(Fc)))

    def scaled(self, n_passes: int, n_vehicles: int | None = None) -> "Information":
        """The information of ``n_passes`` passes like these (Fisher information adds up)."""
        k = n_passes / self.n_passes
        return Information(self.F * k, n_passes, int(round(self.n_vehicles * k)) if n_vehicles is None
                           else n_vehicles)


def crack_jacobian(n_elements: int, span_m: float, depth_m: float, crack_x_m: float, phi: float,
                   dx: float = 0.05, dphi: float = 1e-3) -> np.ndarray:
    """∂θ/∂(x_c, φ, g), (n_e, 3), by central differences of the log crack factor."""
    th = lambda x, p: np.log(crack_ei_factor(n_elements, span_m, depth_m, x, p))  # noqa: E731
    T = np.empty((n_elements, 3))
    T[:, 0] = (th(crack_x_m + dx, phi) - th(crack_x_m - dx, phi)) / (2 * dx)
    T[:, 1] = (th(crack_x_m, phi + dphi) - th(crack_x_m, max(phi - dphi, 0.0))) / (phi + dphi - max(phi - dphi, 0.0))
    T[:, 2] = 1.0
    return T


def fleet_information(sens: Sequence[PassSensitivity], weight_rel_sd: float) -> Information:
    """Sum the passes' information, each vehicle's log wheel load marginalised with its prior
    (relative sd ``weight_rel_sd``) — a vehicle's passes share one load."""
    n_e = sens[0].S.shape[1]
    F = np.zeros((n_e, n_e))
    by_vehicle: dict[str, list[float | np.ndarray]] = {}
    for s in sens:
        F += s.S.T @ s.S
        fw, ww = by_vehicle.get(s.case.vehicle_id, (np.zeros(n_e), 0.0))
        by_vehicle[s.case.vehicle_id] = (fw + s.S.T @ s.s_w, ww + float(s.s_w @ s.s_w))
    for fw, ww in by_vehicle.values():
        F -= np.outer(fw, fw) / (ww + 1.0 / weight_rel_sd**2)
    return Information(F, len(sens), len(by_vehicle))


def noise_sd_of(channel: np.ndarray, noise_pct: float) -> float:
    """The white noise sd that ``noise_pct`` % of a (noisy) channel's sd corresponds to:
    var(noisy) = var(signal)·(1 + p²)."""
    p = noise_pct / 100.0
    return float(p * np.std(channel) / math.sqrt(1.0 + p * p))
