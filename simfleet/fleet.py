"""``driveby fleet``: a live simulated fleet, every vehicle publishing its raw sensor stream over Zenoh.

The world comes from the site registry: each route gets a random ISO 8608 profile (seeded), each
bridge its healthy design beam, and the fleet is drawn from the registry's vehicle class. Each
vehicle then drives passes one after another, at a random speed, and publishes its chunks on
``driveby/<net>/veh/<id>/imu`` as its logger would, paced at X× real time; all vehicles at once,
interleaved by due time in one thread while a small thread pool simulates every vehicle's next
pass ahead of time. Logs carry no ``nominal_params``: the edge cold-starts from the class mean.

Only the first bridge of a route is simulated (the forward model couples one span at a time), and
the road profile continues over the deck.
"""

from __future__ import annotations

import argparse
import heapq
import logging
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import NamedTuple

import numpy as np
import zenoh

from shared import keys
from shared.drivelog import FORMAT, VERSION, DriveLog, DriveLogMeta
from shared.fe.beam import Beam
from shared.fe.design import design_beam, registry_krot
from shared.profiles import RoadProfile, iso8608_profile, tyre_filter
from shared.registry import RegistryError, Site, VehicleClass, load_site
from shared.sensors import add_noise
from shared.security import SecurityError
from shared.transport import LOG_LEVELS, add_zenoh_arguments, config_from_args, zenoh_message
from shared.vbi import simulate_vbi
from shared.vehicles import MODELS, vehicle_from_params

from .replay import CHUNK_S, chunks_of
from .sim import RUN_IN_M, SIM_GAMMA, SUBSTEPS

log = logging.getLogger("driveby.fleet")

SAMPLE_RATE_HZ = 500.0
PROFILE_SPACING_M = 0.01
PROFILE_MARGIN_M = RUN_IN_M + 20.0  # surface beyond both ends of a route (run-in, axles past the end)
START_SPREAD_S = 1.0  # loggers are not phase-locked: each vehicle starts within this much data time
SPEED_RANGE_MPS = (15.0, 22.0)
MAX_DRAWS = 100  # redraws of a vehicle whose parameters are not physical, before giving up
DESCRIPTION = "live simulated fleet: every vehicle publishes its raw sensor stream, paced at X× real time"


class FleetError(ValueError):
    """A user-facing problem with the fleet's inputs: one line, non-zero exit."""


@dataclass(frozen=True)
class RouteWorld:
    """What a vehicle drives over on one route: the surface (m) and, optionally, one bridge."""

    route_id: str
    length_m: float
    surface: RoadProfile
    beam: Beam | None = None
    bridge_start_m: float = 0.0


@dataclass(frozen=True)
class FleetVehicle:
    vehicle_id: str
    model: str
    params: dict[str, float]


@dataclass(frozen=True)
class DrivePlan:
    """One pass to simulate: who, where, how fast (m/s), and the seed of its sensor noise."""

    vehicle: FleetVehicle
    world: RouteWorld
    pass_id: str
    speed_mps: float
    seed: int


class Published(NamedTuple):
    """What :func:`interleave` did: items published, the worst lateness against the schedule (s),
    and the wall time it took (s)."""

    items: int
    max_late_s: float
    seconds: float


# -- the world --------------------------------------------------------------------------------------


def build_worlds(site: Site, seed: int = 0, road_class: str = "A") -> list[RouteWorld]:
    """A seeded ISO 8608 surface (tyre-filtered, zero mean) per route, with its first bridge."""
    worlds = []
    for j, route in enumerate(site.routes):
        raw = iso8608_profile(route.length_m + 2 * PROFILE_MARGIN_M, PROFILE_SPACING_M, road_class,
                              np.random.default_rng([seed, 1, j]))
        smooth = tyre_filter(raw)
        surface = RoadProfile(-PROFILE_MARGIN_M, smooth.spacing_m, smooth.elevation_m - smooth.elevation_m.mean())
        bridges = site.bridges_on(route.id)
        if len(bridges) > 1:
            log.warning("route %s: only bridge %s of %d is simulated", route.id, bridges[0].id, len(bridges))
        beam = design_beam(bridges[0], krot=registry_krot(bridges[0])) if bridges else None
        worlds.append(RouteWorld(route.id, route.length_m, surface, beam,
                                 bridges[0].start_chainage_m if bridges else 0.0))
    return worlds


