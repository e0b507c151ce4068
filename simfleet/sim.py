"""``driveby sim``: simulate a scenario's passes and write drive logs, site.toml and truth.json."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.drivelog import DriveLog, DriveLogMeta, write_drive_log
from shared.fe.beam import Beam, crack_ei_factor, global_ei_factor, natural_frequencies
from shared.profiles import RoadProfile, carpet_profile, draw_lane, iso8608_profile, tyre_filter
from shared.registry import Bridge, Route, Site, VehicleClass, dump_site
from shared.sensors import add_noise
from shared.vbi import simulate_vbi
from shared.vehicles import vehicle_from_params

from .jobs import run_jobs
from .network import generate_network
from .rail import generate_rail
from .scenarios import Scenario, draw_fleet, fleet_class

ROUTE_ID = "R1"
BRIDGE_ID = "B1"
RUN_IN_M = 30.0  # the vehicle is already driving when its logger's record starts
SUBSTEPS = 4  # the simulator integrates 4× finer than the sensor rate (no inverse crime)
# Average acceleration (γ = 1/2): second-order and free of numerical damping, so the simulated
# truth is real physics to ~1e-4 at body bounce; the edge's γ = 0.8 is the inverse's own choice.
SIM_GAMMA = 0.5
TRUTH_SPACING_M = 0.05


@dataclass(frozen=True)
class PassPlan:
    index: int
    vehicle_id: str
    params: dict
    speed_mps: float
    lane: int | None
    seed: int


def bridge_beam(scenario: Scenario) -> Beam | None:
    spec = scenario.bridge
    if spec is None:
        return None
    factor = np.ones(spec.n_elements)
    if spec.crack_x_m is not None:
        factor = factor * crack_ei_factor(spec.n_elements, spec.span_m, spec.depth_m, spec.crack_x_m, spec.crack_phi)
    if spec.global_loss:
        factor = factor * global_ei_factor(spec.n_elements, spec.global_loss)
    krot = None if spec.krot_nm_per_rad is None else (spec.krot_nm_per_rad, spec.krot_nm_per_rad)
    return Beam(span_m=spec.span_m, n_elements=spec.n_elements, E_pa=spec.E_pa, I_m4=spec.I_m4,
                mass_per_m=spec.mass_per_m, damping_ratio=spec.damping_ratio, supports=spec.supports,
                krot_nm_per_rad=krot, ei_factor=factor, depth_m=spec.depth_m)


def surfaces(scenario: Scenario, seed: int) -> tuple[list[RoadProfile], np.ndarray | None]:
    """The surface(s) vehicles drive on: one profile, or the carpet's lanes and lane weights."""
    margin = RUN_IN_M + 20.0
    length = scenario.route_length_m + 2 * margin
    if scenario.carpet:
        carpet = carpet_profile(length, 0.01, scenario.road_class, seed)
        lanes = [_shift(tyre_filter(p), -margin) for p in carpet.lanes]
        return lanes, None
    p = iso8608_profile(length, 0.01, scenario.road_class, seed)
    return [_shift(tyre_filter(p), -margin)], None


def _shift(p: RoadProfile, start_m: float) -> RoadProfile:
    return RoadProfile(start_m=start_m, spacing_m=p.spacing_m, elevation_m=p.elevation_m - p.elevation_m.mean())


def deck_window(scenario: Scenario, x: np.ndarray) -> np.ndarray:
    """1 on the road, 0 on a smooth deck, with 5 m cosine ramps just outside the span."""
    spec = scenario.bridge
    if spec is None or scenario.rough_deck:
        return np.ones_like(x)
    a, b, ramp = spec.start_m, spec.start_m + spec.span_m, 5.0
    d = np.maximum(a - x, x - b)  # distance outside the span (negative inside)
    w = np.clip(d / ramp, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * w)


