"""The carriage's inverse for many runs and parameter sets in one compiled call: the APs of a batch's
trials (:func:`carriage_aps_runs`) and their forward-mode derivatives in the log parameters and the
body's initial state (:func:`carriage_aps_sensitivities`)."""

from __future__ import annotations

import numpy as np

from shared.dynamics.newmark import newmark_constants
from shared.jit import kernel

#: The carriage's parameters the inverse depends on, in the order of :func:`carriage_aps`' columns.
INVERSE_NAMES = ("mv", "Iv", "mb", "Ib", "kp", "cp", "ks", "cs")
#: Newmark γ of the calibration's inverse. Not the edge's 0.8: its numerical damping (~(γ − ½)·ω·Δt/2,
#: a fifth of the bogies' own damping at their bounce) is read as a lower cp relative to the masses,
#: and cp's prior then pulls the batch's common mass scale up beyond what the priors explain.
#: ``tests/test_rail_calibration.py`` checks the common error over seeds.
INVERSE_GAMMA = 0.5
#: The body's state at a record's first sample, relative to the bogies' (m, rad, m/s, rad/s). The
#: inverse's default start at rest is right only for a record that starts at rest; a record that
#: starts mid-motion leaves the body's free oscillation in every AP, and the body modes decay
#: slowly: bounce 1.16 Hz, pitch 1.4 Hz at ζ ≈ 0.07–0.08 with Table 3.1's suspension (e-folding
#: in ~2 s, 60 m at 30 m/s) — no start-up window a 150 m record could spare removes it.
BODY0_NAMES = ("u", "pitch", "u_dot", "pitch_rate")
N_SENS = 1 + len(INVERSE_NAMES) + len(BODY0_NAMES)  # carriage_aps_sensitivities' rows


def _body0(body0: np.ndarray | None, T: int) -> np.ndarray:
    if body0 is None:
        return np.zeros((T, len(BODY0_NAMES)))
    body0 = np.ascontiguousarray(body0, dtype=np.float64)
    if body0.shape != (T, len(BODY0_NAMES)):
        raise ValueError(f"body0 must be ({T}, {len(BODY0_NAMES)}), got {body0.shape}")
    return body0


def carriage_aps_runs(theta: np.ndarray, run_of: np.ndarray, Lb: float, Lv: float, z: np.ndarray,
                      lengths: np.ndarray, dts: np.ndarray, out: np.ndarray | None = None,
                      body0: np.ndarray | None = None) -> np.ndarray:
    """APs (T, N, 4) under T parameter sets ``theta`` (T, 8) in :data:`INVERSE_NAMES` order, trial t
    on run ``run_of[t]``'s channels ``z`` (R, N, 4) (the first ``lengths[r]`` samples, step
    ``dts[r]``; the rest of its AP is zero). Same result as :func:`shared.dynamics.population.
    population_aps` per run; the carriage's matrices are assembled in array form — M, C, K are
    linear in the parameters (:meth:`shared.vehicles.carriage.Carriage._body_bogie`) — and the whole
    batch is one compiled call (:func:`_inverse_kernel` without derivatives), instead of a
    ``Carriage`` per trial and a call per run.

    ``out``: a (≥ T, N, 4) C-contiguous work array to write into (its first T rows; past a run's
    length left as they were, not zeroed): a calibration reuses one across its evaluations.
    ``body0`` (T, 4): the body's initial state of each trial (:data:`BODY0_NAMES`; default at rest)."""
    theta = np.asarray(theta, dtype=float)
    run_of = np.asarray(run_of, dtype=np.int64)
    T, N = len(theta), z.shape[1]
    if out is None:
        out = np.zeros((T, N, 4))  # time-major, as the sensitivities (a step's values in one piece)
    else:
        out = out[:T]
        if out.shape[1:] != (N, 4) or not out.flags.c_contiguous:
            raise ValueError(f"carriage_aps_runs: out must be a C-contiguous (>= {T}, {N}, 4) array")
    _carriage_inverse(theta, run_of, Lb, Lv, z, lengths, dts, _body0(body0, T), 0, out.reshape(T, N, 1, 4))
    return out


