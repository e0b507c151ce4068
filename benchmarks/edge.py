"""One edge process's cost per vehicle-chunk, in process (no Zenoh): pre-encoded raw chunks of
``road-qc`` drive logs (0.1 s at 500 Hz, renamed per vehicle) fed to :class:`edge.node.Edge`.

* ``edge.cpu_us_per_chunk.bank``: CPU µs per vehicle-chunk when each tick's chunks (every vehicle's
  next one) go in as one bank (:meth:`Edge.on_chunks`: what ``driveby edge`` does), over
  ``FLEET`` vehicles, one pass each; decode, inverse, gridding, drift control, error model,
  encode and the outbox included (publish is a no-op).
* ``edge.cpu_us_per_chunk.one_at_a_time``: the same chunks one :meth:`Edge.on_chunk` each (the
  path before the bank), over fewer vehicles.
* ``edge.realtime_fleet.together|staggered``: the largest fleet of ``FLEETS`` whose chunks, paced
  at real time (every vehicle's next chunk due each 0.1 s), the edge turns into AP segments with
  p99 ≤ 100 ms from the releasing chunk's due time to the segment's publication (the edge's share of
  the end-to-end latency; the bus and the cloud add theirs: ``python -m benchmarks bus``).
  ``together``: the fleet starts at once, as in the bus benchmark, so the vehicles sharing a base
  log end their passes, and release their tiles, in the same tick; ``staggered``: starts spread
  over one pass, as a fleet in service.

Each measurement runs as the daemon does once started: what exists before it is kept out of full
garbage collections (:func:`as_the_daemon`). Ratios are to the kernel's own cost measured in the
same run: the inverse Newmark-β of one 0.1 s chunk in the interleaved bank kernel
(:class:`shared.dynamics.inverse.InverseBank`), the physical floor of the edge's work per chunk on
this machine. ``DRIVEBY_BENCH_EDGE_FLEETS=500,1000`` chooses
the real-time ladder, ``DRIVEBY_BENCH_EDGE_FLEET=N`` the bank run's fleet.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import os
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from edge.node import Edge
from edge.outbox import Outbox
from shared.drivelog import list_drive_logs, read_drive_log
from shared.dynamics.inverse import InverseBank, build_inverse, edge_gamma
from shared.registry import load_site
from shared.schema import decode_ap
from shared.vehicles import vehicle_from_params
from simfleet.replay import chunks_of
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

NET = "bench"
CHUNK_S = 0.1
BASE_LOGS = 8
FLEET = int(os.environ.get("DRIVEBY_BENCH_EDGE_FLEET", "1000"))
ONE_AT_A_TIME = 100
FLEETS = tuple(int(n) for n in os.environ.get("DRIVEBY_BENCH_EDGE_FLEETS", "250,500,1000,1500,2000").split(","))
TARGET_US = 50.0
TARGET_P99_MS = 100.0


def fleet_streams(logs, tag: str, n: int) -> list[list[bytes]]:
    """Each vehicle's encoded chunks of one pass (the base logs shared out, renamed)."""
    out = []
    for i in range(n):
        vehicle = f"{tag}-{i:04d}"
        out.append([dataclasses.replace(c, vehicle_id=vehicle, pass_id=f"{vehicle}-p0").encode()
                    for c in chunks_of(logs[i % len(logs)], CHUNK_S)])
    return out


def ticks(streams: list[list[bytes]]) -> list[list[bytes]]:
    """Tick k holds every vehicle's k-th chunk (the fleet starts together, as in the bus benchmark)."""
    longest = max(len(s) for s in streams)
    return [[s[k] for s in streams if k < len(s)] for k in range(longest)]


@contextlib.contextmanager
def as_the_daemon():
    """What exists before the measurement kept out of full garbage collections, as ``driveby edge``
    does once started (:func:`edge.node.main`): without it every full collection scans the modules,
    numba's and pyarrow's internals, which the daemon never does. Undone afterwards (other
    benchmarks may run in this process)."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def new_edge(site) -> Edge:
    edge = Edge(NET, lambda key, payload: None, site, outbox=Outbox())
    edge.on_cloud_presence(True)
    return edge


def kernel_us_per_chunk(logs) -> float:
    """The inverse of one chunk in the bank kernel: 256 quarter-cars of the fleet's class, 1 s updates."""
    m = logs[0].meta
    dt = 1.0 / m.sample_rate_hz
    rng = np.random.default_rng(0)
    models = [build_inverse(vehicle_from_params(m.vehicle_model, {k: v * rng.uniform(0.9, 1.1) for k, v in
                                                                  m.nominal_params.items()}).system(), dt,
                            gamma=edge_gamma(m.vehicle_model)) for _ in range(256)]
    z = np.stack([np.resize(np.asarray(log.channels[next(iter(log.channels))], float), 20_000)
                  for log in (logs * 256)[:256]], axis=-1)[:, None, :]
    bank = InverseBank(models)
    bank.update(z[:500])
    best = float("inf")
    for _ in range(5):
        t0 = time.perf_counter()
        for k in range(500, z.shape[0] - 500, 500):
            bank.update(z[k : k + 500])
        best = min(best, time.perf_counter() - t0)
    samples = (len(range(500, z.shape[0] - 500, 500)) * 500) * 256
    per_chunk_samples = CHUNK_S * m.sample_rate_hz
    return best / samples * per_chunk_samples * 1e6


