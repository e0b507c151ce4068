"""Per-pass data over a bridge: transfer functions, the discretisation correction, the vehicle
filter, and the whitened likelihood's building blocks (against exact answers and slow references)."""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import pytest

from cloud.bridge.basis import MU_PRIOR_SD_M
from cloud.bridge.likelihood import Stacked, VehicleStats, WeightPrior, marginal_loglik, marginal_loglik_batch
from cloud.bridge.passdata import (EdgeSettings, VehicleFilter, Window, continuous_transfer, extract_pass,
                                   newmark_transfer)
from cloud.bridge.setup import Setup
from shared.dynamics.forward import simulate_on_profile
from shared.dynamics.inverse import build_inverse, edge_gamma
from shared.registry import Bridge
from shared.schema import SensorChunk
from shared.vbi import simulate_vbi
from shared.vehicles import QuarterCar
from simfleet import sim
from simfleet.scenarios import SCENARIOS

QC = dict(M=4450.0, m=420.0, K=5.0e5, k=1.95e6, c=2.0e4)
BRIDGE = Bridge("B1", "R1", 100.0, 20.0, 20, 35e9, 1.25, 37500.0, 1.0, 0.03, "simply_supported")


@pytest.mark.parametrize("gamma, order", [(0.8, 1), (0.5, 2)])
def test_newmark_transfer_converges_to_the_continuous_one_at_its_order(gamma, order):
    system = QuarterCar(**QC).system()
    f = np.array([0.5, 1.7, 4.0])
    T = continuous_transfer(system, f)[:, 0, 0]
    errs = [np.max(np.abs(newmark_transfer(system, f, dt, gamma)[:, 0, 0] / T - 1)) for dt in (4e-3, 2e-3, 1e-3)]
    rates = [math.log2(errs[i] / errs[i + 1]) for i in range(2)]
    assert all(abs(r - order) < 0.25 for r in rates), (errs, rates)


def test_newmark_transfer_is_the_forward_integrator():
    """The closed-form discrete response equals the integrator's steady-state response to a sine."""
    system = QuarterCar(**QC).system()
    dt, f0 = 0.002, 1.7
    r = simulate_on_profile(system, lambda s: 1e-3 * np.sin(2 * np.pi * f0 * s / 20.0),
                            lambda s: 1e-3 * 2 * np.pi * f0 / 20.0 * np.cos(2 * np.pi * f0 * s / 20.0),
                            0.0, 20.0, 30.0, dt)
    t, acc = r.t, r.channels[:, 0]
    tail = t > 20.0
    A = np.column_stack([np.sin(2 * np.pi * f0 * t[tail]), np.cos(2 * np.pi * f0 * t[tail])])
    c, *_ = np.linalg.lstsq(A, acc[tail], rcond=None)
    H = newmark_transfer(system, np.array([f0]), dt)[0, 0, 0]
    measured = (c[0] + 1j * c[1]) / 1e-3  # a·sin + b·cos = Im((a + i b)·e^{iωt}), input Im(1e-3·e^{iωt})
    assert abs(abs(measured) / abs(H) - 1) < 2e-3
    assert abs(np.angle(measured) - np.angle(H)) < 2e-3


def test_vehicle_filter_kills_offsets_and_slopes_and_gives_unit_load_on_a_flat_road():
    f = VehicleFilter(QuarterCar(**QC).system(), 20.0, 0.05)
    x = np.arange(3000) * 0.05
    out = f.whiten(np.column_stack([np.full(x.size, 3e-3), 1e-4 * x]))
    assert np.max(np.abs(out[:, 0])) < 1e-9  # an offset: nothing at all
    assert np.max(np.abs(out[-500:, 1])) < 1e-3 * np.max(np.abs(out[:, 1]))  # a slope: a decaying start
    lf = f.load_factor(np.zeros(x.size))
    assert np.allclose(lf, 1.0)


