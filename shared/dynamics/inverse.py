"""Inverse Newmark-β: the apparent profile under each contact from the measured body channels.

The thesis derives the inverse step by step for each vehicle (§2.3, App. B). Here one general step
serves every :class:`~shared.vehicles.VehicleSystem`:

1. measured DOFs: the measured acceleration (or the acceleration implied by a measured rate) is
   integrated by Newmark-β into displacement and velocity (eq. 2.11–2.12, 2.19–2.20);
2. the equations of motion at t+Δt are solved *together* for the accelerations of the unmeasured
   DOFs (axles, or a carriage body) and the contact forces g = kc·y + cc·ẏ — the thesis's
   elimination (eq. 2.23–2.25, B.31) is this solve written out for one model;
3. the profile follows from g: y = g/kc for a tyre (eq. 2.16, 2.31), or, where the contact has a
   damper (bogie on the rail), from the first-order ODE kc·y + cc·ẏ = g by the trapezoidal rule
   (``contact_rule="trapezoid"``, default), or by Newmark's own (γ, β) relations between y, ẏ and ÿ
   (``contact_rule="newmark"``: the rule a coupled train–track Newmark simulation obeys, whose wheel
   displacement *is* the AP; the two coincide for γ = ½, β = ¼).

For fixed vehicle parameters the step is a linear time-invariant map, so it is compiled once into
a state-space recursion  s' = A s + B z,  y = C s + D z  (probing the readable step with unit
vectors); the readable step stays as the definition and the test reference. For speed the
recursion runs in coordinates where A is block diagonal (:func:`realise`): the neutral integrators
of the measured DOFs in one small block, every decaying mode in a 2×2 or 1×1 block, and modes the
output never sees dropped, so a sample costs O(n) multiply-adds instead of O(n²). Small numba
kernels run it for one stream or for many interleaved streams; the state carries across chunks,
so output never depends on chunking.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..jit import fma_kernel
from ..vehicles.base import VehicleSystem
from .newmark import NewmarkConstants, newmark_constants

# ---------------------------------------------------------------------------------------------
# The readable step (definition and reference)


class InverseState(NamedTuple):
    """Newmark state of every DOF plus the contact ODE state (y, ẏ, ÿ) of each contact.

    ``yddot`` is only used by the ``"newmark"`` contact rule; None reads as zeros.
    """

    u: np.ndarray
    v: np.ndarray
    a: np.ndarray
    y: np.ndarray
    ydot: np.ndarray
    yddot: np.ndarray | None = None

    @classmethod
    def zeros(cls, system: VehicleSystem) -> "InverseState":
        n, nc = system.n_dof, system.n_contacts
        return cls(np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(nc), np.zeros(nc), np.zeros(nc))

    def as_vector(self) -> np.ndarray:
        yddot = np.zeros(len(self.y)) if self.yddot is None else self.yddot
        return np.concatenate([self.u, self.v, self.a, self.y, self.ydot, yddot])

    @classmethod
    def from_vector(cls, system: VehicleSystem, s: np.ndarray) -> "InverseState":
        n, nc = system.n_dof, system.n_contacts
        return cls(s[:n], s[n : 2 * n], s[2 * n : 3 * n], s[3 * n : 3 * n + nc], s[3 * n + nc : 3 * n + 2 * nc],
                   s[3 * n + 2 * nc :])


CONTACT_RULES = ("trapezoid", "newmark")


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
    system: VehicleSystem, c: NewmarkConstants, state: InverseState, z: np.ndarray, _solve=None,
    contact_rule: str = "trapezoid",
) -> tuple[InverseState, np.ndarray]:
    """Advance one sample: ``z`` holds the measured channels at t+Δt; returns (state, y at t+Δt).

    ``contact_rule`` integrates a damped contact's kc·y + cc·ẏ = g: ``"trapezoid"`` or ``"newmark"``
    (see the module docstring).
    """
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
    yddot = np.zeros(system.n_contacts)
    y_acc = np.zeros(system.n_contacts) if state.yddot is None else state.yddot
    for i in range(system.n_contacts):
        kc, cc = system.kc[i], system.cc[i]
        if cc == 0.0:
            y[i] = g[i] / kc
        elif contact_rule == "trapezoid":  # kc·y + cc·ẏ = g, trapezoidal rule (A-stable, second order)
            y[i] = (g[i] + cc * (2.0 * state.y[i] / dt + state.ydot[i])) / (kc + 2.0 * cc / dt)
            ydot[i] = 2.0 * (y[i] - state.y[i]) / dt - state.ydot[i]
        else:  # Newmark: y, ẏ are the predictors plus βΔt²ÿ, γΔtÿ; solve kc·y + cc·ẏ = g for ÿ
            y_pred = state.y[i] + dt * state.ydot[i] + dt * dt * (0.5 - beta) * y_acc[i]
            v_pred_c = state.ydot[i] + dt * (1.0 - gamma) * y_acc[i]
            yddot[i] = (g[i] - kc * y_pred - cc * v_pred_c) / (kc * beta * dt * dt + cc * gamma * dt)
            y[i] = y_pred + beta * dt * dt * yddot[i]
            ydot[i] = v_pred_c + gamma * dt * yddot[i]
    return InverseState(u, v, a, y, ydot, yddot), y




# ---------------------------------------------------------------------------------------------
# Compiled form


class InverseModel(NamedTuple):
    """The inverse of one vehicle at one time step as a state-space recursion.

    ``A, B, C, D`` act on the full :class:`InverseState` vector entries indexed by ``keep`` (the
    ones the recursion needs). ``realisation`` is the same recursion in the cheaper coordinates the
    kernels run in (see :func:`realise`). ``n_warmup`` is the number of samples after which a wrong
    initial state has decayed to 1e-4 of its effect, except for the integrators' offset and drift
    (removed by drift control).
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    keep: np.ndarray
    n_warmup: int
    system: VehicleSystem
    constants: NewmarkConstants
    realisation: "Realisation | None" = None
    contact_rule: str = "trapezoid"


