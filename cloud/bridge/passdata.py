"""One pass over one bridge: the apparent profile over the span and its margins, made exact.

The edge publishes each pass's apparent profile (AP) as tiles on the route grid. Over a bridge the
AP is deck profile + deflection under the wheel, drift-controlled (a ±150 m local linear trend
removed). This module turns a pass's segments into what the bridge estimators need:

1. :func:`assemble_pass` — the pass's AP for one axle on the global grid, with a validity mask.
2. :func:`correct_aps` — undo the edge inverse's time-discretisation error. The edge integrates with
   Newmark-β (γ > ½, first-order accurate: ``edge_gamma``); at the body's bounce frequency its AP is
   off in amplitude and phase by a little. That is negligible for a road, but not on a bridge: the
   error an approach ramp leaves on the span is of the order of the deflection itself. The AP the
   edge would have produced with a continuous-time model is ``T⁻¹(ω) H(ω) · AP``, with ``H`` the
   edge's discrete Newmark forward transfer and ``T`` the vehicle's continuous transfer (both closed
   form, :mod:`shared.dynamics.transfer`), applied by FFT at the pass's speed.
3. :class:`VehicleFilter` — the vehicle's continuous forward model on the chainage grid
   (:func:`shared.dynamics.forward.ap_response` at Newmark γ = ½, second-order). It maps a profile
   to the measured channel, which *whitens* AP errors
   (sensor noise is white in the measured channel; the inverse colours it), annihilates offsets,
   slopes and the drift-control trend, and gives the dynamic wheel-load factor ``1 + φ(x)``
   (``φ`` = dynamic tyre force / static wheel load) from the AP and the calibrated ratios alone.
4. :func:`extract_pass` → :class:`PassData` — all of the above on the bridge's fixed window grid
   (``pre_m`` before the first support to ``post_m`` after the second).
5. :class:`Reference` — the consensus AP of many passes on that window (leave-one-out available),
   and :func:`span_profile` — the per-pass deflection estimate on the span, drift-controlled by
   an offset + slope fitted to AP − consensus on the approach and exit margins.
6. :func:`road_load_factor` — ``1 + φ`` without the pass's own noise: the vehicle driven over the
   other passes' consensus road and its own deflection (what the estimator uses by default).

Units: chainage m, AP m (up positive), speed m/s, frequencies Hz.
"""

from __future__ import annotations

import dataclasses
import math
from collections import defaultdict
from collections.abc import Iterable, Sequence

import numpy as np
from scipy.signal import butter, sosfiltfilt

from shared.dynamics.forward import ap_response, contact_forces, measured_channels
from shared.dynamics.inverse import edge_gamma
from shared.dynamics.newmark import newmark_constants
from shared.dynamics.transfer import continuous_transfer, newmark_transfer
from shared.registry import Bridge
from shared.schema import ApSegment
from shared.vehicles import vehicle_from_params
from shared.vehicles.base import VehicleSystem

#: Segment points whose sigma exceeds this multiple of the pass median are unreliable (the edge
#: multiplies the sigma of unreliable points by 100).
UNRELIABLE_SIGMA_RATIO = 10.0
#: The dynamic wheel load is kept below this frequency (Hz).
LOAD_CUTOFF_HZ = 10.0


@dataclasses.dataclass(frozen=True)
class EdgeSettings:
    """How the edge computed the AP (its inverse's sampling and Newmark constants).

    ``correction_cutoff_hz``: the discretisation correction is applied in full below this
    frequency and faded out by 1.5× it (the bridge signal lives below ~10 Hz).

    The vehicles' own dynamics are taken as continuous-time physics: nothing here describes how
    data were made (a simulator must integrate accurately enough to be physics, as ``simfleet``
    does with γ = ½ at 2 kHz).
    """

    sample_rate_hz: float = 500.0
    gamma: float | None = None  # None: the edge's for the vehicle model (shared.dynamics.inverse.edge_gamma)
    beta: float | None = None
    correction_cutoff_hz: float = 30.0

    @property
    def dt(self) -> float:
        return 1.0 / self.sample_rate_hz

    @property
    def beta_value(self) -> float:
        return 0.25 * (0.5 + self.gamma) ** 2 if self.beta is None else self.beta


