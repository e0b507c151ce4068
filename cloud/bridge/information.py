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

**Calibration error.** The vehicles' parameters are known only as well as fleet self-calibration
knows them, and that error is a nuisance of the bound as of the estimator
(:mod:`cloud.bridge.vehicle_error`): a part every pass of the class shares (the fleet-common mode,
prior log-sd ``common_sd`` per quantity) and a part of each pass's own (``pass_sd``). The road off
the span is unknown too (the estimator takes it from the fleet's consensus; the deck on the span is
known flat), so a common error is seen only as what a common change of that road cannot explain:
per pass the channel column ``F_p[u_p − 1_off·ū]`` with ``u_p = F_p⁻¹∂F_p/∂log q [road + deflection]``
(the AP distortion, :func:`~cloud.bridge.vehicle_error.distortion_of`) and ``ū`` its fleet mean —
the error's ringing into the span, and the passes' different speeds. A pass's own error has the
column ``F_p[u_p]`` (the others' consensus does not move with it). Both need the scenario's road
(``PassCase.road``); they are marginalised with their priors jointly with the loads
(:func:`fleet_information`), the common one across all passes (:meth:`Information.marginal`).

**Every element within ±b.** :func:`largest_error`: the distribution of the largest element error
of an estimator at the bound with a given prior, where the truth is what the prior expects (a
healthy span) — its yardstick is A·F·A, not the posterior sd (the function's docstring says why).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from shared.fe.beam import Beam, crack_ei_factor, influence_line
from shared.vbi import simulate_vbi
from shared.vehicles import vehicle_from_params

from cloud.bridge.passdata import VehicleFilter
from cloud.bridge.vehicle_error import distortion_of

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
    #: the road, elevation (m) at distance x (m) from the first support, vectorised; None: flat
    road: object = None


@dataclasses.dataclass(frozen=True, eq=False)
class PassSensitivity:
    """Channel sensitivities of one pass: ``S`` (n, n_e) to each element's log EI and ``s_w`` (n,)
    to the log wheel load, divided by the pass's noise sd (so unit-variance noise)."""

    case: PassCase
    S: np.ndarray
    s_w: np.ndarray
    #: the AP distortion per calibration quantity u_p (n_grid, K) on ``grid_x`` (distance from the
    #: first support, m) and the channel samples' positions ``sample_x`` (empty: not computed)
    u: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0)))
    grid_x: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    sample_x: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

    def calibration_columns(self, mean_u: np.ndarray, span_m: float) -> tuple[np.ndarray, np.ndarray]:
        """The whitened channel columns of the fleet-common error (``F_p[u_p − 1_off·ū]``) and of the
        pass's own (``F_p[u_p]``), (n, K) each, at the channel samples."""
        c = self.case
        spacing = float(self.grid_x[1] - self.grid_x[0])
        vf = VehicleFilter(vehicle_from_params(c.model, dict(c.params)).system(), c.speed_mps, spacing)
        off = (self.grid_x < 0.0) | (self.grid_x > span_m)
        cols = vf.whiten(np.column_stack([self.u - off[:, None] * mean_u, self.u]))
        at = np.column_stack([np.interp(self.sample_x, self.grid_x, col) for col in cols.T]) / c.noise_sd
        k = self.u.shape[1]
        return at[:, :k], at[:, k:]


def _run(beam: Beam, system, speed: float, start_m: float, pre_m: float, post_m: float,
         sample_rate_hz: float) -> np.ndarray:
    x0 = start_m - pre_m
    duration = (pre_m + beam.span_m + post_m) / speed
    flat = lambda x: np.zeros_like(np.asarray(x, dtype=float))  # noqa: E731
    resp = simulate_vbi(system, flat, flat, x0, speed, duration, 1.0 / sample_rate_hz, beam=beam,
                        bridge_start_m=start_m, gamma=0.5)
    return resp.channels[:, 0]


def pass_sensitivity(case: PassCase, beam: Beam, pre_m: float = 5.0, post_m: float = 25.0,
                     sample_rate_hz: float = 500.0, step: float = FD_STEP, calibration: Sequence[str] = (),
                     approach_m: float = 60.0, spacing_m: float = 0.05) -> PassSensitivity:
    """Finite-difference sensitivities of ``case``'s measured channel at the bridge ``beam``
    (its ``ei_factor`` is the linearisation point). The record runs from ``pre_m`` before the first
    support to ``post_m`` after the second (the bridge's free vibration after the vehicle left it
    no longer reaches the vehicle). ``calibration``: the calibration quantities whose error is a
    nuisance (module docstring); their AP distortion is computed over the road from ``approach_m``
    before the span on a ``spacing_m`` grid (the estimator's window)."""
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
    if not calibration:
        return PassSensitivity(case, S / case.noise_sd, s_w / case.noise_sd)
    grid = np.arange(-approach_m, beam.span_m + post_m + 0.5 * spacing_m, spacing_m)
    road = np.zeros(grid.size) if case.road is None else np.asarray(case.road(grid), dtype=float)
    on = (grid >= 0.0) & (grid <= beam.span_m)
    load = float(system.static_contact_forces()[0])
    profile = road - load * on * influence_line(beam, np.clip(grid, 0.0, beam.span_m))
    u = distortion_of(case.model, case.params, case.speed_mps, spacing_m, profile, list(calibration))
    sample_x = -pre_m + case.speed_mps * np.arange(base.size) / sample_rate_hz
    return PassSensitivity(case, S / case.noise_sd, s_w / case.noise_sd, u, grid, sample_x)