class Realisation(NamedTuple):
    """The recursion s' = A s + B z, y = C s + D z in coordinates w = Tinv·s where A is block diagonal.

    Blocks, in order: a leading dense block of size ``nd`` (the neutral integrators of the measured
    DOFs, |λ| = 1, plus any cluster that cannot be split further), ``p`` 2×2 blocks (a complex pair
    of decaying modes, two nearly equal real ones, or two separate real ones) and ``q`` 1×1 blocks
    (at most one real mode). Modes the output never sees are dropped, so a sample costs about
    3·r multiply-adds for r kept states instead of n² + 2n. ``form`` is ``"modal"`` for this, or
    ``"dense"`` (T = I, one dense block) where no well-conditioned transform was found.
    """

    form: str
    T: np.ndarray  # (n_keep, r): s = T w, up to modes the output never sees
    Tinv: np.ndarray  # (r, n_keep)
    Ad: np.ndarray  # (nd, nd)
    A2: np.ndarray  # (p, 4): each 2×2 block row-major
    A1: np.ndarray  # (q,)
    B: np.ndarray  # (r, n_in)
    C: np.ndarray  # (n_out, r)
    D: np.ndarray  # (n_out, n_in)

    @property
    def structure(self) -> tuple[int, int, int]:
        """(nd, p, q): realisations with equal structure can share one bank kernel."""
        return self.Ad.shape[0], self.A2.shape[0], self.A1.shape[0]

    def run(self, s0: np.ndarray, z: np.ndarray) -> np.ndarray:
        """The outputs y (n, n_out) of the recursion from state ``s0`` (n_keep,), in the original
        coordinates, over the inputs ``z`` (n, n_in)."""
        z = np.ascontiguousarray(z, dtype=float)
        y = np.empty((len(z), self.C.shape[0]))
        _run_blocks(self.Ad, self.A2, self.A1, self.B, self.C, self.D, self.Tinv @ s0, z, y)
        return y


def dense_realisation(A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray) -> Realisation:
    """The recursion as it is: one dense block, T = I."""
    n = A.shape[0]
    f = np.ascontiguousarray
    return Realisation("dense", np.eye(n), np.eye(n), f(A), np.zeros((0, 4)), np.zeros(0), f(B), f(C), f(D))


#: Largest condition number accepted for the similarity transform in the balanced coordinates
#: (the balancing itself is an exact power-of-two scaling). Newmark's spurious roots near
#: (γ − 1)/γ = −0.25 of different DOFs lie close together, so cond ~1e6 is common; 1e8 × 1e-16 is
#: still far below what any measurement resolves, and a 256-sample comparison with the dense
#: recursion (relative 1e-9) is the final check.
MAX_TRANSFORM_COND = 1e8
#: Eigenvalues below this modulus form one (possibly defective) nilpotent cluster.
_TINY_EIGENVALUE = 1e-5
#: Real eigenvalues closer than this share a block (they may be defective); tried in turn: the
#: second, coarser, clustering rescues near-coincident triples (they join the dense block).
_CLOSE_EIGENVALUES = (1e-4, 1e-2)
#: A block whose output weight is below this fraction of the output matrix's norm is unobservable.
_UNOBSERVABLE = 1e-12