def carriage_aps_sensitivities(theta: np.ndarray, Lb: float, Lv: float, z: np.ndarray, lengths: np.ndarray,
                               dts: np.ndarray, out: np.ndarray | None = None,
                               body0: np.ndarray | None = None, body_derivatives: bool = True) -> np.ndarray:
    """APs and their derivatives: (R, 13, N, 4), [r, 0] the AP of run r's channels ``z[r]`` (the
    first ``lengths[r]`` samples at step ``dts[r]``) under ``theta[r]`` (R, 8; :data:`INVERSE_NAMES`
    order) from the body's initial state ``body0[r]`` (:data:`BODY0_NAMES`; default at rest) exactly
    as :func:`carriage_aps_runs` gives it, [r, 1 + j] its derivative in log θ_j, [r, 9 + j] in
    body0_j (per m, rad, m/s, rad/s: the free responses, the AP being affine in the initial state) —
    forward mode through the same Newmark-β recursion (exact to rounding, no finite-difference step)
    in one pass per run (:func:`_inverse_kernel`), at ~the cost of 4 of the 13 inverses a one-sided
    finite-difference Jacobian takes. ``out``: a (≥ R, N, 13, 4) C-contiguous work array (past a
    run's length left as it was). ``body_derivatives=False``: rows 9–12 are not computed (left as
    they were)."""
    theta = np.asarray(theta, dtype=float)
    R, N = len(theta), z.shape[1]
    if out is None:
        out = np.zeros((R, N, N_SENS, 4))  # time-major: a step's 52 values in one piece
    else:
        out = out[:R]
        if out.shape[1:] != (N, N_SENS, 4) or not out.flags.c_contiguous:
            raise ValueError(f"carriage_aps_sensitivities: out must be a C-contiguous (>= {R}, {N}, {N_SENS}, 4) array")
    _carriage_inverse(theta, np.arange(R), Lb, Lv, z, lengths, dts, _body0(body0, R), 12 if body_derivatives else 8,
                      out)
    return out.transpose(0, 2, 1, 3)


def _carriage_inverse(theta, run_of, Lb, Lv, z, lengths, dts, body0, nd, out) -> None:
    """:func:`_inverse_kernel` on ``out`` (T, N, ≥ 1 + nd, 4) with the carriage's matrices of each
    trial; ``nd`` 0: the primal alone (the derivatives' inputs are None: compiled without them)."""
    dts = np.asarray(dts, dtype=float)
    M, C, K, G, sec, prim = _carriage_matrices(theta, Lb, Lv)
    c = newmark_constants(float(dts.min()), INVERSE_GAMMA)
    dt = dts[run_of][:, None, None]
    S = np.concatenate([M[:, :, :2] + c.gamma * dt * C[:, :, :2] + c.beta * dt * dt * K[:, :, :2],
                        np.broadcast_to(-G, (len(theta), 6, 4))], axis=2)
    Sinv = np.linalg.inv(S)
    tangents = (Sinv @ C[:, :, :2], Sinv @ K[:, :, :2], Sinv @ prim, Sinv @ sec) if nd else (None,) * 4
    _inverse_kernel(Sinv, M, C, K, *tangents, theta, body0, run_of, nd, np.ascontiguousarray(z, dtype=np.float64),
                    np.asarray(lengths, dtype=np.int64), dts, c.gamma, c.beta, out)


