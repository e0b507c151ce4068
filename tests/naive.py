"""Slow, obviously-correct reference loops, written literally from the thesis (errata fixed).

Each function runs one sample at a time in plain Python, naming the equation it implements, so a
reader can check it against the text line by line. They are the references the compiled kernels of
``shared.dynamics`` are tested against, and the "plain loop" the benchmarks compare with.

Conventions shared by the inverse references: ``initial`` holds the full state at the first
sample as ``(u, v, a)`` (one value per degree of freedom, in the order of the vehicle's
``system()``), the measured channels are sampled every ``dt`` seconds, and the result holds the
profile under each contact at every sample, the first one computed from the initial state.
"""

from __future__ import annotations

import numpy as np


def newmark_constants(dt, gamma=0.8, beta=None):
    """a0..a7 of eq. (2.10) / (B.38), as a plain tuple."""
    if beta is None:
        beta = 0.25 * (0.5 + gamma) ** 2
    a0 = 1.0 / (beta * dt**2)
    a1 = gamma / (beta * dt)
    a2 = 1.0 / (beta * dt)
    a3 = 1.0 / (beta * 2.0) - 1.0
    a4 = gamma / beta - 1.0
    a5 = dt / 2.0 * (gamma / beta - 2.0)
    a6 = (1.0 - gamma) * dt
    a7 = gamma * dt
    return a0, a1, a2, a3, a4, a5, a6, a7


def _matvec(A, x):
    return [sum(A[i][j] * x[j] for j in range(len(x))) for i in range(len(A))]


# ---------------------------------------------------------------------------------------------
# Forward Newmark-β


def newmark_forward(M, C, K, force, dt, u0=None, v0=None, gamma=0.8, beta=None):
    """M ü + C u̇ + K u = f by Newmark-β, one step at a time (effective-stiffness form, eq. 2.28–2.30).

    ``force`` is (n_steps, n_dof). Returns (u, v, a), each (n_steps, n_dof).
    """
    a0, a1, a2, a3, a4, a5, a6, a7 = newmark_constants(dt, gamma, beta)
    M, C, K = (np.atleast_2d(np.asarray(X, float)) for X in (M, C, K))
    f = np.asarray(force, float).reshape(len(force), -1)
    n_steps, n = f.shape
    u = np.zeros((n_steps, n))
    v = np.zeros((n_steps, n))
    a = np.zeros((n_steps, n))
    if u0 is not None:
        u[0] = u0
    if v0 is not None:
        v[0] = v0
    a[0] = np.linalg.solve(M, f[0] - C @ v[0] - K @ u[0])  # equation of motion at t = 0
    K_bar = K + a0 * M + a1 * C  # (2.28)
    for t in range(1, n_steps):
        # effective force: f(t+Δt) plus the inertia and damping of the known state at t
        F_bar = f[t] + M @ (a0 * u[t - 1] + a2 * v[t - 1] + a3 * a[t - 1]) + C @ (
            a1 * u[t - 1] + a4 * v[t - 1] + a5 * a[t - 1]
        )
        u[t] = np.linalg.solve(K_bar, F_bar)
        a[t] = a0 * (u[t] - u[t - 1]) - a2 * v[t - 1] - a3 * a[t - 1]
        v[t] = v[t - 1] + a6 * a[t - 1] + a7 * a[t]
    return u, v, a


# ---------------------------------------------------------------------------------------------
# Inverse Newmark-β, one vehicle model at a time


def sprung_mass_inverse(m, k, acc, dt, initial, gamma=0.8, beta=None):
    """Sprung mass, §2.3.1, eq. (2.11)–(2.16): the profile from the measured acceleration.

    ``m`` (kg), ``k`` (N/m); ``acc`` (n,) m/s²; ``initial`` = (u, v, a) of the mass at the first sample.
    """
    a0, a1, a2, a3, a4, a5, a6, a7 = newmark_constants(dt, gamma, beta)
    u, v, a = (float(np.ravel(x)[0]) for x in initial)
    y = [(m * a + k * u) / k]  # equation of motion at the first sample
    for t in range(1, len(acc)):
        a_new = float(acc[t])
        u_new = (a_new + a2 * v + a3 * a) / a0 + u  # (2.11)
        v_new = v + a6 * a + a7 * a_new  # (2.12), errata: a6 multiplies the acceleration
        K_bar = k + a0 * m  # (2.13)
        F_bar = K_bar * u_new  # (2.14)
        F = F_bar - m * (a0 * u + a2 * v + a3 * a)  # (2.15)
        y.append(F / k)  # (2.16)
        u, v, a = u_new, v_new, a_new
    return np.array(y)[:, None]


