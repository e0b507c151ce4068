"""``driveby reproduce bridge``: the thesis's bridge results (Table 3.3, Table 4.2, Fig. 4.12) beside
ours, and our error beside the Cramér–Rao bound.

Conditions are those the accuracy targets are stated for: 2 % sensor noise, smooth deck (as the
thesis), vehicle parameters from the system's own fleet self-calibration (the edge and cloud cores wired in process,
:func:`simfleet.harness.run_in_process`, ``calibration="fleet"``: the parameters each pass's AP
was computed with), wheel loads from the registry's vehicle class (the class mean mass fixes the
scale, thesis §4.5.5). The bridge estimator (:class:`cloud.bridge.estimator.BridgeEstimator`) gets
the calibrated passes; the simulation's truth is read only here, to score.

The Cramér–Rao bound (:mod:`cloud.bridge.information`) is computed at the true vehicles and
speeds of a sample of passes and scaled to the fleet (information adds up over passes). For
bridge-healthy's "every element within ±5 / ±3 points" it also gives what an estimator at the bound
with our GMRF prior achieves (:func:`cloud.bridge.information.largest_error`: median largest element
error, P(all within)), at 30/300 passes and, with ``--large``, beside ours at 30/100/300.
Nothing here is imported by the daemons.
"""

from __future__ import annotations

import dataclasses
import datetime
import fcntl
import json
import logging
import math
import pickle
import time
from pathlib import Path

import numpy as np

from cloud.bridge.bearings import krot_reading
from cloud.bridge.estimator import BridgeEstimator, BridgeSettings, class_weight_prior
from cloud.bridge.information import PassCase, fleet_information, largest_error, noise_sd_of, pass_sensitivity
from cloud.bridge.passdata import group_segments
from cloud.bridge.stiffness import StiffnessPrior
from cloud.bridge.vehicle_error import class_log_sd
from cloud.daemon.settings import CloudSettings
from shared.drivelog import list_drive_logs, read_drive_log
from shared.fe.beam import influence_line
from shared.fe.design import design_beam
from shared.registry import load_site

from . import sim
from .harness import run_in_process
from .scenarios import SCENARIOS
from .sim import bridge_beam, deck_window, surfaces

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------------
# The thesis's numbers

#: Table 3.3: true loss → calculated damage level (%), 20 half-cars at 10 and 20 m/s.
TABLE_3_3 = {
    "10 m/s D1": (0, 5, 11), "10 m/s D2": (0, 5, 10),
    "20 m/s D1 (filtered)": (0, 5, 12), "20 m/s D1 (unfiltered)": (0, 7, 15), "20 m/s D2": (0, 5, 10),
}
#: Table 4.2: true and MCMC-calculated log10 Krot (both supports) and I_bridge (m⁴), four states.
TABLE_4_2 = {
    "state": ("pinned (Krot = 0)", "1e9", "1e10", "1e12"),
    "log10_krot_true": (0.0, 9.0, 10.0, 12.0),
    "log10_krot1": (7.6, 9.1, 10.0, 12.8),
    "log10_krot2": (7.0, 9.0, 10.0, 12.3),
    "I_true": (1.26, 1.26, 1.26, 1.26),
    "I_calc": (1.22, 1.22, 1.24, 1.23),
}
#: Fig. 4.12 as the text describes it (values not tabulated): healthy within 1–2 %; cracks found.
FIG_4_12_TEXT = ("Fig. 4.12 (30 quarter-cars, 2 % noise, MCMC with a GMRF prior): healthy elements 'within 1 % "
                 "to 2 %' of the truth; for φ = 10 % the two elements at the crack lose 18 % and the two "
                 "neighbours 5 % (φ = 5 %: 10 % and 3 %), and the thesis finds 'the levels and the location'.")

# ---------------------------------------------------------------------------------------------
# One scenario through the system


@dataclasses.dataclass
class Case:
    """One simulated fleet over a bridge after the system's self-calibration."""

    name: str
    seed: int
    passes: int
    sim_dir: Path
    site: object
    truth: dict
    segments: list  # the cloud's held AP segments (latest calibration of each pass)
    params: dict  # vehicle → the calibration those segments were computed with
    calib_rounds: int
    seconds: float


