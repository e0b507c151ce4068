"""Scoring estimates against a simulation's truth (for the demo summary, tests and reports only)."""

from __future__ import annotations

import collections
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
from scipy.signal import butter, sosfiltfilt

from cloud.road.alignment import FINE_BAND_M, estimate_alignment
from cloud.road.calibration import to_calibration
from cloud.road.long_wave import less_local_line
from edge.drift import local_linear_trend
from edge.pipeline import EdgeConfig
from shared.roughness import iri_segments


@dataclass(frozen=True)
class ProfileScore:
    rel_error: float  # std of band-passed (estimate − truth) / std of band-passed truth
    coverage: float  # fraction of grid points whose 95 % band holds the truth (+ a level and slope per 300 m)
    n_points: int
    max_passes: int


def band_pass(x: np.ndarray, spacing_m: float, lo_m: float = 0.5, hi_m: float = 50.0) -> np.ndarray:
    """Zero-phase band-pass to wavelengths lo_m..hi_m (4th-order Butterworth, forward-backward)."""
    sos = butter(4, [1.0 / hi_m, 1.0 / lo_m], btype="band", fs=1.0 / spacing_m, output="sos")
    return sosfiltfilt(sos, x)


def score_profile(export_dir: Path, truth: dict, trim_m: float = 10.0, fit_frame: bool = False) -> ProfileScore:
    """Profile error as the project's accuracy targets define it: both band-passed to 0.5–50 m, ends trimmed.

    ``fit_frame``: first map the truth into the estimate's chainage frame by one global shift and
    stretch. With per-pass GNSS bias and odometry scale errors and no surveyed reference, the fleet's
    mean frame is all the data define (it is off by ~sd/√passes), just as the absolute level is.
    """
    t = pq.read_table(Path(export_dir) / "profile.parquet").to_pydict()
    route = truth["route"]["id"]
    rows = [i for i, r in enumerate(t["route_id"]) if r == route]
    x = np.asarray(t["chainage_m"])[rows]
    est = np.asarray(t["elevation_m"])[rows]
    lo = np.asarray(t["lo95_m"])[rows]
    hi = np.asarray(t["hi95_m"])[rows]
    npass = np.asarray(t["n_passes"])[rows]
    p = truth["profile"]
    h = p["spacing_m"]
    tx = p["start_m"] + h * np.arange(len(p["elevation_m"]))
    true = np.interp(x, tx, p["elevation_m"])
    if fit_frame:
        # The frame that fits inside the scored band (the cloud's last step fits above wheel hop,
        # where the fused profile's phase against the truth is a few mm off: 3x the 2-5 m error).
        al = estimate_alignment(x, est, x, true, max_shift_m=3.0, max_stretch=0.02, refine_band_m=FINE_BAND_M)
        if al is not None:
            true = np.interp(al.x_ref_m + (x - al.x_ref_m - al.shift_m) / (1.0 + al.stretch), tx, p["elevation_m"])
    # Score the longest stretch on a regular grid (points without any pass are not exported).
    gaps = np.flatnonzero(np.diff(x) > 1.5 * h)
    bounds = np.split(np.arange(x.size), gaps + 1)
    seg = max(bounds, key=len)
    k = int(round(trim_m / h))
    a = band_pass(est[seg], h)[k:-k]
    b = band_pass(true[seg], h)[k:-k]
    rel = float(np.std(a - b) / np.std(b))
    # The band's estimand: the road up to a level and slope over the drift control's window (the
    # cloud restores what the edges' drift control removed: cloud.road.long_wave.removed_trend).
    d = est[seg] - true[seg]
    t_seg = est[seg] - less_local_line(d, 2 * EdgeConfig().drift_points + 1)
    inside = (t_seg >= lo[seg]) & (t_seg <= hi[seg])
    return ProfileScore(rel, float(np.mean(inside[k:-k])), int(a.size), int(npass.max(initial=0)))


def pass_extents(n_passes: np.ndarray) -> list[tuple[int, int]]:
    """The index ranges ``[a, b)`` of the passes that add up to a pass count per point.

    Every pass covers one contiguous stretch, so a pass starts wherever the count rises and ends
    wherever it falls; starts are paired with ends in order (first in, first out).
    """
    d = np.diff(np.concatenate([[0], np.asarray(n_passes, dtype=np.int64), [0]]))
    starts = np.repeat(np.arange(d.size), np.maximum(d, 0))
    ends = np.repeat(np.arange(d.size), np.maximum(-d, 0))
    return list(zip(starts.tolist(), ends.tolist()))


