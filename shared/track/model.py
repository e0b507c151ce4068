"""Ballasted track (thesis §3.2.2, Fig. 3.2): the rail as Hermite beam elements on discrete sleepers,
each a three-layer sprung-mass support (pad → sleeper → ballast → sub-ballast → ground, or the deck of
a simply supported bridge span beneath, §3.2.3).

The 2-D track carries a whole carriage, so the rail and its supports stand for both rails of the
track (flexural rigidity, masses and stiffnesses per sleeper for the two rails together). Every
matrix is symmetric and banded; it is stored in LAPACK lower band form ``ab[i - j, j] = A[i, j]``
(i ≥ j), as ``scipy.linalg.cholesky_banded(..., lower=True)`` takes it. DOFs are numbered node by
node along the track (rail w, rail θ, then the sleeper and ballast masses of a sleeper at that node,
then the bridge DOFs at that node), so the bandwidth stays ~10 whatever the length.

Displacements are positive up, from the unloaded track; the track's self-weight is left out (it
only adds a constant settlement that no vehicle measurement can see).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np
from scipy.linalg import cho_solve_banded, cholesky_banded

from ..fe.beam import Beam, assemble, contact_matrix, element_matrices, hermite_shape
from .random_fields import stiffness_factors


@dataclasses.dataclass(frozen=True)
class TrackParams:
    """Track properties for the whole track cross-section (two rails), SI units.

    Defaults: two UIC60 rails; pad, sleeper, ballast and sub-ballast values of the order used by
    Zhai et al. (2004), doubled for two rail seats. The ballast and sub-ballast stiffness of each
    sleeper are multiplied by log-normal factors from a Gaussian process along the track
    (:func:`~shared.track.random_fields.stiffness_factors`) with log-sd ``support_sd`` and
    correlation length ``support_correlation_m`` (``support_sd = 0``: uniform supports).
    """

    length_m: float = 200.0
    sleeper_spacing_m: float = 0.6
    elements_per_spacing: int = 2
    rail_ei_nm2: float = 2 * 2.1e11 * 3.055e-5
    rail_mass_per_m: float = 2 * 60.34
    pad_k: float = 1.56e8
    pad_c: float = 1.0e5
    sleeper_mass: float = 251.0
    ballast_mass: float = 1062.0
    ballast_k: float = 3.6e8
    ballast_c: float = 1.18e5
    subballast_k: float = 1.3e8
    subballast_c: float = 6.2e4
    support_sd: float = 0.1
    support_correlation_m: float = 3.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            x = getattr(self, f.name)
            if f.name == "elements_per_spacing":
                if int(x) != x or x < 1:
                    raise ValueError(f"TrackParams.{f.name}: must be a positive integer, got {x!r}")
                continue
            if not math.isfinite(float(x)):
                raise ValueError(f"TrackParams.{f.name}: must be finite, got {x!r}")
            if float(x) < 0 or (float(x) == 0 and f.name not in ("pad_c", "ballast_c", "subballast_c", "support_sd")):
                raise ValueError(f"TrackParams.{f.name}: must be > 0, got {x!r}")
        if self.length_m < 2 * self.sleeper_spacing_m:
            raise ValueError("TrackParams.length_m: must span at least two sleeper spacings")

    @property
    def element_length_m(self) -> float:
        return self.sleeper_spacing_m / self.elements_per_spacing

    def support_stiffness(self) -> float:
        """Pad, ballast and sub-ballast in series: the static stiffness of one sleeper support, N/m."""
        return 1.0 / (1.0 / self.pad_k + 1.0 / self.ballast_k + 1.0 / self.subballast_k)


@dataclasses.dataclass(frozen=True, eq=False)
class BridgeSpan:
    """A simply supported span beneath the track from ``start_m`` (a sleeper position) over ``span_m``
    (a whole number of sleeper spacings); meshed with one element per sleeper spacing.

    ``ei_factor`` (per element) multiplies E·I: see :func:`damaged_ei_factor`.
    """

    start_m: float
    span_m: float
    E_pa: float
    I_m4: float
    mass_per_m: float
    damping_ratio: float = 0.03
    ei_factor: np.ndarray | None = None

    def beam(self, sleeper_spacing_m: float) -> Beam:
        n = int(round(self.span_m / sleeper_spacing_m))
        if n < 1 or abs(n * sleeper_spacing_m - self.span_m) > 1e-9 * self.span_m:
            raise ValueError(f"BridgeSpan.span_m: {self.span_m} is not a whole number of sleeper spacings")
        return Beam(self.span_m, n, self.E_pa, self.I_m4, self.mass_per_m, self.damping_ratio,
                    ei_factor=self.ei_factor)


def damaged_ei_factor(n_elements: int, global_loss: float, element_sd: float, rng: np.random.Generator) -> np.ndarray:
    """E·I multipliers: a uniform loss ``global_loss`` (e.g. corrosion) times independent per-element
    variation of relative standard deviation ``element_sd`` (0.05 in thesis §3.6)."""
    if not 0.0 <= global_loss < 1.0 or element_sd < 0:
        raise ValueError("damaged_ei_factor: need 0 <= global_loss < 1 and element_sd >= 0")
    scatter = np.clip(1.0 + element_sd * rng.standard_normal(n_elements), 0.2, None)  # never negative
    return (1.0 - global_loss) * scatter


class Track(NamedTuple):
    """The assembled track: banded M, C, K and where each physical DOF sits."""

    params: TrackParams
    node_x: np.ndarray  # (n_nodes,) rail node chainage, m
    rail_w: np.ndarray  # (n_nodes,) global DOF of the rail deflection at each node
    rail_theta: np.ndarray  # (n_nodes,) global DOF of the rail rotation
    sleeper_x: np.ndarray  # (n_sleepers,) m
    sleeper_dof: np.ndarray  # (n_sleepers,)
    ballast_dof: np.ndarray  # (n_sleepers,)
    ballast_k: np.ndarray  # (n_sleepers,) realised ballast stiffness, N/m
    subballast_k: np.ndarray  # (n_sleepers,) realised sub-ballast stiffness, N/m
    bridge: BridgeSpan | None
    bridge_beam: Beam | None
    bridge_dof: np.ndarray  # (n_bridge_free,) global DOF of each free DOF of bridge_beam
    M: np.ndarray  # (bw + 1, n_dof) lower band
    C: np.ndarray
    K: np.ndarray

    @property
    def n_dof(self) -> int:
        return self.K.shape[1]

    @property
    def bandwidth(self) -> int:
        return self.K.shape[0] - 1

    def contact_entries(self, x_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rail deflection at chainages ``x_m``: Σ values·u[dofs]; dofs, values each (n, 4).

        Raises if a point is off the rail.
        """
        x = np.atleast_1d(np.asarray(x_m, dtype=float))
        le = self.params.element_length_m
        n_el = len(self.node_x) - 1
        if np.any(x < 0.0) or np.any(x > self.node_x[-1] + 1e-9):
            raise ValueError(f"contact point off the rail (track is 0..{self.node_x[-1]:.1f} m)")
        e = np.clip(np.floor(x / le).astype(np.int64), 0, n_el - 1)
        xi = np.clip(x / le - e, 0.0, 1.0)
        values = hermite_shape(xi, le)
        dofs = np.stack([self.rail_w[e], self.rail_theta[e], self.rail_w[e + 1], self.rail_theta[e + 1]], axis=1)
        return dofs, values

    def bridge_deflection(self, u: np.ndarray, x_m: np.ndarray) -> np.ndarray:
        """Deck deflection (m, up) at chainages ``x_m`` from a track displacement ``u`` (…, n_dof)."""
        if self.bridge_beam is None:
            raise ValueError("bridge_deflection: this track has no bridge")
        N = contact_matrix(self.bridge_beam, np.atleast_1d(np.asarray(x_m, float)) - self.bridge.start_m)
        return np.asarray(u)[..., self.bridge_dof] @ N.T


