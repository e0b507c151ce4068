"""Soak: a large simulated fleet on an accelerated clock through two routers and two sharded clouds.

``python -m benchmarks soak`` (or ``python -m benchmarks.soak --duration S --vehicles N``): for
``DRIVEBY_SOAK_S`` seconds (default 600) ``DRIVEBY_SOAK_VEHICLES`` vehicles (default 1 000) drive
passes on two routes (R1, R2). Deployment, all separate processes on loopback:

* router A, and router B joined to it (as two machines);
* ``cloud-1 --routes R1`` on A and ``cloud-2 --routes R2`` on B (sharded aggregators, journals on disk,
  ``--calibration nominal``: calibration rounds would re-publish passes and measure themselves);
* the real edge daemon, two of them (``--shard 0/2`` on A, ``--shard 1/2`` on B), with on-disk spools
  of unacknowledged passes as ``driveby run`` starts them, and their raw spool (passes kept to
  recompute under a new calibration) bounded to ``EDGE_RAW_SPOOL_MB``;
* the fleet, in this process: every vehicle publishes its raw chunks through its own advanced
  publisher (``simfleet.replay.ImuPublishers``, as the loggers of ``driveby run``) on router A.

The load fits two shared cores by being sparse, not by faking the edge: real edges process every
raw chunk. Time is accelerated ``SPEEDUP``× (a pass's chunks are published ``SPEEDUP``× faster than
real time), chunks are 0.5 s (a logger's upload granularity; output does not depend on chunking),
and each vehicle drives a pass every ``vehicles / passes_per_s`` seconds of wall time from a random
phase: about ``passes_per_s`` passes per second for the fleet (default 4, ~80 raw chunks/s), i.e. each
of 1 000 vehicles drives about once in 4 minutes (≈ 4 h of simulated time between its passes at 60×). Passes
are the simulated ``road-qc`` drive logs (200 m, ~10 s), renamed per vehicle and pass.

Measured:

* ``soak.passes_lost`` / ``soak.segments_lost``: passes never acknowledged by their cloud, and
  segments the edges published minus segments the clouds accepted (with the edges' re-sends and the
  clouds' duplicates reported beside): both must be 0; the edges' rejection counters (sequence
  gaps, chunks missed beyond a vehicle's cache) must be empty.
* ``soak.latency_p50|p99``: raw chunk published (stamped into the zenoh attachment) → segment applied
  by its cloud, over every traced segment, and the p99 of each tenth of the run (drift shows there).
* ``soak.rss_slope.<process>``: each process's resident memory (``/proc/<pid>/status`` VmRSS) sampled
  every ``SAMPLE_S``; the slope (least squares, MB per hour, with its standard error) over the steady
  state: from the end of the first cycle (``vehicles / passes_per_s`` s, by when every vehicle has
  driven once: the fleet's publication caches, bounded by vehicles × ``CACHE_CHUNKS`` chunks, and the
  edges' per-vehicle tasks exist) or the run's middle, whichever is later (the whole series is in
  ``soak.summary``), and the growth it projects over 24 h.
* ``soak.memory_flat``: the verdict, per process and overall. A process is **flat** when its slope is
  at most ``FLAT_MB_PER_H`` (so at most ``24 × FLAT_MB_PER_H`` MB a day); **growing** when even the
  slope minus two standard errors exceeds it; otherwise **unresolved** (RSS noise of a few MB over a
  short window cannot tell: run longer). Overall flat: every process of the deployment (routers,
  clouds, edges) flat; the fleet (this process, the load generator) is reported, not judged.

Bounded state is bounded only once its bound is reached, so the soak sets the bounds low enough to be
reached in the first minutes, as with the edges' raw spool: each cloud keeps ``CLOUD_RESIDENT_SEGMENTS``
segments and ``CLOUD_RESIDENT_PASSES`` passes' bookkeeping in memory (the rest on disk, exact); at the
daemon's defaults (20 000 and 5 000) this load reaches them after ~40 min, and memory rises until then.

Before the clock starts, one warm-up pass per base log is published and acknowledged (counted in the
totals, not in the latency).
"""

from __future__ import annotations

