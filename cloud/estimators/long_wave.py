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

Cost: computed at snapshot time from the segments held, O(points held × bands); nothing is added
to a segment update, and a retracted segment is simply not among those held.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.stats import t as student_t

from shared.schema import ApSegment

from .mean_profile import ProfileSnapshot

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


def pass_error_variance(snap: ProfileSnapshot, segments: list[ApSegment],
                        band_edges_m: tuple[float, ...] = BAND_EDGES_M, longest: bool = True) -> np.ndarray:
    """Variance (m²) per grid point of the fused profile's error that the white likelihood misses.

    ``longest``: also the band beyond the last edge (> 50 m). Pass False when the posterior
    models those wavelengths itself (the per-pass drift nuisance of :mod:`.pass_drift`, knots at
    ≤ 25 m), so that they are not counted twice.
    """
    P = snap.elevation_m.size
    h = float(snap.chainage_m[1] - snap.chainage_m[0]) if P > 1 else 1.0
    widths = [max(int(round(e / h)) | 1, 1) for e in band_edges_m]  # odd: centred
    g = _white_share(widths)
    nb = len(widths)
    passes: dict[tuple, list[ApSegment]] = {}
    for s in segments:
        if s.route_id == snap.route_id:
            passes.setdefault((s.vehicle_id, s.pass_id, s.axle), []).append(s)
    ss = np.zeros((nb, P))  # Σ_p band residual²
    n = np.zeros(P)  # passes with a residual at the point
    sw = np.zeros(P)  # Σ_p w_p
    sw2 = np.zeros(P)  # Σ_p w_p²
    ssig = np.zeros(P)  # Σ_p σ_p²
    mu = snap.elevation_m
    for segs in passes.values():
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
        mas = [_moving_average(r, ok, w) for w in widths]
        for j in range(nb):
            band = mas[j] - mas[j + 1] if j + 1 < nb else mas[j]
            ss[j, lo:hi] += np.where(ok, band * band, 0.0)
        w = np.where(ok, 1.0 / np.where(ok, sig, 1.0) ** 2, 0.0)
        n[lo:hi] += ok
        sw[lo:hi] += w
        sw2[lo:hi] += w * w
        ssig[lo:hi] += np.where(ok, sig * sig, 0.0)
    var = np.zeros(P)
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
        excess = np.maximum(v - sig2 * g[j], 0.0)
        # An error variance estimated from ν degrees of freedom: the error is Student-t, not normal;
        # its 95 % point is reached by scaling the variance with (t_ν,0.975 / z_0.975)².
        top = widths[j + 1] if j + 1 < nb else 2 * widths[j]
        nu = np.maximum(n - 1, 1) * max(pool / top, 1.0)
        nus, inv = np.unique(nu, return_inverse=True)  # few distinct values; ppf is slow
        var += excess * eff * ((student_t.ppf(0.975, nus) / _Z95) ** 2)[inv.reshape(nu.shape)]
    return np.where(many, var, 0.0)


def with_pass_error_band(snap: ProfileSnapshot, segments: list[ApSegment], longest: bool = True) -> ProfileSnapshot:
    """``snap`` with :func:`pass_error_variance` added to the variance of its 95 % band."""
    sd_post = (snap.hi95_m - snap.lo95_m) / (2 * _Z95)
    sd = np.sqrt(sd_post**2 + pass_error_variance(snap, segments, longest=longest))
    return dataclasses.replace(snap, lo95_m=snap.elevation_m - _Z95 * sd, hi95_m=snap.elevation_m + _Z95 * sd)


with_long_wave_band = with_pass_error_band  # the former name (it only looked at >10 m)
