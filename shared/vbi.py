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
from .fe.beam import Beam, assemble, contact_vector
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
    chainage. Contact damping rates use the exact ẏ = v·slope plus the beam's velocity.
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
        kp = max(k1 - 1, 0)
        state = NewmarkState(
            np.concatenate([u[kp], np.zeros(nb)]), np.concatenate([v[kp], np.zeros(nb)]),
            np.concatenate([a[kp], np.zeros(nb)]),
        )
        for k in range(k1, k2 + 1):
            N = np.zeros((nb, nc))
            for i in np.flatnonzero(on_span[k]):
                N[:, i] = contact_vector(beam, float(xloc[k, i]))
            Kf = np.zeros_like(M)
            Cf = np.zeros_like(M)
            Kf[:nv, :nv] = Kv
            Cf[:nv, :nv] = Cv
            Kf[nv:, nv:] = Kb + N @ (kc[:, None] * N.T)
            Cf[nv:, nv:] = Cb + N @ (cc[:, None] * N.T)
            Kf[:nv, nv:] = -G @ (kc[:, None] * N.T)
            Kf[nv:, :nv] = Kf[:nv, nv:].T
            Cf[:nv, nv:] = -G @ (cc[:, None] * N.T)
            Cf[nv:, :nv] = Cf[:nv, nv:].T
            f = np.concatenate([G @ g_road[k], -N @ (weights + g_road[k])])
            if k > 0:
                state = step(M, Cf, Kf, f, state, c)
            u[k], v[k], a[k] = state.u[:nv], state.v[:nv], state.a[:nv]
            defl[k] = N.T @ state.u[nv:]
        # Rigid road after the span, continuing from the coupled state.
        if k2 + 1 < n:
            tail = integrate(Mv, Cv, Kv, g_road[k2:] @ G.T, c, u0=u[k2], v0=v[k2])
            u[k2:], v[k2:], a[k2 + 1 :] = tail.u, tail.v, tail.a[1:]
    vstate = NewmarkState(u, v, a)
    return VbiResponse(t, x_cg, vstate, r + defl, defl, measured_channels(system, vstate))


__all__ = ["VbiResponse", "simulate_vbi", "trapezoid_rate"]