import argparse
import dataclasses
import heapq
import json
import os
import random
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import zenoh

from benchmarks.bus import BenchError, control_query, spawn_daemon, stop_daemons, watch_alive
from cloud.daemon.node import TRACE
from shared import keys
from shared.drivelog import list_drive_logs, read_drive_log, write_drive_log
from shared.schema import decode_ack
from shared.transport import free_port, start_router, stop_router, zenoh_config
from simfleet.replay import ImuPublishers, chunks_of
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

NET = "soak"
ROUTES = ("R1", "R2")
DURATION_S = float(os.environ.get("DRIVEBY_SOAK_S", "600"))
VEHICLES = int(os.environ.get("DRIVEBY_SOAK_VEHICLES", "1000"))
PASSES_PER_S = 4.0  # the fleet's passes per second of wall time
SPEEDUP = 60.0  # simulated seconds per wall second while a pass streams
CHUNK_S = 0.5
BASE_LOGS = 3  # simulated passes per route, shared out to the vehicles
CACHE_CHUNKS = 24  # per vehicle: a pass and a bit (~6 KB a chunk: ~150 MB for 1 000 vehicles)
HEARTBEAT_S = 5.0  # 1 000 vehicles × 1/5 s: 200 heartbeats/s, a tenth of the chunk rate
SAMPLE_S = 10.0
# The edges' raw passes kept for recomputation: bounded so that the bound is reached in the first
# minutes (~130 passes of ~120 KB per edge); at the default 512 MB it would take ~70 min at this load.
EDGE_RAW_SPOOL_MB = 16.0
# Each cloud's in-memory window (``--max-resident-segments``/``--max-resident-passes``): at ~8 segments
# and ~2 passes per second per cloud, reached after ~2 min.
CLOUD_RESIDENT_SEGMENTS = 1000
CLOUD_RESIDENT_PASSES = 250
FLAT_MB_PER_H = 20.0  # the flat criterion: at most this slope (≤ 480 MB over 24 h)
STARTUP_TIMEOUT_S = 180.0
DRAIN_TIMEOUT_S = 300.0


@dataclasses.dataclass
class Fleet:
    """The base passes (decoded chunks per route) and the schedule of the fleet's passes."""

    chunks: dict[str, list[list]]  # route -> base passes -> chunks

    def schedule(self, vehicles: int, duration_s: float, passes_per_s: float, seed: int = 0):
        """``(start_s, vehicle, route, base index, pass id)`` sorted by start (wall seconds from go)."""
        rng = random.Random(seed)
        interval = vehicles / passes_per_s
        plan = []
        for v in range(vehicles):
            vehicle = f"s{v:04d}"
            route = ROUTES[v % len(ROUTES)]
            t, k = rng.uniform(0.0, interval), 0
            while t < duration_s:
                plan.append((t, vehicle, route, (v + k) % len(self.chunks[route]), f"{vehicle}-p{k}"))
                t, k = t + interval, k + 1
        return sorted(plan)


def make_fleet(work: Path) -> tuple[Fleet, Path]:
    """Simulate ``BASE_LOGS`` passes on each of two routes (road-qc, different seeds); one site."""
    logs = work / "logs"
    logs.mkdir()
    chunks: dict[str, list[list]] = {}
    for i, route in enumerate(ROUTES):
        sim = work / route
        generate(SCENARIOS["road-qc"], sim, seed=40 + i, passes=BASE_LOGS, workers=1, progress=False)
        chunks[route] = []
        for path in list_drive_logs(sim / "logs"):
            log = read_drive_log(path)
            log = dataclasses.replace(log, meta=dataclasses.replace(log.meta, route_id=route))
            write_drive_log(logs / f"{route}-{path.name}", log)
            chunks[route].append(list(chunks_of(log, CHUNK_S)))
    site = (work / "R1" / "site.toml").read_text()
    (work / "site.toml").write_text(site.replace("[[route]]", '[[route]]\nid = "R2"\nlength_m = 200.0\n\n[[route]]', 1))
    return Fleet(chunks), work / "site.toml"


