"""Rail worlds of ``driveby sim`` (thesis §3.4–3.6): one instrumented carriage making batches of runs
over a ballasted track, optionally across a short simply supported span (a culvert).

Each run has its own body mass ``mv``, pitch inertia ``Iv`` and speed ``v`` (passengers, timetable);
the carriage's global properties are the Table 3.1 values with 5 % random error drawn once per
carriage (the thesis's "inaccuracy of a global calibration"), and the site registry only declares the
class means. Speed comes to the logs as a GNSS speed ~2 % off (and the chainage with it).

The train–track(–bridge) model (:mod:`shared.dynamics.train_track`) runs at half the logger's step
with Newmark γ = 0.6, the edge's inverse at the logger's step with γ = 0.8 (no inverse crime). As in
the thesis's blind test, a log starts when the simulation does, with the carriage in static
equilibrium on the track at chainage 0 (body centre of gravity) and running at its speed.

The blind test's bridge (§3.6): "Global damage was simulated but, for each damaged bridge, there
were small random differences (5% standard deviation) between element flexural rigidities
(stiffnesses), reflecting the natural variation in a corroded bridge." We read that variation as a
property of the span (as built, as corroded): it is drawn **once per bridge** (per track profile and
seed) and every state, the healthy one included, has it; the seven states differ only by the global
factor, E·I_state = (1 − loss)·E·I_healthy element by element. So each state's true damage level
relative to the healthy state — what D1/D2 of eq. 3.24 measure against the healthy batch — is its
nominal loss exactly. (Drawn afresh per state, the scatter itself would change the span between
states — a state's static line can lose several points more or less than its nominal loss — and no
method could be scored against the nominal level.) ``truth.json`` keeps the realised E·I per element and the
healthy span's, so the loss against the design drawings (the "effective" level) is reported too.

Each state's batch is a different set of journeys (``RailScenario.batch``: other run properties and
sensor noise; the same carriage, track and span), as the thesis's "data from 50 different train
journeys" for each state.

``rail-track-prior`` and ``rail-bridge-prior-loss0/10`` are a second kind of carriage: its lengths
are known no better than its other globals (the class declares ±5 % for all), and it is drawn with
its bogie spacing 6.5 % short (``RailScenario.carriage_error``), so every speed the wheels' delays
give against the class's spacing is 6.8 % off until the batch calibrates the lengths.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from shared.drivelog import DriveLog, DriveLogMeta, write_drive_log
from shared.dynamics.train_track import simulate_train_track
from shared.registry import Bridge, Route, Site, VehicleClass, dump_site
from shared.sensors import add_noise
from shared.track import BridgeSpan, RailIrregularity, TrackParams, build_track, damaged_ei_factor
from shared.vehicles.carriage import TABLE_3_1, Carriage

from .jobs import run_jobs

ROUTE_ID = "L1"
BRIDGE_ID = "C1"
VEHICLE_ID = "car-0001"
SLEEPER_M = 0.6
TRACK_BEFORE_M = 18.0  # rail before route chainage 0 (a whole number of sleeper spacings)
TRACK_AFTER_M = 25.2  # the leading wheel runs 2·(Lv + Lb) past the end of the route
SUBSTEPS = 2  # the simulator runs at half the logger's step
TRUTH_SPACING_M = 0.05
GLOBAL_NAMES = ("mb", "Ib", "mw", "kp", "cp", "ks", "cs", "Lb", "Lv")
RUN_NAMES = ("mv", "Iv", "v")

#: True damage level (global E·I loss) of blind-test states 1..7 (thesis Table 3.6; state 7 healthy).
STATE_LOSS = (0.03, 0.13, 0.11, 0.07, 0.05, 0.08, 0.0)


@dataclasses.dataclass(frozen=True)
class RailBridgeSpec:
    """A simply supported culvert span under the track (§3.6: 10.2 m), and its true condition."""

    start_m: float = 120.0
    span_m: float = 10.2
    E_pa: float = 35e9
    I_m4: float = 0.2
    mass_per_m: float = 8000.0
    depth_m: float = 0.8
    damping_ratio: float = 0.03
    global_loss: float = 0.0
    #: Per-element E·I scatter of the span (relative sd), drawn once per bridge: every state has it.
    element_sd: float = 0.05

    @property
    def n_elements(self) -> int:
        return int(round(self.span_m / SLEEPER_M))


@dataclasses.dataclass(frozen=True)
class RailScenario:
    """A batch of runs of one instrumented carriage (``kind = "rail"`` dispatches generation here)."""

    name: str
    description: str
    kind: str = "rail"
    vehicle_model: str = "carriage"
    n_passes: int = 50
    route_length_m: float = 150.0
    profile: int = 1  # track profile (irregularity and support field) number
    bridge: RailBridgeSpec | None = None
    noise_pct: float = 2.0
    speed_mean_mps: float = 30.0
    speed_sd_mps: float = 1.5
    mv_sd: float = 0.10  # relative sd of a run's body mass
    Iv_extra_sd: float = 0.05  # Iv = (Iv/mv)_class · mv · (1 + this · N(0,1))
    global_sd: float = 0.05  # relative error of the carriage's global masses, stiffnesses, dampings (once)
    length_sd: float = 0.002  # relative error of its lengths Lb, Lv (design drawings: a few mm)
    speed_error_sd: float = 0.02  # relative GNSS speed error per run
    sample_rate_hz: float = 500.0
    n_vehicles: int = 1
    #: Which set of journeys (run properties, sensor noise): the blind test's states are different
    #: journeys of the same carriage over the same track (0: the default set).
    batch: int = 0
    #: Relative errors of named global properties that replace their random draws ((name, error), …):
    #: a carriage at a chosen point of its class prior (e.g. its bogie spacing 6.5 % short).
    carriage_error: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        unknown = {k for k, _ in self.carriage_error} - set(GLOBAL_NAMES)
        if unknown:
            raise ValueError(f"RailScenario {self.name}: carriage_error names no global property: {sorted(unknown)}")

    @property
    def passes(self) -> int:
        return self.n_passes


def rail_scenarios() -> dict[str, RailScenario]:
    out = [RailScenario("rail-track", "50 runs of a 4-axle carriage (Table 3.1; mv, Iv, v per run), 150 m "
                        "ballasted track, GNSS speed ~2 % off, 2 % noise")]
    for state, loss in enumerate(STATE_LOSS, start=1):
        for profile in (1, 2):
            what = "healthy" if loss == 0 else f"{loss:.0%} global E·I loss"
            out.append(RailScenario(
                f"rail-bridge-state{state}-profile{profile}",
                f"blind test (§3.6) state {state}: 50 carriage runs, 120 m track then a 10.2 m culvert ({what}), "
                f"track profile {profile}; the span's 5 % per-element E·I scatter is the same in every state",
                route_length_m=160.0, profile=profile, bridge=RailBridgeSpec(global_loss=loss), batch=state))
    # A carriage whose globals, lengths included, are known only to the class's ±5 % (the registry
    # declares that sd), drawn at its bogie spacing 6.5 % short: the speed scale the bogies' delay
    # sets is then the batch's to find, with the GNSS speeds' mean as its anchor.
    prior = dict(length_sd=0.05, carriage_error=(("Lv", -0.065),))
    out.append(RailScenario("rail-track-prior", "50 runs of a carriage whose globals (Lv, Lb, bogie masses, "
                            "suspension) are drawn from a ±5 % class prior, its bogie spacing Lv 6.5 % below the "
                            "class mean; 150 m ballasted track, GNSS speed ~2 % off, 2 % noise", **prior))
    for state, loss in ((1, 0.0), (2, 0.10)):
        what = "healthy" if loss == 0 else f"{loss:.0%} global E·I loss"
        out.append(RailScenario(
            f"rail-bridge-prior-loss{round(100 * loss)}",
            f"28 runs of the rail-track-prior carriage, 120 m track then a 10.2 m culvert ({what}); the span's 5 % "
            "per-element E·I scatter is the same in both states", n_passes=28, route_length_m=160.0,
            bridge=RailBridgeSpec(global_loss=loss), batch=state, **prior))
    return {s.name: s for s in out}


def class_prior(scenario: RailScenario) -> tuple[dict[str, float], dict[str, float]]:
    """What the registry declares for the carriage class: Table 3.1 with the run means, and spreads."""
    mean = dict(TABLE_3_1)
    mean["v"] = scenario.speed_mean_mps
    std = {k: (scenario.length_sd if k in ("Lb", "Lv") else scenario.global_sd) * abs(v) for k, v in mean.items()}
    std["mv"] = scenario.mv_sd * mean["mv"]
    std["Iv"] = float(np.hypot(scenario.mv_sd, scenario.Iv_extra_sd)) * mean["Iv"]
    std["v"] = scenario.speed_sd_mps
    return mean, std


def draw_carriage(scenario: RailScenario, seed: int) -> dict[str, float]:
    """The instrumented carriage's true global properties (Table 3.1 with random error, or the
    scenario's chosen error where it names one)."""
    rng = np.random.default_rng([seed, 7])
    chosen = dict(scenario.carriage_error)
    out = {}
    for k in GLOBAL_NAMES:
        # drawn for every name, chosen or not, so the others' draws do not depend on the choice
        draw = (scenario.length_sd if k in ("Lb", "Lv") else scenario.global_sd) * np.clip(rng.standard_normal(), -2.5, 2.5)
        out[k] = float(TABLE_3_1[k] * (1.0 + chosen.get(k, draw)))
    return out


