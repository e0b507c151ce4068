"""The forward model: a vehicle driven by the profile under its contacts (the road model of §2.2, §4.2).

One model serves every caller: the vehicle's linear system (:class:`~shared.vehicles.VehicleSystem`)
integrated by Newmark-β from static equilibrium on the first sample, damped contacts driven by the
contact rate of the trapezoidal rule. That is the discretisation :mod:`shared.dynamics.inverse`
inverts exactly, so :func:`channels_from_ap` followed by the inverse under the same constants returns
the AP it started from: what the cloud relies on wherever it rebuilds a vehicle's channels from an AP.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

from ..jit import kernel
from ..vehicles.base import VehicleSystem
from .inverse import InverseState
from .newmark import NewmarkConstants, NewmarkState, integrate, newmark_constants


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


@kernel
def _trapezoid_kernel(y, ydot0, dt, out):
    m, n, nc = y.shape
    for b in range(m):
        for j in range(nc):
            out[b, 0, j] = ydot0[b, j]
        for k in range(1, n):
            for j in range(nc):
                out[b, k, j] = 2.0 * (y[b, k, j] - y[b, k - 1, j]) / dt - out[b, k - 1, j]


def trapezoid_rate(y: np.ndarray, ydot0: np.ndarray | float, dt: float) -> np.ndarray:
    """Contact rate consistent with the trapezoidal rule the inverse uses for damped contacts.

    ẏ_k = 2 (y_k − y_{k−1}) / Δt − ẏ_{k−1} from ``ydot0``; ``y`` (n,), (n, n_contacts) or a batch
    (m, n, n_contacts) in m, the rate shaped alike in m/s.
    """
    y = np.asarray(y, dtype=float)
    y3 = y.reshape(1, y.shape[0], -1) if y.ndim < 3 else y
    ydot0 = np.broadcast_to(np.asarray(ydot0, dtype=float), (y3.shape[0], y3.shape[2]))
    out = np.empty(y3.shape)
    _trapezoid_kernel(np.ascontiguousarray(y3), np.ascontiguousarray(ydot0), float(dt), out)
    return out.reshape(y.shape)


def measured_channels(system: VehicleSystem, state: NewmarkState) -> np.ndarray:
    """The logger's channels (acceleration or rate of a DOF) from a state history.

    ``state`` arrays (n, n_dof) or a batch (m, n, n_dof); the channels (…, n, n_channels) in
    ``system.channels`` order.
    """
    cols = [(state.a if ch.kind == "acc" else state.v)[..., ch.dof] for ch in system.channels]
    return np.stack(cols, axis=-1)


def static_equilibrium(system: VehicleSystem, y0: np.ndarray) -> np.ndarray:
    """Displacements (n_dof,) of the vehicle at rest on contact elevations ``y0`` (n_contacts,) m;
    for a batch ``y0`` (m, n_contacts), (m, n_dof), each case solved as alone."""
    y0 = np.asarray(y0, dtype=float)
    if y0.ndim == 1:
        return np.linalg.solve(system.K, system.G @ (system.kc * y0))
    return np.array([np.linalg.solve(system.K, system.G @ (system.kc * row)) for row in y0]).reshape(
        len(y0), system.n_dof)


def _drive(system: VehicleSystem, y: np.ndarray, ydot: np.ndarray | None, c: NewmarkConstants,
           u0: np.ndarray | None, v0: np.ndarray | None) -> NewmarkState:
    """Integrate the vehicle under contact elevations ``y`` and rates ``ydot`` (None: undamped
    contacts, no rate term), from static equilibrium on ``y``'s first sample unless ``u0`` is given."""
    g = y * system.kc
    if ydot is not None:
        g = g + ydot * system.cc
    force = g @ system.G.T
    if u0 is None:
        u0 = static_equilibrium(system, y[..., 0, :])
    return integrate(system.M, system.C, system.K, force, c, u0=u0, v0=v0)


def ap_response(system: VehicleSystem, ap: np.ndarray, c: NewmarkConstants, u0: np.ndarray | None = None,
                v0: np.ndarray | None = None) -> NewmarkState:
    """The vehicle's state history driven by the profile ``ap`` under its contacts.

    Parameters
    ----------
    system : VehicleSystem
    ap : ndarray
        (n, n_contacts) contact elevation, m (up positive), one row per step ``c.dt``; or a batch of
        independent profiles (m, n, n_contacts), each integrated exactly as alone.
    c : NewmarkConstants
        The scheme (step, γ, β); the inverse that is to return ``ap`` must use the same.
    u0, v0 : ndarray, optional
        Start state (n_dof,) m and m/s. Default: at rest in static equilibrium on ``ap``'s first row.

    Returns
    -------
    NewmarkState
        u, v, a each (…, n, n_dof). Damped contacts see the trapezoidal rate from zero
        (:func:`trapezoid_rate`); undamped ones need no rate, and none is computed.
    """
    ap = np.asarray(ap, dtype=float)
    if ap.ndim not in (2, 3) or ap.shape[-1] != system.n_contacts:
        raise ValueError(f"ap: expected (n, {system.n_contacts}) or (m, n, {system.n_contacts}), got {ap.shape}")
    ydot = trapezoid_rate(ap, 0.0, c.dt) if np.any(system.cc) else None
    return _drive(system, ap, ydot, c, u0, v0)


