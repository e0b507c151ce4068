"""4-axle carriage (shared.vehicles.carriage) and its inverse on train–track data (thesis §3.2–3.3, App. A–B)."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from shared.dynamics.inverse import InverseStream, build_inverse
from shared.dynamics.train_track import simulate_train_track
from shared.track import RailIrregularity, TrackParams, build_track
from shared.vehicles import GRAVITY, MODELS, BogieHalfCar, Carriage, vehicle_from_params
from shared.vehicles.carriage import TABLE_3_1, table_3_1

DT = 0.002  # 500 Hz, the loggers' rate
X0 = 20.0  # body chainage at the first sample, m (wheel 4 is 10.8 m behind)
DURATION = 1.6  # s: 53 m at 33 m/s
FINE = 8  # the finer-step reference runs at DT / FINE


@functools.lru_cache(maxsize=None)
def track():
    return build_track(TrackParams(length_m=100.0), rng=0)


IRREGULARITY = RailIrregularity(seed=1)


@functools.lru_cache(maxsize=None)
def run(dt: float, gamma: float = 0.6):
    return simulate_train_track(table_3_1(), track(), IRREGULARITY.elevation, X0, DURATION, dt, gamma=gamma)


def relative_after_shift(estimate, truth, norm="max"):
    """Error with its mean removed (the unknown constant), relative to the AP's variation, per wheel."""
    err = estimate - truth
    err = err - err.mean(axis=0)
    spread = truth - truth.mean(axis=0)
    if norm == "max":
        return np.abs(err).max(axis=0) / np.abs(spread).max(axis=0)
    return np.sqrt((err**2).mean(axis=0)) / spread.std(axis=0)


# ---------------------------------------------------------------------------------------------
# The model


def test_registered_and_validated():
    car = vehicle_from_params("carriage", TABLE_3_1)
    assert isinstance(car, Carriage) and MODELS["carriage"] is Carriage
    assert car.params() == TABLE_3_1
    with pytest.raises(ValueError, match="carriage.kp"):
        table_3_1(kp=-1.0)
    with pytest.raises(ValueError, match="missing"):
        vehicle_from_params("carriage", {k: v for k, v in TABLE_3_1.items() if k != "Lv"})
    assert table_3_1(cp=0.0).cp == 0.0  # dampers may be zero


def test_matrices_match_eq_3_6_to_3_8():
    """Our DOF order (u_v, θ_v, u_b1, θ_b1, u_b2, θ_b2) against the thesis's
    (u_v, u_b1, u_b2, θ_v, θ_b1, θ_b2)."""
    car = table_3_1()
    s = car.system()
    Lv, Lb, kp, ks, cp, cs = car.Lv, car.Lb, car.kp, car.ks, car.cp, car.cs

    def thesis(ks1, ks2, kp1, kp2, kp3, kp4):  # eq. (3.7) with Lv1 = Lv2 = Lv, Lb.. = Lb
        return np.array([
            [ks1 + ks2, -ks1, -ks2, Lv * ks1 - Lv * ks2, 0, 0],
            [-ks1, kp1 + kp2 + ks1, 0, -Lv * ks1, Lb * kp1 - Lb * kp2, 0],
            [-ks2, 0, kp3 + kp4 + ks2, Lv * ks2, 0, Lb * kp3 - Lb * kp4],
            [Lv * ks1 - Lv * ks2, -Lv * ks1, Lv * ks2, Lv**2 * ks1 + Lv**2 * ks2, 0, 0],
            [0, Lb * kp1 - Lb * kp2, 0, 0, Lb**2 * kp1 + Lb**2 * kp2, 0],
            [0, 0, Lb * kp3 - Lb * kp4, 0, 0, Lb**2 * kp3 + Lb**2 * kp4],
        ])

    order = [0, 3, 1, 4, 2, 5]  # thesis index of each of our DOFs
    P = np.eye(6)[order]
    for ours, theirs in ((s.K, thesis(ks, ks, kp, kp, kp, kp)), (s.C, thesis(cs, cs, cp, cp, cp, cp))):
        np.testing.assert_allclose(ours, P @ theirs @ P.T, rtol=1e-14, atol=1e-14 * np.abs(theirs).max())
    np.testing.assert_allclose(s.M, np.diag([car.mv, car.Iv, car.mb, car.Ib, car.mb, car.Ib]))
    # Eq. (3.5): the profile forces G (kc·r + cc·r') on bogie 1 bounce and pitch.
    r = np.array([1.0, 2.0, 3.0, 4.0])
    f = s.G @ (s.kc * r)
    assert f[2] == pytest.approx(kp * (r[0] + r[1]))
    assert f[3] == pytest.approx(Lb * kp * r[0] - Lb * kp * r[1])
    assert f[0] == f[1] == 0.0
    assert [ch.name for ch in s.channels] == ["bogie1_acc", "bogie1_pitch_rate", "bogie2_acc", "bogie2_pitch_rate"]
    np.testing.assert_allclose(s.offsets_m, [Lv + Lb, Lv - Lb, -Lv + Lb, -Lv - Lb])