def draw_runs(scenario: RailScenario, n: int, seed: int) -> list[dict[str, float]]:
    """Run properties: mv, Iv, true v and the GNSS speed of each run."""
    rng = np.random.default_rng(_batch_key(scenario, seed, 11))
    ratio = TABLE_3_1["Iv"] / TABLE_3_1["mv"]
    runs = []
    for _ in range(n):
        z = np.clip(rng.standard_normal(4), -2.5, 2.5)
        mv = TABLE_3_1["mv"] * (1.0 + scenario.mv_sd * z[0])
        iv = ratio * mv * (1.0 + scenario.Iv_extra_sd * z[1])
        v = scenario.speed_mean_mps + scenario.speed_sd_mps * z[2]
        runs.append({"mv": float(mv), "Iv": float(iv), "v": float(v),
                     "v_gnss": float(v * (1.0 + scenario.speed_error_sd * z[3]))})
    return runs


def _batch_key(scenario: RailScenario, seed: int, *key: int) -> list[int]:
    """Seed of what differs between journeys (run properties, noise); batch 0's key has no batch entry,
    so a scenario without batches draws the same journeys as its batch 0."""
    return [seed, *key[:1], *([scenario.batch] if scenario.batch else []), *key[1:]]


def bridge_span(scenario: RailScenario, seed: int, global_loss: float | None = None) -> BridgeSpan | None:
    """The scenario's span on the track (``global_loss``: another state of the same bridge).

    The per-element scatter depends on the seed and the track profile only, not on the state (module
    docstring), so E·I of a state is (1 − loss) times the healthy span's, element by element.
    """
    b = scenario.bridge
    if b is None:
        return None
    loss = b.global_loss if global_loss is None else global_loss
    rng = np.random.default_rng([seed, scenario.profile, 13])
    factor = damaged_ei_factor(b.n_elements, loss, b.element_sd, rng)
    return BridgeSpan(TRACK_BEFORE_M + b.start_m, b.span_m, b.E_pa, b.I_m4, b.mass_per_m, b.damping_ratio,
                      ei_factor=factor)


