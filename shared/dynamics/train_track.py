"""Train–track–bridge forward model (thesis §3.2): the 10-DOF carriage coupled to the track through
the wheel–rail contact (no separation), integrated by Newmark-β.

Each wheelset's displacement is constrained to the rail under it: w_i = N(x_i)·u_track + r(x_i), the
rail deflection plus the irregularity — the apparent profile (AP). The contact forces λ are the
Lagrange multipliers of that constraint. One Newmark step solves

    K̂_t u_t = R_t − Nᵀλ,     K̂_v q = R_v + E(λ − P),     Eᵀq = N u_t + r

by condensation: the banded track matrix K̂_t (factored once) is solved for the predictor and the
four unit contact loads (one band sweep with five right-hand sides, O(n_dof·bandwidth)), leaving a
4×4 system for λ; the steps run in a numba kernel.

Each wheelset's (w, ẇ, ẅ) obey Newmark's own relations, which is what the inverse's
``contact_rule="newmark"`` (:mod:`shared.dynamics.inverse`) inverts: at the same Δt, γ and β the
inverse recovers the AP to rounding.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np
from scipy.linalg import cho_solve_banded, cholesky_banded

from ..jit import kernel
from ..track.model import Track
from ..vehicles.carriage import Carriage
from .inverse import InverseState
from .newmark import newmark_constants

#: Newmark γ of the coupled model. The average-acceleration rule (γ = ½) is not stable here: the
#: moving wheel–rail constraint pumps energy into the highest track modes when Δt is small (seen
#: at Δt ≤ 0.5 ms). A little numerical damping (γ = 0.6, β = ¼(½ + γ)²) removes that and costs
#: ~0.3·ωΔt/2 of damping on a mode (≈ 3 % at 50 Hz with Δt = 2 ms).
DEFAULT_GAMMA = 0.6


class TrainTrackResponse(NamedTuple):
    """A simulated run: the logger's channels, and truth for tests."""

    t: np.ndarray  # (n,) s
    x_cg: np.ndarray  # (n,) chainage of the carriage body's centre of gravity, m
    q: np.ndarray  # (n, 10) carriage DOFs (Carriage.full_matrices order), from static equilibrium on a rigid rail
    qd: np.ndarray  # (n, 10)
    qdd: np.ndarray  # (n, 10)
    channels: np.ndarray  # (n, 4) bogie1_acc, bogie1_pitch_rate, bogie2_acc, bogie2_pitch_rate
    ap: np.ndarray  # (n, 4) true AP under each wheel from the track side: rail deflection + irregularity, m
    rail_deflection: np.ndarray  # (n, 4) rail deflection under each wheel, m (up)
    irregularity: np.ndarray  # (n, 4) rail irregularity under each wheel, m
    contact_force_n: np.ndarray  # (n, 4) total wheel–rail force (N, compressive positive)
    probes: np.ndarray  # (n, n_probe) rail deflection at fixed chainages, m
    dt: float

    def initial_inverse_state(self) -> InverseState:
        """The exact state of the 6-DOF carriage system at the first sample."""
        return InverseState(self.q[0, :6], self.qd[0, :6], self.qdd[0, :6], self.q[0, 6:], self.qd[0, 6:],
                            self.qdd[0, 6:])


class _Coupled(NamedTuple):
    """What the kernel needs of the two subsystems at one Δt."""

    L: np.ndarray  # (bw + 1, n_t) band Cholesky factor of the track's K̂ = K + a0·M + a1·C
    Mt: np.ndarray  # (bw + 1, n_t) track mass, lower band
    Ct: np.ndarray  # (bw + 1, n_t) track damping, lower band
    Mv: np.ndarray  # (10, 10) carriage
    Cv: np.ndarray  # (10, 10)
    Kv_inv: np.ndarray  # (10, 10) inverse of the carriage's K̂
    E: np.ndarray  # (10, 4) wheelset DOFs
    P: np.ndarray  # (4,) static wheel loads, N
    k: np.ndarray  # (8,) Newmark a0..a7


class _Path(NamedTuple):
    """Where the wheels are at every step: rail contact rows, irregularity, and fixed probes."""

    dofs: np.ndarray  # (n, 4, 4) int64
    vals: np.ndarray  # (n, 4, 4)
    r: np.ndarray  # (n, 4) m
    probe_dofs: np.ndarray  # (n_probe, 4) int64
    probe_vals: np.ndarray  # (n_probe, 4)


