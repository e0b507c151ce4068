"""Track geometry quality from a rail route's fused apparent profile: longitudinal level in the
EN 13848 D1 wavelength band (3–25 m), its standard deviation per 200 m and the largest |D1|, and
isolated defects against alert limits.

Pure functions on arrays (no I/O). The band-pass is zero-phase (forward–backward Butterworth, as
track recording cars post-process), applied along the regular chainage grid; gaps (NaN) split the
profile into stretches that are filtered on their own, and points within one long wavelength of a
stretch's ends are left out of the statistics (the filter's edge effect).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.signal import butter, sosfiltfilt

D1_BAND_M = (3.0, 25.0)
SEGMENT_M = 200.0
#: Alert limits (mm) for lines of 80 < V <= 120 km/h, within the ranges EN 13848-5 leaves to the
#: infrastructure manager: an isolated defect's |D1| (mean to peak) and the sd per 200 m.
ALERT_ISOLATED_MM = 8.0
ALERT_SD_MM = 1.8


@dataclasses.dataclass(frozen=True)
class QualitySegment:
    start_m: float
    end_m: float
    sd_d1_mm: float  # NaN when the segment has too few valid points
    max_abs_d1_mm: float
    n_points: int


def d1_longitudinal_level(elevation_m: np.ndarray, spacing_m: float, band_m: tuple[float, float] = D1_BAND_M,
                          edge_m: float | None = None) -> np.ndarray:
    """The D1 longitudinal level (m) of a profile on a regular grid; NaN where undefined (gaps,
    stretch ends, stretches shorter than twice the edge)."""
    z = np.asarray(elevation_m, dtype=float)
    if spacing_m <= 0 or not (0 < band_m[0] < band_m[1]):
        raise ValueError("d1_longitudinal_level: need spacing_m > 0 and 0 < band[0] < band[1]")
    nyq = 0.5 / spacing_m  # cycles per m
    lo, hi = 1.0 / band_m[1], 1.0 / band_m[0]
    if hi >= nyq:
        raise ValueError(f"d1_longitudinal_level: grid spacing {spacing_m} m cannot resolve {band_m[0]} m waves")
    sos = butter(4, [lo / nyq, hi / nyq], btype="bandpass", output="sos")
    edge = band_m[1] if edge_m is None else edge_m
    n_edge = int(np.ceil(edge / spacing_m))
    out = np.full(z.shape, np.nan)
    ok = np.isfinite(z)
    idx = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
    for a, b in zip(idx[::2], idx[1::2]):
        if b - a <= 2 * n_edge + 8:
            continue
        seg = z[a:b] - np.polyval(np.polyfit(np.arange(b - a), z[a:b], 1), np.arange(b - a))
        f = sosfiltfilt(sos, seg, padtype="even")
        out[a + n_edge:b - n_edge] = f[n_edge:len(f) - n_edge]
    return out


def segment_quality(chainage_m: np.ndarray, d1_m: np.ndarray, segment_m: float = SEGMENT_M,
                    min_fraction: float = 0.25) -> list[QualitySegment]:
    """Standard deviation and max |D1| (mm) per consecutive ``segment_m`` from chainage 0 (the last
    one may be shorter); NaN where fewer than ``min_fraction`` of a segment's points are valid."""
    x = np.asarray(chainage_m, float)
    d = np.asarray(d1_m, float)
    if x.size == 0:
        return []
    spacing = float(np.median(np.diff(x))) if x.size > 1 else 1.0
    out = []
    end = float(x.max())
    start = 0.0
    while start < end - 1e-9:
        stop = min(start + segment_m, end)
        sel = (x >= start) & (x < stop if stop < end else x <= stop)
        v = d[sel]
        v = v[np.isfinite(v)]
        expected = max((stop - start) / spacing, 1.0)
        if v.size >= max(8, min_fraction * expected):
            out.append(QualitySegment(start, stop, 1e3 * float(np.std(v)), 1e3 * float(np.abs(v).max()), int(v.size)))
        else:
            out.append(QualitySegment(start, stop, float("nan"), float("nan"), int(v.size)))
        start += segment_m
    return out


def isolated_defects(chainage_m: np.ndarray, d1_m: np.ndarray, limit_mm: float) -> list[tuple[float, float]]:
    """(chainage m, D1 mm) of each local extreme of |D1| above ``limit_mm`` (one per exceedance run)."""
    x = np.asarray(chainage_m, float)
    a = 1e3 * np.abs(np.nan_to_num(np.asarray(d1_m, float), nan=0.0))
    over = a > limit_mm
    out = []
    idx = np.flatnonzero(np.diff(np.concatenate([[0], over.astype(np.int8), [0]])))
    for s, e in zip(idx[::2], idx[1::2]):
        k = s + int(np.argmax(a[s:e]))
        out.append((float(x[k]), float(1e3 * d1_m[k])))
    return out