# ---------------------------------------------------------------------------------------------
# 1. A pass's AP on the global grid


@dataclasses.dataclass(frozen=True, eq=False)
class PassAp:
    """The AP of one axle of one pass on the route grid: point i is at ``(start_index + i) * spacing_m``."""

    vehicle_id: str
    pass_id: str
    axle: int
    speed_mps: float
    spacing_m: float
    start_index: int
    values: np.ndarray  # (n,) m
    sigma: np.ndarray  # (n,) m, the edge's per-point error scale
    valid: np.ndarray  # (n,) bool
    calib_version: int = 0

    @property
    def x(self) -> np.ndarray:
        """Route chainage of every point, m."""
        return (self.start_index + np.arange(self.values.size)) * self.spacing_m

    @property
    def end_index(self) -> int:
        return self.start_index + self.values.size


def group_segments(segments: Iterable[ApSegment]) -> dict[tuple[str, str], list[ApSegment]]:
    """Segments grouped by ``(vehicle_id, pass_id)``, in arrival order."""
    out: dict[tuple[str, str], list[ApSegment]] = defaultdict(list)
    for s in segments:
        out[(s.vehicle_id, s.pass_id)].append(s)
    return dict(out)


def assemble_pass(segments: Sequence[ApSegment], axle: int = 1) -> PassAp | None:
    """Stitch one pass's segments of ``axle`` into a :class:`PassAp` (None if there are none).

    Segments of older calibration versions are ignored when a newer one is present (the edge
    republishes a pass when its calibration changes); a repeated tile keeps its latest segment.
    """
    segs = [s for s in segments if s.axle == axle]
    if not segs:
        return None
    ids = {(s.vehicle_id, s.pass_id) for s in segs}
    if len(ids) != 1:
        raise ValueError(f"assemble_pass: segments of several passes {sorted(ids)}")
    version = max(s.calib_version for s in segs)
    segs = [s for s in segs if s.calib_version == version]
    spacing = segs[0].spacing_m
    if any(abs(s.spacing_m - spacing) > 1e-12 for s in segs):
        raise ValueError("assemble_pass: segments on different grids")
    lo = min(s.start_index for s in segs)
    hi = max(s.start_index + s.n for s in segs)
    values = np.zeros(hi - lo)
    sigma = np.full(hi - lo, np.inf)
    for s in sorted(segs, key=lambda s: s.seq):
        a = s.start_index - lo
        values[a : a + s.n] = s.values
        sigma[a : a + s.n] = s.sigma
    finite = np.isfinite(sigma)
    med = float(np.median(sigma[finite])) if finite.any() else 1.0
    valid = finite & (sigma <= UNRELIABLE_SIGMA_RATIO * med)
    n_pts = np.array([s.n for s in segs], dtype=float)
    speed = float(np.average([s.speed_mps for s in segs], weights=n_pts))
    s0 = segs[0]
    return PassAp(s0.vehicle_id, s0.pass_id, axle, speed, spacing, lo, values, np.where(finite, sigma, 1.0),
                  valid, version)


# ---------------------------------------------------------------------------------------------
# 2. Transfer functions and the discretisation correction


def correction_response(system: VehicleSystem, freqs_hz: np.ndarray, edge: EdgeSettings) -> np.ndarray:
    """``T⁻¹H``: maps the edge's AP to the AP of an exact inverse of the vehicles' continuous
    dynamics ``T``, (n_f, n_c, n_c).

    Identity at 0 Hz and faded to identity between ``edge.correction_cutoff_hz`` and 1.5× it.
    """
    if len(system.channels) != system.n_contacts:
        raise ValueError("correction: the model must measure as many channels as it has contacts")
    f = np.asarray(freqs_hz, dtype=float)
    n_c = system.n_contacts
    eye = np.eye(n_c)
    out = np.broadcast_to(eye, (f.size, n_c, n_c)).astype(complex)
    fc = edge.correction_cutoff_hz
    fade = np.clip((1.5 * fc - f) / (0.5 * fc), 0.0, 1.0)
    use = (f > 0) & (fade > 0)
    if use.any():
        H = newmark_transfer(system, f[use], edge.dt, edge.gamma, edge.beta)
        T = continuous_transfer(system, f[use])
        out[use] = eye + fade[use, None, None] * (np.linalg.solve(T, H) - eye)
    return out