def simulate_case(name: str, work: Path, passes: int = 30, seed: int = 0, noise_pct: float = 2.0,
                  calibration: str = "fleet", nominal: str = "class") -> Case:
    """Simulate ``name`` (``nominal``: the class-mean parameters in the logs, or each vehicle's
    true ones — for tests where calibration is not the point), run edge + cloud in process with
    ``calibration`` and return the calibrated segments. Cached under ``work``."""
    d = simulate_dir(work, name, passes, seed, noise_pct, nominal)
    cache = d / f"case-{calibration}.pkl"
    d.mkdir(parents=True, exist_ok=True)
    with open(d.with_name(d.name + ".lock"), "w") as lock:  # several processes may share ``work``
        fcntl.flock(lock, fcntl.LOCK_EX)
        if cache.exists():
            with open(cache, "rb") as f:
                return pickle.load(f)
        return _simulate_case(name, d, cache, passes, seed, noise_pct, calibration, nominal)


def simulate_subset(name: str, work: Path, passes: int, of: int, seed: int = 0, noise_pct: float = 2.0) -> Case:
    """The first ``passes`` of ``of`` simulated passes of ``name`` as a case of its own (edge + cloud
    with fleet calibration on those passes only: what the system knows after them). The passes are
    simulated once, for ``of``: a scenario's first N passes do not depend on how many follow (the
    fleet, speeds and seeds are drawn in pass order), so the subset's logs are links to the first N."""
    if passes > of:
        raise ValueError(f"passes: at most {of}, got {passes}")
    if passes == of:
        return simulate_case(name, work, passes=of, seed=seed, noise_pct=noise_pct)
    full = simulate_dir(work, name, of, seed, noise_pct)
    if not (full / "truth.json").exists():
        sim.generate(SCENARIOS[name], full, seed=seed, passes=of, noise_pct=noise_pct, workers=2, progress=False)
    d = simulate_dir(work, name, passes, seed, noise_pct)
    if not (d / "truth.json").exists():
        logs = sorted((full / "logs").glob("*.parquet"))[:passes]  # pass ids are numbered in order
        (d / "logs").mkdir(parents=True, exist_ok=True)
        for p in logs:
            link = d / "logs" / p.name
            if not link.exists():
                link.symlink_to(p.resolve())
        (d / "site.toml").write_text((full / "site.toml").read_text())
        truth = json.loads((full / "truth.json").read_text())
        keep = {p.stem for p in logs}
        truth["passes"] = [r for r in truth["passes"] if r["pass_id"] in keep]
        (d / "truth.json").write_text(json.dumps(truth))
    return simulate_case(name, work, passes=passes, seed=seed, noise_pct=noise_pct)


def simulate_dir(work: Path, name: str, passes: int, seed: int = 0, noise_pct: float = 2.0, nominal: str = "class") -> Path:
    """Where :func:`simulate_case` keeps a case's logs and its calibrated segments."""
    return Path(work) / (f"{name}-n{passes}-s{seed}-{noise_pct:g}pct" + ("" if nominal == "class" else f"-{nominal}"))


def _simulate_case(name, d: Path, cache: Path, passes, seed, noise_pct, calibration, nominal) -> Case:
    t0 = time.perf_counter()
    if not (d / "truth.json").exists():
        sim.generate(SCENARIOS[name], d, seed=seed, passes=passes, noise_pct=noise_pct, nominal=nominal,
                     workers=2, progress=False)
    logs = [read_drive_log(p) for p in list_drive_logs(d / "logs")]
    site = load_site(d / "site.toml")
    cloud, rounds = run_in_process(logs, site, None, CloudSettings(calibration=calibration))
    if cloud.calibrator is not None:
        params = {v: dict(st.params) for v, st in cloud.calibrator.vehicles.items()}
    else:  # nominal: what the edge computed with, the logs' own parameters
        params = {lg.meta.vehicle_id: dict(lg.meta.nominal_params or site.vehicle_class(lg.meta.vehicle_model).mean)
                  for lg in logs}
    case = Case(name, seed, passes, d, site, json.loads((d / "truth.json").read_text()),
                list(cloud.aggregator.held.values()), params, rounds, time.perf_counter() - t0)
    part = cache.with_suffix(".part")
    with open(part, "wb") as f:
        pickle.dump(case, f)
    part.replace(cache)  # atomic: a reader never sees half a case
    return case


def estimate_case(case: Case, settings=None, model: str = "quarter_car"):
    """The bridge estimate of a case (all passes), and the seconds the final estimate took."""
    bridge = case.site.bridges[0]
    # The registry's word on the deck, as the daemon (cloud.bridge.monitor.BridgeMonitor) takes it.
    settings = dataclasses.replace(settings or BridgeSettings(), deck=bridge.deck)
    est = BridgeEstimator(bridge, class_weight_prior(case.site, model), settings)
    for (vid, _), segs in group_segments(case.segments).items():
        est.add_segments(segs, model, case.params[vid])
    t0 = time.perf_counter()
    e = est.estimate()
    return e, time.perf_counter() - t0


