"""Moving-reference influence line by the matrix method (thesis §3.5.2) and damage indicators D1/D2."""

from __future__ import annotations

import numpy as np
import pytest

from cloud.bridge.hypotheses import Kernels
from cloud.bridge.mril import (AxlePair, Baseline, MrIl, damage_indicators, mril_two_axle, normal_equations)
from cloud.bridge.setup import Setup
from shared.fe.beam import Beam, global_ei_factor, influence_line
from shared.registry import Bridge
from shared.vbi import simulate_vbi
from shared.vehicles.bogie import table_3_2

L = 20.0
X = np.linspace(0.0, L, 401)


def flat(x):
    return np.zeros_like(x)


def thesis_3_5_3_beam(loss: float = 0.0) -> Beam:
    """§3.5.3: 20 m, I = 0.33 m⁴, E = 35 GPa, μ = 9 600 kg/m (f1 ≈ 4.3 Hz)."""
    return Beam(L, 20, 35e9, 0.33, 9600.0, ei_factor=global_ei_factor(20, loss))


def bogie_pass(ms: float, speed: float, loss: float = 0.0, dt: float = 0.002) -> AxlePair:
    """A Table 3.2 bogie half-car (axles 17 m apart) over the beam on a smooth deck, noise-free:
    the deflections under its axles (positive down) on the span grid."""
    veh = table_3_2(ms)
    s = veh.system()
    r = simulate_vbi(s, flat, flat, -18.5, speed, (L + 37.0) / speed, dt, beam=thesis_3_5_3_beam(loss),
                     bridge_start_m=0.0)
    loads = s.static_contact_forces()
    da = -np.interp(X, r.x_cg + veh.D1, r.deflection[:, 0])
    db = -np.interp(X, r.x_cg - veh.D2, r.deflection[:, 1])
    return AxlePair(X, da, db, loads[0], loads[1], veh.D1 + veh.D2)


def naive_mril(p: AxlePair) -> np.ndarray:
    """Eq. 3.17 literally: the dense least-squares problem over all scans, J = 0 off the span."""
    M = p.x_m.size
    c = int(round(p.spacing_m / (p.x_m[1] - p.x_m[0])))
    rows, rhs = [], []
    for k in range(M + c):
        row = np.zeros(M)
        dA = p.delta_a[k] if k < M else 0.0
        dB = p.delta_b[k - c] if 0 <= k - c < M else 0.0
        if k < M:
            row[k] += p.load_a**2
        if 0 <= k - c < M:
            row[k - c] -= p.load_b**2
        rows.append(row)
        rhs.append(p.load_a * dA - p.load_b * dB)
    return np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]


@pytest.mark.parametrize("spacing, loads", [(2.0, (5e4, 3e4)), (7.35, (4e4, 4e4))])
def test_banded_normal_equations_solve_the_least_squares_problem(spacing, loads):
    rng = np.random.default_rng(1)
    x = np.linspace(0.0, 10.0, 201)
    p = AxlePair(x, rng.standard_normal(x.size) * 1e-4, rng.standard_normal(x.size) * 1e-4, loads[0], loads[1],
                 spacing)
    fast = normal_equations(p).solve()
    assert np.allclose(fast, naive_mril(p), rtol=1e-8, atol=1e-14)


def test_mril_at_crawling_speed_is_the_static_influence_line():
    p = bogie_pass(32e3, 2.0, dt=0.004)
    J = influence_line(thesis_3_5_3_beam(), X)
    m = mril_two_axle([p])
    assert np.max(np.abs(m.J - J)) < 5e-3 * J.max()
    # unequal axle loads too (a light front: the matrix stays regular either way)
    p2 = AxlePair(X, p.delta_a, p.delta_b, p.load_a, p.load_b, p.spacing_m)
    assert np.allclose(mril_two_axle([p, p2], pooled=True).J, m.J, rtol=1e-9, atol=1e-20)


def test_d2_reads_global_losses_of_0_5_and_10_percent():
    """Thesis Table 3.3 at 10 m/s: D2 = 0/5/10 %. Baseline and test fleets are different draws."""
    rng = np.random.default_rng(7)

    def fleet(loss, n=3):
        return mril_two_axle([bogie_pass(32e3 + 3.2e3 * rng.standard_normal(), 10.0, loss, dt=0.004)
                              for _ in range(n)])

    healthy = fleet(0.0)
    base = Baseline.learnt(3)
    base.offer(healthy)
    assert base.ready
    for loss in (0.0, 0.05, 0.10):
        d = damage_indicators(base.mril, fleet(loss))
        assert abs(d.D2_pct - 100 * loss) < 1.0, (loss, d)
        assert abs(d.D1_pct - 100 * loss) < 3.0, (loss, d)


def test_declared_baseline_and_indicator_definitions():
    bridge = Bridge("B1", "R1", 0.0, L, 20, 35e9, 0.33, 9600.0, 1.0, 0.03, "simply_supported")
    base = Baseline.declared(bridge, X)
    J = influence_line(thesis_3_5_3_beam(), X)
    assert np.allclose(base.mril.J, J)
    soft = MrIl(X, J / 0.9, 1)
    d = damage_indicators(base.mril, soft)
    assert d.D1_pct == pytest.approx(10.0) and d.D2_pct == pytest.approx(10.0)


def test_bearing_kernel_is_the_fe_influence_line_with_rotational_springs():
    """The hypotheses' closed form (a rank-2 update of the pinned span) against the FE beam."""
    bridge = Bridge("B1", "R1", 100.0, L, 20, 35e9, 1.25, 37500.0, 1.0, 0.03, "simply_supported")
    setup = Setup.of(bridge)
    kern = Kernels.of(setup)
    for scale, krot in ((1.0, 1e9), (0.9, 1e10), (1.1, 1e12)):
        a = kern.bearings(np.array([scale]), np.array([krot]))[0]
        beam = Beam(L, 20, 35e9 * scale, 1.25, 37500.0, supports="rotational_springs", krot_nm_per_rad=(krot, krot))
        exact = influence_line(beam, setup.basis.x)
        assert np.max(np.abs(setup.basis.design @ a - exact)) < 3e-4 * exact.max()
