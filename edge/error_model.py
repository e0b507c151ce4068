"""The AP's error model: each channel's sensor noise pushed through the inverse's own transfer.

Why: the AP error is not white. The half-car's inverse differentiates its pitch-rate channel, so
its error is 10–40× larger (in power) at wavelengths under 0.5 m than at 1–20 m; the quarter-car's
body acceleration is integrated, so its error grows again at long wavelengths. A white σ measured
from second differences is set by the shortest wavelengths and tells the cloud that every
wavelength is as noisy as those, which shrinks the fused profile toward the prior everywhere.

How:
1. Each channel's noise level is measured from the data (:func:`channel_noise_sd`): the vehicle's
   response has no content near the sample rate's Nyquist, so fourth differences of a channel are
   its noise (for white noise their variance is 70 σ²); the MAD makes it robust.
2. The inverse is linear, so the AP error is the sum over channels of σ_c² times the channel's unit
   transfer. That transfer depends only on the inverse (vehicle model, parameters, dt) and, through
   the chainage gridding, on the speed: :func:`unit_spectra` runs the inverse on synthetic unit
   white noise, grids it at the speed and drift-controls it as a pass is, and takes the spectrum on
   the grid (cached per inverse and speed bucket; a few tens of ms each).
3. :func:`fit_error_band` fits a stationary Gaussian process whose precision is banded: its
   spectral density is ``1 / P(ω)`` with ``P(ω) = c₀ + 2 Σ_{k=1..p} c_k cos kω`` (ω in radians per
   grid step), so on ``m`` points its precision is the banded Toeplitz matrix ``c_{|i−j|}`` —
   the cloud adds it in O(m p), exactly retractable. The fit is least squares on the relative
   misfit ``P·S − 1`` over log-spaced bands (each octave counts alike), reweighted so that it
   approaches the log misfit, over wavelengths from the grid's Nyquist to ``longest_m`` (50 m).
   Where the inverse integrates (a body accelerometer), the error spectrum has a valley: it rises
   again toward long wavelengths (twice-integrated noise, 50× up from 10 m to 50 m for the
   quarter-car), which a low-order band cannot follow. The spectrum is therefore first filled up
   to its mean level over ``longest_m/2.5 … longest_m`` (:func:`filled_spectrum`), but not above
   the white level the AP's own second differences show (the segment's own ``sigma``): the model is
   then conservative in the valley rather than over-confident at long
   wavelengths, and never more pessimistic than the white model. (An over-confident long-wave
   level per pass weighs the passes against each other by a number the model does not know, and
   the fused profile is worse than with the white model.) Where
   the inverse differentiates (the half-car's pitch rate) there is no valley and nothing changes;
   where the body accelerometer is all (a quarter-car) the fill gives back the white model.
   Beyond ``longest_m`` the cloud's drift nuisance / long-wave band cover the rest.
4. The AP itself bounds the model from below: if its second differences (what the white ``sigma``
   measures) are larger than the model's own, something besides sensor noise is there (the
   inverse's discretisation, quantisation, road content), and the model is scaled up to match
   (:func:`white_equivalent`).

The result is sent per segment as ``ApSegment.error_model = [r, c₀, …, c_p]``: the band of the
unit-variance process and the ratio ``r`` of the model's marginal sd to the segment's ``sigma``
(see :func:`encode_error_model`).
"""

from __future__ import annotations

import math
from collections import OrderedDict

import numpy as np
from scipy.signal import welch

from shared.dynamics.inverse import InverseModel, InverseStream
from shared.jit import kernel

from .drift import drift_trend

#: Fourth differences of white noise: var(Δ⁴w) = C(8, 4) σ² = 70 σ².
_D4_VAR = 70.0
_MAD = 1.4826  # MAD → sd for a Gaussian
#: Default order of the precision band and the longest wavelength (m) the fit follows.
BAND_ORDER = 4
LONGEST_M = 50.0
#: The long-wave level the spectrum is filled up to is its mean over wavelengths longest_m / this … longest_m.
_FILL_SPAN = 2.5
#: Unit-noise simulation: length (s) and the relative width of a speed bucket.
_UNIT_SECONDS = 120.0
_SPEED_BUCKET = 0.02
_N_BANDS = 40
_CACHE: OrderedDict = OrderedDict()
_CACHE_SIZE = 512