def quarter_car_inverse(M, m, K, k, c, acc, dt, initial, gamma=0.8, beta=None):
    """Quarter-car, App. B.3, eq. (B.26)–(B.37): the profile from the body acceleration.

    DOFs (body u_s, axle u_u); ``initial`` = (u, v, a), each a pair. (B.25) is used as corrected.
    """
    a0, a1, a2, a3, a4, a5, a6, a7 = newmark_constants(dt, gamma, beta)
    M1 = [[M, 0.0], [0.0, m]]  # (B.23)
    C1 = [[c, -c], [-c, c]]  # (B.24)
    K1 = [[K, -K], [-K, K + k]]  # (B.25), errata
    K_bar = [[K1[i][j] + a0 * M1[i][j] + a1 * C1[i][j] for j in range(2)] for i in range(2)]  # (B.34)
    (us, uu), (vs, vu), (as_, au) = ([float(x) for x in s] for s in initial)
    y = [(m * au + c * (vu - vs) + (K + k) * uu - K * us) / k]  # (B.29) at the first sample
    for t in range(1, len(acc)):
        as_new = float(acc[t])
        us_new = (as_new + a2 * vs + a3 * as_) / a0 + us  # (B.26)
        vs_new = vs + a7 * as_new + a6 * as_  # (B.27)
        uu_new = (  # (B.31): (B.30) substituted into the body equation (B.28)
            M * as_new + c * vs_new + K * us_new + c * a4 * vu + c * a5 * au + c * a1 * uu
        ) / (c * a1 + K)
        vu_new = a1 * (uu_new - uu) - a4 * vu - a5 * au  # (B.32)
        au_new = a0 * (uu_new - uu) - a2 * vu - a3 * au  # (B.33)
        F_bar = _matvec(K_bar, [us_new, uu_new])  # (B.35)
        inertia = _matvec(M1, [a0 * us + a2 * vs + a3 * as_, a0 * uu + a2 * vu + a3 * au])
        damping = _matvec(C1, [a1 * us + a4 * vs + a5 * as_, a1 * uu + a4 * vu + a5 * au])
        F = [F_bar[i] - inertia[i] - damping[i] for i in range(2)]  # (B.36)
        y.append(F[1] / k)  # (B.37): the tyre force is the second entry of f_v = {0, F_t}
        us, vs, as_ = us_new, vs_new, as_new
        uu, vu, au = uu_new, vu_new, au_new
    return np.array(y)[:, None]


def half_car_matrices(ms, Is, mu1, mu2, Ks1, Ks2, Cs1, Cs2, Kt1, Kt2, D1, D2):
    """M_v, C_v, K_v of the 4-DOF half-car, rows as in eq. (2.21)–(2.22); DOFs (u_s, θ_s, u_u1, u_u2)."""
    Mv = [[ms, 0, 0, 0], [0, Is, 0, 0], [0, 0, mu1, 0], [0, 0, 0, mu2]]
    Cv = [
        [Cs1 + Cs2, D1 * Cs1 - D2 * Cs2, -Cs1, -Cs2],
        [D1 * Cs1 - D2 * Cs2, D1**2 * Cs1 + D2**2 * Cs2, -D1 * Cs1, D2 * Cs2],
        [-Cs1, -D1 * Cs1, Cs1, 0],
        [-Cs2, D2 * Cs2, 0, Cs2],
    ]
    Kv = [
        [Ks1 + Ks2, D1 * Ks1 - D2 * Ks2, -Ks1, -Ks2],
        [D1 * Ks1 - D2 * Ks2, D1**2 * Ks1 + D2**2 * Ks2, -D1 * Ks1, D2 * Ks2],
        [-Ks1, -D1 * Ks1, Ks1 + Kt1, 0],
        [-Ks2, D2 * Ks2, 0, Ks2 + Kt2],
    ]
    return Mv, Cv, Kv


