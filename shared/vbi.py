"""Forward vehicle–bridge interaction: a vehicle over approach road, an FE bridge and exit road.

The vehicle's contacts ride on the surface ``r(x)`` plus, on the span, the beam's deflection. While
any contact is on the span, vehicle and beam are integrated as one coupled, time-varying linear
system with Newmark-β (the thesis's VBI of §4.2); elsewhere the vehicle runs on the rigid road.
Static wheel loads act on the beam, so the deflection under each wheel includes the weight's.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

from .dynamics.forward import measured_channels, trapezoid_rate
from .dynamics.newmark import NewmarkState, integrate, newmark_constants, step
from .fe.beam import Beam, assemble, contact_entries, hermite_shape
from .vehicles.base import VehicleSystem


class VbiResponse(NamedTuple):
    """Truth and channels of one pass. ``ap`` = surface + deflection under each contact (m)."""

    t: np.ndarray  # (n,) s
    x_cg: np.ndarray  # (n,) m
    state: NewmarkState  # vehicle state histories (n, n_dof)
    ap: np.ndarray  # (n, n_contacts) apparent profile under each contact, m (up positive)
    deflection: np.ndarray  # (n, n_contacts) beam deflection under each contact, m (up positive)
    channels: np.ndarray  # (n, n_channels)


def simulate_vbi(
    system: VehicleSystem,
    elevation: Callable[[np.ndarray], np.ndarray],
    slope: Callable[[np.ndarray], np.ndarray],
    x0_m: float,
    speed_mps: float,
    duration_s: float,
    dt: float,
    beam: Beam | None = None,
    bridge_start_m: float = 0.0,
    gamma: float = 0.8,
    beta: float | None = None,
) -> VbiResponse:
    """Simulate one pass at constant speed; ``beam`` None means a rigid road throughout.

    ``elevation(x)``/``slope(x)`` describe the surface (the deck's own profile included) in route
    chainage. Contact damping rates use the exact rate of the point under the contact,
    ẏ = v·slope + ∂w/∂t + v·∂w/∂x (surface, beam velocity, and the convective term of moving over
    the deflected deck), so the apparent profile an inverse recovers is surface + deflection.
    The vehicle starts in static equilibrium: on the rigid surface, or, if a contact starts on the
    span, together with the loaded beam.
    """
    c = newmark_constants(dt, gamma, beta)
    n = int(round(duration_s / dt)) + 1
    t = np.arange(n) * dt
    x_cg = x0_m + speed_mps * t
    xc = x_cg[:, None] + system.offsets_m[None, :]
    r = elevation(xc.ravel()).reshape(xc.shape)
    rdot = speed_mps * slope(xc.ravel()).reshape(xc.shape)
    nv, nc = system.n_dof, system.n_contacts
    Mv, Cv, Kv, G, kc, cc = system.M, system.C, system.K, system.G, system.kc, system.cc
    weights = system.static_contact_forces()

    if beam is None:
        nb = 0
        Mb = Cb = Kb = np.zeros((0, 0))
    else:
        bs = assemble(beam)
        Mb, Cb, Kb = bs.M, bs.C, bs.K
        nb = Mb.shape[0]
    span = beam.span_m if beam is not None else 0.0

    g_road = kc * r + cc * rdot  # (n, nc) contact forcing from the rigid surface alone
    u = np.zeros((n, nv))
    v = np.zeros((n, nv))
    a = np.zeros((n, nv))
    defl = np.zeros((n, nc))
    if beam is not None:
        xloc = xc - bridge_start_m
        on_span = (xloc >= 0.0) & (xloc <= span)
        active = np.flatnonzero(on_span.any(axis=1))
    else:
        active = np.zeros(0, dtype=int)
    k1, k2 = (int(active[0]), int(active[-1])) if active.size else (n, n)

    # Rigid road before the span: the compiled fixed-system integrator.
    q0 = np.linalg.solve(Kv, G @ (kc * r[0]))
    head = integrate(Mv, Cv, Kv, g_road[: max(k1, 1)] @ G.T, c, u0=q0)
    m = min(k1, n) if k1 < n else n
    u[:m], v[:m], a[:m] = head.u[:m], head.v[:m], head.a[:m]

    if active.size:
        M = np.zeros((nv + nb, nv + nb))
        M[:nv, :nv] = Mv
        M[nv:, nv:] = Mb

        # Contact rows of every coupled sample at once (one vectorised evaluation instead of one
        # per sample and contact, which would dominate a pass's cost).
        rows_N, rows_Nx = _contact_rows(beam, xloc[k1 : k2 + 1])

        def coupled(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
            """C, K, f of vehicle + beam at sample k, and the contact rows N (nb, nc)."""
            N = rows_N[k - k1]
            Nx = rows_Nx[k - k1]  # ∂N/∂x: the contact moves over the deflected deck
            # Force of contact i on the vehicle (up): kc·(y − Gᵀq) + cc·(ẏ − Gᵀq̇), with
            # y = r + Nᵀu_b and ẏ = ṙ + Nᵀu̇_b + v·Nxᵀu_b; the beam feels −(W + that force).
            kn = kc[:, None] * N.T + speed_mps * cc[:, None] * Nx.T  # (nc, nb): contact force per u_b
            Kf = np.zeros_like(M)
            Cf = np.zeros_like(M)
            Kf[:nv, :nv] = Kv
            Cf[:nv, :nv] = Cv
            Kf[nv:, nv:] = Kb + N @ kn
            Cf[nv:, nv:] = Cb + N @ (cc[:, None] * N.T)
            Kf[:nv, nv:] = -G @ kn
            Kf[nv:, :nv] = -N @ (kc[:, None] * G.T)
            Cf[:nv, nv:] = -G @ (cc[:, None] * N.T)
            Cf[nv:, :nv] = Cf[:nv, nv:].T
            f = np.concatenate([G @ g_road[k], -N @ (weights + g_road[k])])
            return Cf, Kf, f, N

        if k1 == 0:  # starts on the span: static equilibrium of vehicle and loaded beam together
            _, Kf, f, _ = coupled(0)
            state = NewmarkState(np.linalg.solve(Kf, f), np.zeros(nv + nb), np.zeros(nv + nb))
        else:  # the beam is unloaded and at rest until the first contact reaches it
            kp = k1 - 1
            state = NewmarkState(
                np.concatenate([u[kp], np.zeros(nb)]), np.concatenate([v[kp], np.zeros(nb)]),
                np.concatenate([a[kp], np.zeros(nb)]),
            )
        for k in range(k1, k2 + 1):
            Cf, Kf, f, N = coupled(k)
            if k > 0:
                state = step(M, Cf, Kf, f, state, c)
            u[k], v[k], a[k] = state.u[:nv], state.v[:nv], state.a[:nv]
            defl[k] = N.T @ state.u[nv:]
        # Rigid road after the span, continuing from the coupled state. integrate() derives the
        # first acceleration from force[0]; choosing force[0] = M a + C v + K u hands it the
        # coupled acceleration instead of the rigid-road one, so Newmark's recurrence is unbroken.
        if k2 + 1 < n:
            force = g_road[k2:] @ G.T
            force[0] = Mv @ a[k2] + Cv @ v[k2] + Kv @ u[k2]
            tail = integrate(Mv, Cv, Kv, force, c, u0=u[k2], v0=v[k2])
            u[k2:], v[k2:], a[k2:] = tail.u, tail.v, tail.a
    vstate = NewmarkState(u, v, a)
    return VbiResponse(t, x_cg, vstate, r + defl, defl, measured_channels(system, vstate))


def _contact_rows(beam: Beam, x_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Contact rows N(x) and their chainage derivatives ∂N/∂x (1/m) on the beam's free DOFs, for
    chainages ``x_m`` (n, n_contacts) from the left support; each (n, n_dof, n_contacts), zero for a
    contact off the span."""
    x = np.asarray(x_m, dtype=float)
    entries = contact_entries(beam, x.ravel())
    n, le = beam.n_elements, beam.element_length_m
    e = np.clip(np.floor(x.ravel() / le).astype(np.int64), 0, n - 1)  # as contact_entries: x = span is in the last element
    xi = np.clip(x.ravel() / le - e, 0.0, 1.0)
    slope = hermite_shape(xi, le, derivative=1)
    keep = entries.dofs >= 0
    rows = np.broadcast_to(np.arange(x.size)[:, None], keep.shape)
    N = np.zeros((x.size, 2 * n))
    Nx = np.zeros((x.size, 2 * n))
    N[rows[keep], entries.dofs[keep]] = entries.values[keep]
    Nx[rows[keep], entries.dofs[keep]] = slope[keep]
    shape = x.shape + (2 * n,)
    return np.moveaxis(N.reshape(shape), -1, -2), np.moveaxis(Nx.reshape(shape), -1, -2)


__all__ = ["VbiResponse", "simulate_vbi", "trapezoid_rate"]
