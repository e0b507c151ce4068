"""The second simulation world ("ivp"): the scenarios of ``driveby sim``, simulated independently.

What differs from :mod:`simfleet.sim` — on purpose, where real data differ from simfleet's world:

* continuous-time equations of motion written here (:mod:`.vehicles`), integrated by RK4 at
  ``oversample`` × the logged rate (:mod:`.ode`), not Newmark;
* the bridge is a continuous beam reduced to its modes by Rayleigh–Ritz with modal damping
  (:mod:`.modal_beam`), E·I(x) continuous (a crack is a triangle in x), not the FE beam;
* a logger (:mod:`.logger`): anti-alias FIR, decimation on the logger's own clock phase, noise;
* every vehicle parameter (half-car axle spacings included) drawn from the registry's class prior;
* the speed wobbles slowly about its mean, the odometer reports it with a per-run scale error,
  and the log's chainage is integrated from the reported speed (plus a GNSS bias where the
  scenario has one); each pass starts after a random run-in, mid-motion.

It writes what ``driveby sim`` writes: ``logs/*.parquet``, ``site.toml`` and ``truth.json``.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.drivelog import DriveLog, DriveLogMeta, write_drive_log
from shared.profiles import RoadProfile, carpet_profile, draw_lane, iso8608_profile, tyre_filter
from shared.sensors import add_noise

from ..jobs import run_jobs
from ..scenarios import Scenario, draw_fleet, fleet_class
from ..sim import BRIDGE_ID, ROUTE_ID, TRUTH_SPACING_M, deck_window, write_site
from .logger import AntiAlias, integrated_chainage, odometer
from .modal_beam import ModalBeam, ModalBeamSpec, modal_beam
from .ode import Drive, integrate, speed
from .vehicles import vehicle_eom

#: Surface generated beyond each end of the route: the longest run-in plus the logger's tail.
SURFACE_MARGIN_M = 100.0
#: Road driven after the last logged sample, so the anti-alias filter has its future samples.
TAIL_M = 10.0


@dataclass(frozen=True)
class WorldSettings:
    """The second world's own choices (the scenario says everything else)."""

    oversample: int = 40  # simulation steps per logged sample (20 kHz behind a 500 Hz logger)
    n_modes: int = 12  # bridge modes kept
    speed_error_sd: float = 0.01  # odometer scale error per run, where the scenario sets none
    wobble: float = 0.02  # relative amplitude of the slow speed variation
    wobble_period_s: tuple[float, float] = (6.0, 15.0)
    run_in_m: tuple[float, float] = (40.0, 80.0)  # driven before the route starts, drawn per pass

    def __post_init__(self) -> None:
        if not (isinstance(self.oversample, int) and self.oversample >= 20):
            raise ValueError(f"WorldSettings.oversample: an integer >= 20 (a 10 kHz step behind 500 Hz), "
                             f"got {self.oversample!r}")
        if not 0.0 <= self.speed_error_sd < 0.2:
            raise ValueError(f"WorldSettings.speed_error_sd: must be in [0, 0.2), got {self.speed_error_sd!r}")
        if not 0.0 <= self.wobble < 0.5:
            raise ValueError(f"WorldSettings.wobble: must be in [0, 0.5), got {self.wobble!r}")
        lo, hi = self.run_in_m
        if not 20.0 <= lo <= hi <= SURFACE_MARGIN_M - 10.0:
            raise ValueError(f"WorldSettings.run_in_m: must satisfy 20 <= lo <= hi <= {SURFACE_MARGIN_M - 10}, "
                             f"got {self.run_in_m!r}")


@dataclass(frozen=True)
class PassPlan:
    index: int
    vehicle_id: str
    params: dict
    speed_mps: float
    lane: int | None
    seed: int


def surfaces(scenario: Scenario, seed: int) -> list[RoadProfile]:
    """The tyre-filtered surface(s) (one, or the carpet's lanes), from ``-SURFACE_MARGIN_M``."""
    length = scenario.route_length_m + 2 * SURFACE_MARGIN_M
    raw = carpet_profile(length, 0.01, scenario.road_class, seed).lanes if scenario.carpet \
        else [iso8608_profile(length, 0.01, scenario.road_class, seed)]
    out = []
    for p in raw:
        f = tyre_filter(p)
        out.append(RoadProfile(start_m=-SURFACE_MARGIN_M, spacing_m=f.spacing_m,
                               elevation_m=f.elevation_m - f.elevation_m.mean()))
    return out


def bridge_model(scenario: Scenario, n_modes: int) -> ModalBeam | None:
    spec = scenario.bridge
    if spec is None:
        return None
    return modal_beam(ModalBeamSpec(
        span_m=spec.span_m, EI_nm2=spec.E_pa * spec.I_m4, mass_per_m=spec.mass_per_m,
        damping_ratio=spec.damping_ratio, depth_m=spec.depth_m, krot_nm_per_rad=spec.krot_nm_per_rad,
        global_loss=spec.global_loss, crack_x_m=spec.crack_x_m, crack_phi=spec.crack_phi, n_modes=n_modes))


