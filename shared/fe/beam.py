"""Euler–Bernoulli bridge beam: Hermite finite elements, supports, damage fields and static influence lines."""

from __future__ import annotations

import dataclasses
import math
import operator
from typing import NamedTuple

import numpy as np
from scipy import linalg

from ..dynamics.newmark import integrate, newmark_constants

# Sign convention (the project's): displacements and forces are positive UP, rotations are
# θ = dw/dx (anticlockwise positive). A wheel pushing down on the deck is a negative force.
#
# Degrees of freedom: node i (x_i = i·le, i = 0..n) carries w_i (global DOF 2i) and θ_i (2i+1).
# Both support types pin the deflection at the two end nodes, w_0 = w_n = 0. Those two DOFs are
# *eliminated* (rows and columns removed), not penalised, so every matrix below acts on the free
# DOFs only, ordered [θ_0, w_1, θ_1, …, w_{n-1}, θ_{n-1}, θ_n] (``BeamSystem.free_dofs`` holds
# their global indices). Rotational springs add Krot to the θ_0 and θ_n diagonal terms of K.

SUPPORTS = ("simply_supported", "rotational_springs")
DAMPING_MODELS = ("rayleigh", "modal")

#: Sinha et al. (2002): a crack softens the beam over 1.5 depths either side of it.
CRACK_HALF_WIDTH_DEPTHS = 1.5


@dataclasses.dataclass(frozen=True, eq=False)
class Beam:
    """A straight prismatic bridge beam on two supports, meshed into equal elements (SI units).

    Parameters
    ----------
    span_m : float
        Span between the supports, m.
    n_elements : int
        Number of equal Hermite beam elements.
    E_pa : float
        Young's modulus, Pa.
    I_m4 : float
        Design (undamaged) second moment of area, m⁴.
    mass_per_m : float
        Mass per unit length μ, kg/m.
    damping_ratio : float
        Viscous damping ratio ζ applied by :func:`assemble` (0.03 in thesis §4.2).
    supports : {"simply_supported", "rotational_springs"}
        Pinned ends, or pinned ends restrained by rotational springs (thesis §4.4.1).
    krot_nm_per_rad : (float, float) or None
        (left, right) rotational spring stiffness, N·m/rad; required for, and only for,
        ``supports="rotational_springs"``. 0 is a pin; ~1e12 is practically fixed (Table 4.2).
    ei_factor : ndarray or None
        Per-element multiplier of E·I (damage); None means undamaged (all ones).
    depth_m : float
        Section depth, m (sets the extent of a crack's softened zone).
    """

    span_m: float
    n_elements: int
    E_pa: float
    I_m4: float
    mass_per_m: float
    damping_ratio: float = 0.03
    supports: str = "simply_supported"
    krot_nm_per_rad: tuple[float, float] | None = None
    ei_factor: np.ndarray | None = None
    depth_m: float = 1.0

    def __post_init__(self) -> None:
        for name in ("span_m", "E_pa", "I_m4", "mass_per_m", "depth_m"):
            object.__setattr__(self, name, _positive(f"Beam.{name}", getattr(self, name)))
        zeta = _finite("Beam.damping_ratio", self.damping_ratio)
        if not 0.0 <= zeta < 1.0:
            raise ValueError(f"Beam.damping_ratio: must be in [0, 1), got {self.damping_ratio!r}")
        object.__setattr__(self, "damping_ratio", zeta)
        object.__setattr__(self, "n_elements", _count("Beam.n_elements", self.n_elements))

        if self.supports not in SUPPORTS:
            raise ValueError(f"Beam.supports: must be one of {SUPPORTS}, got {self.supports!r}")
        if self.supports == "rotational_springs":
            krot = self.krot_nm_per_rad
            if krot is None or np.ndim(krot) != 1 or len(krot) != 2:
                raise ValueError(f"Beam.krot_nm_per_rad: must be a (left, right) pair, got {krot!r}")
            pair = tuple(_finite("Beam.krot_nm_per_rad", k) for k in krot)
            if min(pair) < 0:
                raise ValueError(f"Beam.krot_nm_per_rad: must be >= 0, got {krot!r}")
            object.__setattr__(self, "krot_nm_per_rad", pair)
        elif self.krot_nm_per_rad is not None:
            raise ValueError("Beam.krot_nm_per_rad: only allowed with supports='rotational_springs'")

        if self.ei_factor is not None:
            try:
                factor = np.array(self.ei_factor, dtype=float)  # a private copy, frozen below
            except (TypeError, ValueError):
                raise ValueError(f"Beam.ei_factor: must be an array of numbers, got {self.ei_factor!r}") from None
            if factor.shape != (self.n_elements,):
                raise ValueError(
                    f"Beam.ei_factor: must have shape ({self.n_elements},), got {factor.shape}"
                )
            if not (np.all(np.isfinite(factor)) and np.all(factor > 0)):
                raise ValueError("Beam.ei_factor: every element factor must be finite and > 0")
            factor.flags.writeable = False
            object.__setattr__(self, "ei_factor", factor)

    # ndarray fields defeat the generated __eq__/__hash__; compare by value instead.
    def _key(self) -> tuple:
        return (
            self.span_m, self.n_elements, self.E_pa, self.I_m4, self.mass_per_m,
            self.damping_ratio, self.supports, self.krot_nm_per_rad,
            self.depth_m, self.element_ei_factor().tobytes(),
        )  # fmt: skip

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Beam) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    @property
    def element_length_m(self) -> float:
        return self.span_m / self.n_elements

    def element_ei_factor(self) -> np.ndarray:
        """Per-element E·I multiplier, shape (n_elements,) (ones when undamaged)."""
        if self.ei_factor is None:
            return np.ones(self.n_elements)
        return np.array(self.ei_factor)

    def element_ei(self) -> np.ndarray:
        """Per-element bending stiffness E·I·factor, N·m², shape (n_elements,)."""
        return self.E_pa * self.I_m4 * self.element_ei_factor()

    def node_x(self) -> np.ndarray:
        """Node chainages from the left support, m, shape (n_elements + 1,)."""
        return np.linspace(0.0, self.span_m, self.n_elements + 1)

    def element_bounds(self) -> np.ndarray:
        """(start, end) chainage of each element, m, shape (n_elements, 2)."""
        x = self.node_x()
        return np.column_stack([x[:-1], x[1:]])