def fourth_differences(z: np.ndarray) -> np.ndarray:
    """Fourth differences along axis 0 of (n, channels) samples: (n − 4, channels)."""
    return np.diff(np.asarray(z, dtype=np.float64), n=4, axis=0)


@kernel
def median_abs_deviations(x):
    """Each column's median absolute deviation from its median, of finite values (n ≥ 1, columns):
    ``np.median(np.abs(x - np.median(x, axis=0)), axis=0)``, the same numbers (a median selects an
    element, or averages the middle two as numpy does), without numpy's per-call overhead."""
    n, c = x.shape
    out = np.empty(c)
    col = np.empty(n)
    for j in range(c):
        for i in range(n):
            col[i] = x[i, j]
        med = np.median(col)
        for i in range(n):
            col[i] = abs(x[i, j] - med)
        out[j] = np.median(col)
    return out


def noise_sd_from_d4(d4: np.ndarray) -> np.ndarray:
    """Per channel white-noise sd from its fourth differences (n, channels): MAD-based, robust."""
    d4 = np.asarray(d4, dtype=np.float64)
    if d4.shape[0] == 0 or not np.isfinite(d4).all():  # numpy's NaN rules
        med = np.median(d4, axis=0)
        return _MAD * np.median(np.abs(d4 - med), axis=0) / math.sqrt(_D4_VAR)
    return _MAD * median_abs_deviations(d4) / math.sqrt(_D4_VAR)


def channel_noise_sd(z: np.ndarray) -> np.ndarray:
    """Each channel's white-noise sd (its units) measured from samples (n, channels), n ≥ 5."""
    return noise_sd_from_d4(fourth_differences(z))


_MODEL_KEYS: OrderedDict = OrderedDict()  # id(model) → (model, its key): a fleet's models hashed once each


def _model_key(model: InverseModel) -> tuple:
    hit = _MODEL_KEYS.get(id(model))
    if hit is not None and hit[0] is model:  # (the model is held, so its id is not reused meanwhile)
        return hit[1]
    arrays = (model.A, model.B, model.C, model.D)
    key = (hash(b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)), model.constants.dt, model.contact_rule)
    _MODEL_KEYS[id(model)] = (model, key)
    if len(_MODEL_KEYS) > _CACHE_SIZE:
        _MODEL_KEYS.popitem(last=False)
    return key


def speed_bucket(speed_mps: float) -> float:
    """The speed the unit spectra are computed at: ``speed`` rounded to a 2 % log bucket."""
    k = round(math.log(speed_mps) / math.log1p(_SPEED_BUCKET))
    return math.exp(k * math.log1p(_SPEED_BUCKET))


