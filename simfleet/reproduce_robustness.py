"""``driveby reproduce robustness``: the headline numbers on simfleet's world and on the second (ivp) world,
side by side, each with the coverage of its stated uncertainty.

Every case is simulated in both worlds from the same scenario and seed, run through the same
edge and cloud code (the in-process harness, default ``--calibration fleet``), and scored by the
same functions (:mod:`simfleet.evaluate` and those below).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from cloud.daemon.settings import CloudSettings
from cloud.road.calibration import to_calibration
from shared.drivelog import list_drive_logs, read_drive_log
from shared.registry import load_site

from . import sim
from .evaluate import load_truth, score_iri, score_profile
from .harness import run_in_process
from .scenarios import SCENARIOS
from .worlds import ivp

log = logging.getLogger(__name__)

WORLDS: dict[str, Callable[..., dict]] = {"simfleet": sim.generate, "ivp": ivp.generate}


@dataclasses.dataclass(frozen=True)
class VehicleScore:
    """Per calibrated ratio: median |error| over the fleet, and the share of 95 % intervals holding the truth."""

    median_error: dict[str, float]
    coverage: dict[str, float]
    mean_signed_error: dict[str, float]  # the fleet-common part of the error


def score_vehicle_intervals(export_dir: Path, truth: dict) -> VehicleScore:
    """The exported ratios (``vehicles.parquet``) against each vehicle's true ratios."""
    t = pq.read_table(Path(export_dir) / "vehicles.parquet").to_pydict()
    model = truth["vehicle_model"]
    errs: dict[str, list[float]] = {}
    inside: dict[str, list[bool]] = {}
    for vid, param, mean, lo, hi in zip(t["vehicle_id"], t["param"], t["mean"], t["lo95"], t["hi95"]):
        if vid not in truth["vehicles"]:
            continue
        true = to_calibration(model, truth["vehicles"][vid])[param]
        errs.setdefault(param, []).append(mean / true - 1.0)
        inside.setdefault(param, []).append(bool(lo <= true <= hi))
    return VehicleScore({p: float(np.median(np.abs(e))) for p, e in errs.items()},
                        {p: float(np.mean(v)) for p, v in inside.items()},
                        {p: float(np.mean(e)) for p, e in errs.items()})


@dataclasses.dataclass(frozen=True)
class BridgeScore:
    """The exported bridge estimate against the truth (points = 100 × stiffness ratio)."""

    mean_ratio: float  # exported mean over elements
    true_mean_ratio: float
    mean_error_pts: float  # 100 × (mean_ratio − true_mean_ratio)
    element_coverage: float  # share of elements whose exported 95 % band holds the true ratio
    weakest_element: int  # 1-based, exported
    true_weakest_element: int
    alarm: bool
    n_passes: int


def score_bridge(export_dir: Path, truth: dict) -> BridgeScore | None:
    """``bridge_elements.parquet`` and ``bridge_summary.parquet`` against ``truth['bridge']``; None
    when the run exported no bridge estimate."""
    path = Path(export_dir) / "bridge_elements.parquet"
    if "bridge" not in truth or not path.exists():
        return None
    e = pq.read_table(path).to_pydict()
    if not e["element"]:
        return None
    s = pq.read_table(Path(export_dir) / "bridge_summary.parquet").to_pydict()
    b = truth["bridge"]
    true = np.asarray(b["stiffness_ratio"])
    order = np.argsort(e["element"])
    est = np.asarray(e["stiffness_ratio"])[order]
    ei_design = np.asarray(e["EI_mean"])[order] / est
    lo = np.asarray(e["EI_lo95"])[order] / ei_design
    hi = np.asarray(e["EI_hi95"])[order] / ei_design
    return BridgeScore(
        mean_ratio=float(est.mean()), true_mean_ratio=float(true.mean()),
        mean_error_pts=float(100 * (est.mean() - true.mean())),
        element_coverage=float(np.mean((lo <= true) & (true <= hi))),
        weakest_element=int(np.argmin(est)) + 1, true_weakest_element=int(np.argmin(true)) + 1,
        alarm=bool(s["damaged"][0]) if s["damaged"] else False,
        n_passes=int(s["n_passes"][0]) if s["n_passes"] else 0)


def simulate(world: str, scenario: str, out_dir: Path, seed: int, passes: int | None = None,
             noise_pct: float = 2.0, **kw) -> dict:
    """``scenario`` simulated in ``world`` into ``out_dir``; returns its truth."""
    return WORLDS[world](SCENARIOS[scenario], Path(out_dir), seed=seed, passes=passes, noise_pct=noise_pct,
                         progress=False, **kw)


def run_and_score(sim_dir: Path, export_dir: Path, settings: CloudSettings = CloudSettings(calibration="fleet")) -> dict:
    """The logs of ``sim_dir`` through the in-process edge and cloud, exported and scored."""
    t0 = time.perf_counter()
    logs = [read_drive_log(p) for p in list_drive_logs(Path(sim_dir) / "logs")]
    site = load_site(Path(sim_dir) / "site.toml")
    run_in_process(logs, site, Path(export_dir), settings)
    truth = load_truth(Path(sim_dir) / "truth.json")
    out: dict = {"seconds": time.perf_counter() - t0, "passes": len(logs)}
    prof = score_profile(export_dir, truth)
    out["profile"] = dataclasses.asdict(prof)
    if Path(export_dir, "vehicles.parquet").exists():
        out["vehicles"] = dataclasses.asdict(score_vehicle_intervals(export_dir, truth))
    try:
        out["iri"] = dataclasses.asdict(score_iri(export_dir, truth))
    except ValueError as e:  # a route shorter than one IRI segment
        out["iri"] = {"note": str(e)}
    bridge = score_bridge(export_dir, truth)
    if bridge is not None:
        out["bridge"] = dataclasses.asdict(bridge)
    return out


def save_json(path: Path, obj: dict) -> None:
    Path(path).write_text(json.dumps(obj, indent=1, default=float))
