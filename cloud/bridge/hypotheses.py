"""Damage as hypotheses the data can decide between, and the alarm.

Twenty free element stiffnesses are barely identifiable from a fleet of tens of vehicles; a
handful of physical hypotheses are. Each is a parametric stiffness model; every one also carries
an as-built tolerance on the global stiffness, ``g ~ N(0, tolerance_sd²)`` (EI = EI_design·e^g),
integrated by Gauss–Hermite nodes placed where the data put the level (:func:`_with_tolerance`):

* ``healthy``  — the design bridge (within tolerance);
* ``global``   — a uniform loss ``L ~ U(0, max_loss)`` (corrosion, thesis §3.5.3);
* ``crack``    — one crack at ``x_c ~ U(0, span)`` of depth ratio ``φ ~ U(0, max_phi)``, softening the
  elements around it by :func:`shared.fe.beam.crack_ei_factor` (thesis §4.5.1);
* ``bearings`` — seized bearings: rotational springs ``log10 Krot ~ U(lo, hi)`` at both supports
  (thesis §4.4), the FE influence line in closed form (a rank-2 update of the pinned span).

Every hypothesis can also carry an as-built scatter of the element stiffnesses about its model
(``element_sd``): no real span is uniform, and the railway scenarios give theirs 5 % per element.
Each element's compliance is the model's times ``1 + η_e``, ``η ~ N(0, element_sd² I)``, integrated
out by Laplace the linear-Gaussian way the weights are (the likelihood quadratic in the
influence-line coefficients — curvature at each hypothesis' best node, gradient at each node — and
the coefficients linear in η). Without it, a scattered span's soft elements have only the damage
hypotheses to go to: with enough data they read as a (shallow) crack. Scatter is as-built, not
damage: the alarm's loss stays the hypothesis' own. It costs detection — a φ = 10 % crack at 100
passes (2 % noise) loses its alarm at 5 % scatter (docs/results.md, Bridge) — so it is off by default
until a bridge can declare it.

The likelihood is the weight- and nuisance-marginal one of :mod:`cloud.bridge.likelihood`
(:func:`~cloud.bridge.likelihood.marginal_loglik_batch`); each hypothesis' parameters are integrated
on a grid (adaptive Gauss–Hermite in g), which gives its evidence, its posterior over parameters
and the posterior probability of the hypothesis. The alarm is raised when the model-averaged posterior
probability that some element lost more than ``alarm_loss`` of its design stiffness exceeds
``alarm_probability``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence

import numpy as np

from shared.fe.beam import (assemble, compliance_kernel, contact_matrix, crack_ei_factor, element_stiffness, free_dofs,
                            stiffness_matrix)

from cloud.bridge.likelihood import Stacked, VehicleStats, WeightPrior, marginal_loglik, marginal_loglik_batch
from cloud.bridge.setup import Setup

HYPOTHESES = ("healthy", "global", "crack", "bearings")
#: A crack is reported on an element when its location's 95 % interval spans at most this many
#: elements: wider, the passes say that the span lost stiffness but not where (on a rough deck the
#: deck profile takes most of what they say along the span), and the posterior mean location of a
#: broad posterior sits near mid-span whatever the truth.
LOCATED_ELEMENTS = 3.0


@dataclasses.dataclass(frozen=True)
class HypothesisSettings:
    """Priors and grids of the hypotheses, and the alarm rule."""

    tolerance_sd: float = 0.02  # as-built global stiffness tolerance (log scale)
    #: as-built per-element scatter of EI about each hypothesis' model (relative sd, on the registry's
    #: elements), integrated out (module docstring); 0: none (default: it costs crack detection at
    #: 100 passes). 0.05 is what the railway scenarios give their spans (simfleet/rail.py).
    element_sd: float = 0.0
    tolerance_nodes: int = 9  # Gauss–Hermite nodes for it
    max_loss: float = 0.5
    loss_step: float = 0.005
    max_phi: float = 0.5
    phi_step: float = 0.0125
    crack_step_m: float = 0.25
    log10_krot: tuple[float, float] = (6.0, 13.0)
    log10_krot_step: float = 0.1
    alarm_loss: float = 0.05
    alarm_probability: float = 0.95
    prior: tuple[tuple[str, float], ...] = (("healthy", 0.25), ("global", 0.25), ("crack", 0.25), ("bearings", 0.25))


@dataclasses.dataclass(frozen=True, eq=False)
class Grid:
    """One hypothesis on a grid: coefficient vectors, log prior weights (incl. cell measures),
    element stiffness ratios and named parameter values at every node."""

    name: str
    a: np.ndarray  # (K, n_b)
    log_weight: np.ndarray  # (K,)
    ratio: np.ndarray  # (K, n_e) EI/EI_design per element
    params: dict[str, np.ndarray]
    #: sensitivity of a to each element's relative compliance at node k: ``sens[sens_index[k]] *
    #: sens_scale[k]`` (columns scaled), (n_groups, n_b, n_e), (K,), (K, n_e)
    sens: np.ndarray | None = None
    sens_index: np.ndarray | None = None
    sens_scale: np.ndarray | None = None


@dataclasses.dataclass(frozen=True, eq=False)
class HypothesisResult:
    name: str
    log_evidence: float
    probability: float
    parameters: dict[str, tuple[float, float, float]]  # name → (mean, lo95, hi95)
    loss_probability: float  # P(max element loss > alarm_loss | hypothesis, data)
    element_ratio: np.ndarray  # posterior mean EI/EI_design per element


@dataclasses.dataclass(frozen=True, eq=False)
class Assessment:
    """The hypotheses' posterior probabilities, the best one's parameters, and the alarm decision.

    ``loss_probability``: model-averaged P(some element lost > ``alarm_loss``). ``element``
    (1-based; −1 for the whole bridge) and ``location_m`` locate the damage, ``severity`` is the
    posterior mean of the largest element loss under the most probable damage hypothesis, and
    ``severity_lo95``, ``severity_hi95`` its central 95 % interval under that hypothesis. A crack
    is placed on an element only when the data locate it (:data:`LOCATED_ELEMENTS`); otherwise
    ``element`` is −1 and ``location_lo95``, ``location_hi95`` say how far it could be.
    """

    results: dict[str, HypothesisResult]
    best: str
    alarm: bool
    loss_probability: float
    element: int
    location_m: float
    severity: float
    kind: str
    severity_lo95: float = float("nan")
    severity_hi95: float = float("nan")
    location_lo95: float = float("nan")
    location_hi95: float = float("nan")

    @property
    def probabilities(self) -> dict[str, float]:
        return {k: r.probability for k, r in self.results.items()}

    @property
    def parameters(self) -> dict[str, tuple[float, float, float]]:
        return self.results[self.best].parameters


# ---------------------------------------------------------------------------------------------
# Kernels


@dataclasses.dataclass(frozen=True, eq=False)
class Kernels:
    """Basis coefficients of the pieces every hypothesis' influence line is made of."""

    setup: Setup
    element: np.ndarray  # (n_b, n_e) compliance kernel columns G_z (m³)
    ei_design: float
    bearing_J: np.ndarray  # (n_b,) design pinned-span influence line, m/N
    bearing_zz: np.ndarray  # (n_b, 2, 2) coefficients of z_i(x)·z_j(x), the ends' rotations (rad/N)²
    bearing_C: np.ndarray  # (2, 2) end-rotation flexibility of the design span, rad/(N·m)

    @classmethod
    def of(cls, setup: Setup) -> "Kernels":
        basis = setup.basis
        x = basis.x
        beam = setup.beam
        G = compliance_kernel(beam, x)
        K = assemble(beam).K
        N = contact_matrix(beam, x)
        U = np.linalg.solve(K, N.T)  # (n_dof, n_x)
        J = np.einsum("ij,ji->i", N, U)
        E = np.zeros((K.shape[0], 2))
        E[0, 0] = E[-1, 1] = 1.0  # θ_0 and θ_n are the first and last free DOFs
        z = E.T @ U  # (2, n_x)
        Cf = E.T @ np.linalg.solve(K, E)
        zz = np.einsum("ix,jx->xij", z, z)
        return cls(setup, basis.coefficients(G.T).T, beam.E_pa * beam.I_m4, basis.coefficients(J),
                   np.einsum("bx,xij->bij", basis.projector, zz), Cf)

    @property
    def design_area(self) -> float:
        """∫J dx of the design (pinned) span, m²/N."""
        return float(self.bearing_J @ self.setup.basis.integrals)

    def simply_supported(self, ratio: np.ndarray) -> np.ndarray:
        """Coefficients of J for element stiffness ratios (K, n_e) → (K, n_b)."""
        return (1.0 / (self.ei_design * np.atleast_2d(ratio))) @ self.element.T

    def bearings(self, scale: np.ndarray, krot: np.ndarray) -> np.ndarray:
        """Coefficients of J of a uniform span (EI = scale·EI_design) with equal end springs ``krot``
        (N·m/rad): J = (J_d − zᵀ(scale/Krot·I + C)⁻¹z)/scale (Sherman–Morrison–Woodbury)."""
        scale, krot = np.broadcast_arrays(np.asarray(scale, float), np.asarray(krot, float))
        eye = np.eye(2)
        M = np.linalg.inv((scale / krot)[..., None, None] * eye + self.bearing_C)  # (K, 2, 2)
        corr = np.einsum("bij,kij->kb", self.bearing_zz, M)
        return (self.bearing_J[None, :] - corr) / scale[:, None]

    def bearing_sensitivity(self, krot: np.ndarray) -> np.ndarray:
        """Coefficients of ∂J/∂η_e of the design span on end springs ``krot`` (N·m/rad), η_e the
        relative change of element e's compliance: ∂J(x)/∂η_e = u_xᵀ K_e u_x (u_x = K⁻¹N(x)ᵀ,
        K_e the element's stiffness), the unit-load theorem for any supports. (n_k, n_b, n_e)."""
        beam = self.setup.beam
        x = self.setup.basis.x
        n_e = beam.n_elements
        K0 = stiffness_matrix(beam)
        N = contact_matrix(beam, x)
        ke = element_stiffness(beam.element_length_m, beam.element_ei())
        free = free_dofs(n_e)
        idx = np.arange(4)[None, :] + 2 * np.arange(n_e)[:, None]  # (n_e, 4) global DOFs of each element
        out = []
        for k in np.atleast_1d(krot):
            K = K0.copy()
            K[0, 0] += k
            K[-1, -1] += k
            U = np.zeros((2 * (n_e + 1), x.size))
            U[free] = np.linalg.solve(K, N.T)
            Ue = U[idx]  # (n_e, 4, n_x)
            D = np.einsum("eix,eij,ejx->xe", Ue, ke, Ue)
            out.append(self.setup.basis.coefficients(D.T).T)
        return np.array(out)