def rss_mb(pid: int) -> float | None:
    """Resident memory of a process (MB), or None if it is gone."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def slope_mb_per_h(t_s: np.ndarray, mb: np.ndarray) -> tuple[float, float]:
    """Least-squares slope of a memory series and its standard error, MB per hour (nan with fewer
    than 3 points)."""
    if len(t_s) < 3:
        return float("nan"), float("nan")
    t = np.asarray(t_s, float) - np.mean(t_s)
    slope = float(np.dot(t, mb) / np.dot(t, t))
    resid = mb - np.mean(mb) - slope * t
    se = float(np.sqrt(np.dot(resid, resid) / (len(t) - 2) / np.dot(t, t)))
    return slope * 3600.0, se * 3600.0


def memory_verdict(slope: float, se: float, limit: float = FLAT_MB_PER_H) -> str:
    """``flat`` (slope ≤ limit), ``growing`` (slope − 2 se > limit) or ``unresolved``."""
    if not np.isfinite(slope):
        return "unresolved"
    if slope <= limit:
        return "flat"
    return "growing" if slope - 2.0 * (se if np.isfinite(se) else 0.0) > limit else "unresolved"


class Soak:
    """The deployment, the fleet's publishers and the counters."""

    def __init__(self, work: Path, site: Path):
        self.work = work
        self.routers: dict[str, object] = {}
        a = f"tcp/127.0.0.1:{free_port()}"
        proc, err = start_router(a, None, 30.0)
        if err is not None:
            raise BenchError(f"router A: {err}")
        self.routers["router-a"] = proc
        b = f"tcp/127.0.0.1:{free_port()}"
        proc, err = start_router(b, None, 30.0, ["--connect", a])
        if err is not None:
            stop_router(self.routers["router-a"])
            raise BenchError(f"router B: {err}")
        self.routers["router-b"] = proc
        common = ["--net", NET, "--site", str(site)]
        self.procs = {}
        for cid, route, ep in (("cloud-1", "R1", a), ("cloud-2", "R2", b)):
            self.procs[cid] = spawn_daemon([sys.executable, "-m", "cloud", "--connect", ep, *common, "--id", cid,
                                      "--routes", route, "--calibration", "nominal",
                                      "--state", str(work / f"{cid}-state"),
                                      "--max-resident-segments", str(CLOUD_RESIDENT_SEGMENTS),
                                      "--max-resident-passes", str(CLOUD_RESIDENT_PASSES)], work / f"{cid}.log")
        for i, ep in enumerate((a, b)):
            eid = f"edge-{i + 1}"
            self.procs[eid] = spawn_daemon([sys.executable, "-m", "edge", "--connect", ep, *common, "--id", eid,
                                      "--calibration", "nominal", "--shard", f"{i}/2",
                                      "--spool", str(work / f"{eid}-spool"), "--raw-spool-mb", str(EDGE_RAW_SPOOL_MB)],
                                     work / f"{eid}.log")
        self.session = zenoh.open(zenoh_config("client", connect=[a]))
        self.publish = ImuPublishers(self.session, cache_chunks=CACHE_CHUNKS, heartbeat_s=HEARTBEAT_S)
        self.lock = threading.Lock()
        self.acks: dict[tuple[str, str], int] = {}
        self.progress = threading.Event()
        self.subs = [self.session.declare_subscriber(keys.ack_keyexpr(NET), self._on_ack)]

    def _on_ack(self, sample) -> None:
        ack = decode_ack(sample.payload.to_bytes())
        with self.lock:
            self.acks.setdefault((ack.vehicle_id, ack.pass_id), ack.n_segments_accepted)
        self.progress.set()

    def check_alive(self) -> None:
        for name, p in {**self.procs, **self.routers}.items():
            if p.poll() is not None:
                log = self.work / f"{name}.log"
                tail = log.read_text(errors="replace").strip().splitlines()[-1:] if log.exists() else []
                raise BenchError(f"{name} exited with code {p.returncode}: {tail or '(no output)'}")

    def wait_up(self) -> None:
        wanted = {keys.alive_key(NET, "cloud", c) for c in ("cloud-1", "cloud-2")} | \
                 {keys.alive_key(NET, "edge", e) for e in ("edge-1", "edge-2")}
        up, seen, sub = watch_alive(self.session, wanted, NET)
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not up.wait(0.5):
            self.check_alive()
            if time.monotonic() > deadline:
                raise BenchError(f"daemons not up after {STARTUP_TIMEOUT_S:.0f} s: {sorted(wanted - seen)}")
        sub.undeclare()

    def query(self, node: str, verb: str, params: str = "") -> dict:
        return control_query(self.session, node, verb, params, NET)

    def memory(self) -> dict[str, float | None]:
        pids = {name: p.pid for name, p in {**self.routers, **self.procs}.items()}
        return {**{name: rss_mb(pid) for name, pid in pids.items()}, "fleet": rss_mb(os.getpid())}

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.publish.close()
        self.session.close()
        stop_daemons(list(self.procs.values()))
        for p in self.routers.values():
            stop_router(p)


