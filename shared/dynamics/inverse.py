"""Inverse Newmark-β: the apparent profile under each contact from the measured body channels.

The thesis derives the inverse step by step for each vehicle (§2.3, App. B). Here one general step
serves every :class:`~shared.vehicles.VehicleSystem`:

1. measured DOFs: the measured acceleration (or the acceleration implied by a measured rate) is
   integrated by Newmark-β into displacement and velocity (eq. 2.11–2.12, 2.19–2.20);
2. the equations of motion at t+Δt are solved *together* for the accelerations of the unmeasured
   DOFs (axles, or a carriage body) and the contact forces g = kc·y + cc·ẏ — the thesis's
   elimination (eq. 2.23–2.25, B.31) is this solve written out for one model;
3. the profile follows from g: y = g/kc for a tyre (eq. 2.16, 2.31), or, where the contact has a
   damper (bogie on the rail), from the first-order ODE kc·y + cc·ẏ = g by the trapezoidal rule.

For fixed vehicle parameters the step is a linear time-invariant map, so it is compiled once into
a state-space recursion  s' = A s + B z,  y = C s + D z  (probing the readable step with unit
vectors) and run by a small numba kernel; the readable step stays as the definition and the test
reference. The recursion's state carries across chunks, so output never depends on chunking.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from ..vehicles.base import VehicleSystem
from .newmark import NewmarkConstants, newmark_constants

# ---------------------------------------------------------------------------------------------
# The readable step (definition and reference)


class InverseState(NamedTuple):
    """Newmark state of every DOF plus the contact ODE state (y, ẏ) of each contact."""

    u: np.ndarray
    v: np.ndarray
    a: np.ndarray
    y: np.ndarray
    ydot: np.ndarray

    @classmethod
    def zeros(cls, system: VehicleSystem) -> "InverseState":
        n, nc = system.n_dof, system.n_contacts
        return cls(np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(nc), np.zeros(nc))

    def as_vector(self) -> np.ndarray:
        return np.concatenate(self)

    @classmethod
    def from_vector(cls, system: VehicleSystem, s: np.ndarray) -> "InverseState":
        n, nc = system.n_dof, system.n_contacts
        return cls(s[:n], s[n : 2 * n], s[2 * n : 3 * n], s[3 * n : 3 * n + nc], s[3 * n + nc :])


def _solve_matrix(system: VehicleSystem, c: NewmarkConstants) -> tuple[np.ndarray, np.ndarray]:
    measured = [ch.dof for ch in system.channels]
    free = [i for i in range(system.n_dof) if i not in measured]
    dt = c.dt
    S = np.hstack(
        [
            system.M[:, free] + c.gamma * dt * system.C[:, free] + c.beta * dt * dt * system.K[:, free],
            -system.G,
        ]
    )
    if S.shape[0] != S.shape[1]:
        raise ValueError(
            f"inverse: {len(free)} unmeasured DOFs + {system.n_contacts} contacts must equal "
            f"{system.n_dof} equations of motion"
        )
    return np.linalg.inv(S), np.array(free, dtype=int)


def inverse_step(
    system: VehicleSystem, c: NewmarkConstants, state: InverseState, z: np.ndarray, _solve=None
) -> tuple[InverseState, np.ndarray]:
    """Advance one sample: ``z`` holds the measured channels at t+Δt; returns (state, y at t+Δt)."""
    S_inv, free = _solve if _solve is not None else _solve_matrix(system, c)
    dt, gamma, beta = c.dt, c.gamma, c.beta
    u, v, a = state.u.copy(), state.v.copy(), state.a.copy()
    # Predictors: the parts of u, v at t+Δt that do not depend on the new acceleration.
    u_pred = state.u + dt * state.v + dt * dt * (0.5 - beta) * state.a
    v_pred = state.v + dt * (1.0 - gamma) * state.a
    for ch, value in zip(system.channels, z):
        i = ch.dof
        if ch.kind == "acc":
            a[i] = value
        else:  # measured rate: the acceleration that Newmark's velocity update implies
            a[i] = (value - v_pred[i]) / (gamma * dt)
        u[i] = u_pred[i] + beta * dt * dt * a[i]
        v[i] = v_pred[i] + gamma * dt * a[i]
    measured = np.array([ch.dof for ch in system.channels], dtype=int)
    known = (
        system.M[:, measured] @ a[measured]
        + system.C[:, measured] @ v[measured]
        + system.K[:, measured] @ u[measured]
        + system.C[:, free] @ v_pred[free]
        + system.K[:, free] @ u_pred[free]
    )
    x = -(S_inv @ known)
    a[free] = x[: len(free)]
    u[free] = u_pred[free] + beta * dt * dt * a[free]
    v[free] = v_pred[free] + gamma * dt * a[free]
    g = x[len(free) :]
    y = np.empty(system.n_contacts)
    ydot = np.zeros(system.n_contacts)
    for i in range(system.n_contacts):
        kc, cc = system.kc[i], system.cc[i]
        if cc == 0.0:
            y[i] = g[i] / kc
        else:  # kc·y + cc·ẏ = g, trapezoidal rule (A-stable, second order)
            y[i] = (g[i] + cc * (2.0 * state.y[i] / dt + state.ydot[i])) / (kc + 2.0 * cc / dt)
            ydot[i] = 2.0 * (y[i] - state.y[i]) / dt - state.ydot[i]
    return InverseState(u, v, a, y, ydot), y




# ---------------------------------------------------------------------------------------------
# Compiled form


class InverseModel(NamedTuple):
    """The inverse of one vehicle at one time step as a state-space recursion.

    ``keep`` indexes the full :class:`InverseState` vector entries that the recursion needs.
    ``n_warmup`` is the number of samples after which a wrong initial state has decayed to 1e-4
    of its effect, except for the integrators' offset and drift (removed by drift control).
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    keep: np.ndarray
    n_warmup: int
    system: VehicleSystem
    constants: NewmarkConstants


