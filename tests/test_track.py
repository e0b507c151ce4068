"""Track on discrete three-layer supports, a bridge span beneath, and the coupled model's AP (§3.2.2–3.2.3)."""

from __future__ import annotations

import numpy as np
import pytest

from shared.dynamics.inverse import InverseStream, build_inverse
from shared.dynamics.train_track import simulate_train_track
from shared.fe.beam import Beam, assemble, static_deflection
from shared.track import (
    BridgeSpan,
    RailIrregularity,
    TrackParams,
    band_to_dense,
    beam_on_elastic_foundation,
    build_track,
    damaged_ei_factor,
    static_rail_deflection,
    stiffness_factors,
)
from shared.vehicles import GRAVITY
from shared.vehicles.carriage import table_3_1

AXLE_LOAD = float(table_3_1().axle_loads_n()[0])  # ≈ 110 kN


def test_params_validated():
    with pytest.raises(ValueError, match="TrackParams.pad_k"):
        TrackParams(pad_k=-1.0)
    with pytest.raises(ValueError, match="elements_per_spacing"):
        TrackParams(elements_per_spacing=0)
    with pytest.raises(ValueError, match="BridgeSpan.start_m"):
        build_track(TrackParams(length_m=30.0), 0, BridgeSpan(10.1, 6.0, 35e9, 0.2, 8000.0))
    with pytest.raises(ValueError, match="BridgeSpan.span_m"):
        build_track(TrackParams(length_m=30.0), 0, BridgeSpan(9.0, 6.1, 35e9, 0.2, 8000.0))


def test_matrices_are_banded_symmetric_positive_definite_with_the_right_mass():
    p = TrackParams(length_m=12.0)
    track = build_track(p, 0, BridgeSpan(3.0, 6.0, 35e9, 0.2, 8000.0))
    assert track.bandwidth <= 12  # independent of the length: DOFs numbered along the track
    K, M = band_to_dense(track.K), band_to_dense(track.M)
    assert np.linalg.eigvalsh(K).min() > 0 and np.linalg.eigvalsh(M).min() > 0
    # Total mass: a unit rigid translation of every vertical DOF (rotations zero).
    r = np.zeros(track.n_dof)
    r[track.rail_w] = r[track.sleeper_dof] = r[track.ballast_dof] = 1.0
    free = assemble(track.bridge_beam).free_dofs  # global beam DOF 2·node (+1 for θ)
    r[track.bridge_dof[free % 2 == 0]] = 1.0
    n_sl, n_el, le = len(track.sleeper_x), track.bridge_beam.n_elements, 0.6
    # Consistent deck mass without the supports' w (eliminated): 156/420 of an end element each side.
    deck_mass = 8000.0 * le * (n_el - 2 + 2 * 156 / 420)
    expected = p.rail_mass_per_m * 12.0 + n_sl * (p.sleeper_mass + p.ballast_mass) + deck_mass
    assert r @ M @ r == pytest.approx(expected, rel=1e-12)


def test_static_deflection_matches_beam_on_elastic_foundation():
    """Uniform supports: the rail under an axle load against the Winkler beam with the three layers
    in series smeared over the sleeper spacing (measured: 0.2 % over a sleeper, 0.4 % between)."""
    p = TrackParams(length_m=60.0, support_sd=0.0)
    track = build_track(p, 0)
    x_eval = np.array([0.0, 0.5, 1.0, 2.0, 3.0])
    boef = beam_on_elastic_foundation(AXLE_LOAD, x_eval, p)
    assert -1.0e-3 < boef[0] < -0.4e-3  # a realistic ~0.65 mm
    for x_load in (30.0, 30.3):  # over a sleeper, midway between two
        w = static_rail_deflection(track, [AXLE_LOAD], [x_load], x_load + x_eval)
        assert w[0] == pytest.approx(boef[0], rel=0.01)
        np.testing.assert_allclose(w, boef, rtol=0, atol=0.01 * abs(boef[0]))