def true_ratio(case: Case) -> np.ndarray:
    """The true EI/EI_design per element of the case's bridge."""
    return bridge_beam(SCENARIOS[case.name]).element_ei_factor()


def true_effective(case: Case) -> float:
    """The true 'effective' ratio: design MR-IL area over the true one (what the estimator reports)."""
    beam = bridge_beam(SCENARIOS[case.name])
    x = np.linspace(0.0, beam.span_m, 401)
    design = dataclasses.replace(beam, ei_factor=None, supports="simply_supported", krot_nm_per_rad=None)
    return float(np.trapezoid(influence_line(design, x), x) / np.trapezoid(influence_line(beam, x), x))


def score(case: Case, e) -> dict:
    """The estimate against the truth, in points (100 × ratio)."""
    truth = true_ratio(case)
    p = e.posterior
    a = e.assessment
    out = dict(name=case.name, seed=case.seed, passes=p.n_passes, calib_rounds=case.calib_rounds,
               effective=p.effective_ratio, effective_sd=p.effective_ratio_sd, effective_true=true_effective(case),
               mean_ratio=float(np.mean(p.stiffness_ratio)), mean_true=float(np.mean(truth)),
               element_err_max_pts=float(100 * np.max(np.abs(p.stiffness_ratio - truth))),
               ratios=[float(r) for r in p.stiffness_ratio], lo95=[float(v / p.ei_design) for v in p.ei_lo95],
               hi95=[float(v / p.ei_design) for v in p.ei_hi95], truth=[float(t) for t in truth],
               quasi_static_effective=e.quasi_static.effective_ratio,
               D1=None if e.indicators is None else e.indicators.D1_pct,
               D2=None if e.indicators is None else e.indicators.D2_pct)
    if a is not None:
        out.update(alarm=bool(a.alarm), best=a.best, loss_probability=a.loss_probability,
                   probabilities={k: r.probability for k, r in a.results.items()}, location_m=a.location_m,
                   severity=a.severity)
    if p.krot is not None:
        out["log10_krot"] = [list(k) for k in p.krot]
    return out


def weakest_element(case: Case, e) -> dict:
    """The estimate's weakest element against the truth: its index (1-based), its distance in
    elements from the nearest truly weakest one, and its loss beside the true loss there (points).

    Two readings: the per-element (GMRF) posterior's weakest element (``element``, ``loss_pts``), and
    the damage the hypotheses report when a crack is the most probable damage (``reported_*``: the
    element at the crack's posterior mean location, the crack model's peak element loss) — what
    the alarm publishes. The GMRF prior's smoothness spreads a crack's 18 % over its neighbours
    (measured, crack10-10m, 300 passes: 11.9 % in the GMRF view, 18.9 % from the crack hypothesis)."""
    truth = true_ratio(case)
    est = np.asarray(e.posterior.stiffness_ratio)
    i = int(np.argmin(est))
    worst = np.flatnonzero(truth <= truth.min() + 1e-9)
    out = dict(element=i + 1, distance=int(np.min(np.abs(worst - i))), loss_pts=float(100 * (1 - est[i])),
               true_loss_pts=float(100 * (1 - truth[i])), true_max_loss_pts=float(100 * (1 - truth.min())),
               crack=bool(truth.min() < truth.max() - 1e-9))
    a = e.assessment
    if a is not None and a.kind == "crack":
        j = a.element - 1
        out.update(reported_element=a.element, reported_distance=int(np.min(np.abs(worst - j))),
                   reported_loss_pts=float(100 * a.severity), reported_true_loss_pts=float(100 * (1 - truth[j])))
    return out


# ---------------------------------------------------------------------------------------------
# The Cramér–Rao bound of a case


