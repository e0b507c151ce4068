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

What the band covers: the road less each pass's ±150 m drift trend (over the stretch that pass
covers), averaged over the passes, up to a constant level (:func:`simfleet.evaluate.drift_controlled_truth`).
Errors every pass shares (a calibration bias common to the fleet, the inverse's discretisation)
do not show in the scatter and are not in this term.

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

import dataclasses
import math

import numpy as np
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
                         drift: tuple[float, float] | None = None) -> ProfileSnapshot:
    """``snap`` with :func:`pass_error_variance` added to the variance of its 95 % band."""
    sd_post = (snap.hi95_m - snap.lo95_m) / (2 * _Z95)
    sd = np.sqrt(sd_post**2 + pass_error_variance(snap, segments, longest=longest, drift=drift))
    return dataclasses.replace(snap, lo95_m=snap.elevation_m - _Z95 * sd, hi95_m=snap.elevation_m + _Z95 * sd)


with_long_wave_band = with_pass_error_band  # the former name (it only looked at >10 m)