@dataclasses.dataclass(frozen=True, eq=False)
class Information:
    """Fisher information of a fleet's passes in the element log-stiffnesses, wheel loads
    marginalised (``F``, n_e × n_e), and the bounds derived from it."""

    F: np.ndarray
    n_passes: int
    n_vehicles: int
    #: the fleet-common calibration error's blocks of the joint information (elements × K, K × K)
    #: and its prior precision (K,); empty: not a nuisance
    F_tc: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0)))
    F_cc: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0)))
    common_precision: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

    def marginal(self) -> np.ndarray:
        """The elements' information with the fleet-common calibration error marginalised (Schur
        complement with its prior): it does not add up over passes, the joint blocks do."""
        if self.common_precision.size == 0:
            return self.F
        return self.F - self.F_tc @ np.linalg.solve(self.F_cc + np.diag(self.common_precision), self.F_tc.T)

    def global_sd(self) -> float:
        """CRB sd of the global log EI (≈ relative sd of the global stiffness)."""
        one = np.ones(self.F.shape[0])
        return float(1.0 / math.sqrt(one @ self.marginal() @ one))

    def element_sd(self, prior_precision: np.ndarray | None = None) -> np.ndarray:
        """sd of each element's log EI: the CRB with 20 free elements, or — with the GMRF's
        ``prior_precision`` — the Bayesian (van Trees) bound of the regularised problem."""
        F = self.marginal() if prior_precision is None else self.marginal() + prior_precision
        return np.sqrt(np.diag(np.linalg.pinv(F)))

    def crack_sd(self, n_elements: int, span_m: float, depth_m: float, crack_x_m: float,
                 phi: float) -> np.ndarray:
        """CRB sd of (x_c m, φ, g) of a crack at (``crack_x_m``, ``phi``) (φ > 0: at φ = 0 the
        location is not identifiable)."""
        T = crack_jacobian(n_elements, span_m, depth_m, crack_x_m, phi)
        Fc = T.T @ self.marginal() @ T
        return np.sqrt(np.diag(np.linalg.inv(Fc)))

    def scaled(self, n_passes: int, n_vehicles: int | None = None) -> "Information":
        """The information of ``n_passes`` passes like these (Fisher information adds up)."""
        k = n_passes / self.n_passes
        return Information(self.F * k, n_passes, int(round(self.n_vehicles * k)) if n_vehicles is None
                           else n_vehicles, self.F_tc * k, self.F_cc * k, self.common_precision)


def crack_jacobian(n_elements: int, span_m: float, depth_m: float, crack_x_m: float, phi: float,
                   dx: float = 0.05, dphi: float = 1e-3) -> np.ndarray:
    """∂θ/∂(x_c, φ, g), (n_e, 3), by central differences of the log crack factor."""
    th = lambda x, p: np.log(crack_ei_factor(n_elements, span_m, depth_m, x, p))  # noqa: E731
    T = np.empty((n_elements, 3))
    T[:, 0] = (th(crack_x_m + dx, phi) - th(crack_x_m - dx, phi)) / (2 * dx)
    T[:, 1] = (th(crack_x_m, phi + dphi) - th(crack_x_m, max(phi - dphi, 0.0))) / (phi + dphi - max(phi - dphi, 0.0))
    T[:, 2] = 1.0
    return T


def fleet_information(sens: Sequence[PassSensitivity], weight_rel_sd: float,
                      common_sd: Sequence[float] | None = None, pass_sd: Sequence[float] | None = None,
                      span_m: float | None = None) -> Information:
    """Sum the passes' information, each vehicle's log wheel load marginalised with its prior
    (relative sd ``weight_rel_sd``) — a vehicle's passes share one load.

    With the passes' calibration distortions (:func:`pass_sensitivity` ``calibration``), the
    calibration error is a nuisance too: each pass's own part with prior log-sd ``pass_sd`` (per
    quantity, marginalised pass by pass), and the fleet-common part with ``common_sd`` (kept as
    joint blocks, marginalised by :meth:`Information.marginal`); ``span_m``: the span (m)."""
    if common_sd is not None or pass_sd is not None:
        return _fleet_information_calibrated(sens, weight_rel_sd, common_sd, pass_sd, span_m)
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


