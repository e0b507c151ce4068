"""The network world of ``driveby sim``: routes with coordinates, whole drives with stops and turns.

Four routes share junctions (a triangle and a spur with a bridge). A trip drives several routes
in a row — some against their chainage — from rest: it accelerates, cruises, brakes to a stop at
lights, brakes once mid-route, and stops at the end. Its logger records what a phone or
telematics box records (interfaces.md §5): GNSS fixes at ``gnss_rate_hz`` with a slowly wandering
error and white noise, a dropout of ``dropout_s`` (a tunnel), and a raw IMU in its own tilted
frame with timestamp jitter and a gap.

Vertical dynamics: the quarter-car rides the route's surface at the trip's varying speed
(contact elevation r(x(t)) and rate ṙ = ẋ·r'(x), integrated by the project's Newmark integrator
on a 4× finer grid). Braking and acceleration also pitch the body: the load transfer
M·a·h/L acts on the sprung mass over the sensor's axle (``h_over_l``), so a braking stretch
leaves a transient in ``body_acc`` that is not road. The bridge is a rigid part of the road here
(the coupled VBI solver assumes constant speed): the network world tests matching, fusion and
segmentation, the bridge worlds test bridges.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
from pyproj import CRS, Transformer

from shared.drivelog import DriveLog, DriveLogMeta, write_drive_log
from shared.dynamics.forward import measured_channels, static_equilibrium
from shared.dynamics.newmark import integrate, newmark_constants
from shared.geo import RouteGeometry
from shared.profiles import RoadProfile, iso8608_profile, tyre_filter
from shared.registry import Bridge, Route, Site, VehicleClass, dump_site
from shared.sensors import add_noise
from shared.vbi import simulate_vbi
from shared.vehicles import vehicle_from_params
from shared.vehicles.base import GRAVITY

SUBSTEPS = 4  # the simulator integrates 4× finer than the logger's nominal rate
RUN_IN_M = 30.0  # a clean pass is already driving when its logger's record starts
SIM_GAMMA = 0.5  # average acceleration: no numerical damping in the truth
ORIGIN = (52.0, 4.37)  # lat, lon of the network's local frame
TAPER_M = 8.0  # each route's surface tapers to zero over its ends, so routes join without a step
TRUTH_SPACING_M = 0.05
CORNER_M = 15.0

#: Route id → vertices in the local frame (east, north metres); chainage runs along the list.
ROUTES_EN = {
    "R1": [(0.0, 0.0), (300.0, 12.0), (600.0, 0.0)],
    "R2": [(600.0, 0.0), (660.0, 200.0), (600.0, 420.0)],
    "R3": [(600.0, 420.0), (260.0, 320.0), (0.0, 0.0)],
    "R4": [(600.0, 0.0), (800.0, -40.0), (980.0, -60.0)],
}
BRIDGE = {"id": "B1", "route": "R4", "start_m": 160.0, "span_m": 20.0}

#: Trips: (route, +1 along chainage / −1 against). Routes meet end to start.
TRIPS = [
    [("R1", 1), ("R2", 1), ("R3", 1)],
    [("R1", 1), ("R4", 1)],
    [("R3", -1), ("R2", -1), ("R4", 1)],
    [("R2", 1), ("R3", 1), ("R1", 1)],
]


@dataclasses.dataclass(frozen=True)
class NetworkScenario:
    """A network world; ``kind`` tells ``simfleet.sim.generate`` to hand it to `generate_network`."""

    name: str
    description: str
    kind: str = "network"
    vehicle_model: str = "quarter_car"
    n_vehicles: int = 4
    n_passes: int | None = None  # trips; default one per vehicle
    road_class: str = "A"
    noise_pct: float = 2.0
    sample_rate_hz: float = 200.0
    cruise_mps: tuple[float, float] = (11.0, 15.0)
    accel_mps2: float = 1.5
    brake_mps2: float = 2.5
    stop_s: float = 4.0
    h_over_l: float = 0.2
    gnss_rate_hz: float = 5.0
    gnss_wander_sd_m: float = 1.2  # slowly varying error, per axis
    gnss_wander_tau_s: float = 30.0
    gnss_noise_sd_m: float = 0.7  # white, per axis
    dropout_s: float = 8.0
    imu_jitter_steps: int = 1  # ± fine steps of timestamp jitter
    imu_gap_s: float = 0.6
    tilt_deg: tuple[float, float, float] = (12.0, -20.0, 115.0)  # logger roll, pitch, yaw in the vehicle
    fleet_mean: tuple[tuple[str, float], ...] = ()  # the vehicle class: (name, value) pairs
    fleet_std: tuple[tuple[str, float], ...] = ()
    clean: bool = False  # the reference: the same roads as clean single-route passes, no drives

    @property
    def passes(self) -> int:
        return self.n_passes if self.n_passes is not None else self.n_vehicles


def network_scenarios(fleet_table: dict) -> dict[str, NetworkScenario]:
    """The network worlds, their vehicles drawn from ``fleet_table`` (``{"mean": {...}, "std": {...}}``)."""
    cls = dict(fleet_mean=tuple(fleet_table["mean"].items()), fleet_std=tuple(fleet_table["std"].items()))
    s = NetworkScenario("network", "4 quarter-car trips over a 4-route network with coordinates (bridge on R4): "
                        "stops, braking, turns, 5 Hz GNSS with metres of error and a dropout, a tilted 200 Hz "
                        "phone IMU with jitter and a gap", **cls)
    ref = NetworkScenario("network-clean", "the network's roads and vehicles as clean single-route passes (each "
                          "vehicle once along every route at its field trip's cruise speed, exact chainage): the "
                          "reference",
                          clean=True, **cls)
    return {s.name: s, ref.name: ref}


def local_to_latlon(east, north) -> tuple[np.ndarray, np.ndarray]:
    crs = CRS.from_dict({"proj": "aeqd", "lat_0": ORIGIN[0], "lon_0": ORIGIN[1], "datum": "WGS84", "units": "m"})
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(east, north)
    return np.asarray(lat, float), np.asarray(lon, float)


def latlon_to_local(lat, lon) -> tuple[np.ndarray, np.ndarray]:
    crs = CRS.from_dict({"proj": "aeqd", "lat_0": ORIGIN[0], "lon_0": ORIGIN[1], "datum": "WGS84", "units": "m"})
    x, y = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lon, lat)
    return np.asarray(x, float), np.asarray(y, float)


def geometries() -> dict[str, RouteGeometry]:
    out = {}
    for rid, pts in ROUTES_EN.items():
        # Densified so that the geodesic polyline follows the local straight segments.
        e, n = _densify(np.array(pts, float), 10.0)
        lat, lon = local_to_latlon(e, n)
        out[rid] = RouteGeometry.from_latlon(np.column_stack([lat, lon]))
    return out


def _densify(pts: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    seg = np.hypot(*np.diff(pts, axis=0).T)
    s = np.concatenate(([0.0], np.cumsum(seg)))
    q = np.unique(np.concatenate([np.arange(0.0, s[-1], step), s]))
    return np.interp(q, s, pts[:, 0]), np.interp(q, s, pts[:, 1])


def route_surfaces(geoms: dict[str, RouteGeometry], road_class: str, seed: int) -> dict[str, RoadProfile]:
    """Each route's tyre-filtered surface on its chainage, tapered to 0 over ``TAPER_M`` at both ends."""
    out = {}
    for i, (rid, g) in enumerate(sorted(geoms.items())):
        p = tyre_filter(iso8608_profile(g.length_m + 2.0, 0.01, road_class, np.random.default_rng([seed, 7, i])))
        x = p.start_m + np.arange(len(p.elevation_m)) * p.spacing_m
        d = np.minimum(x, g.length_m - x)
        w = 0.5 - 0.5 * np.cos(np.pi * np.clip(d / TAPER_M, 0.0, 1.0))
        y = (p.elevation_m - p.elevation_m.mean()) * w
        out[rid] = RoadProfile(start_m=p.start_m, spacing_m=p.spacing_m, elevation_m=y)
    return out