def half_car_inverse(ms, Is, mu1, mu2, Ks1, Ks2, Cs1, Cs2, Kt1, Kt2, D1, D2, acc, pitch_rate, dt, initial,
                     gamma=0.8, beta=None):
    """4-DOF half-car, §2.3.2, eq. (2.17)–(2.31): profiles under both axles.

    Measured: body bounce acceleration ``acc`` and pitch *rate* ``pitch_rate``. ``initial`` = (u, v, a),
    each of the four DOFs (u_s, θ_s, u_u1, u_u2).
    """
    a0, a1, a2, a3, a4, a5, a6, a7 = newmark_constants(dt, gamma, beta)
    Mv, Cv, Kv = half_car_matrices(ms, Is, mu1, mu2, Ks1, Ks2, Cs1, Cs2, Kt1, Kt2, D1, D2)
    K_bar = [[Kv[i][j] + a0 * Mv[i][j] + a1 * Cv[i][j] for j in range(4)] for i in range(4)]  # (2.28)
    u, v, a = ([float(x) for x in s] for s in initial)
    f0 = [p + q + r for p, q, r in zip(_matvec(Mv, a), _matvec(Cv, v), _matvec(Kv, u))]
    y = [[f0[2] / Kt1, f0[3] / Kt2]]
    # Coefficients of the eliminated body equations: (2.23) for axle 1 (D2·(2.21) + (2.22)), and the
    # mirror image for axle 2 (D1·(2.21) − (2.22), which removes u_u1), not printed in the thesis.
    c1, k1 = (D2 + D1) * Cs1, (D2 + D1) * Ks1
    c2, k2 = (D1 + D2) * Cs2, (D1 + D2) * Ks2
    for t in range(1, len(acc)):
        us, th, uu1, uu2 = u
        vs, thd, vu1, vu2 = v
        as_, thdd, au1, au2 = a
        # Step 1: the body by Newmark-β from its measured bounce acceleration and pitch rate
        as_new = float(acc[t])
        us_new = (as_new + a2 * vs + a3 * as_) / a0 + us  # (2.17)
        vs_new = vs + a6 * as_ + a7 * as_new  # (2.18), errata
        thd_new = float(pitch_rate[t])
        th_new = (thd_new + a4 * thd + a5 * thdd) / a1 + th  # (2.19)
        thdd_new = a0 * (th_new - th) - a2 * thd - a3 * thdd  # (2.20)
        # Step 2: the axle displacements from the body equations, (2.24) substituted into (2.23)
        uu1_new = (  # (2.25), errata in (2.23): the pitch term is I_s·θ̈_s
            D2 * ms * as_new + Is * thdd_new + c1 * vs_new + (D2 * D1 * Cs1 + D1**2 * Cs1) * thd_new
            + k1 * us_new + (D2 * D1 * Ks1 + D1**2 * Ks1) * th_new + c1 * (a1 * uu1 + a4 * vu1 + a5 * au1)
        ) / (k1 + c1 * a1)
        uu2_new = (
            D1 * ms * as_new - Is * thdd_new + c2 * vs_new - (D1 * D2 * Cs2 + D2**2 * Cs2) * thd_new
            + k2 * us_new - (D1 * D2 * Ks2 + D2**2 * Ks2) * th_new + c2 * (a1 * uu2 + a4 * vu2 + a5 * au2)
        ) / (k2 + c2 * a1)
        # Step 3: axle accelerations and velocities by Newmark-β
        au1_new = a0 * (uu1_new - uu1) - a2 * vu1 - a3 * au1  # (2.26)
        vu1_new = vu1 + a6 * au1 + a7 * au1_new  # (2.27)
        au2_new = a0 * (uu2_new - uu2) - a2 * vu2 - a3 * au2
        vu2_new = vu2 + a6 * au2 + a7 * au2_new
        # Step 4: the force vector f_v = {0, 0, F_t1, F_t2}
        u_new = [us_new, th_new, uu1_new, uu2_new]
        f_bar = _matvec(K_bar, u_new)  # (2.29)
        inertia = _matvec(Mv, [a0 * u[i] + a2 * v[i] + a3 * a[i] for i in range(4)])
        damping = _matvec(Cv, [a1 * u[i] + a4 * v[i] + a5 * a[i] for i in range(4)])
        f = [f_bar[i] - inertia[i] - damping[i] for i in range(4)]  # (2.30)
        # Step 5: the profile under each tyre
        y.append([f[2] / Kt1, f[3] / Kt2])  # (2.31)
        u = u_new
        v = [vs_new, thd_new, vu1_new, vu2_new]
        a = [as_new, thdd_new, au1_new, au2_new]
    return np.array(y)


