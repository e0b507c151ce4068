"""The inverse Newmark-β step of :mod:`shared.dynamics.inverse` for many parameter sets and runs in
one compiled call.

Calibration scores trial parameter sets by the apparent profiles (APs) they give: the Cross-Entropy
reference (:mod:`cloud.reference.cross_entropy`) a population on one vehicle's record, each run
with its own length and time step: trial ``t`` on run ``run_of[t]``, without compiling a state-space
model per trial. Same equations and initial state convention as :class:`~shared.dynamics.inverse.
InverseStream` without an initial state. (The rail batch calibration runs the carriage's own kernel,
with forward-mode derivatives and a body initial state, :func:`cloud.rail.carriage_inverse._inverse_kernel`;
its test checks it against this one.)

The kernel is compiled once per vehicle structure (number of DOFs, which are measured and how,
number of contacts), those being compile-time constants: numba then unrolls the small loops over
DOFs and contacts, much faster than reading the structure from arrays.
"""

from __future__ import annotations

import functools

import numpy as np

from ..jit import kernel


def inverse_runs(Sinv, M, C, K, kc, cc, dof, is_acc, free, run_of, z, lengths, dts, gamma, beta, out) -> None:
    """The inverse Newmark-β step (:func:`shared.dynamics.inverse.inverse_step`) for T parameter sets,
    trial t on run ``run_of[t]``'s channels ``z[run_of[t], :lengths[run_of[t]]]`` at step
    ``dts[run_of[t]]`` (s).

    Sinv (T, nf + nc, n) the inverse of [M + γΔt C + βΔt² K on the free DOFs | −G] at the trial's
    run's step; M/C/K (T, n, n); kc/cc (T, nc) the contacts' stiffness and damping; dof/is_acc
    (n_channels,) the DOF each channel measures and whether it is an acceleration (else a rate);
    free (nf,) the unmeasured DOFs; z (R, N, n_channels); lengths (R,); dts (R,); γ, β Newmark's.
    ``out`` (T, nc, N): the AP under each contact, contact-major — what a per-contact interpolation
    reads in one piece (beyond a run's length: untouched). The state starts at rest with the first
    measured values (a logger switched on while driving).
    """
    run = _compiled(M.shape[1], tuple(int(i) for i in dof), tuple(bool(b) for b in is_acc),
                    tuple(int(i) for i in free), kc.shape[1])
    run(Sinv, M, C, K, kc, cc, run_of, z, lengths, dts, gamma, beta, out)


@functools.cache
def _compiled(n, dof, is_acc, free, nc):
    """:func:`inverse_runs`' kernel for one structure: ``n`` DOFs, the measured ``dof`` and ``is_acc``
    (tuples, channel order), the ``free`` DOFs and ``nc`` contacts, closed over as constants (numba
    freezes closed-over arrays into the code, and caches one machine code per structure)."""
    nm = len(dof)
    nf = len(free)
    # arrays, not tuples: an empty tuple (a vehicle without free DOFs) cannot be indexed in numba
    dof = np.array(dof, dtype=np.int64)
    is_acc = np.array(is_acc, dtype=np.bool_)
    free = np.array(free, dtype=np.int64)

    @kernel
    def run(Sinv, M, C, K, kc, cc, run_of, z, lengths, dts, gamma, beta, out):
        T = M.shape[0]
        u = np.zeros(n)
        v = np.zeros(n)
        a = np.zeros(n)
        up = np.zeros(n)
        vp = np.zeros(n)
        known = np.zeros(n)
        y = np.zeros(nc)
        yd = np.zeros(nc)
        for t in range(T):
            r = run_of[t]
            dt = dts[r]
            bdt2 = beta * dt * dt
            gdt = gamma * dt
            for i in range(n):
                u[i] = 0.0
                v[i] = 0.0
                a[i] = 0.0
            for c in range(nc):
                y[c] = 0.0
                yd[c] = 0.0
                out[t, c, 0] = 0.0
            for m in range(nm):
                if is_acc[m]:
                    a[dof[m]] = z[r, 0, m]
                else:
                    v[dof[m]] = z[r, 0, m]
            for k in range(1, lengths[r]):
                for i in range(n):
                    up[i] = u[i] + dt * v[i] + dt * dt * (0.5 - beta) * a[i]
                    vp[i] = v[i] + dt * (1.0 - gamma) * a[i]
                for m in range(nm):
                    i = dof[m]
                    if is_acc[m]:
                        a[i] = z[r, k, m]
                    else:  # a measured rate: the acceleration Newmark's velocity update implies
                        a[i] = (z[r, k, m] - vp[i]) / gdt
                    u[i] = up[i] + bdt2 * a[i]
                    v[i] = vp[i] + gdt * a[i]
                for row in range(n):
                    s = 0.0
                    for m in range(nm):
                        i = dof[m]
                        s += M[t, row, i] * a[i] + C[t, row, i] * v[i] + K[t, row, i] * u[i]
                    for f in range(nf):
                        i = free[f]
                        s += C[t, row, i] * vp[i] + K[t, row, i] * up[i]
                    known[row] = s
                for q in range(nf + nc):
                    s = 0.0
                    for row in range(n):
                        s -= Sinv[t, q, row] * known[row]
                    if q < nf:
                        i = free[q]
                        a[i] = s
                        u[i] = up[i] + bdt2 * s
                        v[i] = vp[i] + gdt * s
                    else:
                        c = q - nf
                        if cc[t, c] == 0.0:
                            y[c] = s / kc[t, c]
                        else:  # kc·y + cc·ẏ = g by the trapezoidal rule
                            ynew = (s + cc[t, c] * (2.0 * y[c] / dt + yd[c])) / (kc[t, c] + 2.0 * cc[t, c] / dt)
                            yd[c] = 2.0 * (ynew - y[c]) / dt - yd[c]
                            y[c] = ynew
                        out[t, c, k] = y[c]

    return run