def channels_from_ap(system: VehicleSystem, ap: np.ndarray, c: NewmarkConstants, u0: np.ndarray | None = None,
                     v0: np.ndarray | None = None) -> np.ndarray:
    """The channels (…, n, n_channels) the vehicle measures on the profile ``ap`` under its contacts:
    :func:`ap_response` read as the logger reads it (:func:`measured_channels`)."""
    return measured_channels(system, ap_response(system, ap, c, u0, v0))


def _smooth_size(n: int) -> int:
    """The least 2^a·3^b·5^c ≥ n: a length the FFT is fast at."""
    best = 1 << max(n - 1, 0).bit_length()
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            p = p35
            while p < n:
                p *= 2
            best = min(best, p)
            p35 *= 3
        p5 *= 5
    return best


def channels_transpose(system: VehicleSystem, weights: np.ndarray, c: NewmarkConstants) -> np.ndarray:
    """The transpose of :func:`channels_from_ap` (from static equilibrium): per row of ``weights``,
    the weights on the profile that give the same sum.

    :func:`channels_from_ap` is linear in the profile and, away from its first sample, time-invariant
    (a profile that is zero up to step j leaves the vehicle at rest until j), so it is the causal
    convolution of each contact's impulse response plus, for the first sample, the free response from
    static equilibrium on it. Its transpose is therefore a cross-correlation with the same responses
    (FFT), and a weighted sum over the first sample's: two forward runs per contact in all, where
    applying the model to many profiles costs one run each.

    Parameters
    ----------
    system : VehicleSystem
    weights : ndarray
        (b, n, n_channels) (or (n, n_channels)): weights on the channels, one row per step ``c.dt``.
    c : NewmarkConstants

    Returns
    -------
    ndarray
        (b, n, n_contacts) (or (n, n_contacts)) ``V`` with ``Σ weights[r] · channels_from_ap(system, ap, c)
        = Σ V[r] · ap`` for every profile ``ap`` (n, n_contacts), up to rounding.
    """
    w = np.asarray(weights, dtype=float)
    w3 = w[None] if w.ndim == 2 else w
    if w3.ndim != 3 or w3.shape[2] != len(system.channels) or w3.shape[1] < 2:
        raise ValueError(f"weights: expected (b, n >= 2, {len(system.channels)}), got {w.shape}")
    b, n, _ = w3.shape
    nc = system.n_contacts
    impulses = np.zeros((2 * nc, n, nc))
    for i in range(nc):
        impulses[i, 1, i] = 1.0  # the time-invariant part: an impulse after the start
        impulses[nc + i, 0, i] = 1.0  # the start: static equilibrium on the first sample, then zero
    resp = channels_from_ap(system, impulses, c)  # (2 nc, n, n_channels)
    size = _smooth_size(2 * n - 1)  # no wrap-around of the lags read
    fw = np.fft.rfft(w3, size, axis=1)  # (b, f, n_channels)
    out = np.empty((b, n, nc))
    for i in range(nc):
        # V[j] = Σ_m Σ_ch w[j + m, ch] g[m, ch], g[m] the response m + 1 steps after an impulse
        fg = np.fft.rfft(resp[i, 1:], size, axis=0)  # (f, n_channels)
        corr = np.fft.irfft(np.einsum("bfh,fh->bf", fw, np.conj(fg)), size, axis=1)
        out[:, 1:, i] = corr[:, 1:n]
        out[:, 0, i] = np.einsum("bnh,nh->b", w3, resp[nc + i])
    return out[0] if w.ndim == 2 else out


def contact_forces(system: VehicleSystem, ap: np.ndarray, state: NewmarkState, dt: float) -> np.ndarray:
    """Dynamic contact forces kc·(y − Gᵀq) + cc·(ẏ − Gᵀq̇) of :func:`ap_response`'s ``state`` on
    ``ap`` (N, positive pressing the surface down; the static load is not included), shaped like ``ap``."""
    ap = np.asarray(ap, dtype=float)
    force = system.kc * (ap - state.u @ system.G)
    if np.any(system.cc):
        force = force + system.cc * (trapezoid_rate(ap, 0.0, dt) - state.v @ system.G)
    return force


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
    state = _drive(system, y, ydot, c, None, None)
    return RoadResponse(t, x_cg, state, y, ydot, measured_channels(system, state))
