"""The Bayesian profile and vehicle properties by Metropolis-within-Gibbs: the thesis's method (§4.3).

Model (eq. 4.1–4.9)
-------------------
Unknowns: every vehicle's parameters θ_n (for the quarter-car M, m, K, k, c) and the profile
R = (R(y_1), …, R(y_P)) on a chainage grid. Vehicle n drives at constant speed v_n from chainage
x0_n, starting at rest in static equilibrium on the surface (the thesis's simulations), and its
measured channels are the forward model's response plus independent Gaussian errors of variance
σ₁² (eq. 4.1–4.2). The surface under a contact is the linear interpolant of R. Priors: independent
normals on every vehicle parameter (eq. 4.3–4.7, the vehicle class) and the first-order random walk
of eq. (4.8) on R, increments R_i − R_{i−1} ~ N(0, (y_i − y_{i−1})²/τ₁). An optional ``ridge``
(prior precision of every R_i about 0, default 0 as in the thesis) makes the level proper: the
accelerations do not see a constant shift of the profile, so without it the posterior is improper
in that one direction (the thesis's chain drifts along it).

Algorithm (§4.3.4, steps 1–5)
-----------------------------
Each iteration: for each vehicle, propose all its parameters at once from normal random walks with
the thesis's sds, simulate its response, accept with α₁ (eq. 4.15); then for each profile point in
turn propose R_i' ~ N(R_i, s_profile²) and accept with β₁ (eq. 4.17–4.19). Parameters that would
be non-positive are rejected (a vehicle needs positive masses and stiffnesses; equivalently the
class prior is truncated to positive values).

What makes it affordable — and why the target is unchanged
-----------------------------------------------------------
Done literally, every profile proposal needs a forward simulation of every vehicle:
O(n_iter · P · N · n_samples · n_dof²) — days at the thesis's size. For fixed vehicle parameters
the Newmark forward model is *linear and time-invariant* in the surface under each contact, and
the vehicle starts from the static equilibrium (itself linear in the first surface sample). So the
response to the profile is exactly

    A_n(R) = Σ_c [ g0_{n,c} · y_{n,c,0} + Σ_{k≥1} y_{n,c,k} · g_{n,c}[· − k] ],   y_{n,c,k} = W_{n,c}[k, :] R,

with ``g`` the response to a unit surface impulse under contact c at one step (from rest), ``g0``
the response to a unit initial surface height, and ``W`` the interpolation weights (two per sample).
A change δ of R_i changes the surface at the few samples whose contact lies within one grid step
of y_i, and the response by δ·h_{n,i}, h a sum of two or three shifted copies of ``g``. With the
residuals r_n = a_n − A_n kept up to date, the log-likelihood change of eq. (4.17) is exactly
δ·h·r/σ₁² − δ²·h·h/(2σ₁²): two dot products over the rest of the record per vehicle instead of a
simulation, and the acceptance probability is *identical* to the thesis's (no truncation of ``g``,
nothing approximated), so the chain and its target distribution are the same. The columns h_{n,i}
are kept for every vehicle and point (N·P·n_samples numbers: small problems only, see
``MAX_COLUMN_BYTES``) and rebuilt from two simulations per contact whenever a vehicle's parameters
change; the residuals are recomputed from a full simulation every ``refresh_every`` iterations so
that rounding cannot accumulate. The vehicle step runs the full simulation of the proposal as the
thesis does (its current misfit is the kept residual). An iteration costs a small fraction of
the literal one (``python -m benchmarks profile``).

:func:`exact_profile_posterior` is the same model's exact answer for fixed vehicle parameters: with
the response linear in R, the conditional posterior of R is Gaussian with precision
``τ₁ DᵀΛD + ridge·I + Σ_n H_nᵀH_n/σ₁²`` — a GMRF prior plus data — and mean from one solve. This is
what the design means by "the same posterior, far cheaper": the MCMC chain's profile mean converges
to it.
"""

from __future__ import annotations

import logging
import math
import time
from typing import NamedTuple, Sequence

import numpy as np
from scipy.linalg import solve_triangular

from shared.dynamics.forward import channels_from_ap
from shared.dynamics.newmark import newmark_constants
from shared.jit import kernel
from shared.vehicles import MODELS, vehicle_from_params

log = logging.getLogger(__name__)

#: §4.3.4 step 1: random-walk proposal sds of the quarter-car's parameters (SI units).
THESIS_PROPOSAL_SD: dict[str, dict[str, float]] = {
    "quarter_car": {"M": 200.0, "m": 40.0, "K": 30_000.0, "k": 100_000.0, "c": 1000.0},
}
THESIS_S_PROFILE = 0.001  # m
THESIS_TAU1 = 1e5
THESIS_SIGMA2 = 1e-3  # (m/s²)², the observation error variance σ₁²
THESIS_N_ITER = 2000
#: The exact posterior assembles a vehicle's normal equations by lag sums when P² exceeds this many
#: times nc²·n, else by BLAS on H's columns: BLAS's P²n/2 multiply-adds run near the core's peak,
#: and the lag sums' O(n²) only win on fine grids.
LAGS_ABOVE = 400.0
MAX_COLUMN_BYTES = 2e9  # the sampler keeps every vehicle's response to every grid point in memory