def test_full_model_reduces_to_the_six_dof_system():
    """Holding the wheelsets at y, the 10-DOF rows of body and bogies are the 6-DOF system driven by y."""
    car = table_3_1(mv=30e3)
    s, f = car.system(), car.full_matrices()
    np.testing.assert_allclose(f.K[:6, :6], s.K)
    np.testing.assert_allclose(f.K[:6, 6:], -s.G * s.kc)
    np.testing.assert_allclose(f.C[:6, 6:], -s.G * s.cc)
    np.testing.assert_allclose(f.K, f.K.T)
    np.testing.assert_allclose(f.C, f.C.T)
    # Static wheel loads carry the whole carriage; equal here (symmetric carriage).
    total = GRAVITY * (car.mv + 2 * car.mb + 4 * car.mw)
    assert f.static_wheel_loads_n.sum() == pytest.approx(total, rel=1e-12)
    np.testing.assert_allclose(f.static_wheel_loads_n, total / 4, rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# Forward → inverse


def test_round_trip_same_step_recovers_each_wheel():
    """Noise-free, same Δt and Newmark constants: the inverse (started at rest, as a logger is)
    recovers the AP under every wheel up to a constant (measured ≤ 1.2e-12 relative)."""
    response = run(DT)
    assert np.abs(response.q[:, 6:] - response.ap).max() < 1e-12  # the wheels follow the rail
    assert np.ptp(response.rail_deflection) > 2e-4 and np.ptp(response.irregularity) > 2e-3
    model = build_inverse(table_3_1().system(), DT, gamma=0.6, contact_rule="newmark")
    ap = InverseStream(model).update(response.channels)
    assert np.all(relative_after_shift(ap, response.ap) <= 1e-6)
    exact_start = InverseStream(model, response.initial_inverse_state()).update(response.channels)
    assert np.abs(exact_start - response.ap).max() <= 1e-6 * np.abs(response.ap).max()


#: Relative RMS error after the constant shift of the project's default inverse (γ = 0.8,
#: trapezoidal contact rule, Δt = 2 ms) on data from the coupled model run 8× finer:
#: measured 0.0112 (wheels 1, 3) and 0.0094 (wheels 2, 4); bound ≈ measured × 1.4.
FINER_STEP_BOUND = 0.016


def test_inverse_on_finer_step_data():
    """No inverse crime: the coupled model at Δt/8, sampled at Δt, inverted by the default inverse.
    The error is the inverse's own first-order discretisation error: it halves with Δt."""
    response = run(DT / FINE)
    errors = []
    for every in (FINE, FINE // 2):  # Δt = 2 ms and 1 ms
        ap = InverseStream(build_inverse(table_3_1().system(), DT * every / FINE)).update(response.channels[::every])
        errors.append(relative_after_shift(ap, response.ap[::every], norm="rms"))
    assert np.all(errors[0] < FINER_STEP_BOUND), errors[0]
    np.testing.assert_allclose(errors[0] / errors[1], 2.0, rtol=0.15)  # first order in Δt


#: The 2-DOF bogie half-car of App. A.3 (Table A.3 values) on bogie 1's and bogie 2's channels:
#: it leaves out the body's secondary-suspension force, so its AP is biased by that force over
#: 2·kp (mostly low-frequency). Measured relative RMS after the shift: 0.21 (bogie 1), 0.18 (bogie 2).
BOGIE_HALF_CAR_BOUND = 0.28


def test_bogie_half_car_on_carriage_data():
    car = table_3_1()
    bogie = BogieHalfCar(ms=car.mb, Is=car.Ib, K1=car.kp, K2=car.kp, C1=car.cp, C2=car.cp, D1=car.Lb, D2=car.Lb)
    response = run(DT / FINE)
    channels, truth = response.channels[::FINE], response.ap[::FINE]
    for cols in ([0, 1], [2, 3]):  # (acc, pitch rate) of a bogie → AP under its two wheels
        ap = InverseStream(build_inverse(bogie.system(), DT)).update(channels[:, cols])
        error = relative_after_shift(ap, truth[:, cols], norm="rms")
        assert np.all(error < BOGIE_HALF_CAR_BOUND), error
        # Far better than reading the AP as flat: the shape is there.
        assert np.all(np.corrcoef(ap.T, truth[:, cols].T)[[0, 1], [2, 3]] > 0.97)


#: The carriage on a rigid irregular rail solved by scipy's lsim (matrix exponential, exact contact
#: rate), 10× finer, sampled at Δt, against the default inverse: measured 0.0225, 0.0221 (bogie 1's
#: wheels), 0.0347, 0.0338 (bogie 2's); half of that at Δt = 1 ms (first-order discretisation error,
#: not a start-up transient). Bound ≈ measured × 1.4.
LSIM_BOUND = 0.048


def test_inverse_on_data_from_a_different_solver():
    from scipy.signal import lsim

    car = table_3_1()
    system = car.system()
    fine = 10
    h = DT / fine
    t = np.arange(int(round(2.0 / h)) + 1) * h
    xc = X0 + car.v * t[:, None] + system.offsets_m[None, :]
    y = IRREGULARITY.elevation(xc.ravel()).reshape(xc.shape)
    ydot = car.v * IRREGULARITY.slope(xc.ravel()).reshape(xc.shape)
    n = system.n_dof
    Minv = np.linalg.inv(system.M)
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-Minv @ system.K, -Minv @ system.C]])
    to_dofs = np.vstack([np.zeros((n, 4)), Minv @ system.G])
    B = np.hstack([to_dofs * system.kc, to_dofs * system.cc])
    forcing = np.hstack([y, ydot])
    q0 = np.linalg.solve(system.K, system.G @ (system.kc * y[0]))
    _, _, x = lsim((A, B, np.eye(2 * n), np.zeros((2 * n, 8))), forcing, t, X0=np.concatenate([q0, np.zeros(n)]))
    xdot = x @ A.T + forcing @ B.T
    channels = np.stack([xdot[:, n + 2], x[:, n + 3], xdot[:, n + 4], x[:, n + 5]], axis=1)[::fine]
    ap = InverseStream(build_inverse(system, DT)).update(channels)
    error = relative_after_shift(ap, y[::fine], norm="rms")
    assert np.all(error < LSIM_BOUND), error


def test_newmark_contact_rule_is_the_trapezoid_rule_at_average_acceleration():
    """The two contact rules of the inverse coincide for γ = ½, β = ¼ and differ otherwise."""
    system = table_3_1().system()
    z = np.random.default_rng(0).standard_normal((400, 4)) * [0.5, 0.01, 0.5, 0.01]
    runs = {(g, rule): InverseStream(build_inverse(system, DT, g, 0.25 * (0.5 + g) ** 2, rule)).update(z)
            for g in (0.5, 0.8) for rule in ("trapezoid", "newmark")}
    scale = np.abs(runs[0.5, "trapezoid"]).max()
    assert np.abs(runs[0.5, "newmark"] - runs[0.5, "trapezoid"]).max() < 1e-9 * scale
    assert np.abs(runs[0.8, "newmark"] - runs[0.8, "trapezoid"]).max() > 1e-3 * np.abs(runs[0.8, "trapezoid"]).max()
    with pytest.raises(ValueError, match="contact_rule"):
        build_inverse(system, DT, contact_rule="euler")