@functools.lru_cache(maxsize=4)  # fixed per bridge and settings: built once, not at every pass (read-only)
def _grids(kern: Kernels, s: HypothesisSettings) -> list[Grid]:
    """Each hypothesis' grid at the design level (g = 0): its own parameters only. The tolerance g
    is added per assessment (:func:`_with_tolerance`), on nodes placed where the data put it."""
    setup = kern.setup
    n_e = setup.bridge.n_elements
    ss = kern.element[None] / kern.ei_design  # ∂a/∂η_e of a simply supported span, per unit 1/ratio
    zero = lambda k: np.zeros(k, dtype=int)  # noqa: E731
    grids = []

    # healthy
    ratio = np.ones((1, n_e))
    grids.append(Grid("healthy", kern.simply_supported(ratio), np.zeros(1), ratio, {}, ss, zero(1), 1.0 / ratio))
    # global loss
    L = np.arange(0.5 * s.loss_step, s.max_loss, s.loss_step)
    ratio = (1 - L)[:, None] * np.ones((1, n_e))
    grids.append(Grid("global", kern.simply_supported(ratio), np.full(L.size, math.log(s.loss_step / s.max_loss)),
                      ratio, {"loss": L}, ss, zero(L.size), 1.0 / ratio))
    # one crack
    span = setup.bridge.span_m
    xc = np.arange(0.5 * s.crack_step_m, span, s.crack_step_m)
    phi = np.arange(0.5 * s.phi_step, s.max_phi, s.phi_step)
    ratio = np.array([[crack_ei_factor(n_e, span, setup.bridge.depth_m, x, p) for p in phi]
                      for x in xc]).reshape(-1, n_e)
    X, P = np.meshgrid(xc, phi, indexing="ij")
    w = np.full(X.size, math.log(s.crack_step_m / span) + math.log(s.phi_step / s.max_phi))
    grids.append(Grid("crack", kern.simply_supported(ratio), w, ratio, {"x_m": X.ravel(), "phi": P.ravel()}, ss,
                      zero(X.size), 1.0 / ratio))
    # seized bearings
    lk = np.arange(s.log10_krot[0] + 0.5 * s.log10_krot_step, s.log10_krot[1], s.log10_krot_step)
    ratio = np.ones((lk.size, n_e))
    w = np.full(lk.size, math.log(s.log10_krot_step / (s.log10_krot[1] - s.log10_krot[0])))
    # Scatter about a uniform span of EI = scale·EI_design on springs Krot: the design span's
    # sensitivity at Krot/scale, divided by the scale; Krot/scale taken as Krot (|log scale| < 0.1).
    sens = kern.bearing_sensitivity(10.0 ** lk) if s.element_sd > 0 else None
    grids.append(Grid("bearings", kern.bearings(np.ones(lk.size), 10.0 ** lk), w, ratio, {"log10_krot": lk}, sens,
                      np.arange(lk.size), 1.0 / ratio))
    return grids


