"""The Cramér–Rao machinery: sensitivities by finite differences of the coupled simulation, and the
Fisher information with the wheel loads marginalised."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.stats import norm

from cloud.bridge.information import (FD_STEP, PassCase, PassSensitivity, crack_jacobian, efficient_error_covariance,
                                      fleet_information, largest_error, noise_sd_of, pass_sensitivity)
from cloud.bridge.stiffness import StiffnessPrior
from shared.fe.beam import Beam, crack_ei_factor
from shared.vbi import simulate_vbi
from shared.vehicles import QuarterCar

QC = dict(M=4450.0, m=420.0, K=5.0e5, k=1.95e6, c=2.0e4)
BEAM = Beam(20.0, 4, 35e9, 1.25, 37500.0)  # coarse: the test is about the bookkeeping


def _channel(beam, params, speed=18.0):
    flat = lambda x: np.zeros_like(np.asarray(x, dtype=float))  # noqa: E731
    s = QuarterCar(**params).system()
    return simulate_vbi(s, flat, flat, 0.0, speed, 50.0 / speed, 1 / 500.0, beam=beam, bridge_start_m=5.0,
                        gamma=0.5).channels[:, 0]


def test_element_sensitivities_add_up_to_the_global_one_and_the_load_is_a_scale():
    case = PassCase("v1", "quarter_car", QC, 18.0, 1e-3)
    s = pass_sensitivity(case, BEAM)
    g = 2 * FD_STEP  # the response is far from linear over 1 % (the phase of the vibration moves)
    stiff = _channel(dataclasses.replace(BEAM, ei_factor=np.full(4, math.exp(g))), QC)
    base = _channel(BEAM, QC)
    direct = (stiff - base) / g / case.noise_sd
    summed = s.S.sum(axis=1)
    assert np.linalg.norm(summed - direct) < 0.02 * np.linalg.norm(direct)
    # Heavier vehicle, same dynamics: the bridge part of the response scales with the load.
    heavy = {k: v * 1.01 for k, v in QC.items()}
    diff = (_channel(BEAM, heavy) - base) / math.log(1.01) / case.noise_sd
    assert np.linalg.norm(diff - s.s_w) < 0.02 * np.linalg.norm(s.s_w)
    assert FD_STEP < 0.01


def test_marginalising_the_loads_costs_information_and_the_prior_bounds_the_cost():
    rng = np.random.default_rng(0)
    n, ne = 200, 4
    sens = []
    for p in range(6):
        S = rng.standard_normal((n, ne))
        s_w = S.sum(axis=1) * -1.0 + 0.3 * rng.standard_normal(n)  # load and stiffness nearly confounded
        sens.append(PassSensitivity(PassCase(f"v{p % 3}", "quarter_car", QC, 18.0, 1.0), S, s_w))
    known = fleet_information(sens, 1e-9).F  # loads known: no loss
    free = fleet_information(sens, 1e9).F  # loads unknown
    mid = fleet_information(sens, 0.09).F
    raw = sum(s.S.T @ s.S for s in sens)
    assert np.allclose(known, raw, rtol=1e-6)
    one = np.ones(ne)
    assert one @ free @ one < one @ mid @ one < one @ known @ one
    info = fleet_information(sens, 0.09)
    assert math.isclose(info.scaled(12).global_sd(), info.global_sd() / math.sqrt(2), rel_tol=1e-9)


def test_crack_jacobian_matches_the_crack_factor():
    T = crack_jacobian(20, 20.0, 1.0, 10.0, 0.1)
    assert np.allclose(T[:, 2], 1.0)
    th = lambda x, p: np.log(crack_ei_factor(20, 20.0, 1.0, x, p))  # noqa: E731
    d = th(10.0, 0.101) - th(10.0, 0.1)
    assert np.allclose(T[:, 1] * 0.001, d, atol=2e-4)
    assert np.count_nonzero(np.abs(T[:, 1]) > 1e-6) == 4  # ±1.5 depths around a node: four elements


def test_noise_sd_is_the_percentage_of_the_clean_signal():
    rng = np.random.default_rng(1)
    clean = np.sin(np.linspace(0, 60, 20000))
    noisy = clean + 0.02 * np.std(clean) * rng.standard_normal(clean.size)
    assert math.isclose(noise_sd_of(noisy, 2.0), 0.02 * np.std(clean), rel_tol=0.01)


def test_calibration_errors_are_marginalised_as_in_the_joint_information():
    """The common and per-pass calibration nuisances (with their priors) against the brute-force
    joint Fisher information over (θ, every vehicle's load, the common δ, every pass's own δ)."""
    names = ["c/M", "k/M"]
    road = lambda x: 0.009 * np.clip((x + 12.0) / 3.0, 0.0, 1.0) + 2e-3 * np.sin(0.7 * x)  # noqa: E731 (a ramp)
    other = dict(QC, c=QC["c"] * 1.1, M=QC["M"] * 0.95)
    cases = [PassCase("v1", "quarter_car", QC, 16.0, 1e-3, road), PassCase("v1", "quarter_car", QC, 19.0, 1e-3, road),
             PassCase("v2", "quarter_car", other, 21.0, 1e-3, road)]
    sens = [pass_sensitivity(c, BEAM, calibration=names) for c in cases]
    w_rel, common_sd, pass_sd = 0.1, [0.03, 0.02], [0.04, 0.04]
    info = fleet_information(sens, w_rel, common_sd=common_sd, pass_sd=pass_sd, span_m=BEAM.span_m)

    ne, K, P = BEAM.n_elements, len(names), len(sens)
    vehicles = ["v1", "v2"]
    n_par = ne + len(vehicles) + K + P * K
    mean_u = np.mean([s.u for s in sens], axis=0)
    F = np.zeros((n_par, n_par))
    for i, s in enumerate(sens):
        common, own = s.calibration_columns(mean_u, BEAM.span_m)
        X = np.zeros((s.S.shape[0], n_par))
        X[:, :ne] = s.S
        X[:, ne + vehicles.index(s.case.vehicle_id)] = s.s_w
        X[:, ne + 2 : ne + 2 + K] = common
        X[:, ne + 2 + K + i * K : ne + 2 + K + (i + 1) * K] = own
        F += X.T @ X
    prior = np.r_[np.zeros(ne), np.full(2, 1 / w_rel**2), 1 / np.square(common_sd), np.tile(1 / np.square(pass_sd), P)]
    joint = np.linalg.inv(F + np.diag(prior))[:ne, :ne]
    assert np.allclose(np.linalg.inv(info.marginal()), joint, rtol=1e-6)
    # the nuisances cost information, and the columns are not empty
    bare = fleet_information(sens, w_rel)
    assert info.global_sd() > bare.global_sd()
    assert np.linalg.norm(sens[0].calibration_columns(mean_u, BEAM.span_m)[0]) > 0
    # scaling keeps the joint blocks (the common prior does not scale with passes)
    big = info.scaled(30)
    assert big.global_sd() < info.global_sd() and np.allclose(big.common_precision, info.common_precision)


def _p_all_within(bound, sd):
    """P(every |N(0, sd_i²)| ≤ bound), independent elements: Π(2Φ(b/σ_i) − 1)."""
    return float(np.prod(2.0 * norm.cdf(bound / np.asarray(sd)) - 1.0))


def test_largest_error_matches_the_closed_form_for_independent_elements():
    # Diagonal information and prior: independent errors, sd_i = √F_i / (F_i + q_i) (A·F·A), not
    # the posterior's 1/√(F_i + q_i) — a wrong covariance moves P by far more than the tolerance.
    F = np.diag([4.0e3, 1.0e4, 2.5e4, 6.0e3, 1.5e4, 3.0e3])
    Q = np.diag([2.0e3, 1.0e3, 5.0e3, 0.0, 4.0e3, 1.0e3])
    f, q = np.diag(F), np.diag(Q)
    sd = np.sqrt(f) / (f + q)
    r = largest_error(F, Q, 2.0, draws=200_000, rng=np.random.default_rng(3))
    assert np.allclose(r.element_sd_pts, 100 * sd, rtol=1e-12)
    assert np.allclose(r.bayes_sd_pts, 100 / np.sqrt(f + q), rtol=1e-12)
    exact = _p_all_within(0.02, sd)
    assert 0.2 < exact < 0.8  # a bound where P is informative
    assert abs(r.p_within - exact) < 0.006  # ±5 Monte Carlo sd
    # the Monte Carlo median and 90 % point of the largest error sit at CDF 0.5 and 0.9 of the exact law
    assert abs(_p_all_within(r.median_pts / 100, sd) - 0.5) < 0.006
    assert abs(_p_all_within(r.p90_pts / 100, sd) - 0.9) < 0.004
    assert r.median_pts < r.p90_pts


def test_the_efficient_estimator_at_a_healthy_truth_has_error_covariance_AFA_below_the_posterior():
    """The yardstick's claim checked on the estimator itself: the posterior mean of a linear-Gaussian
    model with the GMRF prior, at the design truth (θ = μ = 0), over noise draws."""
    rng = np.random.default_rng(5)
    n_e = 20
    X = rng.standard_normal((60, n_e)) * np.linspace(0.2, 1.0, n_e) ** 2 * 40.0  # ill-seen ends
    X[:, :3] *= 0.05
    F = X.T @ X
    Q = StiffnessPrior().precision(n_e)
    C, A = efficient_error_covariance(F, Q)
    # A·F·A ≤ A (the difference is A·Q·A, positive semi-definite), and strictly below somewhere
    assert np.linalg.eigvalsh(A - C).min() > -1e-12 * np.abs(A).max()
    assert np.allclose(A - C, A @ Q @ A, atol=1e-12 * np.abs(A).max())
    assert np.min(np.diag(C) / np.diag(A)) < 0.5  # the ill-seen ends: the prior, not the noise
    draws = 40_000
    est = A @ (X.T @ rng.standard_normal((X.shape[0], draws)))  # θ̂ − θ at θ = 0
    assert np.allclose(np.cov(est), C, atol=0.05 * np.sqrt(np.outer(np.diag(C), np.diag(C))).max())
    worst = 100 * np.abs(est).max(axis=0)
    b = float(np.median(worst))
    r = largest_error(F, Q, b, draws=draws, rng=np.random.default_rng(6))
    assert abs(r.p_within - 0.5) < 0.02 and abs(r.median_pts / b - 1) < 0.02
    # the posterior covariance A as the yardstick (information F + Q, no prior: A·(F+Q)·A = A) would
    # have called the bound far harder to meet
    post = largest_error(F + Q, np.zeros_like(Q), b, draws=draws, rng=np.random.default_rng(7))
    assert np.allclose(post.element_sd_pts, 100 * np.sqrt(np.diag(A)))
    assert post.p_within < r.p_within - 0.2
