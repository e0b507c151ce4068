"""One pass in the measured-channel domain: its noise model (an AR prewhitener fitted on the approach, its
level read in the element band) and the whitening of its data and model columns."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
from scipy.linalg import solve_toeplitz
from scipy.signal import butter, lfilter, sosfiltfilt

from cloud.bridge.basis import MU_PRIOR_SD_M, SpanBasis, mu_basis, step_basis
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
                  ) -> tuple[Whitener, np.ndarray, tuple[tuple[str, ...], np.ndarray, np.ndarray] | None]:
    """The :class:`Whitener` skeleton (AR and rows not yet known), the pass's band-limited forward-model
    output of its model columns (load basis, μ basis, step basis), (n_dec, n_b + n_mu + n_step), and —
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
