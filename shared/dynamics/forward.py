"""Forward simulation of a vehicle driving over a rigid profile (the road model of §2.2, §4.2)."""

from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

from ..vehicles.base import VehicleSystem
from .inverse import InverseState
from .newmark import NewmarkState, integrate, newmark_constants


class RoadResponse(NamedTuple):
    """What a simulated pass produces: truth for tests, channels for the logger."""

    t: np.ndarray  # (n,) s
    x_cg: np.ndarray  # (n,) chainage of the centre of gravity, m
    state: NewmarkState  # each (n, n_dof)
    y: np.ndarray  # (n, n_contacts) surface elevation under each contact, m
    ydot: np.ndarray  # (n, n_contacts) its rate used by the model, m/s
    channels: np.ndarray  # (n, n_channels) in system.channels order

    def initial_inverse_state(self) -> InverseState:
        """The exact state at the first sample, for noise-free round-trip checks."""
        return InverseState(self.state.u[0], self.state.v[0], self.state.a[0], self.y[0], self.ydot[0])


def trapezoid_rate(y: np.ndarray, ydot0: np.ndarray, dt: float) -> np.ndarray:
    """Contact rate consistent with the trapezoidal rule the inverse uses for damped contacts."""
    out = np.empty_like(y)
    out[0] = ydot0
    for k in range(1, len(y)):
        out[k] = 2.0 * (y[k] - y[k - 1]) / dt - out[k - 1]
    return out


def measured_channels(system: VehicleSystem, state: NewmarkState) -> np.ndarray:
    """The logger's channels (acceleration or rate of a DOF) from a state history."""
    cols = [(state.a if ch.kind == "acc" else state.v)[:, ch.dof] for ch in system.channels]
    return np.stack(cols, axis=1)


def simulate_on_profile(
    system: VehicleSystem,
    elevation: Callable[[np.ndarray], np.ndarray],
    slope: Callable[[np.ndarray], np.ndarray],
    x0_m: float,
    speed_mps: float,
    duration_s: float,
    dt: float,
    gamma: float = 0.8,
    beta: float | None = None,
    contact_rate: str = "trapezoid",
) -> RoadResponse:
    """Drive ``system`` at constant speed over a rigid surface and integrate with Newmark-β.

    ``elevation(x)`` and ``slope(x)`` give the surface (m, m/m) at chainage x. The vehicle starts
    in static equilibrium on the surface under it. ``contact_rate``: ``"exact"`` uses ẏ = v·slope;
    ``"trapezoid"`` differentiates the sampled contact elevation with the trapezoidal rule, the
    discretisation the inverse inverts exactly (only matters for damped contacts).
    """
    c = newmark_constants(dt, gamma, beta)
    n = int(round(duration_s / dt)) + 1
    t = np.arange(n) * dt
    x_cg = x0_m + speed_mps * t
    xc = x_cg[:, None] + system.offsets_m[None, :]
    y = elevation(xc.ravel()).reshape(xc.shape)
    ydot_exact = speed_mps * slope(xc.ravel()).reshape(xc.shape)
    if contact_rate == "exact":
        ydot = ydot_exact
    elif contact_rate == "trapezoid":
        ydot = trapezoid_rate(y, ydot_exact[0], dt)
    else:
        raise ValueError(f"contact_rate: expected 'exact' or 'trapezoid', got {contact_rate!r}")
    g = y * system.kc + ydot * system.cc
    force = g @ system.G.T
    u0 = np.linalg.solve(system.K, system.G @ (system.kc * y[0]))
    state = integrate(system.M, system.C, system.K, force, c, u0=u0)
    return RoadResponse(t, x_cg, state, y, ydot, measured_channels(system, state))