def draw_vehicles(vclass: VehicleClass, n: int, seed: int = 0, prefix: str = "veh-") -> list[FleetVehicle]:
    """``n`` vehicles with parameters ``mean + std·z``, z standard normal clipped at ±3."""
    rng = np.random.default_rng([seed, 2])
    fleet = []
    for i in range(n):
        vehicle_id = keys.check_id(f"{prefix}{i + 1:04d}", "vehicle id")
        for _ in range(MAX_DRAWS):
            params = {k: float(vclass.mean[k] + vclass.std[k] * np.clip(rng.standard_normal(), -3, 3))
                      for k in vclass.mean}
            try:
                vehicle_from_params(vclass.model, params)
            except ValueError:
                continue
            break
        else:
            raise FleetError(f"vehicle_class {vclass.model!r}: no physical vehicle in {MAX_DRAWS} draws "
                             "(std too large for mean?)")
        fleet.append(FleetVehicle(vehicle_id, vclass.model, params))
    return fleet


def simulate_drive(plan: DrivePlan, noise_pct: float, sample_rate_hz: float = SAMPLE_RATE_HZ) -> DriveLog:
    """One pass as the vehicle's logger records it: chainage 0 to the route's end, noisy channels."""
    world, vehicle = plan.world, plan.vehicle
    rng = np.random.default_rng(plan.seed)
    system = vehicle_from_params(vehicle.model, vehicle.params).system()
    x0 = -RUN_IN_M
    rear = float(system.offsets_m.min())
    resp = simulate_vbi(system, world.surface.at, world.surface.slope, x0, plan.speed_mps,
                        (world.length_m - x0) / plan.speed_mps, 1.0 / (sample_rate_hz * SUBSTEPS),
                        beam=world.beam, bridge_start_m=world.bridge_start_m, gamma=SIM_GAMMA)
    x_cg = resp.x_cg[::SUBSTEPS]
    idx = np.flatnonzero((x_cg >= 0.0) & (x_cg <= world.length_m + rear))
    channels = resp.channels[::SUBSTEPS][idx]
    noisy = {ch.name: add_noise(channels[:, i], noise_pct, rng).astype(np.float32)
             for i, ch in enumerate(system.channels)}
    n = idx.size
    now = datetime.now(timezone.utc).isoformat(timespec="seconds").replace("+00:00", "Z")
    meta = DriveLogMeta(format=FORMAT, version=VERSION, vehicle_id=vehicle.vehicle_id, route_id=world.route_id,
                        vehicle_model=vehicle.model, sample_rate_hz=sample_rate_hz, start_time_utc=now,
                        lane_offset_m=None, nominal_params=None, pass_id=plan.pass_id)
    return DriveLog(meta=meta, t=np.arange(n) / sample_rate_hz, chainage=x_cg[idx],
                    speed=np.full(n, plan.speed_mps), channels=noisy)


def drive_plans(vehicle: FleetVehicle, index: int, worlds: Sequence[RouteWorld], seed: int, run_id: str,
                passes: int | None, speed_range: tuple[float, float] = SPEED_RANGE_MPS) -> Iterator[DrivePlan]:
    """The vehicle's passes, one after another: a random route and speed each (``passes`` None: forever)."""
    rng = np.random.default_rng([seed, 3, index])
    k = 0
    while passes is None or k < passes:
        world = worlds[int(rng.integers(len(worlds)))]
        yield DrivePlan(vehicle, world, f"{run_id}-{k:05d}", float(rng.uniform(*speed_range)),
                        int(rng.integers(2**31)))
        k += 1


# -- publishing -------------------------------------------------------------------------------------


def interleave(streams: Sequence[Iterator[tuple[float, str, bytes]]], publish: Callable[[str, bytes], None],
               rate: float | None = None, stop: threading.Event | None = None) -> Published:
    """Publish the items of several streams in order of due time, paced at ``rate``× real time.

    Each stream yields ``(due_s, key, payload)`` with ``due_s`` non-decreasing, in the stream's data
    time (0 = start). Items due at the same time go in stream order. ``rate`` None publishes as fast
    as the transport takes them. Pacing waits on ``stop`` until each due time, so a stop request ends
    publishing at once; a late item (the publisher fell behind) goes out immediately.
    """
    stop = stop or threading.Event()
    heap: list[tuple[float, int, str, bytes]] = []

    def push(i: int) -> None:
        item = next(streams[i], None)
        if item is not None:
            heapq.heappush(heap, (item[0], i, item[1], item[2]))

    for i in range(len(streams)):  # primes every stream (e.g. its first simulation) before the clock starts
        if stop.is_set():
            break
        push(i)
    t0 = time.monotonic()
    n, worst = 0, 0.0
    while heap and not stop.is_set():
        due, i, key, payload = heapq.heappop(heap)
        if rate is not None:
            wait = t0 + due / rate - time.monotonic()
            if wait > 0:
                if stop.wait(wait):
                    break
            else:
                worst = max(worst, -wait)
        publish(key, payload)
        n += 1
        push(i)
    return Published(n, worst, time.monotonic() - t0)