def soak(duration_s: float = DURATION_S, vehicles: int = VEHICLES, passes_per_s: float = PASSES_PER_S,
         speedup: float = SPEEDUP, seed: int = 0, workdir: Path | None = None) -> dict:
    """Run the soak; returns its summary (see the module docstring)."""
    with tempfile.TemporaryDirectory(prefix="driveby-soak-") as tmp:
        work = Path(workdir or tmp)
        work.mkdir(parents=True, exist_ok=True)
        fleet, site = make_fleet(work)
        plan = fleet.schedule(vehicles, duration_s, passes_per_s, seed)
        dep = Soak(work, site)
        try:
            dep.wait_up()
            return _drive(dep, fleet, plan, duration_s, speedup, vehicles, passes_per_s)
        finally:
            dep.close()


def _warm_up(dep: Soak, fleet: Fleet) -> set[tuple[str, str]]:
    """One pass of each base log, published at once and acknowledged before the clock starts: the
    daemons' first passes (inverse models built, caches filled) are not the soak's."""
    wanted = set()
    for route, passes in fleet.chunks.items():
        for i, chunks in enumerate(passes):
            vehicle, pass_id = f"w{route}-{i}", f"w{route}-{i}-p0"
            for c in chunks:
                dep.publish(keys.imu_key(NET, vehicle), dataclasses.replace(c, vehicle_id=vehicle,
                                                                             pass_id=pass_id).encode())
            wanted.add((vehicle, pass_id))
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while True:
        with dep.lock:
            if wanted <= dep.acks.keys():
                return wanted
        dep.progress.clear()
        dep.progress.wait(1.0)
        dep.check_alive()
        if time.monotonic() > deadline:
            raise BenchError("warm-up passes not acknowledged")