def test_supports_carry_the_load():
    p = TrackParams(length_m=40.0)
    track = build_track(p, 3)
    from scipy.linalg import cho_solve_banded, cholesky_banded

    dofs, values = track.contact_entries(np.array([20.13]))
    f = np.zeros(track.n_dof)
    np.add.at(f, dofs[0], -AXLE_LOAD * values[0])
    u = cho_solve_banded((cholesky_banded(track.K, lower=True), True), f)
    reactions = track.subballast_k * u[track.ballast_dof]  # sub-ballast springs to the ground
    assert reactions.sum() == pytest.approx(-AXLE_LOAD, rel=1e-9)


def test_stiffness_field_statistics():
    rng = np.random.default_rng(7)
    f = stiffness_factors(40000, 0.6, 0.1, 3.0, rng)
    g = np.log(f)
    assert f.mean() == pytest.approx(1.0, abs=0.01)
    assert g.std() == pytest.approx(0.1, rel=0.05)
    lag = 5  # 3 m = one correlation length
    rho = np.corrcoef(g[:-lag], g[lag:])[0, 1]
    assert rho == pytest.approx(np.exp(-1.0), abs=0.03)
    track = build_track(TrackParams(length_m=60.0, support_sd=0.1), 1)
    assert 0.02 < np.std(np.log(track.ballast_k)) < 0.3 and not np.allclose(track.ballast_k, track.ballast_k[0])


def test_damaged_ei_factor():
    f = damaged_ei_factor(20000, 0.1, 0.05, np.random.default_rng(0))
    assert f.mean() == pytest.approx(0.9, rel=0.005)
    assert (f / 0.9).std() == pytest.approx(0.05, rel=0.05)


def test_bridge_deck_carries_the_ballast_forces_like_the_fe_beam():
    """The deck inside the track deflects exactly as shared.fe's beam under the sub-ballast spring
    forces; a 20 % global loss of E·I makes it deflect ~1/0.8 as much."""
    from scipy.linalg import cho_solve_banded, cholesky_banded

    p = TrackParams(length_m=30.0, support_sd=0.0)
    deck = {}
    for loss in (0.0, 0.2):
        span = BridgeSpan(9.0, 10.2, 35e9, 0.2, 8000.0, ei_factor=np.full(17, 1.0 - loss))
        track = build_track(p, 0, span)
        dofs, values = track.contact_entries(np.array([14.1]))
        f = np.zeros(track.n_dof)
        np.add.at(f, dofs[0], -AXLE_LOAD * values[0])
        u = cho_solve_banded((cholesky_banded(track.K, lower=True), True), f)
        on = (track.sleeper_x > 9.0 + 1e-9) & (track.sleeper_x < 19.2 - 1e-9)
        x_deck = track.sleeper_x[on]
        w_deck = track.bridge_deflection(u, x_deck)
        force_on_deck = track.subballast_k[on] * (u[track.ballast_dof[on]] - w_deck)  # up positive on the deck
        beam = Beam(10.2, 17, 35e9, 0.2, 8000.0, ei_factor=np.full(17, 1.0 - loss))
        fe = static_deflection(beam, force_on_deck, x_deck - 9.0, x_deck - 9.0)
        np.testing.assert_allclose(w_deck, fe, rtol=1e-9, atol=1e-12)
        deck[loss] = track.bridge_deflection(u, np.array([14.1]))[0]
        assert deck[loss] < 0
    assert 1.2 < deck[0.2] / deck[0.0] <= 1.25 + 1e-9


def test_irregularity_follows_its_spectrum():
    irr = RailIrregularity(seed=4, min_wavelength_m=2.0, max_wavelength_m=50.0)
    x = np.arange(0.0, 2000.0, 0.1)
    r = irr.elevation(x)
    assert r.std() == pytest.approx(np.sqrt((irr.amplitude**2).sum() / 2), rel=0.1)
    assert 0.5e-3 < r.std() < 5e-3  # German low-disturbance track, 2–50 m: a few mm
    x = np.arange(100.0, 110.0, 1e-3)
    slope = irr.slope(x)
    np.testing.assert_allclose(np.gradient(irr.elevation(x), x)[1:-1], slope[1:-1], atol=1e-5 * np.abs(slope).max())
    assert RailIrregularity(seed=4, scale=0.0).elevation(x[:10]).max() == 0.0


