"""The bridge's own dynamics in the pass model: each pass's moving-force excess over the quasi-static kernel.

At 15–22 m/s a 20 m span (f1 ≈ 4.2 Hz) is crossed in about four of its periods, and the deflection
under the wheel differs from the static ``W·J(x)`` by several per cent, oscillating with x and with
a speed-dependent phase; averaged over a fleet's speeds it is a bias of a few per cent in the
global stiffness, and along the span it masquerades as stiffness variations.

Model: the wheel is a moving force ``W·(1 + φ_p(x))`` (the pass's measured dynamic wheel load,
:class:`~cloud.bridge.passdata.VehicleFilter`) on the FE beam with the current stiffness estimate,
integrated from rest (:func:`shared.fe.beam.moving_load_deflection`, Newmark trapezoidal rule).
Its deflection under the force, per newton of static load, minus the quasi-static
``(1 + φ_p)·J`` is the pass's dynamic excess ``ε_p(x)`` (:func:`dynamic_excess`); the estimator
adds it to the load term (``h_p = (1 + φ_p)·J(θ) + ε_p``). ε moves with the stiffness level — in
amplitude and, above all, in phase (f1 ∝ √EI) — and with each element's stiffness, differently for
every pass (speed): :func:`excess_sensitivity` gives its derivatives in every element's θ by forward
mode through the same Newmark solve (n_e more right-hand sides of one factorised matrix).
:func:`dynamic_deltas` and :func:`dynamic_sensitivities` compute them for every pass at given
stiffness parameters and keep them in the caller's cache, so that a live estimator, which evaluates
them at levels on :data:`LEVEL_GRID`, finds the earlier passes' there. How the fits use them:
:mod:`cloud.bridge.dynamic`.

This is a simplification of the coupled vehicle–bridge system the data came from (``shared.vbi``):
the coupling enters only through the measured wheel load. With the coupled simulation's actual
wheel load the moving force reproduces its deflection to < 1 % (``tests/test_bridge_dynamic.py``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from scipy import linalg

from shared.dynamics.newmark import effective_stiffness, integrate, newmark_constants
from shared.fe.beam import (Beam, BeamSystem, assemble, contact_entries, contact_matrix, element_matrices, influence_line,
                            moving_load_deflection)
from shared.fe.design import design_beam
from shared.jit import kernel

from cloud.bridge.passdata import PassData, Window
from cloud.bridge.setup import Setup
from cloud.bridge.whitening import WhitenedPass

SUBSTEPS = 2  # beam time steps per grid point
BAND = 3  # half-bandwidth of a Hermite beam's matrices on its free DOFs (w, θ per node)
#: The dynamic excess is computed at global levels on this grid (log ratio): a live estimator's
#: later updates then find most levels' excesses of earlier passes in its cache. Half a grid step
#: moves ε by far less than its own uncertainty (the level's sd is ~2 % at 30 passes).
LEVEL_GRID = 0.0025


def _moving_force(beam: Beam, p: PassData, substeps: int):
    """The pass's moving force on the beam: span points, their load factor, the time step, the
    force's positions x_t and values (per newton of static wheel load, up positive)."""
    w: Window = p.window
    on = w.on_span
    xs = np.clip(w.x[on], 0.0, beam.span_m)
    lf = p.load_factor[on]
    dt = w.spacing_m / (p.speed_mps * substeps)
    n_steps = int(np.ceil(beam.span_m / (p.speed_mps * dt))) + 2
    x_t = np.arange(n_steps) * p.speed_mps * dt
    force = -np.interp(x_t, xs, lf, left=1.0, right=1.0)
    force[x_t > beam.span_m] = 0.0
    return xs, lf, dt, x_t, force


def dynamic_excess(beam: Beam, p: PassData, substeps: int = SUBSTEPS, system: BeamSystem | None = None,
                   influence: np.ndarray | None = None) -> np.ndarray:
    """ε_p on the window (m/N, positive in the load's direction; zero off the span).

    ``system`` (:func:`~shared.fe.beam.assemble` of ``beam``) and ``influence`` (J on the
    window's span points) may be passed in to share them between passes.
    """
    w: Window = p.window
    on = w.on_span
    xs, lf, dt, x_t, force = _moving_force(beam, p, substeps)
    J = influence_line(beam, xs) if influence is None else influence
    u = -moving_load_deflection(beam, x_t, force, dt, system=system)  # compliance sign
    out = np.zeros(w.n)
    out[on] = np.interp(xs, x_t, u) - lf * J
    return out