def realise(A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, neutral_tol: float = 1e-6) -> Realisation:
    """A block-diagonal realisation of s' = A s + B z, y = C s + D z with the same input→output map.

    In the diagonally balanced coordinates of A, the eigenvalues are grouped into clusters: the
    neutral ones (|λ| ≥ 1 − ``neutral_tol``: the integrators), the tiny ones (|λ| < 1e-5: Newmark's
    pure input delays, possibly defective), then each complex pair, each pair of (nearly) equal
    real eigenvalues, and each single real one. The clusters are peeled off one at a time: an
    ordered real Schur form brings the cluster to the top of what is left and a Sylvester equation
    decouples it. Single real modes are then paired into diagonal 2×2 blocks, so the structure
    depends only on the model (not on its parameter values, at a given γ), and blocks the output
    never sees are dropped, which is exact for any initial state because the blocks no longer feed
    each other. Real eigenvalues are first chained when less than 1e-4 apart; if the transform is
    then ill-conditioned, chains up to 1e-2 apart are tried, and chains of more than two modes join
    the leading dense block.

    Falls back to :func:`dense_realisation` when a step fails, the transform's condition number
    exceeds :data:`MAX_TRANSFORM_COND`, or a 256-sample check against the dense recursion disagrees.
    """
    A, B, C, D = (np.asarray(X, dtype=np.float64) for X in (A, B, C, D))
    dense = dense_realisation(A, B, C, D)
    if A.shape[0] < 2:
        return dense
    for close in _CLOSE_EIGENVALUES:
        try:
            fast = _modal_realisation(A, B, C, D, neutral_tol, close)
        except (np.linalg.LinAlgError, ValueError, ArithmeticError):
            continue
        if fast is not None and _agrees(fast, dense, A):
            return fast
    return dense


def _clusters(lam: np.ndarray, neutral_tol: float, close: float) -> list[tuple[str, np.ndarray]] | None:
    """Eigenvalues grouped into blocks: ("neutral", …), ("tiny", …), then complex pairs and chains
    of real eigenvalues less than ``close`` apart ("pair" if two, "big" if more) and single reals."""
    mod = np.abs(lam)
    rest = lam[(mod < 1.0 - neutral_tol) & (mod >= _TINY_EIGENVALUE)]
    clusters = [("neutral", lam[mod >= 1.0 - neutral_tol]), ("tiny", lam[mod < _TINY_EIGENVALUE])]
    clusters += [("pair", np.array([x, np.conj(x)])) for x in rest[rest.imag > 0]]
    if 2 * (len(clusters) - 2) != np.count_nonzero(rest.imag != 0):
        return None
    reals = np.sort(rest[rest.imag == 0].real)[::-1]
    chains = np.split(reals, np.flatnonzero(-np.diff(reals) >= close) + 1) if len(reals) else []
    kinds = {1: "single", 2: "pair"}
    clusters += [(kinds.get(len(c), "big"), c.astype(complex)) for c in chains]
    return sorted(clusters, key=lambda kc: ["neutral", "tiny", "pair", "big", "single"].index(kc[0]))