def generic_inverse(system, channels, dt, initial, gamma=0.8, beta=None):
    """Any :class:`~shared.vehicles.VehicleSystem` (used for the bogie half-car, which has no printed
    equations): the steps of ``shared.dynamics.inverse``, re-solved from scratch at every sample.

    ``initial`` = (u, v, a, y, ẏ). Each step: Newmark-β on the measured DOFs; the equations of
    motion at t+Δt solved for the unmeasured accelerations and the contact forces g; y from
    g = kc·y (tyre) or from kc·y + cc·ẏ = g by the trapezoidal rule (contact damper).
    """
    if beta is None:
        beta = 0.25 * (0.5 + gamma) ** 2
    M, C, K, G = system.M, system.C, system.K, system.G
    n, nc = system.n_dof, system.n_contacts
    measured = [ch.dof for ch in system.channels]
    free = [i for i in range(n) if i not in measured]
    u, v, a, y, ydot = (np.array(x, float) for x in initial[:5])  # (ÿ is for the Newmark contact rule)
    out = [y.copy()]
    for t in range(1, len(channels)):
        # Newmark predictors: what u, v at t+Δt would be with zero new acceleration
        u_pred = u + dt * v + dt * dt * (0.5 - beta) * a
        v_pred = v + dt * (1.0 - gamma) * a
        a_new = np.zeros(n)
        for ch, value in zip(system.channels, channels[t]):
            if ch.kind == "acc":
                a_new[ch.dof] = value
            else:  # a measured rate fixes the acceleration through v(t+Δt) = v_pred + γΔt·a(t+Δt)
                a_new[ch.dof] = (value - v_pred[ch.dof]) / (gamma * dt)
        # Unknowns x = (a_new[free], g):  M a + C (v_pred + γΔt a) + K (u_pred + βΔt² a) = G g
        S = np.zeros((n, len(free) + nc))
        for col, i in enumerate(free):
            S[:, col] = M[:, i] + gamma * dt * C[:, i] + beta * dt * dt * K[:, i]
        S[:, len(free):] = -G
        a_meas = np.zeros(n)
        a_meas[measured] = a_new[measured]
        rhs = -(M @ a_meas + C @ (v_pred + gamma * dt * a_meas) + K @ (u_pred + beta * dt * dt * a_meas))
        x = np.linalg.solve(S, rhs)
        a_new[free] = x[: len(free)]
        g = x[len(free):]
        u = u_pred + beta * dt * dt * a_new
        v = v_pred + gamma * dt * a_new
        a = a_new
        y_new = np.empty(nc)
        for i in range(nc):
            kc, cc = system.kc[i], system.cc[i]
            if cc == 0.0:
                y_new[i] = g[i] / kc
            else:  # kc·y + cc·ẏ = g with ẏ(t+Δt) = 2(y(t+Δt) − y(t))/Δt − ẏ(t)
                y_new[i] = (g[i] + cc * (2.0 * y[i] / dt + ydot[i])) / (kc + 2.0 * cc / dt)
                ydot[i] = 2.0 * (y_new[i] - y[i]) / dt - ydot[i]
        y = y_new
        out.append(y.copy())
    return np.array(out)


def bogie_half_car_inverse(vehicle, channels, dt, initial, gamma=0.8, beta=None):
    """The 2-DOF bogie half-car (Table 3.2): the generic loop on its system."""
    return generic_inverse(vehicle.system(), channels, dt, initial, gamma, beta)

