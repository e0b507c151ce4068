"""The second simulation world (simfleet.worlds) is right: its physics against closed forms and against
the project's independent discretisations, its sensor chain against its design, its output against
the drive-log contract."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shared.drivelog import list_drive_logs, read_drive_log
from shared.fe.beam import Beam, crack_ei_factor, natural_frequencies
from shared.registry import load_site
from shared.vehicles import vehicle_from_params
from simfleet.scenarios import SCENARIOS, TABLE_4_1, fleet_class
from simfleet.worlds.ivp import WorldSettings, generate
from simfleet.worlds.logger import ATTENUATION_DB, AntiAlias, integrated_chainage
from simfleet.worlds.modal_beam import ModalBeamSpec, modal_beam
from simfleet.worlds.ode import Drive, integrate, position, speed
from simfleet.worlds.vehicles import vehicle_eom

L, EI, MU = 20.0, 35e9 * 1.25, 37500.0


def _spec(**kw) -> ModalBeamSpec:
    return ModalBeamSpec(span_m=L, EI_nm2=EI, mass_per_m=MU, damping_ratio=0.03, **kw)


def test_quarter_car_on_a_sine_road_matches_the_steady_state_response():
    p = dict(TABLE_4_1["mean"])
    eom = vehicle_eom("quarter_car", p)
    v, wavelength, amp = 20.0, 5.0, 1e-3
    x = np.arange(-200.0, 400.0, 0.01)
    drive = Drive(amp * np.sin(2 * np.pi * x / wavelength), -200.0, 0.01, -150.0, v, 0.0, 10.0, 0.0)
    tr = integrate(eom, drive, 12.0, 5e-5)
    w = 2 * np.pi * v / wavelength
    # Steady state of M q̈ + C q̇ + K q = G kc y with y = amp·sin(w t + φ0): a complex amplitude.
    Q = np.linalg.solve(-w**2 * eom.M + 1j * w * eom.C + eom.K, eom.G @ (eom.kc * amp))
    phase = 2 * np.pi * position(drive, tr.t) / wavelength
    body_acc = np.imag(-w**2 * Q[0] * np.exp(1j * phase))
    late = tr.t > 8.0  # the body mode (ζ ≈ 0.2, 10.6 rad/s) has decayed by e^-17 by then
    scale = np.abs(w**2 * Q[0])
    # The 1 cm linear interpolation of the sine errs by (k·dx)²/8 ≈ 2e-5 of its amplitude; RK4 at
    # 50 µs on a 25 rad/s forcing by (ωh)⁴ ≈ 1e-12: 1e-4 holds both with margin.
    assert np.max(np.abs(tr.qddot[late, 0] - body_acc[late])) < 1e-4 * scale


def test_equations_of_motion_agree_with_the_shared_vehicle_models():
    """Two independent derivations (free-body diagrams here, the project's vehicle models) agree."""
    rng = np.random.default_rng(3)
    for sc in (SCENARIOS["road-qc"], SCENARIOS["road-hc"]):
        mean, std = fleet_class(sc)
        p = {k: mean[k] + std[k] * rng.standard_normal() for k in mean}
        mine = vehicle_eom(sc.vehicle_model, p)
        theirs = vehicle_from_params(sc.vehicle_model, p).system()
        for name in ("M", "C", "K", "G", "kc", "offsets_m"):
            np.testing.assert_allclose(getattr(mine, name), getattr(theirs, name), rtol=1e-12, err_msg=name)
        np.testing.assert_allclose(mine.static_loads_n, theirs.static_contact_forces(), rtol=1e-9)
        assert [c[:3] for c in mine.channels] == [(c.name, c.dof, c.kind) for c in theirs.channels]


def test_modal_beam_static_deflection_and_frequencies_match_closed_forms():
    beam = modal_beam(_spec())
    P = -1e5
    # The sine series of a midspan point load converges like Σ 1/j⁴: 40 terms leave ~5e-6.
    assert beam.static_deflection(P, L / 2, np.array([L / 2]))[0] == pytest.approx(P * L**3 / (48 * EI), rel=1e-5)
    # The sines are the exact modes of a uniform pinned beam: f_n = n²π/(2L²)·√(EI/μ) to rounding.
    exact = np.arange(1, 6) ** 2 * np.pi / (2 * L**2) * np.sqrt(EI / MU)
    np.testing.assert_allclose(beam.frequencies_hz[:5], exact, rtol=1e-9)
    # A uniform loss scales every frequency by √(1 − loss).
    lossy = modal_beam(_spec(global_loss=0.10))
    np.testing.assert_allclose(lossy.frequencies_hz[:5], exact * np.sqrt(0.9), rtol=1e-9)
    # Nearly clamped bearings: the fixed–fixed first frequency 22.373/(2πL²)·√(EI/μ), within the
    # bearings' remaining flexibility (Krot·L/EI ≈ 460: ~1 % softer than fully fixed).
    stiff = modal_beam(_spec(krot_nm_per_rad=1e12))
    fixed = 22.373 / (2 * np.pi * L**2) * np.sqrt(EI / MU)
    assert 0.98 * fixed < stiff.frequencies_hz[0] < fixed


@pytest.mark.parametrize("krot, crack", [(None, 10.0), (1e9, None), (1e10, 14.0)])
def test_modal_beam_agrees_with_a_fine_fe_beam(krot, crack):
    """Cracks and bearings: the Ritz model against the project's Hermite FE beam on 400 elements with
    the crack's exact element average — two discretisations of one continuum, each converged to
    ~1e-5 in the lowest frequencies, so 1e-4 separates a modelling error from discretisation."""
    ne = 400
    factor = crack_ei_factor(ne, L, 1.0, crack, 0.10, averaging="exact") if crack is not None else None
    fe = Beam(span_m=L, n_elements=ne, E_pa=35e9, I_m4=1.25, mass_per_m=MU, damping_ratio=0.03,
              supports="simply_supported" if krot is None else "rotational_springs",
              krot_nm_per_rad=None if krot is None else (krot, krot), ei_factor=factor, depth_m=1.0)
    ritz = modal_beam(_spec(krot_nm_per_rad=krot, crack_x_m=crack, crack_phi=0.10 if crack is not None else 0.0))
    np.testing.assert_allclose(ritz.frequencies_hz[:3], natural_frequencies(fe, 3), rtol=1e-4)


def test_element_ratio_is_the_mean_stiffness_over_each_element():
    spec = _spec(crack_x_m=10.0, crack_phi=0.10, global_loss=0.05)
    ratio = spec.element_ratio(20)
    np.testing.assert_allclose(ratio, 0.95 * crack_ei_factor(20, L, 1.0, 10.0, 0.10, averaging="exact"), rtol=1e-9)


def test_moving_load_deflection_is_near_static_at_low_speed():
    """A quarter-car crawling over a smooth span loads it quasi-statically: the midspan deflection as
    the axle crosses midspan is the static one under the axle's weight (the body's, via the
    suspension) within the dynamic amplification of a 2 m/s crossing (a few 0.1 %)."""
    beam = modal_beam(_spec())
    p = dict(TABLE_4_1["mean"])
    eom = vehicle_eom("quarter_car", p)
    x = np.arange(-50.0, 100.0, 0.01)
    v = 2.0
    drive = Drive(np.zeros_like(x), -50.0, 0.01, -10.0, v, 0.0, 10.0, 0.0)
    tr = integrate(eom, drive, 20.0 / v, 2e-4, beam, bridge_start_m=0.0)
    k = int(np.argmin(np.abs(tr.x_cg - L / 2)))
    mid = beam.modes_at(np.array([L / 2]))[0] @ tr.eta[k]
    static = beam.static_deflection(-eom.static_loads_n[0], L / 2, np.array([L / 2]))[0]
    # 12 kept modes reproduce the point-load deflection to ~1e-4 (modes fall as 1/n⁴); a 10 s
    # crossing of a 4.2 Hz span amplifies by ~(v/(2 f1 L))² ≈ 1e-4 plus the body's slow bounce.
    assert mid == pytest.approx(static, rel=5e-3)


def test_anti_alias_passes_the_band_and_rejects_aliases():
    fs, R = 500.0, 40
    aa = AntiAlias(fs, R)
    t = np.arange(200_000) / (fs * R)
    ripple = 10 ** (-ATTENUATION_DB / 20)  # the Kaiser design's pass-band ripple and stop-band gain

    def gain(f):
        y = aa.sample(np.sin(2 * np.pi * f * t), 3)
        ts = t[3::R]
        mid = slice(len(ts) // 4, 3 * len(ts) // 4)  # away from the ends the filter sees zeros past
        return np.max(np.abs(y[mid] - np.sin(2 * np.pi * f * ts[mid]))), np.max(np.abs(y[mid]))

    for f in (1.0, 20.0, 80.0, 140.0):  # the pass band (≤ 0.3 fs), time-aligned: delay compensated
        err, _ = gain(f)
        assert err < 1.5 * ripple, f  # ripple plus the window's rounding
    for f in (260.0, 300.0, 450.0, 700.0):  # would alias into 0–240 Hz
        _, amp = gain(f)
        assert amp < 1.5 * ripple, f
    two = aa.sample(np.stack([np.sin(2 * np.pi * 5 * t), np.cos(2 * np.pi * 5 * t)], axis=1), 0)
    np.testing.assert_array_equal(two[:, 0], aa.sample(np.sin(2 * np.pi * 5 * t), 0))


def test_chainage_integrates_the_reported_speed():
    dt = 0.002
    v = np.full(1001, 20.0) * 1.01
    x = integrated_chainage(5.0, v, dt)
    assert x[0] == 5.0 and x[-1] == pytest.approx(5.0 + 1000 * dt * 20.2, rel=1e-12)
    drive = Drive(np.zeros(3), 0.0, 1.0, -40.0, 20.0, 0.02, 8.0, 1.0)
    t = np.linspace(0.0, 10.0, 100_001)
    np.testing.assert_allclose(np.gradient(position(drive, t), t)[1:-1], speed(drive, t)[1:-1], rtol=1e-7)


def test_generated_logs_keep_the_contract_and_start_in_motion(tmp_path):
    sc = SCENARIOS["road-hc"]
    truth = generate(sc, tmp_path, seed=2, passes=2, workers=1, progress=False,
                     settings=WorldSettings(speed_error_sd=0.02))
    site = load_site(tmp_path / "site.toml")
    assert site.vehicle_class("half_car").mean == fleet_class(sc)[0]
    assert json.loads((tmp_path / "truth.json").read_text()) == json.loads(json.dumps(truth))
    paths = list_drive_logs(tmp_path / "logs")
    assert len(paths) == 2
    mean = fleet_class(sc)[0]
    for path, rec in zip(paths, truth["passes"]):
        log = read_drive_log(path)
        assert log.meta.pass_id == rec["pass_id"] and set(log.channels) == {"body_acc", "body_pitch_rate"}
        assert len(log) == rec["n_samples"]
        params = truth["vehicles"][log.meta.vehicle_id]
        assert params["D1"] != mean["D1"] and params["ms"] != mean["ms"]  # drawn from the prior, not its mean
        assert rec["run_in_m"] >= 40.0 and 0.0 <= log.chainage[0] < 0.05  # logging starts mid-motion, at 0
        # The chainage follows the odometer: the end error is the scale error times the distance
        # (to the wobble's mean over a pass, which the odometer stretches too).
        travelled = log.chainage[-1] - log.chainage[0]
        assert rec["chainage_error_at_end_m"] == pytest.approx(rec["speed_scale_error"] * travelled, rel=0.05)
        acc = np.asarray(log.channels["body_acc"], float)
        assert np.std(acc[:50]) > 0.1 * np.std(acc)  # moving on a rough road from the first sample