def cpu_per_chunk(site, streams, bank: bool) -> float:
    edge = new_edge(site)
    n = 0
    with as_the_daemon():
        t0 = time.process_time()
        for tick in ticks(streams):
            if bank:
                edge.on_chunks([(p, None, None) for p in tick])
            else:
                for p in tick:
                    edge.on_chunk(p)
            n += len(tick)
        cpu = time.process_time() - t0
    if sum(edge.rejected.values()):
        raise RuntimeError(f"edge benchmark: chunks rejected {dict(edge.rejected)}")
    return cpu / n * 1e6


def realtime(site, streams, starts: list[int] | None = None) -> dict:
    """Pace the ticks at real time (vehicle i's first chunk in tick ``starts[i]``; default all in
    the first) and time each AP segment from its releasing chunk's due time to its publication."""
    starts = starts or [0] * len(streams)
    due_ticks: list[list[bytes]] = []
    for stream, start in zip(streams, starts):
        for j, payload in enumerate(stream):
            while len(due_ticks) <= start + j:
                due_ticks.append([])
            due_ticks[start + j].append(payload)
    published: list[tuple[float, bytes]] = []
    due = 0.0

    def publish(key: str, payload: bytes) -> None:
        if "/ap/" in key:
            published.append((time.perf_counter() - due, payload))

    edge = Edge(NET, publish, site, outbox=Outbox())
    edge.on_cloud_presence(True)
    lag, n = [], 0
    with as_the_daemon():
        start = time.perf_counter()
        cpu0 = time.process_time()
        for k, tick in enumerate(due_ticks):
            due = start + (k + 1) * CHUNK_S  # a chunk is sent when its last sample is due
            now = time.perf_counter()
            if now < due:
                time.sleep(due - now)
            edge.on_chunks([(p, None, None) for p in tick])
            lag.append(time.perf_counter() - due)
            n += len(tick)
        cpu = time.process_time() - cpu0
    # each message's latency counts once per segment it carries (as the bus benchmark's, per segment)
    latency = np.repeat([t for t, _ in published], [len(decode_ap(p)) for _, p in published]) * 1e3
    return {"p50_ms": float(np.percentile(latency, 50)), "p99_ms": float(np.percentile(latency, 99)),
            "segments": int(latency.size), "tick_p99_ms": float(np.percentile(np.asarray(lag) * 1e3, 99)),
            "cpu_us_per_chunk": cpu / n * 1e6, "chunks": n}


def staggered(streams: list[list[bytes]]) -> list[int]:
    """Start ticks spread evenly over one pass, so passes end at different ticks (a fleet in
    service) rather than together (the bus benchmark's fleet, started at once)."""
    span = int(np.median([len(s) for s in streams]))
    return [(i * span) // len(streams) for i in range(len(streams))]


def run() -> Iterator[dict]:
    with tempfile.TemporaryDirectory(prefix="driveby-edge-") as tmp:
        work = Path(tmp)
        generate(SCENARIOS["road-qc"], work, seed=11, passes=BASE_LOGS, workers=1, progress=False)
        logs = [read_drive_log(p) for p in list_drive_logs(work / "logs")]
        site = load_site(work / "site.toml")
        cpu_per_chunk(site, fleet_streams(logs, "warm", BASE_LOGS), bank=True)  # numba, caches
        cpu_per_chunk(site, fleet_streams(logs, "warm1", BASE_LOGS), bank=False)
        kernel = kernel_us_per_chunk(logs)
        yield {"name": "edge.kernel_us_per_chunk", "value": kernel, "unit": "us",
               "ratio_to": {}, "note": "inverse of one 0.1 s chunk in the 256-stream bank kernel"}
        bank = cpu_per_chunk(site, fleet_streams(logs, "bank", FLEET), bank=True)
        yield {"name": "edge.cpu_us_per_chunk.bank", "value": bank, "unit": "us",
               "ratio_to": {"kernel": bank / kernel, "target_50us": bank / TARGET_US}, "vehicles": FLEET}
        single = cpu_per_chunk(site, fleet_streams(logs, "one", ONE_AT_A_TIME), bank=False)
        yield {"name": "edge.cpu_us_per_chunk.one_at_a_time", "value": single, "unit": "us",
               "ratio_to": {"kernel": single / kernel, "bank": single / bank}, "vehicles": ONE_AT_A_TIME}
        for mode in ("together", "staggered"):
            best, ladder = 0, []
            for n in FLEETS:
                streams = fleet_streams(logs, f"rt{n}", n)
                r = realtime(site, streams, staggered(streams) if mode == "staggered" else None)
                ladder.append(n)
                yield {"name": f"edge.realtime_{mode}.vehicles_{n}", "value": r["p99_ms"], "unit": "ms",
                       "ratio_to": {"target_100ms": r["p99_ms"] / TARGET_P99_MS}, **r}
                if r["p99_ms"] > TARGET_P99_MS:
                    break
                best = n
            yield {"name": f"edge.realtime_fleet.{mode}", "value": best, "unit": "vehicles",
                   "ratio_to": {"target_1000": best / 1000, "kernel_bound": best / (CHUNK_S * 1e6 / kernel)},
                   "ladder": ladder}