def _fleet_information_calibrated(sens, weight_rel_sd, common_sd, pass_sd, span_m) -> Information:
    if span_m is None or any(s.u.size == 0 for s in sens):
        raise ValueError("fleet_information: calibration nuisances need pass_sensitivity(calibration=...) and span_m")
    n_e, K = sens[0].S.shape[1], sens[0].u.shape[1]
    mean_u = np.mean([s.u for s in sens], axis=0)
    n_c = K if common_sd is not None else 0
    by_vehicle: dict[str, np.ndarray] = {}
    for s in sens:
        common, own = s.calibration_columns(mean_u, span_m)
        X = np.column_stack([s.S, s.s_w, common[:, :n_c]])  # θ, log W, common δ
        info = X.T @ X
        if pass_sd is not None:  # this pass's own error, integrated out with its prior
            G = own.T @ X
            info -= G.T @ np.linalg.solve(own.T @ own + np.diag(1.0 / np.asarray(pass_sd, dtype=float) ** 2), G)
        v = s.case.vehicle_id
        by_vehicle[v] = by_vehicle.get(v, 0.0) + info
    F = np.zeros((n_e + n_c, n_e + n_c))
    keep = np.r_[np.arange(n_e), n_e + 1 + np.arange(n_c)]
    for info in by_vehicle.values():  # the vehicle's load, integrated out with its prior
        w = info[:, n_e]
        reduced = info - np.outer(w, w) / (info[n_e, n_e] + 1.0 / weight_rel_sd**2)
        F += reduced[np.ix_(keep, keep)]
    prec = np.zeros(0) if common_sd is None else 1.0 / np.asarray(common_sd, dtype=float) ** 2
    return Information(F[:n_e, :n_e], len(sens), len(by_vehicle), F[:n_e, n_e:], F[n_e:, n_e:], prec)


@dataclasses.dataclass(frozen=True)
class LargestError:
    """What an estimator at the information bound makes of a bridge whose truth the prior does not
    pull on: per-element error sd, the Bayesian (posterior) sd beside it, and the distribution of
    the largest |element error| over the span — all in points (100 × log EI ≈ % of EI)."""

    element_sd_pts: np.ndarray
    bayes_sd_pts: np.ndarray
    bound_pts: float
    median_pts: float
    p90_pts: float
    p_within: float
    draws: int


def efficient_error_covariance(F: np.ndarray, prior_precision: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A·F·A, A) with A = (F + Q)⁻¹: the frequentist error covariance of the posterior mean of a
    linear-Gaussian model with information ``F`` and prior precision ``Q`` — over noise draws at a
    fixed truth — and its posterior covariance. A·F·A = A − A·Q·A ≤ A."""
    A = np.linalg.inv(F + prior_precision)
    A = 0.5 * (A + A.T)
    C = A @ F @ A
    return 0.5 * (C + C.T), A


def largest_error(F: np.ndarray | Information, prior_precision: np.ndarray, bound_pts: float,
                  draws: int = 20000, rng: np.random.Generator | None = None) -> LargestError:
    """The largest element error of an efficient estimator with the prior ``prior_precision`` (Q),
    given the elements' information ``F`` (an :class:`Information`: its :meth:`~Information.marginal`),
    by Monte Carlo (``draws`` draws of the error vector from A·F·A; ``bound_pts``: a required
    bound, e.g. ±3 points, for P(every element within it)).

    Why A·F·A and not the Bayesian sd (diag A, :meth:`Information.element_sd` with a prior): the
    error of the posterior mean θ̂ = A(F·θ + s) (s ~ N(0, F), the score) at a fixed truth θ is
    −A·Q·(θ − μ) + A·s. Where the prior's pull Q(θ − μ) vanishes — a healthy bridge, exactly at the
    design (θ = μ = 0) or uniform (the GMRF's smoothness is exact there; only the weak level prior
    pulls) — there is no bias and the error covariance is A·F·A, smaller than A: the posterior sd
    also covers truths the prior deems possible (rough fields), which a healthy bridge is not. So
    for "every element within ±b on a healthy bridge" the yardstick is A·F·A. Linear in log EI: at
    3 points the ratio error e^δ − 1 differs from δ by 1.5 % of itself."""
    Fm = F.marginal() if isinstance(F, Information) else np.asarray(F, dtype=float)
    if bound_pts <= 0.0 or draws < 1:
        raise ValueError(f"largest_error: bound_pts {bound_pts} and draws {draws} must be positive")
    C, A = efficient_error_covariance(Fm, np.asarray(prior_precision, dtype=float))
    # eigen-factor, not Cholesky: A·F·A may be singular where F is (an element the data never see)
    w, V = np.linalg.eigh(C)
    L = V * np.sqrt(np.clip(w, 0.0, None))
    rng = np.random.default_rng(0) if rng is None else rng
    worst = 100.0 * np.abs(L @ rng.standard_normal((C.shape[0], draws))).max(axis=0)
    return LargestError(100.0 * np.sqrt(np.diag(C)), 100.0 * np.sqrt(np.diag(A)), float(bound_pts),
                        float(np.median(worst)), float(np.quantile(worst, 0.9)), float(np.mean(worst <= bound_pts)),
                        int(draws))