class BeamSystem(NamedTuple):
    """The beam's linear system on its free DOFs: M ü + C u̇ + K u = f (u, f positive up)."""

    M: np.ndarray  # (n_dof, n_dof) consistent mass, kg (kg·m² on rotations)
    K: np.ndarray  # (n_dof, n_dof) stiffness incl. support springs, N/m (N·m/rad on rotations)
    C: np.ndarray  # (n_dof, n_dof) viscous damping, N·s/m
    free_dofs: np.ndarray  # (n_dof,) global DOF index (2·node + {0: w, 1: θ}) of each free DOF
    n_dof: int  # number of free DOFs = 2·n_elements


class ContactEntries(NamedTuple):
    """Sparse form of the contact rows: deflection at x = Σ_j values[:, j] · u[dofs[:, j]].

    ``dofs`` holds free-DOF indices, or -1 where the DOF is constrained or x is off the beam
    (``values`` is 0 there), so a compiled kernel can skip them without branching on supports.
    """

    dofs: np.ndarray  # (n_x, 4) int64
    values: np.ndarray  # (n_x, 4) float, m/m for w DOFs and m/rad for θ DOFs


# ---------------------------------------------------------------------------------------------
# Elements and assembly


def hermite_shape(xi: np.ndarray | float, le: float, derivative: int = 0) -> np.ndarray:
    """Cubic Hermite shape functions of a beam element (or their x-derivatives).

    Parameters
    ----------
    xi : array_like
        Local coordinate (x − x_start)/le in [0, 1].
    le : float
        Element length, m.
    derivative : {0, 1, 2}
        0: deflection, 1: slope (1/m), 2: curvature (1/m²) per unit nodal DOF.

    Returns
    -------
    ndarray, shape xi.shape + (4,)
        Weights of the element DOFs (w_start, θ_start, w_end, θ_end).
    """
    xi = np.asarray(xi, dtype=float)
    if derivative == 0:
        n = [1 - 3 * xi**2 + 2 * xi**3, le * (xi - 2 * xi**2 + xi**3), 3 * xi**2 - 2 * xi**3, le * (xi**3 - xi**2)]
    elif derivative == 1:
        n = [(6 * xi**2 - 6 * xi) / le, 1 - 4 * xi + 3 * xi**2, (6 * xi - 6 * xi**2) / le, 3 * xi**2 - 2 * xi]
    elif derivative == 2:
        n = [(12 * xi - 6) / le**2, (6 * xi - 4) / le, (6 - 12 * xi) / le**2, (6 * xi - 2) / le]
    else:
        raise ValueError(f"derivative: must be 0, 1 or 2, got {derivative!r}")
    return np.stack(np.broadcast_arrays(*n), axis=-1)