def _static_start(carriage: Carriage, track: Track, dofs0, vals0, r0):
    """Carriage resting on the track at its first position: track displacement, wheel AP, contact force."""
    s = carriage.system()
    P = carriage.axle_loads_n()
    # Contact-force response of the body/bogies to wheel displacements: λ = P + S·y.
    kc = np.diag(s.kc)
    S = kc - kc @ s.G.T @ np.linalg.solve(s.K, s.G @ kc)
    # Track flexibility at the four contact points.
    Lk = cholesky_banded(track.K, lower=True)
    NT = np.zeros((track.n_dof, 4))
    for i in range(4):
        np.add.at(NT[:, i], dofs0[i], vals0[i])
    Z = cho_solve_banded((Lk, True), NT)
    F = NT.T @ Z
    y = np.linalg.solve(np.eye(4) + F @ S, r0 - F @ P)
    lam = P + S @ y
    u_t = -Z @ lam
    q6 = np.linalg.solve(s.K, s.G @ (s.kc * y))
    return u_t, np.concatenate([q6, y]), lam


def simulate_train_track(
    carriage: Carriage,
    track: Track,
    irregularity: Callable[[np.ndarray], np.ndarray] | None,
    x0_m: float,
    duration_s: float,
    dt: float,
    gamma: float = DEFAULT_GAMMA,
    beta: float | None = None,
    probe_x_m: np.ndarray | None = None,
) -> TrainTrackResponse:
    """Run the carriage at its speed ``carriage.v`` over the track from body chainage ``x0_m``.

    ``irregularity(x)`` gives the rail's unloaded vertical profile (m, up; None: smooth). The
    carriage starts at rest in static equilibrium on the track (so every measured channel starts
    at zero and an inverse started at rest sees only a constant offset). ``gamma``/``beta``:
    Newmark constants (see :data:`DEFAULT_GAMMA`). ``probe_x_m``: fixed chainages whose
    rail deflection is recorded (e.g. over a bridge's midspan). Every wheel must stay on the rail.
    """
    c = newmark_constants(dt, gamma, beta)
    if not (np.isfinite(duration_s) and duration_s > 0):
        raise ValueError(f"duration_s: must be a positive number of seconds, got {duration_s!r}")
    n = int(round(duration_s / dt)) + 1
    t = np.arange(n) * dt
    x_cg = x0_m + carriage.v * t
    fm = carriage.full_matrices()
    xw = x_cg[:, None] + fm.offsets_m[None, :]
    dofs, vals = track.contact_entries(xw.ravel())
    dofs, vals = dofs.reshape(n, 4, 4), vals.reshape(n, 4, 4)
    r = np.zeros((n, 4)) if irregularity is None else np.asarray(irregularity(xw.ravel()), float).reshape(n, 4)
    probe_x = np.zeros(0) if probe_x_m is None else np.atleast_1d(np.asarray(probe_x_m, float))
    pd, pv = track.contact_entries(probe_x) if len(probe_x) else (np.zeros((0, 4), np.int64), np.zeros((0, 4)))

    K_eff = track.K + c.a0 * track.M + c.a1 * track.C
    L = np.ascontiguousarray(cholesky_banded(K_eff, lower=True))
    Kv_eff = fm.K + c.a0 * fm.M + c.a1 * fm.C
    Kv_inv = np.linalg.inv(Kv_eff)
    u0, q0, lam0 = _static_start(carriage, track, dofs[0], vals[0], r[0])
    k = np.array([c.a0, c.a1, c.a2, c.a3, c.a4, c.a5, c.a6, c.a7])
    coupled = _Coupled(L, np.ascontiguousarray(track.M), np.ascontiguousarray(track.C), fm.M, fm.C, Kv_inv, fm.E,
                       fm.static_wheel_loads_n, k)
    path = _Path(dofs, vals, r, pd, pv)
    q, qd, qdd, lam, defl, probes = _run(coupled, path, u0, q0, lam0)
    channels = np.stack([qdd[:, 2], qd[:, 3], qdd[:, 4], qd[:, 5]], axis=1)
    return TrainTrackResponse(t, x_cg, q, qd, qdd, channels, defl + r, defl, r, lam, probes, dt)


@kernel
def _band_symv2(A, x, B, y, out):
    """out = A x + B y for A, B symmetric with one lower band storage shape ab[i − j, j]."""
    bw1, n = A.shape
    for j in range(n):
        out[j] = 0.0
    for j in range(n):
        out[j] += A[0, j] * x[j] + B[0, j] * y[j]
        for kk in range(1, min(bw1, n - j)):
            i = j + kk
            out[i] += A[kk, j] * x[j] + B[kk, j] * y[j]
            out[j] += A[kk, j] * x[i] + B[kk, j] * y[i]


@kernel
def _band_cho_solve_multi(L, X):
    """Solve (L Lᵀ) X = B in place for the columns of X (n, m), L the lower band Cholesky factor
    c[i − j, j] = L[i, j]. All right-hand sides in one sweep (the m values of a row are contiguous)."""
    bw1, n = L.shape
    m = X.shape[1]
    for i in range(n):  # forward: L Y = B
        for kk in range(1, min(bw1, i + 1)):
            j = i - kk
            lij = L[kk, j]
            for c in range(m):
                X[i, c] -= lij * X[j, c]
        d = 1.0 / L[0, i]
        for c in range(m):
            X[i, c] *= d
    for i in range(n - 1, -1, -1):  # backward: Lᵀ X = Y
        for kk in range(1, min(bw1, n - i)):
            j = i + kk
            lji = L[kk, i]
            for c in range(m):
                X[i, c] -= lji * X[j, c]
        d = 1.0 / L[0, i]
        for c in range(m):
            X[i, c] *= d


