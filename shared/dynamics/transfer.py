"""Frequency responses of a vehicle, contact profile → measured channels: discrete Newmark and continuous."""

from __future__ import annotations

import math

import numpy as np

from ..vehicles.base import VehicleSystem


def _channel_rows(system: VehicleSystem) -> tuple[np.ndarray, np.ndarray]:
    """The DOF each channel reads and its kind (0: acceleration, 1: rate)."""
    dofs = np.array([ch.dof for ch in system.channels], dtype=np.int64)
    kinds = np.array([0 if ch.kind == "acc" else 1 for ch in system.channels], dtype=np.int64)
    return dofs, kinds


def newmark_transfer(system: VehicleSystem, freqs_hz: np.ndarray, dt: float, gamma: float = 0.8,
                     beta: float | None = None) -> np.ndarray:
    """Frequency response of the *discrete* Newmark-β forward model, contact profile → channels.

    With ``g(z) = 1 − γ + γz`` and ``b(z) = ½ − β + βz`` Newmark's updates give
    ``V = Δt·g/(z−1)·A`` and ``U = Δt²(g + b(z−1))/(z−1)²·A``, so the equation of motion reads
    ``S(z) A = G (kc + cc·ż) Y`` with ``S = M + C·Δt·g/(z−1) + K·Δt²(g + b(z−1))/(z−1)²`` and the
    contact rate by the trapezoidal rule, ``ż = (2/Δt)(z−1)/(z+1)`` — the scheme of
    :func:`shared.dynamics.forward.channels_from_ap`, which the edge's inverse inverts exactly.
    ``beta`` defaults to ``0.25 * (0.5 + gamma)**2``. Returns (n_f, n_channels, n_contacts) complex
    (m/s² or rad/s per m); zero at 0 Hz.
    """
    beta = 0.25 * (0.5 + gamma) ** 2 if beta is None else beta
    f = np.asarray(freqs_hz, dtype=float)
    dofs, kinds = _channel_rows(system)
    out = np.zeros((f.size, len(dofs), system.n_contacts), dtype=complex)
    pos = f > 0.0
    z = np.exp(2j * math.pi * f[pos] * dt)[:, None, None]
    g, b = (1.0 - gamma) + gamma * z, (0.5 - beta) + beta * z
    S = system.M + system.C * (dt * g / (z - 1.0)) + system.K * (dt * dt * (g + b * (z - 1.0)) / (z - 1.0) ** 2)
    rate = (2.0 / dt) * (z - 1.0) / (z + 1.0)  # (n, 1, 1)
    A = np.linalg.solve(S, system.G[None, :, :] * (system.kc[None, None, :] + system.cc[None, None, :] * rate))
    V = (dt * g / (z - 1.0)) * A
    out[pos] = np.where(kinds[None, :, None] == 0, A[:, dofs], V[:, dofs])
    return out


def continuous_transfer(system: VehicleSystem, freqs_hz: np.ndarray) -> np.ndarray:
    """Frequency response of the continuous-time vehicle, contact profile → channels,
    (n_f, n_channels, n_contacts) complex as :func:`newmark_transfer`; zero at 0 Hz."""
    f = np.asarray(freqs_hz, dtype=float)
    dofs, kinds = _channel_rows(system)
    out = np.zeros((f.size, len(dofs), system.n_contacts), dtype=complex)
    pos = f > 0.0
    w = (2.0 * math.pi * f[pos])[:, None, None]
    Z = -w * w * system.M + 1j * w * system.C + system.K
    Q = np.linalg.solve(Z, system.G[None, :, :] * (system.kc[None, None, :] + 1j * w * system.cc[None, None, :]))
    out[pos] = np.where(kinds[None, :, None] == 0, -w * w * Q[:, dofs], 1j * w * Q[:, dofs])
    return out