@pytest.mark.parametrize("stiff", [False, True])
def test_sleeper_spacing_visible_in_the_ap(stiff):
    """On a smooth rail the only spatial excitation is the discrete support: the AP the inverse
    recovers from bogie data (coupled model at Δt/4, inverted at Δt = 2 ms) has its strongest line
    at 1/(sleeper spacing), like the true AP, with the same amplitude (within 15 %; measured +5 %
    default, +9 % stiff). Stiff supports
    (pads, ballast, sub-ballast ~5–10× stiffer) make the modulation larger: measured 12 µm
    peak-to-peak against 2.2 µm for the default track."""
    changes = dict(pad_k=1e9, ballast_k=2e9, subballast_k=1e9) if stiff else {}
    p = TrackParams(length_m=80.0, support_sd=0.0, **changes)
    car = table_3_1()
    dt = 0.002
    response = simulate_train_track(car, build_track(p, 0), None, 25.0, 1.2, dt / 4)
    truth = response.ap[::4, 0]
    ap = InverseStream(build_inverse(car.system(), dt)).update(response.channels[::4])[:, 0]
    x = response.x_cg[::4]
    k0 = len(x) // 4  # past the start-up transient
    dx = car.v * dt
    lines = {}
    for name, s in (("truth", truth[k0:]), ("inverse", ap[k0:])):
        s = s - np.polyval(np.polyfit(x[k0:], s, 2), x[k0:])  # slow drift and the static deflection
        spectrum = np.abs(np.fft.rfft(s * np.hanning(len(s))))
        freq = np.fft.rfftfreq(len(s), dx)
        band = (freq > 0.3) & (freq < 5.0)
        peak = np.argmax(np.where(band, spectrum, 0.0))
        assert abs(freq[peak] - 1.0 / p.sleeper_spacing_m) <= freq[1]  # within one bin
        lines[name] = spectrum[peak]
        if name == "truth":
            p2p = np.ptp(s)
    assert lines["inverse"] == pytest.approx(lines["truth"], rel=0.15)
    assert (p2p > 8e-6) if stiff else (1e-6 < p2p < 5e-6)


def test_coupled_model_is_quasi_static_at_walking_pace_over_a_bridge():
    """At 5 m/s the track's inertia hardly matters: the rail deflection under each wheel equals the
    static deflection of track and bridge under the simulated contact forces (measured ≤ 0.08 %),
    and on the deck it is about twice that off the bridge (the deck's own deflection)."""
    p = TrackParams(length_m=60.0)
    scatter = damaged_ei_factor(17, 0.0, 0.05, np.random.default_rng(0))
    span = BridgeSpan(24.0, 10.2, 35e9, 0.2, 8000.0, ei_factor=scatter)
    track = build_track(p, 0, span)
    car = table_3_1(v=5.0)
    response = simulate_train_track(car, track, None, 15.0, 4.0, 0.002, probe_x_m=[29.1])
    for k in np.linspace(0, len(response.t) - 1, 9).astype(int):
        xw = response.x_cg[k] + car.wheel_offsets_m()
        static = static_rail_deflection(track, response.contact_force_n[k], xw, xw)
        np.testing.assert_allclose(response.rail_deflection[k], static, rtol=0, atol=5e-3 * np.abs(static).max())
    total = GRAVITY * (car.mv + 2 * car.mb + 4 * car.mw)
    assert response.contact_force_n.sum(axis=1) == pytest.approx(np.full(len(response.t), total), rel=0.01)
    x1 = response.x_cg + car.wheel_offsets_m()[0]
    on_deck = response.rail_deflection[np.argmin(np.abs(x1 - 29.1)), 0]
    off_deck = response.rail_deflection[np.argmin(np.abs(x1 - 43.0)), 0]
    assert on_deck < 1.5 * off_deck < 0  # deflections are negative (down)
    assert response.probes[:, 0].min() == pytest.approx(on_deck, rel=0.05)