class McmcResult(NamedTuple):
    """Samples of the chain (one row per stored iteration) and its diagnostics.

    ``profile`` (n_kept, P) m; ``params`` (n_kept, n_vehicles, n_params) in ``stats["param_names"]``
    order; ``stats``: acceptance rates (``profile``, ``vehicles`` per vehicle), ``iterations`` and
    ``seconds`` (cumulative wall time) and ``cpu_seconds`` (the process's CPU time: what it costs on
    a loaded machine) of each stored row, ``param_names``.
    """

    profile: np.ndarray
    params: np.ndarray
    stats: dict


class ProfilePosterior(NamedTuple):
    """The exact Gaussian conditional posterior of the profile for fixed vehicle parameters."""

    mean: np.ndarray  # (P,) m
    sd: np.ndarray  # (P,) m
    precision: np.ndarray  # (P, P) 1/m²


# ---------------------------------------------------------------------------------------------
# The linear response of a vehicle to the profile


class _Geometry(NamedTuple):
    """Where each contact of one vehicle is at each sample, as grid interpolation weights."""

    idx: np.ndarray  # (nc, n) left grid point
    w: np.ndarray  # (nc, n) weight of the right point
    ks: np.ndarray  # (nc, P) first sample touching each grid point
    ke: np.ndarray  # (nc, P) one past the last


def _geometry(grid: np.ndarray, x_cg: np.ndarray, offsets: np.ndarray) -> _Geometry:
    P = grid.size
    idx = np.empty((offsets.size, x_cg.size), dtype=np.int64)
    w = np.empty((offsets.size, x_cg.size))
    ks = np.empty((offsets.size, P), dtype=np.int64)
    ke = np.empty((offsets.size, P), dtype=np.int64)
    for c, off in enumerate(offsets):
        x = x_cg + off
        i = np.clip(np.searchsorted(grid, x, side="right") - 1, 0, P - 2)
        idx[c] = i
        w[c] = np.clip((x - grid[i]) / (grid[i + 1] - grid[i]), 0.0, 1.0)  # np.interp's clamping
        j = np.arange(P)
        ks[c] = np.searchsorted(i, j - 1, side="left")  # i is non-decreasing along the pass
        ke[c] = np.searchsorted(i, j, side="right")
    return _Geometry(idx, w, ks, ke)


def _surface(geo: _Geometry, R: np.ndarray) -> np.ndarray:
    """Surface under each contact at each sample, (n, nc)."""
    return ((1.0 - geo.w) * R[geo.idx] + geo.w * R[geo.idx + 1]).T


def _simulate(system, y: np.ndarray, dt: float) -> np.ndarray:
    """Channels of ``system`` driven by surface ``y`` (n, nc), from static equilibrium at rest (the
    thesis's γ = 0.8)."""
    return channels_from_ap(system, y, newmark_constants(dt))