@functools.lru_cache(maxsize=None)
def _response(speed: float, seed: int = 1, ei_factor: tuple | None = None):
    """One noise-free coupled pass of the bridge-healthy world: chainage (m), body acceleration (m/s²)
    and the true AP (surface + deflection under the wheel, m) at the edge's 500 Hz."""
    sc = SCENARIOS["bridge-healthy"]
    surface = sim.surfaces(sc, seed)[0][0]
    beam = sim.bridge_beam(sc)
    if ei_factor is not None:
        beam = dataclasses.replace(beam, ei_factor=np.asarray(ei_factor, dtype=float))
    system = QuarterCar(**QC).system()

    def elev(x):
        return surface.at(x) * sim.deck_window(sc, x)

    def slope(x):
        return (elev(x + 1e-3) - elev(x - 1e-3)) / 2e-3

    x0, fs = -sim.RUN_IN_M, 500.0
    resp = simulate_vbi(system, elev, slope, x0, speed, (sc.route_length_m - x0) / speed, 1 / (fs * sim.SUBSTEPS),
                        beam=beam, bridge_start_m=sc.bridge.start_m, gamma=sim.SIM_GAMMA)
    keep = slice(None, None, sim.SUBSTEPS)
    x, z, d = resp.x_cg[keep], resp.channels[keep, 0], resp.deflection[keep, 0]
    idx = np.flatnonzero((x >= 0) & (x <= sc.route_length_m))
    x, z, d = x[idx], z[idx], d[idx]
    return x, z, elev(x) + d


@functools.lru_cache(maxsize=None)
def edge_pass(speed: float, seed: int = 1, gamma: float = edge_gamma("quarter_car"), ei_factor: tuple | None = None,
              noise_pct: float = 0.0, noise_seed: int = 0):
    """One pass of the bridge-healthy world through the real edge pipeline (its inverse at Newmark
    ``gamma``), with truth; ``ei_factor``: the span's per-element EI factors instead; ``noise_pct``:
    white sensor noise (% of the channel's sd, as simfleet's), drawn from ``noise_seed``."""
    from edge.pipeline import EdgeConfig, PassProcessor
    from shared.sensors import add_noise

    x, z, truth = _response(speed, seed, ei_factor)
    if noise_pct:
        z = add_noise(z, noise_pct, np.random.default_rng(noise_seed))
    fs = 500.0
    system = QuarterCar(**QC).system()
    proc = PassProcessor(build_inverse(system, 1 / fs, gamma=gamma), "veh-0001", "p1", "R1", 0,
                         EdgeConfig(), "quarter_car")
    segs = []
    for k, i in enumerate(range(0, x.size, 50)):
        sl = slice(i, min(i + 50, x.size))
        segs += proc.feed(SensorChunk(vehicle_id="veh-0001", pass_id="p1", route_id="R1",
                                      vehicle_model="quarter_car", seq=k, t0=i / fs, sample_rate_hz=fs,
                                      chainage=x[sl], speed=np.full(sl.stop - sl.start, speed),
                                      channels={"body_acc": z[sl].astype(np.float32)}, final=sl.stop >= x.size,
                                      nominal_params=QC, lane_offset_m=None))
    segs += proc.finish()[0]
    return segs, x, truth


@pytest.mark.parametrize("speed", [16.0, 21.0])
def test_correction_removes_the_discretisation_error_on_the_span(speed):
    """An edge inverse at Newmark γ = 0.8 (the thesis's; half-cars keep it) leaves tens of µm of error
    on the span behind the 9 mm ramp onto the smooth deck. Corrected to continuous physics it is gone
    (the simulator integrates with γ = ½ at 2 kHz: physics to well below the deflection)."""
    segs, x, truth = edge_pass(speed, gamma=0.8)
    window = Window.of(BRIDGE)
    errors = {}
    edge = EdgeSettings(gamma=0.8)
    for name, correct in (("raw", False), ("continuous", True)):
        p = extract_pass(segs, window, "quarter_car", QC, edge=edge, correct=correct)
        e = p.ap - np.interp(window.chainage, x, truth)
        near = p.valid & (window.x > -10) & (window.x < 30)
        e = e - np.polyval(np.polyfit(window.x[near], e[near], 2), window.x)  # the drift-control trend
        errors[name] = float(np.std(e[window.on_span]))
    assert errors["continuous"] < 0.25 * errors["raw"], errors
    assert errors["continuous"] < 4e-6, errors  # the deflection is 190 µm