def case_information(case: Case, sample: int = 6, noise_pct: float = 2.0):
    """Fisher information of the case's fleet (``sample`` passes computed, scaled to all)."""
    sc = SCENARIOS[case.name]
    beam = bridge_beam(sc)
    if beam.supports != "simply_supported":
        beam = design_beam(case.site.bridges[0])
    # The calibration error is a nuisance of the bound too (cloud.bridge.information): its columns
    # need the road the passes drove (the simulation's, read here on the truth side only).
    surface = surfaces(sc, case.seed)[0][0]
    road = lambda x: surface.at(sc.bridge.start_m + x) * deck_window(sc, sc.bridge.start_m + x)  # noqa: E731
    spread = class_log_sd(case.site, "quarter_car")
    names = sorted(spread)
    records = {r["pass_id"]: r for r in case.truth["passes"]}
    paths = list_drive_logs(case.sim_dir / "logs")
    pick = np.unique(np.linspace(0, len(paths) - 1, min(sample, len(paths))).round().astype(int))
    sens = []
    for i in pick:
        lg = read_drive_log(paths[i])
        rec = records[lg.meta.pass_id]
        ch = next(iter(lg.channels.values()))
        pc = PassCase(lg.meta.vehicle_id, lg.meta.vehicle_model, case.truth["vehicles"][lg.meta.vehicle_id],
                      rec["speed_mps"], noise_sd_of(ch, noise_pct), road)
        sens.append(pass_sensitivity(pc, beam, calibration=names))
    vc = case.site.vehicle_class("quarter_car")
    w_rel = math.hypot(vc.std["M"], vc.std["m"]) / (vc.mean["M"] + vc.mean["m"])
    n_vehicles = len({r["vehicle_id"] for r in case.truth["passes"]})
    per_pass = BridgeSettings().calibration_log_sd or 0.04
    return fleet_information(sens, w_rel, common_sd=[spread[n] / math.sqrt(n_vehicles) for n in names],
                             pass_sd=[per_pass] * len(names), span_m=beam.span_m).scaled(case.passes, n_vehicles)


def healthy_bound_pts(passes: int) -> float:
    """The target bound on every element of bridge-healthy (points): ±5 at 30 passes, ±3 at 300
    (and from 100 on, where no target is stated)."""
    return 5.0 if passes < 100 else 3.0


def largest_error_entry(info, prior_precision: np.ndarray, bound_pts: float, seed: int) -> dict:
    """:func:`cloud.bridge.information.largest_error` of ``info`` as a JSON-able dict."""
    le = largest_error(info, prior_precision, bound_pts, rng=np.random.default_rng(seed))
    d = dataclasses.asdict(le)
    return {k: ([float(x) for x in v] if isinstance(v, np.ndarray) else v) for k, v in d.items()}


# ---------------------------------------------------------------------------------------------
# The report


def _f(x, nd=1) -> str:
    return "–" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{nd}f}"


#: ``--large``: scenario → the pass counts it is estimated from (first N of the largest, one simulation)
LARGE = {
    "bridge-healthy": (30, 100, 300),
    "bridge-crack10-10m": (30, 100, 300),
    "bridge-crack10-14m": (30, 100, 300),
    "fleet-large": (30, 100, 300),
    "bridge-healthy-rough": (30, 100, 300),
    "bridge-global10-rough": (30, 100, 300),
}