def simulate_pass(scenario: Scenario, plan: PassPlan, surface: RoadProfile, beam: Beam | None,
                  noise_pct: float, out_dir: Path, nominal: dict) -> dict:
    rng = np.random.default_rng(plan.seed)
    vehicle = vehicle_from_params(scenario.vehicle_model, plan.params)
    system = vehicle.system()
    fs = scenario.sample_rate_hz
    dt = 1.0 / (fs * SUBSTEPS)

    def elevation(x):
        return surface.at(x) * deck_window(scenario, x)

    def slope(x):
        h = 1e-3  # the window's ramp makes a central difference the simplest exact-enough slope
        return (elevation(x + h) - elevation(x - h)) / (2 * h)

    rear = float(system.offsets_m.min())
    x0 = -RUN_IN_M
    duration = (scenario.route_length_m - x0) / plan.speed_mps
    spec = scenario.bridge
    resp = simulate_vbi(system, elevation, slope, x0, plan.speed_mps, duration, dt, beam=beam,
                        bridge_start_m=spec.start_m if spec else 0.0, gamma=SIM_GAMMA)
    keep = slice(None, None, SUBSTEPS)
    x_cg = resp.x_cg[keep]
    logged = (x_cg >= 0.0) & (x_cg <= scenario.route_length_m + rear)
    idx = np.flatnonzero(logged)
    x_cg = x_cg[idx]
    channels = resp.channels[keep][idx]
    noisy = {ch.name: add_noise(channels[:, i], noise_pct, rng).astype(np.float32)
             for i, ch in enumerate(system.channels)}
    chainage, bias, scale_err = gnss_and_odometry(x_cg, rng, scenario.gnss_bias_sd_m, scenario.gnss_jitter_sd_m,
                                                  scenario.speed_error_sd)
    n = len(idx)
    pass_id = f"p{plan.index + 1:04d}_{plan.vehicle_id}"
    meta = DriveLogMeta(
        format="driveby-drive-log", version=1, vehicle_id=plan.vehicle_id, route_id=ROUTE_ID,
        vehicle_model=scenario.vehicle_model, sample_rate_hz=fs,
        start_time_utc=f"2026-11-20T08:{(plan.index // 60) % 60:02d}:{plan.index % 60:02d}Z",
        lane_offset_m=None if plan.lane is None else float(plan.lane - 5) * 0.1,
        nominal_params=nominal, pass_id=pass_id,
    )
    log = DriveLog(meta=meta, t=np.arange(n) / fs, chainage=chainage,
                   speed=np.full(n, plan.speed_mps * (1.0 + scale_err)), speed_measured=True, channels=noisy)
    write_drive_log(out_dir / "logs" / f"{pass_id}.parquet", log)
    return {"pass_id": pass_id, "vehicle_id": plan.vehicle_id, "speed_mps": plan.speed_mps, "lane": plan.lane,
            "gnss_bias_m": bias, "speed_scale_error": scale_err, "n_samples": n,
            "gnss_error_at_start_m": float(chainage[0] - x_cg[0]), "true_chainage_at_start_m": float(x_cg[0])}


def gnss_and_odometry(x_true: np.ndarray, rng: np.random.Generator, bias_sd_m: float, jitter_sd_m: float,
                      speed_error_sd: float) -> tuple[np.ndarray, float, float]:
    """(GNSS chainage, its bias, the odometer's relative scale error) of one pass.

    GNSS measures position: the true chainage plus a per-pass bias (sd ``bias_sd_m``; constant over
    a pass of seconds) and white noise (sd ``jitter_sd_m``) — no scale error. The odometer's speed
    carries the scale error (sd ``speed_error_sd``); the caller applies it to the logged speed.
    """
    bias = float(rng.normal(0.0, bias_sd_m)) if bias_sd_m > 0 else 0.0
    scale_err = float(rng.normal(0.0, speed_error_sd)) if speed_error_sd > 0 else 0.0
    gnss = np.asarray(x_true, float) + bias
    if jitter_sd_m > 0:
        gnss = gnss + rng.normal(0.0, jitter_sd_m, gnss.shape)
    return gnss, bias, scale_err


def _run_one(args):
    return simulate_pass(*args)


