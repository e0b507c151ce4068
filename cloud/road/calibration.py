"""Fleet self-calibration, the vehicle step: every vehicle's identifiable ratios, jointly.

Only ratios are identifiable, so each vehicle is fitted in the parametrisation of
:mod:`shared.vehicles.calibration`: its reference mass held at the class mean, the logarithms of the
ratios of every other mass, stiffness and damping to it, lengths absolute.

The step runs in the cloud but needs no raw data: a segment's AP under a known calibration is a
lossless encoding of the vehicle's measured channels (the inverse is exactly invertible), so the
cloud reconstructs the channels by running the forward model over the AP (:class:`PassChannels`)
and gets the AP the vehicle *would* have produced under candidate parameters θ as

    AP_θ = inverse_θ( forward_θ0( AP_θ0 ) ).

The fleet objective (:func:`fit_fleet`) is the agreement of all vehicles' APs in a band of
wavelengths every pass resolves, with the road profile *profiled out*: for given θ the best
profile is the weighted mean of the APs (exact, closed form), so

    J(θ) = Σ_passes w_p ‖B AP_p(θ_v(p)) − mean_w(B AP(θ))‖² + ‖(θ − μ)/σ‖²

is minimised over all vehicles' log-ratios at once by Levenberg–Marquardt (variable projection).
Solving for the whole fleet removes the slow mode of alternating "profile given vehicles" with
"vehicles given profile" (all vehicles drifting together); the class prior (μ, σ) pins the
directions the data do not see (the fleet's common scale is only weakly identifiable, some
half-car ratios hardly at all). In AP space the misfit is smooth in the ratios — for a sprung mass
the AP is *linear* in m/k — where the acceleration-space misfit of a lightly damped vehicle has a
local minimum at every resonance match. Per-pass noise weights are re-estimated from the residual
(empirical Bayes), and the Gauss–Newton Hessian at the optimum gives the Laplace 95 % intervals.
Each pass's unknown start state is a nuisance of the fit (see :class:`PassChannels`).

The AP-space misfit weighs every wavelength in the band alike, which is right where the AP's
error is small against the road (noise-free, or a sprung mass) but not where the inverse amplifies
sensor noise beyond the road's signal (a half-car at 1 % noise). :func:`fit_vehicle` is the
per-vehicle alternative in acceleration space, where sensor noise is white (used for quarter-cars
and half-cars, see :mod:`cloud.road.fleet_calibration` and :class:`RemapSettings`).
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import butter, sosfiltfilt

from shared.dynamics.forward import channels_from_ap, channels_transpose
from shared.dynamics.inverse import InverseStream, build_inverse, edge_gamma
from shared.dynamics.newmark import newmark_constants
from shared.vehicles import vehicle_from_params
from shared.vehicles.calibration import REFERENCE, calibration_names, class_prior, from_calibration, to_calibration

log = logging.getLogger(__name__)

#: s: the time grid of the remap where it is a free choice (continuous-time APs; the filter barely
#: depends on it), and the edge's sample interval where a pass does not say (a 500 Hz logger's).
#: Where the remap re-runs or undoes the edge's inverse it uses the pass's own (:attr:`PassAp.dt_s`).
REMAP_DT = 0.002
#: Newmark γ of the remap's inverse under candidate parameters. The channels are reconstructed
#: with the edge's γ = 0.8 (exactly what the edge inverted), but γ = 0.8's numerical damping at a
#: half-car's wheel hop biases what the fleet agrees on in the axle ratios; γ = 0.6 (spurious roots
#: still decaying, at −2/3) removes most of that bias.
REMAP_GAMMA = 0.6
BAND_M = (1.0, 30.0)  # wavelengths compared: resolved by every pass, free of drift-control effects
TRIM_M = 3.0  # m cut at each end of a pass after band-passing (filter edge effects)
GAP_MARGIN_M = 5.0  # m masked around a hole in a pass (the inverse's and the filter's memory)
FD_STEP = 1e-4  # log-step of the finite-difference Jacobian


@dataclasses.dataclass(frozen=True)
class RemapSettings:
    """How the per-vehicle step (:class:`PassRemap`) compares a model's channels.

    The channels are reconstructed from the AP, exactly only for what the AP holds exactly. A
    half-car's AP at 1 % noise is mostly the inverse's amplified noise, and two things then spoil
    the reconstruction: the forward model's start in static equilibrium on that noisy AP leaves a
    free response that outlasts the warm-up, and the linear interpolation from the grid back to the
    samples folds part of the AP's short-wave noise to low frequencies. The start state as a
    nuisance takes out the first, a low-pass of AP and consensus alike the second.

    ``lowpass_cpm``: zero-phase low-pass (cycles per metre) of the AP and the consensus on the grid
    before the remap (both alike, so the comparison stays exact below it; a road vehicle's body and
    wheel-hop content lies well below 1.5 c/m × speed). ``free_start``: the unknown start state of
    each pass is a nuisance, profiled out of the misfit (its free responses projected away, as
    :class:`PassChannels` does for the joint step). ``predict_gamma``: Newmark γ of the prediction
    under candidate parameters (the reconstruction keeps the edge's, so the round trip is exact).
    The edge's γ = 0.8 damps a half-car's wheel hop numerically, so a fit predicting at 0.8 is
    biased even against the true profile. Against a consensus of 0.8 APs (each distorted by its own
    vehicle and speed) predicting at 0.8 leaves a bias the fleet shares, and predicting at ½ one
    larger still. The half-car therefore predicts at ½ against a consensus of
    continuous-time APs (:func:`cloud.road.continuous.continuous_ap`,
    :data:`cloud.road.fleet_calibration.CONTINUOUS_CONSENSUS`);
    its own channels are still reconstructed at the edge's γ (exact round trip).
    """

    lowpass_cpm: float | None = None
    free_start: bool = False
    predict_gamma: float | None = None  # None: the edge's (edge_gamma(model))


#: Per model; the default (the quarter-car's) changes nothing. The half-car needs all three: in
#: AP space (the joint step) its noisy AP does not calibrate.
REMAP_SETTINGS = {"half_car": RemapSettings(lowpass_cpm=1.5, free_start=True, predict_gamma=0.5)}


@dataclasses.dataclass(frozen=True)
class PassAp:
    """One pass's AP under known parameters, per contact, on the route grid (NaN: no data)."""

    start_index: int
    spacing_m: float
    values: np.ndarray  # (n_points, n_contacts)
    speed_mps: float
    #: s: the sample interval the edge inverted the pass at (its pass-done says): the Newmark transfer
    #: of the edge's inverse depends on it, so it is undone at this step, not the grid's
    dt_s: float = REMAP_DT


@dataclasses.dataclass(frozen=True)
class VehicleFit:
    names: list[str]
    mean: np.ndarray  # calibration quantities (ratios, lengths)
    lo95: np.ndarray
    hi95: np.ndarray
    params: dict[str, float]  # full parameter set (reference mass at the class mean)
    residual_m: float  # rms band-passed misfit of the vehicle's APs to the consensus
    n_points: int


def _band(spacing_m: float):
    lo, hi = BAND_M
    return butter(2, [1.0 / hi, 1.0 / lo], btype="band", fs=1.0 / spacing_m, output="sos")


def _lowpass_grid(values: np.ndarray, spacing_m: float, cutoff_cpm: float) -> np.ndarray:
    """Columns of a grid series (n_points, n_contacts) low-passed zero-phase at ``cutoff_cpm``
    cycles/m; holes filled by linear interpolation first (so they do not ring), an empty column 0."""
    sos = butter(4, cutoff_cpm, fs=1.0 / spacing_m, output="sos")
    out = np.zeros(values.shape)
    for i in range(values.shape[1]):
        v = values[:, i]
        ok = np.isfinite(v)
        if ok.sum() < 2:
            continue
        filled = np.interp(np.arange(v.size), np.flatnonzero(ok), v[ok])
        out[:, i] = sosfiltfilt(sos, filled, padlen=min(v.size - 1, 3 * int(round(1.0 / (cutoff_cpm * spacing_m)))))
    return out


def _free_response_basis(model: str, params0: dict, n_samples: int, skip: int, scale: np.ndarray,
                         gamma: float | None = None, dt: float = REMAP_DT) -> np.ndarray:
    """Orthonormal basis (n_samples − skip) · n_channels × 2 n_dof of the channels' free responses of
    the ``params0`` vehicle from a unit displacement or velocity of each degree of freedom, at Newmark
    ``gamma`` (default the edge's), in the units of :meth:`PassRemap.residual`: what a wrong start
    state adds to the reconstructed channels."""
    system = vehicle_from_params(model, params0).system()
    n_dof = system.n_dof
    zero = np.zeros((n_samples, system.G.shape[1]))
    cols = []
    for d in range(n_dof):
        e = np.zeros(n_dof)
        e[d] = 1.0
        for u0, v0 in ((e, None), (np.zeros(n_dof), e)):
            free = channels_from_ap(system, zero, newmark_constants(dt, edge_gamma(model) if gamma is None else gamma),
                                    u0=u0, v0=v0)
            cols.append((free[skip:] / scale).ravel())
    A = np.stack(cols, axis=1)
    q, _ = np.linalg.qr(A / np.maximum(np.linalg.norm(A, axis=0), 1e-300))
    return q


class PassChannels:
    """One pass prepared for the vehicle step: its measured channels, reconstructed from its AP.

    ``values`` of the :class:`PassAp` are the AP of each contact on the route grid under
    ``params0``; contact i sits ``offsets_m[i]`` ahead of the centre of gravity, which moves at the
    pass's speed. :meth:`aps` returns band-passed APs under other parameters on the same grid.

    The vehicle's state when the pass starts is unknown (the forward model starts it in static
    equilibrium), so the reconstructed channels hold a free response of the ``params0`` vehicle
    that the true channels do not. Under ``params0`` it maps back to nothing, under other
    parameters to a spurious AP over the first tens of metres — for an undamped sprung mass over
    the whole pass. It is therefore a nuisance of the fit: ``free`` holds the free responses from
    a unit initial displacement and velocity of each degree of freedom (scaled to a typical state,
    so a coefficient of 1 is a typical start), which the solver adds with unknown coefficients.
    """

    def __init__(self, model: str, params0: dict, ap: PassAp, dt: float | None = None):
        # the edge's step by default: the channels are reconstructed exactly as the edge inverted
        dt = ap.dt_s if dt is None else dt
        self.model, self.dt = model, dt
        self.start_index, self.spacing_m = ap.start_index, ap.spacing_m
        values = np.asarray(ap.values, float)
        self.n_points, self.n_contacts = values.shape
        h = ap.spacing_m
        x = (ap.start_index + np.arange(self.n_points)) * h
        system0 = vehicle_from_params(model, params0).system()
        off0 = system0.offsets_m
        ok = np.isfinite(values)
        if (ok.sum(axis=0) < 2).any():
            raise ValueError("pass: a contact has no AP")
        first = [x[ok[:, i]][0] - off0[i] for i in range(self.n_contacts)]
        last = [x[ok[:, i]][-1] - off0[i] for i in range(self.n_contacts)]
        xc0, xc1 = max(first), min(last)  # centre-of-gravity span over which every contact has data
        if xc1 - xc0 < 20 * h:
            raise ValueError("pass: too short")
        self.x_cg = xc0 + ap.speed_mps * np.arange(0.0, (xc1 - xc0) / ap.speed_mps, dt)
        ap_t = np.stack([np.interp(self.x_cg + off0[i], x[ok[:, i]], values[ok[:, i], i])
                         for i in range(self.n_contacts)], axis=1)
        self.z = channels_from_ap(system0, ap_t, newmark_constants(dt, edge_gamma(model)))
        # Free responses: displacement scale twice the AP's spread (lengths over the contacts'
        # lever arm for rotations), velocity scale that times the DOF's own natural frequency.
        amp = 2.0 * float(np.std(ap_t)) + 1e-6
        lever = float(np.max(np.abs(off0))) if np.any(off0) else 1.0
        n_dof = system0.n_dof
        zero = np.zeros_like(ap_t)
        self.free = []
        for d in range(n_dof):
            u_scale = amp if system0.translational[d] else amp / lever
            omega = math.sqrt(system0.K[d, d] / system0.M[d, d])
            for kind in ("u", "v"):
                e = np.zeros(n_dof)
                e[d] = u_scale if kind == "u" else u_scale * omega
                free = channels_from_ap(system0, zero, newmark_constants(dt, edge_gamma(model)),
                                        u0=e if kind == "u" else np.zeros(n_dof), v0=e if kind == "v" else None)
                self.free.append(free)
        # Holes inside the pass (refused segments): their neighbourhood is never compared.
        hole = np.zeros(self.n_points, bool)
        for i in range(self.n_contacts):
            idx = np.flatnonzero(ok[:, i])
            inner = np.zeros(self.n_points, bool)
            inner[idx[0] : idx[-1] + 1] = True
            hole |= inner & ~ok[:, i]
        if hole.any():
            m = int(round(GAP_MARGIN_M / h))
            hole = np.convolve(hole, np.ones(2 * m + 1), mode="same") > 0
        self.hole = hole
        self.sos = _band(h)

    @property
    def n_free(self) -> int:
        return len(self.free)

    def aps(self, inverse, inputs: list[np.ndarray]) -> list[np.ndarray]:
        """Band-passed APs (each (n_points, n_contacts)) of the channel series ``inputs`` under the
        compiled ``inverse`` on this pass's grid; NaN where not compared (outside the span, the
        inverse's warm-up, trimmed ends, holes)."""
        skip = min(inverse.n_warmup, self.z.shape[0] - 2)
        offsets = inverse.system.offsets_m
        h = self.spacing_m
        trim = self._trim()
        ys = [InverseStream(inverse).update(z)[skip:] for z in inputs]
        out = [np.full((self.n_points, self.n_contacts), np.nan) for _ in inputs]
        for i in range(self.n_contacts):
            pos = self.x_cg[skip:] + offsets[i]
            k0 = max(int(math.ceil(pos[0] / h)) - self.start_index, 0)
            k1 = min(int(math.floor(pos[-1] / h)) - self.start_index + 1, self.n_points)
            if k1 - k0 < 2 * trim + 20:
                continue
            xs = (self.start_index + np.arange(k0, k1)) * h
            cols = np.stack([np.interp(xs, pos, y[:, i]) for y in ys], axis=1)
            band = self._band(cols)
            for j, o in enumerate(out):
                o[k0 + trim : k1 - trim, i] = band[trim : band.shape[0] - trim, j]
        for o in out:
            o[self.hole] = np.nan
        return out

    def _band(self, cols: np.ndarray) -> np.ndarray:
        """Each column less its straight line (the inverse's free drift; the filter's padding likes no
        ramp), band-passed zero-phase."""
        u = np.arange(cols.shape[0]) - 0.5 * (cols.shape[0] - 1)
        cols = cols - cols.mean(axis=0) - np.outer(u, (u @ cols) / (u @ u))
        cols = sosfiltfilt(self.sos, cols, axis=0, padtype="odd", padlen=min(cols.shape[0] - 1, int(round(10.0 / self.spacing_m))))
        return cols

    def _trim(self) -> int:
        """Points cut at each end of a band-passed series (the filters' edge effects)."""
        return int(round(TRIM_M / self.spacing_m))

    def band_like(self, values: np.ndarray, inverse) -> np.ndarray:
        """A profile given on this pass's grid (n_points, n_contacts), band-passed over the spans
        :meth:`aps` uses under ``inverse``, as the APs are (so that the two are comparable)."""
        skip = min(inverse.n_warmup, self.z.shape[0] - 2)
        h = self.spacing_m
        trim = self._trim()
        out = np.full((self.n_points, self.n_contacts), np.nan)
        for i in range(self.n_contacts):
            pos = self.x_cg[skip:] + inverse.system.offsets_m[i]
            k0 = max(int(math.ceil(pos[0] / h)) - self.start_index, 0)
            k1 = min(int(math.floor(pos[-1] / h)) - self.start_index + 1, self.n_points)
            v = values[k0:k1, i]
            ok = np.isfinite(v)
            if k1 - k0 < 2 * trim + 20 or ok.sum() < 20:
                continue
            v = np.interp(np.arange(v.size), np.flatnonzero(ok), v[ok])
            out[k0 + trim : k1 - trim, i] = self._band(v[:, None])[trim : v.size - trim, 0]
        out[self.hole] = np.nan
        return out


def _lm(evaluate, x0: np.ndarray, max_iter: int = 30, tol: float = 1e-4):
    """Levenberg–Marquardt on a Gauss–Newton model: ``evaluate(x, jac)`` → (cost, grad, H or None).

    Returns (x, cost, H at x, iterations)."""
    x = x0.copy()
    cost, grad, H = evaluate(x, True)
    lam = 1e-3
    it = 0
    for it in range(1, max_iter + 1):
        d = np.sqrt(np.maximum(np.diag(H), 1e-12))
        accepted = False
        while lam < 1e8:
            try:
                step = -np.linalg.solve(H + lam * np.diag(d * d), grad)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            step = np.clip(step, -0.5, 0.5)  # no log-quantity moves by more than ×1.6 per iteration
            new_cost = evaluate(x + step, False)[0]
            if np.isfinite(new_cost) and new_cost <= cost:
                x = x + step
                lam = max(lam / 5.0, 1e-7)
                accepted = True
                break
            lam *= 10.0
        if not accepted:
            break
        cost, grad, H = evaluate(x, True)
        if np.max(np.abs(step)) < tol:
            break
    return x, cost, H, it


def fit_fleet(model: str, vehicles: list[tuple[dict, list[PassAp]]],
              prior: tuple[np.ndarray, np.ndarray]) -> list[VehicleFit]:
    """The joint vehicle step for vehicles of one model.

    ``vehicles``: per vehicle, (the parameters its APs were computed with, its passes). The profile
    is profiled out (the weighted mean of all APs). Returns one fit per vehicle, in order.
    """
    names = calibration_names(model)
    ref_name = REFERENCE[model][0]
    P = len(names)
    mu, sd = prior
    V = len(vehicles)
    passes: list[PassChannels] = []
    owner: list[int] = []  # vehicle of each pass
    for v, (params0, aps) in enumerate(vehicles):
        for ap in aps:
            passes.append(PassChannels(model, params0, ap))
            owner.append(v)
    if not passes:
        raise ValueError("fit_fleet: no passes")
    h = passes[0].spacing_m
    dof = min(1.0, 2.0 * h / BAND_M[0])  # band-passed grid points per independent sample
    g0 = min(pc.start_index for pc in passes)
    N = max(pc.start_index + pc.n_points for pc in passes) - g0
    C = passes[0].n_contacts
    # Unknowns: every vehicle's log-quantities, then every pass's initial-state coefficients.
    free_at = np.cumsum([V * P] + [pc.n_free for pc in passes])
    n_x = int(free_at[-1])
    theta0 = np.concatenate([np.log([to_calibration(model, p0)[n] for n in names]) for p0, _ in vehicles])
    x0 = np.concatenate([theta0, np.zeros(n_x - V * P)])
    prior_mu = np.concatenate([np.tile(mu, V), np.zeros(n_x - V * P)])
    prior_sd = np.concatenate([np.tile(sd, V), np.ones(n_x - V * P)])
    state: dict = {}

    cache: dict = {}

    n_dt = len({pc.dt for pc in passes})

    def inverse_of(v, theta_v, dt):
        key = (v, theta_v.tobytes(), dt)
        if key not in cache:
            if len(cache) > 4 * V * (P + 1) * n_dt:
                cache.clear()
            params = from_calibration(model, dict(zip(names, np.exp(theta_v))), vehicles[v][0][ref_name])
            cache[key] = build_inverse(vehicle_from_params(model, params).system(), dt, gamma=REMAP_GAMMA)
        return cache[key]

    def evaluate(x, with_jac):
        # Series rows: (pass, contact); values and, optionally, derivatives along (columns, indices).
        vals = np.full((len(passes), C, N), np.nan)
        jac: list = []
        for v in range(V):
            tv = x[v * P : (v + 1) * P]
            for p in (p for p in range(len(passes)) if owner[p] == v):
                pc = passes[p]
                inv = inverse_of(v, tv, pc.dt)  # (at the pass's own step: its logger's rate)
                pert = [inverse_of(v, tv + FD_STEP * np.eye(P)[j], pc.dt) for j in range(P)] if with_jac else []
                s = x[free_at[p] : free_at[p + 1]]
                z = pc.z + sum(sj * f for sj, f in zip(s, pc.free))
                a = pc.start_index - g0
                base = pc.aps(inv, [z] + (pc.free if with_jac else []))
                vals[p, :, a : a + pc.n_points] = base[0].T
                if with_jac:  # on the pass's own stretch of the grid
                    G = np.zeros((C, pc.n_points, P + pc.n_free))
                    for j in range(P):
                        G[:, :, j] = np.nan_to_num((pc.aps(pert[j], [z])[0] - base[0]).T / FD_STEP)
                    for j in range(pc.n_free):
                        G[:, :, P + j] = np.nan_to_num(base[1 + j].T)
                    idx = np.concatenate([np.arange(v * P, (v + 1) * P), np.arange(free_at[p], free_at[p + 1])])
                    jac.append((idx, a, G))
        vals = vals.reshape(len(passes) * C, N)
        w = 1.0 / state["sigma2"] if "sigma2" in state else np.ones(len(passes) * C)
        finite = np.isfinite(vals)
        mask = finite & (finite.sum(axis=0) >= 2)  # a point only one series sees says nothing
        W = (w[:, None] * mask).sum(axis=0)
        cons = (w[:, None] * np.where(mask, vals, 0.0)).sum(axis=0) / np.maximum(W, 1e-300)
        resid = np.where(mask, vals - cons, 0.0)
        prior_r = (x - prior_mu) / prior_sd
        cost = 0.5 * (dof * float(np.sum(w[:, None] * resid**2)) + float(prior_r @ prior_r))
        state.update(resid=resid, mask=mask)
        if not with_jac:
            return cost, None, None
        H = np.zeros((n_x, n_x))
        grad = np.zeros(n_x)
        S = np.zeros((N, n_x))
        for p, (idx, a, G) in enumerate(jac):
            span = slice(a, a + G.shape[1])
            for i in range(C):
                row = p * C + i
                Gm = G[i] * mask[row, span][:, None]
                H[np.ix_(idx, idx)] += dof * w[row] * (Gm.T @ Gm)
                grad[idx] += dof * w[row] * (Gm.T @ resid[row, span])
                S[span, idx] += w[row] * Gm
        H -= dof * (S.T @ (S / np.maximum(W, 1e-300)[:, None]))  # the profile's response to x (variable projection)
        H += np.diag(1.0 / prior_sd**2)
        grad += prior_r / prior_sd
        return cost, grad, H

    def noise_levels():
        """Each series' misfit variance, corrected for the consensus containing the series itself."""
        resid, mask = state["resid"], state["mask"]
        n = np.maximum(mask.sum(axis=1), 1)
        cover = mask.sum(axis=0)
        shrink = np.array([np.mean(1.0 - 1.0 / np.maximum(cover[m], 2)) if m.any() else 1.0 for m in mask])
        out = np.maximum((resid**2).sum(axis=1) / (n * shrink), 1e-24)
        return np.where(mask.any(axis=1), out, np.median(out))

    def reweight(x):
        """Empirical Bayes: each series' misfit level at x."""
        state.pop("sigma2", None)
        evaluate(x, False)
        state["sigma2"] = noise_levels()
        evaluate(x, False)

    x = x0
    iterations = 0
    for _ in range(3):  # re-estimate the weights near the optimum, then refine
        reweight(x)
        x, cost, H, it = _lm(evaluate, x, max_iter=8, tol=1e-3)
        iterations += it
        if it <= 1:  # already there (a confirming round): the weights will not change either
            break
    reweight(x)
    x, cost, H, it = _lm(evaluate, x)
    iterations += it
    log.debug("fit_fleet %s: %d vehicles, %d passes, %d unknowns, %d LM iterations",
              model, V, len(passes), n_x, iterations)
    try:
        se_all = np.sqrt(np.clip(np.diag(np.linalg.inv(H)), 0.0, None))
    except np.linalg.LinAlgError:
        se_all = prior_sd.copy()
    resid, mask = state["resid"], state["mask"]
    fits = []
    for v in range(V):
        b = slice(v * P, (v + 1) * P)
        t, se = x[b], se_all[b]
        mean = np.exp(t)
        rows = [p * C + i for p in range(len(passes)) if owner[p] == v for i in range(C)]
        m = mask[rows]
        rms = float(np.sqrt(np.sum(resid[rows] ** 2) / max(m.sum(), 1)))
        fits.append(VehicleFit(names, mean, np.exp(t - 1.96 * se), np.exp(t + 1.96 * se),
                               from_calibration(model, dict(zip(names, mean)), vehicles[v][0][ref_name]), rms,
                               int(m.sum())))
    return fits


# ---------------------------------------------------------------------------------------------
# The refinement step for quarter-cars: one vehicle against the others' consensus, in acceleration space


def _autocorrelation_time(r: np.ndarray, max_lag: int = 200) -> float:
    """Integrated autocorrelation time of a series, in samples (1 for white noise): 1 + 2 Σ ρ_k,
    summed while ρ stays positive."""
    if r.size < 4 * max_lag:
        return 1.0
    r = r - r.mean()
    f = np.fft.rfft(r, 2 * r.size)
    acf = np.fft.irfft(f * np.conj(f))[:max_lag] / max(float(r @ r), 1e-300)
    neg = np.flatnonzero(acf < 0)
    k = int(neg[0]) if neg.size else max_lag
    return float(max(1.0, 1.0 + 2.0 * acf[1:k].sum()))

class PassRemap:
    """One pass prepared for the vehicle step, in acceleration space.

    The vehicle's measured channels are reconstructed from its AP (forward model under the
    parameters the AP was computed with); candidate parameters θ are scored by how well the
    forward model under θ, driven by the consensus profile, predicts those channels. Sensor noise
    is white in this space, so least squares here weights every wavelength as the data do
    (the likelihood of thesis eq. 4.1 with the consensus in place of the unknown profile).
    """

    WARMUP_S = 2.0  # both signals start from an assumed rest state: skip the transient

    def __init__(self, model: str, params0: dict, ap: PassAp, consensus: np.ndarray, offsets_m=None,
                 ap_gamma: float | None = None):
        self.model = model
        n_points, n_contacts = ap.values.shape
        x = (ap.start_index + np.arange(n_points)) * ap.spacing_m
        valid = np.all(np.isfinite(ap.values), axis=1) & np.all(np.isfinite(consensus), axis=1)
        # Contact i meets the road at x_cg + offsets_m[i]: the centre of gravity's track xt is where
        # every contact is on the valid data (a half-car's rear axle reaches a bump a wheelbase later).
        off = np.zeros(n_contacts) if offsets_m is None else np.asarray(offsets_m, dtype=float)
        x0, x1 = x[valid][0] - off.min(), x[valid][-1] - off.max()
        # The step: the edge's where the channels are reconstructed as the edge inverted them; for a
        # continuous-time AP a free choice (reconstruction and prediction share it), kept at REMAP_DT.
        self.dt = REMAP_DT if ap_gamma is not None else ap.dt_s
        xt = np.arange(x0, x1, ap.speed_mps * self.dt)
        vals = np.where(np.isfinite(ap.values), ap.values, 0.0)
        cons = np.where(np.isfinite(consensus), consensus, 0.0)
        self.settings = REMAP_SETTINGS.get(model, RemapSettings())
        # ``ap_gamma``: the Newmark γ whose inverse the AP is exact for — the edge's (default), or ½ for
        # a continuous-time AP (:func:`cloud.road.continuous.continuous_segments`; γ = ½ has no numerical
        # damping, and its small frequency warping is common to the reconstruction and the prediction,
        # so it cancels).
        self.ap_gamma = edge_gamma(model) if ap_gamma is None else ap_gamma
        self.predict_gamma = self.settings.predict_gamma if self.settings.predict_gamma is not None else (
            None if ap_gamma is None else ap_gamma)
        if self.settings.lowpass_cpm:
            vals, cons = (_lowpass_grid(a, ap.spacing_m, self.settings.lowpass_cpm) for a in (ap.values, consensus))
        ap_t = np.stack([np.interp(xt + off[i], x, vals[:, i]) for i in range(n_contacts)], axis=1)
        self.profile_t = np.stack([np.interp(xt + off[i], x, cons[:, i]) for i in range(n_contacts)], axis=1)
        self._grid = (x, xt, off, ap.spacing_m)  # where a change of the consensus is read (consensus_response)
        self.z = channels_from_ap(vehicle_from_params(model, params0).system(), ap_t,
                                  newmark_constants(self.dt, self.ap_gamma))
        self.skip = int(self.WARMUP_S / self.dt)
        self.n = max(self.z.shape[0] - self.skip, 0)
        self.scale = np.std(self.z[self.skip:], axis=0) + 1e-12  # channels in comparable units
        self.start_basis = (_free_response_basis(model, params0, self.z.shape[0], self.skip, self.scale,
                                                 self.ap_gamma, self.dt)
                            if self.settings.free_start else None)

    def residual(self, params: dict) -> np.ndarray:
        # (the edge's γ where none is set: the round trip is exact)
        gamma = edge_gamma(self.model) if self.predict_gamma is None else self.predict_gamma
        pred = channels_from_ap(vehicle_from_params(self.model, params).system(), self.profile_t,
                                newmark_constants(self.dt, gamma))
        r = ((pred - self.z)[self.skip:] / self.scale).ravel()
        if self.start_basis is not None:  # the unknown start state, profiled out
            r = r - self.start_basis @ (self.start_basis.T @ r)
        return r

    def consensus_response(self, params: dict, delta: np.ndarray) -> np.ndarray:
        """The change of :meth:`residual` when the consensus changes by ``delta`` (m, on the pass's grid
        slice, (n_points, n_contacts)): the prediction is linear in the profile it is driven by."""
        x, xt, off, _ = self._grid
        d = self.consensus_input(delta)
        d_t = np.stack([np.interp(xt + off[i], x, d[:, i]) for i in range(d.shape[1])], axis=1)
        gamma = edge_gamma(self.model) if self.predict_gamma is None else self.predict_gamma
        pred = channels_from_ap(vehicle_from_params(self.model, params).system(), d_t, newmark_constants(self.dt, gamma))
        r = (pred[self.skip:] / self.scale).ravel()
        if self.start_basis is not None:
            r = r - self.start_basis @ (self.start_basis.T @ r)
        return r

    def consensus_weights(self, params: dict, weights: np.ndarray) -> np.ndarray:
        """The transpose of :meth:`consensus_response`: for rows ``weights`` (b, residual length), the
        weights ``G`` (b, n_points, n_contacts) on the consensus change with ``weights @
        consensus_response(params, delta) = Σ G · d`` (up to rounding), ``d`` the change as
        :meth:`consensus_response` drives the vehicle with it (holes as zero, low-passed where the
        settings say). The prediction is linear in the profile, so a fixed set of rows (a Jacobian's)
        is one map, and any number of changes cost a product each instead of a forward run."""
        x, xt, off, _ = self._grid
        w = np.atleast_2d(np.asarray(weights, float))
        if self.start_basis is not None:  # the projection is symmetric: it moves to the weights' side
            w = w - (w @ self.start_basis) @ self.start_basis.T
        n_ch = self.z.shape[1]
        on_channels = np.zeros((w.shape[0], self.z.shape[0], n_ch))
        on_channels[:, self.skip:] = w.reshape(w.shape[0], self.n, n_ch) / self.scale
        gamma = edge_gamma(self.model) if self.predict_gamma is None else self.predict_gamma
        on_time = channels_transpose(vehicle_from_params(self.model, params).system(), on_channels,
                                     newmark_constants(self.dt, gamma))  # (b, samples, n_contacts)
        out = np.zeros((w.shape[0], x.size, on_time.shape[2]))
        for i in range(on_time.shape[2]):
            # np.interp's weights on the grid: two neighbours inside, the end value beyond either end
            xq = xt + off[i]
            j = np.clip(np.searchsorted(x, xq, side="right") - 1, 0, x.size - 2)
            t = np.clip((xq - x[j]) / (x[j + 1] - x[j]), 0.0, 1.0)
            for r in range(w.shape[0]):
                out[r, :, i] = (np.bincount(j, on_time[r, :, i] * (1.0 - t), minlength=x.size)
                                + np.bincount(j + 1, on_time[r, :, i] * t, minlength=x.size))
        return out

    def consensus_input(self, delta: np.ndarray) -> np.ndarray:
        """A consensus change (n_points, n_contacts) as :meth:`consensus_response` drives the vehicle
        with it on the grid: holes as zero, low-passed where the settings say."""
        d = np.where(np.isfinite(delta), delta, 0.0)
        if self.settings.lowpass_cpm:
            d = _lowpass_grid(d, self._grid[3], self.settings.lowpass_cpm)
        return d


def fit_vehicle(model: str, params0: dict, passes: list[tuple[PassAp, np.ndarray]],
                prior: tuple[np.ndarray, np.ndarray], ref_value: float, ap_gamma: float | None = None) -> VehicleFit:
    """The per-vehicle refinement step, in acceleration space (sensor noise white there).
    ``passes``: (AP under ``params0``, leave-one-out consensus on the same grid slice, shape
    (n_points, n_contacts)). A local method: start it near the answer (:func:`fit_fleet`).
    ``ap_gamma``: see :class:`PassRemap` (½ for continuous-time APs). Returns ratios with 95 % intervals."""
    names = calibration_names(model)
    offsets = vehicle_from_params(model, params0).system().offsets_m
    remaps = [PassRemap(model, params0, ap, cons, offsets, ap_gamma) for ap, cons in passes]
    mu, sd = prior
    theta0 = np.log(np.array([to_calibration(model, params0)[n] for n in names]))
    n_res = sum(r.n * r.z.shape[1] for r in remaps)
    state = {"sigma": None}

    def data_res(theta):
        params = from_calibration(model, dict(zip(names, np.exp(theta))), ref_value)
        return np.concatenate([r.residual(params) for r in remaps])

    r0 = data_res(theta0)
    state["sigma"] = max(float(np.sqrt(np.mean(r0**2))), 1e-9)
    # Each sample counts as independent only if the misfit is white (sensor noise). A misfit the
    # consensus cannot explain — lane scatter on a 3-D carpet, the others' calibration error — is
    # smooth in time: it counts by its integrated autocorrelation time, so that it does not pull
    # the ratios away from the class prior with the weight of white noise. It is measured at the
    # vehicle's current calibration, where the round starts, and held through the round: re-measured
    # at each optimum it lets the rounds wander on.
    taus = [_autocorrelation_time(col) for r in remaps for col in r.residual(
        from_calibration(model, dict(zip(names, np.exp(theta0))), ref_value)).reshape(r.n, -1).T]
    state["n_eff"] = float(max(n_res, 1)) / float(np.mean(taus))

    def fun(theta):
        w = math.sqrt(state["n_eff"] / n_res) / state["sigma"]
        return np.concatenate([w * data_res(theta), (theta - mu) / sd])

    for _ in range(2):  # re-estimate the misfit scale once at the optimum (empirical Bayes)
        sol = least_squares(fun, theta0, x_scale=np.maximum(sd, 0.01), diff_step=1e-4, max_nfev=200)
        theta0 = sol.x
        rr = data_res(theta0)
        state["sigma"] = max(float(np.sqrt(np.mean(rr**2))), 1e-9)
    sol = least_squares(fun, theta0, x_scale=np.maximum(sd, 0.01), diff_step=1e-4, max_nfev=50)
    J = sol.jac
    try:
        cov = np.linalg.inv(J.T @ J)
        se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        se = sd.copy()
    mean = np.exp(sol.x)
    params = from_calibration(model, dict(zip(names, mean)), ref_value)
    return VehicleFit(names, mean, np.exp(sol.x - 1.96 * se), np.exp(sol.x + 1.96 * se), params,
                      float(np.sqrt(np.mean(data_res(sol.x) ** 2))), n_res)


class ConsensusSensitivity:
    """How a vehicle's fitted log-ratios move when the consensus it was fitted against moves (errors in
    variables: the reference profile is an estimate, not the road), and how its own APs move when its
    ratios do (the other side of the fleet's coupling through the consensus).

    ``passes`` as :func:`fit_vehicle`'s, at the vehicle's fitted ``params``. Linearised at ``params``
    with :func:`fit_vehicle`'s weights (misfit scale, effective sample count, class prior), a change
    of the consensus moves the optimum by one Gauss–Newton step, ``δθ = −(JᵀJ)⁻¹ Jᵀ δr``; the matrices
    are built once, and a change costs a product with each pass's map (:meth:`PassRemap.consensus_weights`).
    """

    def __init__(self, model: str, params: dict, passes: list[tuple[PassAp, np.ndarray]],
                 prior: tuple[np.ndarray, np.ndarray], ref_value: float, ap_gamma: float | None = None):
        self.model, self.params = model, params
        self.names = calibration_names(model)
        offsets = vehicle_from_params(model, params).system().offsets_m
        self.remaps = [PassRemap(model, params, ap, cons, offsets, ap_gamma) for ap, cons in passes]
        self.n_points = [ap.values.shape[0] for ap, _ in passes]
        _, sd = prior
        self.theta = np.log(np.array([to_calibration(model, params)[n] for n in self.names]))
        self.ref_value = ref_value
        r0 = self._data_res(self.theta)
        n_res = r0.size
        sigma = max(float(np.sqrt(np.mean(r0**2))), 1e-9)
        taus = [_autocorrelation_time(col) for r in self.remaps for col in r.residual(params).reshape(r.n, -1).T]
        self.w = math.sqrt(float(max(n_res, 1)) / float(np.mean(taus)) / max(n_res, 1)) / sigma
        J = np.empty((n_res, self.theta.size))
        for j in range(self.theta.size):
            step = np.zeros_like(self.theta)
            step[j] = FD_STEP
            J[:, j] = (self._data_res(self.theta + step) - self._data_res(self.theta - step)) / (2 * FD_STEP) * self.w
        self.J = J
        self.A = J.T @ J + np.diag(1.0 / sd**2)
        # Per pass, the map from its consensus change (as its remap drives the vehicle with it) to
        # Jᵀ δr: the step's response is linear in the change and J is fixed, so one transposed
        # forward model per pass replaces a forward run per change (:meth:`moves`).
        self.weights = []
        row = 0
        for r in self.remaps:
            size = r.n * r.z.shape[1]
            self.weights.append(r.consensus_weights(params, self.w * J[row : row + size].T))
            row += size

    def _data_res(self, th: np.ndarray) -> np.ndarray:
        params = from_calibration(self.model, dict(zip(self.names, np.exp(th))), self.ref_value)
        return np.concatenate([r.residual(params) for r in self.remaps])

    def moves(self, deltas: list[np.ndarray]) -> np.ndarray:
        """``deltas[p]`` (K, n_points, n_contacts): K changes of pass p's consensus (the same K for every
        pass). Returns (K, quantities): the fit's moves, log units, in :func:`calibration_names` order."""
        k = deltas[0].shape[0] if deltas else 0
        jr = np.zeros((self.theta.size, k))  # Jᵀ δr per change, through each pass's map
        for r, g, d in zip(self.remaps, self.weights, deltas):
            inputs = np.stack([r.consensus_input(d[i]) for i in range(k)]) if k else np.zeros((0,) + g.shape[1:])
            jr += np.einsum("qnc,knc->qk", g, inputs)
        return -np.linalg.solve(self.A, jr).T if k else np.zeros((0, self.theta.size))

    def ap_response(self) -> list[np.ndarray]:
        """Per pass, (quantities, n_points, n_contacts): the change of the pass's AP on its grid slice per
        unit change of each log-quantity of this vehicle (the measured channels held, the inverse under
        the changed ratios; at the AP's own Newmark γ and step). Zero where the inverse is warming up or
        the pass has no data; each column less its straight line (the edge's drift control takes the
        AP's free drift, which a change of the ratios moves, out alike)."""
        out = []
        for r, n in zip(self.remaps, self.n_points):
            x, xt, off, _ = r._grid
            base = InverseStream(build_inverse(vehicle_from_params(self.model, self.params).system(), r.dt,
                                               gamma=r.ap_gamma)).update(r.z)
            resp = np.zeros((self.theta.size, n, base.shape[1]))
            for j in range(self.theta.size):
                th = self.theta.copy()
                th[j] += FD_STEP * 10
                p = from_calibration(self.model, dict(zip(self.names, np.exp(th))), self.ref_value)
                y = (InverseStream(build_inverse(vehicle_from_params(self.model, p).system(), r.dt,
                                                 gamma=r.ap_gamma)).update(r.z) - base) / (FD_STEP * 10)
                y[: r.skip] = 0.0
                for i in range(base.shape[1]):
                    col = np.interp(x, xt + off[i], y[:, i], left=0.0, right=0.0)
                    u = np.arange(n) - 0.5 * (n - 1)
                    resp[j, :, i] = col - col.mean() - u * (u @ col) / max(float(u @ u), 1e-300)
            out.append(resp)
        return out


def consensus_sensitivity(model: str, params: dict, passes: list[tuple[PassAp, np.ndarray]],
                          deltas: list[np.ndarray], prior: tuple[np.ndarray, np.ndarray], ref_value: float,
                          ap_gamma: float | None = None) -> np.ndarray:
    """How a vehicle's fitted log-ratios move when the consensus it was fitted against moves
    (:class:`ConsensusSensitivity`, for one set of changes).

    ``deltas[p]`` (K, n_points, n_contacts): K changes of pass p's consensus (draws of its error, the
    same K for every pass). Returns (K, quantities) in log units, in :func:`calibration_names` order.
    """
    return ConsensusSensitivity(model, params, passes, prior, ref_value, ap_gamma).moves(deltas)
