"""Vehicle (and modal bridge) as one continuous-time ODE, integrated by classical RK4 at a fine fixed step.

State z = [q, q̇, η, η̇]: the vehicle's DOFs and the bridge's modal coordinates. With y the
surface r(x) plus the deck's deflection w(x) = Σ φ_r(x) η_r under each tyre,

    M q̈ + C q̇ + K q = G (kc ⊙ y)
    η̈_r + 2 ζ ω_r η̇_r + ω_r² η_r = −Σ_i φ_r(x_i) (W_i + kc_i (y_i − (Gᵀq)_i))

(W the static tyre loads: the deck carries the weight as well as the dynamic force). The
vehicle moves at v(t) = v0 (1 + a sin(2πt/T + ψ)), a slow speed wobble, never exactly constant.
The tyres are point followers without damping (the models' contact damping is zero).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from shared.jit import kernel

from .modal_beam import N_SINES, ModalBeam
from .vehicles import Eom


class Drive(NamedTuple):
    """How the vehicle moves and what it drives on (all floats are SI)."""

    surface: np.ndarray  # elevation on a regular grid, deck window applied, m
    surface_x0: float  # chainage of surface[0], m
    surface_dx: float  # grid spacing, m
    x0: float  # chainage of the centre of gravity at t = 0, m
    v0: float  # mean speed, m/s
    wobble: float  # relative amplitude a of the speed wobble
    wobble_period_s: float
    wobble_phase: float


class OdeModel(NamedTuple):
    """Everything the kernel needs, packed (numba takes a NamedTuple of arrays and scalars)."""

    mk: np.ndarray  # M⁻¹K (nv, nv)
    mc: np.ndarray  # M⁻¹C (nv, nv)
    mg: np.ndarray  # M⁻¹ G diag(kc) (nv, nc)
    gt: np.ndarray  # Gᵀ (nc, nv)
    kc: np.ndarray  # (nc,)
    weights: np.ndarray  # (nc,) N
    offsets: np.ndarray  # (nc,) m
    surface: np.ndarray
    surface_x0: float
    surface_dx: float
    x0: float
    v0: float
    wobble: float
    wobble_period_s: float
    wobble_phase: float
    bridge_start: float
    span: float  # 0: no bridge
    omega: np.ndarray  # (nm,) rad/s
    zeta: float
    vectors: np.ndarray  # (nb, nm)
    cubics: bool  # basis carries the two end-moment cubics after the sines


def position(drive: Drive | OdeModel, t: np.ndarray) -> np.ndarray:
    """Chainage of the centre of gravity at times ``t`` (s)."""
    w = 2 * np.pi / drive.wobble_period_s
    return drive.x0 + drive.v0 * t + drive.v0 * drive.wobble / w * (
        np.cos(drive.wobble_phase) - np.cos(w * t + drive.wobble_phase))


def speed(drive: Drive | OdeModel, t: np.ndarray) -> np.ndarray:
    """True speed (m/s) at times ``t``."""
    return drive.v0 * (1.0 + drive.wobble * np.sin(2 * np.pi / drive.wobble_period_s * t + drive.wobble_phase))


def ode_model(eom: Eom, drive: Drive, beam: ModalBeam | None, bridge_start_m: float) -> OdeModel:
    minv = np.diag(1.0 / np.diag(eom.M))
    nb = N_SINES + 2
    return OdeModel(
        mk=minv @ eom.K, mc=minv @ eom.C, mg=minv @ eom.G @ np.diag(eom.kc), gt=np.ascontiguousarray(eom.G.T),
        kc=eom.kc.astype(float), weights=eom.static_loads_n.astype(float), offsets=eom.offsets_m.astype(float),
        surface=np.ascontiguousarray(drive.surface, dtype=float), surface_x0=float(drive.surface_x0),
        surface_dx=float(drive.surface_dx), x0=float(drive.x0), v0=float(drive.v0), wobble=float(drive.wobble),
        wobble_period_s=float(drive.wobble_period_s), wobble_phase=float(drive.wobble_phase),
        bridge_start=float(bridge_start_m), span=0.0 if beam is None else float(beam.spec.span_m),
        omega=np.zeros(0) if beam is None else beam.omega.astype(float),
        zeta=0.0 if beam is None else float(beam.spec.damping_ratio),
        vectors=np.zeros((nb, 0)) if beam is None else np.ascontiguousarray(beam.vectors, dtype=float),
        cubics=beam is not None and beam.spec.krot_nm_per_rad is not None,
    )


@kernel
def _x_of_t(m, t):
    w = 2 * np.pi / m.wobble_period_s
    return m.x0 + m.v0 * t + m.v0 * m.wobble / w * (np.cos(m.wobble_phase) - np.cos(w * t + m.wobble_phase))


@kernel
def _surface_at(m, x):
    s = (x - m.surface_x0) / m.surface_dx
    i = int(np.floor(s))
    n = m.surface.size
    if i < 0:
        return m.surface[0]
    if i >= n - 1:
        return m.surface[n - 1]
    f = s - i
    return (1.0 - f) * m.surface[i] + f * m.surface[i + 1]


@kernel
def _modes_at(m, s, out):
    """Kept modes at s (m from the left support) into ``out`` (nm,); zero off the span."""
    nm = m.omega.size
    for r in range(nm):
        out[r] = 0.0
    if m.span <= 0.0 or s < 0.0 or s > m.span:
        return
    th = np.pi * s / m.span
    c2 = 2.0 * np.cos(th)
    prev, cur = 0.0, np.sin(th)  # sin(0·θ), sin(1·θ): the Chebyshev recurrence gives sin(jθ)
    for j in range(N_SINES):
        for r in range(nm):
            out[r] += cur * m.vectors[j, r]
        prev, cur = cur, c2 * cur - prev
    if m.cubics:
        u = s / m.span
        b1 = u * (1 - u) * (1 - u)
        b2 = u * u * (1 - u)
        for r in range(nm):
            out[r] += b1 * m.vectors[N_SINES, r] + b2 * m.vectors[N_SINES + 1, r]


@kernel
def _rhs(m, t, z, dz, phi):
    nv = m.mk.shape[0]
    nc = m.kc.size
    nm = m.omega.size
    xcg = _x_of_t(m, t)
    for i in range(nv):
        dz[i] = z[nv + i]
        acc = 0.0
        for j in range(nv):
            acc -= m.mk[i, j] * z[j] + m.mc[i, j] * z[nv + j]
        dz[nv + i] = acc
    for r in range(nm):
        dz[2 * nv + r] = z[2 * nv + nm + r]
        dz[2 * nv + nm + r] = -2.0 * m.zeta * m.omega[r] * z[2 * nv + nm + r] - m.omega[r] ** 2 * z[2 * nv + r]
    for c in range(nc):
        x = xcg + m.offsets[c]
        y = _surface_at(m, x)
        if nm > 0:
            _modes_at(m, x - m.bridge_start, phi)
            for r in range(nm):
                y += phi[r] * z[2 * nv + r]
        for i in range(nv):
            dz[nv + i] += m.mg[i, c] * y
        if nm > 0:
            rel = y
            for j in range(nv):
                rel -= m.gt[c, j] * z[j]
            load = m.weights[c] + m.kc[c] * rel  # force of the tyre on the deck, down
            for r in range(nm):
                dz[2 * nv + nm + r] -= phi[r] * load


@kernel
def _rk4(m, z0, h, n_steps):
    n = z0.size
    nv = m.mk.shape[0]
    states = np.empty((n_steps + 1, n))
    accs = np.empty((n_steps + 1, nv))
    phi = np.empty(m.omega.size)
    z = z0.copy()
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    tmp = np.empty(n)
    for s in range(n_steps + 1):
        t = s * h
        states[s] = z
        _rhs(m, t, z, k1, phi)
        accs[s] = k1[nv:2 * nv]
        if s == n_steps:
            break
        for i in range(n):
            tmp[i] = z[i] + 0.5 * h * k1[i]
        _rhs(m, t + 0.5 * h, tmp, k2, phi)
        for i in range(n):
            tmp[i] = z[i] + 0.5 * h * k2[i]
        _rhs(m, t + 0.5 * h, tmp, k3, phi)
        for i in range(n):
            tmp[i] = z[i] + h * k3[i]
        _rhs(m, t + h, tmp, k4, phi)
        for i in range(n):
            z[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
    return states, accs


class Trajectory(NamedTuple):
    t: np.ndarray  # (n,) s
    x_cg: np.ndarray  # (n,) m
    q: np.ndarray  # (n, nv) vehicle displacements
    qdot: np.ndarray  # (n, nv)
    qddot: np.ndarray  # (n, nv)
    eta: np.ndarray  # (n, nm) modal coordinates of the bridge


def integrate(eom: Eom, drive: Drive, duration_s: float, step_s: float, beam: ModalBeam | None = None,
              bridge_start_m: float = 0.0) -> Trajectory:
    """Integrate from static equilibrium on the rigid surface at t = 0 (the deck unloaded and at
    rest: ``drive.x0`` must put every tyre before the span) for ``duration_s`` at step ``step_s``."""
    m = ode_model(eom, drive, beam, bridge_start_m)
    if beam is not None and np.any(drive.x0 + eom.offsets_m >= bridge_start_m):
        raise ValueError("integrate: every tyre must start before the bridge (the deck starts at rest)")
    y0 = np.interp(drive.x0 + eom.offsets_m, drive.surface_x0 + drive.surface_dx * np.arange(drive.surface.size),
                   drive.surface)
    q0 = np.linalg.solve(eom.K, eom.G @ (eom.kc * y0))
    nv, nm = eom.M.shape[0], m.omega.size
    z0 = np.concatenate([q0, np.zeros(nv + 2 * nm)])
    n_steps = int(np.ceil(duration_s / step_s))
    states, accs = _rk4(m, z0, float(step_s), n_steps)
    t = np.arange(n_steps + 1) * step_s
    return Trajectory(t, position(drive, t), states[:, :nv], states[:, nv:2 * nv], accs,
                      states[:, 2 * nv:2 * nv + nm])
