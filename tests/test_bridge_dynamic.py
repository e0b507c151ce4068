"""The bridge's dynamics in the pass model: the moving-force model against the coupled
vehicle–bridge simulation, and the bias it removes from the quasi-static model."""

from __future__ import annotations

import dataclasses

import numpy as np

from cloud.bridge.dynamic import fit_elements_dynamic
from cloud.bridge.likelihood import WeightPrior
from cloud.bridge.passdata import EdgeSettings, extract_pass
from cloud.bridge.setup import Setup, whiten_all
from shared.fe.beam import Beam, influence_line, moving_load_deflection
from shared.vbi import simulate_vbi
from shared.vehicles import QuarterCar
from tests.support import drive_logs, edge_messages
from tests.test_bridge_passdata import BRIDGE, QC, edge_pass


def flat(x):
    return np.zeros_like(x)


def test_moving_force_with_the_measured_wheel_load_reproduces_the_coupled_deflection():
    """At 20 m/s the deflection under the wheel is ~5 % off the static −W·J⁰ at mid-span; a moving
    force carrying the wheel's actual load (static + dynamic tyre force) reproduces it."""
    beam = Beam(20.0, 20, 35e9, 1.25, 37500.0)
    car = QuarterCar(**QC)
    s = car.system()
    W = s.static_contact_forces()[0]
    dt, v = 0.0005, 20.0
    r = simulate_vbi(s, flat, flat, -1.0, v, 22.0 / v, dt, beam=beam, bridge_start_m=0.0)
    x = r.x_cg
    on = (x > 0.0) & (x < 20.0)
    d_vbi = r.deflection[:, 0]
    static = -W * influence_line(beam, np.clip(x, 0, 20)) * on
    mid = np.argmin(np.abs(x - 10.0))
    assert 0.02 < abs(d_vbi[mid] / static[mid] - 1) < 0.08
    tyre = s.kc[0] * (d_vbi - r.state.u[:, 1])  # dynamic part of the contact force, N (up on the car)
    d_mf = moving_load_deflection(beam, x, -(W + tyre) * on, dt, gamma=0.8)
    scale = np.max(np.abs(d_vbi))
    assert np.max(np.abs(d_mf - d_vbi)[on]) < 0.01 * scale
    assert np.max(np.abs(static - d_vbi)[on]) > 0.03 * scale


def test_dynamic_model_removes_the_quasi_static_bias():
    """Noise-free passes of one vehicle (known weight) at 15–22 m/s over the healthy bridge."""
    setup = Setup.of(BRIDGE)
    edge = EdgeSettings()
    pds = []
    for i, v in enumerate(np.linspace(15.0, 22.0, 6)):
        segs, _, _ = edge_pass(float(v))
        p = extract_pass(segs, setup.window, "quarter_car", QC, edge=edge)
        pds.append(dataclasses.replace(p, vehicle_id=f"v{i}", pass_id=f"p{i}"))
    W = float(QuarterCar(**QC).system().static_contact_forces()[0])
    fit = fit_elements_dynamic(whiten_all(pds, setup), setup, WeightPrior(W, 1.0))
    qs, dyn = fit.history[0], fit.posterior
    assert abs(dyn.effective_ratio - 1.0) < 0.01, dyn.effective_ratio
    assert abs(dyn.effective_ratio - 1.0) < abs(qs.effective_ratio - 1.0)
    assert np.max(np.abs(dyn.stiffness_ratio - 1.0)) < np.max(np.abs(qs.stiffness_ratio - 1.0))
    assert dyn.chi2_per_point < 0.6 * qs.chi2_per_point