def reproduce_bridge(out_dir: str | Path, quick: bool = False, seed: int = 0, large: bool = False,
                     only_large: bool = False) -> Path:
    """Run the bridge scenarios and write ``out_dir/bridge.md`` (+ ``bridge.json``). ``large``: also
    the 300-pass cracks, fleet-large and the rough decks at 30/100/300 passes (:data:`LARGE`: hours
    on a loaded machine, so not in the default run); ``only_large``: those alone."""
    out = Path(out_dir)
    work = out / "work-bridge"
    work.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    results: dict = {"quick": quick, "seed": seed, "scenarios": {}, "bearings": {}, "crb": {}, "seeds_global10": [],
                     "large": {}}
    cases = {}

    def flush() -> None:
        """Write what is known so far: a long run that is stopped still leaves its report."""
        results["seconds"] = time.perf_counter() - t_start
        (out / "bridge.md").write_text(_report(results))
        (out / "bridge.json").write_text(json.dumps(results, indent=1, default=float))

    def run(name: str, passes: int = 30, s: int = seed) -> dict:
        c = simulate_case(name, work, passes=passes, seed=s)
        e, secs = estimate_case(c)
        r = score(c, e)
        r["estimate_s"] = secs
        r["system_s"] = c.seconds
        cases[(name, s, passes)] = c
        log.info("%s seed %d: effective %.4f ± %.4f (truth %.4f)", name, s, r["effective"], r["effective_sd"],
                 r["effective_true"])
        return r

    def run_springs_declared(name: str) -> dict:
        """``name``'s passes with the registry declaring rotational-spring bearings (a pinned span
        estimated with the bearing model, like the thesis's 'Krot = 0' state)."""
        c = simulate_case(name, work, passes=30, seed=seed)
        b = dataclasses.replace(c.site.bridges[0], supports="rotational_springs", krot_nm_per_rad=None)
        c = dataclasses.replace(c, site=dataclasses.replace(c.site, bridges=type(c.site.bridges)([b])))
        e, secs = estimate_case(c)
        r = score(c, e)
        r["estimate_s"] = secs
        log.info("%s as springs: log10 Krot %s", name, r.get("log10_krot"))
        return r

    if large or only_large:  # first: the longest runs, and their report is kept as each case ends
        first: dict = {}
        for n, counts in LARGE.items():
            for k in counts:
                c = simulate_subset(n, work, k, max(counts), seed=seed)
                first.setdefault(n, c)
                e, secs = estimate_case(c)
                r = score(c, e)
                r.update(estimate_s=secs, system_s=c.seconds, weakest=weakest_element(c, e))
                results["large"].setdefault(n, {})[str(k)] = r
                log.info("%s, %d passes: effective %.4f (truth %.4f), max element error %.1f points", n, k,
                         r["effective"], r["effective_true"], r["element_err_max_pts"])
                flush()
        if "bridge-healthy" in first:  # the bound's largest error beside ours: the first case's information, scaled
            info = case_information(first["bridge-healthy"], sample=8)
            prior = StiffnessPrior().precision(info.F.shape[0])
            for k, r in results["large"]["bridge-healthy"].items():
                r["bound"] = largest_error_entry(info.scaled(int(k)), prior, healthy_bound_pts(int(k)), seed)
            flush()
        if only_large:
            results["complete"] = True
            flush()
            return out / "bridge.md"
    names = ["bridge-healthy", "bridge-global5", "bridge-global10"]
    if not quick:
        names += ["bridge-crack10-10m", "bridge-crack10-14m", "bridge-crack5-10m", "bridge-crack5-14m"]
    for n in names:
        results["scenarios"][n] = run(n)
        flush()
    for n in [] if quick else ["bearing-1e9", "bearing-1e10", "bearing-1e12"]:
        results["bearings"][n] = run(n)
        flush()
    if not quick:  # the thesis's first row: the bearing model on a pinned span
        results["bearings"]["pinned"] = run_springs_declared("bridge-healthy")
        flush()

    # Cramér–Rao bounds (30 passes), at the true fleet and speeds of a sample of passes.
    crb = results["crb"]
    for n in (["bridge-healthy", "bridge-global10"] if quick else ["bridge-healthy", "bridge-global10",
                                                                    "bridge-crack10-10m", "bridge-crack10-14m"]):
        info = case_information(cases[(n, seed, 30)], sample=3 if quick else 8)
        entry = dict(global_sd=info.global_sd(), global_sd_300=info.scaled(300).global_sd(),
                     element_sd_free=[float(v) for v in info.element_sd()],
                     element_sd_gmrf=[float(v) for v in info.element_sd(StiffnessPrior().precision(20))])
        if n == "bridge-healthy":  # the target "every element within ±5 / ±3" against the efficient estimator
            prior = StiffnessPrior().precision(info.F.shape[0])
            entry["largest_error"] = {str(k): largest_error_entry(info.scaled(k), prior, healthy_bound_pts(k), seed)
                                      for k in (30, 300)}
        if "crack" in n:
            spec = SCENARIOS[n].bridge
            b = cases[(n, seed, 30)].site.bridges[0]
            at = (b.n_elements, b.span_m, b.depth_m, spec.crack_x_m, spec.crack_phi)
            entry["crack_sd_30"] = [float(v) for v in info.crack_sd(*at)]
            entry["crack_sd_300"] = [float(v) for v in info.scaled(300).crack_sd(*at)]
        crb[n] = entry
        flush()

    # Efficiency: spread of the global estimate over seeds of bridge-global10.
    seeds = range(seed, seed + (1 if quick else 10))
    for s_ in seeds:
        results["seeds_global10"].append(run("bridge-global10", s=s_))
        flush()
    results["complete"] = True
    flush()
    return out / "bridge.md"


