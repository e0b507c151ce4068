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


def run_and_score(sim_dir: Path, export_dir: Path,
                  settings: CloudSettings = CloudSettings(calibration="fleet")) -> dict:
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
    for key, length in (("iri", 100.0), ("iri10", 10.0)):
        try:
            out[key] = dataclasses.asdict(score_iri(export_dir, truth, length_m=length))
        except ValueError as e:  # a route shorter than one IRI segment
            out[key] = {"note": str(e)}
    bridge = score_bridge(export_dir, truth)
    if bridge is not None:
        out["bridge"] = dataclasses.asdict(bridge)
    return out


def save_json(path: Path, obj: dict) -> None:
    Path(path).write_text(json.dumps(obj, indent=1, default=float))


@dataclasses.dataclass(frozen=True)
class Case:
    """One scenario in one world: ``settings`` are the ivp world's (None: simfleet's world)."""

    label: str
    scenario: str
    world: str
    passes: int | None
    settings: ivp.WorldSettings | None = None
    route_length_m: float | None = None  # shortened for --quick

    def generate(self, out_dir: Path, seed: int) -> dict:
        sc = SCENARIOS[self.scenario]
        if self.route_length_m is not None:
            sc = dataclasses.replace(sc, route_length_m=self.route_length_m)
        kw = {} if self.settings is None else {"settings": self.settings}
        return WORLDS[self.world](sc, Path(out_dir), seed=seed, passes=self.passes, noise_pct=2.0, progress=False,
                                  **kw)


EXACT_ODOMETER = ivp.WorldSettings(speed_error_sd=0.0)


def cases(quick: bool) -> list[Case]:
    """Every case in simfleet's world, the ivp world as it is (1 % odometer error), and where the
    odometer error hides everything else, the ivp world with an exact odometer."""
    out = []
    road_len = 120.0 if quick else None
    road_passes = 12 if quick else 30
    for label, world, settings in (("simfleet", "simfleet", None), ("ivp", "ivp", ivp.WorldSettings()),
                                   ("ivp, exact odometer", "ivp", EXACT_ODOMETER)):
        out.append(Case(label, "road-qc", world, road_passes, settings, road_len))
    bridge_passes = 12 if quick else 30
    names = ("bridge-healthy", "bridge-global10") if quick else \
        ("bridge-healthy", "bridge-global10", "bridge-global10-rough", "bridge-crack10-10m-rough", "bearing-1e10")
    for name in names:
        for label, world, settings in (("simfleet", "simfleet", None), ("ivp", "ivp", ivp.WorldSettings()),
                                       ("ivp, exact odometer", "ivp", EXACT_ODOMETER)):
            out.append(Case(label, name, world, bridge_passes, settings))
    if not quick:
        for name in ("road-hc", "road-qc-gnss", "carpet"):
            out.append(Case("simfleet", name, "simfleet", None))
            out.append(Case("ivp", name, "ivp", None, ivp.WorldSettings()))
    return out


def run_case(case: Case, work: Path, seed: int) -> dict:
    tag = f"{case.scenario}-{case.label.replace(', ', '-').replace(' ', '_')}-s{seed}"
    d = Path(work) / tag
    cache = d / "score.json"
    if cache.exists():
        return json.loads(cache.read_text())
    log.info("robustness: %s", tag)
    case.generate(d, seed)
    res = run_and_score(d, d / "export")
    res.update(scenario=case.scenario, world=case.label, seed=seed)
    save_json(cache, res)
    return res


def _mean(rows: list[dict], *path: str) -> float | None:
    vals = []
    for r in rows:
        v = r
        for p in path:
            v = v.get(p) if isinstance(v, dict) else None
        if isinstance(v, (int, float)):
            vals.append(float(v))
    return float(np.mean(vals)) if vals else None


def _f(x: float | None, scale: float = 100.0, digits: int = 2, unit: str = " %") -> str:
    return "–" if x is None else f"{scale * x:.{digits}f}{unit}"


RATIOS = ("K/M", "k/M", "c/M", "m/M")


