"""The part of the profile's uncertainty the white-noise likelihood cannot see, from the passes' disagreement.

The banded posterior (:mod:`.gmrf_profile`) treats each pass's AP error as white with the level
the edge measured from the AP's second differences. The real error is not white: sensor noise
integrated twice drifts at wavelengths of tens of metres (what the edge's ±150 m drift control
leaves of it), the inverse amplifies it at short ones, and a vehicle's calibration error filters
the road itself, mostly at 1–30 m. Each of these is independent from pass to pass, so the passes'
disagreement measures it: per wavelength band ``j`` (differences of moving averages of the
residuals ``r_p = y_p − μ``), the scatter of the band's residuals about the consensus estimates
the per-pass error variance ``v_j(x)`` at every point. What exceeds the white model's own share
of that band, ``σ_p² g_j``, is error the posterior ignored; averaged over the passes with the
likelihood's weights ``w_p = 1/σ_p²`` it adds ``(v_j − σ̄² g_j)₊ · Σw²/(Σw)²`` to the variance of
the fused profile. Bands are kept apart so that a band where the white model is pessimistic (the
inverse's noise is blue, not white, at 0.5–10 m) does not cancel one where it is optimistic.

The level is pooled along the route over the longest band edge (it changes over the drift-control
scale, not faster), and since it is estimated from a finite number ``ν`` of degrees of freedom
(``n − 1`` passes times the independent stretches pooled) the fused error it describes is
Student-t, not normal: its variance is scaled by ``(t_ν,0.975 / 1.96)²`` so that mean ± 1.96 sd is
a 95 % band — a factor that matters with a handful of passes and fades (→ 1) as passes arrive.
With one pass there is no scatter and no term.

What the passes measure, and the scatter band covers: the road less each pass's ±150 m drift
trend (over the stretch that pass covers), averaged over the passes, up to a constant level
(:func:`simfleet.evaluate.drift_controlled_truth`). Errors every pass shares (a calibration bias
common to the fleet, the inverse's discretisation) do not show in the scatter and are not in this
term. One of them is known: the drift control itself took the road's long waves out of every pass
alike. :func:`removed_trend` restores them from the consensus where the trend operator leaves
enough of them to invert (a Neumann series in the known operator, its first left-out term added to
the band), so that the exported mean and band (``restore_trend``) are of the road up to a level and
a slope over the drift control's window, which no pass measures.

With the per-pass drift nuisance on (:mod:`.pass_drift`, ``drift = (sd, knot_m)``) the posterior's
band already holds each pass's drift as a homogeneous process of the learnt level; each band's
model share then includes that drift's (:func:`drift_band_shares`), the longest band included, so
that only what the passes' scatter shows beyond it — where the drift is locally larger than the
route-wide level, or shaped otherwise than the knots' hats — is added (not the drift twice).

Draws (:func:`pass_error_draws`): whatever is computed from posterior draws (the IRI and its band)
must carry this term too. Its variance alone does not say how it moves the IRI: a calibration error
scales the road (first order in the IRI), sensor noise adds to it (second order). So per band the
passes' residuals are also regressed on the consensus's band; the scatter of those gains is drawn
as a gain on the road's band, the rest of the band's variance as band-limited noise.

Cost: computed at snapshot time from the segments held, O(points held × bands); nothing is added
to a segment update, and a retracted segment is simply not among those held.
"""

from __future__ import annotations

import collections
import dataclasses
import math

import numpy as np
from scipy.ndimage import correlate1d
from scipy.signal import butter, sosfiltfilt
from scipy.stats import t as student_t

from shared.schema import ApSegment

from cloud.road.gmrf_profile import error_band_shares
from cloud.road.mean_profile import ProfileSnapshot

#: Band edges (m): wavelengths below the first are the white model's (the prior smooths them).
BAND_EDGES_M = (0.5, 2.0, 10.0, 50.0)
_Z95 = 1.959963984540054


