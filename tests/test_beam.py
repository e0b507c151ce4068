"""Bridge beam FE kernels against closed-form beam theory and the thesis's numbers."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from shared.fe import (
    Beam,
    assemble,
    compliance_kernel,
    contact_entries,
    contact_matrix,
    contact_vector,
    crack_ei_factor,
    crack_peak_loss,
    global_ei_factor,
    hermite_shape,
    influence_line,
    natural_frequencies,
    static_deflection,
)

L = 20.0
E = 35e9


def thesis_beam(**kw) -> Beam:
    """§4.2: 20 m simply supported, 20 elements, I = 1.25 m⁴, μ = 37 500 kg/m, 3 % damping."""
    return Beam(**{"span_m": L, "n_elements": 20, "E_pa": E, "I_m4": 1.25, "mass_per_m": 37_500.0, **kw})


def springs(krot: float, **kw) -> Beam:
    return thesis_beam(supports="rotational_springs", krot_nm_per_rad=(krot, krot), **kw)


# --- closed-form references (up-positive deflection under an upward force P) ---------------


def ss_frequency(mode: int, ei: float, mu: float) -> float:
    return mode**2 * math.pi / (2 * L**2) * math.sqrt(ei / mu)


def ss_deflection(p: float, a: float, x: np.ndarray, ei: float) -> np.ndarray:
    """Simply supported span, force p (up) at a, deflection (up) at x."""
    b = L - a
    x = np.asarray(x, dtype=float)
    left = p * b * x * (L**2 - b**2 - x**2) / (6 * L * ei)
    xr = L - x
    right = p * a * xr * (L**2 - a**2 - xr**2) / (6 * L * ei)
    return np.where(x <= a, left, right)


def naive_compliance(x: float, ei: np.ndarray, n_sub: int = 20_000) -> float:
    """Unit-load theorem by brute quadrature: ∫ M(s)²/EI(s) ds for a unit load at x."""
    s = (np.arange(n_sub) + 0.5) * (L / n_sub)  # midpoint rule on a fine grid
    m = np.where(s <= x, (L - x) * s / L, x * (L - s) / L)
    ei_s = ei[np.minimum((s / (L / len(ei))).astype(int), len(ei) - 1)]
    return float(np.sum(m**2 / ei_s) * (L / n_sub))


# --- natural frequencies --------------------------------------------------------------------


def test_first_frequency_matches_thesis_beams():
    f_353 = natural_frequencies(Beam(L, 20, E, 0.33, 9_600.0), 1)[0]
    f_42 = natural_frequencies(thesis_beam(), 1)[0]
    assert f_353 == pytest.approx(4.31, rel=5e-3)  # §3.5.3
    assert f_42 == pytest.approx(4.24, rel=5e-3)  # §4.2
    assert f_42 == pytest.approx(ss_frequency(1, E * 1.25, 37_500.0), rel=1e-6)


def test_simply_supported_modes_follow_n_squared():
    f = natural_frequencies(thesis_beam(), 5)
    assert f[1] == pytest.approx(4 * ss_frequency(1, E * 1.25, 37_500.0), rel=1e-5)
    exact = [ss_frequency(k, E * 1.25, 37_500.0) for k in range(1, 6)]
    np.testing.assert_allclose(f, exact, rtol=5e-4)


def test_frequency_converges_at_fourth_order_in_element_length():
    # Cubic Hermite elements with consistent mass: eigenvalue error O(h⁴).
    exact = ss_frequency(2, E * 1.25, 37_500.0)
    errors = [abs(natural_frequencies(thesis_beam(n_elements=n), 2)[1] - exact) / exact for n in (4, 8, 16)]
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    np.testing.assert_allclose(rates, 4.0, atol=0.1)


def test_natural_frequencies_rejects_too_many_modes():
    with pytest.raises(ValueError, match="n_modes"):
        natural_frequencies(thesis_beam(n_elements=2), 5)


# --- statics --------------------------------------------------------------------------------


def test_midspan_deflection_is_pl3_over_48ei():
    p = 1e5
    w = static_deflection(thesis_beam(), -p, L / 2, L / 2)
    assert w == pytest.approx(-p * L**3 / (48 * E * 1.25), rel=1e-12)


@pytest.mark.parametrize("n_elements", [2, 5, 20])
def test_nodal_load_deflection_is_exact_everywhere(n_elements):
    # Under nodal loads the exact solution is cubic in each element, so Hermite FE is exact.
    beam = thesis_beam(n_elements=n_elements)
    a = beam.node_x()[1]
    x = np.linspace(0.0, L, 97)
    np.testing.assert_allclose(
        static_deflection(beam, -2e5, a, x), ss_deflection(-2e5, a, x, E * 1.25), rtol=1e-10, atol=1e-18
    )


def test_off_node_load_is_exact_at_nodes_and_converges_between():
    # Nodal values are exact for any load; inside the loaded element the FE field is the cubic
    # interpolant, missing exactly the clamped–clamped element's own deflection under the
    # load: P le³ ξ³(1−ξ)³ / (3 EI) — third order in element length.
    a, ei = 7.3, E * 1.25  # never on a node of the meshes below
    for n in (4, 8, 16, 32):
        beam = thesis_beam(n_elements=n)
        nodes = beam.node_x()
        np.testing.assert_allclose(
            static_deflection(beam, -1.0, a, nodes), ss_deflection(-1.0, a, nodes, ei), rtol=1e-10, atol=1e-22
        )
        le = beam.element_length_m
        xi = a / le - math.floor(a / le)
        missing = le**3 * xi**3 * (1 - xi) ** 3 / (3 * ei)
        error = static_deflection(beam, -1.0, a, a) - ss_deflection(-1.0, a, a, ei)
        assert error == pytest.approx(missing, rel=1e-6)


def test_loads_superpose_and_are_reciprocal():
    beam = thesis_beam(ei_factor=crack_ei_factor(20, L, 1.0, 10.0, 0.1))
    w_ab = static_deflection(beam, 1.0, 3.3, 12.7)
    w_ba = static_deflection(beam, 1.0, 12.7, 3.3)
    assert w_ab == pytest.approx(w_ba, rel=1e-10)  # Maxwell–Betti
    both = static_deflection(beam, [-1e5, -2e5], [4.0, 9.5], [6.0, 15.0])
    apart = static_deflection(beam, -1e5, 4.0, [6.0, 15.0]) + static_deflection(beam, -2e5, 9.5, [6.0, 15.0])
    np.testing.assert_allclose(both, apart, rtol=1e-12)
    assert static_deflection(beam, -1e5, 25.0, 10.0) == 0.0  # a load off the span does nothing


def test_influence_line_is_a_positive_compliance():
    beam = thesis_beam()
    x = np.array([0.0, 3.3, 10.0, 17.25, 20.0, -1.0, 21.0])
    j = influence_line(beam, x)
    np.testing.assert_allclose(j, [-static_deflection(beam, -1.0, xi, xi) for xi in x], rtol=1e-12)
    assert j[2] == pytest.approx(L**3 / (48 * E * 1.25), rel=1e-12)
    np.testing.assert_array_equal(j[[0, 4, 5, 6]], 0.0)
    assert np.all(j[1:4] > 0)


# --- rotational springs (§4.4.1) ------------------------------------------------------------


def test_stiff_springs_approach_fixed_fixed():
    ei, p = E * 1.25, 1e5
    beam = springs(1e15)  # ~1e6 · EI/L: practically clamped
    f_fixed = 22.373 / (2 * math.pi * L**2) * math.sqrt(ei / 37_500.0)
    assert natural_frequencies(beam, 1)[0] == pytest.approx(f_fixed, rel=1e-4)
    assert static_deflection(beam, -p, L / 2, L / 2) == pytest.approx(-p * L**3 / (192 * ei), rel=1e-4)


def test_zero_springs_are_simply_supported_and_stiffness_grows_with_krot():
    ss = thesis_beam()
    np.testing.assert_allclose(natural_frequencies(springs(0.0), 3), natural_frequencies(ss, 3), rtol=1e-13)
    assert natural_frequencies(springs(1e3), 1)[0] == pytest.approx(natural_frequencies(ss, 1)[0], rel=1e-6)
    f1 = [natural_frequencies(springs(k), 1)[0] for k in (0.0, 1e9, 1e10, 1e12)]
    assert np.all(np.diff(f1) > 0)


def test_one_sided_spring_lands_on_its_own_end():
    left = thesis_beam(supports="rotational_springs", krot_nm_per_rad=(1e15, 0.0))
    right = thesis_beam(supports="rotational_springs", krot_nm_per_rad=(0.0, 1e15))
    # Propped cantilever: the deflection field of one is the mirror image of the other's.
    x = np.linspace(0.0, L, 41)
    np.testing.assert_allclose(
        static_deflection(left, -1.0, 8.0, x), static_deflection(right, -1.0, L - 8.0, L - x), rtol=1e-9
    )
    # eigh's eigenvalues carry an absolute error of ~eps·λ_max (Weyl), so the stiff spring's λ_max/λ_1
    # = (f_max/f_1)² sets how far the two mirror images' f_1 ∝ √λ_1 may part: eps·λ_max/λ_1 between them.
    f = natural_frequencies(left, 2 * left.n_elements)
    assert f[0] == pytest.approx(natural_frequencies(right, 1)[0], rel=np.finfo(float).eps * (f[-1] / f[0]) ** 2)


# --- damping --------------------------------------------------------------------------------


def modal_damping_ratios(beam: Beam, damping: str) -> np.ndarray:
    from scipy import linalg

    sys = assemble(beam, damping=damping)
    lam, phi = linalg.eigh(sys.K, sys.M)
    return np.diag(phi.T @ sys.C @ phi) / (2 * np.sqrt(lam))


def test_rayleigh_damping_is_three_percent_on_modes_one_and_two():
    zeta = modal_damping_ratios(thesis_beam(), "rayleigh")
    np.testing.assert_allclose(zeta[:2], 0.03, rtol=1e-9)
    assert np.all(zeta[2:] > 0.03)  # stiffness-proportional part grows with frequency


def test_modal_damping_is_three_percent_on_every_mode():
    np.testing.assert_allclose(modal_damping_ratios(springs(1e10), "modal"), 0.03, rtol=1e-8)


def test_assembled_system_shapes_and_symmetry():
    sys = assemble(thesis_beam())
    assert sys.n_dof == 40 and sys.M.shape == sys.K.shape == sys.C.shape == (40, 40)
    assert 0 not in sys.free_dofs and 40 not in sys.free_dofs  # w at both supports removed
    for m in (sys.M, sys.K, sys.C):
        np.testing.assert_allclose(m, m.T, rtol=0, atol=1e-9 * np.abs(m).max())
    # A cubic field is represented exactly, so its kinetic and strain energies are exact:
    # uᵀMu = μ∫w² dx and uᵀKu = EI∫w''² dx.
    w = np.polynomial.Polynomial([0.0, 3 * L, L - 3.0, -1.0]) * 1e-3  # x (L − x)(x + 3)
    beam = thesis_beam()
    nodes = beam.node_x()
    u = np.column_stack([w(nodes), w.deriv()(nodes)]).ravel()[sys.free_dofs]
    assert u @ sys.M @ u == pytest.approx(37_500.0 * ((w**2).integ()(L)), rel=1e-12)
    assert u @ sys.K @ u == pytest.approx(E * 1.25 * ((w.deriv(2) ** 2).integ()(L)), rel=1e-12)
    with pytest.raises(ValueError, match="damping"):
        assemble(thesis_beam(), damping="hysteretic")


# --- coupling: shape functions and contact rows ---------------------------------------------


def test_hermite_shape_partition_and_derivatives():
    le = 0.8
    xi = np.linspace(0.0, 1.0, 11)
    n = hermite_shape(xi, le)
    np.testing.assert_allclose(n[:, 0] + n[:, 2], 1.0)  # rigid translation
    np.testing.assert_allclose(n[:, 1] + n[:, 3] + le * n[:, 2], le * xi)  # rigid rotation about start
    h = 1e-6
    for d in (1, 2):
        fd = (hermite_shape(xi + h, le, d - 1) - hermite_shape(xi - h, le, d - 1)) / (2 * h * le)
        np.testing.assert_allclose(hermite_shape(xi, le, d), fd, atol=1e-5)


def test_contact_rows_interpolate_a_cubic_exactly():
    beam = thesis_beam(n_elements=7)  # irrational element length

    def w(x):  # any cubic vanishing at both supports
        return 1e-3 * x * (L - x) * (x + 3.0)

    def dw(x):
        return 1e-3 * ((L - x) * (x + 3.0) - x * (x + 3.0) + x * (L - x))

    nodes = beam.node_x()
    full = np.column_stack([w(nodes), dw(nodes)]).ravel()
    u = full[assemble(beam).free_dofs]
    x = np.linspace(0.0, L, 53)
    np.testing.assert_allclose(contact_matrix(beam, x) @ u, w(x), atol=1e-12)


def test_contact_forms_agree_and_vanish_off_span():
    beam = thesis_beam()
    x = np.array([-0.5, 0.0, 2.7, 10.0, 19.99, 20.0, 20.5])
    dense = contact_matrix(beam, x)
    for i, xi in enumerate(x):
        np.testing.assert_array_equal(contact_vector(beam, xi), dense[i])
    entries = contact_entries(beam, x)
    rebuilt = np.zeros_like(dense)
    for i in range(len(x)):
        for dof, val in zip(entries.dofs[i], entries.values[i]):
            if dof >= 0:
                rebuilt[i, dof] += val
    np.testing.assert_array_equal(rebuilt, dense)
    np.testing.assert_array_equal(dense[[0, 1, 5, 6]], 0.0)  # supports and off the deck
    assert np.all(entries.values[entries.dofs < 0] == 0.0)
    with pytest.raises(ValueError, match="x_m"):
        contact_matrix(beam, np.array([1.0, np.nan]))


# --- damage (§4.5.1) ------------------------------------------------------------------------


@pytest.mark.parametrize("crack_x", [10.0, 14.0])
@pytest.mark.parametrize(("phi", "inner", "outer"), [(0.10, 0.18, 0.05), (0.05, 0.10, 0.03)])
def test_crack_reproduces_thesis_element_losses(crack_x, phi, inner, outer):
    loss = 1.0 - crack_ei_factor(20, L, 1.0, crack_x, phi)
    k = int(crack_x)  # the crack sits on node k: elements k-1 and k touch it
    affected = [k - 2, k - 1, k, k + 1]
    assert np.count_nonzero(loss) == 4 and np.all(loss[affected] > 0)
    np.testing.assert_allclose(loss[[k - 1, k]], inner, atol=0.007)  # thesis quotes whole percent
    np.testing.assert_allclose(loss[[k - 2, k + 1]], outer, atol=0.007)
    assert loss[k - 1] == loss[k] and loss[k - 2] == loss[k + 1]


def test_crack_exact_averaging_conserves_the_lost_area():
    peak = crack_peak_loss(0.1)
    assert peak == pytest.approx(1 - 0.9**3)
    for x in (10.0, 10.4, 0.7):  # on a node, inside an element, truncated by the support
        loss = 1.0 - crack_ei_factor(20, L, 1.0, x, 0.1, averaging="exact")
        s = np.linspace(0.0, L, 200_001)
        tri = peak * np.clip(1 - np.abs(s - x) / 1.5, 0, None)
        assert loss.sum() * 1.0 == pytest.approx(np.trapezoid(tri, s), rel=1e-6)
    exact = 1.0 - crack_ei_factor(20, L, 1.0, 10.0, 0.1, averaging="exact")
    np.testing.assert_allclose(exact[8:12], peak * np.array([1 / 12, 2 / 3, 2 / 3, 1 / 12]), rtol=1e-12)


def test_crack_rules_agree_on_a_fine_mesh():
    nodal = crack_ei_factor(400, L, 1.0, 10.37, 0.1)
    exact = crack_ei_factor(400, L, 1.0, 10.37, 0.1, averaging="exact")
    assert np.max(np.abs(nodal - exact)) < 0.01


def test_global_loss():
    np.testing.assert_array_equal(global_ei_factor(20, 0.05), np.full(20, 0.95))
    beam = thesis_beam(ei_factor=global_ei_factor(20, 0.10))
    assert static_deflection(beam, -1.0, 10.0, 10.0) == pytest.approx(-(L**3) / (48 * E * 1.25 * 0.9), rel=1e-12)
    with pytest.raises(ValueError, match="loss"):
        global_ei_factor(20, 1.0)


@pytest.mark.parametrize("bad", [{"phi": 1.0}, {"phi": -0.1}, {"crack_x_m": 21.0}, {"depth_m": 0.0}])
def test_crack_rejects_bad_input(bad):
    args = {"n_elements": 20, "span_m": L, "depth_m": 1.0, "crack_x_m": 10.0, "phi": 0.1, **bad}
    with pytest.raises(ValueError, match=next(iter(bad))):
        crack_ei_factor(**args)


# --- closed-form compliance kernel -------------------------------------------------------------


@pytest.mark.parametrize("damaged", [False, True])
def test_compliance_kernel_matches_fe_influence_line_at_nodes(damaged):
    factor = crack_ei_factor(20, L, 1.0, 14.0, 0.1) if damaged else None
    beam = thesis_beam(ei_factor=factor)
    x = beam.node_x()[1:-1]
    j_kernel = compliance_kernel(beam, x) @ (1.0 / beam.element_ei())
    np.testing.assert_allclose(j_kernel, influence_line(beam, x), rtol=1e-9)


def test_compliance_kernel_matches_brute_quadrature_off_nodes():
    beam = thesis_beam(ei_factor=crack_ei_factor(20, L, 1.0, 10.0, 0.1))
    x = np.array([0.37, 5.5, 9.9, 13.21])
    j_kernel = compliance_kernel(beam, x) @ (1.0 / beam.element_ei())
    j_naive = [naive_compliance(xi, beam.element_ei()) for xi in x]
    np.testing.assert_allclose(j_kernel, j_naive, rtol=1e-7)
    # The FE influence line approaches it between nodes at third order in element length.
    xs = np.linspace(0.0, L, 801)
    exact = xs**2 * (L - xs) ** 2 / (3 * L * E * 1.25)
    np.testing.assert_allclose(compliance_kernel(thesis_beam(), xs).sum(axis=1) / (E * 1.25), exact, atol=1e-22)
    errs = [np.max(np.abs(influence_line(thesis_beam(n_elements=n), xs) - exact)) for n in (5, 10, 20)]
    np.testing.assert_allclose(np.log2(np.array(errs[:-1]) / np.array(errs[1:])), 3.0, atol=0.2)


def test_compliance_kernel_shape_and_guards():
    beam = thesis_beam()
    g = compliance_kernel(beam, np.array([-1.0, 0.0, 10.0, 20.0, 25.0]))
    assert g.shape == (5, 20) and np.all(g >= 0)
    np.testing.assert_array_equal(g[[0, 1, 3, 4]], 0.0)
    with pytest.raises(ValueError, match="supports"):
        compliance_kernel(springs(1e9), 10.0)


# --- parameter validation -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("span_m", 0.0),
        ("span_m", math.inf),
        ("n_elements", 0),
        ("n_elements", 2.5),
        ("E_pa", -1.0),
        ("I_m4", float("nan")),
        ("mass_per_m", 0.0),
        ("damping_ratio", 1.0),
        ("damping_ratio", -0.01),
        ("supports", "fixed"),
        ("krot_nm_per_rad", (1e9, 1e9)),  # springs given to a simply supported beam
        ("ei_factor", np.ones(19)),
        ("ei_factor", np.r_[np.ones(19), 0.0]),
        ("depth_m", -1.0),
    ],
)
def test_beam_rejects_bad_fields(field, value):
    with pytest.raises(ValueError, match=f"Beam.{field}"):
        thesis_beam(**{field: value})


@pytest.mark.parametrize("krot", [None, (1e9,), (1e9, -1.0), (1e9, math.inf)])
def test_rotational_springs_need_a_valid_pair(krot):
    with pytest.raises(ValueError, match="krot_nm_per_rad"):
        thesis_beam(supports="rotational_springs", krot_nm_per_rad=krot)


def test_beam_is_a_frozen_value():
    factor = np.ones(20)
    beam = thesis_beam(ei_factor=factor)
    factor[3] = 0.5  # the caller's array is copied, not aliased
    assert beam.element_ei()[3] == E * 1.25
    assert beam == thesis_beam() and hash(beam) == hash(thesis_beam())
    assert beam != thesis_beam(ei_factor=global_ei_factor(20, 0.05))
    with pytest.raises(dataclasses.FrozenInstanceError):
        beam.span_m = 30.0
    with pytest.raises(ValueError):
        beam.ei_factor[0] = 2.0
    np.testing.assert_allclose(beam.element_bounds()[[0, -1]], [[0.0, 1.0], [19.0, 20.0]])