def element_stiffness(le: float, ei: np.ndarray) -> np.ndarray:
    """Stiffness of Hermite elements of length ``le`` (m), each of constant E·I ``ei`` (n_e,) N·m²:
    (n_e, 4, 4), DOFs (w_start, θ_start, w_end, θ_end) in N/m, N, N·m/rad."""
    k = np.array(
        [
            [12.0, 6 * le, -12.0, 6 * le],
            [6 * le, 4 * le**2, -6 * le, 2 * le**2],
            [-12.0, -6 * le, 12.0, -6 * le],
            [6 * le, 2 * le**2, -6 * le, 4 * le**2],
        ]
    )
    return (ei / le**3)[:, None, None] * k


def _element_mass(le: float, mu: float) -> np.ndarray:
    """Consistent mass of one element of uniform mass per length, shape (4, 4)."""
    m = np.array(
        [
            [156.0, 22 * le, 54.0, -13 * le],
            [22 * le, 4 * le**2, 13 * le, -3 * le**2],
            [54.0, 13 * le, 156.0, -22 * le],
            [-13 * le, -3 * le**2, -22 * le, 4 * le**2],
        ]
    )
    return mu * le / 420.0 * m


def element_matrices(le: float, ei: np.ndarray, mass_per_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Stiffness and consistent mass of Hermite elements of length ``le`` (m), for assembling other
    beams (e.g. a rail on discrete supports): ``ei`` (n_e,) N·m², ``mass_per_m`` kg/m.

    Returns (ke, me), each (n_e, 4, 4), DOFs (w_start, θ_start, w_end, θ_end).
    """
    ei = np.atleast_1d(np.asarray(ei, dtype=float))
    me = np.broadcast_to(_element_mass(le, mass_per_m), (len(ei), 4, 4))
    return element_stiffness(le, ei), np.array(me)


def free_dofs(n_elements: int) -> np.ndarray:
    """Global indices (2·node + {0: w, 1: θ}) of the DOFs every matrix here acts on: all but the
    support deflections w_0 and w_n, in order."""
    n_total = 2 * (n_elements + 1)
    return np.setdiff1d(np.arange(n_total), [0, n_total - 2])


def _assemble_full(n_elements: int, element_matrices: np.ndarray) -> np.ndarray:
    n_total = 2 * (n_elements + 1)
    out = np.zeros((n_total, n_total))
    for e in range(n_elements):  # consecutive elements share two DOFs
        out[2 * e : 2 * e + 4, 2 * e : 2 * e + 4] += element_matrices[e]
    return out


def stiffness_matrix(beam: Beam) -> np.ndarray:
    """The beam's stiffness K on its free DOFs (:func:`free_dofs`), support springs included,
    N/m (N·m/rad on rotations): what :func:`assemble` returns as ``K``, without the mass and damping."""
    ke = element_stiffness(beam.element_length_m, beam.element_ei())
    free = free_dofs(beam.n_elements)
    K = _assemble_full(beam.n_elements, ke)[np.ix_(free, free)]
    if beam.supports == "rotational_springs":
        K[0, 0] += beam.krot_nm_per_rad[0]  # θ_0 is free DOF 0 and θ_n the last one
        K[-1, -1] += beam.krot_nm_per_rad[1]
    return K


def _mass(beam: Beam) -> np.ndarray:
    """Consistent M on the free DOFs (the supports carry no lumped mass)."""
    me = np.broadcast_to(_element_mass(beam.element_length_m, beam.mass_per_m), (beam.n_elements, 4, 4))
    free = free_dofs(beam.n_elements)
    return _assemble_full(beam.n_elements, me)[np.ix_(free, free)]


def assemble(beam: Beam, damping: str = "rayleigh") -> BeamSystem:
    """Assemble the beam's mass, stiffness and damping matrices on its free DOFs.

    Boundary conditions are applied by elimination: the deflections of the two support nodes
    are removed from the system (w = 0 exactly), the end rotations stay free, and rotational
    support springs add Krot to the stiffness of the end rotations.

    Parameters
    ----------
    beam : Beam
    damping : {"rayleigh", "modal"}
        "rayleigh" (default): C = a0·M + a1·K with a0, a1 chosen so that modes 1 and 2 both have
        exactly ``beam.damping_ratio``; higher modes are damped more (ζ grows ∝ ω), which also
        suppresses the spurious high-frequency content of a moving-load simulation.
        "modal": C = M Φ diag(2ζω) Φᵀ M with mass-normalised modes Φ, so that every mode has
        ``damping_ratio`` (a full matrix, fine for the few tens of DOFs used here).

    Returns
    -------
    BeamSystem
        M (kg), K (N/m), C (N·s/m) on the free DOFs, the DOF map and the DOF count.
    """
    if damping not in DAMPING_MODELS:
        raise ValueError(f"damping: must be one of {DAMPING_MODELS}, got {damping!r}")
    M, K = _mass(beam), stiffness_matrix(beam)
    zeta = beam.damping_ratio
    if damping == "rayleigh":
        lam = linalg.eigh(K, M, eigvals_only=True, subset_by_index=[0, min(1, len(M) - 1)])
        w1, w2 = np.sqrt(lam[0]), np.sqrt(lam[-1])
        C = (2 * zeta * w1 * w2 / (w1 + w2)) * M + (2 * zeta / (w1 + w2)) * K
    else:
        lam, phi = linalg.eigh(K, M)  # phi is M-orthonormal
        Mphi = M @ phi
        C = (Mphi * (2 * zeta * np.sqrt(lam))) @ Mphi.T
    return BeamSystem(M=M, K=K, C=0.5 * (C + C.T), free_dofs=free_dofs(beam.n_elements), n_dof=len(M))


def natural_frequencies(beam: Beam, n_modes: int = 5) -> np.ndarray:
    """Lowest natural frequencies of the undamped beam, Hz, ascending, shape (n_modes,).

    Solves the generalised symmetric eigenproblem K φ = ω² M φ on the free DOFs.
    """
    n_modes = _count("n_modes", n_modes)
    n_dof = 2 * beam.n_elements
    if n_modes > n_dof:
        raise ValueError(f"n_modes: at most {n_dof} for {beam.n_elements} elements, got {n_modes}")
    lam = linalg.eigh(stiffness_matrix(beam), _mass(beam), eigvals_only=True, subset_by_index=[0, n_modes - 1])
    return np.sqrt(lam) / (2 * math.pi)


# ---------------------------------------------------------------------------------------------
# Coupling a point on the deck to the DOFs


def contact_entries(beam: Beam, x_m: np.ndarray | float) -> ContactEntries:
    """Sparse contact rows for chainages ``x_m`` (m from the left support).

    A point force P (N, up positive) at x contributes P·values to the free-DOF load vector at
    ``dofs``; the deck deflection at x is Σ values·u[dofs]. Off the span both are zero.
    """
    x = np.atleast_1d(np.asarray(x_m, dtype=float))
    if x.ndim != 1:
        raise ValueError(f"x_m: must be a scalar or 1-D array, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("x_m: chainages must be finite")
    n, le = beam.n_elements, beam.element_length_m
    on = (x >= 0.0) & (x <= beam.span_m)
    e = np.clip(np.floor(x / le).astype(np.int64), 0, n - 1)  # x = span falls in the last element
    xi = np.clip(x / le - e, 0.0, 1.0)
    values = hermite_shape(xi, le) * on[:, None]

    full_to_free = np.full(2 * (n + 1), -1, dtype=np.int64)
    full_to_free[free_dofs(n)] = np.arange(2 * n)
    dofs = full_to_free[2 * e[:, None] + np.arange(4)]
    dofs[~on] = -1
    values[dofs < 0] = 0.0
    return ContactEntries(dofs=dofs, values=values)


def contact_matrix(beam: Beam, x_m: np.ndarray) -> np.ndarray:
    """Dense contact rows N(x), shape (len(x_m), n_dof): deflection at x_m[i] is N[i] @ u."""
    entries = contact_entries(beam, x_m)
    out = np.zeros((len(entries.dofs), 2 * beam.n_elements))
    rows = np.broadcast_to(np.arange(len(entries.dofs))[:, None], entries.dofs.shape)
    keep = entries.dofs >= 0
    out[rows[keep], entries.dofs[keep]] = entries.values[keep]
    return out


def contact_vector(beam: Beam, x_m: float) -> np.ndarray:
    """Contact row N(x), shape (n_dof,), for one chainage x_m (m); zero off the span.

    The load vector of a point force P (N, up positive) at x is P·N(x) and the deflection
    under it is N(x) @ u.
    """
    if np.ndim(x_m) != 0:
        raise ValueError("x_m: contact_vector takes one chainage; use contact_matrix for many")
    return contact_matrix(beam, np.array([x_m]))[0]


# ---------------------------------------------------------------------------------------------
# Damage fields (per-element E·I multipliers)


def global_ei_factor(n_elements: int, loss: float) -> np.ndarray:
    """Uniform loss of bending stiffness: every element keeps (1 − loss) of its E·I."""
    n_elements = _count("n_elements", n_elements)
    loss = _finite("loss", loss)
    if not 0.0 <= loss < 1.0:
        raise ValueError(f"loss: must be in [0, 1), got {loss!r}")
    return np.full(n_elements, 1.0 - loss)


def crack_peak_loss(phi: float) -> float:
    """Loss of E·I at the crack section for crack depth ratio φ of a solid rectangle: 1 − (1 − φ)³."""
    phi = _finite("phi", phi)
    if not 0.0 <= phi < 1.0:
        raise ValueError(f"phi: crack depth ratio must be in [0, 1), got {phi!r}")
    return 1.0 - (1.0 - phi) ** 3


def crack_ei_factor(
    n_elements: int,
    span_m: float,
    depth_m: float,
    crack_x_m: float,
    phi: float,
    *,
    averaging: str = "nodal",
) -> np.ndarray:
    """Per-element E·I multiplier for one open crack (thesis §4.5.1, after Sinha et al. 2002).

    The loss of E·I is a triangle: ``crack_peak_loss(phi)`` = 1 − (1 − φ)³ at the crack (the
    cracked section keeps depth (1 − φ)·d, and I ∝ d³) falling linearly to zero at 1.5·depth
    either side. Each element then takes one value:

    * ``averaging="nodal"`` (default): the triangle is sampled at the nodes and interpolated
      linearly along each element, so an element's loss is the mean of its two nodal losses.
      For the thesis beam (20 × 1 m elements, d = 1 m, crack on a node) this gives
      18.1 % / 4.5 % for φ = 10 % and 9.5 % / 2.4 % for φ = 5 %, against the quoted 18/5 and
      10/3 — the closest simple rule found (within 0.7 points). It converges to the triangle
      as the mesh is refined, but on a coarse mesh it overstates the softened area (by 1/9 for
      a crack on a node).
    * ``averaging="exact"``: the exact mean of the triangle over each element (conserves the
      lost area at any mesh). Inner elements match (18.1 %, 9.5 %) but the outer ones get only
      2.3 % / 1.2 %: no element-averaged triangle of ±1.5 d reproduces the quoted 5 %/3 %.

    Parameters
    ----------
    n_elements : int
    span_m, depth_m : float
        Span and section depth, m.
    crack_x_m : float
        Crack chainage from the left support, m, in [0, span].
    phi : float
        Crack depth / section depth, in [0, 1).
    averaging : {"nodal", "exact"}

    Returns
    -------
    ndarray, shape (n_elements,)
        E·I multiplier (1 − element loss) of each element.
    """
    n_elements = _count("n_elements", n_elements)
    span_m, depth_m = _positive("span_m", span_m), _positive("depth_m", depth_m)
    crack_x_m = _finite("crack_x_m", crack_x_m)
    if not 0.0 <= crack_x_m <= span_m:
        raise ValueError(f"crack_x_m: must lie on the span [0, {span_m}], got {crack_x_m!r}")
    peak = crack_peak_loss(phi)
    half = CRACK_HALF_WIDTH_DEPTHS * depth_m
    x = np.linspace(0.0, span_m, n_elements + 1)

    if averaging == "nodal":
        nodal = peak * np.clip(1.0 - np.abs(x - crack_x_m) / half, 0.0, None)
        loss = 0.5 * (nodal[:-1] + nodal[1:])
    elif averaging == "exact":
        # ∫ of the triangle over [a, b] = peak·(H(b) − H(a)), H the antiderivative of the
        # unit triangle centred on the crack: H(s) = sign(s)·(t − t²/(2h)), t = min(|s|, h).
        def antiderivative(s: np.ndarray) -> np.ndarray:
            t = np.minimum(np.abs(s), half)
            return np.sign(s) * (t - t * t / (2 * half))

        h = antiderivative(x - crack_x_m)
        loss = peak * np.diff(h) / np.diff(x)
    else:
        raise ValueError(f"averaging: must be 'nodal' or 'exact', got {averaging!r}")
    return 1.0 - loss


# ---------------------------------------------------------------------------------------------
# Statics and influence lines


def static_deflection(
    beam: Beam,
    load_n: np.ndarray | float,
    x_load_m: np.ndarray | float,
    x_eval_m: np.ndarray | float,
) -> np.ndarray:
    """Static deflection (m, positive UP) at ``x_eval_m`` under point forces (N, positive UP).

    Several forces are superposed: ``load_n`` and ``x_load_m`` broadcast together (e.g. the
    axles of one vehicle). A downward wheel load W is ``load_n = -W``. Returns an array of the
    shape of ``x_eval_m``; forces or evaluation points off the span contribute / read zero.
    """
    p, xl = np.broadcast_arrays(np.asarray(load_n, dtype=float), np.asarray(x_load_m, dtype=float))
    if not np.all(np.isfinite(p)):
        raise ValueError("load_n: forces must be finite")
    f = contact_matrix(beam, xl.ravel()).T @ p.ravel()
    u = linalg.solve(stiffness_matrix(beam), f, assume_a="pos")
    x_eval = np.asarray(x_eval_m, dtype=float)
    return (contact_matrix(beam, x_eval.ravel()) @ u).reshape(x_eval.shape)


def influence_line(beam: Beam, x_m: np.ndarray | float) -> np.ndarray:
    """Moving-reference influence line J⁰(x) (thesis §3.5.1), m/N, from the FE model.

    J⁰(x) = N(x) K⁻¹ N(x)ᵀ: the deflection at x under a unit force at x, measured in the
    direction of the force, so it is >= 0 (compliance). In the project's up-positive convention
    a downward wheel load W at x deflects the deck there by −W·J⁰(x). Exact at the nodes
    (Hermite elements with piecewise-constant E·I); between nodes the error falls as le³.
    Zero off the span.
    """
    x = np.asarray(x_m, dtype=float)
    N = contact_matrix(beam, x.ravel())
    U = linalg.solve(stiffness_matrix(beam), N.T, assume_a="pos")
    return np.einsum("ij,ji->i", N, U).reshape(x.shape)


def compliance_kernel(beam: Beam, x_m: np.ndarray | float) -> np.ndarray:
    """Closed-form per-element compliance kernel of a simply supported span, m³.

    G[i, z] = ∫_{element z} M_i(s)² ds, where M_i is the bending moment (N·m per N) of the
    simply supported span under a unit force at x_i; by the unit-load theorem

        J⁰(x_i) = Σ_z G[i, z] / EI_z          (m/N, the deflection under the load, >= 0)

    exactly, for any piecewise-constant E·I. Like :func:`influence_line`, the result is a
    compliance: positive in the direction of the load (DOWN for a wheel; the up-positive
    deflection is −W·J⁰). Linear in 1/EI, which is what makes per-element stiffness inference
    cheap. Only E·I-independent geometry is used; ``beam.ei_factor`` is ignored.

    Returns
    -------
    ndarray, shape (len(x_m), n_elements)
        Zero rows for x off the span.
    """
    if beam.supports != "simply_supported":
        raise ValueError("beam.supports: compliance_kernel is closed-form for simply supported spans only")
    x = np.atleast_1d(np.asarray(x_m, dtype=float))
    if x.ndim != 1 or not np.all(np.isfinite(x)):
        raise ValueError("x_m: must be a finite scalar or 1-D array")
    L = beam.span_m
    on = (x >= 0.0) & (x <= L)
    a = np.clip(x, 0.0, L)[:, None]
    lo, hi = beam.element_bounds().T[:, None, :]  # each (1, n_elements)

    # Left of the load M = (L − a)·s/L; right of it M = a·(L − s)/L. Integrate each square
    # exactly over the part of the element on that side.
    s0, s1 = np.minimum(lo, a), np.minimum(hi, a)
    left = ((L - a) / L) ** 2 * (s1**3 - s0**3) / 3.0
    s0, s1 = np.maximum(lo, a), np.maximum(hi, a)
    right = (a / L) ** 2 * ((L - s0) ** 3 - (L - s1) ** 3) / 3.0
    return (left + right) * on[:, None]


# ---------------------------------------------------------------------------------------------
# Validation helpers


def _finite(name: str, value: object) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise ValueError(f"{name}: must be finite, got {value!r}")
    return x


def _positive(name: str, value: object) -> float:
    x = _finite(name, value)
    if x <= 0:
        raise ValueError(f"{name}: must be > 0, got {value!r}")
    return x


def _count(name: str, value: object) -> int:
    if isinstance(value, bool):
        raise ValueError(f"{name}: must be a positive integer, got {value!r}")
    try:
        n = operator.index(value)
    except TypeError:
        raise ValueError(f"{name}: must be a positive integer, got {value!r}") from None
    if n < 1:
        raise ValueError(f"{name}: must be a positive integer, got {value!r}")
    return n


# ---------------------------------------------------------------------------------------------
# Moving loads


def moving_load_deflection(
    beam: Beam,
    x_m: np.ndarray,
    force_n: np.ndarray,
    dt: float,
    gamma: float = 0.5,
    beta: float = 0.25,
    damping: str = "rayleigh",
    system: BeamSystem | None = None,
) -> np.ndarray:
    """Deflection under a moving point force, from rest (m, positive UP), by Newmark-β.

    The force ``force_n[k]`` (N, positive UP: a wheel pushing down is negative) acts at
    ``x_m[k]`` (m from the left support) at time ``k·dt``; off the span it does nothing. The
    beam (mass, stiffness and damping of :func:`assemble`) starts at rest, unloaded. Returns the
    beam's deflection at the force's position at every step, shape (n_steps,). The default
    γ = ½, β = ¼ is the trapezoidal rule (second order, no numerical damping). ``system``: the
    beam's :func:`assemble` result, if already at hand (saves an eigen-solve per call).
    """
    x = np.asarray(x_m, dtype=float)
    p = np.asarray(force_n, dtype=float)
    if x.ndim != 1 or p.shape != x.shape:
        raise ValueError("moving_load_deflection: x_m and force_n must be 1-D arrays of equal length")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(p))):
        raise ValueError("moving_load_deflection: positions and forces must be finite")
    if system is None:
        system = assemble(beam, damping)
    N = contact_matrix(beam, x)  # (n_steps, n_dof), zero rows off the span
    state = integrate(system.M, system.C, system.K, N * p[:, None], newmark_constants(dt, gamma, beta))
    return np.einsum("kd,kd->k", N, state.u)