def _report(r: dict) -> str:
    L = ["# Bridge results beside the thesis", "",
         f"Generated {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC by `driveby reproduce bridge"
         f"{' --quick' if r['quick'] else ''}` in {r['seconds']:.0f} s"
         f"{'' if r.get('complete') else ' (PARTIAL: the run had not finished; sections below may be missing)'}. Conditions: 30 quarter-car passes "
         "(Table 4.1 fleet, 15–22 m/s), 2 % sensor noise, smooth deck, vehicle parameters from the system's own "
         "fleet self-calibration (edge + cloud cores in process), wheel-load prior = the registry's class "
         "(class-mean mass fixes the scale). Ratios are EI/EI_design; 'effective' = area of the design MR-IL over "
         "the estimated one (the well-determined global stiffness).", ""]
    sc = r["scenarios"]
    L += ["## Global stiffness and Table 3.3 (damage indicators)", "",
          "| scenario | true loss % | our effective loss % (±1σ) | our mean element loss % | quasi-static only % | "
          "D1 % | D2 % | alarm | best hypothesis | thesis D1/D2 (10 m/s) |", "|---|---|---|---|---|---|---|---|---|---|"]
    thesis = {"bridge-healthy": "0 / 0", "bridge-global5": "5 / 5", "bridge-global10": "11 / 10"}
    for n in ("bridge-healthy", "bridge-global5", "bridge-global10"):
        if n not in sc:
            continue
        s = sc[n]
        L.append(f"| {n} | {_f(100 * (1 - s['effective_true']))} | {_f(100 * (1 - s['effective']))} "
                 f"(±{_f(100 * s['effective_sd'])}) | {_f(100 * (1 - s['mean_ratio']))} | {_f(100 * (1 - s['quasi_static_effective']))} | {_f(s['D1'])} | "
                 f"{_f(s['D2'])} | {s.get('alarm')} | {s.get('best')} | {thesis[n]} |")
    L += ["", "Thesis Table 3.3 used 20 two-axle half-cars at fixed speeds 10 and 20 m/s on a 0.33 m⁴ beam, "
          "without noise; ours: single-axle quarter-cars at 15–22 m/s, 2 % noise, calibrated vehicles.", ""]
    L += ["## Fig. 4.12 (element stiffness) — ours", "", FIG_4_12_TEXT, ""]
    for n, s in sc.items():
        L.append(f"**{n}** (true mean {_f(100 * s['mean_true'])} %, ours {_f(100 * s['mean_ratio'])} %, "
                 f"max element error {_f(s['element_err_max_pts'])} points, alarm {s.get('alarm')}, best "
                 f"{s.get('best')}, crack location {_f(s.get('location_m'))} m, severity {_f(100 * s.get('severity', float('nan')))} %)")
        L.append("")
        L.append("| element | " + " | ".join(str(i + 1) for i in range(len(s["ratios"]))) + " |")
        L.append("|---|" + "---|" * len(s["ratios"]))
        L.append("| true % | " + " | ".join(_f(100 * v, 0) for v in s["truth"]) + " |")
        L.append("| ours % | " + " | ".join(_f(100 * v, 0) for v in s["ratios"]) + " |")
        L.append("| 95 % band | " + " | ".join(f"{100 * lo:.0f}–{100 * hi:.0f}" for lo, hi in zip(s["lo95"], s["hi95"]))
                 + " |")
        L.append("")
    L += ["## Table 4.2 (bearings)" + ("" if r["bearings"] else " — not run with --quick"), "",
          "Ours: one log10 Krot for both supports (the data do not separate them), its grid posterior "
          "(`cloud/bridge/bearings.py`) with the beam's level integrated against the as-built tolerance on its "
          "EI (2 %): the passes fix the effective stiffness, not the split between beam and bearings. "
          "The prior is uniform in the restraint's effect on the span (its influence-line area between pinned "
          "and clamped), so it saturates where decades of Krot all mean 'fixed'. Where the data do not exclude "
          "a clamped span (likelihood at 10^13 within the 95 % likelihood-ratio threshold of its maximum) the "
          "interval is one-sided — '≥ 10^lo' with lo the 5 % quantile, a lower bound — and likewise '≤ 10^hi' "
          "for a span that may be pinned.", "",
          "| state | thesis log10 Krot (1/2) | ours log10 Krot mean (95 %) | reading | thesis I/I_true | "
          "ours mean EI ratio % | ours effective ratio (truth) | P(healthy) / P(bearings) | alarm |",
          "|---|---|---|---|---|---|---|---|---|"]
    row = {"pinned": 0, "bearing-1e9": 1, "bearing-1e10": 2, "bearing-1e12": 3}
    for n, s in sorted(r["bearings"].items(), key=lambda kv: row.get(kv[0], 9)):
        k = (s.get("log10_krot") or [[float("nan")] * 3])[0]
        i = row[n]
        reading = krot_reading(k[1], k[2])
        pr = s.get("probabilities", {})
        L.append(f"| {n} | {TABLE_4_2['log10_krot1'][i]} / {TABLE_4_2['log10_krot2'][i]} | {k[0]:.2f} "
                 f"({k[1]:.2f}–{k[2]:.2f}) | {reading} | {TABLE_4_2['I_calc'][i] / TABLE_4_2['I_true'][i]:.3f} | "
                 f"{_f(100 * s['mean_ratio'])} | {_f(s['effective'], 3)} ({_f(s['effective_true'], 3)}) | "
                 f"{_f(pr.get('healthy'), 3)} / {_f(pr.get('bearings'), 3)} | {s.get('alarm')} |")
    if "bridge-healthy" in sc:
        pr = sc["bridge-healthy"].get("probabilities", {})
        L += ["", f"Pinned vs stiff told apart by the hypotheses (registry: simply supported): on bridge-healthy "
              f"P(healthy) = {_f(pr.get('healthy'), 3)}, P(bearings) = {_f(pr.get('bearings'), 3)}."]
    L += _large_report(r.get("large") or {})
    L += ["", "## Cramér–Rao bound", "",
          "Fisher information of the measured channel (body acceleration, white noise 2 % of its sd) from the "
          "coupled vehicle–bridge model by finite differences, wheel loads marginalised with the class prior "
          "(`cloud/bridge/information.py`), 30 passes unless stated.", "",
          "| scenario | CRB global (30) % | CRB global (300) % | our posterior sd % | CRB elements (GMRF prior) % | "
          "CRB crack (x m, φ, g) 30 / 300 |", "|---|---|---|---|---|---|"]
    for n, c in r["crb"].items():
        ours = sc.get(n, {}).get("effective_sd", float("nan"))
        crack = ("–" if "crack_sd_30" not in c else
                 f"({c['crack_sd_30'][0]:.2f}, {c['crack_sd_30'][1]:.3f}, {c['crack_sd_30'][2]:.3f}) / "
                 f"({c['crack_sd_300'][0]:.2f}, {c['crack_sd_300'][1]:.3f}, {c['crack_sd_300'][2]:.3f})")
        L.append(f"| {n} | {100 * c['global_sd']:.2f} | {100 * c['global_sd_300']:.2f} | {100 * ours:.2f} | "
                 f"{100 * min(c['element_sd_gmrf']):.1f}–{100 * max(c['element_sd_gmrf']):.1f} | {crack} |")
    L += largest_error_report(r)
    sp = r["seeds_global10"]
    crb = r["crb"].get("bridge-global10", r["crb"].get("bridge-healthy"))
    if not sp or crb is None:
        return "\n".join(L + ["", "**Efficiency**: not run yet."]) + "\n"
    eff = np.array([s["effective"] for s in sp])
    bound = crb["global_sd"]
    spread = (f"spread (sd) {100 * np.std(eff, ddof=1):.2f} points (ratio to the bound "
              f"{np.std(eff, ddof=1) / bound:.1f}×; the target is ≤ 1.5×)" if eff.size > 1 else
              "spread: needs several seeds (run without --quick)")
    L += ["", f"**Efficiency** (bridge-global10, {len(sp)} seed(s)): estimates "
          + ", ".join(f"{100 * (1 - v):.1f}" for v in eff) + " % loss (truth 10 %); "
          f"{spread}; RMS error {100 * np.sqrt(np.mean((eff - 0.9) ** 2)):.2f} points; bound "
          f"{100 * bound:.2f} points; median posterior sd "
          f"{100 * float(np.median([s['effective_sd'] for s in sp])):.2f} points. "
          "A spread from 10 seeds is itself uncertain by ±24 % (1σ). The bound and the estimator carry the same "
          "nuisances (wheel loads, the calibration error common to the fleet and each pass's own), not the same "
          "noise level: the bound has white sensor noise at 2 % of the channel's sd; the estimator reads each "
          "pass's level on its approach, in the band of its element directions (cloud.bridge.whitening."
          "element_band_sigma, which reads the level there as noise-free twins do, where the whole band's level reads "
          "it low), and the approach's noise holds more "
          "than sensor noise (the AP's processing, a low-frequency excess near the record's start).", ""]
    return "\n".join(L) + "\n"


