"""Kernels on symmetric positive-definite banded matrices in LAPACK's lower storage.

A matrix ``A`` of half-bandwidth ``b`` on ``n`` points is held as ``ab[d, j] = A[j + d, j]``
(``(b + 1, n)``), its Cholesky factor ``L`` likewise as ``cb[d, j] = L[j + d, j]``. The profile
posterior (:mod:`.gmrf_profile`) and the drift nuisance it eliminates (:mod:`.pass_drift`) both
factorise, solve, take the band of the inverse and draw with them.
"""

from __future__ import annotations

import math

import numpy as np

from shared.jit import kernel


@kernel
def band_cholesky(ab):
    """Lower banded Cholesky factor (``cb[d, j] = L[j + d, j]``) of the lower banded ``ab``."""
    u1, n = ab.shape
    cb = ab.copy()
    for j in range(n):
        s = cb[0, j]
        for k in range(max(0, j - u1 + 1), j):
            s -= cb[j - k, k] * cb[j - k, k]
        if not s > 0.0:
            raise ValueError("matrix not positive definite")
        ljj = math.sqrt(s)
        cb[0, j] = ljj
        for d in range(1, min(u1, n - j)):
            i = j + d
            t = cb[d, j]
            for k in range(max(0, i - u1 + 1), j):
                t -= cb[i - k, k] * cb[j - k, k]
            cb[d, j] = t / ljj
    return cb


@kernel
def band_solve(cb, M):
    """``M ← (L Lᵀ)⁻¹ M`` in place for the banded factor ``cb`` and right-hand sides ``M`` (n, r)."""
    u1, n = cb.shape
    r = M.shape[1]
    for i in range(n):  # L y = M
        for d in range(1, min(u1, i + 1)):
            l = cb[d, i - d]
            for c in range(r):
                M[i, c] -= l * M[i - d, c]
        inv = 1.0 / cb[0, i]
        for c in range(r):
            M[i, c] *= inv
    for i in range(n - 1, -1, -1):  # Lᵀ x = y
        for d in range(1, min(u1, n - i)):
            l = cb[d, i]
            for c in range(r):
                M[i, c] -= l * M[i + d, c]
        inv = 1.0 / cb[0, i]
        for c in range(r):
            M[i, c] *= inv
    return M


@kernel
def selected_inverse(cb):
    """Band of ``Σ = (L Lᵀ)⁻¹`` from the lower banded Cholesky factor ``cb[d, i] = L[i + d, i]``.

    Takahashi recursion, from the last row up: ``Σ_ij = δ_ij / L_ii² − Σ_k L_ki Σ_kj / L_ii`` over
    ``i < k ≤ i + b``. Returns ``S[d, i] = Σ[i, i + d]`` for ``d ≤ b``. O(n b²).
    """
    u1, n = cb.shape
    b = u1 - 1
    S = np.zeros((u1, n))
    for i in range(n - 1, -1, -1):
        lii = cb[0, i]
        kmax = min(b, n - 1 - i)
        for dj in range(kmax, -1, -1):
            j = i + dj
            s = 0.0
            for dk in range(1, kmax + 1):
                k = i + dk
                v = S[j - k, k] if k <= j else S[k - j, j]
                s += cb[dk, i] * v
            if dj == 0:
                S[0, i] = (1.0 / lii - s) / lii
            else:
                S[dj, i] = -s / lii
    return S


@kernel
def draw_into(cb, mean, z):
    """Turn standard normal rows ``z`` (n_rhs, n) into ``mean + L⁻ᵀ z`` in place (back substitution)."""
    u1, n = cb.shape
    b = u1 - 1
    n_rhs = z.shape[0]
    inv = 1.0 / cb[0]  # a multiply, not a division, on the recurrence's critical path
    for r in range(n_rhs):
        for i in range(n - 1, -1, -1):
            acc = z[r, i]
            for d in range(1, min(b, n - 1 - i) + 1):
                acc -= cb[d, i] * z[r, i + d]
            z[r, i] = acc * inv[i]
        for i in range(n):
            z[r, i] += mean[i]