def test_batched_marginal_likelihood_equals_the_newton_integral():
    rng = np.random.default_rng(0)
    nb, nm, V = 5, 2, 4
    stats = []
    for v in range(V):
        n = 60
        P, B, w = rng.standard_normal((n, nb)), rng.standard_normal((n, nm)), rng.standard_normal(n)
        d = 0.1 * rng.standard_normal(n)
        stats.append(VehicleStats(f"v{v}", P.T @ P, P.T @ d, float(d @ d), P.T @ w, P.T @ B, float(d @ w), B.T @ d,
                                  B.T @ w, B.T @ B, float(w @ w), n, 1))
    S = Stacked.of(stats, WeightPrior(2.0, 0.3))
    a = 0.2 * rng.standard_normal(nb)
    batch = marginal_loglik_batch(S, a[None])[0]
    q = 1 / MU_PRIOR_SD_M**2
    mu = np.zeros(nm)
    for _ in range(3):  # quadratic in μ: one Newton step is exact
        T = marginal_loglik(S, a, mu)
        mu = mu - np.linalg.solve(T["Hmm"] - q * np.eye(nm), T["gm"] - q * mu)
    T = marginal_loglik(S, a, mu)
    direct = (T["value"] - 0.5 * q * mu @ mu + 0.5 * nm * math.log(q)
              - 0.5 * np.linalg.slogdet(-(T["Hmm"] - q * np.eye(nm)))[1])
    assert batch == pytest.approx(direct, rel=1e-10, abs=1e-8)
    # and the weight integral itself, by quadrature over W for one vehicle with μ = 0
    S1 = Stacked.of(stats[:1], WeightPrior(2.0, 0.3))
    T1 = marginal_loglik(S1, a, np.zeros(nm), derivatives=False)
    W = np.linspace(-20.0, 20.0, 400001)
    st = stats[0]
    h2 = a @ st.A @ a + 2 * st.e @ a + st.f
    g = a @ st.Pw + st.dw
    logint = (-0.5 * st.ww - W * g - 0.5 * W**2 * h2 - 0.5 * (W - 2.0) ** 2 / 0.09
              - 0.5 * math.log(2 * math.pi * 0.09))
    top = logint.max()
    quad = top + math.log(np.trapezoid(np.exp(logint - top), W))
    assert T1["value"] == pytest.approx(quad, abs=1e-6)


def test_setup_window_and_basis_cover_the_span():
    s = Setup.of(BRIDGE)
    assert s.window.on_span.sum() == 401
    J = s.basis.design @ s.model().a(np.zeros(20))
    from shared.fe.beam import influence_line

    exact = influence_line(s.beam, s.basis.x)
    assert np.max(np.abs(J - exact)) < 2e-4 * exact.max()


def test_calibration_marginal_whitens_the_calibration_error_covariance():
    """(I + CΣCᵀ)^(-1/2) as a rank-K correction: it maps the covariance of noise plus a Gaussian
    calibration error to the identity, and its log-determinant is the covariance's."""
    from cloud.bridge.vehicle_error import CalibrationMarginal

    rng = np.random.default_rng(3)
    C = rng.normal(size=(60, 4)) * np.array([5.0, 1.0, 0.2, 0.0])  # one column without effect
    sd = np.array([0.04, 0.1, 0.3, 0.5])
    cov = np.eye(60) + (C * sd**2) @ C.T
    L = CalibrationMarginal.of(C, sd)
    M = L(np.eye(60))
    assert np.allclose(M @ cov @ M.T, np.eye(60), atol=1e-10)
    assert abs(L.logdet - np.linalg.slogdet(cov)[1]) < 1e-9
    v = rng.normal(size=60)
    assert np.allclose(L(v), M @ v)


def test_calibration_sensitivity_is_the_forward_models_change_with_the_quantity():
    """The load columns' sensitivity to a calibration quantity (model_columns) predicts what the
    forward model with that quantity changed by 1 % does to them (first order: within 3 %), and
    names map to parameters as the calibration's do ('c/M' moves c, not M)."""
    import dataclasses as dc

    from cloud.bridge.whitening import model_columns
    from cloud.bridge.vehicle_error import perturbed_params

    segs, _, _ = edge_pass(21.0)
    setup = Setup.of(BRIDGE)
    p = extract_pass(segs, setup.window, "quarter_car", QC, params_log_sd={"c/M": 0.04, "K/M": 0.04})
    assert perturbed_params(QC, "c/M", math.log(1.03))["c"] == pytest.approx(1.03 * QC["c"])
    assert perturbed_params(QC, "c/M", math.log(1.03))["M"] == QC["M"]
    _, white, (names, sd, D) = model_columns(p, setup.basis)
    assert names == ("K/M", "c/M") and np.allclose(sd, 0.04)
    a = setup.model().a(np.zeros(BRIDGE.n_elements))
    nb = setup.basis.n
    for k, name in enumerate(names):
        moved = dc.replace(p, params=perturbed_params(QC, name, math.log(1.01)))
        _, white_moved, _ = model_columns(dc.replace(moved, params_log_sd=None), setup.basis)
        change = (white_moved[:, :nb] - white[:, :nb]) @ a
        predicted = math.log(1.01) * (D[:, k, :] @ a)
        assert np.linalg.norm(change - predicted) < 0.03 * np.linalg.norm(change), name
        assert np.linalg.norm(change) > 1e-3 * np.linalg.norm(white[:, :nb] @ a)  # not a null effect