def unit_spectra(model: InverseModel, speed_mps: float, spacing_m: float, drift_points: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Spectrum on the grid of the AP error from unit white noise on each channel.

    Returns ``(omega, S)``: ``omega`` (rad per grid step, > 0) and ``S`` (channels, contacts,
    len(omega)) in m² per unit channel variance, normalised so that a process's variance is
    ``(1/π) ∫₀^π S dω``. Cached per inverse, speed bucket, spacing and drift half-width; the
    synthetic noise has a fixed seed, so the result is a deterministic function of those.
    """
    v = speed_bucket(max(speed_mps, 0.5))
    key = (_model_key(model), v, spacing_m, drift_points)
    hit = _CACHE.get(key)
    if hit is not None:
        _CACHE.move_to_end(key)
        return hit
    dt = model.constants.dt
    n_ch = len(model.system.channels)
    n_ct = model.system.n_contacts
    n = int(_UNIT_SECONDS / dt)
    warm = min(model.n_warmup + int(1.0 / dt), n // 4)
    x = v * dt * np.arange(n - warm)
    xg = np.arange(0.0, x[-1], spacing_m)
    nper = min(4096, 1 << int(math.floor(math.log2(max(xg.size // 8, 64)))))
    rng = np.random.default_rng(20261122)
    S = None
    for c in range(n_ch):
        z = np.zeros((n, n_ch))
        z[:, c] = rng.standard_normal(n)
        ap = InverseStream(model).update(z)[warm:]
        for i in range(n_ct):
            g = np.interp(xg, x, ap[:, i])
            if drift_points > 0:
                g = g - drift_trend(g, np.ones(g.size, dtype=bool), drift_points)
            f, G = welch(g, fs=1.0 / spacing_m, nperseg=nper, detrend="linear")
            if S is None:
                S = np.zeros((n_ch, n_ct, f.size - 1))
            S[c, i] = G[1:] * (0.5 / spacing_m)  # one-sided density per cycle/m → per rad/step
    omega = 2.0 * math.pi * f[1:] * spacing_m
    out = (omega, S)
    _CACHE[key] = out
    if len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return out


_UNIT_FITS: OrderedDict = OrderedDict()


def unit_error_band(model: InverseModel, speed_mps: float, spacing_m: float, drift_points: int, axle: int,
                    order: int = BAND_ORDER, longest_m: float = LONGEST_M) -> tuple[float, np.ndarray, float, float]:
    """The fit of a one-channel vehicle's error model at unit channel variance, once per inverse,
    speed bucket and axle: ``(sd, band, white, level)``, the fit's marginal sd and band
    (:func:`fit_error_band` without a fill ceiling), the :func:`white_equivalent` of the band at
    unit sd and the fill's long-wave level of the unit spectrum.

    Why once: with one channel the spectrum is ``σ² S`` and the fit is scale-equivariant — the band
    is the same for every σ and the sd scales with σ — as long as the fill's ceiling (the AP's own
    white level) lies above ``σ² · level``; a segment whose ceiling binds is fitted on its own. The
    results agree with a fit per segment up to rounding (the least squares solved at another scale).
    """
    v = speed_bucket(max(speed_mps, 0.5))
    key = (_model_key(model), v, spacing_m, drift_points, axle, order, longest_m)
    hit = _UNIT_FITS.get(key)
    if hit is not None:
        _UNIT_FITS.move_to_end(key)
        return hit
    omega, S = unit_spectra(model, speed_mps, spacing_m, drift_points)
    unit = S[0, axle - 1]
    long = _fit_grid(omega, spacing_m, longest_m)[2]
    level = float(np.mean(unit[long])) if long.any() else 0.0
    sd, band = fit_error_band(omega, unit, spacing_m, order, longest_m)
    out = (sd, band, white_equivalent(1.0, band), level)
    _UNIT_FITS[key] = out
    if len(_UNIT_FITS) > _CACHE_SIZE:
        _UNIT_FITS.popitem(last=False)
    return out


def band_symbol(band: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """``P(ω) = c₀ + 2 Σ c_k cos kω`` of a precision band ``c`` (its inverse is the spectral density)."""
    band = np.asarray(band, dtype=np.float64)
    out = np.full(np.shape(omega), band[0])
    for k in range(1, band.size):
        out = out + 2.0 * band[k] * np.cos(k * omega)
    return out


_OMEGA_CHECK = np.linspace(0.0, math.pi, 2049)
#: cos kω on the check grid for every order the edge fits (EdgeConfig allows up to 8): the symbol
#: there is then one small product, not an array of cosines per coefficient (it is evaluated a few
#: times per segment, for each of a fleet's segments).
_COS_CHECK = np.cos(np.outer(np.arange(9), _OMEGA_CHECK))
#: |2 − 2 cos ω|²: the power gain of a second difference.
_D2_GAIN = (2.0 - 2.0 * _COS_CHECK[1]) ** 2


def _check_symbol(band: np.ndarray) -> np.ndarray:
    """:func:`band_symbol` on ``_OMEGA_CHECK``."""
    band = np.asarray(band, dtype=np.float64)
    if band.size > _COS_CHECK.shape[0]:
        return band_symbol(band, _OMEGA_CHECK)
    return band[0] + 2.0 * (band[1:] @ _COS_CHECK[1 : band.size])


def band_variance(band: np.ndarray) -> float:
    """Marginal variance ``(1/π) ∫₀^π dω / P(ω)`` of the stationary process with precision band ``c``."""
    return float(np.trapezoid(1.0 / _check_symbol(band), _OMEGA_CHECK) / math.pi)


def filled_spectrum(omega: np.ndarray, S: np.ndarray, spacing_m: float, longest_m: float = LONGEST_M,
                    ceiling: float = math.inf) -> np.ndarray:
    """``max(S, min(S_L, ceiling))`` with ``S_L`` the mean of ``S`` over wavelengths
    ``longest_m / 2.5 … longest_m`` (the valley fill of the module docstring; ``ceiling`` in the
    units of ``S``, a white process's variance)."""
    return _fill(S, _fit_grid(omega, spacing_m, longest_m)[2], ceiling)


def _fill(S: np.ndarray, long: np.ndarray, ceiling: float) -> np.ndarray:
    if not long.any():
        return S
    return np.maximum(S, min(float(np.mean(S[long])), ceiling))


_FIT_GRIDS: OrderedDict = OrderedDict()


def _fit_grid(omega: np.ndarray, spacing_m: float, longest_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the fit needs of the frequencies alone, cached (the unit spectra of a fleet share a few
    grids): each frequency's log band (``_N_BANDS`` bands from ``longest_m`` to the grid's Nyquist;
    outside: < 0 or ≥ ``_N_BANDS``), the mask of those inside, and the fill's long-wave mask."""
    omega = np.asarray(omega, dtype=np.float64)
    key = (omega.tobytes(), spacing_m, longest_m)
    hit = _FIT_GRIDS.get(key)
    if hit is not None:
        return hit
    lam = 2.0 * math.pi * spacing_m / omega
    long = (lam >= longest_m / _FILL_SPAN) & (lam <= longest_m)
    w_min = 2.0 * math.pi * spacing_m / longest_m
    edges = np.geomspace(w_min, math.pi * (1 + 1e-12), _N_BANDS + 1)
    idx = np.searchsorted(edges, omega, side="right") - 1
    out = (idx, (idx >= 0) & (idx < _N_BANDS), long)
    for a in out:
        a.flags.writeable = False  # shared by every fit on this grid
    _FIT_GRIDS[key] = out
    if len(_FIT_GRIDS) > _CACHE_SIZE:
        _FIT_GRIDS.popitem(last=False)
    return out


def fit_error_band(omega: np.ndarray, S: np.ndarray, spacing_m: float, order: int = BAND_ORDER,
                   longest_m: float = LONGEST_M, fill_ceiling: float = math.inf) -> tuple[float, np.ndarray]:
    """Fit ``1/P(ω)`` to the spectrum ``S(ω)`` (see the module docstring); returns ``(sd, band)``.

    ``sd`` is the model's marginal sd (m) and ``band`` the precision band of the unit-variance
    process (``c·sd²``), positive definite (``P > 0`` on [0, π]); the order drops until it is
    (order 0: white at the spectrum's mean level in the fitted range). ``S`` is filled first
    (:func:`filled_spectrum`, up to ``fill_ceiling``).
    """
    idx, inside, long = _fit_grid(omega, spacing_m, longest_m)
    S = _fill(S, long, fill_ceiling)
    use = inside & (S > 0)
    counts = np.bincount(idx[use], minlength=_N_BANDS)
    sums = np.bincount(idx[use], weights=S[use], minlength=_N_BANDS)
    wsum = np.bincount(idx[use], weights=omega[use], minlength=_N_BANDS)
    have = counts > 0
    wc, Sc = wsum[have] / counts[have], sums[have] / counts[have]
    for p in range(order, -1, -1):
        X = np.column_stack([np.ones_like(wc)] + [2.0 * np.cos(k * wc) for k in range(1, p + 1)]) * Sc[:, None]
        weight = np.ones_like(wc)
        c = None
        for _ in range(6):  # reweighting: the relative misfit P·S − 1 tends to the log misfit
            c, *_ = np.linalg.lstsq(X * weight[:, None], weight, rcond=None)
            weight = 1.0 / np.maximum(X @ c, 1e-3)
        if c is not None and np.min(_check_symbol(c)) > 0:
            var = band_variance(c)
            return math.sqrt(var), c * var
    raise ArithmeticError("fit_error_band: no positive definite fit")  # p = 0 cannot fail with S > 0


def white_equivalent(sd_m: float, band: np.ndarray) -> float:
    """The white sd that the MAD of second differences (``edge.pipeline.ap_sigma``) reads on this
    model: ``sqrt(var(Δ²e) / 6)``, from ``(1/π) ∫ |2 − 2 cos ω|² S(ω) dω``."""
    var_d2 = np.trapezoid(_D2_GAIN * sd_m**2 / _check_symbol(band), _OMEGA_CHECK) / math.pi
    return math.sqrt(var_d2 / 6.0)


def encode_error_model(sd_m: float, band: np.ndarray, sigma_m: float) -> np.ndarray:
    """The wire form ``[sd/sigma, band…]``: the cloud's error sd at a point is ``r · sigma`` there."""
    return np.concatenate([[sd_m / sigma_m], np.asarray(band, dtype=np.float64)])