def largest_error_report(r: dict) -> list[str]:
    """bridge-healthy's "every element within ±b": what an estimator at the bound achieves, and ours."""
    le = r["crb"].get("bridge-healthy", {}).get("largest_error")
    if not le:
        return []
    ours = {"30": r["scenarios"].get("bridge-healthy", {}).get("element_err_max_pts")}
    ours.update({k: s.get("element_err_max_pts") for k, s in (r.get("large") or {}).get("bridge-healthy", {}).items()})
    L = ["", "**bridge-healthy: every element within ±b** (the target bounds) for an estimator at the information "
         "bound with the estimator's GMRF prior (`StiffnessPrior()`, τ = 1; the estimator itself weighs scales τ by "
         "their evidence): on a healthy span the prior's smoothness is exact, so such an estimator is unbiased and "
         "its error covariance is A·F·A (A = (F + Q)⁻¹), below the posterior's A "
         "(`cloud.bridge.information.largest_error`; Monte Carlo of the largest |element error|, "
         "the 30-pass information scaled).", "",
         "| passes | bound ± pts | efficient element sd (pts) | Bayesian sd (pts) | largest error: median (90 %) pts | "
         "P(all within) | ours: largest error pts |", "|---|---|---|---|---|---|---|"]
    for k, e in sorted(le.items(), key=lambda kv: int(kv[0])):
        L.append(f"| {k} | {e['bound_pts']:.0f} | {min(e['element_sd_pts']):.1f}–{max(e['element_sd_pts']):.1f} | "
                 f"{min(e['bayes_sd_pts']):.1f}–{max(e['bayes_sd_pts']):.1f} | {e['median_pts']:.2f} "
                 f"({e['p90_pts']:.2f}) | {e['p_within']:.2f} | {_f(ours.get(k), 2)} |")
    return L


