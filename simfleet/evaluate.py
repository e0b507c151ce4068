"""Scoring estimates against a simulation's truth (for the demo summary, tests and reports only)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
from scipy.signal import butter, sosfiltfilt


@dataclass(frozen=True)
class ProfileScore:
    rel_error: float  # std of band-passed (estimate − truth) / std of band-passed truth
    coverage: float  # fraction of grid points whose 95 % band holds the truth (offset removed)
    n_points: int
    max_passes: int


def band_pass(x: np.ndarray, spacing_m: float, lo_m: float = 0.5, hi_m: float = 50.0) -> np.ndarray:
    """Zero-phase band-pass to wavelengths lo_m..hi_m (4th-order Butterworth, forward-backward)."""
    sos = butter(4, [1.0 / hi_m, 1.0 / lo_m], btype="band", fs=1.0 / spacing_m, output="sos")
    return sosfiltfilt(sos, x)


def score_profile(export_dir: Path, truth: dict, trim_m: float = 10.0, fit_frame: bool = False) -> ProfileScore:
    """Profile error as the issues define it: both band-passed to 0.5–50 m, ends trimmed.

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
        from cloud.alignment import estimate_alignment

        al = estimate_alignment(x, est, x, true, max_shift_m=3.0, max_stretch=0.02, stretch_step=0.0005)
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
    # Coverage of the estimand: the edge's drift control removes each pass's ±150 m local linear
    # trend, so the profile is known relative to that trend (and up to a constant level).
    from edge.drift import drift_trend
    from edge.pipeline import EdgeConfig

    cfg = EdgeConfig()
    t_seg = true[seg] - drift_trend(true[seg], np.ones(len(seg), bool), cfg.drift_points)
    off = float(np.mean(est[seg] - t_seg))
    inside = (t_seg + off >= lo[seg]) & (t_seg + off <= hi[seg])
    return ProfileScore(rel, float(np.mean(inside[k:-k])), int(a.size), int(npass.max(initial=0)))


def load_truth(path: Path) -> dict:
    return json.loads(Path(path).read_text())


def score_vehicles(export_dir: Path, truth: dict) -> dict[str, tuple[float, float]]:
    """Per calibrated quantity: (median, max) relative error of the exported means against truth."""
    from cloud.calibration import to_calibration

    t = pq.read_table(Path(export_dir) / "vehicles.parquet").to_pydict()
    model = truth["vehicle_model"]
    errs: dict[str, list[float]] = {}
    for vid, param, mean in zip(t["vehicle_id"], t["param"], t["mean"]):
        true = to_calibration(model, truth["vehicles"][vid])[param]
        errs.setdefault(param, []).append(abs(mean / true - 1.0))
    return {p: (float(np.median(e)), float(np.max(e))) for p, e in errs.items()}
