"""Cubic B-splines on a bridge's span, and the nuisance columns on the likelihood window: μ common to all
passes, each pass's own steps."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.interpolate import BSpline

from cloud.bridge.passdata import Window

DECKS = ("smooth", "rough")
MU_PRIOR_SD_M = 0.05  # broad prior on the nuisance coefficients (m), so the evidence is proper


@dataclasses.dataclass(frozen=True, eq=False)
class SpanBasis:
    """Cubic B-splines on the span with knots at the element nodes, sampled on the window grid.

    ``design`` (n_span, n_b) evaluates a coefficient vector on the span points of the window;
    ``projector`` (n_b, n_span) is its least-squares inverse.
    """

    window: Window
    n_elements: int
    design: np.ndarray
    projector: np.ndarray

    @classmethod
    def of(cls, window: Window, n_elements: int) -> "SpanBasis":
        L = window.span_m
        x = np.clip(window.x[window.on_span], 0.0, L)
        knots = np.linspace(0.0, L, n_elements + 1)
        t = np.r_[[0.0] * 3, knots, [L] * 3]
        design = BSpline.design_matrix(x, t, 3).toarray()
        return cls(window, n_elements, design, np.linalg.pinv(design))

    @property
    def n(self) -> int:
        return self.design.shape[1]

    @property
    def integrals(self) -> np.ndarray:
        """∫ψ_j dx over the span (m), so that ∫J dx = integrals @ a."""
        return np.trapezoid(self.design, self.x, axis=0)

    @property
    def x(self) -> np.ndarray:
        """Distance from the first support of the span points, m."""
        return np.clip(self.window.x[self.window.on_span], 0.0, self.window.span_m)

    def coefficients(self, values: np.ndarray) -> np.ndarray:
        """Basis coefficients of function values on the span points (last axis)."""
        return np.asarray(values) @ self.projector.T


def mu_basis(window: Window, basis: SpanBasis, deck: str) -> np.ndarray:
    """Columns (n_window, n_mu) of the nuisance μ common to all passes (:mod:`cloud.bridge.likelihood`):
    none on a smooth deck, the span's B-splines on a rough one (the fleet-mean deflection)."""
    if deck not in DECKS:
        raise ValueError(f"deck: must be one of {DECKS}, got {deck!r}")
    if deck == "smooth":
        return np.zeros((window.n, 0))
    out = np.zeros((window.n, basis.n))
    out[window.on_span] = basis.design
    return out


def step_basis(window: Window, deck: str) -> np.ndarray:
    """Columns (n_window, 4) of each pass's own nuisance on a smooth deck: ``{1, ξ, ξ², ξ³}`` on the
    span (the drift-control trend of the consensus, a step at the supports, which differs from
    pass to pass by ~2 % — tens of µm, as much as the deflection signal of a precise pass); none on
    a rough deck. Each pass's coefficients are projected out of its likelihood."""
    if deck == "rough":
        return np.zeros((window.n, 0))
    on = window.on_span
    xi = (window.x - 0.5 * window.span_m) / (0.5 * window.span_m)
    return np.column_stack([on * 1.0, on * xi, on * xi**2, on * xi**3])