def correct_aps(aps: dict[int, PassAp], system: VehicleSystem, edge: EdgeSettings = EdgeSettings()) -> dict[int, PassAp]:
    """The pass's APs (axle → :class:`PassAp`) as a continuous-time inverse would have made them.

    All axles are resampled to the edge's time step at the pass's (constant) speed on their common
    valid extent, corrected together by FFT (after removing a straight line, zero-padded) and mapped
    back to each axle's grid. Points outside the common extent become invalid.
    """
    axles = sorted(aps)
    if len(axles) != system.n_contacts:
        raise ValueError(f"correct_aps: the model has {system.n_contacts} contacts, got axles {axles}")
    offsets = system.offsets_m
    v = float(np.mean([aps[a].speed_mps for a in axles]))
    if not v > 0:
        raise ValueError("correct_aps: the pass has no speed")
    # Common extent in centre-of-gravity chainage.
    lo, hi = -math.inf, math.inf
    for i, a in enumerate(axles):
        ap = aps[a]
        idx = np.flatnonzero(ap.valid)
        if idx.size < 8:
            raise ValueError("correct_aps: too few valid points")
        lo = max(lo, ap.x[idx[0]] - offsets[i])
        hi = min(hi, ap.x[idx[-1]] - offsets[i])
    dt = edge.dt
    t = np.arange(0.0, (hi - lo) / v, dt)
    if t.size < 16:
        raise ValueError("correct_aps: the axles' common extent is too short")
    series = np.empty((t.size, len(axles)))
    for i, a in enumerate(axles):
        ap = aps[a]
        xs = ap.x[ap.valid]
        series[:, i] = np.interp(lo + offsets[i] + v * t, xs, ap.values[ap.valid])
    k = np.arange(t.size, dtype=float)
    trend = np.empty_like(series)
    for i in range(series.shape[1]):
        trend[:, i] = np.polyval(np.polyfit(k, series[:, i], 1), k)
    n_fft = 1 << int(math.ceil(math.log2(2 * t.size)))
    spec = np.fft.rfft(series - trend, n_fft, axis=0)
    C = correction_response(system, np.fft.rfftfreq(n_fft, dt), edge)
    fixed = np.fft.irfft(np.einsum("fij,fj->fi", C, spec), n_fft, axis=0)[: t.size] + trend
    out = {}
    for i, a in enumerate(axles):
        ap = aps[a]
        x_cg = ap.x - offsets[i]
        inside = (x_cg >= lo) & (x_cg <= lo + v * t[-1])
        vals = np.where(inside, np.interp(x_cg, lo + v * t, fixed[:, i]), ap.values)
        out[a] = dataclasses.replace(ap, values=vals, valid=ap.valid & inside)
    return out


# ---------------------------------------------------------------------------------------------
# 3. The vehicle's continuous forward model on the chainage grid


