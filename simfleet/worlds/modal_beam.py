"""A bridge deck as a continuous Euler–Bernoulli beam reduced to its modes by Rayleigh–Ritz.

The second world's bridge shares no code with the project's Hermite FE beam: the deflection is
expanded in assumed modes (the sine modes of the simply supported span, plus two cubics that carry
end moments when the bearings are rotational springs), mass and stiffness are integrated with
Gauss–Legendre quadrature against the continuous E·I(x) (a crack is a triangle of lost E·I in x,
not an element value), and the Ritz eigenproblem gives the modes that are kept and damped modally.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import linalg

from shared.fe.beam import crack_peak_loss

#: A crack softens E·I over ±1.5 section depths (the thesis's triangle after Sinha et al.).
CRACK_HALF_WIDTH_DEPTHS = 1.5
#: Assumed sine modes: enough that the kept modes converge (a Ritz mode is accurate well below
#: the highest basis function) and a point load's static deflection converges like Σ 1/j⁴.
N_SINES = 40
#: Gauss points per quadrature cell and cells per span: E·I's kinks (crack triangle) fall inside
#: cells, so the cells are many and short against the 1.5-depth triangle.
GAUSS_POINTS = 4
QUAD_CELLS = 800


@dataclass(frozen=True)
class ModalBeamSpec:
    """The beam's design values and true condition (SI units)."""

    span_m: float
    EI_nm2: float  # design E·I
    mass_per_m: float
    damping_ratio: float  # modal, every kept mode
    depth_m: float = 1.0
    krot_nm_per_rad: float | None = None  # None: simply supported (pinned) bearings
    global_loss: float = 0.0
    crack_x_m: float | None = None
    crack_phi: float = 0.0
    n_modes: int = 12

    def __post_init__(self) -> None:
        for name in ("span_m", "EI_nm2", "mass_per_m", "depth_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ModalBeamSpec.{name}: must be > 0, got {getattr(self, name)!r}")
        if not 0.0 <= self.damping_ratio < 1.0:
            raise ValueError(f"ModalBeamSpec.damping_ratio: must be in [0, 1), got {self.damping_ratio!r}")
        if not 0.0 <= self.global_loss < 1.0:
            raise ValueError(f"ModalBeamSpec.global_loss: must be in [0, 1), got {self.global_loss!r}")
        if self.krot_nm_per_rad is not None and not self.krot_nm_per_rad > 0:
            raise ValueError(f"ModalBeamSpec.krot_nm_per_rad: must be > 0 or None, got {self.krot_nm_per_rad!r}")
        if self.crack_x_m is not None and not 0.0 <= self.crack_x_m <= self.span_m:
            raise ValueError(f"ModalBeamSpec.crack_x_m: must lie on the span, got {self.crack_x_m!r}")
        if not 1 <= self.n_modes <= N_SINES // 2:
            raise ValueError(f"ModalBeamSpec.n_modes: must be in 1..{N_SINES // 2}, got {self.n_modes!r}")

    @property
    def n_basis(self) -> int:
        return N_SINES + (0 if self.krot_nm_per_rad is None else 2)

    def ei(self, x_m: np.ndarray) -> np.ndarray:
        """True E·I (N·m²) at chainages ``x_m`` from the left support."""
        x = np.asarray(x_m, dtype=float)
        factor = np.full(x.shape, 1.0 - self.global_loss)
        if self.crack_x_m is not None and self.crack_phi > 0:
            half = CRACK_HALF_WIDTH_DEPTHS * self.depth_m
            factor = factor * (1.0 - crack_peak_loss(self.crack_phi)
                               * np.clip(1.0 - np.abs(x - self.crack_x_m) / half, 0.0, None))
        return self.EI_nm2 * factor

    def element_ratio(self, n_elements: int) -> np.ndarray:
        """Mean of E·I / design E·I over each of ``n_elements`` equal elements (the registry's grid)."""
        edges = np.linspace(0.0, self.span_m, n_elements + 1)
        g, w = np.polynomial.legendre.leggauss(GAUSS_POINTS)
        out = np.empty(n_elements)
        for e in range(n_elements):
            sub = np.linspace(edges[e], edges[e + 1], 41)  # 40 cells per element: the crack's kinks resolved
            a, b = sub[:-1, None], sub[1:, None]
            x = 0.5 * (a + b) + 0.5 * (b - a) * g[None, :]
            out[e] = np.sum(0.5 * (b - a) * w[None, :] * self.ei(x)) / (edges[e + 1] - edges[e])
        return out / self.EI_nm2