def _modal_realisation(A, B, C, D, neutral_tol, close):
    import scipy.linalg as sla  # heavy import, only when a model is built

    n = A.shape[0]
    _, (scale, _) = sla.matrix_balance(A, permute=False, separate=True)  # exact powers of two
    Ab = A * scale[None, :] / scale[:, None]
    clusters = _clusters(np.linalg.eigvals(Ab), neutral_tol, close)
    if clusters is None:
        return None

    def selects(index):
        """Schur sort predicate: the group's own criterion, or being nearest to the cluster's values."""
        kind, _ = clusters[index]
        if kind == "neutral":
            return lambda re, im: np.hypot(re, im) >= 1.0 - neutral_tol
        if kind == "tiny":
            return lambda re, im: np.hypot(re, im) < _TINY_EIGENVALUE
        values = np.concatenate([c for _, c in clusters[index:]])
        owner = np.concatenate([np.full(len(c), i) for i, (_, c) in enumerate(clusters[index:])])
        return lambda re, im: owner[np.argmin(np.abs(complex(re, im) - values))] == 0

    # Peel the clusters off one at a time: an ordered real Schur form of what is left brings the
    # cluster to the top, then Y = [[I, X], [0, I]] with T11 X − X T22 = −T12 decouples it.
    P, Pinv = np.eye(n), np.eye(n)
    rest = Ab
    spans: list[tuple[int, int]] = []
    pos = 0
    for index, (_, cluster) in enumerate(clusters):
        k = len(cluster)
        if k == 0:
            spans.append((pos, pos))
            continue
        Ts, Zs, sdim = sla.schur(rest, output="real", sort=selects(index))
        if sdim != k:
            return None
        P[:, pos:] = P[:, pos:] @ Zs
        Pinv[pos:] = Zs.T @ Pinv[pos:]
        if pos + k < n:
            X = sla.solve_sylvester(Ts[:k, :k], -Ts[k:, k:], -Ts[:k, k:])
            P[:, pos + k :] += P[:, pos : pos + k] @ X
            Pinv[pos : pos + k] -= X @ Pinv[pos + k :]
        rest = Ts[k:, k:]
        spans.append((pos, pos + k))
        pos += k
    if not np.isfinite(P).all() or np.linalg.cond(P) > MAX_TRANSFORM_COND:
        return None
    # Drop blocks the output never sees. The neutral group, an observable tiny group and clusters of
    # more than two modes make up the leading dense block.
    Cw = (C * scale[None, :]) @ P
    c_ref = np.linalg.norm(C * scale[None, :], 2)

    def seen(span):
        return span[1] > span[0] and np.linalg.norm(Cw[:, span[0] : span[1]], 2) > _UNOBSERVABLE * c_ref

    kinds = [kind for kind, _ in clusters]
    lead = [c for kind, span in zip(kinds, spans) if kind == "neutral" or (kind in ("tiny", "big") and seen(span))
            for c in range(*span)]
    blocks2 = [list(range(*span)) for kind, span in zip(kinds, spans) if kind == "pair" and seen(span)]
    n_coupled = len(blocks2)
    singles = [span[0] for kind, span in zip(kinds, spans) if kind == "single" and seen(span)]
    blocks2 += [singles[i : i + 2] for i in range(0, len(singles) - 1, 2)]  # two real modes share a block
    blocks1 = singles[-1:] if len(singles) % 2 else []
    order = lead + [c for blk in blocks2 for c in blk] + blocks1
    Af = (Pinv @ Ab @ P)[np.ix_(order, order)]
    nd, p, q = len(lead), len(blocks2), len(blocks1)
    structured = np.zeros_like(Af)
    structured[:nd, :nd] = Af[:nd, :nd]
    A2 = np.zeros((p, 4))
    for b in range(p):
        i = nd + 2 * b
        A2[b] = Af[i : i + 2, i : i + 2].ravel()
        if b >= n_coupled:  # two separate real modes: their coupling is rounding noise
            A2[b, 1] = A2[b, 2] = 0.0
        structured[i : i + 2, i : i + 2] = A2[b].reshape(2, 2)
    A1 = np.array([Af[nd + 2 * p + b, nd + 2 * p + b] for b in range(q)])
    for b in range(q):
        structured[nd + 2 * p + b, nd + 2 * p + b] = A1[b]
    if np.linalg.norm(Af - structured) > 1e-10 * max(np.linalg.norm(Af), 1.0):
        return None
    T = scale[:, None] * P[:, order]
    Tinv = Pinv[order] / scale[None, :]
    f = np.ascontiguousarray
    return Realisation("modal", f(T), f(Tinv), f(Af[:nd, :nd]), A2, A1, f(Tinv @ B), f(C @ T), f(D))


def _agrees(fast: Realisation, dense: Realisation, A: np.ndarray, n_check: int = 256) -> bool:
    """Run both realisations from one random state on one random input; compare the outputs."""
    import scipy.linalg as sla  # heavy import, only when a model is built

    rng = np.random.default_rng(12345)
    _, (scale, _) = sla.matrix_balance(A, permute=False, separate=True)
    s0 = scale * rng.standard_normal(A.shape[0])  # every mode excited at its natural scale
    z = rng.standard_normal((n_check, dense.B.shape[1]))
    y_dense = np.empty((n_check, dense.C.shape[0]))
    y_fast = np.empty_like(y_dense)
    _run_blocks(dense.Ad, dense.A2, dense.A1, dense.B, dense.C, dense.D, s0.copy(), z, y_dense)
    _run_blocks(fast.Ad, fast.A2, fast.A1, fast.B, fast.C, fast.D, fast.Tinv @ s0, z, y_fast)
    ref = np.abs(y_dense).max()
    return bool(np.isfinite(y_fast).all() and np.abs(y_fast - y_dense).max() <= 1e-9 * max(ref, 1e-300))