@kernel
def _inverse_kernel(Sinv, M, C, K, PC, PK, SP, SS, theta, body0, run_of, nd, z, lengths, dts, gamma, beta, out):
    """The carriage's inverse step (:func:`shared.dynamics.batched_inverse.inverse_runs` with the carriage's
    structure: DOFs 2–5 measured, accelerations and pitch rates alternately; 0–1 the body, free;
    four contacts, the primary suspensions kp, cp), parameter set t on run ``run_of[t]``'s channels,
    the body started from ``body0[t]`` (u, θ, u̇, θ̇; its acceleration 0 as the at-rest inverse has
    it: a wrong start acceleration only moves the state after the first step, within the same free
    responses), with the forward-mode derivatives in the first ``nd`` directions carried alongside:
    8 the log parameters, 12 also the body's initial state. ``out`` (T, N, ≥ 1 + nd, 4),
    time-major: [t, k, 0] the AP, [t, k, 1 + j] its derivative j (rows past 1 + nd untouched).

    ``PC`` None (``nd`` 0): the AP alone, for the chord steps' trials. numba compiles that call
    without the derivatives' code (its branches test the argument against None, which it prunes at
    compile time): as fast as a kernel of the primal alone, which a run-time flag is not.

    The measured DOFs' states are data, so only the body's and the contacts' states have
    derivatives. Differentiating M a + C v + K u − G g = 0 in log θ_j: S [ds_f; dg] = −(b_j + C_f
    dvp_f + K_f dup_f), with b_j = θ_j (∂_j M a + ∂_j C v + ∂_j K u) at the step's state — a few
    entries per parameter (mv, Iv, mb, Ib a diagonal entry each; kp, cp the primary pattern
    ``prim``; ks, cs the secondary ``sec``), pre-multiplied by S⁻¹: ``PC``/``PK`` = S⁻¹C/K on the
    free columns, ``SP``/``SS`` = S⁻¹ prim / S⁻¹ sec. Directions 8–11, the initial state's, have no
    right-hand side and unit initial tangents."""
    T = Sinv.shape[0]
    u = np.zeros(6)
    v = np.zeros(6)
    a = np.zeros(6)
    up = np.zeros(6)
    vp = np.zeros(6)
    s = np.zeros(6)
    known = np.zeros(6)
    y = np.zeros(4)
    yd = np.zeros(4)
    du = np.zeros((2, 12))
    dv = np.zeros((2, 12))
    da = np.zeros((2, 12))
    dup = np.zeros((2, 12))
    dvp = np.zeros((2, 12))
    ds = np.zeros((6, 12))
    dy = np.zeros((4, 12))
    dyd = np.zeros((4, 12))
    dyn = np.zeros(12)
    for t in range(T):
        r = run_of[t]
        dt = dts[r]
        bdt2 = beta * dt * dt
        gdt = gamma * dt
        mv, Iv, mb, Ib, kp, cp, ks, cs = theta[t]
        two_dt = 2.0 / dt
        inv_kp = 1.0 / kp
        inv_den = 1.0 / (kp + 2.0 * cp / dt)
        u[:] = 0.0
        v[:] = 0.0
        a[:] = 0.0
        y[:] = 0.0
        yd[:] = 0.0
        u[0] = body0[t, 0]
        u[1] = body0[t, 1]
        v[0] = body0[t, 2]
        v[1] = body0[t, 3]
        a[2] = z[r, 0, 0]
        v[3] = z[r, 0, 1]
        a[4] = z[r, 0, 2]
        v[5] = z[r, 0, 3]
        for c in range(4):
            out[t, 0, 0, c] = 0.0
        if PC is not None:
            du[:] = 0.0
            dv[:] = 0.0
            da[:] = 0.0
            dy[:] = 0.0
            dyd[:] = 0.0
            if nd > 8:
                du[0, 8] = 1.0
                du[1, 9] = 1.0
                dv[0, 10] = 1.0
                dv[1, 11] = 1.0
            for q in range(1, 1 + nd):
                for c in range(4):
                    out[t, 0, q, c] = 0.0
        for k in range(1, lengths[r]):
            for i in range(6):
                up[i] = u[i] + dt * v[i] + dt * dt * (0.5 - beta) * a[i]
                vp[i] = v[i] + dt * (1.0 - gamma) * a[i]
            if PC is not None:
                for f in range(2):
                    for j in range(nd):
                        dup[f, j] = du[f, j] + dt * dv[f, j] + dt * dt * (0.5 - beta) * da[f, j]
                        dvp[f, j] = dv[f, j] + dt * (1.0 - gamma) * da[f, j]
            for m in range(4):
                i = 2 + m
                if m % 2 == 0:
                    a[i] = z[r, k, m]
                else:  # a measured rate: the acceleration Newmark's velocity update implies
                    a[i] = (z[r, k, m] - vp[i]) / gdt
                u[i] = up[i] + bdt2 * a[i]
                v[i] = vp[i] + gdt * a[i]
            # the primal solve, as inverse_runs: S [s_f; g] = −known
            for row in range(6):
                acc = 0.0
                for i in range(2, 6):
                    acc += M[t, row, i] * a[i] + C[t, row, i] * v[i] + K[t, row, i] * u[i]
                for i in range(2):
                    acc += C[t, row, i] * vp[i] + K[t, row, i] * up[i]
                known[row] = acc
            for q in range(6):
                acc = 0.0
                for row in range(6):
                    acc -= Sinv[t, q, row] * known[row]
                s[q] = acc
            for f in range(2):
                a[f] = s[f]
                u[f] = up[f] + bdt2 * s[f]
                v[f] = vp[f] + gdt * s[f]
            if PC is not None:
                # the eight right-hand sides b_j, pre-multiplied by −S⁻¹, at the updated state
                for q in range(6):
                    sp_u = 0.0
                    sp_v = 0.0
                    ss_u = 0.0
                    ss_v = 0.0
                    for i in range(2, 6):  # prim: the bogies' DOFs only
                        sp_u += SP[t, q, i] * u[i]
                        sp_v += SP[t, q, i] * v[i]
                    for i in (0, 1, 2, 4):  # sec: the body's and the bogies' bounce
                        ss_u += SS[t, q, i] * u[i]
                        ss_v += SS[t, q, i] * v[i]
                    ds[q, 0] = -mv * Sinv[t, q, 0] * a[0]
                    ds[q, 1] = -Iv * Sinv[t, q, 1] * a[1]
                    ds[q, 2] = -mb * (Sinv[t, q, 2] * a[2] + Sinv[t, q, 4] * a[4])
                    ds[q, 3] = -Ib * (Sinv[t, q, 3] * a[3] + Sinv[t, q, 5] * a[5])
                    ds[q, 4] = -kp * sp_u
                    ds[q, 5] = -cp * sp_v
                    ds[q, 6] = -ks * ss_u
                    ds[q, 7] = -cs * ss_v
                    for j in range(8, nd):
                        ds[q, j] = 0.0
                    p0 = PC[t, q, 0]
                    p1 = PC[t, q, 1]
                    k0 = PK[t, q, 0]
                    k1 = PK[t, q, 1]
                    for j in range(nd):
                        ds[q, j] -= p0 * dvp[0, j] + p1 * dvp[1, j] + k0 * dup[0, j] + k1 * dup[1, j]
                for f in range(2):
                    for j in range(nd):
                        da[f, j] = ds[f, j]
                        du[f, j] = dup[f, j] + bdt2 * ds[f, j]
                        dv[f, j] = dvp[f, j] + gdt * ds[f, j]
            for c in range(4):
                g = s[2 + c]
                if cp == 0.0:
                    ynew = g / kp
                    if PC is not None:
                        for j in range(nd):
                            dy[c, j] = ds[2 + c, j] * inv_kp
                        dy[c, 4] -= ynew  # d/dlog kp of g/kp
                    y[c] = ynew
                else:  # kc·y + cc·ẏ = g by the trapezoidal rule (the primal as inverse_runs has it)
                    den = kp + 2.0 * cp / dt
                    hist = 2.0 * y[c] / dt + yd[c]
                    ynew = (g + cp * hist) / den
                    if PC is not None:
                        for j in range(nd):  # (reciprocals: divisions are slow)
                            dyn[j] = (ds[2 + c, j] + cp * (two_dt * dy[c, j] + dyd[c, j])) * inv_den
                        dyn[4] -= ynew * kp * inv_den  # the contact's stiffness is kp
                        dyn[5] += cp * (hist - two_dt * ynew) * inv_den  # and its damping cp
                        for j in range(nd):
                            dyd[c, j] = two_dt * (dyn[j] - dy[c, j]) - dyd[c, j]
                            dy[c, j] = dyn[j]
                    yd[c] = 2.0 * (ynew - y[c]) / dt - yd[c]
                    y[c] = ynew
                out[t, k, 0, c] = y[c]
                if PC is not None:
                    for j in range(nd):
                        out[t, k, 1 + j, c] = dy[c, j]


