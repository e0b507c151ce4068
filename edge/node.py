"""The edge daemon: vehicle tasks turning raw sensor streams into AP segments over Zenoh.

One process can host the tasks of many vehicles (``driveby run`` starts one for the fleet) or of
one (``--vehicle``, as on board). Each vehicle's task is isolated: a bad stream or a failure in
one vehicle's processing is counted and logged, and the others carry on.
"""

from __future__ import annotations

import argparse
import collections
import logging
import queue
import signal
import sys
import threading
from dataclasses import dataclass, field

import zenoh

from shared import keys
from shared.dynamics.inverse import InverseModel, build_inverse
from shared.registry import RegistryError, Site, load_site
from shared.schema import Calibration, DecodeError, SensorChunk, decode_calibration, decode_sensor_chunk
from shared.transport import add_zenoh_arguments, config_from_args
from shared.vehicles import MODELS, vehicle_from_params

from .pipeline import EdgeConfig, PassProcessor

log = logging.getLogger("driveby.edge")

SPOOL_PASSES = 64  # raw passes kept per vehicle for recomputation when calibration changes


@dataclass
class VehicleTask:
    """One vehicle: its calibration, the pass in progress and a bounded spool of raw passes."""

    vehicle_id: str
    calibration: Calibration | None = None
    current: PassProcessor | None = None
    current_chunks: list = field(default_factory=list)
    expected_seq: int = 0
    spool: collections.OrderedDict = field(default_factory=collections.OrderedDict)
    errors: int = 0


class Edge:
    """Transport-free core of the edge: ``on_chunk``/``on_calibration`` call ``publish(key, bytes)``."""

    def __init__(self, net: str, publish, site: Site | None = None, calibration: str = "fleet",
                 config: EdgeConfig = EdgeConfig(), vehicles: set[str] | None = None):
        if calibration not in ("fleet", "nominal"):
            raise ValueError(f"calibration: expected 'fleet' or 'nominal', got {calibration!r}")
        self.net, self.publish, self.site, self.mode, self.config = net, publish, site, calibration, config
        self.only = vehicles
        self.tasks: dict[str, VehicleTask] = {}
        self.rejected: collections.Counter[str] = collections.Counter()
        self.segments_published = 0
        # Opaque tag of the message being processed (the zenoh attachment of a raw chunk, if any): what
        # that chunk releases is published with it, so a benchmark can time a segment from its raw chunk.
        self.trace: bytes | None = None
        self._models: dict[tuple, InverseModel] = {}

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
            m = build_inverse(vehicle_from_params(model_name, params).system(), dt)
            if len(self._models) > 4096:
                self._models.clear()
            self._models[key] = m
        return m

    # -- streams ---------------------------------------------------------------------------
    def on_chunk(self, payload, key_vehicle: str | None = None) -> None:
        try:
            chunk = decode_sensor_chunk(payload)
        except DecodeError as e:
            self.rejected[e.reason] += 1
            return
        if key_vehicle is not None and key_vehicle != chunk.vehicle_id:
            self.rejected["key_mismatch"] += 1
            return
        if self.only is not None and chunk.vehicle_id not in self.only:
            return
        if chunk.vehicle_model not in MODELS:
            self.rejected["unsupported_model"] += 1
            return
        task = self.tasks.setdefault(chunk.vehicle_id, VehicleTask(chunk.vehicle_id))
        try:
            self._feed(task, chunk)
        except Exception:  # isolation: one vehicle's failure must not stop the others
            task.errors += 1
            self.rejected["processing_error"] += 1
            log.exception("vehicle %s: pass %s failed", chunk.vehicle_id, chunk.pass_id)
            task.current, task.current_chunks = None, []

    def _feed(self, task: VehicleTask, chunk: SensorChunk) -> None:
        if task.current is None or task.current.pass_id != chunk.pass_id:
            if chunk.seq != 0:
                self.rejected["missing_pass_start"] += 1
                return
            chosen = self._params_for(task, chunk)
            if chosen is None:
                self.rejected["no_calibration"] += 1
                return
            params, version = chosen
            model = self._model(chunk.vehicle_model, params, 1.0 / chunk.sample_rate_hz)
            task.current = PassProcessor(model, chunk.vehicle_id, chunk.pass_id, chunk.route_id, version,
                                         self.config, chunk.vehicle_model)
            task.current_chunks, task.expected_seq = [], 0
        if chunk.seq != task.expected_seq:
            self.rejected["sequence_gap"] += 1
            task.current, task.current_chunks = None, []
            return
        task.expected_seq += 1
        task.current_chunks.append(chunk)
        self._publish_segments(task.current.feed(chunk))
        if chunk.final:
            segments, done = task.current.finish()
            self._publish_segments(segments)
            self.publish(keys.done_key(self.net, chunk.vehicle_id), done.encode())
            task.spool[chunk.pass_id] = task.current_chunks
            while len(task.spool) > SPOOL_PASSES:
                task.spool.popitem(last=False)
            task.current, task.current_chunks = None, []

    def _publish_segments(self, segments) -> None:
        for seg in segments:
            self.publish(keys.ap_key(self.net, seg.route_id, seg.tile, seg.vehicle_id), seg.encode())
            self.segments_published += 1

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
        for pass_id, chunks in list(task.spool.items()):
            first = chunks[0]
            model = self._model(first.vehicle_model, dict(cal.params), 1.0 / first.sample_rate_hz)
            proc = PassProcessor(model, first.vehicle_id, pass_id, first.route_id, cal.version, self.config,
                                 first.vehicle_model)
            for ch in chunks:
                self._publish_segments(proc.feed(ch))
            segments, done = proc.finish()
            self._publish_segments(segments)
            self.publish(keys.done_key(self.net, cal.vehicle_id), done.encode())