#: Newmark γ of the edge's inverse at the logger rate, by vehicle model (default the thesis's 0.8),
#: and of every cloud step that reconstructs the measured channels from an AP (the round trip is
#: exact only at the same γ). γ = 0.8 (the thesis's, at Δt = 1 ms) adds numerical damping that at
#: a 2 ms step biases a quarter-car's calibration against the continuous physics, and a fleet fitted
#: with the same model agrees on the biased values. γ = 0.6 keeps the spurious roots decaying (at
#: −2/3) with a third of the damping. Half-cars stay at 0.8: at 0.6 their AP from the pitch rate is
#: implausible (the edge refuses it).
EDGE_GAMMA = {"quarter_car": 0.6, "sprung_mass": 0.6}


def edge_gamma(model: str) -> float:
    """The edge inverse's Newmark γ for a vehicle model (:data:`EDGE_GAMMA`)."""
    return EDGE_GAMMA.get(model, 0.8)


def build_inverse(
    system: VehicleSystem, dt: float, gamma: float = 0.8, beta: float | None = None, contact_rule: str = "trapezoid"
) -> InverseModel:
    """Compile the inverse step of ``system`` at time step ``dt`` (s) into state-space matrices.

    ``contact_rule``: how a damped contact's first-order ODE is integrated (module docstring).
    """
    if contact_rule not in CONTACT_RULES:
        raise ValueError(f"contact_rule: must be one of {CONTACT_RULES}, got {contact_rule!r}")
    c = newmark_constants(dt, gamma, beta)
    solve = _solve_matrix(system, c)
    n_state = 3 * system.n_dof + 3 * system.n_contacts
    n_in, n_out = len(system.channels), system.n_contacts
    A = np.zeros((n_state, n_state))
    B = np.zeros((n_state, n_in))
    C = np.zeros((n_out, n_state))
    D = np.zeros((n_out, n_in))
    zero_state, zero_in = np.zeros(n_state), np.zeros(n_in)
    for j in range(n_state):
        e = zero_state.copy()
        e[j] = 1.0
        s1, y = inverse_step(system, c, InverseState.from_vector(system, e), zero_in, solve, contact_rule)
        A[:, j], C[:, j] = s1.as_vector(), y
    for m in range(n_in):
        e = zero_in.copy()
        e[m] = 1.0
        s1, y = inverse_step(system, c, InverseState.from_vector(system, zero_state), e, solve, contact_rule)
        B[:, m], D[:, m] = s1.as_vector(), y
    # Drop state entries nothing reads (e.g. a tyre contact's ẏ), repeatedly.
    keep = np.arange(n_state)
    while True:
        used = np.any(A[np.ix_(keep, keep)] != 0, axis=0) | np.any(C[:, keep] != 0, axis=0)
        if used.all():
            break
        keep = keep[used]
    A, B, C = A[np.ix_(keep, keep)], B[keep], C[:, keep]
    neutral_tol = 1e-6
    eig = np.abs(np.linalg.eigvals(A)) if len(keep) else np.zeros(0)
    decaying = eig[eig < 1.0 - neutral_tol]
    rho = float(decaying.max()) if decaying.size else 0.0
    n_warmup = 1 if rho <= 1e-12 else int(math.ceil(math.log(1e-4) / math.log(rho)))
    return InverseModel(A, B, C, D, keep, max(n_warmup, 1), system, c, realise(A, B, C, D, neutral_tol), contact_rule)