def generate(scenario: Scenario, out_dir: Path, seed: int = 0, passes: int | None = None,
             vehicles: int | None = None, noise_pct: float | None = None, nominal: str = "class",
             workers: int | None = None, progress: bool | None = None) -> dict:
    """Simulate ``scenario`` into ``out_dir`` (logs/, site.toml, truth.json); returns the truth dict.

    ``passes``, ``vehicles`` and ``noise_pct`` override the scenario's (vehicles cycle when passes
    exceed vehicles); ``nominal`` is "class" (the class mean in every log) or "true" (each vehicle's
    own parameters). Invalid values raise ValueError before anything is written.
    """
    for name, value in (("passes", passes), ("vehicles", vehicles)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1):
            raise ValueError(f"{name}: must be a positive integer, got {value!r}")
    if noise_pct is not None and not (isinstance(noise_pct, (int, float, np.number)) and 0 <= noise_pct < 100):
        raise ValueError(f"noise_pct: must be a percentage in [0, 100), got {noise_pct!r}")
    if nominal not in ("class", "true"):
        raise ValueError(f"nominal: must be 'class' or 'true', got {nominal!r}")
    out_dir = Path(out_dir)
    (out_dir / "logs").mkdir(parents=True, exist_ok=True)
    for old in (out_dir / "logs").glob("*.parquet"):
        old.unlink()
    if getattr(scenario, "kind", "road") == "rail":  # a carriage's batch of runs: simfleet.rail
        return generate_rail(scenario, out_dir, seed, passes, noise_pct, nominal, workers, progress)
    if getattr(scenario, "kind", "road") == "network":  # whole drives over a network: simfleet.network
        return generate_network(scenario, out_dir, seed, passes, noise_pct, nominal)
    rng = np.random.default_rng(seed)
    n_veh = vehicles if vehicles is not None else scenario.n_vehicles
    n_pass = passes if passes is not None else (scenario.n_passes or n_veh)
    noise = scenario.noise_pct if noise_pct is None else noise_pct
    fleet = draw_fleet(scenario, n_veh, rng)
    ids = [f"veh-{i + 1:04d}" for i in range(n_veh)]
    mean, std = fleet_class(scenario)
    lanes, _ = surfaces(scenario, seed)
    beam = bridge_beam(scenario)
    plans = []
    lane_rng = np.random.default_rng([seed, 1])
    for p in range(n_pass):
        v = p % n_veh
        lane = int(draw_lane(lane_rng, n_lanes=len(lanes))) if scenario.carpet else None
        speed = float(lane_rng.uniform(*scenario.speed_range_mps))
        plans.append(PassPlan(p, ids[v], fleet[v], speed, lane, int(rng.integers(2**31))))
    jobs = []
    for plan in plans:
        surface = lanes[plan.lane] if plan.lane is not None else lanes[0]
        nominal_params = dict(plan.params) if nominal == "true" else dict(mean)
        jobs.append((scenario, plan, surface, beam, noise, out_dir, nominal_params))
    records = run_jobs(_run_one, jobs, f"sim {scenario.name}", workers, progress)

    write_site(scenario, out_dir / "site.toml", mean, std)
    truth = build_truth(scenario, seed, lanes, fleet, ids, records, beam, noise)
    (out_dir / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def write_site(scenario: Scenario, path: Path, mean: dict, std: dict) -> None:
    """The scenario's site registry (its route, its bridge if any, the vehicle class ``mean``/``std``) to ``path``."""
    bridges = []
    spec = scenario.bridge
    if spec is not None:
        bridges.append(Bridge(id=BRIDGE_ID, route=ROUTE_ID, start_chainage_m=spec.start_m, span_m=spec.span_m,
                              n_elements=spec.n_elements, E_pa=spec.E_pa, I_m4=spec.I_m4,
                              mass_per_m=spec.mass_per_m, depth_m=spec.depth_m,
                              damping_ratio=spec.damping_ratio, supports=spec.supports,
                              deck="rough" if scenario.rough_deck else "smooth"))
    site = Site(routes=(Route(id=ROUTE_ID, length_m=scenario.route_length_m),), bridges=tuple(bridges),
                vehicle_classes=(VehicleClass(model=scenario.vehicle_model, mean=mean, std=std),))
    dump_site(site, path)


def build_truth(scenario, seed, lanes, fleet, ids, records, beam, noise) -> dict:
    """What ``truth.json`` holds: the fleet-mean surface the passes drove on (``lanes`` weighted by the
    passes' ``records``), each vehicle's parameters (``fleet`` by ``ids``), the passes and the bridge."""
    grid = np.arange(0.0, scenario.route_length_m + 1e-9, TRUTH_SPACING_M)
    window = deck_window(scenario, grid)
    lane_profiles = [p.at(grid) * window for p in lanes]
    if scenario.carpet:
        counts = np.bincount([r["lane"] for r in records], minlength=len(lanes)).astype(float)
        mean_profile = np.average(lane_profiles, axis=0, weights=counts)
    else:
        mean_profile = lane_profiles[0]
    truth = {
        "scenario": scenario.name,
        "seed": seed,
        "noise_pct": noise,
        "route": {"id": ROUTE_ID, "length_m": scenario.route_length_m},
        "profile": {"start_m": 0.0, "spacing_m": TRUTH_SPACING_M, "elevation_m": mean_profile.tolist(),
                    "what": "fleet-mean tyre-filtered surface (per-lane weights = lane counts)"
                    if scenario.carpet else "tyre-filtered surface"},
        "vehicle_model": scenario.vehicle_model,
        "vehicles": {vid: params for vid, params in zip(ids, fleet)},
        "passes": records,
    }
    if beam is not None:
        spec = scenario.bridge
        ei = beam.element_ei()
        truth["bridge"] = {
            "id": BRIDGE_ID, "start_m": spec.start_m, "span_m": spec.span_m, "supports": spec.supports,
            "krot_nm_per_rad": spec.krot_nm_per_rad, "crack_x_m": spec.crack_x_m, "crack_phi": spec.crack_phi,
            "global_loss": spec.global_loss, "EI": ei.tolist(),
            "stiffness_ratio": (ei / (spec.E_pa * spec.I_m4)).tolist(),
            "f1_hz": float(natural_frequencies(beam, 1)[0]),
        }
    return truth