def _level_posterior(S: Stacked, kern: Kernels, level: Callable | None, s: HypothesisSettings
                     ) -> tuple[float, float]:
    """Where the data put the effective log level λ = log(design area / area) of a uniform span, and
    the sd of their information on it: the healthy family's log-likelihood in g (λ = g) over every
    level a hypothesis can reach (down to the largest global loss), then on a fine grid about its
    maximum, and a quadratic fit within 4 nats of that."""
    a1 = kern.simply_supported(np.ones((1, kern.element.shape[1])))

    def loglik(g: np.ndarray) -> np.ndarray:
        ll = marginal_loglik_batch(S, np.exp(-g)[:, None] * a1)
        return ll if level is None else ll + level(g)

    coarse = np.arange(math.log(1.0 - s.max_loss) - 0.1, 0.3, 0.005)
    top = float(coarse[np.argmax(loglik(coarse))])
    g = top + np.linspace(-0.03, 0.03, 121)
    ll = loglik(g)
    near = ll > ll.max() - 4.0
    if near.sum() >= 5:
        c2, c1, _ = np.polyfit(g[near], ll[near], 2)
        if c2 < 0:
            return float(-c1 / (2 * c2)), float(1.0 / math.sqrt(-2.0 * c2))
    return float(g[np.argmax(ll)]), math.inf