@dataclasses.dataclass(frozen=True, eq=False)
class VehicleFilter:
    """The vehicle's continuous forward model driven along the chainage grid at ``speed_mps``.

    Time step = ``spacing_m / speed_mps``; Newmark γ = ½, β = ¼ (trapezoidal: second-order, no
    numerical damping). Linear in the profile.
    """

    system: VehicleSystem
    speed_mps: float
    spacing_m: float

    @property
    def dt(self) -> float:
        return self.spacing_m / self.speed_mps

    def run(self, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Channels (n, n_ch, k) and dynamic contact forces (n, n_c, k), N, for profiles (n, n_c, k) m."""
        Y = np.asarray(Y, dtype=np.float64)
        if Y.ndim != 3 or Y.shape[1] != self.system.n_contacts:
            raise ValueError(f"VehicleFilter.run: expected (n, {self.system.n_contacts}, k), got {Y.shape}")
        profiles = np.ascontiguousarray(np.moveaxis(Y, 2, 0))  # (k, n, n_c): a batch of independent profiles
        c = newmark_constants(self.dt, 0.5, 0.25)
        state = ap_response(self.system, profiles, c)
        channels = measured_channels(self.system, state)
        forces = contact_forces(self.system, profiles, state, c.dt)
        return np.moveaxis(channels, 0, 2), np.moveaxis(forces, 0, 2)

    def whiten(self, y: np.ndarray) -> np.ndarray:
        """First measured channel for single-contact profiles ``y`` (n,) or (n, k): the whitening map."""
        y = np.asarray(y, dtype=float)
        cols = y[:, None] if y.ndim == 1 else y
        ch, _ = self.run(cols[:, None, :])
        out = ch[:, 0, :]
        return out[:, 0] if y.ndim == 1 else out

    def load_factor(self, y: np.ndarray) -> np.ndarray:
        """``1 + φ`` per contact, (n, n_c): total wheel load over static wheel load, for profiles (n, n_c)."""
        y = np.asarray(y, dtype=float)
        if y.ndim == 1:
            y = y[:, None]
        _, dyn = self.run(y[:, :, None])
        static = self.system.static_contact_forces()
        return 1.0 + dyn[:, :, 0] / static[None, :]


# ---------------------------------------------------------------------------------------------
# 4. One pass on a bridge's window


@dataclasses.dataclass(frozen=True)
class Window:
    """A bridge's fixed analysis grid: global grid indices ``[i0, i0 + n)``, and the span on it."""

    bridge_id: str
    start_m: float  # route chainage of the first support
    span_m: float
    spacing_m: float
    i0: int
    n: int

    @classmethod
    def of(cls, bridge: Bridge, spacing_m: float = 0.05, pre_m: float = 60.0, post_m: float = 25.0) -> "Window":
        i0 = int(math.floor((bridge.start_chainage_m - pre_m) / spacing_m + 1e-9))
        i1 = int(math.ceil((bridge.end_chainage_m + post_m) / spacing_m - 1e-9))
        return cls(bridge.id, bridge.start_chainage_m, bridge.span_m, spacing_m, max(i0, 0), i1 - max(i0, 0) + 1)

    @property
    def chainage(self) -> np.ndarray:
        """Route chainage of every window point, m."""
        return (self.i0 + np.arange(self.n)) * self.spacing_m

    @property
    def x(self) -> np.ndarray:
        """Distance from the first support, m."""
        return self.chainage - self.start_m

    @property
    def on_span(self) -> np.ndarray:
        x = self.x
        return (x >= -1e-9) & (x <= self.span_m + 1e-9)


@dataclasses.dataclass(frozen=True, eq=False)
class PassData:
    """One axle of one pass over a bridge, on the bridge's :class:`Window`.

    ``ap`` is the corrected AP (m), NaN-free (0 where invalid); ``load_factor`` = total / static
    wheel load along the window (1 where unknown) — as extracted, from the pass's own AP; the
    estimator replaces it by :func:`road_load_factor`'s (see there why); ``ap_sigma_m`` the edge's median per-point
    error scale (m). ``model`` and ``params`` are the vehicle parameters the AP was computed with
    (its calibration; only their ratios matter).
    """

    window: Window
    vehicle_id: str
    pass_id: str
    axle: int
    model: str
    params: dict
    speed_mps: float
    ap: np.ndarray
    valid: np.ndarray
    load_factor: np.ndarray
    ap_sigma_m: float
    #: log-sd of each calibration quantity (name → sd, e.g. {'k/M': 0.03}) that ``params`` carry:
    #: the calibration's uncertainty, integrated out of the bridge likelihood
    #: (:mod:`cloud.bridge.vehicle_error`); None or empty: the parameters are taken as exact.
    params_log_sd: dict | None = None

    def system(self) -> VehicleSystem:
        return vehicle_from_params(self.model, dict(self.params)).system()

    def vehicle_filter(self) -> VehicleFilter:
        return VehicleFilter(self.system(), self.speed_mps, self.window.spacing_m)


def _low_pass(factor: np.ndarray, speed_mps: float, spacing_m: float, cutoff_hz: float | None) -> np.ndarray:
    """A load factor ``1 + φ`` with φ low-passed at ``cutoff_hz`` (zero phase; unchanged if short or no cutoff)."""
    if not cutoff_hz or factor.size <= 30:
        return factor
    nyq = 0.5 * speed_mps / spacing_m
    if cutoff_hz >= nyq:
        return factor
    sos = butter(4, cutoff_hz / nyq, output="sos")
    return 1.0 + sosfiltfilt(sos, factor - 1.0)


def extract_pass(segments: Sequence[ApSegment], window: Window, model: str, params: dict,
                 edge: EdgeSettings = EdgeSettings(), axle: int = 1, correct: bool = True,
                 min_cover_m: float = 10.0, load_cutoff_hz: float = LOAD_CUTOFF_HZ,
                 params_log_sd: dict | None = None) -> PassData | None:
    """The :class:`PassData` of one pass's segments over ``window`` (None if it does not cross it).

    ``model``/``params``: the vehicle model and the parameters the edge used for this pass (the
    calibration of its ``calib_version``). A pass must cover the span and at least ``min_cover_m``
    either side of it. Every axle of the pass is assembled (the correction acts on all contacts
    together); ``axle`` chooses the one returned. The wheel-load factor is low-passed at
    ``load_cutoff_hz`` (zero phase): above it the AP is mostly noise, and the beam does not follow
    such fast load changes anyway. ``params_log_sd``: the calibration's uncertainty (see
    :attr:`PassData.params_log_sd`).
    """
    system = vehicle_from_params(model, dict(params)).system()
    if edge.gamma is None:
        edge = dataclasses.replace(edge, gamma=edge_gamma(model))
    aps = {}
    for a in range(1, system.n_contacts + 1):
        ap = assemble_pass(segments, a)
        if ap is None:
            return None
        aps[a] = ap
    if correct:
        aps = correct_aps(aps, system, edge)
    ap = aps[axle]
    if abs(ap.spacing_m - window.spacing_m) > 1e-12:
        raise ValueError("extract_pass: the segments' grid differs from the window's")
    valid_x = ap.x[ap.valid]
    if valid_x.size == 0:
        return None
    if valid_x[0] > window.start_m - min_cover_m or valid_x[-1] < window.start_m + window.span_m + min_cover_m:
        return None
    # Dynamic wheel load from the whole pass (the forward model needs its run-up before the window).
    idx = np.flatnonzero(ap.valid)
    a, b = idx[0], idx[-1] + 1
    vals = np.interp(np.arange(a, b), idx, ap.values[idx])  # interior gaps bridged linearly
    filt = VehicleFilter(system, ap.speed_mps, ap.spacing_m)
    prof = np.zeros((b - a, system.n_contacts))
    prof[:, axle - 1] = vals  # other contacts: their own APs when present
    for other, ap_o in aps.items():
        if other != axle:
            io = np.flatnonzero(ap_o.valid)
            prof[:, other - 1] = np.interp(ap.x[a:b] - system.offsets_m[axle - 1] + system.offsets_m[other - 1],
                                           ap_o.x[io], ap_o.values[io])
    factor_pass = _low_pass(filt.load_factor(prof)[:, axle - 1], ap.speed_mps, ap.spacing_m, load_cutoff_hz)
    # Onto the window.
    out_vals = np.zeros(window.n)
    out_valid = np.zeros(window.n, dtype=bool)
    out_factor = np.ones(window.n)
    g = window.i0 + np.arange(window.n)  # global grid index of each window point
    j = g - ap.start_index
    inside = (j >= a) & (j < b)
    out_vals[inside] = vals[j[inside] - a]
    out_valid[inside] = ap.valid[j[inside]]
    out_factor[inside] = factor_pass[j[inside] - a]
    sig = float(np.median(ap.sigma[ap.valid]))
    log_sd = None if not params_log_sd else {str(k): float(v) for k, v in params_log_sd.items() if v > 0}
    return PassData(window, ap.vehicle_id, ap.pass_id, axle, model, dict(params), ap.speed_mps, out_vals,
                    out_valid, out_factor, sig, log_sd or None)


# ---------------------------------------------------------------------------------------------
# 5. The consensus over the window, and the per-pass deflection on the span


@dataclasses.dataclass(frozen=True, eq=False)
class Reference:
    """Sum and count of the passes' APs at each window point (the consensus is their mean)."""

    window: Window
    total: np.ndarray
    count: np.ndarray

    @classmethod
    def of(cls, passes: Sequence[PassData]) -> "Reference":
        if not passes:
            raise ValueError("Reference.of: no passes")
        w = passes[0].window
        total = np.zeros(w.n)
        count = np.zeros(w.n)
        for p in passes:
            total += np.where(p.valid, p.ap, 0.0)
            count += p.valid
        return cls(w, total, count)

    def mean(self, leave_out: PassData | None = None) -> np.ndarray:
        """The consensus AP (m), optionally without ``leave_out``; NaN where no pass is valid."""
        total, count = self.total, self.count
        if leave_out is not None:
            total = total - np.where(leave_out.valid, leave_out.ap, 0.0)
            count = count - leave_out.valid
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def consensus_used(p: PassData, ref: Reference, smooth_deck: bool = True, leave_out: bool = True) -> np.ndarray:
    """The consensus AP that :func:`residual` subtracts from ``p`` (m, window grid): 0 on the span
    of a smooth deck, NaN where no other pass has data."""
    r = ref.mean(p if leave_out else None)
    if smooth_deck:
        r = np.where(p.window.on_span, 0.0, r)
    return r


#: the largest share of the other passes that may drop out of a pass's consensus before its end: the
#: consensus then averages a subset and jumps by that share of the subset's difference in drift trend
CONSENSUS_DROPOUT = 0.1


def consensus_end(p: PassData, ref: Reference, leave_out: bool = True) -> int:
    """The last window index of ``p`` at which its consensus still averages (nearly) the same passes
    as on the rest of ``p``: passes end at staggered points (the edge drops the last grid points a
    pass's anti-alias window cuts, a speed-dependent count), and where more than
    :data:`CONSENSUS_DROPOUT` of them have ended the consensus is the mean of the longer ones only,
    and its second difference jumps there. One pass that ends early does not cut the others (it
    moves the consensus by 1/n of its own drift)."""
    valid = np.flatnonzero(p.valid)
    first, last = int(valid[0]), int(valid[-1])
    count = ref.count - p.valid if leave_out else ref.count
    inside = count[first : last + 1]
    ok = np.flatnonzero(p.valid[first : last + 1] & (inside >= (1.0 - CONSENSUS_DROPOUT) * inside.max()))
    return first + int(ok[-1]) if ok.size else last


def residual(p: PassData, ref: Reference, smooth_deck: bool = True, leave_out: bool = True) -> np.ndarray:
    """AP − consensus on the window (m): the consensus is taken as 0 on the span of a smooth deck
    (the deck profile is then known; only the drift-control trend of the consensus remains, which
    the estimators carry as a smooth nuisance). Points without data are filled linearly."""
    r = consensus_used(p, ref, smooth_deck, leave_out)
    res = p.ap - r
    ok = p.valid & np.isfinite(res)
    if ok.sum() < 2:
        raise ValueError("residual: the pass has no overlap with the consensus")
    idx = np.flatnonzero(ok)
    return np.interp(np.arange(res.size), idx, res[idx])


@dataclasses.dataclass(frozen=True, eq=False)
class SpanProfile:
    """A pass's deflection estimate on the span grid (m, up positive) and its noise sd (m)."""

    x_m: np.ndarray  # distance from the first support
    y_m: np.ndarray
    sigma_m: float
    load_factor: np.ndarray


def span_profile(p: PassData, ref: Reference, margin_m: float = 15.0, leave_out: bool = True,
                 common: np.ndarray | None = None, smooth_deck: bool = True) -> SpanProfile:
    """Drift control of one pass's deflection: fit offset + slope to AP − consensus on the
    ``margin_m`` either side of the span (excluding it), subtract it, and return the span part.

    ``common`` (window-length, m) is subtracted from AP − consensus first: what all passes share
    that is not deflection — on a smooth deck the consensus' own drift-control trend, a step of up
    to millimetres at the supports that no per-pass line can remove; on a rough deck the consensus'
    fleet-mean deflection (with a minus sign). The estimators fit it (``μ``); without it the result
    is only right where the consensus carries no trend. The noise sd is that of the margins.
    """
    w = p.window
    x = w.x
    res = residual(p, ref, smooth_deck=smooth_deck, leave_out=leave_out)
    if common is not None:
        res = res - np.asarray(common, dtype=float)
    margins = ((x >= -margin_m) & (x < 0)) | ((x > w.span_m) & (x <= w.span_m + margin_m))
    margins &= p.valid
    if margins.sum() < 10:
        raise ValueError("span_profile: margins have too few valid points")
    A = np.column_stack([np.ones(margins.sum()), x[margins]])
    coef, *_ = np.linalg.lstsq(A, res[margins], rcond=None)
    line = coef[0] + coef[1] * x
    sigma = float(np.std(res[margins] - line[margins]))
    on = w.on_span
    return SpanProfile(x[on], (res - line)[on], sigma, p.load_factor[on])


# ---------------------------------------------------------------------------------------------
# 6. The wheel-load factor without the pass's own noise


def road_load_factor(p: PassData, road_m: np.ndarray, deflection_m: np.ndarray | None = None,
                     load_cutoff_hz: float = LOAD_CUTOFF_HZ) -> np.ndarray:
    """``1 + φ`` on the window (n,) as the pass's vehicle (its calibrated ratios, its speed) would feel
    it driving over ``road_m`` (window grid, m, up positive, NaN-free) and its own deflection under it.

    :func:`extract_pass` computes ``φ̂`` from the pass's own AP, so it carries the pass's AP noise —
    the very noise the load term ``W·(1 + φ)·J`` is then regressed against: an errors-in-variables
    bias (spurious free-element gain, the bridge read soft). Driven over what the cloud knows
    instead — the fleet's leave-one-out consensus road (:func:`~cloud.bridge.whitening.driven_road`) —
    φ holds the other passes' noise only, averaged down by their number and independent of this
    pass's.

    ``deflection_m`` (window grid, m, down positive): the deflection under the pass's *static* wheel
    load at each position of the wheel (e.g. W̄·J(x; θ), zero off the span), if the road does not
    already hold it (a smooth deck's consensus is taken flat on the span). The wheel rides over
    ``road − (1 + φ)·deflection``: φ from the static deflection first, then once more with it (the
    factor changes the deflection by φ itself, a few per cent). The forward model starts from static
    equilibrium at the window's start (the window's approach is several of the body's decay times
    long). Single-contact vehicles.
    """
    filt = p.vehicle_filter()
    if filt.system.n_contacts != 1:
        raise ValueError(f"road_load_factor: single-contact vehicles only, {p.model} has {filt.system.n_contacts}")
    road = np.asarray(road_m, dtype=float)
    if road.shape != (p.window.n,) or not np.all(np.isfinite(road)):
        raise ValueError(f"road_load_factor: the road must be finite on the window ({p.window.n},), got {road.shape}")
    factor = np.ones(p.window.n)
    for _ in range(1 if deflection_m is None else 2):
        driven = road if deflection_m is None else road - factor * np.asarray(deflection_m, dtype=float)
        factor = _low_pass(filt.load_factor(driven)[:, 0], p.speed_mps, p.window.spacing_m, load_cutoff_hz)
    return factor