def speed_profile(path_len: float, stops_at: list[float], cruise: float, accel: float, brake: float, stop_s: float,
                  dt: float, brake_at: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance, speed and acceleration along a path of ``path_len`` m, from rest to rest, sampled
    every ``dt``: accelerate at ``accel`` to ``cruise``, brake at ``brake`` to stop ``stop_s`` at each
    of ``stops_at`` (m), and at ``brake_at`` slow to half the cruise and speed up again. The
    acceleration is smoothed by a 0.4 s lag (a driver's jerk)."""
    stops = sorted([*stops_at, path_len])
    s = v = a = 0.0
    S, V, A = [], [], []
    wait = 0.0
    nxt = 0
    tau = 0.4
    slow_done = brake_at is None
    for _ in range(int(3600 / dt)):
        S.append(s)
        V.append(v)
        A.append(a)
        if nxt >= len(stops):
            break
        if wait > 0:
            wait -= dt
            a_cmd = 0.0
            if wait <= 0 and nxt >= len(stops):
                break
        else:
            to_stop = stops[nxt] - s
            # The braking curve with margin, so the lagged acceleration still stops short of the line.
            v_lim = math.sqrt(2.0 * brake * 0.8 * max(to_stop - 1.0, 0.0))
            target = min(cruise, v_lim)
            if not slow_done and brake_at - 40.0 < s < brake_at:
                target = min(target, 0.5 * cruise)
            if not slow_done and s >= brake_at:
                slow_done = True
            a_cmd = float(np.clip(2.0 * (target - v), -brake, accel))
            if to_stop < 1.5 and v < 0.4:  # creeping the last metre: brake to a standstill
                # Braking, not a jump of the speed: an accelerometer sees every change of speed.
                a = -min(brake, v / dt)
                v = max(v + a * dt, 0.0)
                s += v * dt
                if v == 0.0:
                    a = 0.0
                    nxt += 1
                    wait = stop_s
                    if nxt >= len(stops):
                        break
                continue
        a += (a_cmd - a) * dt / tau
        v = max(v + a * dt, 0.0)
        if v == 0.0 and a < 0:
            a = 0.0
        s += v * dt
    S.append(s)
    V.append(0.0)
    A.append(0.0)
    return np.array(S), np.array(V), np.array(A)


def logger_rotation(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """Logger ← vehicle rotation (vehicle axes: x forward, y left, z up)."""
    r, p, y = np.radians([roll_deg, pitch_deg, yaw_deg])
    Rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    Ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    Rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    return (Rz @ Ry @ Rx).T


def trip_cruise(sc: NetworkScenario, rng: np.random.Generator) -> float:
    """A trip's cruise speed (m/s): the first draw of the trip's own generator."""
    return float(rng.uniform(*sc.cruise_mps))


def trip_seeds(rng: np.random.Generator, n_trips: int) -> list[int]:
    """The trips' seeds, drawn from the world's generator right after its vehicles."""
    return [int(rng.integers(2**31)) for _ in range(n_trips)]


def simulate_trip(sc: NetworkScenario, legs: list[tuple[str, int]], geoms: dict[str, RouteGeometry],
                  surfaces: dict[str, RoadProfile], params: dict, vehicle_id: str, index: int, seed: int,
                  nominal: dict | None) -> tuple[DriveLog, dict]:
    """One trip: its drive log (no chainage, no route) and its truth at the logger's samples."""
    rng = np.random.default_rng(seed)
    fs = sc.sample_rate_hz
    dt = 1.0 / (fs * SUBSTEPS)
    lengths = [geoms[r].length_m for r, _ in legs]
    starts = np.concatenate(([0.0], np.cumsum(lengths)))
    cruise = trip_cruise(sc, rng)
    # Stops at every other junction and at a light on the last route; a braking along the first.
    stops = [float(starts[k]) for k in range(1, len(legs)) if k % 2 == 1]
    stops.append(float(starts[-2] + 0.7 * lengths[-1]))  # a light along the last route
    s, v, a_long = speed_profile(float(starts[-1]), stops, cruise, sc.accel_mps2, sc.brake_mps2, sc.stop_s, dt,
                                 brake_at=float(starts[0] + 0.6 * lengths[0]))
    n = len(s)
    t = np.arange(n) * dt
    leg = np.clip(np.searchsorted(starts, s, side="right") - 1, 0, len(legs) - 1)
    along = s - starts[leg]
    sign = np.array([d for _, d in legs], float)[leg]
    length = np.array(lengths)[leg]
    along = np.clip(along, 0.0, length)  # the final stop may overshoot the path's end by centimetres
    chain = np.where(sign > 0, along, length - along)
    route_idx = leg
    # Surface under the tyre and its rate.
    r = np.zeros(n)
    rdot = np.zeros(n)
    lat = np.zeros(n)
    lon = np.zeros(n)
    for k, (rid, _) in enumerate(legs):
        m = route_idx == k
        prof = surfaces[rid]
        r[m] = prof.at(chain[m])
        h = 1e-3
        slope = (prof.at(chain[m] + h) - prof.at(np.clip(chain[m] - h, 0, None))) / (2 * h)
        rdot[m] = slope * v[m] * sign[m]
        lat[m], lon[m] = geoms[rid].position(chain[m])
    vehicle = vehicle_from_params(sc.vehicle_model, params)
    system = vehicle.system()
    force = (system.kc * r[:, None] + system.cc * rdot[:, None]) @ system.G.T
    # Load transfer of braking/acceleration onto the body over the sensor's axle (down when braking).
    force[:, 0] += system.M[0, 0] * sc.h_over_l * a_long
    c = newmark_constants(dt, SIM_GAMMA)
    state = integrate(system.M, system.C, system.K, force, c, u0=static_equilibrium(system, r[:1]))
    body = measured_channels(system, state)[:, 0]
    # Heading and curvature of the path (for the lateral acceleration and yaw rate).
    x, y = latlon_to_local(lat, lon)
    # Curvature along the path, the polyline's corners rounded over CORNER_M of road (a driver's
    # line), then yaw rate = v·κ: a vehicle standing at a corner does not turn.
    grid = np.arange(0.0, s[-1] + 0.1, 0.1)
    gx, gy = np.interp(grid, s, x), np.interp(grid, s, y)
    heading = np.unwrap(np.arctan2(np.gradient(gy), np.gradient(gx)))
    width = int(CORNER_M / 0.1) | 1
    kappa_grid = np.convolve(np.gradient(heading, grid), np.ones(width) / width, mode="same")
    kappa = np.interp(s, grid, kappa_grid)
    yaw_rate = v * kappa
    a_lat = v * yaw_rate
    # Logger samples: every SUBSTEPS fine steps, jittered, with a gap in the second leg's cruise.
    k = np.arange(0, n - SUBSTEPS, SUBSTEPS)
    k = np.clip(k + rng.integers(-sc.imu_jitter_steps, sc.imu_jitter_steps + 1, len(k)), 0, n - 1)
    k = np.unique(k)
    gap_at = float(starts[1] + 0.5 * lengths[1]) if len(legs) > 1 else 0.5 * lengths[0]
    g0 = np.searchsorted(s[k], gap_at)
    k = np.delete(k, slice(g0, g0 + int(sc.imu_gap_s * fs)))
    noisy_body = add_noise(body[k], sc.noise_pct, rng)
    f_vehicle = np.column_stack([a_long[k], a_lat[k], noisy_body + GRAVITY])
    f_vehicle[:, :2] += rng.normal(0.0, 0.02, (len(k), 2))
    gyro_vehicle = np.column_stack([np.zeros(len(k)), np.zeros(len(k)), yaw_rate[k]]) + rng.normal(0.0, 1e-3, (len(k), 3))
    R = logger_rotation(*sc.tilt_deg)
    acc_log = f_vehicle @ R.T
    gyro_log = gyro_vehicle @ R.T
    # GNSS: fixes every 1/gnss_rate_hz at the nearest logger sample, wandering error + noise, a dropout.
    tk = t[k]
    fix_rows = np.unique(np.searchsorted(tk, np.arange(0.0, tk[-1], 1.0 / sc.gnss_rate_hz)))
    fix_rows = fix_rows[fix_rows < len(k)]
    drop_at = float(starts[0] + 0.3 * lengths[0])
    t_drop = tk[np.searchsorted(s[k], drop_at)]
    fix_rows = fix_rows[(tk[fix_rows] < t_drop) | (tk[fix_rows] > t_drop + sc.dropout_s)]
    tf = tk[fix_rows]
    phi = np.exp(-np.diff(tf, prepend=tf[0]) / sc.gnss_wander_tau_s)
    wander = np.zeros((len(tf), 2))
    wander[0] = rng.normal(0.0, sc.gnss_wander_sd_m, 2)
    for i in range(1, len(tf)):
        wander[i] = phi[i] * wander[i - 1] + math.sqrt(1 - phi[i] ** 2) * rng.normal(0.0, sc.gnss_wander_sd_m, 2)
    err = wander + rng.normal(0.0, sc.gnss_noise_sd_m, (len(tf), 2))
    fx, fy = latlon_to_local(lat[k][fix_rows], lon[k][fix_rows])
    flat, flon = local_to_latlon(fx + err[:, 0], fy + err[:, 1])
    la = np.full(len(k), np.nan)
    lo = np.full(len(k), np.nan)
    acc_m = np.full(len(k), np.nan, np.float32)
    la[fix_rows], lo[fix_rows] = flat, flon
    acc_m[fix_rows] = math.hypot(sc.gnss_wander_sd_m, sc.gnss_noise_sd_m)
    pass_id = f"trip{index + 1:03d}_{vehicle_id}"
    meta = DriveLogMeta("driveby-drive-log", 1, vehicle_id, None, sc.vehicle_model, fs,
                        f"2026-11-20T09:{index % 60:02d}:00Z", None, nominal, pass_id)
    imu = {n_: acc_log[:, i].astype(np.float32) for i, n_ in enumerate(("acc_x", "acc_y", "acc_z"))}
    imu |= {n_: gyro_log[:, i].astype(np.float32) for i, n_ in enumerate(("gyro_x", "gyro_y", "gyro_z"))}
    log = DriveLog(meta, tk.copy(), None, None, {}, True, la, lo, acc_m, imu)
    truth = {"pass_id": pass_id, "vehicle_id": vehicle_id, "legs": [[r_, d] for r_, d in legs], "cruise_mps": cruise,
             "t": tk, "route": [legs[i][0] for i in route_idx[k]], "chainage": chain[k], "speed": v[k],
             "long_acc": a_long[k], "fix_t": tf, "fix_error_m": np.hypot(err[:, 0], err[:, 1])}
    return log, truth


def generate_network(sc: NetworkScenario, out_dir: Path, seed: int = 0, passes: int | None = None,
                     noise_pct: float | None = None, nominal: str = "class") -> dict:
    """Write ``logs/`` (one drive per trip), ``site.toml`` (routes with geometry, the bridge) and
    ``truth.json`` (route surfaces; per trip the true route, chainage and speed at 10 Hz)."""
    out_dir = Path(out_dir)
    (out_dir / "logs").mkdir(parents=True, exist_ok=True)
    if noise_pct is not None:
        sc = dataclasses.replace(sc, noise_pct=noise_pct)
    n_trips = passes if passes is not None else sc.passes
    geoms = geometries()
    surfaces = route_surfaces(geoms, sc.road_class, seed)
    rng = np.random.default_rng(seed)
    mean, std = dict(sc.fleet_mean), dict(sc.fleet_std)
    fleet = [{k_: float(mean[k_] + std[k_] * np.clip(rng.standard_normal(), -3, 3)) for k_ in mean}
             for _ in range(sc.n_vehicles)]
    if sc.clean:
        # Each vehicle drives the clean passes at the cruise of its (first) field trip of this seed, so
        # the reference differs from the field world only in what a drive brings (GNSS, stops, turns,
        # tilt, jitter, gaps), not in speed, on which the inverse's bandwidth and error model depend.
        # The field trips' seeds come from a copy of the generator, so the clean passes' own seeds stay.
        field_seeds = trip_seeds(copy.deepcopy(rng), sc.n_vehicles)
        cruise = [trip_cruise(sc, np.random.default_rng(s_)) for s_ in field_seeds]
        records = [simulate_clean_pass(sc, rid, geoms[rid], surfaces[rid], fleet[v], f"veh-{v + 1:04d}",
                                       int(rng.integers(2**31)), dict(fleet[v]) if nominal == "true" else dict(mean),
                                       out_dir / "logs", cruise[v])
                   for v in range(sc.n_vehicles) for rid in sorted(geoms)]
        write_network_site(out_dir / "site.toml", geoms, mean, std, sc.vehicle_model)
        doc = network_truth(sc, seed, geoms, surfaces, fleet, [])
        doc["passes"] = records
        (out_dir / "truth.json").write_text(json.dumps(doc))
        return doc
    trips = []
    for i, trip_seed in enumerate(trip_seeds(rng, n_trips)):
        vid = f"veh-{i % sc.n_vehicles + 1:04d}"
        params = fleet[i % sc.n_vehicles]
        nom = dict(params) if nominal == "true" else dict(mean)
        log, truth = simulate_trip(sc, TRIPS[i % len(TRIPS)], geoms, surfaces, params, vid, i, trip_seed, nom)
        write_drive_log(out_dir / "logs" / f"{log.meta.pass_id}.parquet", log)
        trips.append(truth)
    write_network_site(out_dir / "site.toml", geoms, mean, std, sc.vehicle_model)
    doc = network_truth(sc, seed, geoms, surfaces, fleet, trips)
    (out_dir / "truth.json").write_text(json.dumps(doc))
    return doc


def simulate_clean_pass(sc: NetworkScenario, rid: str, geom: RouteGeometry, surface: RoadProfile, params: dict,
                        vehicle_id: str, seed: int, nominal: dict | None, logs_dir: Path, speed: float) -> dict:
    """One clean pass of ``rid``: in motion from before chainage 0 at the constant ``speed`` (m/s), the
    logger's own sample grid, exact chainage and speed (the surface is flat beyond the route's tapered ends)."""
    rng = np.random.default_rng(seed)
    fs = sc.sample_rate_hz
    L = geom.length_m

    def elevation(x):
        return surface.at(np.clip(x, 0.0, L))

    def slope(x):
        h = 1e-3
        return (elevation(x + h) - elevation(x - h)) / (2 * h)

    system = vehicle_from_params(sc.vehicle_model, params).system()
    x0 = -RUN_IN_M
    resp = simulate_vbi(system, elevation, slope, x0, speed, (L - x0) / speed, 1.0 / (fs * SUBSTEPS), gamma=SIM_GAMMA)
    x = resp.x_cg[::SUBSTEPS]
    keep = (x >= 0.0) & (x <= L)
    body = add_noise(resp.channels[::SUBSTEPS, 0][keep], sc.noise_pct, rng).astype(np.float32)
    n = int(keep.sum())
    pass_id = f"clean_{rid}_{vehicle_id}"
    meta = DriveLogMeta("driveby-drive-log", 1, vehicle_id, rid, sc.vehicle_model, fs, "2026-11-20T10:00:00Z", None,
                        nominal, pass_id)
    write_drive_log(logs_dir / f"{pass_id}.parquet",
                    DriveLog(meta, np.arange(n) / fs, x[keep], np.full(n, speed), {"body_acc": body}, True))
    return {"pass_id": pass_id, "vehicle_id": vehicle_id, "route": rid, "speed_mps": speed}


def route_truths(truth: dict) -> dict[str, dict]:
    """Each route of a network truth in the single-route form `simfleet.evaluate` scores against."""
    return {rid: {"route": {"id": rid, "length_m": r["length_m"]}, "profile": r["profile"]}
            for rid, r in truth["routes"].items()}


def write_network_site(path: Path, geoms: dict[str, RouteGeometry], mean: dict, std: dict, model: str) -> None:
    routes = tuple(Route(id=rid, length_m=g.length_m, geometry=g) for rid, g in sorted(geoms.items()))
    b = BRIDGE
    bridge = Bridge(id=b["id"], route=b["route"], start_chainage_m=b["start_m"], span_m=b["span_m"], n_elements=20,
                    E_pa=35e9, I_m4=1.25, mass_per_m=37500.0, depth_m=1.0, damping_ratio=0.03,
                    supports="simply_supported", deck="rough")
    dump_site(Site(routes=routes, bridges=(bridge,), vehicle_classes=(VehicleClass(model=model, mean=mean, std=std),)),
              path)


def network_truth(sc, seed, geoms, surfaces, fleet, trips) -> dict:
    routes = {}
    for rid, g in sorted(geoms.items()):
        grid = np.arange(0.0, g.length_m, TRUTH_SPACING_M)
        routes[rid] = {"length_m": g.length_m, "profile": {"start_m": 0.0, "spacing_m": TRUTH_SPACING_M,
                                                           "elevation_m": surfaces[rid].at(grid).tolist()}}
    out_trips = []
    for tr in trips:
        t = tr["t"]
        keep = np.searchsorted(t, np.arange(t[0], t[-1], 0.1))
        out_trips.append({k: (np.asarray(v)[keep].tolist() if k in ("t", "chainage", "speed", "long_acc") else
                              [v[i] for i in keep] if k == "route" else
                              np.asarray(v).tolist() if isinstance(v, np.ndarray) else v) for k, v in tr.items()})
    return {"scenario": sc.name, "seed": seed, "noise_pct": sc.noise_pct, "vehicle_model": sc.vehicle_model,
            "routes": routes, "bridge": dict(BRIDGE),
            "vehicles": {f"veh-{i + 1:04d}": p for i, p in enumerate(fleet)}, "passes": out_trips}