def _drive(dep: Soak, fleet: Fleet, plan, duration_s, speedup, vehicles, passes_per_s) -> dict:
    warm = _warm_up(dep, fleet)
    stop = threading.Event()
    t_go = time.monotonic()
    since = time.time()
    published = {"chunks": 0, "passes": 0, "max_late_s": 0.0}

    def publisher():
        # One heap of chunk events (due, order, key, chunk, ids): a pass's chunks are released when due.
        events: list = []
        order = 0
        i = 0
        while not stop.is_set() and (i < len(plan) or events):
            while i < len(plan) and (not events or plan[i][0] <= events[0][0]):
                start, vehicle, route, base, pass_id = plan[i]
                clock = 0.0
                for c in fleet.chunks[route][base]:
                    clock += c.n / c.sample_rate_hz
                    heapq.heappush(events, (start + clock / speedup, order, vehicle, pass_id, c))
                    order += 1
                published["passes"] += 1
                i += 1
            due, _, vehicle, pass_id, c = heapq.heappop(events)
            if stop.wait(max(0.0, t_go + due - time.monotonic())):
                return
            published["max_late_s"] = max(published["max_late_s"], time.monotonic() - t_go - due)
            payload = dataclasses.replace(c, vehicle_id=vehicle, pass_id=pass_id).encode()
            dep.publish(keys.imu_key(NET, vehicle), payload, attachment=TRACE.pack(time.time()))
            published["chunks"] += 1

    feeder = threading.Thread(target=publisher, daemon=True, name="fleet")
    feeder.start()
    samples: list[dict] = []
    latencies: list[np.ndarray] = []
    lat_t: list[np.ndarray] = []

    def sample() -> None:
        now = time.monotonic() - t_go
        with dep.lock:
            acked = len(dep.acks)
        samples.append({"t_s": round(now, 1), "acked": acked, "published_chunks": published["chunks"],
                        "rss_mb": {k: (None if v is None else round(v, 1)) for k, v in dep.memory().items()}})

    next_sample = time.monotonic()
    while feeder.is_alive():
        feeder.join(max(0.0, next_sample - time.monotonic()))
        dep.check_alive()
        if time.monotonic() >= next_sample:
            sample()
            next_sample += SAMPLE_S
    t_published = time.monotonic() - t_go
    wanted = {(p[1], p[4]) for p in plan} | warm
    deadline = time.monotonic() + DRAIN_TIMEOUT_S
    while True:
        with dep.lock:
            missing = wanted - dep.acks.keys()
        if not missing or time.monotonic() > deadline:
            break
        dep.progress.clear()
        dep.progress.wait(min(SAMPLE_S, max(0.1, next_sample - time.monotonic())))
        dep.check_alive()
        if time.monotonic() >= next_sample:
            sample()
            next_sample += SAMPLE_S
    sample()
    t_end = time.monotonic() - t_go
    # Latency records are asked for once, at the end: a periodic "since the last answer" would skip the
    # segments still in flight at each answer, the slow ones. Each cloud keeps the last 100 000.
    for cid in ("cloud-1", "cloud-2"):
        body = dep.query(cid, "latency", f"since={since!r}")
        sent, applied = np.asarray(body["sent"], float), np.asarray(body["applied"], float)
        latencies.append((applied - sent) * 1e3)
        lat_t.append(sent - since)

    edges = {e: dep.query(e, "stats") for e in ("edge-1", "edge-2")}
    cloud_bodies = {c: dep.query(c, "stats") for c in ("cloud-1", "cloud-2")}
    clouds = {c: b["stats"] for c, b in cloud_bodies.items()}
    seg_published = sum(e["segments_published"] for e in edges.values())
    accepted = sum(c.get("accepted", 0) for c in clouds.values())
    duplicates = sum(c.get("rejected", {}).get("duplicate", 0) for c in clouds.values())
    lat = np.concatenate(latencies) if latencies else np.zeros(0)
    lt = np.concatenate(lat_t) if lat_t else np.zeros(0)
    windows = []
    for k in range(10):
        sel = (lt >= k * duration_s / 10) & (lt < (k + 1) * duration_s / 10)
        windows.append(round(float(np.percentile(lat[sel], 99)), 1) if sel.any() else None)
    t = np.asarray([s["t_s"] for s in samples])
    steady_from = max(vehicles / passes_per_s, t[-1] / 2)
    if np.count_nonzero(t >= steady_from) < 3:
        steady_from = t[-1] / 2  # too short a run for a whole cycle: its second half
    steady = t >= steady_from
    slopes, slope_se, verdict, final = {}, {}, {}, {}
    for name in samples[-1]["rss_mb"]:
        mb = np.asarray([np.nan if s["rss_mb"].get(name) is None else s["rss_mb"][name] for s in samples])
        ok = steady & np.isfinite(mb)
        slope, se = slope_mb_per_h(t[ok], mb[ok])
        slopes[name], slope_se[name] = round(slope, 2), round(se, 2)
        verdict[name] = memory_verdict(slope, se)
        final[name] = samples[-1]["rss_mb"][name]
    return {
        "vehicles": vehicles, "duration_s": duration_s, "passes_per_s": passes_per_s, "speedup": speedup,
        "chunk_s": CHUNK_S, "cache_chunks": CACHE_CHUNKS, "heartbeat_s": HEARTBEAT_S,
        "passes": len(wanted), "passes_acked": len(wanted & dep.acks.keys()),
        "passes_lost": len(wanted - dep.acks.keys()),
        "chunks_published": published["chunks"], "publisher_max_late_s": round(published["max_late_s"], 3),
        "segments_published": seg_published, "segments_accepted": accepted,
        "segments_lost": seg_published - accepted, "edge_resent": sum(e["resent"] for e in edges.values()),
        "cloud_duplicates": duplicates,
        "edge_rejected": {e: s["rejected"] for e, s in edges.items()},
        "cloud_rejected": {c: s.get("rejected", {}) for c, s in clouds.items()},
        "latency_ms": {"n": int(lat.size), "p50": round(float(np.percentile(lat, 50)), 1) if lat.size else None,
                       "p99": round(float(np.percentile(lat, 99)), 1) if lat.size else None,
                       "p99_by_tenth": windows},
        "rss_slope_mb_per_h": slopes, "rss_slope_se_mb_per_h": slope_se,
        "rss_slope_from_s": round(float(steady_from), 1),
        "rss_mb_final": final, "memory_verdict": verdict,
        # The deployment's processes; the fleet is this harness (its publication caches fill in a cycle).
        "memory_flat": all(v == "flat" for k, v in verdict.items() if k != "fleet"),
        "flat_mb_per_h": FLAT_MB_PER_H,
        "cloud_resident": {"segments": CLOUD_RESIDENT_SEGMENTS, "passes": CLOUD_RESIDENT_PASSES},
        "cloud_stats": clouds, "cloud_durability": {c: b.get("durability") for c, b in cloud_bodies.items()},
        "seconds_publishing": round(t_published, 1), "seconds_total": round(t_end, 1),
        "samples": samples,
    }