def track_of(scenario: RailScenario, seed: int):
    """The track (and span) of a scenario; chainage 0 is at track coordinate ``TRACK_BEFORE_M``."""
    length = TRACK_BEFORE_M + scenario.route_length_m + TRACK_AFTER_M
    length = SLEEPER_M * np.ceil(length / SLEEPER_M - 1e-9)
    return build_track(TrackParams(length_m=float(length)), rng=np.random.default_rng([seed, scenario.profile, 3]),
                       bridge=bridge_span(scenario, seed))


def irregularity_of(scenario: RailScenario, seed: int) -> RailIrregularity:
    return RailIrregularity(seed=1000 * seed + scenario.profile, min_wavelength_m=1.0, max_wavelength_m=80.0)


def simulate_run(scenario: RailScenario, index: int, carriage: dict, run: dict, seed: int, noise_pct: float,
                 out_dir: Path, nominal: dict) -> dict:
    track = track_of(scenario, seed)
    irr = irregularity_of(scenario, seed)
    car = Carriage(**carriage, mv=run["mv"], Iv=run["Iv"], v=run["v"])
    fs = scenario.sample_rate_hz
    dt = 1.0 / (fs * SUBSTEPS)
    rear = float(-car.wheel_offsets_m().min())
    duration = (scenario.route_length_m + rear) / car.v
    probe = None
    if scenario.bridge is not None:
        probe = [TRACK_BEFORE_M + scenario.bridge.start_m + scenario.bridge.span_m / 2]
    resp = simulate_train_track(car, track, lambda x: irr.elevation(x), TRACK_BEFORE_M, duration, dt,
                                probe_x_m=probe)
    keep = slice(None, None, SUBSTEPS)
    channels = resp.channels[keep]
    n = len(channels)
    rng = np.random.default_rng(_batch_key(scenario, seed, 17, index))
    names = ("bogie1_acc", "bogie1_pitch_rate", "bogie2_acc", "bogie2_pitch_rate")
    noisy = {name: add_noise(channels[:, i], noise_pct, rng).astype(np.float32) for i, name in enumerate(names)}
    t = np.arange(n) / fs
    pass_id = f"run{index + 1:03d}"
    meta = DriveLogMeta(
        format="driveby-drive-log", version=1, vehicle_id=VEHICLE_ID, route_id=ROUTE_ID,
        vehicle_model="carriage", sample_rate_hz=fs,
        start_time_utc=f"2026-11-20T{6 + index // 60:02d}:{index % 60:02d}:00Z",
        lane_offset_m=None, nominal_params=nominal, pass_id=pass_id,
    )
    log = DriveLog(meta=meta, t=t, chainage=run["v_gnss"] * t, speed=np.full(n, run["v_gnss"]), speed_measured=True,
                   channels=noisy)
    write_drive_log(out_dir / "logs" / f"{pass_id}.parquet", log)
    rec = {"pass_id": pass_id, "vehicle_id": VEHICLE_ID, **run, "speed_mps": run["v"], "n_samples": n,
           "speed_scale_error": run["v_gnss"] / run["v"] - 1.0}
    ap = resp.ap[keep]
    rec["ap_mean_m"] = [float(a) for a in ap.mean(axis=0)]
    if probe is not None:
        rec["midspan_rail_deflection_min_m"] = float(resp.probes[keep, 0].min())
    return rec


