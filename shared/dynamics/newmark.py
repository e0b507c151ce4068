"""Newmark-beta time integration for linear multi-degree-of-freedom systems (thesis eq. 2.10, B.38)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..jit import kernel

#: The thesis's choice: gamma > 1/2 adds numerical damping of spurious high-frequency modes,
#: which is what keeps the *inverse* recursion stable; beta = (gamma + 1/2)^2 / 4.
DEFAULT_GAMMA = 0.8


class NewmarkConstants(NamedTuple):
    """Integration constants a0..a7 of eq. (2.10) for one time step ``dt`` (s)."""

    dt: float
    gamma: float
    beta: float
    a0: float
    a1: float
    a2: float
    a3: float
    a4: float
    a5: float
    a6: float
    a7: float


def newmark_constants(dt: float, gamma: float = DEFAULT_GAMMA, beta: float | None = None) -> NewmarkConstants:
    """Constants of eq. (2.10); ``beta`` defaults to ``0.25 * (0.5 + gamma)**2``."""
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt: must be a positive finite time step, got {dt!r}")
    if not (math.isfinite(gamma) and gamma >= 0.5):
        raise ValueError(f"gamma: must be >= 0.5 for a stable scheme, got {gamma!r}")
    if beta is None:
        beta = 0.25 * (0.5 + gamma) ** 2
    if not (math.isfinite(beta) and beta > 0):
        raise ValueError(f"beta: must be positive, got {beta!r}")
    return NewmarkConstants(
        dt=dt,
        gamma=gamma,
        beta=beta,
        a0=1.0 / (beta * dt * dt),
        a1=gamma / (beta * dt),
        a2=1.0 / (beta * dt),
        a3=1.0 / (2.0 * beta) - 1.0,
        a4=gamma / beta - 1.0,
        a5=dt / 2.0 * (gamma / beta - 2.0),
        a6=(1.0 - gamma) * dt,
        a7=gamma * dt,
    )


class NewmarkState(NamedTuple):
    """Displacement, velocity and acceleration vectors of all degrees of freedom."""

    u: np.ndarray
    v: np.ndarray
    a: np.ndarray


def effective_stiffness(M: np.ndarray, C: np.ndarray, K: np.ndarray, c: NewmarkConstants) -> np.ndarray:
    """K̄ = K + a0·M + a1·C (eq. 2.28)."""
    return K + c.a0 * M + c.a1 * C


def step(M, C, K, f_next, state: NewmarkState, c: NewmarkConstants, K_eff_inv=None) -> NewmarkState:
    """One Newmark step of M ü + C u̇ + K u = f for a (possibly time-varying) linear system.

    Used where the matrices change from step to step (moving contacts); fixed systems use
    :func:`integrate`, which runs the same recurrence compiled.
    """
    u, v, a = state
    rhs = f_next + M @ (c.a0 * u + c.a2 * v + c.a3 * a) + C @ (c.a1 * u + c.a4 * v + c.a5 * a)
    if K_eff_inv is None:
        u1 = np.linalg.solve(effective_stiffness(M, C, K, c), rhs)
    else:
        u1 = K_eff_inv @ rhs
    a1 = c.a0 * (u1 - u) - c.a2 * v - c.a3 * a
    v1 = v + c.a6 * a + c.a7 * a1
    return NewmarkState(u1, v1, a1)


@kernel
def _integrate_kernel(K_eff_inv, M, C, f, u0, v0, a0_, k):
    """The recurrence of :func:`step` for ``m`` load cases ``f`` (m, n_steps, n) from (m, n) states
    (scalar loops: no temporary per step, the same operations in the same order)."""
    m, n_steps, n = f.shape
    u = np.empty((m, n_steps, n))
    v = np.empty((m, n_steps, n))
    a = np.empty((m, n_steps, n))
    rhs = np.empty(n)
    pu = np.empty(n)
    pc = np.empty(n)
    for b in range(m):
        u[b, 0] = u0[b]
        v[b, 0] = v0[b]
        a[b, 0] = a0_[b]
        for s in range(1, n_steps):
            for j in range(n):
                pu[j] = k[0] * u[b, s - 1, j] + k[2] * v[b, s - 1, j] + k[3] * a[b, s - 1, j]
                pc[j] = k[1] * u[b, s - 1, j] + k[4] * v[b, s - 1, j] + k[5] * a[b, s - 1, j]
            for i in range(n):
                acc = f[b, s, i]
                for j in range(n):
                    acc += M[i, j] * pu[j] + C[i, j] * pc[j]
                rhs[i] = acc
            for i in range(n):
                acc = 0.0
                for j in range(n):
                    acc += K_eff_inv[i, j] * rhs[j]
                u[b, s, i] = acc
            for i in range(n):
                a[b, s, i] = k[0] * (u[b, s, i] - u[b, s - 1, i]) - k[2] * v[b, s - 1, i] - k[3] * a[b, s - 1, i]
                v[b, s, i] = v[b, s - 1, i] + k[6] * a[b, s - 1, i] + k[7] * a[b, s, i]
    return u, v, a


def integrate(
    M: np.ndarray,
    C: np.ndarray,
    K: np.ndarray,
    force: np.ndarray,
    c: NewmarkConstants,
    u0: np.ndarray | None = None,
    v0: np.ndarray | None = None,
) -> NewmarkState:
    """Integrate M ü + C u̇ + K u = f(t) over ``force`` (n_steps, n_dof) sampled every ``c.dt``.

    ``force`` may also be a batch of independent load cases (m, n_steps, n_dof) of one system, with
    ``u0``/``v0`` (n_dof,) shared or (m, n_dof) each: integrated in one compiled call, each case
    exactly as alone. The initial acceleration follows from the equation of motion at t = 0.
    Returns the state histories, each shaped like ``force``.
    """
    M = np.atleast_2d(np.asarray(M, float))
    C = np.atleast_2d(np.asarray(C, float))
    K = np.atleast_2d(np.asarray(K, float))
    f = np.asarray(force, float)
    if f.ndim == 1:
        f = f[:, None]
    n = M.shape[0]
    if f.ndim not in (2, 3) or f.shape[-1] != n or M.shape != (n, n) or C.shape != (n, n) or K.shape != (n, n):
        raise ValueError("integrate: matrices and force must agree on the number of degrees of freedom")
    if not np.all(np.isfinite(f)):
        raise ValueError("integrate: force contains NaN or inf")
    K_eff_inv = np.linalg.inv(effective_stiffness(M, C, K, c))
    k = np.array([c.a0, c.a1, c.a2, c.a3, c.a4, c.a5, c.a6, c.a7])
    if f.ndim == 2:
        u0 = np.zeros(n) if u0 is None else np.asarray(u0, float)
        v0 = np.zeros(n) if v0 is None else np.asarray(v0, float)
        acc0 = np.linalg.solve(M, f[0] - C @ v0 - K @ u0)
        u, v, a = _integrate_kernel(K_eff_inv, M, C, f[None], u0[None], v0[None], acc0[None], k)
        return NewmarkState(u[0], v[0], a[0])
    m = f.shape[0]
    u0 = np.broadcast_to(np.zeros(n) if u0 is None else np.asarray(u0, float), (m, n))
    v0 = np.broadcast_to(np.zeros(n) if v0 is None else np.asarray(v0, float), (m, n))
    acc0 = np.array([np.linalg.solve(M, f[b, 0] - C @ v0[b] - K @ u0[b]) for b in range(m)]).reshape(m, n)
    return NewmarkState(*_integrate_kernel(K_eff_inv, M, C, np.ascontiguousarray(f), np.ascontiguousarray(u0),
                                           np.ascontiguousarray(v0), np.ascontiguousarray(acc0), k))