def draw_vehicles(scenario: Scenario, n_vehicles: int, rng: np.random.Generator) -> list[dict[str, float]]:
    """True parameters: every one drawn from the class prior the registry declares (± 3 sd at most)."""
    if scenario.fleet == "table_4_1":
        return draw_fleet(scenario, n_vehicles, rng)
    mean, std = fleet_class(scenario)
    return [{k: float(mean[k] + std[k] * np.clip(rng.standard_normal(), -3, 3)) for k in mean}
            for _ in range(n_vehicles)]


def simulate_pass(scenario: Scenario, plan: PassPlan, surface: RoadProfile, beam: ModalBeam | None,
                  noise_pct: float, out_dir: Path, nominal: dict, settings: WorldSettings) -> dict:
    rng = np.random.default_rng(plan.seed)
    eom = vehicle_eom(scenario.vehicle_model, plan.params)
    fs = scenario.sample_rate_hz
    R = settings.oversample
    window = deck_window(scenario, surface.chainage_m)
    run_in = float(rng.uniform(*settings.run_in_m))
    drive = Drive(surface=surface.elevation_m * window, surface_x0=surface.start_m, surface_dx=surface.spacing_m,
                  x0=-run_in, v0=plan.speed_mps, wobble=settings.wobble,
                  wobble_period_s=float(rng.uniform(*settings.wobble_period_s)),
                  wobble_phase=float(rng.uniform(0.0, 2 * np.pi)))
    rear = float(eom.offsets_m.min())
    end_m = scenario.route_length_m + rear
    duration = (end_m + TAIL_M + run_in) / (plan.speed_mps * (1.0 - settings.wobble))
    spec = scenario.bridge
    traj = integrate(eom, drive, duration, 1.0 / (fs * R), beam, spec.start_m if spec else 0.0)

    # The logger's clock: its first tick at a random phase once the route has begun.
    first = int(np.searchsorted(traj.x_cg, 0.0)) + int(rng.integers(R))
    aa = AntiAlias(fs, R)
    cols = np.stack([(traj.qddot if kind == "acc" else traj.qdot)[:, dof] for _, dof, kind in eom.channels], axis=1)
    logged = aa.sample(cols, first)
    t_sim = traj.t[first::R]
    x_cg = traj.x_cg[first::R]
    n = int(np.searchsorted(x_cg, end_m, side="right"))
    logged, t_sim, x_cg = logged[:n], t_sim[:n], x_cg[:n]
    noisy = {name: add_noise(logged[:, i], noise_pct, rng).astype(np.float32)
             for i, (name, _, _) in enumerate(eom.channels)}

    scale_err = float(rng.normal(0.0, _speed_error_sd(scenario, settings)))
    bias = float(rng.normal(0.0, scenario.gnss_bias_sd_m)) if scenario.gnss_bias_sd_m > 0 else 0.0
    reported = odometer(speed(drive, t_sim), scale_err)
    chainage = integrated_chainage(float(x_cg[0]) + bias, reported, 1.0 / fs)
    if scenario.gnss_jitter_sd_m > 0:
        chainage = chainage + rng.normal(0.0, scenario.gnss_jitter_sd_m, n)
    pass_id = f"p{plan.index + 1:04d}_{plan.vehicle_id}"
    meta = DriveLogMeta(
        format="driveby-drive-log", version=1, vehicle_id=plan.vehicle_id, route_id=ROUTE_ID,
        vehicle_model=scenario.vehicle_model, sample_rate_hz=fs,
        start_time_utc=f"2026-11-20T09:{(plan.index // 60) % 60:02d}:{plan.index % 60:02d}Z",
        lane_offset_m=None if plan.lane is None else float(plan.lane - 5) * 0.1,
        nominal_params=nominal, pass_id=pass_id,
    )
    log = DriveLog(meta=meta, t=np.arange(n) / fs, chainage=chainage, speed=reported, speed_measured=True,
                   channels=noisy)
    write_drive_log(out_dir / "logs" / f"{pass_id}.parquet", log)
    return {"pass_id": pass_id, "vehicle_id": plan.vehicle_id, "speed_mps": plan.speed_mps, "lane": plan.lane,
            "gnss_bias_m": bias, "speed_scale_error": scale_err, "n_samples": n,
            "gnss_error_at_start_m": float(chainage[0] - x_cg[0]), "true_chainage_at_start_m": float(x_cg[0]),
            "chainage_error_at_end_m": float(chainage[-1] - x_cg[-1]), "run_in_m": run_in,
            "speed_wobble_period_s": drive.wobble_period_s}


def _speed_error_sd(scenario: Scenario, settings: WorldSettings) -> float:
    return scenario.speed_error_sd if scenario.speed_error_sd > 0 else settings.speed_error_sd


def _run_one(args):
    return simulate_pass(*args)


