"""GNSS error: align each pass in chainage against the consensus before it is fused.

A pass's reported chainage carries a constant bias (GNSS) and a stretch (the speed/odometry scale
error): x_reported = x_ref + b + (1 + ε)(x_true − x_ref). The pass's AP is compared with the
consensus of the *other* passes in a band of wavelengths both resolve (1–30 m); (b, ε) maximise
their correlation (a grid over ε, cross-correlation over b, parabolic refinement). The fleet's
biases average to zero, so the estimated shifts are centred across passes: the consensus frame
is the fleet's mean frame, not the first pass's.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.signal import butter, sosfiltfilt

from shared.schema import ApSegment

BAND_M = (1.0, 30.0)


@dataclasses.dataclass(frozen=True)
class Alignment:
    shift_m: float  # b: reported − true chainage at x_ref
    stretch: float  # ε: relative scale error of the reported chainage
    x_ref_m: float
    score: float  # correlation at the optimum (0..1)

    def true_to_reported(self, x_true: np.ndarray) -> np.ndarray:
        return self.x_ref_m + self.shift_m + (1.0 + self.stretch) * (x_true - self.x_ref_m)


def _band(x: np.ndarray, spacing: float) -> np.ndarray:
    sos = butter(2, [1.0 / BAND_M[1], 1.0 / BAND_M[0]], btype="band", fs=1.0 / spacing, output="sos")
    return sosfiltfilt(sos, x)


def estimate_alignment(x_rep: np.ndarray, ap: np.ndarray, x_cons: np.ndarray, cons: np.ndarray,
                       max_shift_m: float = 10.0, max_stretch: float = 0.06,
                       stretch_step: float = 0.002) -> Alignment | None:
    """(b, ε) of a pass's AP (on its reported grid ``x_rep``) against the consensus ``cons``."""
    ok = np.isfinite(ap)
    okc = np.isfinite(cons)
    if ok.sum() < 400 or okc.sum() < 400:
        return None
    h = float(x_cons[1] - x_cons[0])
    x_rep, ap = x_rep[ok], ap[ok]
    x_ref = float(x_rep[0])
    xc, c = x_cons[okc], cons[okc]
    c_band = _band(c, h)
    lags = int(round(max_shift_m / h))

    def best_shift(eps: float) -> tuple[float, float]:
        """(correlation, b) of the best shift for stretch ``eps``."""
        # The pass's AP on the consensus grid if the true chainage were x: ap(x_ref + (1+ε)(x−x_ref)).
        x_true = x_ref + (x_rep - x_ref) / (1.0 + eps)
        lo, hi = max(x_true[0], xc[0]), min(x_true[-1], xc[-1])
        sel = (xc >= lo) & (xc <= hi)
        if sel.sum() < 400:
            return -np.inf, 0.0
        a = _band(np.interp(xc[sel], x_true, ap), h)
        b = c_band[sel]
        n = a.size
        # Correlation over lags: at lag k the consensus at x + k·h matches the pass at x.
        full = np.correlate(b, a, mode="full")[n - 1 - lags : n + lags]
        norm = np.sqrt(np.sum(a * a) * np.sum(b * b)) + 1e-30
        k = int(np.argmax(full))
        frac = 0.0
        if 0 < k < full.size - 1:
            y0, y1, y2 = full[k - 1], full[k], full[k + 1]
            den = y0 - 2 * y1 + y2
            frac = 0.5 * (y0 - y2) / den if den != 0 else 0.0
        return float(full[k] / norm), -((k - lags) + frac) * h

    grid = np.arange(-max_stretch, max_stretch + 1e-12, stretch_step)
    scores = np.array([best_shift(e)[0] for e in grid])
    if not np.isfinite(scores).any():
        return None
    i = int(np.argmax(scores))
    eps = float(grid[i])
    if 0 < i < grid.size - 1 and np.all(np.isfinite(scores[i - 1 : i + 2])):
        y0, y1, y2 = scores[i - 1 : i + 2]
        den = y0 - 2 * y1 + y2
        if den < 0:
            eps += 0.5 * (y0 - y2) / den * stretch_step
    score, b = best_shift(eps)
    return Alignment(shift_m=float(b), stretch=float(eps), x_ref_m=x_ref, score=float(score))


def realign(segments: list[ApSegment], al: Alignment) -> list[ApSegment]:
    """The pass's segments re-gridded to true chainage (same identities, values interpolated)."""
    out = []
    for seg in segments:
        h = seg.spacing_m
        x_rep = seg.chainage_m
        x_true_first = al.x_ref_m + (x_rep[0] - al.x_ref_m - al.shift_m) / (1.0 + al.stretch)
        x_true_last = al.x_ref_m + (x_rep[-1] - al.x_ref_m - al.shift_m) / (1.0 + al.stretch)
        i0, i1 = int(np.ceil(x_true_first / h)), int(np.floor(x_true_last / h))
        if i1 - i0 < 1 or i0 < 0:
            i0 = max(i0, 0)
            if i1 - i0 < 1:
                continue
        xg = np.arange(i0, i1 + 1) * h
        xr = al.true_to_reported(xg)
        vals = np.interp(xr, x_rep, seg.values)
        sig = np.interp(xr, x_rep, seg.sigma)
        out.append(ApSegment.make(vals, sig, vehicle_id=seg.vehicle_id, pass_id=seg.pass_id, route_id=seg.route_id,
                                  tile=seg.tile, axle=seg.axle, start_index=i0, spacing_m=h,
                                  calib_version=seg.calib_version, speed_mps=seg.speed_mps, t_first=seg.t_first,
                                  t_last=seg.t_last, seq=seg.seq, flags=seg.flags))
    return out
