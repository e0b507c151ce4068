"""How a span's stiffness is parametrised: the elements' prior (a Gaussian Markov random field about a
common level) and the element models that map the parameters to the load term's basis coefficients."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from shared.fe.beam import Beam, compliance_kernel, influence_line
from shared.fe.design import design_beam
from shared.registry import Bridge

from cloud.bridge.basis import SpanBasis

#: sd of log τ in the hyperprior of the departure scale (:attr:`StiffnessPrior.scale_sd`): the design
#: guess τ = 1 is right within a factor 2 (1σ). Not flat on the grid: at 30 passes the evidence
#: hardly tells the scales apart, and a flat hyperprior would give the loose scales — which let the
#: barely seen end elements swing — a third of the weight.
SCALE_SD: float | None = math.log(2.0)


@dataclasses.dataclass(frozen=True)
class StiffnessPrior:
    """Gaussian Markov random field on θ_z = log(EI_z / EI_design) (cf. thesis eq. 4.34) about a
    level common to the span: θ = g·1 + η.

    ``common_sd``: prior sd of the span's level g about the design (None: no common level, the
    elements depart from the design value itself); ``level_sd``: sd of each element's departure
    η_z from that level; ``step_sd``: sd of the difference between neighbouring elements
    (smoothness).

    Why a common level: the passes fix the span's level sharply (through its dynamics) but barely
    see the end elements (the deflection hardly depends on them). Anchored on the design value
    alone, an end element is its neighbour's value drifting towards the design, so the ends of a
    span whose level is off the design read points away from the rest; drawn towards the span's
    level, they follow it. ``level_sd`` 0.1 leaves a crack's 18 % peak element loss at ~2σ: cracks
    are read from the damage hypotheses, which do not use this prior. The Laplace evidence hardly
    tells level_sd 0.03–0.2 apart on healthy spans; on cracks it prefers the looser ones.
    """

    level_sd: float = 0.1
    step_sd: float = 0.05
    common_sd: float | None = 0.3
    #: Empirical Bayes over the departure scale τ (``level_sd`` and ``step_sd`` both times τ): the
    #: posterior is integrated over these τ, each weighted by its Laplace evidence times the
    #: hyperprior (log τ ~ N(0, ``scale_sd``²)); empty: τ = 1 only. A fixed scale is too loose for a
    #: healthy span and too tight for a crack: learnt, a healthy span's field tightens and a crack's
    #: loosens (its weakest element comes closer to the crack's loss, while the barely seen ends swing
    #: more); at 30 passes the evidence hardly tells the scales apart. The grid spans level_sd
    #: 0.025–0.4. A fit costs milliseconds (the data are per-vehicle statistics), so the grid costs
    #: little beside the dynamics — except with bearings, where τ stays 1 (:meth:`~cloud.bridge.setup.Setup.model`).
    scales: tuple[float, ...] = tuple(float(v) for v in 2.0 ** np.arange(-2.0, 2.01, 0.5))
    #: sd of the hyperprior of log τ about 1 (None: uniform on the grid)
    scale_sd: float | None = SCALE_SD

    def scaled(self, tau: float) -> "StiffnessPrior":
        """This prior with the departure sds times ``tau`` and no integration over the scale."""
        return dataclasses.replace(self, level_sd=self.level_sd * tau, step_sd=self.step_sd * tau, scales=())

    def precision(self, n: int) -> np.ndarray:
        D = np.diff(np.eye(n), axis=0)
        Q = np.eye(n) / self.level_sd**2 + D.T @ D / self.step_sd**2
        if self.common_sd:
            # The precision of Cov = Q⁻¹ + σ_g²·11ᵀ (Woodbury); Q·1 = 1/level_sd² (the differences
            # annihilate a constant).
            q1 = np.full(n, 1.0 / self.level_sd**2)
            Q = Q - np.outer(q1, q1) / (1.0 / self.common_sd**2 + q1.sum())
        return Q


@dataclasses.dataclass(frozen=True, eq=False)
class ElementModel:
    """Per-element flexural rigidity of a simply supported span: ``a(θ) = P·G·c``, c_z = e^{−θ_z}/EI_d.

    ``kernel`` = basis coefficients (n_b, n_e) of the compliance kernel columns G_z (m³). The
    parameters are θ (n_e); :meth:`a_jac` gives a, ∂a/∂θ and the diagonal second derivatives.
    """

    basis: SpanBasis
    ei_design: float
    kernel: np.ndarray
    prior: StiffnessPrior = StiffnessPrior()

    @classmethod
    def of(cls, basis: SpanBasis, beam: Beam, prior: StiffnessPrior = StiffnessPrior()) -> "ElementModel":
        if beam.supports != "simply_supported":
            raise ValueError("ElementModel: simply supported spans only (see BearingElementModel)")
        G = compliance_kernel(beam, basis.x)
        return cls(basis, beam.E_pa * beam.I_m4, basis.coefficients(G.T).T, prior)

    @property
    def n_elements(self) -> int:
        return self.kernel.shape[1]

    @property
    def n(self) -> int:
        return self.n_elements

    def prior_mean(self) -> np.ndarray:
        return np.zeros(self.n)

    def prior_precision(self) -> np.ndarray:
        return self.prior.precision(self.n_elements)

    def compliance(self, theta: np.ndarray) -> np.ndarray:
        return np.exp(-np.asarray(theta)) / self.ei_design

    def a(self, params: np.ndarray) -> np.ndarray:
        return self.kernel @ self.compliance(params[: self.n_elements])

    def a_jac(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        c = self.compliance(params)
        Ja = -self.kernel * c[None, :]
        return self.kernel @ c, Ja, -Ja  # ∂²a/∂θ_z² = K_z c_z

    def influence(self, params: np.ndarray) -> np.ndarray:
        """J(x) on the span points, m/N."""
        return self.basis.design @ self.a(params)


@dataclasses.dataclass(frozen=True, eq=False)
class LinearisedDynamicModel(ElementModel):
    """:class:`ElementModel` with each pass's dynamic excess linear in θ about ``theta0``:
    ``h_p = Ψ_p·a(θ) + δ_p(θ₀) + D_p·(θ − θ₀)`` (D_p: the pass's whitened ∂ε_p/∂θ,
    :func:`~cloud.bridge.dynamic.dynamic_sensitivities`). The load term stays linear in an extended
    coefficient vector ``[a(θ), θ − θ₀]`` over the columns ``[Ψ_p, D_p]``
    (:func:`~cloud.bridge.dynamic.extended_passes`), so the weights are integrated out and the data
    reduce to per-vehicle statistics exactly as in :class:`ElementModel` — only the per-pass columns differ, since the
    dynamics depend on the pass's speed. :meth:`a` gives the extended vector; :meth:`influence`
    the influence line."""

    theta0: np.ndarray | None = None

    def a(self, params: np.ndarray) -> np.ndarray:
        par = np.asarray(params, dtype=float)[: self.n_elements]
        return np.r_[self.kernel @ self.compliance(par), par - self.theta0]

    def a_jac(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a, Ja, d2 = ElementModel.a_jac(self, params)
        eye = np.eye(self.n_elements)
        par = np.asarray(params, dtype=float)[: self.n_elements]
        return np.r_[a, par - self.theta0], np.vstack([Ja, eye]), np.vstack([d2, np.zeros_like(eye)])

    def influence(self, params: np.ndarray) -> np.ndarray:
        return self.basis.design @ ElementModel.a(self, params)


@dataclasses.dataclass(frozen=True, eq=False)
class BearingElementModel:
    """Per-element EI and rotational-spring bearings (thesis §4.4): parameters θ (n_e) and
    κ = log10 Krot (one shared value, or one per support). J comes from the FE beam with
    ``supports="rotational_springs"``; ∂a/∂(θ, κ) by finite differences (Gauss–Newton).
    The passes fix only the span's effective stiffness, not its split between beam and bearings: with
    the dynamics on, κ is read along that ridge with the as-built tolerance (:mod:`cloud.bridge.bearings`)
    and this model's fit is conditioned on it.
    """

    basis: SpanBasis
    bridge: Bridge
    prior: StiffnessPrior = StiffnessPrior()
    krot_prior: tuple[float, float] = (8.0, 2.5)  # mean and sd of log10 Krot (N·m/rad)
    per_support: bool = True
    fd_step: float = 1e-3

    @property
    def n_elements(self) -> int:
        return self.bridge.n_elements

    @property
    def n_krot(self) -> int:
        return 2 if self.per_support else 1

    @property
    def n(self) -> int:
        return self.n_elements + self.n_krot

    @property
    def ei_design(self) -> float:
        return self.bridge.EI

    def prior_mean(self) -> np.ndarray:
        return np.r_[np.zeros(self.n_elements), np.full(self.n_krot, self.krot_prior[0])]

    def prior_precision(self) -> np.ndarray:
        Q = np.zeros((self.n, self.n))
        Q[: self.n_elements, : self.n_elements] = self.prior.precision(self.n_elements)
        Q[self.n_elements :, self.n_elements :] = np.eye(self.n_krot) / self.krot_prior[1] ** 2
        return Q

    def influence(self, params: np.ndarray) -> np.ndarray:
        theta, kap = params[: self.n_elements], params[self.n_elements :]
        k = 10.0 ** np.clip(kap, -3.0, 16.0)
        krot = (float(k[0]), float(k[-1]))
        beam = design_beam(self.bridge, ei_factor=np.exp(theta), krot=krot)
        return influence_line(beam, self.basis.x)

    def a(self, params: np.ndarray) -> np.ndarray:
        return self.basis.coefficients(self.influence(params))

    def a_jac(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a0 = self.a(params)
        Ja = np.empty((a0.size, self.n))
        for i in range(self.n):
            p = params.copy()
            p[i] += self.fd_step
            Ja[:, i] = (self.a(p) - a0) / self.fd_step
        return a0, Ja, np.zeros_like(Ja)


def design_influence(model) -> np.ndarray:
    """The design bridge's J on the span points (pinned supports), m/N."""
    b = model.bridge if hasattr(model, "bridge") else None
    if b is not None:
        return influence_line(design_beam(b), model.basis.x)
    return model.basis.design @ (model.kernel @ np.full(model.n_elements, 1.0 / model.ei_design))