def generate(scenario: Scenario, out_dir: Path, seed: int = 0, passes: int | None = None,
             vehicles: int | None = None, noise_pct: float | None = None, nominal: str = "class",
             workers: int | None = None, progress: bool | None = None,
             settings: WorldSettings = WorldSettings()) -> dict:
    """Simulate ``scenario`` in the second world into ``out_dir`` (logs/, site.toml, truth.json); returns
    the truth dict. Arguments as :func:`simfleet.sim.generate`; invalid values raise ValueError first."""
    for name, value in (("passes", passes), ("vehicles", vehicles)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1):
            raise ValueError(f"{name}: must be a positive integer, got {value!r}")
    if noise_pct is not None and not (isinstance(noise_pct, (int, float, np.number)) and 0 <= noise_pct < 100):
        raise ValueError(f"noise_pct: must be a percentage in [0, 100), got {noise_pct!r}")
    if nominal not in ("class", "true"):
        raise ValueError(f"nominal: must be 'class' or 'true', got {nominal!r}")
    if getattr(scenario, "kind", "road") == "rail":
        raise ValueError(f"{scenario.name}: the ivp world simulates road vehicles; rail worlds are simfleet.rail's")
    vehicle_eom(scenario.vehicle_model, fleet_class(scenario)[0])  # an unsupported model fails here
    out_dir = Path(out_dir)
    (out_dir / "logs").mkdir(parents=True, exist_ok=True)
    for old in (out_dir / "logs").glob("*.parquet"):
        old.unlink()
    # Streams apart from simfleet's (same seed, other draws): the worlds share no random numbers.
    rng = np.random.default_rng([seed, 19])
    n_veh = vehicles if vehicles is not None else scenario.n_vehicles
    n_pass = passes if passes is not None else (scenario.n_passes or n_veh)
    noise = scenario.noise_pct if noise_pct is None else noise_pct
    fleet = draw_vehicles(scenario, n_veh, rng)
    ids = [f"veh-{i + 1:04d}" for i in range(n_veh)]
    mean, std = fleet_class(scenario)
    lanes = surfaces(scenario, seed)
    beam = bridge_model(scenario, settings.n_modes)
    lane_rng = np.random.default_rng([seed, 19, 1])
    jobs = []
    for p in range(n_pass):
        v = p % n_veh
        lane = int(draw_lane(lane_rng, n_lanes=len(lanes))) if scenario.carpet else None
        speed_mps = float(lane_rng.uniform(*scenario.speed_range_mps))
        plan = PassPlan(p, ids[v], fleet[v], speed_mps, lane, int(rng.integers(2**31)))
        nominal_params = dict(plan.params) if nominal == "true" else dict(mean)
        jobs.append((scenario, plan, lanes[lane if lane is not None else 0], beam, noise, out_dir, nominal_params,
                     settings))
    records = run_jobs(_run_one, jobs, f"sim/ivp {scenario.name}", workers, progress)
    write_site(scenario, out_dir / "site.toml", mean, std)
    truth = build_truth(scenario, seed, lanes, fleet, ids, records, beam, noise, settings)
    (out_dir / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def build_truth(scenario: Scenario, seed: int, lanes: list[RoadProfile], fleet: list[dict], ids: list[str],
                records: list[dict], beam: ModalBeam | None, noise: float, settings: WorldSettings) -> dict:
    """``truth.json`` with the fields of :func:`simfleet.sim.build_truth` (what the scorers read), plus
    the world's own settings; the bridge's element stiffness is the mean of E·I(x) over each element."""
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
        "world": {"name": "ivp", **dataclasses.asdict(settings)},
        "route": {"id": ROUTE_ID, "length_m": scenario.route_length_m},
        "profile": {"start_m": 0.0, "spacing_m": TRUTH_SPACING_M, "elevation_m": mean_profile.tolist(),
                    "what": "fleet-mean tyre-filtered surface (per-lane weights = lane counts)"
                    if scenario.carpet else "tyre-filtered surface"},
        "vehicle_model": scenario.vehicle_model,
        "vehicles": {vid: params for vid, params in zip(ids, fleet)},
        "passes": sorted(records, key=lambda r: r["pass_id"]),
    }
    if beam is not None:
        spec = scenario.bridge
        ratio = beam.spec.element_ratio(spec.n_elements)
        truth["bridge"] = {
            "id": BRIDGE_ID, "start_m": spec.start_m, "span_m": spec.span_m, "supports": spec.supports,
            "krot_nm_per_rad": spec.krot_nm_per_rad, "crack_x_m": spec.crack_x_m, "crack_phi": spec.crack_phi,
            "global_loss": spec.global_loss, "EI": (ratio * spec.E_pa * spec.I_m4).tolist(),
            "stiffness_ratio": ratio.tolist(), "f1_hz": float(beam.frequencies_hz[0]),
            "model": f"Rayleigh–Ritz modal beam, {beam.spec.n_modes} modes kept",
        }
    return truth