# FMA contraction only (no reassociation): the bank kernel matches the single-stream one bit for bit.
@fma_kernel
def _run_blocks(Ad, A2, A1, B, C, D, w, z, y):
    """y_k = C w + D z_k ; w' = A w + B z_k over all samples k, A block diagonal (see Realisation).

    ``w`` (r,) is updated in place; z (K, n_in), y (K, n_out).
    """
    n_samples, n_in = z.shape
    n_out = y.shape[1]
    nd, p, q = Ad.shape[0], A2.shape[0], A1.shape[0]
    r = nd + 2 * p + q
    tmp = np.empty(nd)
    for k in range(n_samples):
        for o in range(n_out):
            acc = 0.0
            for j in range(r):
                acc += C[o, j] * w[j]
            for m in range(n_in):
                acc += D[o, m] * z[k, m]
            y[k, o] = acc
        for i in range(nd):
            acc = 0.0
            for j in range(nd):
                acc += Ad[i, j] * w[j]
            for m in range(n_in):
                acc += B[i, m] * z[k, m]
            tmp[i] = acc
        for i in range(nd):
            w[i] = tmp[i]
        for b in range(p):
            i = nd + 2 * b
            w0 = w[i]
            w1 = w[i + 1]
            acc0 = 0.0
            acc0 += A2[b, 0] * w0
            acc0 += A2[b, 1] * w1
            acc1 = 0.0
            acc1 += A2[b, 2] * w0
            acc1 += A2[b, 3] * w1
            for m in range(n_in):
                acc0 += B[i, m] * z[k, m]
                acc1 += B[i + 1, m] * z[k, m]
            w[i] = acc0
            w[i + 1] = acc1
        for b in range(q):
            i = nd + 2 * p + b
            acc = 0.0
            acc += A1[b] * w[i]
            for m in range(n_in):
                acc += B[i, m] * z[k, m]
            w[i] = acc


@fma_kernel
def _run_blocks_bank(Ad, A2, A1, B, C, D, w, z, y):
    """:func:`_run_blocks` for many streams, streams innermost (contiguous) so every loop vectorises.

    Ad (nd, nd, S), A2 (p, 4, S), A1 (q, S), B (r, n_in, S), C (n_out, r, S), D (n_out, n_in, S),
    w (r, S), z (K, n_in, S), y (K, n_out, S). Same operations in the same order as the single
    stream, so each stream's output is bit-identical to running it alone.
    """
    n_samples, n_in, n_streams = z.shape
    n_out = y.shape[1]
    nd, p, q = Ad.shape[0], A2.shape[0], A1.shape[0]
    r = nd + 2 * p + q
    tmp = np.empty((nd, n_streams))
    acc = np.empty(n_streams)
    acc1 = np.empty(n_streams)
    for k in range(n_samples):
        for o in range(n_out):
            for s in range(n_streams):
                acc[s] = 0.0
            for j in range(r):
                for s in range(n_streams):
                    acc[s] += C[o, j, s] * w[j, s]
            for m in range(n_in):
                for s in range(n_streams):
                    acc[s] += D[o, m, s] * z[k, m, s]
            for s in range(n_streams):
                y[k, o, s] = acc[s]
        for i in range(nd):
            for s in range(n_streams):
                tmp[i, s] = 0.0
            for j in range(nd):
                for s in range(n_streams):
                    tmp[i, s] += Ad[i, j, s] * w[j, s]
            for m in range(n_in):
                for s in range(n_streams):
                    tmp[i, s] += B[i, m, s] * z[k, m, s]
        for i in range(nd):
            for s in range(n_streams):
                w[i, s] = tmp[i, s]
        for b in range(p):
            i = nd + 2 * b
            for s in range(n_streams):
                w0 = w[i, s]
                w1 = w[i + 1, s]
                a0 = 0.0
                a0 += A2[b, 0, s] * w0
                a0 += A2[b, 1, s] * w1
                a1 = 0.0
                a1 += A2[b, 2, s] * w0
                a1 += A2[b, 3, s] * w1
                acc[s] = a0
                acc1[s] = a1
            for m in range(n_in):
                for s in range(n_streams):
                    acc[s] += B[i, m, s] * z[k, m, s]
                    acc1[s] += B[i + 1, m, s] * z[k, m, s]
            for s in range(n_streams):
                w[i, s] = acc[s]
                w[i + 1, s] = acc1[s]
        for b in range(q):
            i = nd + 2 * p + b
            for s in range(n_streams):
                a0 = 0.0
                a0 += A1[b, s] * w[i, s]
                acc[s] = a0
            for m in range(n_in):
                for s in range(n_streams):
                    acc[s] += B[i, m, s] * z[k, m, s]
            for s in range(n_streams):
                w[i, s] = acc[s]