def basis(spec: ModalBeamSpec, x_m: np.ndarray, derivative: int = 0) -> np.ndarray:
    """Assumed modes (or their ``derivative``-th x-derivative) at ``x_m``: shape (x.size, n_basis).

    Sines sin(jπx/L), j = 1 … N_SINES; with rotational-spring bearings also (x/L)(1 − x/L)² and
    (x/L)²(1 − x/L), which vanish at the supports but carry the end moments the sines cannot.
    """
    x = np.atleast_1d(np.asarray(x_m, dtype=float))
    L = spec.span_m
    j = np.arange(1, N_SINES + 1)
    k = j * np.pi / L
    arg = x[:, None] * k[None, :]
    if derivative == 0:
        cols = [np.sin(arg)]
    elif derivative == 1:
        cols = [np.cos(arg) * k[None, :]]
    else:
        cols = [-np.sin(arg) * k[None, :] ** 2]
    if spec.krot_nm_per_rad is not None:
        s = x / L
        if derivative == 0:
            extra = [s * (1 - s) ** 2, s**2 * (1 - s)]
        elif derivative == 1:
            extra = [(1 - s) * (1 - 3 * s) / L, s * (2 - 3 * s) / L]
        else:
            extra = [(6 * s - 4) / L**2, (2 - 6 * s) / L**2]
        cols.append(np.stack(extra, axis=1))
    return np.concatenate(cols, axis=1)


@dataclass(frozen=True)
class ModalBeam:
    """The Ritz model: mass and stiffness in the assumed modes, and the kept, mass-normalised modes."""

    spec: ModalBeamSpec
    mass: np.ndarray  # (n_basis, n_basis)
    stiffness: np.ndarray  # (n_basis, n_basis)
    omega: np.ndarray  # (n_modes,) rad/s
    vectors: np.ndarray  # (n_basis, n_modes): mode r = basis @ vectors[:, r], with vectorsᵀ·mass·vectors = I

    def modes_at(self, x_m: np.ndarray) -> np.ndarray:
        """Kept mode shapes at ``x_m`` (from the left support), (x.size, n_modes); zero off the span."""
        x = np.atleast_1d(np.asarray(x_m, dtype=float))
        on = (x >= 0.0) & (x <= self.spec.span_m)
        return basis(self.spec, x) @ self.vectors * on[:, None]

    @property
    def frequencies_hz(self) -> np.ndarray:
        return self.omega / (2 * np.pi)

    def static_deflection(self, load_n: float, x_load_m: float, x_eval_m: np.ndarray) -> np.ndarray:
        """Deflection (m, up positive) at ``x_eval_m`` under a point force ``load_n`` (N, up positive)
        at ``x_load_m``, from the full Ritz stiffness (every assumed mode, not only the kept ones)."""
        coef = np.linalg.solve(self.stiffness, basis(self.spec, np.array([x_load_m]))[0] * load_n)
        return basis(self.spec, x_eval_m) @ coef


def modal_beam(spec: ModalBeamSpec) -> ModalBeam:
    """Assemble the Ritz mass and stiffness of ``spec`` and solve for its lowest ``n_modes`` modes."""
    L = spec.span_m
    g, w = np.polynomial.legendre.leggauss(GAUSS_POINTS)
    edges = np.linspace(0.0, L, QUAD_CELLS + 1)
    a, b = edges[:-1, None], edges[1:, None]
    x = (0.5 * (a + b) + 0.5 * (b - a) * g[None, :]).ravel()
    wx = (0.5 * (b - a) * w[None, :]).ravel()
    psi = basis(spec, x)
    psi2 = basis(spec, x, derivative=2)
    mass = (psi * (wx * spec.mass_per_m)[:, None]).T @ psi
    stiffness = (psi2 * (wx * spec.ei(x))[:, None]).T @ psi2
    if spec.krot_nm_per_rad is not None:
        ends = basis(spec, np.array([0.0, L]), derivative=1)
        stiffness = stiffness + spec.krot_nm_per_rad * ends.T @ ends  # ½ Krot θ² at each bearing
    lam, vec = linalg.eigh(stiffness, mass, subset_by_index=[0, spec.n_modes - 1])
    return ModalBeam(spec, mass, stiffness, np.sqrt(lam), vec)