def build_inverse(system: VehicleSystem, dt: float, gamma: float = 0.8, beta: float | None = None) -> InverseModel:
    """Compile the inverse step of ``system`` at time step ``dt`` (s) into state-space matrices."""
    c = newmark_constants(dt, gamma, beta)
    solve = _solve_matrix(system, c)
    n_state = 3 * system.n_dof + 2 * system.n_contacts
    n_in, n_out = len(system.channels), system.n_contacts
    A = np.zeros((n_state, n_state))
    B = np.zeros((n_state, n_in))
    C = np.zeros((n_out, n_state))
    D = np.zeros((n_out, n_in))
    zero_state, zero_in = np.zeros(n_state), np.zeros(n_in)
    for j in range(n_state):
        e = zero_state.copy()
        e[j] = 1.0
        s1, y = inverse_step(system, c, InverseState.from_vector(system, e), zero_in, solve)
        A[:, j], C[:, j] = s1.as_vector(), y
    for m in range(n_in):
        e = zero_in.copy()
        e[m] = 1.0
        s1, y = inverse_step(system, c, InverseState.from_vector(system, zero_state), e, solve)
        B[:, m], D[:, m] = s1.as_vector(), y
    # Drop state entries nothing reads (e.g. a tyre contact's ẏ), repeatedly.
    keep = np.arange(n_state)
    while True:
        used = np.any(A[np.ix_(keep, keep)] != 0, axis=0) | np.any(C[:, keep] != 0, axis=0)
        if used.all():
            break
        keep = keep[used]
    A, B, C = A[np.ix_(keep, keep)], B[keep], C[:, keep]
    eig = np.abs(np.linalg.eigvals(A)) if len(keep) else np.zeros(0)
    decaying = eig[eig < 1.0 - 1e-6]
    rho = float(decaying.max()) if decaying.size else 0.0
    n_warmup = 1 if rho <= 1e-12 else int(math.ceil(math.log(1e-4) / math.log(rho)))
    return InverseModel(A, B, C, D, keep, max(n_warmup, 1), system, c)


@njit(cache=True, fastmath=True)
def _run(A, B, C, D, s, z, y):
    """s' = A s + B z_k ; y_k = C s + D z_k, over all samples k (state ``s`` updated in place)."""
    n_samples, n_in = z.shape
    n = s.shape[0]
    n_out = y.shape[1]
    s_new = np.empty(n)
    for k in range(n_samples):
        for o in range(n_out):
            acc = 0.0
            for j in range(n):
                acc += C[o, j] * s[j]
            for m in range(n_in):
                acc += D[o, m] * z[k, m]
            y[k, o] = acc
        for i in range(n):
            acc = 0.0
            for j in range(n):
                acc += A[i, j] * s[j]
            for m in range(n_in):
                acc += B[i, m] * z[k, m]
            s_new[i] = acc
        for i in range(n):
            s[i] = s_new[i]


@njit(cache=True, fastmath=True)
def _run_bank(A, B, C, D, s, z, y):
    """Many streams at once, streams innermost so the loop vectorises.

    A (n, n, S), B (n, m, S), C (o, n, S), D (o, m, S), s (n, S), z (K, m, S), y (K, o, S).
    """
    n_samples, n_in, n_streams = z.shape
    n = s.shape[0]
    n_out = y.shape[1]
    s_new = np.empty((n, n_streams))
    for k in range(n_samples):
        for o in range(n_out):
            for q in range(n_streams):
                y[k, o, q] = 0.0
            for j in range(n):
                for q in range(n_streams):
                    y[k, o, q] += C[o, j, q] * s[j, q]
            for m in range(n_in):
                for q in range(n_streams):
                    y[k, o, q] += D[o, m, q] * z[k, m, q]
        for i in range(n):
            for q in range(n_streams):
                s_new[i, q] = 0.0
            for j in range(n):
                for q in range(n_streams):
                    s_new[i, q] += A[i, j, q] * s[j, q]
            for m in range(n_in):
                for q in range(n_streams):
                    s_new[i, q] += B[i, m, q] * z[k, m, q]
        for i in range(n):
            for q in range(n_streams):
                s[i, q] = s_new[i, q]