def _with_tolerance(base: Grid, kern: Kernels, s: HypothesisSettings, centre: float, info_sd: float) -> Grid:
    """The grid with the as-built tolerance g ~ N(0, tolerance_sd²) integrated by adaptive
    Gauss–Hermite: at each base node (effective level λ_i), nodes around g's conditional posterior —
    the data's λ̂ ± ``info_sd`` shifted by λ_i, times the prior — with weights w_j·prior/proposal.

    Fixed Gauss–Hermite nodes on the prior (2 % apart for a 2 % tolerance) under-resolve the level
    likelihood once the passes pin it to a fraction of that: each hypothesis' evidence would depend
    on whether its best g falls on a node, and a hypothesis whose best g does can win on that alone.
    Placed on g's conditional posterior, 5, 9 or 15 nodes give the same evidence as a 0.05 %-step
    grid to 10⁻³ nats (docs/results.md, Bridge)."""
    u, wu = np.polynomial.hermite.hermgauss(s.tolerance_nodes)
    integrals = kern.setup.basis.integrals
    lam = np.log(kern.design_area / (base.a @ integrals))  # (K,) each base node's effective level
    prec = 1.0 / s.tolerance_sd**2 + (0.0 if not math.isfinite(info_sd) else 1.0 / info_sd**2)
    sd = 1.0 / math.sqrt(prec)
    c = (centre - lam) * (prec - 1.0 / s.tolerance_sd**2) / prec  # conditional posterior mean of g
    g = c[:, None] + math.sqrt(2.0) * sd * u[None, :]  # (K, J)
    logw = (np.log(wu / math.sqrt(math.pi))[None, :] - 0.5 * (g / s.tolerance_sd) ** 2
            - math.log(s.tolerance_sd) + u[None, :] ** 2 + math.log(sd))  # prior / proposal
    K, J = g.shape
    rep = lambda v: np.repeat(v, J, axis=0)  # noqa: E731
    scale = np.exp(g.ravel())
    if base.name == "bearings":
        a = kern.bearings(scale, 10.0 ** rep(base.params["log10_krot"]))
    else:
        a = rep(base.a) / scale[:, None]
    ratio = rep(base.ratio) * scale[:, None]
    params = {k: rep(v) for k, v in base.params.items()}
    params["tolerance"] = g.ravel()
    return Grid(base.name, a, (base.log_weight[:, None] + logw).ravel(), ratio, params, base.sens,
                rep(base.sens_index), 1.0 / ratio)


