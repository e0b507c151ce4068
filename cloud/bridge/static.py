"""Bridge stiffness and vehicle weights from passes' APs: the likelihood and its posterior.

Model of one pass p (vehicle v, speed v_p) over the window, in AP units (m, up positive)::

    ρ_p(x) = AP_p(x) − consensus(x) = μ(x) + s_p(x) − W_v · (1 + φ_p(x)) · J(x; θ) − W_v·ε_p(x) + e_p(x)

* ``J(x; θ)`` (m/N) — the deflection under a unit wheel load at x (the moving-reference
  influence line), zero off the span; for a simply supported span ``J = Σ_z G_z(x)/EI_z``
  (unit-load theorem, :func:`shared.fe.beam.compliance_kernel`), linear in the compliances.
  Every J is carried in a cubic B-spline basis with knots at the element nodes
  (:class:`SpanBasis`, relative error < 2e-4), ``J = Σ_j a_j ψ_j``.
* ``1 + φ_p`` — the dynamic wheel load over the static one, from the vehicle's calibrated ratios
  (:class:`~cloud.bridge.passdata.VehicleFilter`) driven over the fleet's consensus road and its own
  deflection — not the pass's own AP, whose noise it would carry
  (:func:`~cloud.bridge.passdata.road_load_factor`); on a bridge entrance it
  swings by ±10 %, so it is part of the model, not of the noise.
* ``ε_p`` — the bridge's own dynamics (:mod:`cloud.bridge.dynamic`), zero in the quasi-static model.
* ``s_p(x)`` — on a smooth deck (where the consensus is taken as 0 on the span) the consensus'
  drift-control trend shows as a step of up to millimetres at the supports; it differs between
  passes by a few per cent, so each pass has its own cubic on the span (``{1, ξ, ξ², ξ³}``,
  values and slopes at both supports), projected out of its likelihood. A quadratic would leave an
  antisymmetric error that reads as a stiffness gradient along the span (of about ±6 %).
* ``μ(x)`` — on a rough deck the consensus holds the fleet-mean deflection: a common unknown
  shape on the span (basis ``{ψ_j}``), estimated with the rest.
* the fleet-common calibration error δ_c (:mod:`cloud.bridge.vehicle_error`): one coefficient per
  calibration quantity shared by every pass, its columns the pass's AP distortion less the
  consensus'; carried as further coordinates of μ with their own prior (``mu_precision``).
* ``W_v`` — the vehicle's static wheel load (N), prior ``N(W̄, s_W²)`` from its class: W̄ fixes the
  scale between loads and compliances (thesis §4.5.5).

AP errors are far from white (twice-integrated sensor noise), so each pass is compared in the
measured-channel domain: everything above goes through the vehicle's forward model F_p
(:meth:`~cloud.bridge.passdata.VehicleFilter.whiten`), where sensor noise is white; F_p
annihilates offsets, slopes and (to O(ω²)) the drift-control trend. The result is band-limited
to ``BAND_HZ`` and decimated (the model is trusted, and the deflection's information lives,
below ~10 Hz), then prewhitened by an AR model of the pass's own residual on the approach, whose
level — read in the band of the pass's element directions, as they would see it on new data —
gives the pass's noise sd. At 2 % sensor noise one pass pins the global compliance to ≈ 27 % (1σ),
so the information grows as 27 %/√passes.

Inference: the weights enter linearly given J, so they are integrated out analytically, vehicle by
vehicle (a pass shares W_v with the vehicle's other passes). What remains is a smooth
log-posterior in the stiffness parameters and μ, maximised by Newton's method; the Laplace
approximation gives 95 % intervals and the evidence. Integrating W (rather than maximising over
it) matters: the joint mode over (θ, W) is biased by ≈ s_W²/W̄² ≈ 1 % in the global scale.

All data reduce to small per-vehicle sufficient statistics (:class:`VehicleStats`), so a fit costs
O(vehicles × basis²), independent of the record lengths.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import numpy as np
from scipy.interpolate import BSpline
from scipy.linalg import solve_toeplitz
from scipy.signal import butter, lfilter, sosfiltfilt

from shared.fe.beam import Beam, compliance_kernel, influence_line
from shared.fe.design import design_beam
from shared.registry import Bridge

from cloud.bridge.passdata import PassData, Reference, Window, consensus_end, consensus_used, residual
from cloud.bridge.vehicle_error import FD_STEP, CalibrationMarginal, ap_distortion, perturbed_params

#: The likelihood window starts this far before the first support (m); the noise is estimated on
#: the approach before it, after a burn-in of the forward model.
LEAD_M = 5.0
TAIL_M = 25.0  # and ends this far after the second support (or at the end of the pass)
#: The burn-in (m). The approach's noise is not settled at the start of a record: below 3 Hz the
#: measured channel holds many times the span's noise power over the first tens of metres (tied to
#: the position along the record, not to the forward model's start), so the AR fitted after this
#: burn-in over-models the low band and the likelihood is conservative below ~3 Hz. The noise level
#: is read where the element directions are (:func:`element_band_sigma`), not from this band. A longer
#: burn-in fits the low band better, but on fleet-calibrated passes the band it then weighs more
#: carries an unmodelled, calibration-related error and the element estimates get worse
#: (docs/results.md).
BURN_IN_M = 8.0
DECKS = ("smooth", "rough")
AR_ORDER = 8  # order of the per-pass autoregressive prewhitener of the measured-channel residual
AR_ORDER_DECIMATED = 3  # the same after band limiting and decimation
BAND_HZ = {"smooth": 20.0, "rough": 8.0}  # band limit of the likelihood per deck model, Hz: on a
# rough deck the 8–20 Hz band carries mostly the consensus' roughness mismatch, which reads as a
# softer bridge


def ar_prewhitener(x: np.ndarray, order: int = AR_ORDER) -> np.ndarray:
    """FIR coefficients ``[1, −φ_1, …, −φ_p]`` of the Yule–Walker AR(p) model of ``x``."""
    x = np.asarray(x, dtype=float) - np.mean(x)
    n = x.size
    r = np.array([x[: n - k] @ x[k:] for k in range(order + 1)]) / n
    if r[0] <= 0:
        return np.r_[1.0, np.zeros(order)]
    phi = solve_toeplitz(r[:order], r[1 : order + 1])
    return np.r_[1.0, -phi]


def out_of_sample_factor(n: int, order: int) -> float:
    """How much larger (in sd) an AR(``order``) model's prediction errors are on new data than on the
    ``n`` points it was fitted to: Akaike's final prediction error, ``(n + p + 1)/(n − p − 1)`` in
    variance (the mean counts as a parameter). The span is new data; the approach is ~100–140 points."""
    if n <= order + 1:
        raise ValueError(f"out_of_sample_factor: {n} points cannot fit an AR({order})")
    return math.sqrt((n + order + 1) / (n - order - 1))


def element_band_sigma(noise: np.ndarray, directions: np.ndarray) -> float:
    """The noise sd as ``directions`` see it: the periodogram of ``noise`` (n,) averaged over
    frequency with the power spectrum of ``directions`` (rows, k) as weights, both already
    prewhitened (the approach residual, and a pass's element directions on its likelihood rows).

    The AR(p) whitener is only approximately right across the band (it cannot follow the band
    limit's edge, nor a low-frequency excess of the approach); its level, read from the whole band,
    is then wrong where the stiffness information is. Read in that band instead, the likelihood is
    right there and conservative where the whitened noise comes out below 1."""
    x = np.asarray(noise, dtype=float) - np.mean(noise)
    d = np.asarray(directions, dtype=float)
    n_fft = 1 << int(math.ceil(math.log2(max(x.size, d.shape[0], 2))))
    weight = np.sum(np.abs(np.fft.rfft(d, n_fft, axis=0)) ** 2, axis=1)
    if not np.any(weight > 0):
        raise ValueError("element_band_sigma: the directions are zero")
    periodogram = np.abs(np.fft.rfft(x, n_fft)) ** 2 / x.size
    return float(np.sqrt(np.sum(periodogram * weight) / np.sum(weight)))


def _fir(coef: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Apply an FIR filter down the rows of ``cols`` (causal, zero initial state)."""
    return lfilter(coef, [1.0], cols, axis=0)


# ---------------------------------------------------------------------------------------------
# Basis on the span


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
    """Columns (n_window, n_mu) of the nuisance μ common to all passes (see module docstring):
    none on a smooth deck, the span's B-splines on a rough one (the fleet-mean deflection)."""
    if deck not in DECKS:
        raise ValueError(f"deck: must be one of {DECKS}, got {deck!r}")
    if deck == "smooth":
        return np.zeros((window.n, 0))
    out = np.zeros((window.n, basis.n))
    out[window.on_span] = basis.design
    return out


def step_basis(window: Window, deck: str) -> np.ndarray:
    """Columns (n_window, 3) of each pass's own nuisance on a smooth deck: ``{1, ξ, ξ²}`` on the
    span (the drift-control trend of the consensus, a step at the supports, which differs from
    pass to pass by ~2 % — tens of µm, as much as the deflection signal of a precise pass); none on
    a rough deck. Each pass's coefficients are projected out of its likelihood."""
    if deck == "rough":
        return np.zeros((window.n, 0))
    on = window.on_span
    xi = (window.x - 0.5 * window.span_m) / (0.5 * window.span_m)
    return np.column_stack([on * 1.0, on * xi, on * xi**2, on * xi**3])


# ---------------------------------------------------------------------------------------------
# One pass, whitened


@dataclasses.dataclass(frozen=True, eq=False)
class Whitener:
    """The linear map from a column on the window grid to a pass's likelihood points.

    1. the vehicle's forward model (:meth:`~cloud.bridge.passdata.VehicleFilter.whiten`);
    2. optionally a zero-phase low-pass at ``band_hz`` and decimation by ``step`` — the model is
       trusted, and the deflection's information lives, below ~10 Hz;
    3. the pass's autoregressive prewhitener ``ar`` (FIR), fitted on the approach;
    4. the likelihood points ``rows`` (indices into the decimated series), divided by ``sigma``.
    """

    data: PassData
    sos: np.ndarray | None
    step: int
    ar: np.ndarray
    rows: np.ndarray
    sigma: float
    steps: np.ndarray | None = None  # (n_rows, k) whitened per-pass nuisance columns, projected out
    #: the vehicle's calibration error integrated out (:mod:`cloud.bridge.vehicle_error`), or None
    marginal: CalibrationMarginal | None = None

    def project(self, v: np.ndarray) -> np.ndarray:
        """Remove the per-pass nuisance columns' span from whitened values (rows × k)."""
        if self.steps is None or self.steps.shape[1] == 0:
            return v
        coef, *_ = np.linalg.lstsq(self.steps, v, rcond=None)
        return v - self.steps @ coef

    def raw(self, cols: np.ndarray) -> np.ndarray:
        """Whitened likelihood values before the per-pass projection."""
        cols = np.asarray(cols, dtype=float)
        one = cols.ndim == 1
        out = _fir(self.ar, self.stage1(cols[:, None] if one else cols))[self.rows] / self.sigma
        if self.marginal is not None:
            out = self.marginal(out)
        return out[:, 0] if one else out

    def stage1(self, cols: np.ndarray) -> np.ndarray:
        """Steps 1–2: forward model, band limit, decimation; (n_window, k) → (n_dec, k)."""
        cols = np.asarray(cols, dtype=float)
        nz = np.flatnonzero(np.any(cols != 0.0, axis=tuple(range(1, cols.ndim))))
        first = max(int(nz[0]) - 1, 0) if nz.size else 0
        # The forward model starts from rest: on leading zero rows (a column on the span only) its
        # output is exactly zero, so it is run from the last of them.
        white = np.zeros(cols.shape)
        white[first:] = self.data.vehicle_filter().whiten(cols[first:])
        if self.sos is not None:
            white = sosfiltfilt(self.sos, white, axis=0)
        return white[:: self.step]

    def from_stage1(self, white: np.ndarray) -> np.ndarray:
        """Steps 3–4 and the projection, for columns already through :meth:`stage1` (n_dec, k): what
        does not depend on the consensus can be cached in that form (it does not move with the fleet)."""
        out = _fir(self.ar, np.asarray(white, dtype=float))[self.rows] / self.sigma
        if self.marginal is not None:
            out = self.marginal(out)
        return self.project(out)

    def __call__(self, cols: np.ndarray) -> np.ndarray:
        """Whitened (projected) likelihood values of window column(s) (n_window,) or (n_window, k)."""
        cols = np.asarray(cols, dtype=float)
        one = cols.ndim == 1
        out = self.project(self.raw(cols[:, None] if one else cols))
        return out[:, 0] if one else out


@dataclasses.dataclass(frozen=True, eq=False)
class WhitenedPass:
    """One pass in the measured-channel domain, divided by its noise sd (so unit-variance noise).

    ``w`` (n,) data; ``Psi`` (n, n_b) basis columns of the load term; ``B`` (n, n_mu) nuisance
    columns; ``whitener`` the map that made them (:meth:`whiten_extra` applies it to more columns).
    """

    vehicle_id: str
    pass_id: str
    w: np.ndarray
    Psi: np.ndarray
    B: np.ndarray
    whitener: Whitener
    raw: np.ndarray | None = None  # unprojected [w, Ψ, B] columns, to recover the step coefficients
    #: prior precision of the common coefficients of ``B`` (the deck's μ, 1/m², then the fleet-common
    #: calibration error's, per log unit²); None: all μ at ``MU_PRIOR_SD_M``
    mu_precision: np.ndarray | None = None

    def step_coefficients(self, a: np.ndarray, weight: float, mu: np.ndarray, delta: np.ndarray | None = None
                          ) -> np.ndarray:
        """This pass's nuisance step coefficients (m) given the load term ``a``, its wheel load (N),
        the common μ and its dynamic column (projected or not: only its raw form is used)."""
        st = self.whitener.steps
        if st is None or st.shape[1] == 0 or self.raw is None:
            return np.zeros(0)
        nb = self.Psi.shape[1]
        w, P, B = self.raw[:, 0], self.raw[:, 1 : 1 + nb], self.raw[:, 1 + nb :]
        target = w - B @ mu + weight * (P @ a + (0.0 if delta is None else delta))
        coef, *_ = np.linalg.lstsq(st, target, rcond=None)
        return coef

    @property
    def data(self) -> PassData:
        return self.whitener.data

    @property
    def sigma(self) -> float:
        return self.whitener.sigma

    def whiten_extra(self, column_on_window: np.ndarray) -> np.ndarray:
        """Whiten another model column given on the window grid (e.g. a dynamic correction)."""
        return self.whitener(column_on_window)


def model_columns(p: PassData, basis: SpanBasis, deck: str = "smooth", band_hz: float | None = None
                  ) -> tuple[Whitener, np.ndarray]:
    """The pass's band-limited forward-model output of its model columns (load basis, μ basis, step
    basis), (n_dec, n_b + n_mu + n_step), the :class:`Whitener` skeleton (AR and rows not yet known), and —
    when the pass carries calibration uncertainty (:attr:`~cloud.bridge.passdata.PassData.params_log_sd`) —
    the sensitivities of the load columns to each calibration quantity, ``(names, sd, D)`` with D
    (n_dec, K, n_b) = ∂/∂log q_k of the band-limited forward model of the load basis (None otherwise).
    They do not depend on the consensus, so a live estimator computes them once per pass."""
    band_hz = BAND_HZ[deck] if band_hz is None else band_hz
    w = p.window
    on = w.on_span
    load = np.zeros((w.n, basis.n))
    load[on] = p.load_factor[on, None] * basis.design
    cols = np.column_stack([load, mu_basis(w, basis, deck), step_basis(w, deck)])
    fs = p.speed_mps / w.spacing_m  # grid points per second
    sos, step = None, 1
    if band_hz and band_hz < 0.4 * fs:
        sos = butter(6, band_hz / (0.5 * fs), output="sos")
        step = max(1, int(fs / (2.5 * band_hz)))
    skeleton = Whitener(p, sos, step, np.ones(1), np.zeros(0, dtype=int), 1.0)
    white = skeleton.stage1(cols)
    sens = None
    if p.params_log_sd:
        names = sorted(p.params_log_sd)
        D = np.empty((white.shape[0], len(names), basis.n))
        for k, name in enumerate(names):
            moved = dataclasses.replace(skeleton, data=dataclasses.replace(
                p, params=perturbed_params(p.params, name, FD_STEP)))
            D[:, k, :] = (moved.stage1(load) - white[:, : basis.n]) / FD_STEP
        sens = (tuple(names), np.array([p.params_log_sd[n] for n in names]), D)
    return skeleton, white, sens


#: On a smooth deck the consensus' level at each support is the mean over this distance outside it (m).
SUPPORT_LEVEL_M = 0.5


def driven_road(p: PassData, ref: Reference, deck: str = "smooth", leave_out: bool = True) -> np.ndarray:
    """The road the vehicle drove over as far as its calibration error can tell (m, window grid,
    NaN-free): the consensus AP, and on a smooth deck's span the consensus' level bridged linearly
    from one support to the other.

    The consensus off the span carries the edge's drift-control trend (millimetres, :mod:`edge.drift`),
    which the vehicle never drove over; smooth and hundreds of metres long, it is harmless to the
    calibration error's columns (the forward model annihilates offsets and slopes). Taken as 0 on
    the span (:func:`~cloud.bridge.passdata.consensus_used`) it becomes a step at each support
    instead, whose response to the calibration error rings on into the span, where the columns then
    hold a ringing the data do not, and the first elements read several points stiff. Bridged, the
    road the vehicle is modelled to have driven over has no step at the supports and no ringing.
    """
    road = consensus_used(p, ref, smooth_deck=(deck == "smooth"), leave_out=leave_out)
    ok = np.isfinite(road)
    n = p.window.n
    road = np.interp(np.arange(n), np.flatnonzero(ok), road[ok]) if ok.any() else np.zeros(n)
    if deck == "smooth":
        w = p.window
        x, L = w.x, w.span_m
        on = w.on_span
        before = ok & (x < 0) & (x >= -SUPPORT_LEVEL_M)
        after = ok & (x > L) & (x <= L + SUPPORT_LEVEL_M)
        if before.any() and after.any():
            y0, y1 = float(np.mean(road[before])), float(np.mean(road[after]))
            road = road.copy()
            road[on] = y0 + (y1 - y0) * np.clip(x[on], 0.0, L) / L
    return road


def road_sensitivity(p: PassData, ref: Reference, skeleton: Whitener, names: Sequence[str], deck: str = "smooth",
                     leave_out: bool = True) -> np.ndarray:
    """∂/∂log q_k of the band-limited forward model of the consensus road the pass is compared with
    (:func:`driven_road`), (n_dec, K): the dominant part of a calibration
    error's effect — the vehicle's response to the road before the bridge rings on into the span."""
    road = driven_road(p, ref, deck, leave_out)
    base = skeleton.stage1(road[:, None])[:, 0]
    C = np.empty((base.size, len(names)))
    for k, name in enumerate(names):
        moved = dataclasses.replace(skeleton, data=dataclasses.replace(
            p, params=perturbed_params(p.params, name, FD_STEP)))
        C[:, k] = (moved.stage1(road[:, None])[:, 0] - base) / FD_STEP
    return C


def whiten_pass(p: PassData, ref: Reference, basis: SpanBasis, deck: str = "smooth",
                leave_out: bool = True, band_hz: float | None = None,
                columns: tuple | None = None, load: np.ndarray | None = None,
                weight_n: float | None = None, road: np.ndarray | None = None,
                common: Sequence[tuple[str, float]] | None = None,
                common_columns: np.ndarray | None = None) -> WhitenedPass:
    """The :class:`WhitenedPass` of ``p`` against the consensus ``ref``.

    The measured-channel residual is white only to first order (the AP was gridded in chainage,
    the edge's inverse damps high frequencies, the band limit shapes it): an AR(p) model of it on
    the approach (after a burn-in, :data:`BURN_IN_M`) prewhitens data and model alike. Its level
    is read where the pass's element directions are (:func:`element_band_sigma`) and scaled to new
    data (:func:`out_of_sample_factor`), so the whitened noise's variance along the element
    directions is 1 (plus ~0.04 from the per-pass estimate's own scatter, E[1/σ̂²] > 1/σ²); a level
    read from the whole band would be too low there.
    ``columns``: the pass's :func:`model_columns`, if cached. If the pass carries calibration
    uncertainty, its error is integrated out (:mod:`cloud.bridge.vehicle_error`), linearised at the
    load-term coefficients ``load`` and the static wheel load ``weight_n`` (N); without them the
    parameters are taken as exact. ``road``: the pass's :func:`road_sensitivity`, if cached (it
    moves little as the consensus grows). ``common``: (name, prior log-sd) of the calibration
    quantities whose error is shared by every pass of the vehicle class, and ``common_columns``
    (n_dec, K) the band-limited forward model (:meth:`Whitener.stage1`) of how this pass's residual
    AP moves with them (:func:`common_calibration_columns`): whitened (through this pass's own
    calibration marginal), they join the common nuisance columns ``B`` after the deck's own, with
    that prior.
    """
    w = p.window
    x = w.x
    skeleton, model_white, sens = columns or model_columns(p, basis, deck, band_hz)
    rho = residual(p, ref, smooth_deck=(deck == "smooth"), leave_out=leave_out)
    # Not where the consensus has lost the passes that ended first: rows stop there, and the
    # residual is held (as after the pass's own end) so the band limit does not carry the jump back.
    last = consensus_end(p, ref, leave_out)
    rho[last + 1 :] = rho[last]
    white = np.column_stack([skeleton.stage1(rho[:, None]), model_white])
    step = skeleton.step
    xd = x[::step]
    idx = np.arange(w.n)[::step]
    first = np.flatnonzero(p.valid)[0]
    noise = np.flatnonzero((xd < -LEAD_M) & (idx >= first + int(BURN_IN_M / w.spacing_m)) & p.valid[::step])
    order = AR_ORDER if step == 1 else AR_ORDER_DECIMATED
    if noise.size < 6 * order:
        raise ValueError(f"pass {p.pass_id}: too little approach before the bridge to estimate its noise")
    ar = ar_prewhitener(white[noise, 0], order)
    pre = _fir(ar, white)
    rows = np.flatnonzero((xd >= -LEAD_M) & (idx <= last) & (xd <= w.span_m + TAIL_M))
    n_step = step_basis(w, deck).shape[1]
    # The noise level where the element directions are: the load columns less what the pass's own
    # nuisances (its steps) and its wheel load (the load term's overall size) can take.
    nb = basis.n
    directions = pre[rows, 1 : 1 + nb]
    taken = [pre[rows, white.shape[1] - n_step :]] if n_step else []
    if load is not None:
        taken.append(directions @ np.asarray(load, dtype=float)[:, None])
    if taken:
        T = np.column_stack(taken)
        directions = directions - T @ np.linalg.lstsq(T, directions, rcond=None)[0]
    resid = pre[noise[order:], 0]
    sigma = element_band_sigma(resid, directions) * out_of_sample_factor(resid.size, order)
    wr = pre[rows] / sigma
    marginal = None
    if sens is not None and load is not None and weight_n is not None:
        # The calibration error acts on everything the vehicle drove over: the road before the
        # bridge (whose response rings on into the span — the dominant part) and the deflection.
        names, sd, D = sens
        C = road_sensitivity(p, ref, skeleton, names, deck, leave_out) if road is None else np.array(road)
        C -= weight_n * (D @ np.asarray(load, dtype=float))  # deflection = −W·h
        Cw = _fir(ar, C)[rows] / sigma
        marginal = CalibrationMarginal.of(Cw, sd)
        wr = marginal(wr)
    raw, steps = (wr[:, :-n_step], wr[:, -n_step:]) if n_step else (wr, None)
    mu_precision = np.full(raw.shape[1] - 1 - basis.n, 1.0 / MU_PRIOR_SD_M**2)
    if common:
        # The fleet-common calibration error: coefficients shared by all passes, seen through this
        # pass's own (per-pass) calibration marginal.
        if common_columns is None or np.shape(common_columns) != (white.shape[0], len(common)):
            raise ValueError(f"pass {p.pass_id}: common calibration columns must be ({white.shape[0]}, {len(common)})")
        Bc = _fir(ar, np.asarray(common_columns, dtype=float))[rows] / sigma
        raw = np.column_stack([raw, Bc if marginal is None else marginal(Bc)])
        mu_precision = np.r_[mu_precision, [1.0 / s_**2 for _, s_ in common]]
    whitener = dataclasses.replace(skeleton, ar=ar, rows=rows, sigma=sigma, steps=steps, marginal=marginal)
    proj = whitener.project(raw)
    return WhitenedPass(p.vehicle_id, p.pass_id, proj[:, 0], proj[:, 1 : 1 + nb], proj[:, 1 + nb :], whitener, raw,
                        mu_precision)


def common_calibration_columns(passes: Sequence[PassData], ref: Reference, names: Sequence[str], deck: str,
                               deflection: Sequence[np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """How each pass's residual AP − consensus moves with a calibration error δ shared by all passes
    (window grid, (n, K) per pass, m per log unit; :mod:`cloud.bridge.vehicle_error`).

    Every AP moves by its distortion ``u_p`` (:func:`~cloud.bridge.vehicle_error.ap_distortion` of
    what the vehicle drove over: the consensus road and its deflection ``deflection[p]``, m), and
    so does the consensus off the span, by the fleet mean ``ū``: the column is ``u_p − 1_off·ū``. On
    the approach the two nearly cancel (an error every pass shares is in the consensus too), which
    a per-pass model cannot know; what is left is the error ringing on into the span, where a smooth
    deck's consensus is known to be flat — the same sign in every pass. Returns the columns and
    the u_p.
    """
    us = [pass_distortion(p, ref, names, deck, d) for p, d in zip(passes, deflection)]
    if not us:
        return [], []
    mean = consensus_distortion(us, passes[0].window, deck)
    return [u - mean for u in us], us


def pass_distortion(p: PassData, ref: Reference, names: Sequence[str], deck: str, deflection: np.ndarray) -> np.ndarray:
    """``u_p`` of :func:`common_calibration_columns`: the pass's AP distortion (n_window, K) over
    the consensus road plus its deflection ``deflection`` (m)."""
    return ap_distortion(p, driven_road(p, ref, deck) + deflection, names)


def consensus_distortion(us: Sequence[np.ndarray], window: Window, deck: str) -> np.ndarray:
    """``1_off·ū`` of :func:`common_calibration_columns`: how the consensus the passes are compared
    with moves (the fleet-mean distortion where the consensus is used: off the span of a smooth deck)."""
    off = ~window.on_span if deck == "smooth" else np.ones(window.n, dtype=bool)
    return np.mean(us, axis=0) * off[:, None]


# ---------------------------------------------------------------------------------------------
# Sufficient statistics


@dataclasses.dataclass(frozen=True, eq=False)
class VehicleStats:
    """Sums over one vehicle's passes of the products of its whitened columns.

    With ``h = Ψa + δ`` (δ: the dynamic correction column, zero when quasi-static)::

        A = ΣΨᵀΨ, e = ΣΨᵀδ, f = Σδᵀδ, Pw = ΣΨᵀw, Pb = ΣΨᵀB, dw = Σδᵀw, db = ΣBᵀδ,
        Bw = ΣBᵀw, BB = ΣBᵀB, ww = Σwᵀw, n = number of points, passes = number of passes.
    """

    vehicle_id: str
    A: np.ndarray
    e: np.ndarray
    f: float
    Pw: np.ndarray
    Pb: np.ndarray
    dw: float
    db: np.ndarray
    Bw: np.ndarray
    BB: np.ndarray
    ww: float
    n: int
    passes: int
    mu_precision: np.ndarray | None = None  # prior precision of μ (see :class:`WhitenedPass`)

    @classmethod
    def of_pass(cls, wp: WhitenedPass, delta: np.ndarray | None = None) -> "VehicleStats":
        P, B, w = wp.Psi, wp.B, wp.w
        d = np.zeros(w.size) if delta is None else np.asarray(delta, dtype=float)
        return cls(wp.vehicle_id, P.T @ P, P.T @ d, float(d @ d), P.T @ w, P.T @ B, float(d @ w), B.T @ d,
                   B.T @ w, B.T @ B, float(w @ w), int(w.size), 1, wp.mu_precision)

    def __add__(self, other: "VehicleStats") -> "VehicleStats":
        if other.vehicle_id != self.vehicle_id:
            raise ValueError("VehicleStats: adding statistics of different vehicles")
        return VehicleStats(self.vehicle_id, self.A + other.A, self.e + other.e, self.f + other.f,
                            self.Pw + other.Pw, self.Pb + other.Pb, self.dw + other.dw, self.db + other.db,
                            self.Bw + other.Bw, self.BB + other.BB, self.ww + other.ww, self.n + other.n,
                            self.passes + other.passes, self.mu_precision)


def vehicle_stats(passes: Sequence[WhitenedPass], deltas: dict[str, np.ndarray] | None = None) -> list[VehicleStats]:
    """Per-vehicle sums of :meth:`VehicleStats.of_pass` (``deltas``: pass_id → whitened δ column)."""
    out: dict[str, VehicleStats] = {}
    for wp in passes:
        s = VehicleStats.of_pass(wp, None if deltas is None else deltas.get(wp.pass_id))
        out[wp.vehicle_id] = out[wp.vehicle_id] + s if wp.vehicle_id in out else s
    return list(out.values())


@dataclasses.dataclass(frozen=True, eq=False)
class Stacked:
    """:class:`VehicleStats` of all vehicles stacked along a leading axis, with each one's weight prior."""

    ids: tuple[str, ...]
    A: np.ndarray
    e: np.ndarray
    f: np.ndarray
    Pw: np.ndarray
    Pb: np.ndarray
    dw: np.ndarray
    db: np.ndarray
    Bw: np.ndarray
    BB: np.ndarray
    ww: np.ndarray
    w_mean: np.ndarray  # prior mean wheel load per vehicle, N
    w_sd: np.ndarray  # prior sd, N
    n: int
    passes: int
    q_mu: np.ndarray | None = None  # prior precision of every μ coordinate (default 1/MU_PRIOR_SD_M²)

    @classmethod
    def of(cls, stats: Sequence[VehicleStats], prior: Callable[[str], tuple[float, float]]) -> "Stacked":
        if not stats:
            raise ValueError("no passes")
        pri = np.array([prior(s.vehicle_id) for s in stats], dtype=float)
        st = lambda name: np.array([getattr(s, name) for s in stats])  # noqa: E731
        nm = np.shape(stats[0].Bw)[0]
        q = stats[0].mu_precision
        q = np.full(nm, 1.0 / MU_PRIOR_SD_M**2) if q is None else np.asarray(q, dtype=float)
        if q.shape != (nm,):
            raise ValueError(f"mu_precision: {q.shape} for {nm} common nuisance columns")
        return cls(tuple(s.vehicle_id for s in stats), st("A"), st("e"), st("f"), st("Pw"), st("Pb"), st("dw"),
                   st("db"), st("Bw"), st("BB"), st("ww"), pri[:, 0], pri[:, 1], int(sum(s.n for s in stats)),
                   int(sum(s.passes for s in stats)), q)


# ---------------------------------------------------------------------------------------------
# The weight-marginalised log-likelihood in basis coefficients a and nuisance μ


class Terms(dict):
    """Value, gradients and Hessian blocks of the marginal log-likelihood (a dict for brevity)."""


def marginal_loglik(S: Stacked, a: np.ndarray, mu: np.ndarray, derivatives: bool = True) -> Terms:
    """log p(data | a, μ) with every vehicle's wheel load integrated over its prior.

    Per vehicle, with λ = hᵀh + 1/s², g = hᵀρ, u = W̄/s² − g, m = u/λ (the weight's conditional
    posterior mean, N) and 1/λ its variance::

        ℓ = −½‖ρ‖² + ½u²/λ − ½W̄²/s² − ½ log(λ s²)

    Returns ``value``, ``m``, ``var`` and, with ``derivatives``, ``ga``, ``gm`` (gradients) and
    ``Haa``, ``Hmm``, ``Hma`` (Hessian blocks), all summed over vehicles.
    """
    inv_s2 = 1.0 / S.w_sd**2
    r = S.A @ a + S.e  # (V, nb)
    lam = r @ a + S.e @ a + S.f + inv_s2
    q = S.Pw - S.Pb @ mu  # (V, nb)
    t = np.einsum("vbm,b->vm", S.Pb, a) + S.db  # (V, nm)
    g = q @ a + S.dw - S.db @ mu
    u = S.w_mean * inv_s2 - g
    m = u / lam
    rr = S.ww - 2.0 * (S.Bw @ mu) + np.einsum("m,vmn,n->v", mu, S.BB, mu)
    val = float(np.sum(-0.5 * rr + 0.5 * u * m - 0.5 * S.w_mean**2 * inv_s2 - 0.5 * np.log(lam / inv_s2)))
    out = Terms(value=val, m=m, var=1.0 / lam)
    if not derivatives:
        return out
    ew2 = m * m + 1.0 / lam  # E[W²]
    out["ga"] = np.sum(-m[:, None] * q - ew2[:, None] * r, axis=0)
    out["gm"] = np.sum(S.Bw - np.einsum("vmn,n->vm", S.BB, mu) + m[:, None] * t, axis=0)
    k = q + 2.0 * m[:, None] * r  # (V, nb)
    out["Haa"] = (np.einsum("vi,vj,v->ij", k, k, 1.0 / lam) + 2.0 * np.einsum("vi,vj,v->ij", r, r, 1.0 / lam**2)
                  - np.einsum("v,vij->ij", ew2, S.A))
    out["Hmm"] = -S.BB.sum(axis=0) + np.einsum("vi,vj,v->ij", t, t, 1.0 / lam)
    out["Hma"] = -np.einsum("vm,vb,v->mb", t, k, 1.0 / lam) + np.einsum("v,vbm->mb", m, S.Pb)
    # dm/da and dm/dμ, for the weights' uncertainty propagation.
    out["dm_da"] = -k / lam[:, None]
    out["dm_dmu"] = t / lam[:, None]
    return out


def marginal_loglik_batch(S: Stacked, a: np.ndarray, delta_scale: np.ndarray | None = None,
                          chunk: int = 512) -> np.ndarray:
    """log p(data | a) for a batch of coefficient vectors ``a`` (K, n_b): weights *and* μ integrated.

    μ has the prior N(0, diag(1/S.q_mu)) and enters the weight-marginal log-likelihood
    quadratically, so its integral is exact. ``delta_scale`` (K,) multiplies the dynamic
    correction column of every pass (ε scales with the compliance). Returns (K,).
    """
    a = np.atleast_2d(np.asarray(a, dtype=float))
    K = a.shape[0]
    ds = np.ones(K) if delta_scale is None else np.asarray(delta_scale, dtype=float)
    nm = S.Bw.shape[1]
    q_mu = S.q_mu
    inv_s2 = 1.0 / S.w_sd**2
    out = np.empty(K)
    for lo in range(0, K, chunk):
        ak, dk = a[lo : lo + chunk], ds[lo : lo + chunk]
        Aa = np.matmul(ak[None], S.A)  # (V, k, nb), batched BLAS
        lam = (np.sum(Aa * ak[None], axis=2).T + 2 * dk[:, None] * (ak @ S.e.T) + dk[:, None] ** 2 * S.f[None, :]
               + inv_s2[None, :])  # (k, V)
        t = np.matmul(ak[None], S.Pb).transpose(1, 0, 2) + dk[:, None, None] * S.db[None, :, :]  # (k, V, nm)
        u0 = S.w_mean * inv_s2 - (ak @ S.Pw.T) - dk[:, None] * S.dw[None, :]  # (k, V)
        H = S.BB.sum(axis=0)[None] - np.matmul(t.transpose(0, 2, 1) / lam[:, None, :], t) + np.diag(q_mu)[None]
        b = S.Bw.sum(axis=0)[None] + np.matmul((u0 / lam)[:, None, :], t)[:, 0, :]
        c0 = np.sum(-0.5 * S.ww[None] + 0.5 * u0**2 / lam - 0.5 * S.w_mean[None] ** 2 * inv_s2[None]
                    - 0.5 * np.log(lam / inv_s2[None]), axis=1)
        sol = np.linalg.solve(H, b[:, :, None])[:, :, 0]
        _, logdet = np.linalg.slogdet(H)
        out[lo : lo + chunk] = (c0 + 0.5 * np.einsum("km,km->k", b, sol) - 0.5 * logdet
                                + 0.5 * float(np.sum(np.log(q_mu))))
    return out


# ---------------------------------------------------------------------------------------------
# Stiffness parametrisations


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
    #: little beside the dynamics — except with bearings, where τ stays 1 (:meth:`Setup.model`).
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


# ---------------------------------------------------------------------------------------------
# Posterior


@dataclasses.dataclass(frozen=True, eq=False)
class ElementPosterior:
    """Laplace posterior of the element stiffnesses (and the vehicles' wheel loads).

    ``theta``/``cov``: mode and covariance of log(EI/EI_design) per element; ``weights``: vehicle →
    (mean, sd) of its static wheel load, N; ``log_evidence``: Laplace approximation of
    log p(data) under the prior (nuisance μ integrated); ``chi2_per_point``: mean squared
    whitened residual at the mode (≈ 1 when the noise model is right; the covariance is widened by
    it when above 1). ``effective_ratio``: area under the design influence line over the area
    under the estimated one — the well-determined global stiffness (the ends of a span barely
    affect any deflection, so a plain mean over elements is dominated by prior-driven elements);
    with bearings it includes their restraint (relative to the pinned design span).
    ``krot``: bearings' log10 Krot (mean, lo95, hi95) per support, when modelled.
    """

    theta: np.ndarray
    cov: np.ndarray
    ei_design: float
    element_bounds: np.ndarray
    weights: dict[str, tuple[float, float]]
    mu: np.ndarray
    log_evidence: float
    chi2_per_point: float
    n_passes: int
    n_vehicles: int
    iterations: int
    effective_ratio: float = float("nan")
    effective_ratio_sd: float = float("nan")
    krot: tuple[tuple[float, float, float], ...] | None = None  # per support: log10 Krot (mean, lo95, hi95)
    params: np.ndarray | None = None
    #: the departure scale τ of the stiffness prior (:attr:`StiffnessPrior.scales`): its posterior
    #: weight per τ (empty: fixed at 1)
    scale_weights: tuple[tuple[float, float], ...] = ()

    @property
    def departure_scale(self) -> float:
        """Posterior mean of log τ, as τ (1.0 when τ was fixed)."""
        if not self.scale_weights:
            return 1.0
        return float(math.exp(sum(w * math.log(t) for t, w in self.scale_weights)))

    @property
    def sd(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    @property
    def ei_mean(self) -> np.ndarray:
        """Posterior mean of EI per element (log-normal), N·m²."""
        return self.ei_design * np.exp(self.theta + 0.5 * self.sd**2)

    @property
    def ei_lo95(self) -> np.ndarray:
        return self.ei_design * np.exp(self.theta - 1.96 * self.sd)

    @property
    def ei_hi95(self) -> np.ndarray:
        return self.ei_design * np.exp(self.theta + 1.96 * self.sd)

    @property
    def stiffness_ratio(self) -> np.ndarray:
        """EI_mean / EI_design per element."""
        return self.ei_mean / self.ei_design

    def mean_ratio(self) -> tuple[float, float]:
        """Span-mean stiffness ratio exp(mean θ) and the sd of mean θ (≈ relative sd)."""
        n = self.theta.size
        return float(np.exp(self.theta.mean())), float(math.sqrt(np.sum(self.cov) / n**2))

    def rows(self, bridge_id: str) -> list[dict]:
        """Rows of ``bridge_elements.parquet`` (interfaces.md §3)."""
        return [dict(bridge_id=bridge_id, element=i + 1, x_start_m=float(b[0]), x_end_m=float(b[1]),
                     EI_mean=float(m), EI_lo95=float(lo), EI_hi95=float(hi), stiffness_ratio=float(r))
                for i, (b, m, lo, hi, r) in enumerate(zip(self.element_bounds, self.ei_mean, self.ei_lo95,
                                                          self.ei_hi95, self.stiffness_ratio))]


def _newton(fun: Callable[[np.ndarray], tuple[float, np.ndarray, np.ndarray]], x0: np.ndarray,
            max_iter: int = 60, tol: float = 1e-9, max_step: float = 0.5,
            max_step_dims: int = 0) -> tuple[np.ndarray, int]:
    """Maximise ``fun`` (value, gradient, Hessian) by damped Newton steps with backtracking.

    Steps are shortened so that none of the first ``max_step_dims`` coordinates moves by more
    than ``max_step`` (log-stiffness: a factor e^0.5 per iteration at most).
    """
    x = x0.copy()
    val, g, H = fun(x)
    for it in range(1, max_iter + 1):
        damp = 0.0
        scale = np.maximum(np.abs(np.diag(H)), 1e-12)
        while True:
            Hd = -H + damp * np.diag(scale)
            try:
                L = np.linalg.cholesky(Hd)
                break
            except np.linalg.LinAlgError:
                damp = max(2 * damp, 1e-6)
        step = np.linalg.solve(L.T, np.linalg.solve(L, g))
        big = np.max(np.abs(step[:max_step_dims])) if max_step_dims else 0.0
        t = min(1.0, max_step / big) if big > 0 else 1.0
        while True:
            cand = x + t * step
            with np.errstate(all="ignore"):
                v2, g2, H2 = fun(cand)
            if (np.isfinite(v2) and v2 >= val - 1e-10 * abs(val)) or t < 1e-8:
                break
            t *= 0.5
        if not np.isfinite(v2):
            return x, it
        x, decrease = cand, v2 - val
        val, g, H = v2, g2, H2
        if abs(decrease) < tol * max(1.0, abs(val)) and float(g @ step) < 1e-6:
            return x, it
    return x, max_iter


@dataclasses.dataclass(frozen=True)
class WeightPrior:
    """Prior of static wheel loads: ``(mean, sd)`` N per vehicle, by default the class's."""

    mean_n: float
    sd_n: float
    per_vehicle: tuple[tuple[str, float, float], ...] = ()
    #: the class's log-sd of each calibration quantity, (name, sd): the scale of the fleet-common
    #: calibration error (:class:`~cloud.bridge.estimator.BridgeSettings`); empty: not known
    class_log_sd: tuple[tuple[str, float], ...] = ()

    def __call__(self, vehicle_id: str) -> tuple[float, float]:
        for vid, m, s in self.per_vehicle:
            if vid == vehicle_id:
                return m, s
        return self.mean_n, self.sd_n


MU_PRIOR_SD_M = 0.05  # broad prior on the nuisance coefficients (m), so the evidence is proper


def fit_elements(stats: Sequence[VehicleStats], model: "ElementModel | BearingElementModel",
                 weight_prior: WeightPrior, theta0: np.ndarray | None = None) -> ElementPosterior:
    """Laplace posterior of the model's parameters (θ = log EI/EI_design per element, and
    log10 Krot for bearings) with μ and the vehicles' weights integrated out; with
    :attr:`StiffnessPrior.scales`, the prior's departure scale integrated out too
    (:func:`fit_elements_per_scale`, :func:`mix_scales`)."""
    return mix_scales(fit_elements_per_scale(stats, model, weight_prior, theta0), model.prior)


def fit_elements_per_scale(stats: Sequence[VehicleStats], model: "ElementModel | BearingElementModel",
                           weight_prior: WeightPrior, theta0: np.ndarray | None = None) -> list[ElementPosterior]:
    """One Laplace posterior per departure scale τ of :attr:`StiffnessPrior.scales` (one, at the
    prior as it stands, when there are none). A fit costs milliseconds: the data are reduced to
    per-vehicle statistics once."""
    S = Stacked.of(stats, weight_prior)
    scales = model.prior.scales
    if not scales:
        return [_fit_elements(S, model, theta0)]
    return [_fit_elements(S, dataclasses.replace(model, prior=model.prior.scaled(t)), theta0) for t in scales]


def mix_scales(fits: Sequence[ElementPosterior], prior: StiffnessPrior) -> ElementPosterior:
    """The posterior with the departure scale τ integrated out: the fits at each τ of
    ``prior.scales`` weighted by evidence × hyperprior (log τ ~ N(0, ``scale_sd``²) on the grid),
    moment-matched in θ — the mean, and a covariance that includes the spread between the fits
    (the bands widen when the data cannot tell the scales apart). The other fields are the most
    probable τ's; the result's ``log_evidence`` is the mixture's."""
    if len(fits) == 1:
        return fits[0]
    scales = np.asarray(prior.scales, dtype=float)
    log_z = np.array([f.log_evidence for f in fits], dtype=float)
    log_h = -0.5 * (np.log(scales) / prior.scale_sd) ** 2 if prior.scale_sd else np.zeros(scales.size)
    log_h -= np.log(np.sum(np.exp(log_h)))
    lp = log_z + log_h
    w = np.exp(lp - lp.max())
    log_ev = float(lp.max() + math.log(w.sum()))
    w /= w.sum()
    best = fits[int(np.argmax(w))]
    thetas = np.array([f.theta for f in fits])
    theta = w @ thetas
    dev = thetas - theta
    cov = np.einsum("k,kij->ij", w, np.array([f.cov for f in fits])) + (dev.T * w) @ dev
    params = np.array(best.params, dtype=float)
    params[: theta.size] = theta
    effs = np.array([f.effective_ratio for f in fits])
    eff = float(w @ effs)
    eff_sd = float(math.sqrt(w @ (np.array([f.effective_ratio_sd for f in fits]) ** 2 + (effs - eff) ** 2)))
    return dataclasses.replace(best, theta=theta, cov=cov, params=params, log_evidence=log_ev,
                               effective_ratio=eff, effective_ratio_sd=eff_sd,
                               scale_weights=tuple((float(t), float(v)) for t, v in zip(scales, w)))


def _fit_elements(S: "Stacked", model, theta0: np.ndarray | None) -> ElementPosterior:
    """:func:`fit_elements` at the model's prior as it stands (τ fixed)."""
    npar, nm = model.n, S.Bw.shape[1]
    ne = model.n_elements
    Q, m0 = model.prior_precision(), model.prior_mean()
    q_mu = S.q_mu  # (nm,)

    def fun(z):
        par, mu = z[:npar], z[npar:]
        a, Ja, d2 = model.a_jac(par)
        T = marginal_loglik(S, a, mu)
        gp = Ja.T @ T["ga"]
        H_pp = Ja.T @ T["Haa"] @ Ja + np.diag(d2.T @ T["ga"]) - Q
        H_mp = T["Hma"] @ Ja
        g = np.r_[gp - Q @ (par - m0), T["gm"] - q_mu * mu]
        H = np.block([[H_pp, H_mp.T], [H_mp, T["Hmm"] - np.diag(q_mu)]])
        val = T["value"] - 0.5 * (par - m0) @ Q @ (par - m0) - 0.5 * mu @ (q_mu * mu)
        return val, g, H

    z0 = np.r_[m0, np.zeros(nm)]
    if theta0 is not None:
        z0[: len(theta0)] = theta0
    z, iters = _newton(fun, z0, max_step_dims=npar)
    val, g, H = fun(z)
    par, mu = z[:npar], z[npar:]
    a, Ja, _ = model.a_jac(par)
    T = marginal_loglik(S, a, mu)
    chi2 = _chi2(S, a, mu, T["m"])
    # Residuals a little larger than the noise model says (consensus noise, model error): widen.
    cov_full = np.linalg.inv(-H) * max(1.0, chi2)
    # Weights: conditional variance plus the propagated uncertainty of (θ, μ).
    J_w = np.hstack([T["dm_da"] @ Ja, T["dm_dmu"]])  # (V, npar + nm)
    var_w = T["var"] + np.einsum("vi,ij,vj->v", J_w, cov_full, J_w)
    weights = {vid: (float(m), float(math.sqrt(v))) for vid, m, v in zip(S.ids, T["m"], var_w)}
    # Laplace evidence with normalised Gaussian priors.
    _, logdet_H = np.linalg.slogdet(-H)
    _, logdet_Q = np.linalg.slogdet(Q)
    log_ev = (val + 0.5 * (npar + nm) * math.log(2 * math.pi) - 0.5 * logdet_H
              + 0.5 * logdet_Q - 0.5 * npar * math.log(2 * math.pi)
              + 0.5 * float(np.sum(np.log(q_mu))) - 0.5 * nm * math.log(2 * math.pi))
    edges = np.linspace(0.0, model.basis.window.span_m, ne + 1)
    bounds = np.column_stack([edges[:-1], edges[1:]])
    # Effective stiffness: area under the design influence line over the area under J (D2-like).
    wint = model.basis.integrals
    a_design = model.basis.coefficients(design_influence(model))
    nb = wint.size  # the load term's coefficients lead a (a linearised dynamic model appends its own)
    area = float(wint @ a[:nb])
    eff = float(wint @ a_design) / area
    geff = -eff / area * (wint @ Ja[:nb])
    eff_sd = float(math.sqrt(max(geff @ cov_full[:npar, :npar] @ geff, 0.0)))
    krot = None
    if npar > ne:
        kap = par[ne:]
        ksd = np.sqrt(np.diag(cov_full)[ne:npar])
        krot = tuple((float(k), float(k - 1.96 * s_), float(k + 1.96 * s_)) for k, s_ in zip(kap, ksd))
        if len(krot) == 1:
            krot = krot * 2
    return ElementPosterior(par[:ne], cov_full[:ne, :ne], model.ei_design, bounds, weights, mu, float(log_ev),
                            chi2, S.passes, len(S.ids), iters, eff, eff_sd, krot, par)


def design_influence(model) -> np.ndarray:
    """The design bridge's J on the span points (pinned supports), m/N."""
    b = model.bridge if hasattr(model, "bridge") else None
    if b is not None:
        return influence_line(design_beam(b), model.basis.x)
    return model.basis.design @ (model.kernel @ np.full(model.n_elements, 1.0 / model.ei_design))


def _chi2(S: Stacked, a: np.ndarray, mu: np.ndarray, m: np.ndarray) -> float:
    """Mean squared whitened residual with every weight at its conditional mean."""
    # ‖ρ + W h‖² = ‖ρ‖² + 2W g + W² hᵀh
    rr = S.ww - 2.0 * (S.Bw @ mu) + np.einsum("m,vmn,n->v", mu, S.BB, mu)
    g = (S.Pw - S.Pb @ mu) @ a + S.dw - S.db @ mu
    hh = np.einsum("b,vbc,c->v", a, S.A, a) + 2 * S.e @ a + S.f
    return float(np.sum(rr + 2 * m * g + m * m * hh) / max(S.n, 1))


# ---------------------------------------------------------------------------------------------
# Convenience: from PassData to a posterior


@dataclasses.dataclass(frozen=True)
class Setup:
    """Everything fixed about one bridge's estimation: window, basis, design beam, deck model."""

    bridge: Bridge
    window: Window
    basis: SpanBasis
    beam: Beam
    deck: str = "smooth"

    @classmethod
    def of(cls, bridge: Bridge, deck: str = "smooth", spacing_m: float = 0.05, pre_m: float = 60.0,
           post_m: float = 25.0) -> "Setup":
        window = Window.of(bridge, spacing_m, pre_m, post_m)
        basis = SpanBasis.of(window, bridge.n_elements)
        return cls(bridge, window, basis, design_beam(bridge), deck)

    def model(self, prior: StiffnessPrior = StiffnessPrior()) -> "ElementModel | BearingElementModel":
        """The per-element model the registry calls for: bearings when ``supports`` says so."""
        if self.bridge.supports == "rotational_springs":
            k0 = 8.0 if self.bridge.krot_nm_per_rad is None else math.log10(max(self.bridge.krot_nm_per_rad, 1.0))
            # The departure scale is not learnt here: each of the bearing model's fits costs a finite-
            # difference Jacobian (n + 2 FE solves) per Newton step, and the grid would multiply that by
            # nine for the same Krot and mean stiffness.
            return BearingElementModel(self.basis, self.bridge, dataclasses.replace(prior, scales=()), (k0, 2.5))
        if self.deck == "rough":
            # Nor on a rough deck: what of the deck profile the weights' spread leaves unseparated is
            # smooth along the span, reads as departures, and the evidence would loosen the prior until
            # the bump is fitted as stiffness.
            prior = dataclasses.replace(prior, scales=())
        return ElementModel.of(self.basis, self.beam, prior)


def whiten_all(passes: Sequence[PassData], setup: Setup) -> list[WhitenedPass]:
    """Whiten every pass against the leave-one-out consensus of the others."""
    ref = Reference.of(passes)
    return [whiten_pass(p, ref, setup.basis, setup.deck) for p in passes]