def serve(session: zenoh.Session, edge: Edge, node_id: str, stop: threading.Event) -> None:
    """Wire ``edge`` to a session: subscriptions feed one worker thread, in arrival order."""
    inbox: queue.Queue = queue.Queue(maxsize=4096)  # full → zenoh's thread waits: back-pressure

    def on_imu(sample):
        trace = sample.attachment
        inbox.put(("imu", str(sample.key_expr), sample.payload.to_bytes(),
                   None if trace is None else trace.to_bytes()))

    def on_calib(sample):
        inbox.put(("calib", str(sample.key_expr), sample.payload.to_bytes(), None))

    subs = [session.declare_subscriber(keys.imu_keyexpr(edge.net), on_imu),
            session.declare_subscriber(keys.calib_keyexpr(edge.net), on_calib)]
    token = session.liveliness().declare_token(keys.alive_key(edge.net, "edge", node_id))
    try:
        while not stop.is_set():
            try:
                kind, key, payload, trace = inbox.get(timeout=0.2)
            except queue.Empty:
                continue
            edge.trace = trace
            if kind == "imu":
                try:
                    _, vehicle = keys.parse_vehicle_key(key, "imu")
                except ValueError:
                    edge.rejected["bad_key"] += 1
                    continue
                edge.on_chunk(payload, vehicle)
            else:
                try:
                    _, vehicle = keys.parse_vehicle_key(key, "calib")
                except ValueError:
                    edge.rejected["bad_key"] += 1
                    continue
                edge.on_calibration(payload, vehicle)
    finally:
        token.undeclare()
        for s in subs:
            s.undeclare()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="driveby edge", description="edge daemon: inverse Newmark-β → AP segments")
    add_zenoh_arguments(p)
    p.add_argument("--net", default="net", help="network name in the key space")
    p.add_argument("--id", default="edge-1", help="this daemon's id (liveliness)")
    p.add_argument("--site", help="site registry TOML (vehicle-class priors for cold start)")
    p.add_argument("--calibration", choices=("fleet", "nominal"), default="fleet")
    p.add_argument("--vehicle", action="append", help="only process these vehicles (repeatable)")
    p.add_argument("--log-level", default="WARNING")
    args = p.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s edge %(levelname)s %(message)s")
    try:
        site = load_site(args.site) if args.site else None
        keys.check_id(args.net, "net")
        conf = config_from_args(args)
    except (RegistryError, ValueError) as e:
        print(f"driveby edge: {e}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    try:
        with zenoh.open(conf) as session:
            def publish(key, payload):
                session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK, attachment=edge.trace)

            edge = Edge(args.net, publish, site, args.calibration,
                        vehicles=set(args.vehicle) if args.vehicle else None)
            serve(session, edge, args.id, stop)
    except zenoh.ZError as e:
        print(f"driveby edge: zenoh: {e}", file=sys.stderr)
        return 1
    return 0