def _moving_average(x: np.ndarray, valid: np.ndarray, width: int) -> np.ndarray:
    """Centred mean over ``width`` points of the valid entries (0 where none)."""
    c = np.concatenate([[0.0], np.cumsum(np.where(valid, x, 0.0))])
    k = np.concatenate([[0], np.cumsum(valid)])
    i = np.arange(x.size)
    lo = np.clip(i - width // 2, 0, x.size)
    hi = np.clip(i + width // 2 + 1, 0, x.size)
    n = k[hi] - k[lo]
    return np.where(n > 0, (c[hi] - c[lo]) / np.maximum(n, 1), 0.0)


def _white_share(widths: list[int]) -> list[float]:
    """Variance of each band of unit white noise: band j is ``MA_{a_j} − MA_{a_{j+1}}`` (the last
    ``MA_{a_last}`` itself); for nested centred means ``cov(MA_a, MA_b) = 1/b`` (a ≤ b), so the
    band's variance is ``1/a − 1/b``."""
    out = [1.0 / a - 1.0 / b for a, b in zip(widths[:-1], widths[1:])]
    out.append(1.0 / widths[-1])
    return out


def drift_band_shares(knot_m: float, spacing_m: float, widths: list[int]) -> np.ndarray:
    """Variance, per unit drift variance ``s²``, of each moving-average band (as :func:`band_error_variances`
    cuts them) of a drift ``Σ_k β_k φ_k(x)`` with independent ``β_k ~ N(0, s²)`` on linear hats at
    knots every ``knot_m`` (:mod:`.pass_drift`'s model), averaged over the position between knots."""
    key = (float(knot_m), float(spacing_m), tuple(widths))
    hit = _DRIFT_SHARES.get(key)
    if hit is None:
        knot_pts = knot_m / spacing_m
        pad = max(widths) + int(math.ceil(2 * knot_pts))
        n_knots = 4
        x = (np.arange(-pad, int(math.ceil(n_knots * knot_pts)) + pad) / knot_pts)  # in knots
        mid = (x >= 1.0) & (x < 2.0)  # one knot period, far from the lattice's ends
        every = np.ones(x.size, dtype=bool)
        out = np.zeros(len(widths))
        for k in range(int(math.floor(x[0])) - 1, int(math.ceil(x[-1])) + 2):
            hat = np.clip(1.0 - np.abs(x - k), 0.0, None)
            if not hat.any():
                continue
            mas = [_moving_average(hat, every, w) for w in widths]
            for j in range(len(widths)):
                band = mas[j] - mas[j + 1] if j + 1 < len(widths) else mas[j]
                out[j] += float(np.mean(band[mid] ** 2))
        _DRIFT_SHARES[key] = hit = out
    return hit


_DRIFT_SHARES: dict = {}


def drift_of(profile, route_id: str) -> tuple[float, float] | None:
    """``(sd_m, knot_m)`` of the per-pass drift nuisance a profile estimator holds for a route (after
    its snapshot), or None when it models none: the ``drift`` argument of this module's functions."""
    knot = getattr(profile, "drift_knot_m", None)
    return None if knot is None else (float(profile.drift_sd[route_id]), float(knot))


def _pass_residuals(snap: ProfileSnapshot, segments: list[ApSegment]):
    """Each pass's ``(lo, hi, r, ok, sigma)``: its residual ``y − μ`` on grid points ``[lo, hi)``, where
    it counts (finite, and not flagged unreliable by the edge) and its stated sd."""
    P = snap.elevation_m.size
    mu = snap.elevation_m
    passes: dict[tuple, list[ApSegment]] = {}
    for s in segments:
        if s.route_id == snap.route_id:
            passes.setdefault((s.vehicle_id, s.pass_id, s.axle), []).append(s)
    # Passes by key and each pass's segments by position, not in the order they arrived: the sums over
    # passes and the segment whose error model stands for the pass are then the same whatever the
    # run's history (a re-sent pass, a retraction and re-add) — exact replays.
    for key in sorted(passes):
        segs = sorted(passes[key], key=lambda s: (s.start_index, s.end_index))
        lo = max(min(s.start_index for s in segs), 0)
        hi = min(max(s.end_index for s in segs), P)
        if hi - lo < 3:
            continue
        y = np.full(hi - lo, np.nan)
        sig = np.full(hi - lo, np.nan)
        for s in segs:
            a, b = max(s.start_index, lo), min(s.end_index, hi)
            if b > a:
                y[a - lo : b - lo] = s.values[a - s.start_index : b - s.start_index]
                sig[a - lo : b - lo] = s.sigma[a - s.start_index : b - s.start_index]
        r = y - mu[lo:hi]
        ok = np.isfinite(r)
        if ok.sum() < 3:
            continue
        # Points the edge flagged unreliable carry ~no weight in the posterior: not in the scatter.
        ok &= sig <= 10.0 * np.nanmin(sig)
        yield lo, hi, r, ok, sig, segs[len(segs) // 2].error_model  # (the edge's, or empty: white)


def pass_error_variance(snap: ProfileSnapshot, segments: list[ApSegment],
                        band_edges_m: tuple[float, ...] = BAND_EDGES_M, longest: bool = True,
                        drift: tuple[float, float] | None = None) -> np.ndarray:
    """Variance (m²) per grid point of the fused profile's error that the white likelihood misses.

    ``longest``: also the band beyond the last edge (> 50 m). Pass False when the posterior
    models those wavelengths itself and nothing of them is to be added. ``drift``: ``(sd_m, knot_m)``
    of the per-pass drift nuisance the posterior holds (:mod:`.pass_drift`): its share of every band
    counts as modelled, so only the scatter beyond it is added (with the longest band).
    """
    return band_error_variances(snap, segments, band_edges_m, longest, drift).sum(axis=0)


def band_error_variances(snap: ProfileSnapshot, segments: list[ApSegment],
                         band_edges_m: tuple[float, ...] = BAND_EDGES_M, longest: bool = True,
                         drift: tuple[float, float] | None = None) -> np.ndarray:
    """:func:`pass_error_variance` band by band: (bands, P), the band beyond the last edge last
    (zero unless ``longest``)."""
    P = snap.elevation_m.size
    h = float(snap.chainage_m[1] - snap.chainage_m[0]) if P > 1 else 1.0
    widths = [max(int(round(e / h)) | 1, 1) for e in band_edges_m]  # odd: centred
    nb = len(widths)
    # The drift nuisance's per-pass variance in each band (0 without it): modelled, like the white share.
    dshare = (drift[0] ** 2 * drift_band_shares(drift[1], h, widths) if drift is not None and drift[0] > 0
              else np.zeros(nb))
    ss = np.zeros((nb, P))  # Σ_p band residual²
    n = np.zeros(P)  # passes with a residual at the point
    sw = np.zeros(P)  # Σ_p w_p
    sw2 = np.zeros(P)  # Σ_p w_p²
    ssig = np.zeros((nb, P))  # Σ_p σ_p² × the pass's own error model's share of the band (white: g)
    for lo, hi, r, ok, sig, em in _pass_residuals(snap, segments):
        mas = [_moving_average(r, ok, w) for w in widths]
        for j in range(nb):
            band = mas[j] - mas[j + 1] if j + 1 < nb else mas[j]
            ss[j, lo:hi] += np.where(ok, band * band, 0.0)
        w = np.where(ok, 1.0 / np.where(ok, sig, 1.0) ** 2, 0.0)
        n[lo:hi] += ok
        sw[lo:hi] += w
        sw2[lo:hi] += w * w
        ssig[:, lo:hi] += (np.where(ok, sig * sig, 0.0) * error_band_shares(em, widths)[:, None]
                           + np.where(ok, 1.0, 0.0) * dshare[:, None])
    var = np.zeros((nb, P))
    many = n > 1
    if not many.any():
        return var
    eff = np.where(many, sw2 / np.where(many, sw * sw, 1.0), 0.0)  # 1 / effective number of passes
    sig2 = np.where(many, ssig / np.maximum(n, 1), 0.0)
    pool = widths[-1]
    for j in range(nb if longest else nb - 1):
        # The residual scatter about the consensus has n − 1 degrees of freedom per independent
        # stretch; it is pooled along the route over the longest band edge (the error's level
        # changes over the drift-control scale, not faster), which holds about pool / (band's
        # longest wavelength) independent stretches of the band.
        v = np.where(many, ss[j] / np.maximum(n - 1, 1), 0.0)
        v = _moving_average(v, many, pool)
        excess = np.maximum(v - sig2[j], 0.0)
        # An error variance estimated from ν degrees of freedom: the error is Student-t, not normal;
        # its 95 % point is reached by scaling the variance with (t_ν,0.975 / z_0.975)².
        top = widths[j + 1] if j + 1 < nb else 2 * widths[j]
        nu = np.maximum(n - 1, 1) * max(pool / top, 1.0)
        nus, inv = np.unique(nu, return_inverse=True)  # few distinct values; ppf is slow
        var[j] = np.where(many, excess * eff * ((student_t.ppf(0.975, nus) / _Z95) ** 2)[inv.reshape(nu.shape)], 0.0)
    return var


def _road_bands(mu: np.ndarray, widths: list[int]) -> np.ndarray:
    """The consensus ``μ`` split into the bands (bands, P) as residuals are (0 where μ is NaN)."""
    ok = np.isfinite(mu)
    x = np.where(ok, mu, 0.0)
    mas = [_moving_average(x, ok, w) for w in widths]
    return np.array([mas[j] - mas[j + 1] if j + 1 < len(mas) else mas[j] for j in range(len(mas))]) * ok


def band_gain_covariance(snap: ProfileSnapshot, segments: list[ApSegment],
                         band_edges_m: tuple[float, ...] = BAND_EDGES_M) -> tuple[np.ndarray, np.ndarray]:
    """The part of the passes' disagreement that moves with the road: per band, each pass's residual
    regressed on the consensus's band, ``ε_p = Σ r_p m / Σ m²`` (a calibration error scales the road
    it filters; sensor noise does not). Returns the covariance (bands, bands) of the fused profile's
    gain errors (the ε's sample covariance over the passes — a vehicle's transfer error is smooth
    in wavelength, so neighbouring bands' gains go together — times the effective ``1/n`` of the
    likelihood's weights and the Student-t factor of ``n − 1`` degrees of freedom) and the
    consensus's bands ``m`` (bands, P)."""
    P = snap.elevation_m.size
    h = float(snap.chainage_m[1] - snap.chainage_m[0]) if P > 1 else 1.0
    widths = [max(int(round(e / h)) | 1, 1) for e in band_edges_m]
    m = _road_bands(snap.elevation_m, widths)
    eps, wts = [], []
    for lo, hi, r, ok, sig, _ in _pass_residuals(snap, segments):
        mas = [_moving_average(r, ok, w) for w in widths]
        e = np.zeros(len(widths))
        for j in range(len(widths)):
            band = mas[j] - mas[j + 1] if j + 1 < len(widths) else mas[j]
            mm = np.where(ok, m[j, lo:hi], 0.0)
            den = float((mm * mm).sum())
            e[j] = float((np.where(ok, band, 0.0) * mm).sum()) / den if den > 0 else 0.0
        eps.append(e)
        wts.append(float(np.mean(1.0 / sig[ok] ** 2)))
    if len(eps) < 2:
        return np.zeros((len(widths), len(widths))), m
    eps, w = np.array(eps), np.array(wts)
    k = eps.shape[0]
    t2 = (student_t.ppf(0.975, k - 1) / _Z95) ** 2
    return np.cov(eps, rowvar=False, ddof=1) * float((w * w).sum() / w.sum() ** 2) * t2, m


def pass_error_draws(snap: ProfileSnapshot, segments: list[ApSegment], n: int,
                     rng: np.random.Generator | int | None = None, band_edges_m: tuple[float, ...] = BAND_EDGES_M,
                     longest: bool = True, drift: tuple[float, float] | None = None) -> np.ndarray:
    """``n`` draws (n, P) of the error :func:`pass_error_variance` describes, to add to posterior
    draws so that what is computed from them (the IRI) carries the band's every error term.

    Band by band, the error's variance is split as the passes show it (:func:`band_gain_variances`):
    the part that moves with the road is drawn as a gain on the consensus's band (one factor per
    draw: a calibration error scales the road, and that moves the IRI to first order, where
    independent noise of the same size hardly does); the rest as white noise filtered as the band
    was measured (difference of centred moving averages), scaled to that variance at each point.
    The bands are drawn independently. NaN where the snapshot has no profile.
    """
    rng = np.random.default_rng(rng)
    P = snap.elevation_m.size
    v = band_error_variances(snap, segments, band_edges_m, longest, drift)
    gcov, m = band_gain_covariance(snap, segments, band_edges_m)
    gvar = np.diag(gcov)
    sd = np.sqrt(np.where(gvar > 0, gvar, 1.0))
    corr = gcov / np.outer(sd, sd)
    lam, vec = np.linalg.eigh(corr)  # correlated unit gains, one set per draw
    zg = rng.standard_normal((int(n), lam.size)) @ (vec * np.sqrt(np.clip(lam, 0.0, None))).T
    h = float(snap.chainage_m[1] - snap.chainage_m[0]) if P > 1 else 1.0
    widths = [max(int(round(e / h)) | 1, 1) for e in band_edges_m]
    g = _white_share(widths)
    out = np.zeros((int(n), P))
    pad = widths[-1]  # noise beyond the ends, so that the filters are whole at every point
    every = np.ones(P + 2 * pad, dtype=bool)
    for j in range(len(widths)):
        if not v[j].any():
            continue
        # The gain part: one factor per draw scaling the road's band, so the error keeps the road's
        # shape (largest where the road is rough); its level pooled as the excess is, and at most it.
        level = gvar[j] * _moving_average(m[j] ** 2, every[:P], widths[-1])
        f = np.where(level > v[j], v[j] / np.where(level > 0, level, 1.0), 1.0)
        out += zg[:, j : j + 1] * (np.sqrt(f * gvar[j]) * m[j])[None, :]
        sd = np.sqrt(np.maximum(v[j] - f * level, 0.0) / g[j])
        for r in range(out.shape[0]):
            z = rng.standard_normal(P + 2 * pad)
            band = _moving_average(z, every, widths[j])
            if j + 1 < len(widths):
                band -= _moving_average(z, every, widths[j + 1])
            out[r] += sd * band[pad : pad + P]
    out[:, ~np.isfinite(snap.elevation_m)] = np.nan
    return out


def with_pass_error_band(snap: ProfileSnapshot, segments: list[ApSegment], longest: bool = True,
                         drift: tuple[float, float] | None = None, restore_trend: bool = False) -> ProfileSnapshot:
    """``snap`` with :func:`pass_error_variance` added to the variance of its 95 % band; with
    ``restore_trend`` then also what the edges' drift control removed (:func:`with_removed_trend`),
    so that mean and band are of the road up to a level and slope."""
    sd_post = (snap.hi95_m - snap.lo95_m) / (2 * _Z95)
    var = sd_post**2 + pass_error_variance(snap, segments, longest=longest, drift=drift)
    sd = np.sqrt(var)
    out = dataclasses.replace(snap, lo95_m=snap.elevation_m - _Z95 * sd, hi95_m=snap.elevation_m + _Z95 * sd)
    # (after the passes' scatter: their residuals are about the drift-controlled consensus they measure)
    return with_removed_trend(out, segments) if restore_trend else out



# -- what the edges' drift control removed -------------------------------------------------------

#: Half-width (m) of the edge's drift control (``EdgeConfig.drift_half_width_m``'s default): every
#: pass's AP has its own local linear trend over ±this removed before it is sent.
DRIFT_HALF_WIDTH_M = 150.0
#: Lattice step (m) the removed trend is restored on: it lives at wavelengths of fifty metres and
#: more, which a metre lattice resolves at a thousandth of the grid's cost.
TREND_STEP_M = 1.0
#: Most terms of the series :func:`removed_trend` sums for its remainder, and the largest ratio of
#: successive terms it still sums and extrapolates the tail with: a slower one is a wave the trend
#: keeps nearly whole, which the data do not give back (its tail, up to ten times the next term).
TREND_TERMS = 12
TREND_RATIO_MAX = 0.9
#: m: what the first term leaves out is counted at wavelengths beyond this only (zero-phase
#: low-pass). The waves the trend takes mostly everywhere are longer than its half-width; shorter
#: ones it takes mostly only near a pass's ends (a one-sided window follows them), where the series'
#: further terms are mostly the consensus's own error amplified, which the band holds already.
TREND_LONG_M = 100.0


def _lowpass_stretches(y: np.ndarray, edges: np.ndarray, step_m: float) -> np.ndarray:
    """``y`` low-passed (zero phase) beyond :data:`TREND_LONG_M` on each covered stretch."""
    out = np.zeros_like(y)
    sos = butter(2, step_m / TREND_LONG_M * 2.0, output="sos")
    for a, b in zip(edges[::2], edges[1::2]):
        if b - a < 8:
            out[a:b] = y[a:b]
            continue
        out[a:b] = sosfiltfilt(sos, y[a:b], padlen=min(b - a - 1, int(TREND_LONG_M / step_m)), padtype="even")
    return out


def _pass_extents(snap: ProfileSnapshot, segments: list[ApSegment]) -> list[tuple[int, int]]:
    """Each pass's ``[lo, hi)`` on the route grid (one per vehicle, pass and axle), sorted."""
    P = snap.elevation_m.size
    ext: dict[tuple, list[int]] = {}
    for s in segments:
        if s.route_id == snap.route_id:
            e = ext.setdefault((s.vehicle_id, s.pass_id, s.axle), [P, 0])
            e[0], e[1] = min(e[0], max(s.start_index, 0)), max(e[1], min(s.end_index, P))
    return sorted((a, b) for a, b in ext.values() if b > a)


def _local_linear_trend(y: np.ndarray, valid: np.ndarray, half: int) -> np.ndarray:
    """The edge's drift trend of ``y`` (:func:`edge.drift.local_linear_trend`, vectorised): at every
    point the intercept of the line fitted with triangular weights ``1 − |d|/(half + 1)`` to the valid
    points within ``±half``."""
    d = np.arange(-half, half + 1, dtype=float)
    w = 1.0 - np.abs(d) / (half + 1.0)
    v = valid.astype(float)
    s0, s1, s2 = (correlate1d(v, w * d**p, mode="constant") for p in range(3))
    yv = np.where(valid, y, 0.0)
    t0 = correlate1d(yv, w, mode="constant")
    t1 = correlate1d(yv, w * d, mode="constant")
    det = s0 * s2 - s1 * s1
    line = det > 1e-12 * s0 * s0
    flat = t0 / np.where(s0 > 0, s0, 1.0)
    return np.where(line, (s2 * t0 - s1 * t1) / np.where(line, det, 1.0), flat)


def less_local_line(y: np.ndarray, window: int) -> np.ndarray:
    """``y`` less, at every point, the least-squares line through the ``window`` points around it
    (centred, moved inwards at the ends; all of them when fewer) evaluated there."""
    n = y.size
    window = min(window, n)
    i = np.arange(n)
    a = np.clip(i - window // 2, 0, n - window)
    b = a + window
    x = (i - (n - 1) / 2.0) / max(n, 1)  # centred and scaled: the sums stay well conditioned

    def cum(v):
        return np.concatenate([[0.0], np.cumsum(v)])

    cx, cxx, cy, cxy = cum(x), cum(x * x), cum(y), cum(x * y)
    m = float(window)
    sx, sxx, sy, sxy = cx[b] - cx[a], cxx[b] - cxx[a], cy[b] - cy[a], cxy[b] - cxy[a]
    det = m * sxx - sx * sx
    ok = det > 1e-15
    slope = np.where(ok, (m * sxy - sx * sy) / np.where(ok, det, 1.0), 0.0)
    return y - ((sy - slope * sx) / m + slope * x)


def removed_trend(snap: ProfileSnapshot, segments: list[ApSegment], half_width_m: float = DRIFT_HALF_WIDTH_M,
                  step_m: float = TREND_STEP_M) -> tuple[np.ndarray, np.ndarray]:
    """The road's long waves the edges' drift control took out, estimated from the consensus, and
    the size of what that estimate leaves: ``(restore, remainder)`` (m) per grid point.

    Each pass measures the road less its own local linear trend over ±``half_width_m`` (over the
    stretch it covers), so the consensus is ``μ ≈ (I − T̄)R``, ``T̄`` the average of the passes' trend
    operators at a point. Every pass shares that loss, so their scatter cannot show it; but ``T̄`` is
    known, and ``R = Σ_k T̄ᵏ μ`` wherever the series converges. A level and slope over
    ``2·half_width_m`` (or over a shorter covered stretch) are what the data cannot give (``T̄`` keeps
    them whole), so every term is taken less its line over that window. ``restore = T̄μ`` is the
    first term. Further terms would restore more of the waves the trend takes mostly (eigenvalue λ
    near 1 — on a route not much longer than the window, its curvature), but they multiply the
    consensus's own long-wave error by as much (``Σ λᵏ``), and its band would have to grow with it;
    so they go to the band instead: ``remainder`` is everything the first term leaves out, the terms
    after it while they shrink (at most :data:`TREND_TERMS`) and their geometric tail ``T̄^{K+1}μ / (1 − ρ)``
    (``ρ`` the last ratio of successive terms' sizes, at most :data:`TREND_RATIO_MAX`), beyond
    :data:`TREND_LONG_M` — one term left ``λ²/(1 − λ)`` of such a wave out, of which ``T̄²μ`` is
    ``λ²``. Computed on a lattice of ``step_m`` (the consensus averaged over it) and interpolated;
    zero where no pass has been.
    """
    P = snap.elevation_m.size
    restore, remainder = np.zeros(P), np.zeros(P)
    ext = _pass_extents(snap, segments)
    if not ext or half_width_m <= 0 or P < 2:
        return restore, remainder
    h = float(snap.chainage_m[1] - snap.chainage_m[0])
    k = max(1, int(round(step_m / h)))
    half = max(1, int(round(half_width_m / (k * h))))
    mu = snap.elevation_m
    ok = np.isfinite(mu)
    # The consensus on the lattice: the mean of each lattice cell's valid points.
    n = (P + k - 1) // k
    pad = n * k - P
    cells_ok = np.concatenate([ok, np.zeros(pad, dtype=bool)]).reshape(n, k)
    cells = np.concatenate([np.where(ok, mu, 0.0), np.zeros(pad)]).reshape(n, k)
    cnt = cells_ok.sum(axis=1)
    valid = cnt > 0
    v = np.where(valid, cells.sum(axis=1) / np.maximum(cnt, 1), 0.0)
    spans = collections.Counter((a // k, min((b - 1) // k + 1, n)) for a, b in ext)

    def mean_trend(y):
        total, count = np.zeros(n), np.zeros(n)
        for (a, b), m in spans.items():
            if b - a >= 2:
                total[a:b] += m * _local_linear_trend(y[a:b], valid[a:b], half)
                count[a:b] += m
        return np.where(count > 0, total / np.maximum(count, 1), 0.0), count > 0

    t, covered = mean_trend(v)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], covered.astype(np.int8), [0]])))

    def less_line(y):
        out = np.zeros(n)
        for a, b in zip(edges[::2], edges[1::2]):  # each contiguous covered stretch
            out[a:b] = less_local_line(y[a:b], 2 * half + 1)
        return out

    term = less_line(t)
    first = term
    total = np.zeros(n)  # the terms summed (the first included)
    size = float(np.sqrt(np.mean(term[covered] ** 2))) if covered.any() else 0.0
    ratio = 0.0
    for _ in range(TREND_TERMS):
        total += term
        t = mean_trend(t)[0]
        nxt = less_line(t)
        nxt_size = float(np.sqrt(np.mean(nxt[covered] ** 2))) if covered.any() else 0.0
        ratio = nxt_size / size if size > 0 else 0.0
        term, size = nxt, nxt_size
        if ratio > TREND_RATIO_MAX or size == 0.0:  # no longer converging (or nothing left): stop here
            break
    # Every term after the first, with the geometric tail, is what one term leaves out: the band's.
    left_out = _lowpass_stretches(total - first + term / (1.0 - min(ratio, TREND_RATIO_MAX)), edges, k * h)
    centre = (np.arange(n) + 0.5) * k - 0.5  # each cell's centre on the grid
    xi = np.arange(P)
    restore = np.where(ok, np.interp(xi, centre, first), 0.0)
    remainder = np.where(ok, np.interp(xi, centre, left_out), 0.0)
    return restore, remainder


def with_removed_trend(snap: ProfileSnapshot, segments: list[ApSegment],
                       half_width_m: float = DRIFT_HALF_WIDTH_M) -> ProfileSnapshot:
    """``snap`` with :func:`removed_trend` restored to its mean and its remainder added (as an sd) to
    its band: the band then holds the road up to a level and slope (over ``2·half_width_m``), not
    the drift-controlled profile the passes measure."""
    restore, remainder = removed_trend(snap, segments, half_width_m)
    sd = np.sqrt(((snap.hi95_m - snap.lo95_m) / (2 * _Z95)) ** 2 + remainder**2)
    mean = snap.elevation_m + restore
    return dataclasses.replace(snap, elevation_m=mean, lo95_m=mean - _Z95 * sd, hi95_m=mean + _Z95 * sd)


with_long_wave_band = with_pass_error_band  # the former name (it only looked at >10 m)