def _gradient_batch(S: Stacked, a: np.ndarray, chunk: int = 512) -> np.ndarray:
    """∂/∂a of :func:`~cloud.bridge.likelihood.marginal_loglik_batch` (weights and μ integrated) at each
    row of ``a`` (K, n_b) → (K, n_b): the weight-marginal gradient at μ's conditional mode
    (envelope theorem; the μ integral's log-determinant term, slowly varying, left out)."""
    inv_s2 = 1.0 / S.w_sd**2
    out = np.empty_like(a)
    BB = S.BB.sum(axis=0)[None] + np.diag(S.q_mu)[None]
    for lo in range(0, a.shape[0], chunk):
        ak = a[lo : lo + chunk]
        r = np.matmul(ak[None], S.A).transpose(1, 0, 2) + S.e[None]  # (k, V, nb)
        lam = np.einsum("kvb,kb->kv", r, ak) + ak @ S.e.T + S.f[None] + inv_s2[None]
        t = np.matmul(ak[None], S.Pb).transpose(1, 0, 2) + S.db[None]  # (k, V, nm)
        u0 = S.w_mean * inv_s2 - ak @ S.Pw.T - S.dw[None]
        H = BB - np.matmul(t.transpose(0, 2, 1) / lam[:, None, :], t)
        b = S.Bw.sum(axis=0)[None] + np.matmul((u0 / lam)[:, None, :], t)[:, 0, :]
        mu = np.linalg.solve(H, b[:, :, None])[:, :, 0]  # (k, nm) μ's conditional mode
        m = (u0 + np.einsum("kvm,km->kv", t, mu)) / lam  # weights' conditional means
        q = S.Pw[None] - np.einsum("vbm,km->kvb", S.Pb, mu)
        ew2 = m * m + 1.0 / lam
        out[lo : lo + chunk] = -np.einsum("kv,kvb->kb", m, q) - np.einsum("kv,kvb->kb", ew2, r)
    return out


def _fisher(S: Stacked, a0: np.ndarray) -> np.ndarray:
    """Fisher matrix (−Hessian, negative eigenvalues clipped) of the weight- and μ-marginal
    log-likelihood in the coefficients a at ``a0``: the μ-conditional Hessian's Schur complement at
    μ's mode (the log-determinant terms' curvature left out — checked against the exact function,
    2 % element perturbations: within 1 % of the change)."""
    mu = np.zeros(S.Bw.shape[1])
    for _ in range(2):  # μ's mode given a0 (quadratic in μ: one Newton step is exact)
        t = marginal_loglik(S, a0, mu)
        mu = mu - np.linalg.solve(t["Hmm"] - np.diag(S.q_mu), t["gm"] - S.q_mu * mu)
    t = marginal_loglik(S, a0, mu)
    H = t["Haa"] - t["Hma"].T @ np.linalg.solve(t["Hmm"] - np.diag(S.q_mu), t["Hma"])
    w, V = np.linalg.eigh(-0.5 * (H + H.T))
    return (V * np.clip(w, 0.0, None)) @ V.T