class _BandBuilder:
    """Adds symmetric entries into lower band storage."""

    def __init__(self, n: int, bw: int):
        self.ab = np.zeros((bw + 1, n))

    def add(self, i: np.ndarray, j: np.ndarray, v: np.ndarray) -> None:
        i, j, v = np.broadcast_arrays(np.asarray(i), np.asarray(j), np.asarray(v, dtype=float))
        lo, hi = np.maximum(i, j), np.minimum(i, j)
        np.add.at(self.ab, (lo - hi, hi), v)

    def spring(self, a: int | np.ndarray, b: int | np.ndarray | None, k: float | np.ndarray) -> None:
        """A spring between DOFs a and b (b None: to ground)."""
        self.add(a, a, k)
        if b is not None:
            self.add(b, b, k)
            self.add(a, b, -np.asarray(k))


def build_track(
    params: TrackParams, rng: np.random.Generator | int | None = 0, bridge: BridgeSpan | None = None
) -> Track:
    """Assemble the track (and the bridge span beneath it, if any).

    Sleepers stand at every ``sleeper_spacing_m`` from chainage 0 to ``length_m`` (rounded to whole
    spacings); the rail is free at both ends. ``rng`` draws the support stiffness field.
    """
    rng = np.random.default_rng(rng) if not isinstance(rng, np.random.Generator) else rng
    p = params
    eps = int(p.elements_per_spacing)
    n_spacings = int(round(p.length_m / p.sleeper_spacing_m))
    n_nodes = n_spacings * eps + 1
    le = p.element_length_m
    node_x = np.arange(n_nodes) * le
    sleeper_node = np.arange(n_spacings + 1) * eps
    n_sl = len(sleeper_node)

    beam, bs, j0 = None, None, 0
    bridge_nodes: dict[int, list[int]] = {}  # rail node → bridge free-DOF indices stationed there
    if bridge is not None:
        beam = bridge.beam(p.sleeper_spacing_m)
        j0 = int(round(bridge.start_m / p.sleeper_spacing_m))  # the sleeper over the first support
        if abs(j0 * p.sleeper_spacing_m - bridge.start_m) > 1e-9 * max(1.0, bridge.start_m):
            raise ValueError(f"BridgeSpan.start_m: {bridge.start_m} is not at a sleeper")
        if j0 < 1 or j0 + beam.n_elements > n_sl - 2:
            raise ValueError("BridgeSpan: the span must lie inside the track with a sleeper to spare each side")
        bs = assemble(beam)  # supports eliminated: free DOFs θ0, w1, θ1, …, θn
        for f, g in enumerate(bs.free_dofs):  # global beam DOF g = 2·node + {0: w, 1: θ}
            bridge_nodes.setdefault(sleeper_node[j0 + g // 2], []).append(f)

    # Number the DOFs node by node.
    rail_w = np.empty(n_nodes, dtype=np.int64)
    rail_theta = np.empty(n_nodes, dtype=np.int64)
    sleeper_dof = np.empty(n_sl, dtype=np.int64)
    ballast_dof = np.empty(n_sl, dtype=np.int64)
    bridge_dof = np.empty(0 if beam is None else bs.n_dof, dtype=np.int64)
    sl_at = {int(nd): j for j, nd in enumerate(sleeper_node)}
    k = 0
    for i in range(n_nodes):
        rail_w[i], rail_theta[i] = k, k + 1
        k += 2
        if i in sl_at:
            sleeper_dof[sl_at[i]], ballast_dof[sl_at[i]] = k, k + 1
            k += 2
        for f in bridge_nodes.get(i, []):
            bridge_dof[f] = k
            k += 1
    n_dof = k

    kba = p.ballast_k * stiffness_factors(n_sl, p.sleeper_spacing_m, p.support_sd, p.support_correlation_m, rng)
    ksb = p.subballast_k * stiffness_factors(n_sl, p.sleeper_spacing_m, p.support_sd, p.support_correlation_m, rng)

    # The deck DOF under each sleeper (-1: the sub-ballast rests on the ground or on a support).
    deck_of_sleeper = np.full(n_sl, -1, dtype=np.int64)
    if beam is not None:
        free = bs.free_dofs
        deck_w = free % 2 == 0
        deck_of_sleeper[j0 + free[deck_w] // 2] = bridge_dof[deck_w]
        # Deck DOFs couple within one element (adjacent nodes) in M, K and Rayleigh C.
        a, b = np.meshgrid(np.arange(bs.n_dof), np.arange(bs.n_dof), indexing="ij")
        adjacent = np.abs(free[a] // 2 - free[b] // 2) <= 1
        if np.abs(bs.C[~adjacent]).max(initial=0.0) > 1e-9 * np.abs(bs.C).max():
            raise ValueError("bridge damping matrix is not banded")

    # Bandwidth: the widest coupling is within a rail element, a deck element or a sub-ballast spring.
    widths = [int(np.max(rail_theta[1:] - rail_w[:-1]))]
    if beam is not None:
        widths.append(int(np.abs(bridge_dof[a] - bridge_dof[b])[adjacent].max()))
        on_deck = deck_of_sleeper >= 0
        widths.append(int(np.abs(deck_of_sleeper[on_deck] - ballast_dof[on_deck]).max()))
    bw = max(widths + [3])

    Mb, Cb, Kb = _BandBuilder(n_dof, bw), _BandBuilder(n_dof, bw), _BandBuilder(n_dof, bw)
    # Rail elements.
    ke, me = element_matrices(le, np.full(n_nodes - 1, p.rail_ei_nm2), p.rail_mass_per_m)
    el_dofs = np.stack([rail_w[:-1], rail_theta[:-1], rail_w[1:], rail_theta[1:]], axis=1)
    ii = np.broadcast_to(el_dofs[:, :, None], ke.shape)
    jj = np.broadcast_to(el_dofs[:, None, :], ke.shape)
    lower = ii >= jj
    Kb.add(ii[lower], jj[lower], ke[lower])
    Mb.add(ii[lower], jj[lower], me[lower])
    # Sleepers: pad (rail–sleeper), ballast (sleeper–ballast mass), sub-ballast (ballast–ground/deck).
    rw = rail_w[sleeper_node]
    Kb.spring(rw, sleeper_dof, np.full(n_sl, p.pad_k))
    Cb.spring(rw, sleeper_dof, np.full(n_sl, p.pad_c))
    Mb.add(sleeper_dof, sleeper_dof, np.full(n_sl, p.sleeper_mass))
    Kb.spring(sleeper_dof, ballast_dof, kba)
    Cb.spring(sleeper_dof, ballast_dof, np.full(n_sl, p.ballast_c))
    Mb.add(ballast_dof, ballast_dof, np.full(n_sl, p.ballast_mass))
    ground = deck_of_sleeper < 0
    Kb.spring(ballast_dof[ground], None, ksb[ground])
    Cb.spring(ballast_dof[ground], None, np.full(int(ground.sum()), p.subballast_c))
    on = ~ground
    if on.any():
        Kb.spring(ballast_dof[on], deck_of_sleeper[on], ksb[on])
        Cb.spring(ballast_dof[on], deck_of_sleeper[on], np.full(int(on.sum()), p.subballast_c))
    # Bridge beam.
    if beam is not None:
        keep = adjacent & (bridge_dof[a] >= bridge_dof[b])
        for B, X in ((Kb, bs.K), (Mb, bs.M), (Cb, bs.C)):
            B.add(bridge_dof[a[keep]], bridge_dof[b[keep]], X[keep])

    return Track(p, node_x, rail_w, rail_theta, sleeper_node * le, sleeper_dof, ballast_dof, kba, ksb,
                 bridge, beam, bridge_dof, Mb.ab, Cb.ab, Kb.ab)


def band_to_dense(ab: np.ndarray) -> np.ndarray:
    """The full symmetric matrix of a lower band (tests and small tracks only)."""
    bw1, n = ab.shape
    A = np.zeros((n, n))
    for k in range(bw1):
        idx = np.arange(n - k)
        A[idx + k, idx] = ab[k, : n - k]
        A[idx, idx + k] = ab[k, : n - k]
    return A


def static_rail_deflection(track: Track, loads_n: np.ndarray, x_load_m: np.ndarray, x_eval_m: np.ndarray) -> np.ndarray:
    """Static rail deflection (m, up) at ``x_eval_m`` under downward loads ``loads_n`` (N) at ``x_load_m``."""
    loads = np.atleast_1d(np.asarray(loads_n, float))
    dofs, values = track.contact_entries(x_load_m)
    f = np.zeros(track.n_dof)
    np.add.at(f, dofs, -loads[:, None] * values)
    u = cho_solve_banded((cholesky_banded(track.K, lower=True), True), f)
    de, ve = track.contact_entries(x_eval_m)
    return (u[de] * ve).sum(axis=1)


def beam_on_elastic_foundation(load_n: float, x_m: np.ndarray, params: TrackParams) -> np.ndarray:
    """Winkler estimate of the rail deflection (m, up) at distance ``x_m`` from a downward point load:
    w = −P·β/(2k)·e^(−β|x|)(cos β|x| + sin β|x|), k = support stiffness / sleeper spacing (N/m²),
    β = (k / 4EI)^(1/4) (Timoshenko; the discrete sleepers smeared into a continuous foundation)."""
    k = params.support_stiffness() / params.sleeper_spacing_m
    beta = (k / (4.0 * params.rail_ei_nm2)) ** 0.25
    bx = beta * np.abs(np.asarray(x_m, float))
    return -load_n * beta / (2.0 * k) * np.exp(-bx) * (np.cos(bx) + np.sin(bx))
