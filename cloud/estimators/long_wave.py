"""The long-wavelength part of the profile's uncertainty, from the scatter between passes.

Each pass's AP keeps a little integration drift at wavelengths of tens of metres after the edge's
drift control; the banded posterior treats per-point errors as independent and so cannot see it.
The scatter of the passes' smoothed residuals about the consensus measures it directly: its
variance over the number of passes is the variance of the consensus's long-wave error, which is
added to the posterior variance of the band.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from shared.schema import ApSegment

from .mean_profile import ProfileSnapshot


def _moving_average(x: np.ndarray, valid: np.ndarray, width: int) -> np.ndarray:
    c = np.concatenate([[0.0], np.cumsum(np.where(valid, x, 0.0))])
    k = np.concatenate([[0], np.cumsum(valid)])
    i = np.arange(x.size)
    lo = np.clip(i - width // 2, 0, x.size)
    hi = np.clip(i + width // 2 + 1, 0, x.size)
    n = k[hi] - k[lo]
    return np.where(n > 0, (c[hi] - c[lo]) / np.maximum(n, 1), 0.0)


def with_long_wave_band(snap: ProfileSnapshot, segments: list[ApSegment], window_m: float = 10.0) -> ProfileSnapshot:
    """``snap`` with its 95 % band widened by the between-pass long-wave scatter."""
    P = snap.elevation_m.size
    h = float(snap.chainage_m[1] - snap.chainage_m[0]) if P > 1 else 1.0
    passes: dict[tuple, list[ApSegment]] = {}
    for s in segments:
        if s.route_id == snap.route_id:
            passes.setdefault((s.vehicle_id, s.pass_id, s.axle), []).append(s)
    ss = np.zeros(P)
    n = np.zeros(P)
    for segs in passes.values():
        lo = max(min(s.start_index for s in segs), 0)
        hi = min(max(s.end_index for s in segs), P)
        if hi - lo < 3:
            continue
        r = np.full(hi - lo, np.nan)
        for s in segs:
            a, b = max(s.start_index, lo), min(s.end_index, hi)
            if b > a:
                r[a - lo : b - lo] = s.values[a - s.start_index : b - s.start_index]
        r = r - snap.elevation_m[lo:hi]
        ok = np.isfinite(r)
        if ok.sum() < 3:
            continue
        lp = _moving_average(r, ok, max(int(round(window_m / h)), 1))
        ss[lo:hi] += np.where(ok, lp * lp, 0.0)
        n[lo:hi] += ok
    var_lw = np.where(n > 1, ss / np.maximum(n * (n - 1), 1.0), 0.0)
    sd_post = (snap.hi95_m - snap.lo95_m) / (2 * 1.96)
    sd = np.sqrt(sd_post**2 + var_lw)
    return dataclasses.replace(snap, lo95_m=snap.elevation_m - 1.96 * sd, hi95_m=snap.elevation_m + 1.96 * sd)