def vehicle_stream(first: Future, plans: Iterator[DrivePlan], simulate: Callable[[DrivePlan], Future], key: str,
                   start_s: float = 0.0, chunk_s: float = CHUNK_S,
                   on_pass: Callable[[], None] | None = None) -> Iterator[tuple[float, str, bytes]]:
    """``(due_s, key, payload)`` for one vehicle's passes back to back; each chunk is due when its
    last sample has been recorded. The next pass is simulated while this one is published."""
    clock, pending = start_s, first
    while pending is not None:
        drive = pending.result()
        plan = next(plans, None)
        pending = simulate(plan) if plan is not None else None
        for chunk in chunks_of(drive, chunk_s):
            clock += chunk.n / chunk.sample_rate_hz
            yield clock, key, chunk.encode()
        if on_pass is not None:
            on_pass()


@dataclass
class FleetRun:
    """Counters of a fleet run (filled while it runs)."""

    vehicles: int = 0
    passes: int = 0
    published: Published | None = None


def run_fleet(publish: Callable[[str, bytes], None], site: Site, vehicles: int, *, net: str = "net",
              rate: float | None = 1.0, passes: int | None = None, seed: int = 0, noise_pct: float = 2.0,
              model: str | None = None, road_class: str = "A", speed_range: tuple[float, float] = SPEED_RANGE_MPS,
              prefix: str = "veh-", run_id: str | None = None, workers: int = 2,
              stop: threading.Event | None = None) -> FleetRun:
    """Simulate and publish the fleet until every vehicle has driven ``passes`` (None: until ``stop``)."""
    keys.check_id(net, "net")
    vclass = _vehicle_class(site, model)
    worlds = build_worlds(site, seed, road_class)
    fleet = draw_vehicles(vclass, vehicles, seed, prefix)
    run_id = run_id or datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    result = FleetRun(vehicles=len(fleet))

    def counted() -> None:
        result.passes += 1

    pool = ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="fleet-sim")
    try:
        def simulate(plan: DrivePlan) -> Future:
            return pool.submit(simulate_drive, plan, noise_pct)

        streams = []
        spread = np.random.default_rng([seed, 4]).uniform(0.0, START_SPREAD_S, len(fleet))
        for i, vehicle in enumerate(fleet):
            plans = drive_plans(vehicle, i, worlds, seed, run_id, passes, speed_range)
            first = next(plans, None)
            if first is None:
                continue
            streams.append(vehicle_stream(simulate(first), plans, simulate, keys.imu_key(net, vehicle.vehicle_id),
                                          float(spread[i]), on_pass=counted))
        result.published = interleave(streams, publish, rate, stop)
    finally:
        pool.shutdown(wait=False, cancel_futures=True)
    return result


def _vehicle_class(site: Site, model: str | None) -> VehicleClass:
    classes = [c for c in site.vehicle_classes if model is None or c.model == model]
    if not classes:
        what = f"no vehicle_class for model {model!r}" if model else "no vehicle_class"
        raise FleetError(f"vehicle_class: {what}; the fleet draws its vehicles from one")
    if len(classes) > 1:
        raise FleetError(f"several vehicle classes ({', '.join(c.model for c in classes)}): choose one with --model")
    if classes[0].model not in MODELS:
        raise FleetError(f"vehicle_class model {classes[0].model!r} cannot be simulated yet "
                         f"(supported: {', '.join(sorted(MODELS))})")
    return classes[0]


# -- command line -------------------------------------------------------------------------------------