def _carriage_matrices(theta: np.ndarray, Lb: float, Lv: float):
    """M, C, K (T, 6, 6) of T parameter sets (:data:`INVERSE_NAMES` order), the contact matrix G
    (6, 4) and the secondary and primary suspensions' patterns ``sec``, ``prim`` (6, 6): M, C, K are
    linear in the parameters (:meth:`shared.vehicles.carriage.Carriage._body_bogie`)."""
    T = len(theta)
    mv, Iv, mb, Ib, kp, cp, ks, cs = theta.T
    s1 = np.array([1.0, Lv, -1.0, 0.0, 0.0, 0.0])
    s2 = np.array([1.0, -Lv, 0.0, 0.0, -1.0, 0.0])
    sec = np.outer(s1, s1) + np.outer(s2, s2)
    G = np.zeros((6, 4))
    G[2, 0], G[3, 0], G[2, 1], G[3, 1] = 1.0, Lb, 1.0, -Lb
    G[4, 2], G[5, 2], G[4, 3], G[5, 3] = 1.0, Lb, 1.0, -Lb
    prim = G @ G.T
    K = ks[:, None, None] * sec + kp[:, None, None] * prim
    C = cs[:, None, None] * sec + cp[:, None, None] * prim
    M = np.zeros((T, 6, 6))
    for j, m in enumerate((mv, Iv, mb, Ib, mb, Ib)):
        M[:, j, j] = m
    return M, C, K, G, sec, prim


def carriage_aps(theta: np.ndarray, Lb: float, Lv: float, z: np.ndarray, dt: float) -> np.ndarray:
    """APs (T, n, 4) of one run's channels ``z`` (n, 4) under T parameter sets (:func:`carriage_aps_runs`)."""
    z = np.asarray(z, dtype=float)
    return carriage_aps_runs(theta, np.zeros(len(theta), dtype=np.int64), Lb, Lv, z[None], np.array([len(z)]),
                             np.array([dt]))