def drift_controlled_truth(true: np.ndarray, n_passes: np.ndarray) -> np.ndarray:
    """The estimand of the exported profile and its band (up to a constant level).

    Each pass's AP is drift-controlled on the edge: its own ±``drift_half_width_m`` local linear
    trend, fitted over the stretch that pass covers, is removed (:mod:`edge.drift`). What a pass
    measures of the road is therefore ``R − T_p R``, ``T_p`` that trend over the pass's own
    stretch; near a route's ends, where passes start and stop at different points, the ``T_p``
    differ. The fused profile estimates their average over the passes covering each point, which is
    what this returns (the trend at full resolution, the ideal the edge's lattice approximates).
    Pass stretches are recovered from the exported ``n_passes`` (:func:`pass_extents`).
    """
    H = EdgeConfig().drift_points
    total = np.zeros(true.size)
    count = np.zeros(true.size)
    for (a, b), m in collections.Counter(pass_extents(n_passes)).items():
        part = true[a:b]
        total[a:b] += m * (part - local_linear_trend(part, np.ones(part.size, dtype=np.bool_), H))
        count[a:b] += m
    has = count > 0
    if not has.any():
        return true - local_linear_trend(true, np.ones(true.size, dtype=np.bool_), H)
    out = np.empty(true.size)
    out[has] = total[has] / count[has]
    i = np.arange(true.size)
    out[~has] = np.interp(i[~has], i[has], out[has])  # gaps the prior bridges: no pass defines them
    return out


def load_truth(path: Path) -> dict:
    return json.loads(Path(path).read_text())


def score_vehicles(export_dir: Path, truth: dict) -> dict[str, tuple[float, float]]:
    """Per calibrated quantity: (median, max) relative error of the exported means against truth."""
    t = pq.read_table(Path(export_dir) / "vehicles.parquet").to_pydict()
    model = truth["vehicle_model"]
    errs: dict[str, list[float]] = {}
    for vid, param, mean in zip(t["vehicle_id"], t["param"], t["mean"]):
        true = to_calibration(model, truth["vehicles"][vid])[param]
        errs.setdefault(param, []).append(abs(mean / true - 1.0))
    return {p: (float(np.median(e)), float(np.max(e))) for p, e in errs.items()}


@dataclass(frozen=True)
class IriScore:
    median_rel_error: float  # over the scored segments: |exported IRI / truth's IRI − 1|
    max_rel_error: float
    coverage: float  # fraction of segments whose exported 95 % band holds the truth's IRI
    n_segments: int


def score_iri(export_dir: Path, truth: dict, length_m: float = 100.0, trim_m: float = 0.0) -> IriScore:
    """The exported IRI per ``length_m`` segment against the IRI of the true profile on the same segments.

    The truth's IRI is computed by the same Golden-Car code on the simulation's profile (the tyre-
    filtered surface the fleet drove). Segments within ``trim_m`` of the route's ends are left out,
    as for the profile score. The IRI is a slope statistic and blind to the absolute level and
    linear trend, so no frame or offset is fitted.
    """
    t = pq.read_table(Path(export_dir) / "roughness.parquet").to_pydict()
    route = truth["route"]["id"]
    rows = [i for i, (r, L) in enumerate(zip(t["route_id"], t["length_m"])) if r == route and L == length_m]
    start = np.asarray(t["start_m"])[rows]
    end = np.asarray(t["end_m"])[rows]
    est = np.asarray(t["iri_m_per_km"])[rows]
    lo = np.asarray(t["iri_lo95"])[rows]
    hi = np.asarray(t["iri_hi95"])[rows]
    p = truth["profile"]
    tx = p["start_m"] + p["spacing_m"] * np.arange(len(p["elevation_m"]))
    ty = np.asarray(p["elevation_m"])
    if start.size:  # over the stretch the exported profile covers (its segments' bounds): the same run-up
        on = (tx >= start.min() - 1e-6) & (tx <= end.max() + 1e-6)
        tx, ty = tx[on], ty[on]
    ts, te, tv = iri_segments(tx, ty, length_m)
    length = truth["route"]["length_m"]
    keep = (start >= trim_m - 1e-9) & (end <= length - trim_m + 1e-9) & (end - start >= 0.99 * length_m)
    j = np.clip(np.searchsorted(ts, start - 1e-6), 0, ts.size - 1)
    keep &= np.isclose(ts[j], start) & np.isclose(te[j], end) & np.isfinite(est)  # the same segment
    true = tv[j]
    rel = np.abs(est[keep] / true[keep] - 1.0)
    inside = (true[keep] >= lo[keep]) & (true[keep] <= hi[keep])
    if not rel.size:
        raise ValueError(f"{export_dir}: no {length_m:g} m roughness segment to score")
    return IriScore(float(np.median(rel)), float(rel.max()), float(inside.mean()), int(rel.size))
