"""Moving-reference influence line (MR-IL) by the matrix method, and damage indicators D1/D2.

Thesis §3.5.1–3.5.2. For a two-axle vehicle with axle loads W_A (leading) and W_B, axle spacing d,
the deflections under the axles (positive in the load's direction) at scan k (axle A at x_k,
axle B at x_k − d, c = d/Δx scans) are

    δ_A,k = W_A·J_k + W_B·J¹(x_k, x_k − d),     δ_B,k = W_A·J¹(x_k − d, x_k) + W_B·J_{k−c}

and Betti's theorem removes the cross terms: y_k = W_A·δ_A,k − W_B·δ_B,k = W_A²·J_k − W_B²·J_{k−c}
(eq. 3.16). Least squares over the scans, E = Σ_k (y_k − W_A²J_k + W_B²J_{k−c})² (eq. 3.17), with
J = 0 off the span. Setting ∂E/∂J_m = 0 (derived here; the printed eq. 3.22 is garbled):

    (W_A⁴ + W_B⁴)·J_m − W_A²W_B²·(J_{m−c} + J_{m+c}) = W_A²·y_m − W_B²·y_{m+c}
        = W_A³δ_A,m − W_A²W_B·δ_B,m − W_A·W_B²·δ_A,m+c + W_B³·δ_B,m+c

a symmetric system with non-zeros on the diagonal and at ±c only (eq. 3.19–3.21), solved as a
banded system. It is regular whenever the span holds a finite number of axle spacings (the
chains J_m, J_{m+c}, … end at the supports), even for equal axle loads. The normal equations of
several passes add, so a batch is solved jointly or pass by pass and averaged (the thesis).

D1 and D2 (eq. 3.24) compare the mean MR-IL with a healthy baseline: D1 on the mean mid-span
ordinate, D2 on the area under the line, ``D = 100·(1 − IL_H / IL_D)`` (%): both read as the
percentage loss of a uniform flexural rigidity.

Units: x m, deflection m, loads N, J m/N.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from scipy.linalg import solveh_banded

from shared.fe.beam import influence_line
from shared.fe.design import design_beam
from shared.registry import Bridge


@dataclasses.dataclass(frozen=True, eq=False)
class AxlePair:
    """One pass of a two-axle vehicle: deflections (m, positive down) under each axle on the span
    grid ``x_m`` (distance from the first support, spacing ``x_m[1] − x_m[0]``), the axle loads
    (N) and the axle spacing (m)."""

    x_m: np.ndarray
    delta_a: np.ndarray
    delta_b: np.ndarray
    load_a: float
    load_b: float
    spacing_m: float


@dataclasses.dataclass(frozen=True, eq=False)
class NormalEquations:
    """``A J = b`` of eq. 3.18 in symmetric banded storage: ``band[c - i, m + i]`` = A[m, m + i]
    (scipy's upper form) for the offsets 0 and c."""

    band: np.ndarray  # (c + 1, M)
    rhs: np.ndarray  # (M,)
    c: int

    def __add__(self, other: "NormalEquations") -> "NormalEquations":
        if other.c != self.c or other.rhs.size != self.rhs.size:
            raise ValueError("NormalEquations: different grids or axle spacings")
        return NormalEquations(self.band + other.band, self.rhs + other.rhs, self.c)

    def solve(self, ridge: float = 0.0) -> np.ndarray:
        """J (m/N) on the span grid; ``ridge`` adds a small multiple of the mean diagonal."""
        band = self.band.copy()
        band[-1] += ridge * float(np.mean(band[-1]))
        return solveh_banded(band, self.rhs)


def normal_equations(p: AxlePair) -> NormalEquations:
    """The banded normal equations of one pass (derived in the module docstring)."""
    x = np.asarray(p.x_m, dtype=float)
    M = x.size
    h = (x[-1] - x[0]) / (M - 1)
    c = int(round(p.spacing_m / h))
    if c < 1:
        raise ValueError("normal_equations: the axle spacing is shorter than the grid step")
    # Scans k = 0 .. M + c − 1: axle A at x_k (k < M on the span), axle B at x_{k−c}.
    K = M + c
    dA = np.zeros(K)
    dB = np.zeros(K)
    dA[:M] = p.delta_a
    dB[c : c + M] = p.delta_b
    wa, wb = float(p.load_a), float(p.load_b)
    y = wa * dA - wb * dB  # eq. 3.16, left-hand side
    rhs = wa**2 * y[:M] - wb**2 * y[c : c + M]
    band = np.zeros((c + 1, M))
    band[c, :] = wa**4 + wb**4
    if c < M:
        band[0, c:] = -(wa**2) * wb**2
    return NormalEquations(band, rhs, c)


@dataclasses.dataclass(frozen=True, eq=False)
class MrIl:
    """A fundamental MR-IL J⁰(x) (m/N) on the span grid, from ``n_passes`` passes."""

    x_m: np.ndarray
    J: np.ndarray
    n_passes: int

    @property
    def area(self) -> float:
        """∫ J dx over the span, m²/N."""
        return float(np.trapezoid(self.J, self.x_m))

    def midspan(self, half_width_fraction: float = 0.025) -> float:
        """Mean ordinate within ±``half_width_fraction``·span of mid-span, m/N."""
        L = self.x_m[-1] - self.x_m[0]
        mid = self.x_m[0] + 0.5 * L
        sel = np.abs(self.x_m - mid) <= half_width_fraction * L + 1e-12
        return float(np.mean(self.J[sel]))


def mril_two_axle(passes: Sequence[AxlePair], pooled: bool = False, ridge: float = 0.0) -> MrIl:
    """The fundamental MR-IL of a batch: the mean of the passes' MR-ILs (thesis), or with
    ``pooled`` the least-squares solution of all passes' summed normal equations."""
    if not passes:
        raise ValueError("mril_two_axle: no passes")
    x = np.asarray(passes[0].x_m, dtype=float)
    eqs = [normal_equations(p) for p in passes]
    if pooled:
        total = eqs[0]
        for e in eqs[1:]:
            total = total + e
        return MrIl(x, total.solve(ridge), len(passes))
    return MrIl(x, np.mean([e.solve(ridge) for e in eqs], axis=0), len(passes))


def mril_single_axle(x_m: np.ndarray, deltas: Sequence[np.ndarray], loads: Sequence[float]) -> MrIl:
    """Single-axle vehicles (quarter-cars): J⁰ = δ/W directly; the mean over passes."""
    J = np.mean([np.asarray(d, float) / float(w) for d, w in zip(deltas, loads)], axis=0)
    return MrIl(np.asarray(x_m, float), J, len(deltas))


def design_mril(bridge: Bridge, x_m: np.ndarray, krot: tuple[float, float] | None = None) -> MrIl:
    """The declared baseline: the design bridge's static MR-IL (J⁰ = N K⁻¹ Nᵀ) on ``x_m``; simply
    supported, or on rotational springs ``krot`` (left, right; N·m/rad) if given."""
    beam = design_beam(bridge, krot=krot)
    return MrIl(np.asarray(x_m, float), influence_line(beam, np.clip(x_m, 0.0, bridge.span_m)), 0)


@dataclasses.dataclass(frozen=True)
class DamageIndicators:
    """D1 (mid-span ordinate) and D2 (area), % loss of stiffness against the baseline (eq. 3.24)."""

    D1_pct: float
    D2_pct: float


def damage_indicators(healthy: MrIl, current: MrIl, half_width_fraction: float = 0.025) -> DamageIndicators:
    """D = 100·(1 − IL_H/IL_D) with IL the mean mid-span ordinate (D1) or the area (D2)."""
    d1 = 100.0 * (1.0 - healthy.midspan(half_width_fraction) / current.midspan(half_width_fraction))
    d2 = 100.0 * (1.0 - healthy.area / current.area)
    return DamageIndicators(float(d1), float(d2))


@dataclasses.dataclass
class Baseline:
    """The healthy baseline of a bridge: declared (the design MR-IL) or learnt from the first
    ``n_learn`` passes' MR-ILs (frozen once complete)."""

    mril: MrIl | None = None
    n_learn: int = 0
    _learning: list = dataclasses.field(default_factory=list)

    @classmethod
    def declared(cls, bridge: Bridge, x_m: np.ndarray, krot: tuple[float, float] | None = None) -> "Baseline":
        return cls(design_mril(bridge, x_m, krot))

    @classmethod
    def learnt(cls, n_passes: int) -> "Baseline":
        return cls(None, n_passes)

    def offer(self, mril: MrIl) -> None:
        """A new MR-IL of the bridge (e.g. one per pass); used while the baseline is being learnt."""
        if self.mril is not None:
            return
        self._learning.append(mril)
        if sum(m.n_passes or 1 for m in self._learning) >= self.n_learn:
            w = np.array([m.n_passes or 1 for m in self._learning], dtype=float)
            J = np.average([m.J for m in self._learning], axis=0, weights=w)
            self.mril = MrIl(self._learning[0].x_m, J, int(w.sum()))

    @property
    def ready(self) -> bool:
        return self.mril is not None
