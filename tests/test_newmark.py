"""Newmark-β (shared.dynamics.newmark): exact SDOF answers, convergence order, MDOF against lsim."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from shared.dynamics.newmark import (
    NewmarkState,
    effective_stiffness,
    integrate,
    newmark_constants,
    step,
)
from shared.vehicles import HalfCar, QuarterCar
from shared.vehicles.half_car import TABLE_2_1

from . import naive

TRAPEZOID = dict(gamma=0.5, beta=0.25)  # average acceleration: second order, no numerical damping
THESIS = dict(gamma=0.8)  # eq. (2.10): beta = (gamma + 1/2)^2 / 4, first order


# ---------------------------------------------------------------------------------------------
# Exact single-degree-of-freedom answers


def free_vibration(omega, zeta, u0, v0, t):
    """u(t) of ü + 2ζω u̇ + ω² u = 0, underdamped."""
    wd = omega * math.sqrt(1.0 - zeta**2)
    return np.exp(-zeta * omega * t) * (u0 * np.cos(wd * t) + (v0 + zeta * omega * u0) / wd * np.sin(wd * t))


def harmonic_response(omega, zeta, f0, Omega, t):
    """u(t) of ü + 2ζω u̇ + ω² u = f0 sin(Ωt) from rest: steady state plus the transient that cancels it."""
    amp = f0 / math.hypot(omega**2 - Omega**2, 2 * zeta * omega * Omega)
    phase = math.atan2(2 * zeta * omega * Omega, omega**2 - Omega**2)
    steady = amp * np.sin(Omega * t - phase)
    u_p0, v_p0 = amp * math.sin(-phase), amp * Omega * math.cos(-phase)
    return steady + free_vibration(omega, zeta, -u_p0, -v_p0, t)


OMEGA, ZETA = 2 * math.pi * 1.5, 0.05  # a body-bounce-like mode: 1.5 Hz, 5 % damping
M_SDOF = 2.0


def sdof_error(dt, forced, **scheme):
    """Max |Newmark − exact| over 3 s of free (u0 = 1 mm) or harmonically forced motion, m."""
    t = np.arange(int(round(3.0 / dt)) + 1) * dt
    k, c = M_SDOF * OMEGA**2, 2 * ZETA * OMEGA * M_SDOF
    if forced:
        f0, Omega = 5.0, 2 * math.pi * 2.3
        force = M_SDOF * f0 * np.sin(Omega * t)
        exact = harmonic_response(OMEGA, ZETA, f0, Omega, t)
        u0 = 0.0
    else:
        force = np.zeros_like(t)
        u0 = 1e-3
        exact = free_vibration(OMEGA, ZETA, u0, 0.0, t)
    u = integrate(M_SDOF, c, k, force, newmark_constants(dt, **scheme), u0=[u0]).u[:, 0]
    return np.abs(u - exact).max(), np.abs(exact).max()


@pytest.mark.parametrize("forced", [False, True], ids=["free", "harmonic"])
def test_sdof_matches_exact_solution(forced):
    err, scale = sdof_error(1e-3, forced, **TRAPEZOID)
    assert err < 1e-4 * scale
    err, scale = sdof_error(1e-3, forced, **THESIS)  # first order, numerically damped: looser
    assert err < 2e-2 * scale


@pytest.mark.parametrize(
    "scheme, order",
    [(TRAPEZOID, 2.0), (THESIS, 1.0), (dict(gamma=0.6, beta=0.3025), 1.0)],
    ids=["trapezoid", "thesis-gamma-0.8", "gamma-0.6"],
)
@pytest.mark.parametrize("forced", [False, True], ids=["free", "harmonic"])
def test_convergence_order(scheme, order, forced):
    """The slope of log(error) against log(Δt): 2 for γ = 1/2, 1 for any γ > 1/2."""
    dts = np.array([4e-3, 2e-3, 1e-3, 5e-4])
    errors = np.array([sdof_error(dt, forced, **scheme)[0] for dt in dts])
    slope = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    assert abs(slope - order) < 0.15, f"observed order {slope:.3f}, expected {order}"


def test_trapezoid_conserves_energy_of_undamped_oscillator():
    """γ = 1/2, β = 1/4 has no numerical damping; γ = 0.8 has some (eq. 2.10's purpose)."""
    t = np.arange(20001) * 1e-3
    amplitude = {}
    for name, scheme in (("trapezoid", TRAPEZOID), ("thesis", THESIS)):
        s = integrate(1.0, 0.0, OMEGA**2, np.zeros_like(t), newmark_constants(1e-3, **scheme), u0=[1.0])
        energy = 0.5 * s.v[:, 0] ** 2 + 0.5 * OMEGA**2 * s.u[:, 0] ** 2
        amplitude[name] = energy[-1] / energy[0]
    assert amplitude["trapezoid"] == pytest.approx(1.0, abs=1e-9)
    assert amplitude["thesis"] < 0.999


# ---------------------------------------------------------------------------------------------
# Multi-degree-of-freedom vehicles against scipy.signal.lsim of the continuous system


def road_force(system, t, speed=15.0):
    """Contact forces G·kc·y(t) from a smooth two-tone surface under each contact, N (n_steps, n_dof)."""
    x = speed * t[:, None] + system.offsets_m[None, :]
    y = 0.004 * np.sin(2 * np.pi * x / 7.3) + 0.002 * np.sin(2 * np.pi * x / 1.9 + 0.4)
    return (y * system.kc) @ system.G.T


def continuous_response(system, t, force):
    """q(t) of M q̈ + C q̇ + K q = f(t) by lsim (matrix exponential, f linear between samples)."""
    from scipy.signal import lsim

    n = system.n_dof
    Minv = np.linalg.inv(system.M)
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-Minv @ system.K, -Minv @ system.C]])
    B = np.vstack([np.zeros((n, n)), Minv])
    C = np.hstack([np.eye(n), np.zeros((n, n))])
    q0 = np.linalg.solve(system.K, force[0])  # start in equilibrium on the surface
    _, q, _ = lsim((A, B, C, np.zeros((n, n))), force, t, X0=np.concatenate([q0, np.zeros(n)]))
    return q.reshape(len(t), n), q0