def _level_derivatives(level: Callable, kern: Kernels, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradient (K, n_b) of ``level(λ(a))``, λ = log(design area / ∫J), and its Hessian at a[0]."""
    integrals = kern.setup.basis.integrals
    area = a @ integrals
    lam = np.log(kern.design_area / area)
    h = 1e-3
    l0, lp, lm = level(lam), level(lam + h), level(lam - h)
    d1, d2 = (lp - lm) / (2 * h), (lp - 2 * l0 + lm) / h**2
    grad = -(d1 / area)[:, None] * integrals[None]
    hess = (d2[0] + d1[0]) * np.outer(integrals, integrals) / area[0] ** 2  # ∂²/∂a² at a[0]
    return grad, hess


def _scatter_correction(grid: Grid, ll: np.ndarray, S: Stacked, kern: Kernels, sd: float,
                        level: Callable | None, chunk: int = 2048, steps: int = 3) -> np.ndarray:
    """log ∫ p(data | node k, element compliances × (1 + η)) N(η; 0, sd² I) dη − log p(data | node k),
    per node (K,), by Laplace about the mode in η: the log-likelihood's gradient at the node
    (exact), its curvature Φ at the grid's best node (it changes little across the nodes that carry
    weight), a linear in η (D = ∂a/∂η at the node), η* by ``steps`` Newton steps with M = I/sd² + DᵀΦD
    (the gradient evaluated afresh at each: one step fell 12 nats short of sampling on a span that
    the data see well); then

        log p(data | a + Dη*) − ½|η*|²/sd² − ½ log det(sd² M)

    with the likelihood at the shifted point evaluated exactly — so a node far from the data, where
    the quadratic model overstates what scatter can recover, is not lifted beyond what it gets."""
    integrals = kern.setup.basis.integrals
    a0 = grid.a[int(np.argmax(ll))]
    Phi = _fisher(S, a0)
    if level is not None:
        _, hl = _level_derivatives(level, kern, a0[None])
        Phi = Phi - hl
    n_e = grid.ratio.shape[1]
    FB = np.einsum("gbe,bc,gcf->gef", grid.sens, Phi, grid.sens)  # (G, n_e, n_e), made PSD
    w, V = np.linalg.eigh(0.5 * (FB + FB.transpose(0, 2, 1)))
    FB = np.einsum("gij,gj,gkj->gik", V, np.clip(w, 0.0, None), V)
    eye = np.eye(n_e) / sd**2
    out = np.empty(len(ll))
    for lo in range(0, len(ll), chunk):
        sl = slice(lo, lo + chunk)
        j, sc, a = grid.sens_index[sl], grid.sens_scale[sl], grid.a[sl]
        D = grid.sens[j] * sc[:, None, :]  # (k, n_b, n_e)
        L = np.linalg.cholesky(FB[j] * sc[:, :, None] * sc[:, None, :] + eye)
        eta = np.zeros(sc.shape)
        shifted = a
        for _ in range(steps):  # Newton in η with the fixed curvature: the exact gradient at each step
            gamma = _gradient_batch(S, shifted)
            if level is not None:
                gamma = gamma + _level_derivatives(level, kern, shifted)[0]
            beta = np.einsum("kbe,kb->ke", D, gamma) - eta / sd**2
            eta = eta + np.linalg.solve(L.transpose(0, 2, 1), np.linalg.solve(L, beta[:, :, None]))[:, :, 0]
            shifted = a + np.einsum("kbe,ke->kb", D, eta)
        ll_s = marginal_loglik_batch(S, shifted)
        if level is not None:
            ll_s = ll_s + level(np.log(kern.design_area / (shifted @ integrals)))
        logdet = 2.0 * np.sum(np.log(np.diagonal(L, axis1=1, axis2=2)), axis=1) + n_e * math.log(sd**2)
        out[sl] = ll_s - 0.5 * np.sum(eta * eta, axis=1) / sd**2 - 0.5 * logdet - ll[sl]
    return out


def _summary(values: np.ndarray, p: np.ndarray) -> tuple[float, float, float]:
    order = np.argsort(values)
    v, c = values[order], np.cumsum(p[order])
    return float(np.sum(values * p)), float(v[np.searchsorted(c, 0.025)]), float(v[min(np.searchsorted(c, 0.975), v.size - 1)])


def assess(stats: Sequence[VehicleStats], setup: Setup, weight_prior: WeightPrior,
           settings: HypothesisSettings = HypothesisSettings(), kernels: Kernels | None = None,
           level_loglik: Callable[[np.ndarray], np.ndarray] | None = None) -> Assessment:
    """Compare the hypotheses on the data summarised by ``stats`` and decide the alarm.

    The stats' dynamic correction columns (if any) are used as they are for every hypothesis: they
    were computed at the fleet's estimated stiffness level (:mod:`cloud.bridge.dynamic`), and
    rescaling them with each hypothesis' compliance is worse than keeping them (the excess depends
    on the frequency, not only on the amplitude, so rescaling its amplitude biases the loss).

    With ε fixed, though, the likelihood misses what the bridge's vibration says about its
    stiffness — most of the information on the global level at 15–22 m/s. ``level_loglik(g)``
    adds it back as a function of each node's effective log level ``g = log(area of the design
    MR-IL / area of the node's)`` (see :meth:`~cloud.bridge.estimator.BridgeEstimator.estimate`).
    """
    S = Stacked.of(stats, weight_prior)
    kern = kernels or Kernels.of(setup)
    prior = dict(settings.prior)
    names = [n for n in HYPOTHESES if prior.get(n, 0.0) > 0]
    results, logz = {}, {}
    post_w = {}
    centre, info_sd = _level_posterior(S, kern, level_loglik, settings)
    for base in _grids(kern, settings):
        if base.name not in names:
            continue
        grid = _with_tolerance(base, kern, settings, centre, info_sd)
        ll = marginal_loglik_batch(S, grid.a)
        if level_loglik is not None:
            ll = ll + level_loglik(np.log(kern.design_area / (grid.a @ kern.setup.basis.integrals)))
        if settings.element_sd > 0:
            ll = ll + _scatter_correction(grid, ll, S, kern, settings.element_sd, level_loglik)
        ll = ll + grid.log_weight
        top = ll.max()
        z = top + math.log(np.sum(np.exp(ll - top)))
        p = np.exp(ll - z)
        logz[grid.name] = z + math.log(prior[grid.name])
        post_w[grid.name] = (grid, p)
    top = max(logz.values())
    norm = top + math.log(sum(math.exp(v - top) for v in logz.values()))
    for name, (grid, p) in post_w.items():
        prob = math.exp(logz[name] - norm)
        maxloss = 1.0 - grid.ratio.min(axis=1)
        params = {k: _summary(v, p) for k, v in grid.params.items()}
        if name == "crack":
            params["peak_element_loss"] = _summary(maxloss, p)
        results[name] = HypothesisResult(name, float(logz[name] - math.log(prior[name])), prob, params,
                                         float(np.sum(p[maxloss > settings.alarm_loss])),
                                         p @ grid.ratio)
    loss_p = sum(r.probability * r.loss_probability for r in results.values())
    best = max(results, key=lambda k: results[k].probability)
    damage = max((k for k in results if k != "healthy"), key=lambda k: results[k].probability)
    grid, p = post_w[damage]
    span = setup.bridge.span_m
    n_e = setup.bridge.n_elements
    # The largest element loss under the damage hypothesis: its mean and central 95 % interval.
    severity, lo, hi = _summary(1.0 - grid.ratio.min(axis=1), p)
    if damage == "crack":
        x_mean, x_lo, x_hi = results["crack"].parameters["x_m"]
        located = x_hi - x_lo <= LOCATED_ELEMENTS * span / n_e
        element = int(min(n_e, max(1, math.floor(x_mean / span * n_e) + 1))) if located else -1
        location, kind = x_mean, "crack"
    else:
        element, location, kind = -1, 0.5 * span, damage
        x_lo, x_hi = 0.0, span
    alarm = loss_p > settings.alarm_probability
    return Assessment(results, best, bool(alarm), float(loss_p), element, float(location), float(max(severity, 0.0)),
                      kind, float(max(lo, 0.0)), float(max(hi, 0.0)), float(x_lo), float(x_hi))