def _run_one(args):
    return simulate_run(*args)


def generate_rail(scenario: RailScenario, out_dir: Path, seed: int = 0, passes: int | None = None,
                  noise_pct: float | None = None, nominal: str = "class", workers: int | None = None,
                  progress: bool | None = None) -> dict:
    """Simulate a rail batch into ``out_dir`` (logs/, site.toml, truth.json); returns the truth dict.

    Called by :func:`simfleet.sim.generate`, which validates the arguments and prepares ``out_dir``
    (one carriage makes every run, so there is no vehicle count). ``nominal``: "class" writes the
    class mean into each log, "true" the run's own properties.
    """
    n = passes if passes is not None else scenario.n_passes
    noise = scenario.noise_pct if noise_pct is None else noise_pct
    carriage = draw_carriage(scenario, seed)
    runs = draw_runs(scenario, n, seed)
    mean, std = class_prior(scenario)
    jobs = []
    for i, run in enumerate(runs):
        nom = dict(mean) if nominal == "class" else {**carriage, **{k: run[k] for k in RUN_NAMES}}
        jobs.append((scenario, i, carriage, run, seed, noise, out_dir, nom))
    records = run_jobs(_run_one, jobs, f"sim {scenario.name}", workers, progress)
    _write_site(scenario, out_dir / "site.toml", mean, std)
    truth = _truth(scenario, seed, carriage, records, noise)
    (out_dir / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def _write_site(scenario: RailScenario, path: Path, mean: dict, std: dict) -> None:
    bridges = []
    b = scenario.bridge
    if b is not None:
        bridges.append(Bridge(id=BRIDGE_ID, route=ROUTE_ID, start_chainage_m=b.start_m, span_m=b.span_m,
                              n_elements=b.n_elements, E_pa=b.E_pa, I_m4=b.I_m4, mass_per_m=b.mass_per_m,
                              depth_m=b.depth_m, damping_ratio=b.damping_ratio, supports="simply_supported"))
    site = Site(routes=(Route(id=ROUTE_ID, length_m=scenario.route_length_m),), bridges=tuple(bridges),
                vehicle_classes=(VehicleClass(model="carriage", mean=mean, std=std),))
    dump_site(site, path)


def _truth(scenario: RailScenario, seed: int, carriage: dict, records: list[dict], noise: float) -> dict:
    grid = np.arange(0.0, scenario.route_length_m + 1e-9, TRUTH_SPACING_M)
    irr = irregularity_of(scenario, seed)
    truth = {
        "scenario": scenario.name,
        "kind": "rail",
        "seed": seed,
        "noise_pct": noise,
        "route": {"id": ROUTE_ID, "length_m": scenario.route_length_m},
        "profile": {"start_m": 0.0, "spacing_m": TRUTH_SPACING_M,
                    "elevation_m": irr.elevation(grid + TRACK_BEFORE_M).tolist(),
                    "what": "unloaded rail irregularity (the AP adds the track's deflection under the wheels)"},
        "vehicle_model": "carriage",
        "vehicles": {VEHICLE_ID: carriage},
        "passes": records,
    }
    b = scenario.bridge
    if b is not None:
        ei = bridge_span(scenario, seed).ei_factor * b.E_pa * b.I_m4
        healthy = bridge_span(scenario, seed, 0.0).ei_factor * b.E_pa * b.I_m4
        truth["bridge"] = {"id": BRIDGE_ID, "start_m": b.start_m, "span_m": b.span_m, "supports": "simply_supported",
                           "global_loss": b.global_loss, "element_sd": b.element_sd, "EI": ei.tolist(),
                           "EI_healthy": healthy.tolist(), "stiffness_ratio": (ei / (b.E_pa * b.I_m4)).tolist()}
    return truth