def _initial_state(model: InverseModel, initial: InverseState | None, z0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The kept state entries and the output at the first sample.

    With ``initial`` that is the given state; without it the vehicle is taken at rest with the first
    measured values, which is all a logger switched on while driving knows.
    """
    system = model.system
    if initial is not None:
        state = initial
    else:
        state = InverseState.zeros(system)
        for ch, value in zip(system.channels, z0):
            (state.a if ch.kind == "acc" else state.v)[ch.dof] = value
    return state.as_vector()[model.keep], np.array(state.y, dtype=float)


def _realisation_of(model: InverseModel) -> Realisation:
    if model.realisation is not None:
        return model.realisation
    return dense_realisation(model.A, model.B, model.C, model.D)


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
        self._real = _realisation_of(model)
        self._s = np.zeros(self._real.Tinv.shape[0])
        self.n_seen = 0

    @property
    def reliable_from(self) -> int:
        """Index of the first sample not affected by the unknown initial state."""
        return 0 if self._initial is not None else self.model.n_warmup

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
            s0, out[0] = _initial_state(self.model, self._initial, z[0])
            self._s = self._real.Tinv @ s0
            start = 1
        r = self._real
        _run_blocks(r.Ad, r.A2, r.A1, r.B, r.C, r.D, self._s, z[start:], out[start:])
        self.n_seen += z.shape[0]
        return out


def apparent_profile(
    system: VehicleSystem,
    channels: np.ndarray,
    dt: float,
    initial: InverseState | None = None,
    gamma: float = 0.8,
    beta: float | None = None,
    contact_rule: str = "trapezoid",
) -> np.ndarray:
    """The whole-record convenience: AP (n_samples, n_contacts) from channels (n_samples, n_channels)."""
    return InverseStream(build_inverse(system, dt, gamma, beta, contact_rule), initial).update(channels)


class InverseBank:
    """Many vehicles of one model processed together (interleaved across streams, one kernel call).

    Every stream must have the same model (same state size); parameters may differ.
    ``update(z)`` takes (n_samples, n_channels, n_streams) and returns (n_samples, n_contacts,
    n_streams). Streams start at rest like :class:`InverseStream` without ``initial``, and each
    stream's output is bit-identical to that of its own :class:`InverseStream`. (Streams whose
    realisations differ in structure, e.g. one that fell back to the dense form, run as separate
    groups.)
    """

    def __init__(self, models: list[InverseModel]):
        if not models:
            raise ValueError("InverseBank: needs at least one model")
        keep = models[0].keep
        if any(not np.array_equal(m.keep, keep) for m in models):
            raise ValueError("InverseBank: all streams must share one vehicle model")
        self.models = models
        self._reals = [_realisation_of(m) for m in models]
        by_structure: dict[tuple, list[int]] = {}
        for q, r in enumerate(self._reals):
            by_structure.setdefault((r.form, r.structure), []).append(q)
        self._groups = [_BankGroup(np.array(idx), [self._reals[q] for q in idx]) for idx in by_structure.values()]
        self.n_seen = 0

    def update(self, z: np.ndarray) -> np.ndarray:
        z = np.ascontiguousarray(z, dtype=np.float64)
        n_channels = len(self.models[0].system.channels)
        if z.ndim != 3 or z.shape[1] != n_channels or z.shape[2] != len(self.models):
            raise ValueError(f"expected (n_samples, {n_channels}, {len(self.models)}), got {z.shape}")
        n_out = self.models[0].system.n_contacts
        out = np.empty((z.shape[0], n_out, z.shape[2]))
        if z.shape[0] == 0:
            return out
        start = 0
        if self.n_seen == 0:
            for group in self._groups:
                for j, q in enumerate(group.streams):
                    s0, out[0, :, q] = _initial_state(self.models[q], None, z[0, :, q])
                    group.s[:, j] = self._reals[q].Tinv @ s0
            start = 1
        if len(self._groups) == 1:
            self._groups[0].run(z[start:], out[start:])
        else:
            for group in self._groups:
                part = np.empty((z.shape[0] - start, n_out, len(group.streams)))
                group.run(np.ascontiguousarray(z[start:, :, group.streams]), part)
                out[start:, :, group.streams] = part
        self.n_seen += z.shape[0]
        return out


class _BankGroup:
    """Streams whose realisations share one block structure: matrices stacked streams-last."""

    def __init__(self, streams: np.ndarray, reals: list[Realisation]):
        self.streams = streams

        def stack(name):
            return np.ascontiguousarray(np.stack([getattr(r, name) for r in reals], axis=-1))

        self.Ad, self.A2, self.A1, self.B, self.C, self.D = (stack(x) for x in ("Ad", "A2", "A1", "B", "C", "D"))
        self.s = np.zeros((reals[0].Tinv.shape[0], len(reals)))

    def run(self, z: np.ndarray, y: np.ndarray) -> None:
        _run_blocks_bank(self.Ad, self.A2, self.A1, self.B, self.C, self.D, self.s, z, y)


_BANK_FIELDS = ("Ad", "A2", "A1", "B", "C", "D")
# The last bank's matrices per block structure: (its members' realisations, their stacks). A memo
# of this process (each entry replaced whole, never changed in place), not configuration.
_banks: dict[tuple, tuple[tuple, tuple[np.ndarray, ...]]] = {}


def _bank_matrices(key: tuple, reals: tuple) -> tuple[np.ndarray, ...]:
    """The realisations' matrices stacked along a last axis, one member each. A fleet's bank keeps
    most of its members from one chunk to the next, so the last bank's stacks are reused: whole
    when its members are the same, else the members it had taken from it in one indexing, and only
    those that join gathered one by one. (The same numbers either way: only copies.)"""
    last = _banks.get(key)
    if last is not None and len(last[0]) == len(reals) and all(a is b for a, b in zip(last[0], reals)):
        return last[1]
    at = {} if last is None else {id(r): j for j, r in enumerate(last[0])}
    new = [r for r in reals if id(r) not in at]
    for j, r in enumerate(new):
        at[id(r)] = len(last[0]) + j if last is not None else j
    order = np.array([at[id(r)] for r in reals], dtype=np.intp)
    stacks = []
    for f, name in enumerate(_BANK_FIELDS):
        parts = ([last[1][f]] if last is not None else []) + \
                ([np.stack([getattr(r, name) for r in new], axis=-1)] if new else [])
        source = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=-1)
        stacks.append(np.ascontiguousarray(source[..., order]))
    out = tuple(stacks)
    _banks[key] = (reals, out)
    return out


def update_streams(streams: list[InverseStream], z: np.ndarray) -> np.ndarray:
    """One chunk of each of many :class:`InverseStream` in one compiled call per block structure:
    ``z`` (n_samples, n_channels, n_streams) → AP (n_samples, n_contacts, n_streams), and each
    stream's state advanced, exactly as ``streams[s].update(z[:, :, s])`` each (bit for bit: the
    bank kernel does the single stream's operations in the same order). The streams must share a
    vehicle model (channels and contacts); members may change from call to call (an edge's fleet
    whose passes start and end): the last call's stacked matrices are kept per block structure and
    only what changed is gathered again.
    """
    z = np.ascontiguousarray(z, dtype=np.float64)
    if not streams:
        raise ValueError("update_streams: needs at least one stream")
    system = streams[0].model.system
    n_in, n_out = len(system.channels), system.n_contacts
    if z.ndim != 3 or z.shape[1] != n_in or z.shape[2] != len(streams):
        raise ValueError(f"expected (n_samples, {n_in}, {len(streams)}), got {z.shape}")
    systems = {id(s.model.system): s.model.system for s in streams}  # (a fleet's streams share a few)
    if any(len(sy.channels) != n_in or sy.n_contacts != n_out for sy in systems.values()):
        raise ValueError("update_streams: all streams must share one vehicle model")
    out = np.empty((z.shape[0], n_out, z.shape[2]))
    if z.shape[0] == 0:
        return out
    groups: dict[tuple, list[int]] = {}
    keys: dict[int, tuple] = {}  # a realisation's block structure, by id (a fleet's streams share a few)
    for q, s in enumerate(streams):
        if s.n_seen == 0:  # a stream's first chunk sets its initial state: run alone, as it would
            out[:, :, q] = s.update(z[:, :, q])
            continue
        r = s._real
        key = keys.get(id(r))
        if key is None:
            key = keys[id(r)] = (r.form, r.structure)
        groups.setdefault(key, []).append(q)
    for key, idx in groups.items():
        Ad, A2, A1, B, C, D = _bank_matrices(key, tuple(streams[q]._real for q in idx))
        # The states gathered and handed back in one copy each way (np.array of equal-length
        # arrays and the rows of a transposed copy: no per-stream array calls).
        w = np.ascontiguousarray(np.array([streams[q]._s for q in idx]).T)
        zz = z if len(idx) == len(streams) else np.ascontiguousarray(z[:, :, idx])
        y = out if len(idx) == len(streams) else np.empty((z.shape[0], n_out, len(idx)))
        _run_blocks_bank(Ad, A2, A1, B, C, D, w, zz, y)
        if y is not out:
            out[:, :, idx] = y
        for q, state in zip(idx, w.T.copy()):
            streams[q]._s = state
            streams[q].n_seen += z.shape[0]
    return out