def report(results: dict[tuple[str, str], list[dict]], seeds: list[int], quick: bool) -> list[str]:
    lines = ["# Robustness: simfleet's world and the second (ivp) world side by side", "",
             f"Seeds {', '.join(map(str, seeds))}; 2 % noise; default run (in-process edge + cloud, "
             f"`--calibration fleet`, no `--align`){'; --quick: 120 m road, 12 passes' if quick else ''}. "
             "Errors are means over seeds; coverage is the share of points, intervals or elements whose "
             "95 % band holds the truth, pooled over seeds (goal ≥ 0.90).", "",
             "The ivp world: RK4 at 20 kHz on its own equations of motion, a Rayleigh–Ritz modal bridge, "
             "an anti-alias FIR and decimation, every vehicle parameter drawn from the class prior, a "
             "slowly varying speed, a per-run odometer scale error (sd 1 %) with the chainage integrated "
             "from it, random run-ins. \"exact odometer\": the same without the odometer error.", "",
             "## Road profile, IRI, vehicle ratios", "",
             "| scenario | world | profile error | profile coverage | IRI 100 m error | IRI 10 m error | "
             "IRI 10 m coverage | " + " | ".join(f"{p} error" for p in RATIOS) + " | "
             + " | ".join(f"{p} coverage" for p in RATIOS) + " |",
             "|---" * (7 + 2 * len(RATIOS)) + "|"]
    for (scenario, world), rows in results.items():
        cells = [scenario, world, _f(_mean(rows, "profile", "rel_error")),
                 _f(_mean(rows, "profile", "coverage"), 1, 2, ""),
                 _f(_mean(rows, "iri", "median_rel_error")), _f(_mean(rows, "iri10", "median_rel_error")),
                 _f(_mean(rows, "iri10", "coverage"), 1, 2, "")]
        cells += [_f(_mean(rows, "vehicles", "median_error", p)) for p in RATIOS]
        cells += [_f(_mean(rows, "vehicles", "coverage", p), 1, 2, "") for p in RATIOS]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "## Bridges", "",
              "| scenario | world | passes | mean stiffness (est / true) | error, points | element coverage | "
              "weakest element (est / true) | alarm |", "|---" * 8 + "|"]
    for (scenario, world), rows in results.items():
        b = [r["bridge"] for r in rows if "bridge" in r]
        if not b:
            if SCENARIOS[scenario].bridge is not None:
                lines.append(f"| {scenario} | {world} | – | no bridge estimate exported | | | | |")
            continue
        lines.append(
            f"| {scenario} | {world} | {b[0]['n_passes']} | "
            f"{np.mean([x['mean_ratio'] for x in b]):.3f} / {np.mean([x['true_mean_ratio'] for x in b]):.3f} | "
            f"{np.mean([x['mean_error_pts'] for x in b]):+.2f} | {np.mean([x['element_coverage'] for x in b]):.2f} | "
            f"{', '.join(str(x['weakest_element']) for x in b)} / {b[0]['true_weakest_element']} | "
            f"{sum(x['alarm'] for x in b)}/{len(b)} |")
    return lines


def reproduce_robustness(out_dir: str | Path, quick: bool = False, seed: int = 0) -> Path:
    """Run every case of :func:`cases` for the seeds (one with ``quick``, three otherwise) and write
    ``robustness.md`` and ``robustness.json`` to ``out_dir``; cases already scored there are reused."""
    out = Path(out_dir)
    work = out / "robustness"
    work.mkdir(parents=True, exist_ok=True)
    seeds = [seed] if quick else [seed, seed + 1, seed + 2]
    results: dict[tuple[str, str], list[dict]] = {}
    for case in cases(quick):
        for s in seeds:
            results.setdefault((case.scenario, case.label), []).append(run_case(case, work, s))
    path = out / "robustness.md"
    path.write_text("\n".join(report(results, seeds, quick)) + "\n")
    save_json(out / "robustness.json", {f"{k[0]} | {k[1]}": v for k, v in results.items()})
    return path