@pytest.mark.parametrize(
    "vehicle",
    [QuarterCar(M=4450, m=420, K=5e5, k=1.95e6, c=2e4), HalfCar(**TABLE_2_1)],
    ids=["quarter_car", "half_car"],
)
def test_vehicle_forced_response_matches_lsim(vehicle):
    system = vehicle.system()
    dt = 1e-4
    t = np.arange(int(round(2.0 / dt)) + 1) * dt
    force = road_force(system, t)
    q_ref, q0 = continuous_response(system, t, force)
    scale = np.abs(q_ref).max(axis=0)
    # Trapezoidal Newmark at Δt = 0.1 ms: relative error O((ωΔt)²), measured 5e-7 … 8e-6 per DOF.
    q = integrate(system.M, system.C, system.K, force, newmark_constants(dt, **TRAPEZOID), u0=q0).u
    assert np.all(np.abs(q - q_ref).max(axis=0) < 3e-5 * scale)
    # The thesis's γ = 0.8 is first order: measured 5e-4 … 2.5e-3 per DOF at this step.
    q = integrate(system.M, system.C, system.K, force, newmark_constants(dt, **THESIS), u0=q0).u
    assert np.all(np.abs(q - q_ref).max(axis=0) < 1e-2 * scale)


def test_integrate_matches_naive_loop_and_step():
    system = HalfCar(**TABLE_2_1).system()
    dt = 2e-3
    t = np.arange(600) * dt
    force = road_force(system, t)
    c = newmark_constants(dt)
    q0 = np.linalg.solve(system.K, force[0])
    fast = integrate(system.M, system.C, system.K, force, c, u0=q0)
    u, v, a = naive.newmark_forward(system.M, system.C, system.K, force, dt, u0=q0)
    for x_fast, x_ref in zip(fast, (u, v, a)):
        np.testing.assert_allclose(x_fast, x_ref, rtol=0, atol=1e-10 * np.abs(x_ref).max())
    state = NewmarkState(fast.u[0], fast.v[0], fast.a[0])
    K_eff_inv = np.linalg.inv(effective_stiffness(system.M, system.C, system.K, c))
    for s in range(1, 50):
        state = step(system.M, system.C, system.K, force[s], state, c, K_eff_inv if s % 2 else None)
    np.testing.assert_allclose(state.u, fast.u[49], rtol=1e-10, atol=0)


# ---------------------------------------------------------------------------------------------
# Constants and validation


def test_constants_of_eq_2_10():
    dt, gamma = 0.001, 0.8
    c = newmark_constants(dt)
    beta = 0.25 * (0.5 + gamma) ** 2
    assert c.gamma == gamma and c.beta == pytest.approx(0.4225)
    expected = dict(
        a0=1 / (beta * dt**2), a1=gamma / (beta * dt), a2=1 / (beta * dt), a3=1 / (2 * beta) - 1,
        a4=gamma / beta - 1, a5=dt / 2 * (gamma / beta - 2), a6=(1 - gamma) * dt, a7=gamma * dt,
    )
    for name, value in expected.items():
        assert getattr(c, name) == pytest.approx(value, rel=1e-15), name


@given(
    dt=st.floats(1e-6, 1.0),
    gamma=st.floats(0.5, 2.0),
)
def test_constants_are_consistent(dt, gamma):
    c = newmark_constants(dt, gamma)
    assert all(math.isfinite(x) for x in c)
    assert c.a1 == pytest.approx(c.gamma * c.a2)
    assert c.a2 == pytest.approx(c.a0 * dt)
    assert c.a6 + c.a7 == pytest.approx(dt)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(dt=0.0), "dt"),
        (dict(dt=-1e-3), "dt"),
        (dict(dt=float("nan")), "dt"),
        (dict(dt=float("inf")), "dt"),
        (dict(dt=1e-3, gamma=0.49), "gamma"),
        (dict(dt=1e-3, gamma=float("nan")), "gamma"),
        (dict(dt=1e-3, beta=0.0), "beta"),
        (dict(dt=1e-3, beta=-0.1), "beta"),
        (dict(dt=1e-3, beta=float("inf")), "beta"),
    ],
)
def test_constants_reject_bad_input(kwargs, field):
    with pytest.raises(ValueError, match=field):
        newmark_constants(**kwargs)


def test_integrate_rejects_bad_input():
    c = newmark_constants(1e-3)
    M = C = K = np.eye(2)
    with pytest.raises(ValueError, match="degrees of freedom"):
        integrate(M, C, K, np.zeros((10, 3)), c)
    with pytest.raises(ValueError, match="NaN"):
        integrate(M, C, K, np.full((10, 2), np.nan), c)
