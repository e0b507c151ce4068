"""Bus throughput and latency over real Zenoh on loopback: router, cloud and edge as separate processes.

Measured in one run, each on the same daemons:

* ``bus.segments_per_s.synthetic``: AP segments per second the cloud accepts when synthetic edges
  (``PUBLISHERS`` processes publishing pre-made passes of four 50 m tiles of 1000 points, and an
  end-of-pass marker per pass) push as fast as they can: the time from "go" until the cloud has
  acknowledged every pass, i.e. until every segment has been decoded, validated and applied to
  the estimate. They publish as the edge does: what one raw chunk releases goes in one
  ``ap_batch`` message, and on the 200 m ``road-qc`` route the last chunk of a pass releases all
  four tiles. The target is 20 000 segments/s (5 000/s for one-segment messages).
* ``bus.segments_per_s.synthetic_single``: the same with one ``ap_segment`` message per segment
  (``driveby edge --ap-batch 1``, or a long route, where tiles are released one at a time). It runs
  second, so the cloud (at its default resident bounds, 20 000 segments and 5 000 passes) spills
  a segment to disk for each one it takes in: the steady state of a long-running cloud.
  Both report the cloud's CPU per segment (``cloud_cpu_us_per_segment``: the whole process, from
  ``/proc``; ``cloud_ingest_cpu_us_per_segment``: inside its message callbacks, decode to acknowledgement),
  which a loaded machine disturbs much less than the rate.
* ``bus.segments_per_s.synthetic_durable``: the batched run again into a cloud that journals its
  input (``--state``), so an acknowledgement waits until its input is fsync'd (a group of them per
  fsync: :class:`cloud.daemon.durable.GroupCommit`). It runs last, on a cloud of its own.
* ``bus.latency_p50|p99.segment_hop``: one AP segment from ``put`` to applied, unloaded (a
  synthetic ``ap_segment`` every 5 ms): the bus and the cloud's per-segment work without the edge.
* For 1, 10 and 100 replayed vehicles (chunks of 0.1 s at 500 Hz from ``road-qc`` drive logs,
  renamed per vehicle), at full speed (as fast as back-pressure allows) and in real time (all
  vehicles' chunks interleaved, each published when its last sample is due):
  ``bus.segments_per_s.<mode>.vehicles_<n>`` (raw chunks → edge → cloud, until the last pass is
  acknowledged), ``bus.chunks_per_s.<mode>.vehicles_<n>`` (ratio: how many real-time vehicle
  streams that is) and ``bus.latency_p50|p99.<mode>.vehicles_<n>``.

Latency, precisely: from the publication of the raw chunk that releases a segment at the edge
(the publisher stamps ``time.time()`` into the chunk's zenoh attachment just before ``put``;
the edge passes the attachment on to what that chunk releases) to the moment the cloud has
applied the segment to its estimate (``cloud.daemon.node`` records the time after the aggregator
accepted it and answers ``control/<id>/latency``). It covers both router hops, the edge's queue,
decode, inverse Newmark-β, tiling, drift control and encode, the cloud's queue, decode,
validation and estimator update. It does not cover the data's own wait: the edge releases a tile
once the vehicle has driven the drift-control half-width (150 m) beyond it or the pass ends, so
on the 200 m ``road-qc`` route nearly every tile is released by the pass's last chunks.
At full speed the queues are full by design, so full-speed latency is mostly queueing.

One edge daemon serves every vehicle; ``DRIVEBY_BENCH_EDGES=N`` runs N, each with ``--shard i/N``.
``DRIVEBY_BENCH_ONLY=realtime:100`` (a comma list of ``fullspeed`` / ``realtime``, each with an
optional ``:N`` vehicles) measures only those replayed-vehicle runs, for a quick before/after of
the edge; its warm-up then replays every base log once, as the full run's earlier parts would.
``DRIVEBY_BENCH_ONLY=synthetic`` measures only the synthetic runs and the segment hop (the cloud's
ingest, no edge work).

The physical floor, measured in the same run (``bus.kernel_us_per_segment``): the estimators'
own update of one synthetic segment (the profile posterior's banded information and the
consensus sums, the compiled kernels every accepted segment runs through), timed in a tight loop
in this process. Each synthetic result carries ``ratio_to.cloud_cpu_over_kernel`` (the cloud
process's CPU per segment over that floor) and ``ratio_to.cloud_ingest_cpu_over_kernel`` (its
message callbacks' CPU over it): the overhead around the kernels, which a loaded machine disturbs
less than the rates (both slow down together).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import queue
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import zenoh

from cloud.daemon.node import TRACE
from shared import keys
from shared.drivelog import DriveLog, list_drive_logs, read_drive_log
from shared.registry import Site, load_site
from shared.schema import ApBatch, ApSegment, PassDone, decode_ack
from shared.transport import run_router, zenoh_config
from simfleet.fleet import interleave
from simfleet.replay import chunks_of
from simfleet.scenarios import SCENARIOS, fleet_class
from simfleet.sim import generate, write_site

from cloud.daemon.settings import CloudSettings
from cloud.road.gmrf_profile import GmrfProfile
from cloud.road.mean_profile import MeanProfile

NET = "bench"
CLOUD_ID, EDGE_ID = "bc", "be"
EDGE_SHARDS = int(os.environ.get("DRIVEBY_BENCH_EDGES", "1"))  # edge daemons sharing the fleet (--shard i/n)
ONLY = os.environ.get("DRIVEBY_BENCH_ONLY", "")  # e.g. "realtime:100": only these pipeline runs
ROUTE = "R1"
TILE_POINTS = 1000  # a 50 m tile on the 0.05 m grid
TARGET_SEGMENTS_PER_S = 5000.0  # one-segment messages (and the replayed-vehicle runs)
TARGET_BATCHED_SEGMENTS_PER_S = 20000.0  # ap_batch messages
CHUNK_S = 0.1  # real-time chunk period: 10 chunks/s per vehicle stream
VEHICLES = (1, 10, 100)
FULLSPEED_PASSES = {1: 10, 10: 2, 100: 1}  # passes per vehicle at full speed (enough latency samples)
BASE_LOGS = 8  # simulated passes (different speeds, so different lengths), shared out to the vehicles
HOP_PASSES = 50  # traced synthetic passes for the unloaded segment-hop latency
HOP_INTERVAL_S = 0.005
SYNTHETIC_SEGMENTS = 20_000
PUBLISHERS = 2
SYNTHETIC_VEHICLES = 50  # per publisher
STARTUP_TIMEOUT_S = 120.0  # a cold numba cache compiles on the daemons' first start
IDLE_TIMEOUT_S = 60.0  # no acknowledgement for this long: something is wrong
KERNEL_SEGMENTS = 2000  # segments timed for the kernel floor
KERNEL_WORKER = 1000  # the synthetic worker number of the floor's segments (none of the bus's)



def watch_alive(session: zenoh.Session, wanted: set[str], net: str = NET) -> tuple[threading.Event, set[str], object]:
    """Watch the daemons' liveliness tokens: an event set once every key of ``wanted`` is alive, the
    keys seen so far, and the subscriber (undeclare it when done)."""
    seen: set[str] = set()
    up = threading.Event()

    def on_alive(sample):
        if sample.kind == zenoh.SampleKind.PUT:
            seen.add(str(sample.key_expr))
        if wanted <= seen:
            up.set()

    return up, seen, session.liveliness().declare_subscriber(keys.alive_keyexpr(net), on_alive, history=True)

class BenchError(RuntimeError):
    """The benchmark could not measure (a daemon died, a timeout)."""


# -- the deployment ---------------------------------------------------------------------------------


class Deployment:
    """Cloud and edge daemons on a router, and this process's session: acks, stats, latency records."""

    def __init__(self, endpoint: str, site: Path, workdir: Path, edges: int = EDGE_SHARDS, state: Path | None = None):
        self.workdir = workdir
        self.session = zenoh.open(zenoh_config("client", connect=[endpoint]))
        common = ["--connect", endpoint, "--net", NET, "--site", str(site)]
        # The cloud trusts the edges' calibration: fleet self-calibration would re-publish passes mid-run
        # and measure itself, not the bus. The edge cold-starts every vehicle from the class mean. Nor does
        # it align passes in chainage: a sweep between two runs is idle work over every pass held, longer
        # than zenoh's limit on a blocked link once thousands are held, which the next run would wait for.
        # ``state``: the cloud journals its input there (an acknowledgement then waits for its fsync).
        durable = ["--state", str(state)] if state is not None else []
        self.procs = {"cloud": spawn_daemon([sys.executable, "-m", "cloud", *common, "--id", CLOUD_ID,
                                       "--calibration", "nominal", "--no-align", *durable], workdir / "cloud.log")}
        self.edge_ids = [EDGE_ID if edges == 1 else f"{EDGE_ID}{i}" for i in range(edges)]
        for i, edge_id in enumerate(self.edge_ids):
            shard = ["--shard", f"{i}/{edges}"]
            self.procs[edge_id] = spawn_daemon([sys.executable, "-m", "edge", *common, "--id", edge_id, *shard],
                                         workdir / f"{edge_id}.log")
        self._lock = threading.Lock()
        self._acks: dict[tuple[str, str], tuple[float, int]] = {}  # (vehicle, pass) → (monotonic s, segments)
        self._wanted: set[tuple[str, str]] = set()
        self._complete = threading.Event()
        self._progress = threading.Event()
        self._subs = [self.session.declare_subscriber(keys.ack_keyexpr(NET), self._on_ack)]
        self._publishers: dict[str, zenoh.Publisher] = {}

    def wait_up(self) -> None:
        wanted = {keys.alive_key(NET, "cloud", CLOUD_ID), *(keys.alive_key(NET, "edge", e) for e in self.edge_ids)}
        up, _, sub = watch_alive(self.session, wanted)
        try:
            self._wait(up, STARTUP_TIMEOUT_S, "the cloud and edge daemons to start")
        finally:
            sub.undeclare()

    def _on_ack(self, sample) -> None:
        ack = decode_ack(sample.payload.to_bytes())
        now = time.monotonic()
        with self._lock:
            self._acks.setdefault((ack.vehicle_id, ack.pass_id), (now, ack.n_segments_accepted))
            self._progress.set()
            if self._wanted and self._wanted <= self._acks.keys():
                self._complete.set()

    def expect(self, passes: set[tuple[str, str]]) -> None:
        """Arm the completion event for these ``(vehicle, pass)`` acknowledgements."""
        with self._lock:
            self._wanted = set(passes)
            self._complete.clear()
            if self._wanted <= self._acks.keys():
                self._complete.set()

    def wait_acks(self) -> tuple[float, int]:
        """Wait until every expected pass is acknowledged; returns (last ack time, segments accepted)."""
        while not self._complete.is_set():
            self._progress.clear()
            if not self._progress.wait(IDLE_TIMEOUT_S) and not self._complete.is_set():
                with self._lock:
                    missing = sorted(self._wanted - self._acks.keys())
                raise BenchError(f"no acknowledgement for {IDLE_TIMEOUT_S:.0f} s; {len(missing)} passes missing, "
                                 f"e.g. {missing[:3]}")
            self._check_alive()
        with self._lock:
            done = [self._acks[p] for p in self._wanted]
        return max(t for t, _ in done), sum(n for _, n in done)

    def publish_traced(self, key: str, payload: bytes) -> None:
        """Publish a raw chunk stamped with its publication time (the latency trace)."""
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK)
        pub.put(payload, attachment=TRACE.pack(time.time()))  # the stamp is the last thing before put

    def query(self, verb: str, params: str = "") -> dict:
        return control_query(self.session, CLOUD_ID, verb, params)

    def latencies_ms(self, since: float) -> np.ndarray:
        body = self.query("latency", f"since={since!r}")
        return (np.asarray(body["applied"]) - np.asarray(body["sent"])) * 1e3

    def _wait(self, event: threading.Event, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not event.wait(0.5):
            self._check_alive()
            if time.monotonic() > deadline:
                raise BenchError(f"timed out after {timeout:.0f} s waiting for {what}")

    def _check_alive(self) -> None:
        for name, p in self.procs.items():
            if p.poll() is not None:
                tail = (self.workdir / f"{name}.log").read_text(errors="replace").strip().splitlines()[-1:]
                raise BenchError(f"{name} daemon exited with code {p.returncode}: {tail or '(no output)'}")

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.session.close()
        stop_daemons(list(self.procs.values()))


def control_query(session: zenoh.Session, node: str, verb: str, params: str = "", net: str = NET) -> dict:
    """A daemon's answer to a control query (``driveby/<net>/control/<node>/<verb>``), as JSON."""
    selector = keys.control_key(net, node, verb) + (f"?{params}" if params else "")
    for reply in session.get(selector, timeout=30.0):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
        raise BenchError(f"{node} {verb}: {reply.err.payload.to_bytes().decode(errors='replace')}")
    raise BenchError(f"{node} did not answer {verb}")


def spawn_daemon(cmd: list[str], log_path: Path, **kw) -> subprocess.Popen:
    """Start ``cmd`` unbuffered, its output (stdout and stderr) to ``log_path``, no stdin."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(cmd, env=env, stdout=open(log_path, "wb"), stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL, **kw)


def stop_daemons(procs: list[subprocess.Popen]) -> None:
    """SIGTERM every process, then wait for each (SIGKILL after 15 s)."""
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(15)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


# -- synthetic edges --------------------------------------------------------------------------------


def synthetic_segments(worker: int, passes: int, tiles: int) -> Iterator[list[ApSegment]]:
    """The AP segments (``tiles`` per pass, 1000-point 50 m tiles) of ``passes`` synthetic passes."""
    rng = np.random.default_rng(worker)
    sigma = np.full(TILE_POINTS, 2e-4)
    for k in range(passes):
        vehicle = f"syn{worker}-{k % SYNTHETIC_VEHICLES:03d}"
        pass_id = f"syn{worker}-p{k:05d}"
        yield [ApSegment.make(rng.normal(0.0, 2e-3, TILE_POINTS), sigma, vehicle_id=vehicle, pass_id=pass_id,
                              route_id=ROUTE, tile=tile, axle=1, start_index=tile * TILE_POINTS,
                              spacing_m=0.05, calib_version=0, speed_mps=18.0, t_first=2.5 * tile,
                              t_last=2.5 * tile + 2.5, seq=tile, n_segments_in_pass=tiles)
               for tile in range(tiles)]


def synthetic_messages(worker: int, passes: int, tiles: int, batch: bool = False,
                       net: str = NET) -> Iterator[tuple[str, bytes]]:
    """Pre-made AP segments (``tiles`` per pass; in one ``ap_batch`` if ``batch``) and end-of-pass
    markers of ``passes`` passes."""
    for segments in synthetic_segments(worker, passes, tiles):
        vehicle, pass_id = segments[0].vehicle_id, segments[0].pass_id
        if batch:
            yield keys.ap_key(net, ROUTE, 0, vehicle), ApBatch(tuple(segments)).encode()
        else:
            for seg in segments:
                yield keys.ap_key(net, ROUTE, seg.tile, vehicle), seg.encode()
        done = PassDone(vehicle_id=vehicle, pass_id=pass_id, route_id=ROUTE, calib_version=0, n_segments=tiles)
        yield keys.done_key(net, vehicle), done.encode()


def synthetic_passes(worker: int, passes: int) -> set[tuple[str, str]]:
    return {(f"syn{worker}-{k % SYNTHETIC_VEHICLES:03d}", f"syn{worker}-p{k:05d}") for k in range(passes)}


def _publisher_main(argv: list[str]) -> int:
    """A synthetic edge: encode everything, say ``ready``, publish on ``go``, say ``sent``, leave on EOF."""
    p = argparse.ArgumentParser(prog="python -m benchmarks.bus publisher")
    p.add_argument("--connect", required=True)
    p.add_argument("--worker", type=int, required=True)
    p.add_argument("--passes", type=int, required=True)
    p.add_argument("--tiles", type=int, required=True)
    p.add_argument("--batch", action="store_true", help="one ap_batch per pass instead of one message per segment")
    p.add_argument("--net", default=NET, help=f"network name in the key space (default {NET})")
    args = p.parse_args(argv)
    messages = list(synthetic_messages(args.worker, args.passes, args.tiles, args.batch, args.net))
    with zenoh.open(zenoh_config("client", connect=[args.connect])) as session:
        print("ready", flush=True)
        if sys.stdin.readline().strip() != "go":
            return 1
        t0 = time.monotonic()
        for key, payload in messages:
            session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
        print(f"sent {len(messages)} {time.monotonic() - t0:.6f}", flush=True)
        sys.stdin.readline()  # keep the session (and what it still sends) until told to go
    return 0


class _Worker:
    """A publisher subprocess spoken to by lines: its stdout is read by a thread into a queue."""

    def __init__(self, cmd: list[str], log_path: Path):
        self.log_path = log_path
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=open(log_path, "wb"),
                                     text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
        self.lines: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line.strip())
        self.lines.put(None)

    def expect(self, word: str, timeout: float) -> list[str]:
        try:
            line = self.lines.get(timeout=timeout)
        except queue.Empty:
            line = None
        if line is None or not line.startswith(word):
            err = self.log_path.read_text(errors="replace").strip().splitlines()[-1:]
            raise BenchError(f"synthetic publisher: expected {word!r}, got {line!r}; {err}")
        return line.split()[1:]

    def say(self, line: str) -> None:
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.proc.stdin.close()
        stop_daemons([self.proc])


def bench_synthetic(dep: Deployment, endpoint: str, tiles: int, workdir: Path, batch: bool = True,
                    suffix: str = "") -> Iterator[dict]:
    passes = SYNTHETIC_SEGMENTS // (tiles * PUBLISHERS)
    n = passes * tiles * PUBLISHERS
    first = 0 if batch else PUBLISHERS + 1  # worker numbers: distinct passes in each run (and the hop's)
    ids = range(first, first + PUBLISHERS)
    before = dep.query("stats")
    cpu0 = _process_cpu_s(dep.procs["cloud"].pid)
    workers = [_Worker([sys.executable, "-m", "benchmarks.bus", "publisher", "--connect", endpoint,
                        "--worker", str(w), "--passes", str(passes), "--tiles", str(tiles), *(["--batch"] * batch)],
                       workdir / f"publisher{w}.log") for w in ids]
    try:
        for w in workers:
            w.expect("ready", STARTUP_TIMEOUT_S)
        dep.expect(set().union(*(synthetic_passes(w, passes) for w in ids)))
        t0 = time.monotonic()
        for w in workers:
            w.say("go")
        sent = [float(w.expect("sent", STARTUP_TIMEOUT_S)[1]) for w in workers]
        t_end, accepted = dep.wait_acks()
    finally:
        for w in workers:
            w.close()
    cpu1 = _process_cpu_s(dep.procs["cloud"].pid)
    after_body = dep.query("stats")
    after = after_body["stats"]
    rejected = sum(after["rejected"].values()) - sum(before["stats"]["rejected"].values())
    if accepted != n or after["accepted"] - before["stats"]["accepted"] != n or rejected:
        raise BenchError(f"synthetic: {n} segments sent, {accepted} acknowledged, {rejected} rejected")
    rate = n / (t_end - t0)
    targets = {"target_5000": rate / TARGET_SEGMENTS_PER_S}
    if batch:
        targets["target_20000"] = rate / TARGET_BATCHED_SEGMENTS_PER_S
    yield {"name": "bus.segments_per_s.synthetic" + ("" if batch else "_single") + suffix, "value": rate,
           "unit": "segments/s",
           "ratio_to": targets, "segments": n, "publishers": PUBLISHERS,
           "segments_per_message": tiles if batch else 1, "publish_segments_per_s": n / max(sent),
           "cloud_cpu_us_per_segment": (cpu1 - cpu0) / n * 1e6 if cpu0 is not None and cpu1 is not None else None,
           "cloud_ingest_cpu_us_per_segment": (after_body["cpu"]["callback_s"] - before["cpu"]["callback_s"]) / n * 1e6}


def _process_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of process ``pid`` so far (Linux ``/proc``; None elsewhere)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def bench_segment_hop(dep: Deployment, tiles: int) -> Iterator[dict]:
    """Unloaded bus latency of one AP segment: put (stamped) → router → cloud applied it."""
    messages = list(synthetic_messages(PUBLISHERS, HOP_PASSES, tiles))  # a worker number no publisher uses
    dep.expect(synthetic_passes(PUBLISHERS, HOP_PASSES))
    since = time.time()
    interleave([iter((i * HOP_INTERVAL_S, key, payload) for i, (key, payload) in enumerate(messages))],
               dep.publish_traced, rate=1.0)
    _, segments = dep.wait_acks()
    latency = dep.latencies_ms(since)
    if latency.size != segments:
        raise BenchError(f"segment hop: {segments} segments acknowledged, {latency.size} traced")
    for q in (50, 99):
        value = float(np.percentile(latency, q))
        yield {"name": f"bus.latency_p{q}.segment_hop", "value": value, "unit": "ms",
               "ratio_to": {"chunk_100ms": value / (CHUNK_S * 1e3)}, "n": int(latency.size)}


# -- replayed vehicles through edge and cloud ---------------------------------------------------------


def vehicle_streams(logs: list[DriveLog], tag: str, n_vehicles: int, passes: int):
    """Encoded chunk streams ``(due_s, key, payload)`` of ``n_vehicles`` renamed replays, and their passes."""
    streams, wanted = [], set()
    for i in range(n_vehicles):
        vehicle = f"{tag}-{i:03d}"
        key = keys.imu_key(NET, vehicle)
        items, clock = [], 0.0
        for k in range(passes):
            pass_id = f"{vehicle}-p{k}"
            for chunk in chunks_of(logs[(i + k) % len(logs)], CHUNK_S):
                chunk = dataclasses.replace(chunk, vehicle_id=vehicle, pass_id=pass_id)
                clock += chunk.n / chunk.sample_rate_hz
                items.append((clock, key, chunk.encode()))
            wanted.add((vehicle, pass_id))
        streams.append(iter(items))
    return streams, wanted


def bench_pipeline(dep: Deployment, logs: list[DriveLog], realtime: bool, n_vehicles: int,
                   report: bool = True) -> Iterator[dict]:
    mode = "realtime" if realtime else "fullspeed"
    passes = 1 if realtime else FULLSPEED_PASSES.get(n_vehicles, 1)
    tag = f"{'rt' if realtime else 'fs'}{n_vehicles}" if report else "warmup"
    streams, wanted = vehicle_streams(logs, tag, n_vehicles, passes)
    dep.expect(wanted)
    since = time.time()
    cpu0 = {name: _process_cpu_s(proc.pid) for name, proc in dep.procs.items()}
    t0 = time.monotonic()
    published = interleave(streams, dep.publish_traced, rate=1.0 if realtime else None)
    t_end, segments = dep.wait_acks()
    cpu1 = {name: _process_cpu_s(proc.pid) for name, proc in dep.procs.items()}
    latency = dep.latencies_ms(since)
    if not report:
        return
    if latency.size != segments:
        raise BenchError(f"{mode} x{n_vehicles}: {segments} segments acknowledged, {latency.size} traced")
    elapsed = t_end - t0
    suffix = f"{mode}.vehicles_{n_vehicles}"
    common = {"vehicles": n_vehicles, "passes": len(wanted)}
    yield {"name": f"bus.segments_per_s.{suffix}", "value": segments / elapsed, "unit": "segments/s",
           "ratio_to": {"target_5000": segments / elapsed / TARGET_SEGMENTS_PER_S}, "segments": segments, **common}
    chunks_per_s = published.items / elapsed
    # each daemon's CPU over the run, per raw chunk (µs): which process a latency has to wait for
    cpu = {f"{'cloud' if name == 'cloud' else 'edge'}_cpu_us_per_chunk" + ("" if name in ("cloud", EDGE_ID) else f".{name}"):
           (cpu1[name] - cpu0[name]) / published.items * 1e6 for name in dep.procs
           if cpu0[name] is not None and cpu1[name] is not None}
    yield {"name": f"bus.chunks_per_s.{suffix}", "value": chunks_per_s, "unit": "chunks/s",
           "ratio_to": {"realtime_vehicle_streams": chunks_per_s * CHUNK_S}, "chunks": published.items,
           "publisher_max_late_ms": published.max_late_s * 1e3, **cpu, **common}
    for q in (50, 99):
        value = float(np.percentile(latency, q))
        yield {"name": f"bus.latency_p{q}.{suffix}", "value": value, "unit": "ms",
               "ratio_to": {"chunk_100ms": value / (CHUNK_S * 1e3)}, "n": int(latency.size), **common}


# -- the benchmark ------------------------------------------------------------------------------------


def _only_runs(text: str) -> list[tuple[bool, int]] | None:
    """``DRIVEBY_BENCH_ONLY`` → the (realtime, vehicles) runs it names (empty for ``synthetic``); None when unset."""
    if not text.strip():
        return None
    runs = []
    for part in text.split(","):
        if part.strip() == "synthetic":
            continue
        mode, _, n = part.strip().partition(":")
        if mode not in ("fullspeed", "realtime") or not (n == "" or (n.isdigit() and int(n) > 0)):
            raise ValueError(f"DRIVEBY_BENCH_ONLY: expected fullspeed|realtime[:N], got {part.strip()!r}")
        runs += [(mode == "realtime", int(k)) for k in ([n] if n else VEHICLES)]
    return runs


def kernel_floor(site: Site, tiles: int, n: int = KERNEL_SEGMENTS) -> Iterator[dict]:
    """The estimators' own update of one synthetic segment (µs of this thread's CPU): ``n`` distinct
    segments like the synthetic edges' into the cloud's two road estimators, in one timed loop."""
    routes = {r.id: r.length_m for r in site.routes}
    settings = CloudSettings()
    profile = GmrfProfile(routes, settings.spacing_m, drift_knot_m=settings.drift_knot_m)
    consensus = MeanProfile(routes, settings.spacing_m)
    segments = [seg for segs in synthetic_segments(KERNEL_WORKER, n // tiles + 1, tiles) for seg in segs][:n]
    warm = segments[0]
    for est in (profile, consensus):  # compiled (or loaded from the cache) before the clock runs
        est.update(warm)
        est.retract(warm)
    t0 = time.thread_time()
    for seg in segments:
        profile.update(seg)
        consensus.update(seg)
    us = (time.thread_time() - t0) / len(segments) * 1e6
    yield {"name": "bus.kernel_us_per_segment", "value": us, "unit": "us/segment", "segments": len(segments),
           "what": "GmrfProfile.update + MeanProfile.update of one 1000-point segment, this process's thread CPU"}


def run() -> Iterator[dict]:
    """Simulate a few passes, start router, cloud and edge, and measure (see the module docstring)."""
    only = _only_runs(ONLY)
    synthetic = only is None or "synthetic" in {p.strip() for p in ONLY.split(",")}
    with tempfile.TemporaryDirectory(prefix="driveby-bus-") as tmp:
        work = Path(tmp)
        scenario = SCENARIOS["road-qc"]
        if only == []:  # the synthetic runs alone: the site is all they need
            write_site(scenario, work / "site.toml", *fleet_class(scenario))
            logs = []
        else:
            generate(scenario, work, seed=11, passes=BASE_LOGS, workers=min(BASE_LOGS, os.cpu_count() or 1),
                     progress=False)
            logs = [read_drive_log(p) for p in list_drive_logs(work / "logs")]
        tiles = int(scenario.route_length_m // (TILE_POINTS * 0.05))
        floor = None
        if synthetic:
            (floor,) = kernel_floor(load_site(work / "site.toml"), tiles)
            yield floor
        with run_router() as endpoint:
            dep = Deployment(endpoint, work / "site.toml", work)
            try:
                dep.wait_up()
                if synthetic:
                    for batch in (True, False):
                        yield from _over_kernel(bench_synthetic(dep, endpoint, tiles, work, batch=batch), floor)
                    yield from bench_segment_hop(dep, tiles)
                if only != []:
                    # warm-up (numba, the edge's caches); alone, over every base log, as the skipped parts would
                    warm = 2 if only is None else len(logs)
                    yield from bench_pipeline(dep, logs, realtime=False, n_vehicles=warm, report=False)
                    for realtime, n in only or [(rt, n) for rt in (False, True) for n in VEHICLES]:
                        yield from bench_pipeline(dep, logs, realtime, n)
            finally:
                dep.close()
            if synthetic:  # a cloud that journals its input (--state): batched, an fsync before acknowledging
                dep = Deployment(endpoint, work / "site.toml", work, edges=0, state=work / "state")
                try:
                    dep.wait_up()
                    yield from _over_kernel(bench_synthetic(dep, endpoint, tiles, work, suffix="_durable"), floor)
                finally:
                    dep.close()


def _over_kernel(results: Iterator[dict], floor: dict) -> Iterator[dict]:
    """The results with their cloud CPU per segment over the kernel's (``ratio_to``)."""
    for result in results:
        for key in ("cloud_cpu_us_per_segment", "cloud_ingest_cpu_us_per_segment"):
            if result.get(key) is not None:
                result["ratio_to"][key.replace("_us_per_segment", "") + "_over_kernel"] = result[key] / floor["value"]
        yield result


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["publisher"]:
        return _publisher_main(argv[1:])
    for result in run():
        print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