def _impulse_responses(system, n: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``gk`` (nc, n, nch): response at step k+s to a unit surface at step k ≥ 1 under contact c;
    ``g0`` (nc, n, nch): response to a unit surface under contact c at the first sample."""
    nc = system.n_contacts
    nch = len(system.channels)
    gk = np.zeros((nc, n, nch))
    g0 = np.zeros((nc, n, nch))
    for c in range(nc):
        if n > 1:
            y = np.zeros((n, nc))
            y[1, c] = 1.0  # an impulse at step 1 from rest: by time invariance, every step's response
            gk[c, : n - 1] = _simulate(system, y, dt)[1:]
        y = np.zeros((n, nc))
        y[0, c] = 1.0
        g0[c] = _simulate(system, y, dt)
    return gk, g0


@kernel
def _build_h(n_len, idx, w, ks, ke, gk, g0, j, h):
    """h[t] = response of the channels to a unit change of grid point j (rows ≥ the returned kmin)."""
    nc = idx.shape[0]
    nch = h.shape[1]
    kmin = n_len
    for c in range(nc):
        if ks[c, j] < ke[c, j] and ks[c, j] < kmin:
            kmin = ks[c, j]
    for t in range(kmin, n_len):
        for q in range(nch):
            h[t, q] = 0.0
    for c in range(nc):
        for k in range(ks[c, j], ke[c, j]):
            if idx[c, k] == j:
                wt = 1.0 - w[c, k]
            elif idx[c, k] == j - 1:
                wt = w[c, k]
            else:
                wt = 0.0
            if wt == 0.0:
                continue
            if k == 0:
                for t in range(0, n_len):
                    for q in range(nch):
                        h[t, q] += wt * g0[c, t, q]
            else:
                for t in range(k, n_len):
                    for q in range(nch):
                        h[t, q] += wt * gk[c, t - k, q]
    return kmin


@kernel
def _columns(n_len, idx, w, ks, ke, gk, g0, cols, kmin):
    """Every column of H (the response to a unit change of each grid point): cols (P, n, nch)."""
    P = cols.shape[0]
    for j in range(P):
        kmin[j] = _build_h(n_len, idx, w, ks, ke, gk, g0, j, cols[j])


@kernel
def _profile_sweep(R, grid, tau1, ridge, s_profile, inv_s2, n_len, cols, kmin, resid, normals, uniforms):
    """One Metropolis sweep over every profile point (eq. 4.16–4.19), residuals kept exact.

    ``cols`` (N, P, n_max, nch) holds each vehicle's response to a unit change of each grid point
    (rows from ``kmin`` on), ``resid`` (N, n_max, nch) the current residuals. Returns the number of
    accepted proposals.
    """
    P = R.size
    N = n_len.size
    nch = inv_s2.size
    accepted = 0
    for j in range(P):
        delta = s_profile * normals[j]
        # likelihood change: δ hᵀΣ⁻¹r − δ²/2 hᵀΣ⁻¹h, summed over vehicles
        dot = 0.0
        hh = 0.0
        for n in range(N):
            for t in range(kmin[n, j], n_len[n]):
                for q in range(nch):
                    hv = cols[n, j, t, q]
                    dot += hv * resid[n, t, q] * inv_s2[q]
                    hh += hv * hv * inv_s2[q]
        dlog = delta * dot - 0.5 * delta * delta * hh
        # random-walk prior (eq. 4.8): the increments on either side of point j
        new = R[j] + delta
        if j > 0:
            d2 = (grid[j] - grid[j - 1]) ** 2
            dlog -= 0.5 * tau1 / d2 * ((new - R[j - 1]) ** 2 - (R[j] - R[j - 1]) ** 2)
        if j < P - 1:
            d2 = (grid[j + 1] - grid[j]) ** 2
            dlog -= 0.5 * tau1 / d2 * ((R[j + 1] - new) ** 2 - (R[j + 1] - R[j]) ** 2)
        dlog -= 0.5 * ridge * (new * new - R[j] * R[j])
        if math.log(uniforms[j]) < dlog:
            R[j] = new
            accepted += 1
            for n in range(N):
                for t in range(kmin[n, j], n_len[n]):
                    for q in range(nch):
                        resid[n, t, q] -= delta * cols[n, j, t, q]
    return accepted


@kernel
def _columns_by_sample(n_len, idx, w, gk, g0, cols):
    """Every column of H at once into ``cols`` (P, nch, n), zeroed: cols[j, q, t] = H[t, q, j].

    ``gk``, ``g0`` (nc, nch, n): the impulse responses channel-major. Sample k of contact c puts
    weight 1 − w on grid point idx[k] and w on idx[k] + 1, and each adds its weight times the
    impulse response from k on (k = 0: the initial-height response) to that point's column: the
    same terms as :func:`_build_h`, in the same order (contacts outer, samples increasing), with
    the inner loop along contiguous memory.
    """
    nc = idx.shape[0]
    nch = cols.shape[1]
    for c in range(nc):
        for k in range(n_len):
            for side in range(2):
                j = idx[c, k] + side
                wt = w[c, k] if side == 1 else 1.0 - w[c, k]
                if wt == 0.0:
                    continue
                for q in range(nch):
                    col = cols[j, q]
                    if k == 0:
                        g = g0[c, q]
                        for t in range(n_len):
                            col[t] += wt * g[t]
                    else:
                        g = gk[c, q]
                        for t in range(k, n_len):
                            col[t] += wt * g[t - k]


@kernel
def _gram_by_lags(idx, w, gk, g0, wq, z, M, D0, b):
    """HᵀΛH and HᵀΛz from the impulse responses in O(nc²·nch·n²) operations, never forming H.

    H = Σ_c T_c W_c: T_c (n·nch, n) the causal convolution with contact c's impulse response
    (column 0: the response to the initial height, ``g0``), W_c (n, P) the interpolation weights
    (two per sample). So HᵀΛH = Σ_{c,c'} W_cᵀ A_{cc'} W_{c'} with A_{cc'}[k, l] = Σ_q w_q Σ_{t≥max(k,l)}
    T_c[t,k,q] T_{c'}[t,l,q]; for 1 ≤ k ≤ l, d = l − k, that is Σ_{s=0}^{n−1−l} g_c[s+d] g_{c'}[s]: a
    running sum as l falls at fixed lag d. Adds the pairs k < l into ``M`` and k = l into ``D0``
    (HᵀΛH = M + Mᵀ + D0) and HᵀΛz into ``b``: the dense product's sums, reordered.
    """
    nc, n = idx.shape
    nch = wq.size
    for c in range(nc):
        for c2 in range(nc):
            gc = gk[c]
            g2 = gk[c2]
            for d in range(n):
                T = D0 if d == 0 else M
                acc = 0.0
                for l in range(n - 1, d, -1):  # k = l − d ≥ 1
                    s = n - 1 - l
                    for q in range(nch):
                        acc += wq[q] * gc[s + d, q] * g2[s, q]
                    k = l - d
                    i = idx[c, k]
                    j = idx[c2, l]
                    a0 = (1.0 - w[c, k]) * acc
                    a1 = w[c, k] * acc
                    wj = w[c2, l]
                    T[i, j] += a0 * (1.0 - wj)
                    T[i, j + 1] += a0 * wj
                    T[i + 1, j] += a1 * (1.0 - wj)
                    T[i + 1, j + 1] += a1 * wj
            # k = 0: the initial-height column against every l (l = 0 with itself)
            h0 = g0[c]
            for l in range(n):
                acc = 0.0
                if l == 0:
                    for t in range(n):
                        for q in range(nch):
                            acc += wq[q] * h0[t, q] * g0[c2, t, q]
                else:
                    for t in range(l, n):
                        for q in range(nch):
                            acc += wq[q] * h0[t, q] * g2[t - l, q]
                T = D0 if l == 0 else M
                i = idx[c, 0]
                j = idx[c2, l]
                a0 = (1.0 - w[c, 0]) * acc
                a1 = w[c, 0] * acc
                wj = w[c2, l]
                T[i, j] += a0 * (1.0 - wj)
                T[i, j + 1] += a0 * wj
                T[i + 1, j] += a1 * (1.0 - wj)
                T[i + 1, j + 1] += a1 * wj
        # HᵀΛz: y[k] = Σ_q w_q Σ_{t≥k} T_c[t,k,q] z[t,q], spread by the weights
        for k in range(n):
            y = 0.0
            if k == 0:
                for t in range(n):
                    for q in range(nch):
                        y += wq[q] * g0[c, t, q] * z[t, q]
            else:
                for t in range(k, n):
                    for q in range(nch):
                        y += wq[q] * gk[c, t - k, q] * z[t, q]
            b[idx[c, k]] += (1.0 - w[c, k]) * y
            b[idx[c, k] + 1] += w[c, k] * y


class VehiclePass:
    """One vehicle's pass as the sampler sees it: its channels ``data`` (n_samples, n_channels), driven
    at ``speed`` from chainage ``x0`` and sampled every ``dt``, over the profile ``grid``; and its current
    linear structure (rebuilt by :meth:`set_params` when its parameters change)."""

    def __init__(self, model: str, data: np.ndarray, speed: float, x0: float, dt: float, grid: np.ndarray):
        self.model, self.data, self.speed, self.x0, self.dt, self.grid = model, data, speed, x0, dt, grid
        self.n = data.shape[0]
        self.x_cg = x0 + speed * dt * np.arange(self.n)

    def set_params(self, params: dict[str, float]) -> None:
        self.params = dict(params)
        self.system = vehicle_from_params(self.model, params).system()
        self.geo = _geometry(self.grid, self.x_cg, self.system.offsets_m)
        self.gk, self.g0 = _impulse_responses(self.system, self.n, self.dt)

    def columns(self, cols: np.ndarray, kmin: np.ndarray) -> None:
        """Fill ``cols`` (P, ≥ n, nch) with the response to a unit change of each grid point."""
        g = self.geo
        _columns(self.n, g.idx, g.w, g.ks, g.ke, self.gk, self.g0, cols, kmin)

    def forward(self, R: np.ndarray, params: dict[str, float] | None = None) -> np.ndarray:
        if params is None:
            return _simulate(self.system, _surface(self.geo, R), self.dt)
        system = vehicle_from_params(self.model, params).system()
        geo = _geometry(self.grid, self.x_cg, system.offsets_m)
        return _simulate(system, _surface(geo, R), self.dt)


def forward_channels(model: str, params: dict[str, float], grid: np.ndarray, R: np.ndarray, speed: float,
                     x0: float, n_samples: int, dt: float) -> np.ndarray:
    """The model's channels (n_samples, n_channels) for a pass over the linear interpolant of R on grid."""
    v = VehiclePass(model, np.zeros((n_samples, 1)), speed, x0, dt, np.asarray(grid, float))
    return v.forward(np.asarray(R, float), params)


def response_matrix(model: str, params: dict[str, float], grid: np.ndarray, speed: float, x0: float,
                    n_samples: int, dt: float) -> np.ndarray:
    """H (n_samples, n_channels, P) with channels = H·R exactly (the linearity the sampler uses)."""
    grid = np.asarray(grid, float)
    v = VehiclePass(model, np.zeros((n_samples, 1)), speed, x0, dt, grid)
    v.set_params(params)
    nch = len(v.system.channels)
    cols = np.zeros((grid.size, n_samples, nch))
    v.columns(cols, np.zeros(grid.size, dtype=np.int64))
    return cols.transpose(1, 2, 0)


def _prior_precision(grid: np.ndarray, tau1: float, ridge: float) -> np.ndarray:
    """τ₁DᵀD + ridge·I (dense, tridiagonal): D the first differences over the grid steps."""
    P = grid.size
    d2 = 1.0 / np.diff(grid) ** 2
    Q = np.zeros((P, P))
    i = np.arange(P - 1)
    Q[i, i + 1] = Q[i + 1, i] = -tau1 * d2
    diag = np.zeros(P)
    diag[:-1] += d2
    diag[1:] += d2
    Q[np.arange(P), np.arange(P)] = tau1 * diag + ridge
    return Q


def _inv_sigma2(sigma2, nch: int) -> np.ndarray:
    s = np.broadcast_to(np.asarray(sigma2, float), (nch,))
    if not np.all(s > 0):
        raise ValueError("sigma2: observation error variances must be > 0")
    return 1.0 / s


def _data_normal_equations(veh: VehiclePass, z: np.ndarray, w: np.ndarray, buffer: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """One vehicle's ``HᵀΛH`` (P, P) and ``HᵀΛz`` (P,), Λ = diag(w) per channel.

    The columns of H are built in ``buffer`` (≥ P·n·nch numbers, reused across vehicles: a fresh
    array per vehicle costs more in page faults than the columns themselves), each a contiguous
    row of C (P, n·nch), weighted by √w once; the Gram matrix is one symmetric rank-k product
    (``C @ C.T``: BLAS syrk, half the multiply-adds of a general product, no transposed copy of H).
    That is ~P²·n·nch/2 multiply-adds; on fine grids (P² > ``LAGS_ABOVE``·nc²·n) the lag sums of
    :func:`_gram_by_lags` (~nc²·n²·(nch + 4), scalar) are cheaper.
    """
    P = veh.grid.size
    n, nch = z.shape
    nc = veh.geo.idx.shape[0]
    if P * P > LAGS_ABOVE * nc * nc * n:
        M, D0, b = np.zeros((P, P)), np.zeros((P, P)), np.zeros(P)
        _gram_by_lags(veh.geo.idx, veh.geo.w, veh.gk, veh.g0, np.asarray(w, float), z, M, D0, b)
        return M + M.T + D0, b
    C = buffer[: P * nch * n].reshape(P, nch * n)  # rows of H ordered (channel, sample)
    C.fill(0.0)
    _columns_by_sample(n, veh.geo.idx, veh.geo.w, np.ascontiguousarray(veh.gk.transpose(0, 2, 1)),
                       np.ascontiguousarray(veh.g0.transpose(0, 2, 1)), C.reshape(P, nch, n))
    zt = z.T  # (nch, n), matching the rows
    if np.any(w != 1.0):
        rw = np.sqrt(w)
        C.reshape(P, nch, n)[...] *= rw[:, None]  # HᵀΛH = (√Λ H)ᵀ(√Λ H)
        zt = zt * rw[:, None]
    return C @ C.T, C @ zt.ravel()


def exact_profile_posterior(
    model: str,
    channels_list: Sequence[np.ndarray],
    speeds: Sequence[float],
    dt: float,
    grid: np.ndarray,
    params_list: Sequence[dict[str, float]],
    *,
    x0: Sequence[float] | None = None,
    tau1: float = THESIS_TAU1,
    sigma2: float | Sequence[float] = THESIS_SIGMA2,
    ridge: float = 0.0,
) -> ProfilePosterior:
    """The exact posterior of R given fixed vehicle parameters under the model of §4.3 (Gaussian).

    Same likelihood (eq. 4.1–4.2) and prior (eq. 4.8, plus ``ridge``) as
    :func:`mcmc_profile_and_vehicles`: precision ``τ₁DᵀD + ridge·I + Σ_n H_nᵀH_n/σ₁²``, mean from
    one Cholesky solve, sd from the inverse factor. Each H_n is assembled from the vehicle's impulse
    responses (two simulations per contact, as the chain's columns are; no simulation per grid
    point) and enters as one symmetric rank-k product, or on fine grids as lag sums of the impulse
    responses, O(n²) (:func:`_data_normal_equations`). The data make the precision dense — the
    quarter-car's impulse response does not decay within a 20 m pass — so the algebra is dense: at
    the thesis's size (P 201, n ≈ 550) ~P²n/2 multiply-adds per vehicle, which BLAS runs near the
    core's peak; skipping H's causal zeros block-wise (half the multiply-adds) is no faster there,
    nor are the lag sums, so neither is used there. Small problems only.
    """
    grid = np.asarray(grid, float)
    x0 = [0.0] * len(channels_list) if x0 is None else list(x0)
    Q = _prior_precision(grid, tau1, ridge)
    b = np.zeros(grid.size)
    zs = [np.asarray(z, float).reshape(len(z), -1) for z in channels_list]
    buffer = np.empty(grid.size * max(z.size for z in zs))
    for z, v, x, p in zip(zs, speeds, x0, params_list):
        veh = VehiclePass(model, z, float(v), float(x), dt, grid)
        veh.set_params(p)
        Qn, bn = _data_normal_equations(veh, z, _inv_sigma2(sigma2, z.shape[1]), buffer)
        Q += Qn
        b += bn
    L = np.linalg.cholesky(Q)
    mean = solve_triangular(L.T, solve_triangular(L, b, lower=True), lower=False)
    Linv = solve_triangular(L, np.eye(grid.size), lower=True)
    sd = np.sqrt(np.einsum("ij,ij->j", Linv, Linv))
    return ProfilePosterior(mean, sd, Q)


# ---------------------------------------------------------------------------------------------
# Metropolis-within-Gibbs


def _log_normal_prior(x: np.ndarray, mean: np.ndarray, sd: np.ndarray) -> float:
    return float(-0.5 * np.sum(((x - mean) / sd) ** 2))


def mcmc_profile_and_vehicles(
    model: str,
    channels_list: Sequence[np.ndarray],
    speeds: Sequence[float],
    dt: float,
    grid: np.ndarray,
    prior_mean: dict[str, float],
    prior_sd: dict[str, float],
    rng: np.random.Generator,
    n_iter: int = THESIS_N_ITER,
    *,
    x0: Sequence[float] | None = None,
    tau1: float = THESIS_TAU1,
    sigma2: float | Sequence[float] = THESIS_SIGMA2,
    s_profile: float = THESIS_S_PROFILE,
    proposal_sd: dict[str, float] | None = None,
    init_params: Sequence[dict[str, float]] | None = None,
    init_profile: np.ndarray | None = None,
    update_vehicles: bool = True,
    ridge: float = 0.0,
    thin: int = 1,
    refresh_every: int = 50,
    time_budget_s: float | None = None,
    cpu_budget_s: float | None = None,
) -> McmcResult:
    """Sample the profile and every vehicle's parameters by Metropolis-within-Gibbs (§4.3.4).

    Parameters
    ----------
    model : str
        Vehicle model; the thesis uses ``"quarter_car"`` (channel: body acceleration).
    channels_list : sequence of arrays (n_samples_i, n_channels)
        Each vehicle's measured channels, sampled every ``dt`` s from the moment it is at chainage
        ``x0[i]`` (default 0) in static equilibrium; constant speed ``speeds[i]`` (m/s).
    grid : array (P,)
        Chainage of the unknown profile points (m), increasing.
    prior_mean, prior_sd : dict
        The vehicle class (Table 4.1): independent normal priors of every parameter.
    rng : numpy.random.Generator
    n_iter : int
        Iterations (thesis: 2000).
    tau1, sigma2, s_profile : float
        Smoothing precision of eq. (4.8) (thesis 1e5), observation error variance σ₁² (thesis
        0.001 (m/s²)², or one per channel) and the profile proposal sd (thesis 0.001 m).
    proposal_sd : dict, optional
        Random-walk sds of the parameters; default the thesis's for the quarter-car, else 2 % of
        the prior mean. A parameter with sd 0 is held fixed.
    init_params, init_profile : optional
        Starting point; default the class mean for every vehicle and a flat profile.
    update_vehicles : bool
        False holds every vehicle at ``init_params`` (the profile's conditional posterior given the
        vehicles, which :func:`exact_profile_posterior` gives exactly).
    ridge : float
        Prior precision of each R_i about 0 (1/m²); 0 is eq. (4.8) as printed.
    thin : int
        Keep every ``thin``-th iteration.
    refresh_every : int
        Recompute the residuals from a full simulation every this many iterations (the
        incremental updates are exact up to rounding).
    time_budget_s : float, optional
        Stop early after this much wall time (the samples so far are returned).
    cpu_budget_s : float, optional
        Stop early after this much CPU time of the process (the same work on a loaded machine).

    Returns
    -------
    McmcResult
        ``(profile, params, stats)``.
    """
    if model not in MODELS:
        raise ValueError(f"model: unknown {model!r}")
    grid = np.asarray(grid, float)
    if grid.ndim != 1 or grid.size < 3 or not np.all(np.diff(grid) > 0):
        raise ValueError("grid: needs at least 3 increasing chainages")
    n_veh = len(channels_list)
    names = list(MODELS[model].param_names())
    if proposal_sd is None:
        proposal_sd = THESIS_PROPOSAL_SD.get(model, {n: 0.02 * prior_mean[n] for n in names})
    step_sd = np.array([proposal_sd.get(n, 0.0) for n in names], dtype=float)
    mean = np.array([prior_mean[n] for n in names], dtype=float)
    sd = np.array([prior_sd[n] for n in names], dtype=float)
    sd = np.where(sd > 0, sd, np.inf)  # a zero prior sd: flat (the parameter is held by its step sd 0)
    x0 = [0.0] * n_veh if x0 is None else [float(x) for x in x0]
    init_params = [dict(prior_mean) for _ in range(n_veh)] if init_params is None else [dict(p) for p in init_params]
    R = np.zeros(grid.size) if init_profile is None else np.array(init_profile, dtype=float)

    vehicles = []
    for z, v, x, p in zip(channels_list, speeds, x0, init_params):
        veh = VehiclePass(model, np.asarray(z, float).reshape(len(z), -1), float(v), x, dt, grid)
        veh.set_params({n: p[n] for n in names})
        vehicles.append(veh)
    nch = vehicles[0].data.shape[1]
    inv_s2 = _inv_sigma2(sigma2, nch)
    n_max = max(v.n for v in vehicles)
    n_len = np.array([v.n for v in vehicles], dtype=np.int64)
    size = n_veh * grid.size * n_max * nch * 8
    if size > MAX_COLUMN_BYTES:
        raise ValueError(f"mcmc: the response columns need {size / 1e9:.1f} GB (> {MAX_COLUMN_BYTES / 1e9:.0f} GB); "
                         "this reference is for small problems (fewer points, vehicles or samples)")
    # Stacked per-vehicle arrays for the compiled sweep, padded to the longest record.
    cols = np.zeros((n_veh, grid.size, n_max, nch))
    kmin = np.zeros((n_veh, grid.size), dtype=np.int64)
    resid = np.zeros((n_veh, n_max, nch))

    def load(i: int) -> None:
        vehicles[i].columns(cols[i], kmin[i])

    for i in range(n_veh):
        load(i)

    n_keep = n_iter // thin
    prof_out = np.empty((n_keep, grid.size))
    par_out = np.empty((n_keep, n_veh, len(names)))
    iters = np.empty(n_keep, dtype=np.int64)
    seconds = np.empty(n_keep)
    cpu_seconds = np.empty(n_keep)
    acc_prof = 0
    acc_veh = np.zeros(n_veh, dtype=np.int64)
    kept = 0
    t_start = time.perf_counter()
    cpu_start = time.process_time()
    it = 0
    for i, v in enumerate(vehicles):
        resid[i, : v.n] = v.data - v.forward(R)
    for it in range(1, n_iter + 1):
        for i, v in enumerate(vehicles):
            if it % refresh_every == 0:  # from a full simulation, so that rounding cannot accumulate
                resid[i, : v.n] = v.data - v.forward(R)
            if not (update_vehicles and np.any(step_sd > 0)):
                continue
            theta = np.array([v.params[n] for n in names])
            prop = theta + step_sd * rng.standard_normal(theta.size)
            if not np.all(prop[step_sd > 0] > 0):
                continue  # outside the (positive) support: rejected
            p_dict = dict(zip(names, map(float, prop)))
            try:
                pred_new = v.forward(R, p_dict)  # step 4b: the thesis's full simulation
            except (ValueError, np.linalg.LinAlgError):
                continue
            r_old = resid[i, : v.n]
            r_new = v.data - pred_new
            log_a = (-0.5 * (float(np.sum(r_new * r_new * inv_s2)) - float(np.sum(r_old * r_old * inv_s2)))
                     + _log_normal_prior(prop, mean, sd) - _log_normal_prior(theta, mean, sd))
            if math.log(rng.uniform()) < log_a:
                v.set_params(p_dict)
                load(i)
                resid[i, : v.n] = r_new
                acc_veh[i] += 1
        acc_prof += _profile_sweep(R, grid, tau1, ridge, s_profile, inv_s2, n_len, cols, kmin, resid,
                                   rng.standard_normal(grid.size), rng.uniform(size=grid.size))
        if it % thin == 0:
            prof_out[kept] = R
            par_out[kept] = [[v.params[n] for n in names] for v in vehicles]
            iters[kept] = it
            seconds[kept] = time.perf_counter() - t_start
            cpu_seconds[kept] = time.process_time() - cpu_start
            kept += 1
        if time_budget_s is not None and time.perf_counter() - t_start > time_budget_s:
            break
        if cpu_budget_s is not None and time.process_time() - cpu_start > cpu_budget_s:
            break
    stats = {
        "profile": acc_prof / max(it * grid.size, 1),
        "vehicles": (acc_veh / max(it, 1)).tolist(),
        "iterations": iters[:kept],
        "seconds": seconds[:kept],
        "cpu_seconds": cpu_seconds[:kept],
        "param_names": names,
        "n_iter": it,
    }
    return McmcResult(prof_out[:kept], par_out[:kept], stats)


# ---------------------------------------------------------------------------------------------
# Bridge: per-element second moments of area and vehicle weights (thesis §4.5.4)


class BridgeMcmcResult(NamedTuple):
    """Samples of the bridge MCMC: ``I`` (kept, n_e) m⁴, ``weights`` (kept, n_vehicles) N, and
    ``stats`` (acceptance rates, iteration numbers and wall seconds of every kept sample)."""

    I: np.ndarray
    weights: np.ndarray
    stats: dict


def mcmc_bridge_elements(deflections: list[np.ndarray], vehicle_of_pass: list[int], G: np.ndarray, E_pa: float,
                         I0: np.ndarray, weight_prior: tuple[float, float], n_iter: int = 2000,
                         s_weight_n: float = 200.0 * 9.81, s_I: float = 0.001, tau2: float = 1e4,
                         sigma2: float = 1e-11, seed: int = 0, thin: int = 1,
                         time_budget_s: float | None = None) -> BridgeMcmcResult:
    """Metropolis-within-Gibbs for the element second moments of area ``I_z`` and each vehicle's
    static wheel load ``W_n`` from per-pass deflections (thesis §4.5.4, eq. 4.36–4.41).

    ``deflections[p]`` (n_x,) m, positive downwards, observed under the wheel at the points where
    ``G`` (n_x, n_e, m³) — the unit-load compliance kernel, deflection = W·Σ_z G_z/(E·I_z) — is
    given; ``vehicle_of_pass[p]`` the vehicle index of pass p; ``weight_prior`` (mean, sd) N, the
    class prior (its mean fixes the scale); ``I0`` the start. The thesis's settings are the defaults
    (n_iter 2000, s_M 200 kg, s_I 0.001 m⁴, τ₂ 1e4, σ₃² 1e-11); each iteration proposes every vehicle's
    load in turn (eq. 4.36–4.37), then every element in turn (eq. 4.38–4.41, GMRF prior eq. 4.34).

    The thesis computes the expected deflection by a vehicle–bridge simulation per proposal; it is
    linear in the compliances and the load, so here a proposal updates the kept residuals by one
    scaled kernel column — the acceptance probabilities are the thesis's, for the quasi-static
    model (which is what its likelihood reduces to for a static load).
    """
    rng = np.random.default_rng(seed)
    D = np.asarray(deflections, dtype=float)  # (P, n_x)
    veh = np.asarray(vehicle_of_pass, dtype=int)
    nv = int(veh.max()) + 1
    I = np.array(I0, dtype=float)
    n_e = I.size
    wm, ws = weight_prior
    W = np.full(nv, float(wm))
    comp = G @ (1.0 / (E_pa * I))  # (n_x,) deflection per newton
    resid = D - W[veh][:, None] * comp[None, :]
    inv2s = 0.5 / sigma2
    passes_of = [np.flatnonzero(veh == n) for n in range(nv)]
    kept = n_iter // thin
    I_out = np.empty((kept, n_e))
    W_out = np.empty((kept, nv))
    iters = np.empty(kept, dtype=int)
    secs = np.empty(kept)
    acc_w = np.zeros(nv)
    acc_i = np.zeros(n_e)
    k = 0
    it = 0
    t0 = time.perf_counter()
    for it in range(1, n_iter + 1):
        for n in range(nv):
            ps = passes_of[n]
            if ps.size == 0:
                continue
            w_new = W[n] + s_weight_n * rng.standard_normal()
            if w_new <= 0:
                continue
            r_new = D[ps] - w_new * comp[None, :]
            log_a = (-inv2s * (float(np.sum(r_new * r_new)) - float(np.sum(resid[ps] ** 2)))
                     - 0.5 * ((w_new - wm) ** 2 - (W[n] - wm) ** 2) / ws**2)
            if math.log(rng.uniform()) < log_a:
                W[n] = w_new
                resid[ps] = r_new
                acc_w[n] += 1
        Wp = W[veh][:, None]
        for z in range(n_e):
            i_new = I[z] + s_I * rng.standard_normal()
            if i_new <= 0:
                continue
            dcol = (1.0 / (E_pa * i_new) - 1.0 / (E_pa * I[z])) * G[:, z]
            r_new = resid - Wp * dcol[None, :]
            prior_old = prior_new = 0.0
            if z > 0:
                prior_old += (I[z] - I[z - 1]) ** 2
                prior_new += (i_new - I[z - 1]) ** 2
            if z < n_e - 1:
                prior_old += (I[z + 1] - I[z]) ** 2
                prior_new += (I[z + 1] - i_new) ** 2
            log_a = -inv2s * (float(np.sum(r_new * r_new)) - float(np.sum(resid * resid))) - 0.5 * tau2 * (
                prior_new - prior_old)
            if math.log(rng.uniform()) < log_a:
                I[z] = i_new
                resid = r_new
                comp = comp + dcol
                acc_i[z] += 1
        if it % thin == 0 and k < kept:
            I_out[k], W_out[k], iters[k], secs[k] = I, W, it, time.perf_counter() - t0
            k += 1
        if time_budget_s is not None and time.perf_counter() - t0 > time_budget_s:
            break
    stats = {"weights": (acc_w / max(it, 1)).tolist(), "elements": (acc_i / max(it, 1)).tolist(),
             "iterations": iters[:k], "seconds": secs[:k], "n_iter": it}
    return BridgeMcmcResult(I_out[:k], W_out[:k], stats)