class InverseStream:
    """Streaming apparent profile of one vehicle: feed chunks of measured channels, get the AP.

    ``update(z)`` takes an array (n_samples, n_channels) in ``system.channels`` order and returns
    (n_samples, n_contacts): the apparent profile under each contact, m. The first
    ``model.n_warmup`` samples are unreliable when the initial state was unknown (see
    :attr:`reliable_from`).

    With ``initial`` (the full state at the first sample, e.g. from a simulation) the output is
    exact from the start; without it the state starts at rest with the first measured values,
    which is all a logger switched on while driving knows.
    """

    def __init__(self, model: InverseModel, initial: InverseState | None = None):
        self.model = model
        self._initial = initial
        self._s = np.zeros(len(model.keep))
        self.n_seen = 0

    @property
    def reliable_from(self) -> int:
        """Index of the first sample not affected by the unknown initial state."""
        return 0 if self._initial is not None else self.model.n_warmup

    def _start(self, z0: np.ndarray) -> np.ndarray:
        system = self.model.system
        if self._initial is not None:
            state = self._initial
        else:
            state = InverseState.zeros(system)
            for ch, value in zip(system.channels, z0):
                (state.a if ch.kind == "acc" else state.v)[ch.dof] = value
        self._s = state.as_vector()[self.model.keep].copy()
        return np.array(state.y, dtype=float)

    def update(self, z: np.ndarray) -> np.ndarray:
        z = np.ascontiguousarray(z, dtype=np.float64)
        if z.ndim == 1:
            z = z[:, None]
        if z.shape[1] != len(self.model.system.channels):
            raise ValueError(f"expected {len(self.model.system.channels)} channels, got {z.shape[1]}")
        out = np.empty((z.shape[0], self.model.system.n_contacts))
        if z.shape[0] == 0:
            return out
        start = 0
        if self.n_seen == 0:
            out[0] = self._start(z[0])
            start = 1
        m = self.model
        _run(m.A, m.B, m.C, m.D, self._s, z[start:], out[start:])
        self.n_seen += z.shape[0]
        return out


def apparent_profile(
    system: VehicleSystem,
    channels: np.ndarray,
    dt: float,
    initial: InverseState | None = None,
    gamma: float = 0.8,
    beta: float | None = None,
) -> np.ndarray:
    """The whole-record convenience: AP (n_samples, n_contacts) from channels (n_samples, n_channels)."""
    return InverseStream(build_inverse(system, dt, gamma, beta), initial).update(channels)


class InverseBank:
    """Many vehicles of one model processed together (interleaved across streams, one kernel call).

    Every stream must have the same model (same state size); parameters may differ.
    ``update(z)`` takes (n_samples, n_channels, n_streams) and returns (n_samples, n_contacts,
    n_streams). Streams start at rest like :class:`InverseStream` without ``initial``.
    """

    def __init__(self, models: list[InverseModel]):
        if not models:
            raise ValueError("InverseBank: needs at least one model")
        n = len(models[0].keep)
        if any(len(m.keep) != n or not np.array_equal(m.keep, models[0].keep) for m in models):
            raise ValueError("InverseBank: all streams must share one vehicle model")
        self.models = models
        self.A = np.ascontiguousarray(np.stack([m.A for m in models], axis=-1))
        self.B = np.ascontiguousarray(np.stack([m.B for m in models], axis=-1))
        self.C = np.ascontiguousarray(np.stack([m.C for m in models], axis=-1))
        self.D = np.ascontiguousarray(np.stack([m.D for m in models], axis=-1))
        self._s = np.zeros((n, len(models)))
        self._streams = [InverseStream(m) for m in models]
        self.n_seen = 0

    def update(self, z: np.ndarray) -> np.ndarray:
        z = np.ascontiguousarray(z, dtype=np.float64)
        n_out = self.models[0].system.n_contacts
        out = np.empty((z.shape[0], n_out, z.shape[2]))
        if z.shape[0] == 0:
            return out
        start = 0
        if self.n_seen == 0:
            for q, stream in enumerate(self._streams):
                out[0, :, q] = stream._start(z[0, :, q])
                self._s[:, q] = stream._s
            start = 1
        _run_bank(self.A, self.B, self.C, self.D, self._s, z[start:], out[start:])
        self.n_seen += z.shape[0]
        return out