def test_the_estimators_wheel_load_factor_holds_none_of_the_passs_own_noise():
    """The load term is W·(1 + φ_p)·J. φ̂ from the pass's own AP (:func:`extract_pass`) carries that
    pass's AP noise into the regressor the same noise is fitted against (errors in variables; measured
    on 300 healthy passes: ~4 nats of spurious free-element gain, removed with the noise-free twins'
    φ). The estimator drives the vehicle over the other passes' consensus road and its own deflection
    instead: two noise draws of one pass must give it the same φ, while their φ̂ differ by their noise
    image; and that φ must be accurate — without the deflection under its own load (0.19 mm) it is off
    by ~1 % of φ's swing at the bridge's ramp (measured 1.0 %), with it 0.3 %."""
    from cloud.bridge.estimator import BridgeEstimator, BridgeSettings
    from cloud.bridge.likelihood import WeightPrior
    from cloud.bridge.whitening import model_columns

    setup = Setup.of(BRIDGE)
    on = setup.window.on_span

    def data(speed, noise_seed, name, noise_pct=2.0):
        segs, _, _ = edge_pass(speed, noise_pct=noise_pct, noise_seed=noise_seed)
        p = extract_pass(segs, setup.window, "quarter_car", QC)
        return dataclasses.replace(p, vehicle_id=name, pass_id=name)

    def rms(d):
        return float(np.sqrt(np.mean(d[on] ** 2)))

    others = [data(v, 10 + i, f"o{i}") for i, v in enumerate((15.5, 17.0, 18.5))]
    twin = data(21.0, 0, "P", noise_pct=0.0)  # the same pass without noise: φ as near the truth as the edge gets
    weight = QuarterCar(**QC).system().static_contact_forces()[0]
    used, own = [], []
    for draw in (1, 2):
        p = data(21.0, draw, "P")
        est = BridgeEstimator(BRIDGE, WeightPrior(weight, 0.05 * weight), BridgeSettings())
        for q in others + [p]:
            est.add(q)
        assert est.estimate() is not None
        used.append(est.passes[("P", "P")].data.load_factor)
        own.append(p.load_factor)
    swing = rms(twin.load_factor - 1.0)
    noise_image = rms(own[0] - own[1]) / math.sqrt(2)
    assert noise_image > 2e-3 * swing, (noise_image, swing)  # φ̂ carries its pass's noise (measured 0.35 %)
    # The estimator's φ none of it, but for rounding: the draws' leave-one-out roads (sum − own AP) differ in
    # their last bits, so the roundings of φ's n-step recursion part ways, by up to ~eps of the load per step.
    assert np.max(np.abs(used[0] - used[1])) < setup.window.n * np.finfo(float).eps
    assert rms(used[0] - twin.load_factor) < 5e-3 * swing, (rms(used[0] - twin.load_factor), swing)

    # Live: when the fleet behind the consensus has grown by a quarter, φ and the load columns follow.
    key = ("P", "P")
    before = est.passes[key].load_at
    for i, v in enumerate((16.2, 19.3)):
        est.add(data(v, 20 + i, f"n{i}"))
    est.estimate()
    entry = est.passes[key]
    assert entry.load_at == 6 and before == 4
    nb = setup.basis.n
    fresh = model_columns(entry.data, setup.basis, "smooth")[1]
    assert np.allclose(entry.columns[1][:, :nb], fresh[:, :nb], rtol=0, atol=1e-12 * np.abs(fresh[:, :nb]).max())
    assert not np.array_equal(entry.data.load_factor, used[1])