def run() -> Iterator[dict]:
    s = soak()
    common = {"vehicles": s["vehicles"], "duration_s": s["duration_s"], "passes": s["passes"]}
    yield {"name": "soak.passes_lost", "value": s["passes_lost"], "unit": "passes", **common}
    yield {"name": "soak.segments_lost", "value": s["segments_lost"], "unit": "segments",
           "segments_published": s["segments_published"], "segments_accepted": s["segments_accepted"],
           "edge_resent": s["edge_resent"], "cloud_duplicates": s["cloud_duplicates"],
           "edge_rejected": s["edge_rejected"], **common}
    for q in ("p50", "p99"):
        yield {"name": f"soak.latency_{q}", "value": s["latency_ms"][q], "unit": "ms", "n": s["latency_ms"]["n"],
               **({"p99_by_tenth": s["latency_ms"]["p99_by_tenth"]} if q == "p99" else {}), **common}
    for name, v in s["rss_slope_mb_per_h"].items():
        se = s["rss_slope_se_mb_per_h"][name]
        yield {"name": f"soak.rss_slope.{name}", "value": v, "unit": "MB/h", "se": se,
               "projected_24h_mb": round(24.0 * v, 1), "verdict": s["memory_verdict"][name],
               "final_mb": s["rss_mb_final"][name], "from_s": s["rss_slope_from_s"], **common}
    yield {"name": "soak.memory_flat", "value": s["memory_flat"], "unit": "bool",
           "criterion": f"per process: RSS slope over the steady state <= {s['flat_mb_per_h']:g} MB/h "
                        f"(<= {24 * s['flat_mb_per_h']:g} MB per 24 h); growing if slope - 2 se exceeds it, "
                        "else unresolved; the deployment's processes (not the fleet, the load generator)",
           "verdict": s["memory_verdict"], "snapshots": s["cloud_durability"], **common}
    yield {"name": "soak.summary", "value": s["seconds_total"], "unit": "s", **s}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.soak", description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=DURATION_S, help="seconds of publishing (default %(default)s)")
    p.add_argument("--vehicles", type=int, default=VEHICLES)
    p.add_argument("--passes-per-s", type=float, default=PASSES_PER_S, help="the fleet's passes per wall second")
    p.add_argument("--speedup", type=float, default=SPEEDUP)
    p.add_argument("--workdir", type=Path, help="keep the daemons' logs and state here")
    args = p.parse_args(argv)
    s = soak(args.duration, args.vehicles, args.passes_per_s, args.speedup, workdir=args.workdir)
    print(json.dumps(s))
    return 0 if s["passes_lost"] == 0 and s["segments_lost"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
