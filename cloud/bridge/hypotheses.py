"""Damage as hypotheses the data can decide between, and the alarm.

Twenty free element stiffnesses are barely identifiable from a fleet of tens of vehicles; a
handful of physical hypotheses are. Each is a parametric stiffness model; every one also carries
an as-built tolerance on the global stiffness, ``g ~ N(0, tolerance_sd²)`` (EI = EI_design·e^g):

* ``healthy``  — the design bridge (within tolerance);
* ``global``   — a uniform loss ``L ~ U(0, max_loss)`` (corrosion, thesis §3.5.3);
* ``crack``    — one crack at ``x_c ~ U(0, span)`` of depth ratio ``φ ~ U(0, max_phi)``, softening the
  elements around it by :func:`shared.fe.beam.crack_ei_factor` (thesis §4.5.1);
* ``bearings`` — seized bearings: rotational springs ``log10 Krot ~ U(lo, hi)`` at both supports
  (thesis §4.4), the FE influence line in closed form (a rank-2 update of the pinned span).

The likelihood is the weight- and nuisance-marginal one of :mod:`cloud.bridge.static`
(:func:`~cloud.bridge.static.marginal_loglik_batch`); each hypothesis' parameters are integrated
on a grid (Gauss–Hermite in g), which gives its evidence, its posterior over parameters and the
posterior probability of the hypothesis. The alarm is raised when the model-averaged posterior
probability that some element lost more than ``alarm_loss`` of its design stiffness exceeds
``alarm_probability``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence

import numpy as np

from shared.fe.beam import assemble, contact_matrix, crack_ei_factor

from .static import Setup, Stacked, VehicleStats, WeightPrior, marginal_loglik_batch

HYPOTHESES = ("healthy", "global", "crack", "bearings")


@dataclasses.dataclass(frozen=True)
class HypothesisSettings:
    """Priors and grids of the hypotheses, and the alarm rule."""

    tolerance_sd: float = 0.02  # as-built global stiffness tolerance (log scale)
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
    posterior mean of the largest element loss under the most probable damage hypothesis.
    """

    results: dict[str, HypothesisResult]
    best: str
    alarm: bool
    loss_probability: float
    element: int
    location_m: float
    severity: float
    kind: str

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
        from shared.fe.beam import compliance_kernel

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


def _hermite(sd: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.hermite.hermgauss(n)
    return math.sqrt(2.0) * sd * x, np.log(w / math.sqrt(math.pi))


@functools.lru_cache(maxsize=4)  # fixed per bridge and settings: built once, not at every pass (read-only)
def _grids(kern: Kernels, s: HypothesisSettings) -> list[Grid]:
    setup = kern.setup
    n_e = setup.bridge.n_elements
    g, lg = _hermite(s.tolerance_sd, s.tolerance_nodes)
    grids = []

    # healthy
    ratio = np.exp(g)[:, None] * np.ones((1, n_e))
    grids.append(Grid("healthy", kern.simply_supported(ratio), lg, ratio, {"tolerance": g}))
    # global loss
    L = np.arange(0.5 * s.loss_step, s.max_loss, s.loss_step)
    LL, GG = np.meshgrid(L, g, indexing="ij")
    LW = np.broadcast_to(lg, LL.shape) + math.log(s.loss_step / s.max_loss)
    ratio = (np.exp(GG) * (1 - LL)).ravel()[:, None] * np.ones((1, n_e))
    grids.append(Grid("global", kern.simply_supported(ratio), LW.ravel(), ratio,
                      {"loss": LL.ravel(), "tolerance": GG.ravel()}))
    # one crack
    span = setup.bridge.span_m
    xc = np.arange(0.5 * s.crack_step_m, span, s.crack_step_m)
    phi = np.arange(0.5 * s.phi_step, s.max_phi, s.phi_step)
    factors = np.array([[crack_ei_factor(n_e, span, setup.bridge.depth_m, x, p) for p in phi] for x in xc])
    X, P, Gc = np.meshgrid(xc, phi, g, indexing="ij")
    ratio = (factors[:, :, None, :] * np.exp(g)[None, None, :, None]).reshape(-1, n_e)
    w = (np.broadcast_to(lg, X.shape) + math.log(s.crack_step_m / span) + math.log(s.phi_step / s.max_phi)).ravel()
    grids.append(Grid("crack", kern.simply_supported(ratio), w, ratio,
                      {"x_m": X.ravel(), "phi": P.ravel(), "tolerance": Gc.ravel()}))
    # seized bearings
    lk = np.arange(s.log10_krot[0] + 0.5 * s.log10_krot_step, s.log10_krot[1], s.log10_krot_step)
    LK, Gb = np.meshgrid(lk, g, indexing="ij")
    scale = np.exp(Gb.ravel())
    ratio = scale[:, None] * np.ones((1, n_e))
    w = (np.broadcast_to(lg, LK.shape) + math.log(s.log10_krot_step / (s.log10_krot[1] - s.log10_krot[0]))).ravel()
    grids.append(Grid("bearings", kern.bearings(scale, 10.0 ** LK.ravel()), w, ratio,
                      {"log10_krot": LK.ravel(), "tolerance": Gb.ravel()}))
    return grids


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
    on the frequency, not only on the amplitude: measured, it moved a 10 % loss to 8 %).

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
    for grid in _grids(kern, settings):
        if grid.name not in names:
            continue
        ll = marginal_loglik_batch(S, grid.a) + grid.log_weight
        if level_loglik is not None:
            ll = ll + level_loglik(np.log(kern.design_area / (grid.a @ kern.setup.basis.integrals)))
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
    if damage == "crack":
        x_mean = results["crack"].parameters["x_m"][0]
        element = int(min(n_e, max(1, math.floor(x_mean / span * n_e) + 1)))
        location, kind = x_mean, "crack"
        severity = results["crack"].parameters["peak_element_loss"][0]
    else:
        element, location, kind = -1, 0.5 * span, damage
        severity = float(p @ (1.0 - grid.ratio.min(axis=1)))
    alarm = loss_p > settings.alarm_probability
    return Assessment(results, best, bool(alarm), float(loss_p), element, float(location), float(max(severity, 0.0)),
                      kind)