@dataclasses.dataclass(frozen=True, eq=False)
class StiffnessDerivatives:
    """How the beam's matrices move with θ_z = log of element z's EI factor (free DOFs).

    ∂K/∂θ_z is element z's own stiffness at the current EI (``ke`` (n_e, 4, 4) on free DOFs
    ``dofs`` (n_e, 4), −1 where constrained). The Rayleigh damping C = α·M + β·K of
    :func:`~shared.fe.beam.assemble` moves with K and with its two anchor frequencies
    (∂ω_i/∂θ_z = φ_iᵀ·∂K/∂θ_z·φ_i / 2ω_i, mass-normalised modes):
    ∂C/∂θ_z = ``dalpha[z]``·M + ``dbeta[z]``·K + ``beta``·∂K/∂θ_z.
    """

    ke: np.ndarray
    dofs: np.ndarray
    beta: float
    dalpha: np.ndarray
    dbeta: np.ndarray

    @classmethod
    def of(cls, beam: Beam, system: BeamSystem) -> "StiffnessDerivatives":
        ne = beam.n_elements
        ke, _ = element_matrices(beam.element_length_m, beam.element_ei(), beam.mass_per_m)
        full_to_free = np.full(2 * (ne + 1), -1, dtype=np.int64)
        full_to_free[system.free_dofs] = np.arange(system.n_dof)
        dofs = full_to_free[2 * np.arange(ne)[:, None] + np.arange(4)]
        ke = np.where((dofs[:, :, None] >= 0) & (dofs[:, None, :] >= 0), ke, 0.0)
        lam, phi = linalg.eigh(system.K, system.M, subset_by_index=[0, 1])
        w1, w2 = np.sqrt(lam)
        zeta = beam.damping_ratio
        pad = np.vstack([phi, np.zeros((1, 2))])  # row −1: a constrained DOF
        loc = pad[dofs]  # (n_e, 4, 2)
        dlam = np.einsum("zim,zij,zjm->zm", loc, ke, loc)
        dw1, dw2 = dlam[:, 0] / (2 * w1), dlam[:, 1] / (2 * w2)
        s = w1 + w2
        dalpha = 2 * zeta * (w2**2 * dw1 + w1**2 * dw2) / s**2
        dbeta = -2 * zeta * (dw1 + dw2) / s**2
        return cls(np.ascontiguousarray(ke), dofs, 2 * zeta / s, dalpha, dbeta)

    def influence(self, beam: Beam, system: BeamSystem, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """J(x) and ∂J/∂θ_z = −Uᵀ·∂K/∂θ_z·U (U = K⁻¹Nᵀ) on ``xs``; (n_x,), (n_x, n_e)."""
        N = contact_matrix(beam, xs)
        U = linalg.solve(system.K, N.T, assume_a="pos")  # (n_dof, n_x)
        J = np.einsum("ij,ji->i", N, U)
        loc = np.vstack([U, np.zeros((1, U.shape[1]))])[self.dofs]  # (n_e, 4, n_x)
        return J, -np.einsum("zix,zij,zjx->xz", loc, self.ke, loc)


@kernel
def _tangent_kernel(L, M, C, K, k, u, v, ke, dofs, beta, dalpha, dbeta, cdofs, cvals, band):
    """Forward-mode sensitivity of the Newmark moving-force solve to each element's θ.

    The primal (``u``, ``v``: (n_steps, n_dof)) satisfies M·a + C·v + K·u = f at every step; its
    derivative along θ_z satisfies the same recurrence with the force −∂K_z·u − ∂C_z·v, from rest.
    All n_e tangents are integrated together (same effective matrix, ``L`` its Cholesky factor).
    M, C, K and L are banded (``band``: half-bandwidth). Returns the deflection under the force,
    N(x_t)·u_z, (n_steps, n_e).
    """
    n_steps, n = u.shape
    ne = ke.shape[0]
    U = np.zeros((n, ne))
    V = np.zeros((n, ne))
    A = np.zeros((n, ne))
    rhs = np.zeros((n, ne))
    pu = np.zeros((n, ne))
    pc = np.zeros((n, ne))
    mv = np.zeros(n)
    kv = np.zeros(n)
    out = np.zeros((n_steps, ne))
    for s in range(1, n_steps):
        for i in range(n):
            for z in range(ne):
                pu[i, z] = k[0] * U[i, z] + k[2] * V[i, z] + k[3] * A[i, z]
                pc[i, z] = k[1] * U[i, z] + k[4] * V[i, z] + k[5] * A[i, z]
        for i in range(n):
            am = 0.0
            ak = 0.0
            for j in range(max(0, i - band), min(n, i + band + 1)):
                am += M[i, j] * v[s, j]
                ak += K[i, j] * v[s, j]
            mv[i] = am
            kv[i] = ak
        for i in range(n):  # (loops ordered for contiguous inner runs over the elements)
            for z in range(ne):
                rhs[i, z] = -dalpha[z] * mv[i] - dbeta[z] * kv[i]
            for j in range(max(0, i - band), min(n, i + band + 1)):
                m = M[i, j]
                c = C[i, j]
                for z in range(ne):
                    rhs[i, z] += m * pu[j, z] + c * pc[j, z]
        for z in range(ne):  # −∂K_z·(u + β·v), element z's four DOFs
            for a in range(4):
                da = dofs[z, a]
                if da < 0:
                    continue
                acc = 0.0
                for b in range(4):
                    db = dofs[z, b]
                    if db >= 0:
                        acc += ke[z, a, b] * (u[s, db] + beta * v[s, db])
                rhs[da, z] -= acc
        for i in range(n):  # L·y = rhs, then Lᵀ·u = y (in place, banded)
            for j in range(max(0, i - band), i):
                lij = L[i, j]
                for z in range(ne):
                    rhs[i, z] -= lij * rhs[j, z]
            d = 1.0 / L[i, i]
            for z in range(ne):
                rhs[i, z] *= d
        for i in range(n - 1, -1, -1):
            for j in range(i + 1, min(n, i + band + 1)):
                lji = L[j, i]
                for z in range(ne):
                    rhs[i, z] -= lji * rhs[j, z]
            d = 1.0 / L[i, i]
            for z in range(ne):
                rhs[i, z] *= d
        for i in range(n):
            for z in range(ne):
                un = rhs[i, z]
                an = k[0] * (un - U[i, z]) - k[2] * V[i, z] - k[3] * A[i, z]
                V[i, z] = V[i, z] + k[6] * A[i, z] + k[7] * an
                A[i, z] = an
                U[i, z] = un
        for c in range(4):
            d = cdofs[s, c]
            if d >= 0:
                for z in range(ne):
                    out[s, z] += cvals[s, c] * U[d, z]
    return out


def excess_sensitivity(beam: Beam, p: PassData, substeps: int = SUBSTEPS, system: BeamSystem | None = None,
                       derivatives: StiffnessDerivatives | None = None,
                       influence: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """ε_p on the window (as :func:`dynamic_excess`) and its derivative with respect to each
    element's θ_z = log EI factor, (n_window,), (n_window, n_e), m/N per log unit.

    Forward mode through the same Newmark solve (:func:`_tangent_kernel`: n_e more right-hand
    sides of the factorised effective matrix), minus ``lf``·∂J/∂θ_z of the FE influence line — the
    exact derivative of the discretised ε (checked against finite differences in
    ``tests/test_bridge_dynamic.py``). ``influence``: (J, ∂J/∂θ) on the span points, to share.
    """
    w: Window = p.window
    on = w.on_span
    system = assemble(beam) if system is None else system
    der = StiffnessDerivatives.of(beam, system) if derivatives is None else derivatives
    xs, lf, dt, x_t, force = _moving_force(beam, p, substeps)
    J, dJ = der.influence(beam, system, xs) if influence is None else influence
    consts = newmark_constants(dt, 0.5, 0.25)
    ce = contact_entries(beam, x_t)
    N = contact_matrix(beam, x_t)
    state = integrate(system.M, system.C, system.K, N * force[:, None], consts)
    u_t = -np.einsum("kd,kd->k", N, state.u)  # compliance sign
    K_eff = effective_stiffness(system.M, system.C, system.K, consts)
    band = BAND
    if np.any(np.triu(K_eff, band + 1)):
        raise ValueError(f"excess_sensitivity: the beam's matrices are wider than {band} off the diagonal")
    k = np.array([consts.a0, consts.a1, consts.a2, consts.a3, consts.a4, consts.a5, consts.a6, consts.a7])
    du_t = -_tangent_kernel(np.linalg.cholesky(K_eff), system.M, system.C, system.K, k, state.u, state.v, der.ke,
                            der.dofs, der.beta, der.dalpha, der.dbeta, ce.dofs, ce.values, band)
    eps = np.zeros(w.n)
    eps[on] = np.interp(xs, x_t, u_t) - lf * J
    deps = np.zeros((w.n, der.ke.shape[0]))
    for z in range(deps.shape[1]):
        deps[on, z] = np.interp(xs, x_t, du_t[:, z])
    deps[on] -= lf[:, None] * dJ
    return eps, deps


def dynamic_deltas(passes: Sequence[WhitenedPass], setup: Setup, params: np.ndarray,
                   cache: dict | None = None) -> dict[str, np.ndarray]:
    """Every pass's whitened dynamic excess at the stiffness ``params`` (θ, then log10 Krot if any).

    ``cache``: a dict kept by the caller; the (unwhitened) excess of a pass at the same parameters
    is then computed once (a live estimator keeps it across updates).
    """
    ne = setup.bridge.n_elements
    key = tuple(np.round(np.asarray(params, dtype=float), 9))
    beam = system = J = None
    out = {}
    for wp in passes:
        ck = (wp.vehicle_id, wp.pass_id, key)
        excess = None if cache is None else cache.get(ck)
        if excess is None:
            if beam is None:
                theta = np.asarray(params[:ne], dtype=float)
                krot = None
                if len(params) > ne:
                    k = 10.0 ** np.asarray(params[ne:], dtype=float)
                    krot = (float(k[0]), float(k[-1]))
                beam = design_beam(setup.bridge, ei_factor=np.exp(theta), krot=krot)
                system = assemble(beam)
                J = influence_line(beam, setup.basis.x)
            excess = dynamic_excess(beam, wp.data, system=system, influence=J)
            if cache is not None:
                cache[ck] = excess
        out[wp.pass_id] = wp.whiten_extra(excess)
    return out


def _params_key(params: np.ndarray) -> tuple:
    return tuple(np.round(np.asarray(params, dtype=float), 9))


def dynamic_sensitivities(passes: Sequence[WhitenedPass], setup: Setup, params: np.ndarray,
                          cache: dict | None = None) -> dict[str, np.ndarray]:
    """Every pass's whitened ∂ε_p/∂θ at the element stiffnesses ``params`` (simply supported),
    pass_id → (n_rows, n_e): the columns D_p of :class:`~cloud.bridge.stiffness.LinearisedDynamicModel`.

    ``cache`` as for :func:`dynamic_deltas` (which then finds ε at ``params`` there too): the
    derivatives are kept through the pass's forward model and band limit
    (:meth:`~cloud.bridge.whitening.Whitener.stage1`), which do not depend on the consensus.
    """
    ne = setup.bridge.n_elements
    key = _params_key(params)
    beam = None
    out = {}
    for wp in passes:
        ck = (wp.vehicle_id, wp.pass_id, key, "dtheta")
        white = None if cache is None else cache.get(ck)
        if white is None:
            if beam is None:
                beam = design_beam(setup.bridge, ei_factor=np.exp(np.asarray(params[:ne], dtype=float)))
                system = assemble(beam)
                der = StiffnessDerivatives.of(beam, system)
                inf = der.influence(beam, system, setup.basis.x)
            excess, d = excess_sensitivity(beam, wp.data, system=system, derivatives=der, influence=inf)
            white = wp.whitener.stage1(d)
            if cache is not None:
                cache[ck] = white
                cache[(wp.vehicle_id, wp.pass_id, key)] = excess
        out[wp.pass_id] = wp.whitener.from_stage1(white)
    return out


def extended_passes(passes: Sequence[WhitenedPass], sensitivities: dict[str, np.ndarray]) -> list[WhitenedPass]:
    """The passes with their load columns extended by their dynamic sensitivities, ``[Ψ_p, D_p]``
    (:class:`~cloud.bridge.stiffness.LinearisedDynamicModel`), for :func:`~cloud.bridge.likelihood.vehicle_stats`."""
    return [dataclasses.replace(wp, Psi=np.hstack([wp.Psi, sensitivities[wp.pass_id]]), raw=None) for wp in passes]