def _large_report(large: dict) -> list[str]:
    """The ``--large`` section: error against the number of passes."""
    if not large:
        return []
    L = ["", "## Large fleets and rough decks: error against the number of passes", "",
         "The first 30, 100 and 300 passes of one simulation each (fleet calibration on those passes only). "
         "Cracks (the targets at 300 passes): the weakest element within one element of the crack, its loss within "
         "±5 points of the truth, an alarm — read from the damage the hypotheses report (the crack's location "
         "and its model's peak element loss: 'reported'), with the per-element GMRF view beside it (its "
         "smoothness prior spreads a crack over its neighbours). Rough decks: the registry says "
         "`deck = \"rough\"`; the damage "
         "hypotheses (and so the alarm) run there too (`BridgeSettings.assess_rough`), a crack placed on an element only "
         "when the passes locate it (`cloud.bridge.hypotheses.LOCATED_ELEMENTS`).", "",
         "| scenario | passes | effective loss % (±1σ) | truth | mean element error (pts) | max element error (pts) | "
         "weakest element: # (elements from the crack) | its loss % (truth there / crack max) | "
         "reported crack element # (from the crack) | its loss % (truth there) | best hypothesis | crack x m, "
         "severity % | alarm | estimate s | bound: largest element error median (90 %) pts, P(≤ ±b) |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, by_n in large.items():
        for k, s in sorted(by_n.items(), key=lambda kv: int(kv[0])):
            w = s.get("weakest", {})
            err = np.abs(np.array(s["ratios"]) - np.array(s["truth"]))
            crack = (f"{w['element']} ({w['distance']})" if w.get("crack") else str(w.get("element", "–")))
            loss = (f"{_f(w.get('loss_pts'))} ({_f(w.get('true_loss_pts'))} / {_f(w.get('true_max_loss_pts'))})"
                    if w else "–")
            rep = ("–", "–") if "reported_element" not in w else (
                f"{w['reported_element']} ({w['reported_distance']})",
                f"{_f(w['reported_loss_pts'])} ({_f(w['reported_true_loss_pts'])})")
            loc = ("–" if s.get("location_m") is None else
                   f"{_f(s.get('location_m'))}, {_f(100 * s.get('severity', float('nan')))}")
            L.append(f"| {name} | {k} | {_f(100 * (1 - s['effective']))} (±{_f(100 * s['effective_sd'])}) | "
                     f"{_f(100 * (1 - s['effective_true']))} | {_f(100 * float(np.mean(err)))} | "
                     f"{_f(s['element_err_max_pts'])} | {crack} | {loss} | {rep[0]} | {rep[1]} | "
                     f"{s.get('best', '–')} | {loc} | "
                     f"{s.get('alarm', '–')} | {_f(s.get('estimate_s'), 0)} | {bound_cell(s.get('bound'))} |")
    if any("bound" in s for by_n in large.values() for s in by_n.values()):
        L += ["", "Bound column (bridge-healthy): an estimator at the information bound with the estimator's GMRF "
              "prior, on the first 30 passes' information scaled to the row's passes (see the Cramér–Rao section)."]
    return L


def bound_cell(b: dict | None) -> str:
    """A report cell for a :func:`largest_error_entry` ``b``: median (90th percentile) and P(within the bound)."""
    if not b:
        return "–"
    return f"{b['median_pts']:.2f} ({b['p90_pts']:.2f}), P(≤ ±{b['bound_pts']:.0f}) = {b['p_within']:.2f}"
