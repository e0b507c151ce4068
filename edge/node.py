"""The edge daemon: vehicle tasks turning raw sensor streams into AP segments over Zenoh.

One process can host the tasks of many vehicles (``driveby run`` starts one for the fleet), of
one (``--vehicle``, as on board), or of a hash shard of the fleet (``--shard i/n``: several
processes share a fleet too large for one). Each vehicle's task is isolated: a bad stream or a
failure in one vehicle's processing is counted and logged, and the others carry on.

What one raw chunk releases (every tile and axle the pass has completed) is published as one
``ap_batch`` message, or as single ``ap_segment`` messages with ``--ap-batch 1``.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import gc
import json
import logging
import signal
import sys
import threading
import zlib
from dataclasses import dataclass, field

import zenoh
import zenoh.ext as zx

from shared import keys
from shared.dynamics.inverse import InverseModel, build_inverse, edge_gamma
from shared.registry import RegistryError, Site, load_site
from shared.schema import (
    MAX_BATCH_SEGMENTS,
    ApBatch,
    ApSegment,
    Calibration,
    DecodeError,
    SensorChunk,
    decode_ack,
    decode_calibration,
    decode_sensor_chunk,
)
from shared.security import SecurityError
from shared.transport import (LOG_LEVELS, IdInUseError, Presence, add_zenoh_arguments, config_from_args, default_id,
                              zenoh_message)
from shared.vehicles import MODELS, vehicle_from_params

from .bank import feed_bank
from .bank_decode import ChunkDecoder
from .outbox import DEFAULT_MAX_BYTES, Outbox
from .pipeline import EdgeConfig, PassProcessor

log = logging.getLogger("driveby.edge")

SPOOL_PASSES = 64  # raw passes kept per vehicle for recomputation when calibration changes
SPOOL_MAX_BYTES = 512 * 2**20  # and at most this much of them for the whole edge (a large fleet)
AP_BATCH = 64  # segments per AP message (1: one message per segment)
INBOX_MESSAGES = 4096  # messages waiting for the edge's worker before zenoh is held back (~14 MB of raw chunks)


def parse_shard(text: str) -> tuple[int, int]:
    """``"i/n"`` → ``(i, n)`` with ``0 <= i < n``; raises ``ValueError``."""
    try:
        i, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise ValueError(f"shard: expected i/n (e.g. 0/2), got {text!r}") from None
    if not 0 <= i < n:
        raise ValueError(f"shard: expected 0 <= i < n, got {text!r}")
    return i, n


def in_shard(vehicle_id: str, shard: tuple[int, int]) -> bool:
    """Whether a vehicle belongs to shard ``(i, n)``: CRC-32 of its id modulo n (stable across
    processes and machines, unlike ``hash``)."""
    i, n = shard
    return n == 1 or zlib.crc32(vehicle_id.encode()) % n == i


@dataclass
class VehicleTask:
    """One vehicle: its calibration, the pass in progress and a bounded spool of raw passes.

    Passes are spooled as their raw chunk payloads (``bytes``), decoded again only to recompute:
    decoded chunks are several objects each, which the garbage collector would scan on every
    full collection (a pause growing with the fleet's spool, in the middle of the stream).
    """

    vehicle_id: str
    calibration: Calibration | None = None
    current: PassProcessor | None = None
    current_raw: list[bytes] = field(default_factory=list)
    current_params: dict = field(default_factory=dict)  # what the pass in progress is computed with
    expected_seq: int = 0
    spool: collections.OrderedDict[str, list[bytes]] = field(default_factory=collections.OrderedDict)
    errors: int = 0


class Edge:
    """Transport-free core of the edge: ``on_chunk``/``on_calibration`` call ``publish(key, bytes)``.

    With an ``outbox`` every pass's messages are kept until the cloud acknowledges the pass
    (``on_ack``), published only while an aggregator is alive (``on_cloud_presence``) and sent
    again whenever one (re)appears; without one they are published at once and forgotten.
    """

    def __init__(self, net: str, publish, site: Site | None = None, calibration: str = "fleet",
                 config: EdgeConfig = EdgeConfig(), vehicles: set[str] | None = None,
                 shard: tuple[int, int] = (0, 1), ap_batch: int = AP_BATCH, outbox: Outbox | None = None,
                 spool_max_bytes: int = SPOOL_MAX_BYTES):
        if calibration not in ("fleet", "nominal"):
            raise ValueError(f"calibration: expected 'fleet' or 'nominal', got {calibration!r}")
        if not 1 <= ap_batch <= MAX_BATCH_SEGMENTS:
            raise ValueError(f"ap_batch: expected 1 to {MAX_BATCH_SEGMENTS}, got {ap_batch}")
        self.net, self.publish, self.site, self.mode, self.config = net, publish, site, calibration, config
        self.only = vehicles
        self.shard = shard
        self.ap_batch = ap_batch
        self.tasks: dict[str, VehicleTask] = {}
        self.rejected: collections.Counter[str] = collections.Counter()
        self.segments_published = 0
        # Opaque tag of the message being processed (the zenoh attachment of a raw chunk, if any): what
        # that chunk releases is published with it, so a benchmark can time a segment from its raw chunk.
        self.trace: bytes | None = None
        self._models: dict[tuple, InverseModel] = {}
        self.decoder = ChunkDecoder()
        self.outbox = outbox
        self.cloud_present = outbox is None
        self.resent = 0  # messages sent again because an aggregator (re)appeared
        self.restarted = 0  # passes begun again from their first chunk while in progress (a vehicle's resend)
        # The raw passes kept for recomputation, oldest first across the fleet: without a bound over
        # the whole edge, SPOOL_PASSES per vehicle grows with the fleet (1 000 vehicles: ~20 GB).
        self.spool_max_bytes = spool_max_bytes
        self._spooled: collections.OrderedDict[tuple[str, str], int] = collections.OrderedDict()
        self.spool_bytes = 0
        self.spool_evicted = 0  # passes dropped from the spool by the byte bound (not recomputable)

    # -- calibration -----------------------------------------------------------------------
    def _params_for(self, task: VehicleTask, chunk: SensorChunk) -> tuple[dict, int] | None:
        if task.calibration is not None and task.calibration.vehicle_model == chunk.vehicle_model:
            return dict(task.calibration.params), task.calibration.version
        if self.mode == "nominal" and chunk.nominal_params:
            return dict(chunk.nominal_params), 0
        if self.site is not None:
            try:
                return dict(self.site.vehicle_class(chunk.vehicle_model).mean), 0  # cold start: class prior
            except KeyError:
                pass
        if chunk.nominal_params:
            return dict(chunk.nominal_params), 0
        return None

    def _model(self, model_name: str, params: dict, dt: float) -> InverseModel:
        key = (model_name, tuple(sorted(params.items())), dt)
        m = self._models.get(key)
        if m is None:
            m = build_inverse(vehicle_from_params(model_name, params).system(), dt, gamma=edge_gamma(model_name))
            if len(self._models) > 4096:
                self._models.clear()
            self._models[key] = m
        return m

    # -- streams ---------------------------------------------------------------------------
    def on_chunk(self, payload, key_vehicle: str | None = None) -> None:
        """One raw chunk (tagged with ``self.trace``): :meth:`on_chunks` of one."""
        self.on_chunks([(payload, key_vehicle, self.trace)])

    def on_chunks(self, messages: list[tuple[object, str | None, bytes | None]]) -> None:
        """Raw chunks as one tick, ``(payload, key_vehicle, trace)`` in arrival order: decoded together
        (:class:`edge.bank_decode.ChunkDecoder`), then fed in rounds, each vehicle's next chunk per
        round, every round's passes as one bank (:func:`edge.bank.feed_bank`). Each vehicle's
        chunks are processed in their order, with the results of feeding them one at a time; what
        a chunk releases is published tagged with its own trace."""
        raws = [p.to_bytes() if hasattr(p, "to_bytes") else bytes(p) for p, _, _ in messages]  # zenoh.ZBytes, or bytes
        # rounds[r]: each vehicle's (r + 1)-th chunk of the tick, the vehicles in order of first arrival
        rounds: list[list] = [[]]
        depth: dict[str, int] = {}  # chunks of the vehicle so far in this tick
        rank: dict[str, int] = {}  # its order of first arrival
        only, shard, rejected = self.only, self.shard, self.rejected
        for (_, key_vehicle, trace), raw, chunk in zip(messages, raws, self.decoder.decode(raws)):
            if isinstance(chunk, DecodeError):
                rejected[chunk.reason] += 1
                continue
            vehicle = chunk.vehicle_id
            if key_vehicle is not None and key_vehicle != vehicle:
                rejected["key_mismatch"] += 1
                continue
            if (only is not None and vehicle not in only) or not in_shard(vehicle, shard):
                continue
            if chunk.vehicle_model not in MODELS:
                rejected["unsupported_model"] += 1
                continue
            r = depth.get(vehicle, 0)
            depth[vehicle] = r + 1
            if r == 0:
                rank[vehicle] = len(rank)
            elif r == len(rounds):
                rounds.append([])
            rounds[r].append((chunk, raw, trace))
        for r in range(1, len(rounds)):
            rounds[r].sort(key=lambda item: rank[item[0].vehicle_id])
        tasks = self.tasks
        for round_ in rounds:
            ready = []
            for chunk, raw, trace in round_:
                vehicle = chunk.vehicle_id
                task = tasks.get(vehicle)
                if task is None:
                    task = tasks[vehicle] = VehicleTask(vehicle)
                current, seq = task.current, chunk.seq
                if current is not None and seq != 0 and seq == task.expected_seq and current.pass_id == chunk.pass_id:
                    task.expected_seq += 1  # (the pass goes on: what _begin does then)
                    task.current_raw.append(raw)
                    ready.append((task, chunk, trace))
                    continue
                try:
                    if self._begin(task, chunk, raw):
                        ready.append((task, chunk, trace))
                except Exception:  # isolation: one vehicle's failure must not stop the others
                    self._failed(task, chunk)
            if not ready:
                continue

            ending: list[tuple[int, list[ApSegment]]] = []

            def publish(i: int, segments) -> None:  # each vehicle's release leaves as soon as it is ready
                task, chunk, trace = ready[i]
                if chunk.final and not isinstance(segments, Exception):
                    ending.append((i, segments))  # after the round's other releases (see below)
                    return
                self.trace = trace
                try:
                    if isinstance(segments, Exception):
                        raise segments
                    self._end(task, chunk, segments)
                except Exception:  # isolation, as above
                    self._failed(task, chunk)

            feed_bank([(task.current, chunk) for task, chunk, _ in ready], publish)
            # (feed_bank calls publish only for what releases, fails or ends; the trace is left as
            # if every chunk's release had been published)
            for task, chunk, trace in reversed(ready):
                if not chunk.final:
                    self.trace = trace
                    break
            # A pass's end tiles, drift-controls and encodes every tile still waiting for the drift
            # window (on a route shorter than that window, the whole pass): passes ending together
            # (a fleet in lockstep) would hold back the releases of the vehicles behind them in the
            # round, which are cheap. Ends go last; each vehicle's own order is unchanged.
            for i, segments in ending:
                task, chunk, trace = ready[i]
                self.trace = trace
                try:
                    self._end(task, chunk, segments)
                except Exception:  # isolation, as above
                    self._failed(task, chunk)

    def _failed(self, task: VehicleTask, chunk) -> None:
        task.errors += 1
        self.rejected["processing_error"] += 1
        log.exception("vehicle %s: pass %s failed", chunk.vehicle_id, chunk.pass_id)
        task.current, task.current_raw = None, []

    def _begin(self, task: VehicleTask, chunk, raw: bytes) -> bool:
        """Start or continue the vehicle's pass with this chunk; False if the chunk is refused."""
        if task.current is not None and task.current.pass_id == chunk.pass_id and chunk.seq == 0:
            # The vehicle sends the pass again from its start (it was never acknowledged): start over.
            self.restarted += 1
            task.current, task.current_raw = None, []
        if task.current is None or task.current.pass_id != chunk.pass_id:
            if chunk.seq != 0:
                self.rejected["missing_pass_start"] += 1
                return False
            chosen = self._params_for(task, chunk)
            if chosen is None:
                self.rejected["no_calibration"] += 1
                return False
            params, version = chosen
            model = self._model(chunk.vehicle_model, params, 1.0 / chunk.sample_rate_hz)
            task.current = PassProcessor(model, chunk.vehicle_id, chunk.pass_id, chunk.route_id, version,
                                         self.config, chunk.vehicle_model)
            task.current_raw, task.expected_seq, task.current_params = [], 0, params
        if chunk.seq != task.expected_seq:
            self.rejected["sequence_gap"] += 1
            task.current, task.current_raw = None, []
            return False
        task.expected_seq += 1
        task.current_raw.append(raw)
        return True

    def _end(self, task: VehicleTask, chunk, segments: list[ApSegment]) -> None:
        """Publish what the chunk released; at the pass's last chunk, its end."""
        self._publish_segments(segments)
        if chunk.final:
            segments, done = task.current.finish()
            done = dataclasses.replace(done, params=task.current_params)  # the cloud models the pass alike
            self._publish_segments(segments)
            self._send(done.vehicle_id, done.pass_id, done.calib_version,
                       keys.done_key(self.net, chunk.vehicle_id), done.encode())
            self._spool(task, chunk.pass_id, task.current_raw)
            task.current, task.current_raw = None, []

    def _spool(self, task: VehicleTask, pass_id: str, raw: list[bytes]) -> None:
        """Keep a finished pass's raw chunks: at most SPOOL_PASSES per vehicle and ``spool_max_bytes``
        in all, the oldest dropped first."""
        key = (task.vehicle_id, pass_id)
        if key in self._spooled:
            self.spool_bytes -= self._spooled.pop(key)
        task.spool[pass_id] = raw
        self._spooled[key] = n = sum(len(r) for r in raw)
        self.spool_bytes += n
        while len(task.spool) > SPOOL_PASSES:
            old, _ = task.spool.popitem(last=False)
            self.spool_bytes -= self._spooled.pop((task.vehicle_id, old))
        while self.spool_bytes > self.spool_max_bytes and len(self._spooled) > 1:
            (vehicle, old), n = self._spooled.popitem(last=False)
            self.tasks[vehicle].spool.pop(old, None)
            self.spool_bytes -= n
            self.spool_evicted += 1

    def _publish_segments(self, segments: list[ApSegment]) -> None:
        """Publish what one chunk released, in batches of up to ``ap_batch`` per route (one vehicle)."""
        if not segments:  # (most chunks)
            return
        by_route: dict[str, list[ApSegment]] = {}
        for seg in segments:
            by_route.setdefault(seg.route_id, []).append(seg)
        for group in by_route.values():
            for i in range(0, len(group), self.ap_batch):
                part = group[i : i + self.ap_batch]
                msg = part[0] if len(part) == 1 else ApBatch(tuple(part))
                s0 = part[0]
                self._send(s0.vehicle_id, s0.pass_id, s0.calib_version,
                           keys.ap_key(self.net, s0.route_id, s0.tile, s0.vehicle_id), msg.encode())
                self.segments_published += len(part)

    def _send(self, vehicle: str, pass_id: str, calib_version: int, key: str, payload: bytes) -> None:
        if self.outbox is not None:
            self.outbox.add(vehicle, pass_id, calib_version, key, payload, self.trace)
        if self.cloud_present:
            self.publish(key, payload)

    def stats(self) -> dict:
        """Counters for operators (``driveby/<net>/control/<id>/stats``)."""
        return {"rejected": dict(self.rejected), "segments_published": self.segments_published,
                "vehicles": len(self.tasks), "cloud_present": self.cloud_present, "resent": self.resent,
                "restarted": self.restarted,
                "raw_spool": {"passes": len(self._spooled), "bytes": self.spool_bytes,
                              "evicted": self.spool_evicted},
                "outbox": self.outbox.stats() if self.outbox is not None else None}

    # -- delivery ----------------------------------------------------------------------------
    def on_ack(self, payload, key_vehicle: str | None = None) -> None:
        """The cloud acknowledged a pass: it need not be kept any longer."""
        if self.outbox is None:
            return
        try:
            ack = decode_ack(payload)
        except DecodeError as e:
            self.rejected[f"ack_{e.reason}"] += 1
            return
        if key_vehicle is not None and key_vehicle != ack.vehicle_id:
            self.rejected["key_mismatch"] += 1
            return
        self.outbox.ack(ack.vehicle_id, ack.pass_id, ack.calib_version)

    def on_cloud_presence(self, present: bool) -> None:
        """An aggregator appeared (send everything unacknowledged again) or the last one left."""
        if self.outbox is None:
            return
        if present:
            pending, current = self.outbox.traced(), self.trace
            try:
                for key, payload, trace in pending:
                    self.trace = trace  # publish tags with self.trace: each resend with its own message's
                    self.publish(key, payload)
            finally:
                self.trace = current
            self.resent += len(pending)
        self.cloud_present = present

    def on_calibration(self, payload, key_vehicle: str | None = None) -> None:
        """A new calibration: recompute and republish every spooled pass under its version."""
        try:
            cal = decode_calibration(payload)
        except DecodeError as e:
            self.rejected[e.reason] += 1
            return
        if key_vehicle is not None and key_vehicle != cal.vehicle_id:
            self.rejected["key_mismatch"] += 1
            return
        task = self.tasks.setdefault(cal.vehicle_id, VehicleTask(cal.vehicle_id))
        if task.calibration is not None and cal.version <= task.calibration.version:
            return
        try:
            vehicle_from_params(cal.vehicle_model, dict(cal.params))
        except ValueError:
            self.rejected["bad_calibration"] += 1
            return
        task.calibration = cal
        for pass_id, payloads in list(task.spool.items()):
            chunks = [decode_sensor_chunk(p) for p in payloads]  # validated once already: cannot fail
            first = chunks[0]
            model = self._model(first.vehicle_model, dict(cal.params), 1.0 / first.sample_rate_hz)
            proc = PassProcessor(model, first.vehicle_id, pass_id, first.route_id, cal.version, self.config,
                                 first.vehicle_model)
            for ch in chunks:
                self._publish_segments(proc.feed(ch))
            segments, done = proc.finish()
            done = dataclasses.replace(done, params=dict(cal.params))
            self._publish_segments(segments)
            self._send(done.vehicle_id, done.pass_id, done.calib_version,
                       keys.done_key(self.net, cal.vehicle_id), done.encode())


def serve(session: zenoh.Session, edge: Edge, node_id: str, stop: threading.Event) -> None:
    """Wire ``edge`` to a session: zenoh's threads put each raw chunk, calibration and acknowledgement
    in an inbox; one worker takes everything there at once and processes it under a lock, in arrival
    order, the raw chunks as one tick (:meth:`Edge.on_chunks`: a bank, far cheaper per chunk than
    one at a time, and the busier the edge the larger the tick).

    Back-pressure on purpose: the inbox holds at most ``INBOX_MESSAGES``; past that, zenoh's
    delivering thread waits, so zenoh holds back the next message and a busy edge slows its
    publishers (their puts block) instead of buffering without bound or dropping.
    """
    lock = threading.Lock()  # the edge's state
    queued = threading.Condition()  # the inbox
    inbox: list[tuple[str, str, bytes, str, bytes | None]] = []  # (topic, key, payload, vehicle, trace)
    closed = threading.Event()  # no more deliveries: the worker drains the inbox and ends

    def on_sample(topic: str, sample) -> None:
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        trace = sample.attachment
        try:
            _, vehicle = keys.parse_vehicle_key(key, topic)
        except ValueError:
            with lock:
                edge.rejected["bad_key"] += 1
            return
        with queued:
            while len(inbox) >= INBOX_MESSAGES and not closed.is_set():
                queued.wait(0.5)
            inbox.append((topic, key, payload, vehicle, None if trace is None else trace.to_bytes()))
            queued.notify_all()

    handlers = {"calib": edge.on_calibration, "ack": edge.on_ack}
    # An observer that wraps this edge's on_chunk (a test watching the real handler) sees every chunk.
    per_chunk = "on_chunk" in vars(edge)

    def process(batch) -> None:
        i = 0
        while i < len(batch):
            topic, key = batch[i][0], batch[i][1]
            j = i + 1
            while topic == "imu" and j < len(batch) and batch[j][0] == "imu":
                j += 1  # consecutive raw chunks: one tick
            try:
                if topic != "imu":
                    edge.trace = batch[i][4]
                    handlers[topic](batch[i][2], batch[i][3])
                elif per_chunk:
                    for _, _, payload, vehicle, trace in batch[i:j]:
                        edge.trace = trace
                        edge.on_chunk(payload, vehicle)
                else:
                    edge.on_chunks([(payload, vehicle, trace) for _, _, payload, vehicle, trace in batch[i:j]])
            except Exception:  # a daemon never dies of one message; it is counted and logged
                edge.rejected["internal_error"] += 1
                log.exception("failed to process %s", key)
            i = j

    def work() -> None:
        while True:
            with queued:
                while not inbox and not closed.is_set():
                    queued.wait(0.5)
                if not inbox:
                    return
                batch = inbox[:]
                inbox.clear()
                queued.notify_all()
            with lock:
                process(batch)

    worker = threading.Thread(target=work, name="edge-worker", daemon=True)
    worker.start()

    clouds: set[str] = set()

    def on_cloud(sample) -> None:  # liveliness of the aggregators: is anyone there to deliver to?
        with lock:
            key = str(sample.key_expr)
            if sample.kind == zenoh.SampleKind.PUT:
                appeared = key not in clouds
                clouds.add(key)
                if appeared:
                    edge.on_cloud_presence(True)
            else:
                clouds.discard(key)
                if not clouds:
                    edge.on_cloud_presence(False)

    def on_stats(query):
        with query:
            with lock:
                body = edge.stats()
            query.reply(keys.control_key(edge.net, node_id, "stats"), json.dumps(body).encode())

    def on_miss(miss) -> None:  # chunks a vehicle's cache no longer held: a real gap (the pass is dropped)
        with lock:
            edge.rejected["missed_chunks"] += miss.nb
            log.warning("%d raw chunk(s) of %s lost beyond its publisher's cache", miss.nb, miss.source)

    # Raw chunks through an advanced subscriber: chunks missed while a router was down or a link
    # partitioned are detected (sequence numbers, the vehicles' heartbeats) and fetched from the
    # vehicle's publication cache (simfleet.replay.ImuPublishers), delivered in order. Plain puts
    # (publishers without a cache) are delivered as by a plain subscriber.
    imu = zx.declare_advanced_subscriber(session, keys.imu_keyexpr(edge.net),
                                         lambda s: on_sample("imu", s),
                                         recovery=zx.RecoveryConfig(periodic_queries=None, heartbeat=True))
    misses = imu.sample_miss_listener(on_miss)
    subs = [imu, misses,
            session.declare_queryable(keys.control_key(edge.net, node_id, "stats"), on_stats),
            session.declare_subscriber(keys.calib_keyexpr(edge.net), lambda s: on_sample("calib", s)),
            session.declare_subscriber(keys.ack_keyexpr(edge.net), lambda s: on_sample("ack", s)),
            session.liveliness().declare_subscriber(keys.alive_keyexpr(edge.net, "cloud"), on_cloud, history=True)]
    token = session.liveliness().declare_token(keys.alive_key(edge.net, "edge", node_id))
    try:
        stop.wait()
    finally:
        token.undeclare()
        for s in subs:
            s.undeclare()
        closed.set()
        with queued:
            queued.notify_all()
        worker.join()


def build_parser() -> argparse.ArgumentParser:
    """``driveby edge``'s options."""
    p = argparse.ArgumentParser(prog="driveby edge", description="edge daemon: inverse Newmark-β → AP segments")
    add_zenoh_arguments(p)
    p.add_argument("--net", default="net", help="network name in the key space (the same on every daemon; default net)")
    p.add_argument("--id", help="this daemon's id, unique on the net (liveliness, control keys, its TLS certificate's "
                                "name with --tls-cert; default edge-<host>)")
    p.add_argument("--site", help="site registry TOML (vehicle-class priors for cold start)")
    p.add_argument("--calibration", choices=("fleet", "nominal"), default="fleet",
                   help="parameters before the cloud calibrates a vehicle: fleet, its class mean (default); nominal, its log's nominal_params")
    p.add_argument("--vehicle", action="append", help="only process these vehicles (repeatable)")
    p.add_argument("--shard", default="0/1", metavar="I/N",
                   help="only process the vehicles of hash shard I of N (run N edges to share a fleet)")
    p.add_argument("--ap-batch", type=int, default=AP_BATCH, metavar="N",
                   help=f"AP segments per message, 1 to {MAX_BATCH_SEGMENTS} (1: one ap_segment each)")
    p.add_argument("--spool", metavar="DIR",
                   help="keep unacknowledged passes on disk here (survives an edge restart; default: memory)")
    p.add_argument("--spool-max-mb", type=float, default=DEFAULT_MAX_BYTES / 2**20, metavar="MB",
                   help="bound of the unacknowledged store; the oldest passes are dropped (counted) beyond it")
    p.add_argument("--raw-spool-mb", type=float, default=SPOOL_MAX_BYTES / 2**20, metavar="MB",
                   help="bound of the raw passes kept (in memory) to recompute when a calibration changes; "
                        f"also at most {SPOOL_PASSES} per vehicle; the oldest are dropped (counted) beyond it")
    p.add_argument("--log-level", default="WARNING", type=str.upper, choices=LOG_LEVELS,
                   help="logging level (default WARNING; start, connection and peers are logged unless ERROR)")
    return p


def main(argv: list[str] | None = None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s edge %(levelname)s %(message)s")
    try:
        keys.check_id(args.net, "net")
        args.id = keys.check_id(args.id or default_id("edge"), "id")
        shard = parse_shard(args.shard)
        if not 1 <= args.ap_batch <= MAX_BATCH_SEGMENTS:
            raise ValueError(f"--ap-batch: expected 1 to {MAX_BATCH_SEGMENTS}, got {args.ap_batch}")
        if not args.raw_spool_mb >= 0:
            raise ValueError(f"--raw-spool-mb: expected >= 0, got {args.raw_spool_mb}")
        if not args.spool_max_mb > 0:
            raise ValueError(f"--spool-max-mb: expected > 0, got {args.spool_max_mb}")
        conf = config_from_args(args)
    except SecurityError as e:  # a TLS file it names is missing
        print(f"driveby edge: {e}", file=sys.stderr)
        return 1
    except ValueError as e:  # the command line itself: a usage error, as argparse's
        print(f"driveby edge: {e}", file=sys.stderr)
        return 2
    try:
        site = load_site(args.site) if args.site else None
        outbox = Outbox(args.spool, int(args.spool_max_mb * 2**20))
    except (RegistryError, ValueError, OSError) as e:  # what the arguments name is unusable
        print(f"driveby edge: {e}", file=sys.stderr)
        return 1
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    try:
        with zenoh.open(conf) as session:
            presence = Presence(session, args.net, "edge", args.id, args.connect + args.listen, args.log_level)

            def publish(key, payload):
                session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK, attachment=edge.trace)

            edge = Edge(args.net, publish, site, args.calibration,
                        vehicles=set(args.vehicle) if args.vehicle else None, shard=shard, ap_batch=args.ap_batch,
                        outbox=outbox, spool_max_bytes=int(args.raw_spool_mb * 2**20))
            # What exists now (modules, numba and pyarrow internals, the session) lives as long as the
            # process: keep it out of full garbage collections, whose pause scans every tracked object
            # (~0.1 s of them) and would land in the middle of the stream.
            gc.collect()
            gc.freeze()
            try:
                serve(session, edge, args.id, stop)
            finally:
                presence.close()
    except zenoh.ZError as e:
        print(f"driveby edge: zenoh: {zenoh_message(e)}", file=sys.stderr)
        return 1
    except IdInUseError as e:
        print(f"driveby edge: {e}", file=sys.stderr)
        return 1
    return 0