def test_uncalibrated_vehicles_give_no_false_alarm_and_a_band_that_knows_it(tmp_path):
    """8 passes of a healthy bridge computed with the class-mean parameters (no calibration; the
    true vehicles differ by ~10 % per quantity), the calibration error carried at the class prior's
    width: no alarm, and the effective stiffness's 95 % band covers the truth."""
    from cloud.bridge.estimator import BridgeEstimator, BridgeSettings, class_weight_prior
    from cloud.bridge.passdata import group_segments
    from cloud.bridge.vehicle_error import class_log_sd
    from shared.registry import load_site
    from shared.schema import decode_ap
    from simfleet import sim
    from simfleet.scenarios import SCENARIOS

    sim.generate(SCENARIOS["bridge-healthy"], tmp_path, seed=5, passes=8, nominal="class", workers=1, progress=False)
    site = load_site(tmp_path / "site.toml")
    logs = drive_logs(tmp_path)
    segments = [seg for key, payload in edge_messages(site, logs, "net") if "/ap/" in key for seg in decode_ap(payload)]
    used = {log.meta.vehicle_id: dict(log.meta.nominal_params) for log in logs}
    assert all(u == dict(site.vehicle_class("quarter_car").mean) for u in used.values())
    est = BridgeEstimator(site.bridges[0], class_weight_prior(site, "quarter_car"), BridgeSettings())
    sd = class_log_sd(site, "quarter_car")
    for (vid, _), segs in group_segments(segments).items():
        assert est.add_segments(segs, "quarter_car", used[vid], sd)
    e = est.estimate()
    assert not e.assessment.alarm, e.assessment.probabilities
    p = e.posterior
    assert abs(p.effective_ratio - 1.0) < 1.96 * p.effective_ratio_sd, (p.effective_ratio, p.effective_ratio_sd)


def test_excess_sensitivities_match_finite_differences():
    """∂ε_p/∂θ_z by forward mode through the Newmark solve (Rayleigh damping moving with K and its
    anchor frequencies) against central differences of the excess itself, on a non-uniform beam."""
    from cloud.bridge.excess import dynamic_excess, excess_sensitivity
    from cloud.bridge.passdata import PassData, Window
    from shared.fe.design import design_beam

    window = Window.of(BRIDGE)
    lf = 1.0 + 0.08 * np.sin(2 * np.pi * window.x / 7.0) * window.on_span  # a dynamic wheel load
    p = PassData(window, "v", "p", 0, "quarter_car", QC, 18.0, np.zeros(window.n), np.ones(window.n, bool), lf, 1e-5)
    theta = 0.05 * np.random.default_rng(1).standard_normal(BRIDGE.n_elements)
    eps, d = excess_sensitivity(design_beam(BRIDGE, ei_factor=np.exp(theta)), p)
    assert np.allclose(eps, dynamic_excess(design_beam(BRIDGE, ei_factor=np.exp(theta)), p), rtol=0, atol=1e-15)
    h = 1e-4
    for z in (0, 4, 10, 19):
        tp, tm = theta.copy(), theta.copy()
        tp[z] += h
        tm[z] -= h
        fd = (dynamic_excess(design_beam(BRIDGE, ei_factor=np.exp(tp)), p)
              - dynamic_excess(design_beam(BRIDGE, ei_factor=np.exp(tm)), p)) / (2 * h)
        assert np.max(np.abs(fd)) > 0
        # (without the damping's dependence on θ the derivative is 2–3 % off: measured)
        assert np.max(np.abs(d[:, z] - fd)) < 1e-3 * np.max(np.abs(fd)), z


def test_dynamic_sensitivities_read_a_soft_end_better():
    """The end elements barely move the quasi-static deflection; their share of the bridge's
    dynamics (each pass's ∂ε/∂θ_z in the per-element fit) is most of what the passes say about them.
    Coupled simulations (not the moving-force model) of a span whose last four elements are 20 %
    soft, noise-free, six speeds: with the sensitivities the soft end reads closer to the truth than
    with the dynamics fixed at the global level (measured: mean error of the four 13.0 vs 15.6 points)."""
    factor = np.ones(BRIDGE.n_elements)
    factor[-4:] = 0.8
    setup = Setup.of(BRIDGE)
    pds = []
    for i, v in enumerate(np.linspace(15.0, 22.0, 6)):
        segs, _, _ = edge_pass(float(v), ei_factor=tuple(factor))
        p = extract_pass(segs, setup.window, "quarter_car", QC, edge=EdgeSettings())
        pds.append(dataclasses.replace(p, vehicle_id=f"v{i}", pass_id=f"p{i}"))
    W = float(QuarterCar(**QC).system().static_contact_forces()[0])
    wps = whiten_all(pds, setup)
    end = {}
    for sens in (False, True):
        r = fit_elements_dynamic(wps, setup, WeightPrior(W, 1.0), sensitivities=sens).posterior.stiffness_ratio
        end[sens] = abs(float(np.mean(r[-4:] - factor[-4:])))
    assert end[True] < 0.9 * end[False], end