def add_fleet_arguments(p: argparse.ArgumentParser) -> None:
    add_zenoh_arguments(p)
    p.add_argument("--site", required=True, help="site registry TOML (routes, bridges, vehicle class)")
    p.add_argument("--vehicles", type=int, required=True, help="number of vehicles")
    p.add_argument("--rate", type=float, default=1.0, help="speed-up over real time (default 1)")
    p.add_argument("--passes", type=int, help="passes per vehicle (default: until SIGINT/SIGTERM)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the fleet and its profiles (default 0)")
    p.add_argument("--net", default="net", help="network name in the key space (the same on every daemon; default net)")
    p.add_argument("--noise", type=float, default=2.0, help="sensor noise, %% of each channel's std (default 2)")
    p.add_argument("--model", help="vehicle class to draw from, when the site declares several")
    p.add_argument("--road-class", default="A", choices=tuple("ABCDE"), help="ISO 8608 road class (default A)")
    p.add_argument("--speed-range", type=float, nargs=2, metavar=("MIN", "MAX"), default=SPEED_RANGE_MPS,
                   help="speeds drawn uniformly in m/s (default 15 22)")
    p.add_argument("--prefix", default="veh-", help="vehicle ids are PREFIX0001, PREFIX0002, ...")
    p.add_argument("--run-id", help="pass ids are RUN_ID-00000, ... (default: the UTC start time)")
    p.add_argument("--workers", type=int, default=2, help="threads simulating passes ahead (default 2)")
    p.add_argument("--log-level", default="WARNING", type=str.upper, choices=LOG_LEVELS,
                   help="logging level (default WARNING)")


def _check_args(args: argparse.Namespace) -> None:
    if args.vehicles < 1:
        raise FleetError(f"--vehicles must be >= 1, got {args.vehicles}")
    if args.passes is not None and args.passes < 1:
        raise FleetError(f"--passes must be >= 1, got {args.passes}")
    if not (math.isfinite(args.rate) and args.rate > 0):
        raise FleetError(f"--rate must be a speed-up > 0, got {args.rate}")
    if not (0 <= args.noise < 100):
        raise FleetError(f"--noise must be a percentage in [0, 100), got {args.noise}")
    lo, hi = args.speed_range
    if not (0.5 <= lo <= hi <= 100.0):
        raise FleetError(f"--speed-range must satisfy 0.5 <= MIN <= MAX <= 100 m/s, got {lo} {hi}")
    keys.check_id(args.net, "--net")
    keys.check_id(f"{args.prefix}0001", "--prefix")
    if args.run_id is not None and not keys.is_valid_id(args.run_id):
        raise FleetError(f"--run-id {args.run_id!r}: expected [A-Za-z0-9_.-]+")


def run(args: argparse.Namespace) -> int:
    """Run ``driveby fleet`` from parsed arguments; returns the exit code."""
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s fleet %(levelname)s %(message)s")
    try:
        _check_args(args)
        conf = config_from_args(args)
    except SecurityError as e:  # a TLS file it names is missing
        print(f"driveby fleet: {e}", file=sys.stderr)
        return 1
    except (FleetError, ValueError) as e:  # the command line itself: a usage error, as argparse's
        print(f"driveby fleet: {e}", file=sys.stderr)
        return 2
    try:
        site = load_site(args.site)  # its errors name the file and the key
        try:
            _vehicle_class(site, args.model)
            for bridge in site.bridges:
                design_beam(bridge, krot=registry_krot(bridge))
        except (FleetError, ValueError) as e:
            raise FleetError(f"{args.site}: {e}") from None
    except (FleetError, RegistryError, ValueError) as e:  # what the arguments name is unusable
        print(f"driveby fleet: {e}", file=sys.stderr)
        return 1
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    try:
        with zenoh.open(conf) as session:
            publishers: dict[str, zenoh.Publisher] = {}

            def publish(key: str, payload: bytes) -> None:
                pub = publishers.get(key)
                if pub is None:
                    pub = publishers[key] = session.declare_publisher(
                        key, congestion_control=zenoh.CongestionControl.BLOCK)
                pub.put(payload)

            res = run_fleet(publish, site, args.vehicles, net=args.net, rate=args.rate, passes=args.passes,
                            seed=args.seed, noise_pct=args.noise, model=args.model, road_class=args.road_class,
                            speed_range=tuple(args.speed_range), prefix=args.prefix, run_id=args.run_id,
                            workers=args.workers, stop=stop)
    except zenoh.ZError as e:
        print(f"driveby fleet: zenoh: {zenoh_message(e)}", file=sys.stderr)
        return 1
    pub = res.published
    print(f"{res.passes} passes ({pub.items} chunks) from {res.vehicles} vehicles in {pub.seconds:.1f} s "
          f"at {args.rate:g}x real time; worst lag {pub.max_late_s:.2f} s")
    return 0


def main(argv: Iterable[str] | None = None) -> int:
    """``driveby fleet --site FILE --vehicles N [--rate X] [--passes K] ...``."""
    return run(build_parser().parse_args(None if argv is None else list(argv)))


def build_parser() -> argparse.ArgumentParser:
    """``driveby fleet``'s options."""
    p = argparse.ArgumentParser(prog="driveby fleet", description=DESCRIPTION)
    add_fleet_arguments(p)
    return p


if __name__ == "__main__":
    sys.exit(main())