@kernel
def _run(coupled, path, u0, q0, lam0):
    """Newmark steps of the coupled system from the static start (u0, q0, λ0) along ``path``."""
    L, Mt, Ct, Mv, Cv, Kv_inv, E, P, k = coupled
    dofs, vals, r, pd, pv = path
    n_steps = dofs.shape[0]
    nt = Mt.shape[1]
    nv = Mv.shape[0]
    n_probe = pd.shape[0]
    a0, a1, a2, a3, a4, a5, a6, a7 = k[0], k[1], k[2], k[3], k[4], k[5], k[6], k[7]
    q = np.zeros((n_steps, nv))
    qd = np.zeros((n_steps, nv))
    qdd = np.zeros((n_steps, nv))
    lam = np.zeros((n_steps, 4))
    defl = np.zeros((n_steps, 4))
    probes = np.zeros((n_steps, n_probe))
    u = u0.copy()
    v = np.zeros(nt)
    a = np.zeros(nt)
    q[0] = q0
    lam[0] = lam0
    Ye = Kv_inv @ E  # (nv, 4)
    EtYe = E.T @ Ye
    EtYeP = EtYe @ P
    for i in range(4):
        acc = 0.0
        for m in range(4):
            acc += vals[0, i, m] * u[dofs[0, i, m]]
        defl[0, i] = acc
    for p in range(n_probe):
        acc = 0.0
        for m in range(4):
            acc += pv[p, m] * u[pd[p, m]]
        probes[0, p] = acc
    pm = np.empty(nt)
    pc = np.empty(nt)
    R = np.empty(nt)
    X = np.zeros((nt, 5))  # column 0: K̂⁻¹R (the predictor); 1..4: K̂⁻¹Nᵢᵀ (unit contact loads)
    A4 = np.empty((4, 4))
    b4 = np.empty(4)
    qp = np.empty(nv)
    qc = np.empty(nv)
    for s in range(1, n_steps):
        for j in range(nt):
            pm[j] = a0 * u[j] + a2 * v[j] + a3 * a[j]
            pc[j] = a1 * u[j] + a4 * v[j] + a5 * a[j]
        _band_symv2(Mt, pm, Ct, pc, R)
        for j in range(nt):
            X[j, 0] = R[j]
            X[j, 1] = 0.0
            X[j, 2] = 0.0
            X[j, 3] = 0.0
            X[j, 4] = 0.0
        for i in range(4):
            for m in range(4):
                X[dofs[s, i, m], 1 + i] += vals[s, i, m]
        _band_cho_solve_multi(L, X)
        for j in range(nv):
            qp[j] = a0 * q[s - 1, j] + a2 * qd[s - 1, j] + a3 * qdd[s - 1, j]
            qc[j] = a1 * q[s - 1, j] + a4 * qd[s - 1, j] + a5 * qdd[s - 1, j]
        Y0 = Kv_inv @ (Mv @ qp + Cv @ qc)
        EtY0 = E.T @ Y0
        for i in range(4):
            nx0 = 0.0
            for m in range(4):
                nx0 += vals[s, i, m] * X[dofs[s, i, m], 0]
            b4[i] = nx0 + r[s, i] - EtY0[i] + EtYeP[i]
            for jw in range(4):
                nxn = 0.0
                for m in range(4):
                    nxn += vals[s, i, m] * X[dofs[s, i, m], 1 + jw]
                A4[i, jw] = EtYe[i, jw] + nxn
        lam_s = np.linalg.solve(A4, b4)
        lam[s] = lam_s
        for j in range(nt):
            un = X[j, 0] - X[j, 1] * lam_s[0] - X[j, 2] * lam_s[1] - X[j, 3] * lam_s[2] - X[j, 4] * lam_s[3]
            an = a0 * (un - u[j]) - a2 * v[j] - a3 * a[j]
            v[j] = v[j] + a6 * a[j] + a7 * an
            a[j] = an
            u[j] = un
        q[s] = Y0 + Ye @ (lam_s - P)
        qdd[s] = a0 * (q[s] - q[s - 1]) - a2 * qd[s - 1] - a3 * qdd[s - 1]
        qd[s] = qd[s - 1] + a6 * qdd[s - 1] + a7 * qdd[s]
        for i in range(4):
            acc = 0.0
            for m in range(4):
                acc += vals[s, i, m] * u[dofs[s, i, m]]
            defl[s, i] = acc
        for p in range(n_probe):
            acc = 0.0
            for m in range(4):
                acc += pv[p, m] * u[pd[p, m]]
            probes[s, p] = acc
    return q, qd, qdd, lam, defl, probes
