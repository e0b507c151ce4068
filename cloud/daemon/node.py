"""The cloud aggregator daemon: AP segments in over Zenoh, estimates out (queries, Rerun, Parquet).

The process around :class:`cloud.daemon.core.Cloud`: arguments, the Zenoh session, its subscribers
and queryables, the journal, signals and the quiet-bus schedule. Everything it applies is the core's.
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import signal
import struct
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from shared import keys
from shared.registry import RegistryError, load_site
from shared.security import SecurityError
from shared.transport import (LOG_LEVELS, IdInUseError, Presence, add_zenoh_arguments, config_from_args, default_id,
                              zenoh_message)

from cloud.daemon.core import Cloud
from cloud.daemon.durable import AP, CALIB, DONE, Durability, GroupCommit
from cloud.daemon.journal import Journal, JournalError
from cloud.daemon.settings import CloudSettings
from cloud.ingest.aggregator import DEFAULT_MAX_RESIDENT_PASSES, MIN_RESIDENT_PASSES
from cloud.ingest.segment_store import DEFAULT_MAX_RESIDENT

log = logging.getLogger("driveby.cloud")

#: Latency tracing (benchmarks): a raw chunk published with this zenoh attachment (its publication
#: time, Unix s, little-endian float64) passes it, via the edge, to the segments it releases; the
#: cloud records (sent, applied) for each such segment it accepts and answers ``control/<id>/latency``.
TRACE = struct.Struct("<d")
TRACE_RECORDS = 100_000
# The idle loop's shortest pause between alignment slices: long enough for input threads waiting
# on the lock to wake and take it before the next slice does.
MIN_SLICE_GAP_S = 0.005


class LatencyTrace:
    """The last ``n`` traced segments' (sent, applied) times, Unix s, in a ring allocated (and
    written, so resident) up front: the daemon's memory does not creep up as it fills."""

    def __init__(self, n: int = TRACE_RECORDS):
        self.rows = np.full((n, 2), np.nan)
        self.count = 0  # records ever added

    def add(self, sent: float, applied: float, times: int = 1) -> None:
        for _ in range(min(times, len(self.rows))):
            self.rows[self.count % len(self.rows)] = (sent, applied)
            self.count += 1

    def since(self, t: float) -> tuple[list[float], list[float]]:
        """(sent, applied) of the records whose raw chunk was published at ``t`` or later."""
        n = len(self.rows)
        order = np.arange(self.count - min(self.count, n), self.count) % n
        rows = self.rows[order]
        rows = rows[rows[:, 0] >= t]
        return rows[:, 0].tolist(), rows[:, 1].tolist()


#: The attachment of the first reply to ``control/<id>/tables``: JSON naming the files that follow
#: (each a reply whose attachment is its file name) and the aggregator's counters.
MANIFEST = "manifest.json"


def status_body(cloud: Cloud, node_id: str) -> dict:
    """The answer to ``control/<id>/status``: the cloud's status (passes, calibration), its
    aggregator's counters (segments accepted, rejected by reason), the vehicles it has heard of, and
    each bridge's summary row and assessment (:func:`cloud.daemon.queries.bridge_state`)."""
    bridges = {bid: json.loads(cloud.bridge_state(bid)) for bid in cloud.bridges.bridges}
    return {"id": node_id, "net": cloud.net, **cloud.status(), "stats": cloud.aggregator.stats(),
            "vehicles": sorted(cloud.vehicles),
            "bridges": {bid: {"summary": b["summary"], "assessment": b["assessment"]} for bid, b in bridges.items()}}


def serve(session: zenoh.Session, cloud: Cloud, stop: threading.Event, default_export: Path | None = None,
          durability: Durability | None = None, group: GroupCommit | None = None) -> None:
    """Apply each message on the zenoh thread that delivers it, one at a time under a lock.

    No queue between the subscription and the aggregator: a hand-off per message cost as much as
    decoding it. Queries are answered under the same lock, from state that has applied every
    message delivered so far. The calling thread publishes a held-back status and runs the core's
    idle work once the bus has been quiet for ``quiet_s`` (the cloud's settings).

    Back-pressure, chosen: when the cloud falls behind, nothing is buffered without bound and
    nothing is dropped. While a message is applied zenoh holds back the next one; the cloud's queue
    at the router (a few 64 kB batches) and the TCP buffers fill; the router stops reading the
    edges' links; an edge's ``put`` (``CongestionControl.BLOCK``) waits, and so does the edge's
    loop, whose input then waits in the same way upstream. What the edge has sent stays in its
    outbox until acknowledged. Zenoh bounds one wait: a link blocked for longer than its
    ``wait_before_close`` (5 s) is closed. The cloud then reconnects, its liveliness token comes
    back and every edge resends what it has not had acknowledged (duplicates are idempotent), so
    even then nothing is lost, at the price of a resend; so work that holds the lock (the quiet-bus
    work below) must be bounded well under those 5 s.

    With a journal, what the cloud publishes goes through ``group`` (:class:`GroupCommit`): a thread
    here publishes each group once the journal is synced for it, outside the lock.
    """
    settings, node_id, shard = cloud.settings, cloud.node_id, cloud.settings.shard
    lock = threading.Lock()
    traced = LatencyTrace()
    # CPU of the message callbacks (thread time): in the cloud's own code (``apply_s``), and with
    # the hand-over from zenoh (``callback_s``); the process's total is the OS's (benchmarks).
    cpu = {"messages": 0, "apply_s": 0.0, "callback_s": 0.0}
    last_input = cloud.clock()

    def apply(on_message, sample, kind: str) -> None:
        nonlocal last_input
        t0 = time.thread_time()
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        trace = sample.attachment
        with lock:
            t1 = time.thread_time()
            try:
                if durability is not None:  # journalled before it can affect any state
                    durability.record(kind, key, payload)
                before = cloud.aggregator.accepted
                on_message(key, payload)
                accepted = cloud.aggregator.accepted - before  # segments: a batch holds several
                if trace is not None and accepted:
                    trace = trace.to_bytes()
                    if len(trace) == TRACE.size:
                        traced.add(TRACE.unpack(trace)[0], time.time(), accepted)
            except Exception:  # a daemon never dies of one message; it is counted and logged
                cloud.aggregator.rejected["internal_error"] += 1
                log.exception("failed to process %s", key)
            last_input = cloud.clock()
            t2 = time.thread_time()
            cpu["messages"] += 1
            cpu["apply_s"] += t2 - t1
            cpu["callback_s"] += t2 - t0
        if group is not None and group.full():  # (the flusher is behind: this thread waits for it)
            flush_group()

    def flush_group() -> None:
        try:
            group.flush()
        except Exception:  # a daemon never dies of a publication; an edge resends what it has not had acknowledged
            log.exception("publishing a group of messages failed")

    def flusher() -> None:
        while not flusher_stop.is_set():
            group.wait(flusher_stop)
            flush_group()

    def on_state(query):
        with query:
            try:
                parts = str(query.key_expr).split("/")
                if len(parts) != 6 or "*" in parts[4] or "*" in parts[5]:
                    raise ValueError
                route, tile_i = parts[4], int(parts[5])
            except ValueError:
                query.reply_err(b"expected driveby/<net>/state/profile/<route>/<tile>")
                return
            with lock:
                data = cloud.tile_state(route, tile_i)
            if data is None:
                query.reply_err(f"unknown route {route}".encode())
            else:
                query.reply(keys.state_profile_key(cloud.net, route, tile_i), data)

    def on_export(query):
        with query:
            params = dict(p.split("=", 1) for p in str(query.parameters).split(";") if "=" in p)
            target = params.get("dir") or (str(default_export) if default_export else None)
            if not target:
                query.reply_err(b"no export directory: pass ?dir=PATH or start the daemon with --export")
                return
            with lock:
                job = cloud.table_job()
            table = job() if job is not None else None  # the vehicle table without the lock (a snapshot's)
            with lock:
                if table is not None:
                    cloud.keep_table(*table)
                try:
                    written = cloud.export(Path(target))
                except OSError as e:
                    query.reply_err(f"export failed: {e}".encode())
                    return
                body = {"written": [str(p) for p in written], "stats": cloud.aggregator.stats()}
            query.reply(keys.control_key(cloud.net, node_id, "export"), json.dumps(body).encode())

    def on_status(query):  # what `driveby status` prints
        with query:
            with lock:
                body = status_body(cloud, node_id)
            query.reply(keys.control_key(cloud.net, node_id, "status"), json.dumps(body).encode())

    def on_tables(query):  # what `driveby export` writes: the export's files travel, the client writes them
        with query:
            with lock:
                job = cloud.table_job()
            table = job() if job is not None else None  # the vehicle table without the lock (a snapshot's)
            with lock, tempfile.TemporaryDirectory(prefix="driveby-export-") as tmp:
                if table is not None:
                    cloud.keep_table(*table)
                try:
                    written = cloud.export(Path(tmp))
                    files = {p.name: p.read_bytes() for p in written}
                except OSError as e:
                    query.reply_err(f"export failed: {e}".encode())
                    return
                stats = cloud.aggregator.stats()
            key = keys.control_key(cloud.net, node_id, "tables")
            manifest = {"files": sorted(files), "stats": stats}
            query.reply(key, json.dumps(manifest).encode(), attachment=MANIFEST.encode())
            for name, data in files.items():
                query.reply(key, data, attachment=name.encode())

    def on_stats(query):
        with query:
            with lock:
                body = {"stats": cloud.aggregator.stats(), "passes_complete": cloud.passes_complete, "cpu": cpu,
                        **({"durability": {**durability.stats(), **(group.stats() if group is not None else {})}}
                           if durability is not None else {})}
            query.reply(keys.control_key(cloud.net, node_id, "stats"), json.dumps(body).encode())

    def on_latency(query):  # ?since=T: the traced segments whose raw chunk was published at T or later
        with query:
            params = dict(p.split("=", 1) for p in str(query.parameters).split(";") if "=" in p)
            try:
                since = float(params.get("since", "-inf"))
            except ValueError:
                query.reply_err(b"since: expected Unix seconds")
                return
            with lock:
                sent, applied = traced.since(since)
            body = {"sent": sent, "applied": applied}
            query.reply(keys.control_key(cloud.net, node_id, "latency"), json.dumps(body).encode())

    decl = [
        session.declare_subscriber(keys.done_keyexpr(cloud.net), lambda sample: apply(cloud.on_done, sample, DONE)),
        session.declare_queryable(keys.control_key(cloud.net, node_id, "export"), on_export),
        session.declare_queryable(keys.control_key(cloud.net, node_id, "stats"), on_stats),
        session.declare_queryable(keys.control_key(cloud.net, node_id, "status"), on_status),
        session.declare_queryable(keys.control_key(cloud.net, node_id, "tables"), on_tables),
        session.declare_queryable(keys.control_key(cloud.net, node_id, "latency"), on_latency),
    ]
    # A shard subscribes to, and answers state queries for, its own routes only: Zenoh routes each
    # segment and each query to its owner, so scaling out needs no routing code of ours.
    for route in sorted(shard) if shard is not None else ["*"]:
        decl.append(session.declare_subscriber(keys.ap_keyexpr(cloud.net, route),
                                               lambda sample: apply(cloud.on_segment, sample, AP)))
        decl.append(session.declare_queryable(keys.state_profile_keyexpr(cloud.net, route), on_state))

    def on_bridge_state(query, bridge_id: str):
        with query:
            with lock:
                body = cloud.bridge_state(bridge_id)
            query.reply(keys.state_bridge_key(cloud.net, bridge_id), body)

    if shard is not None and cloud.calibrator is not None:
        # Each vehicle is calibrated by one shard (cloud.daemon.sharding); the others apply what it publishes.
        decl.append(session.declare_subscriber(keys.calib_keyexpr(cloud.net),
                                               lambda sample: apply(cloud.on_calibration, sample, CALIB)))
    for bid in cloud.bridges.bridges:  # this aggregator's bridges (a shard's: those on its routes)
        decl.append(session.declare_queryable(keys.state_bridge_key(cloud.net, bid),
                                              lambda query, bid=bid: on_bridge_state(query, bid)))
    flusher_stop = threading.Event()
    flushing = None
    if group is not None:
        group.grouping = True
        flushing = threading.Thread(target=flusher, name="group-commit", daemon=True)
        flushing.start()
    token = session.liveliness().declare_token(keys.alive_key(cloud.net, "cloud", node_id))
    # While alignment has slices to run, the loop comes back after a short gap rather than a whole
    # status interval: input waiting on the lock takes it in the gap, and a long sweep on a quiet bus
    # is not stretched out by idle time.
    slice_wait = min(settings.status_interval_s, MIN_SLICE_GAP_S)
    wait = settings.status_interval_s
    try:
        while not stop.wait(wait):
            wait = settings.status_interval_s
            try:
                with lock:
                    quiet = cloud.clock() - last_input >= settings.quiet_s
                    cloud.flush_status(force=quiet)
                    if quiet:  # align, calibrate and estimate bridges when the bus is quiet
                        cloud.fuse_pending(settings.flush_budget_s)  # bounded: the next input waits on the lock
                        if cloud.maybe_align():  # one slice of a sweep (align_budget_s): bounded too
                            if cloud.aligning:
                                wait = slice_wait
                            cloud.bridge_sync_due = True  # the passes' held segments may have moved
                        else:
                            # (A round journals the calibrator through cloud.record before publishing.)
                            cloud.maybe_calibrate(tail=cloud.since_new_pass_s() >= settings.epoch_tail_s)
                            if cloud.calibrating:  # a round in slices (round_budget_s): back after a short gap
                                wait = slice_wait
                            cloud.step_rail()  # carriage batches
                            # Bridges take passes at their vehicle's current calibration only, so a
                            # round just published leaves them as they are until recomputed.
                            cloud.maybe_estimate_bridges()
                        cloud.flush_spill()
                        if durability is not None:
                            durability.maybe_snapshot()
                    elif cloud.bridges_may_run():  # streaming: bridges within their share of the time
                        cloud.maybe_estimate_bridges()
            except Exception:
                log.exception("calibration round failed")
    finally:
        token.undeclare()
        for d in decl:
            d.undeclare()
        if group is not None:
            flusher_stop.set()
            flushing.join()
            group.grouping = False  # (from here on, published at once)
            flush_group()


def build_parser() -> argparse.ArgumentParser:
    """``driveby cloud``'s options."""
    p = argparse.ArgumentParser(prog="driveby cloud", description="cloud aggregator daemon")
    add_zenoh_arguments(p)
    p.add_argument("--net", default="net", help="network name in the key space (the same on every daemon; default net)")
    p.add_argument("--id", help="this daemon's id, unique on the net (liveliness, control keys, its TLS "
                                "certificate's name with --tls-cert; default cloud-<host>)")
    p.add_argument("--site", required=True, help="site registry TOML")
    p.add_argument("--routes", metavar="R1,R2,…",
                   help="own only these routes (a shard: segments, state queries, bridges; default: every route)")
    p.add_argument("--calibration", choices=("fleet", "nominal"), default="fleet",
                   help="fleet: calibrate every vehicle from the fleet's consensus; nominal: trust the edges")
    p.add_argument("--align", action=argparse.BooleanOptionalAction, default=True,
                   help="align road passes in chainage against the consensus (GNSS bias, odometry stretch; "
                        "default on, --no-align trusts the reported chainage)")
    p.add_argument("--export", type=Path, help="default export directory")
    p.add_argument("--state", type=Path, metavar="DIR",
                   help="durable state (journal + snapshots): a restarted cloud resumes from it")
    p.add_argument("--max-resident-segments", type=int, default=DEFAULT_MAX_RESIDENT, metavar="N",
                   help="keep at most N segments decoded in memory, the rest spilled to disk (under --state, "
                        "else the temporary directory) and read back exactly when needed "
                        f"(default {DEFAULT_MAX_RESIDENT}, ~4 kB each)")
    p.add_argument("--max-resident-passes", type=int, default=DEFAULT_MAX_RESIDENT_PASSES, metavar="N",
                   help="keep the bookkeeping of at most N passes (the most recent) in memory, the rest on disk "
                        f"like spilled segments (default {DEFAULT_MAX_RESIDENT_PASSES}, a few kB each)")
    p.add_argument("--epoch-first", type=int, default=CloudSettings.epoch_first, metavar="N",
                   help="completed passes of the first calibration epoch (default "
                        f"{CloudSettings.epoch_first}; a batch of known size calibrates once on all of it)")
    p.add_argument("--rrd", type=Path, help="save the Rerun recording to this file")
    p.add_argument("--viewer", action="store_true", help="spawn a Rerun viewer")
    p.add_argument("--log-level", default="WARNING", type=str.upper, choices=LOG_LEVELS,
                   help="logging level (default WARNING; start, connection and peers are logged unless ERROR)")
    return p


def main(argv: list[str] | None = None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s cloud %(levelname)s %(message)s")
    try:
        keys.check_id(args.net, "net")
        args.id = keys.check_id(args.id or default_id("cloud"), "id")
        conf = config_from_args(args)
        if args.max_resident_segments < 1:
            raise ValueError(f"--max-resident-segments: expected >= 1, got {args.max_resident_segments}")
        if args.max_resident_passes < MIN_RESIDENT_PASSES:
            raise ValueError(f"--max-resident-passes: expected >= {MIN_RESIDENT_PASSES}, "
                             f"got {args.max_resident_passes}")
    except SecurityError as e:  # a TLS file it names is missing
        print(f"driveby cloud: {e}", file=sys.stderr)
        return 1
    except ValueError as e:  # the command line itself: a usage error, as argparse's
        print(f"driveby cloud: {e}", file=sys.stderr)
        return 2
    try:
        site = load_site(args.site)
        shard = None
        if args.routes:
            shard = frozenset(r.strip() for r in args.routes.split(",") if r.strip())
            unknown = sorted(shard - {r.id for r in site.routes})
            if unknown or not shard:
                raise ValueError(f"--routes: {', '.join(unknown) or 'empty'}: not a route of {args.site}")
        settings = CloudSettings(calibration=args.calibration, align=args.align, shard=shard,
                                 max_resident=args.max_resident_segments,
                                 max_resident_passes=args.max_resident_passes, spill_dir=args.state,
                                 epoch_first=args.epoch_first)
        journal = Journal(args.state) if args.state else None
    except (RegistryError, ValueError, JournalError, OSError) as e:  # what the arguments name is unusable
        print(f"driveby cloud: {e}", file=sys.stderr)
        return 1
    view = None
    if args.rrd or args.viewer:
        from cloud.view import View  # rerun: loaded only by a daemon that draws

        view = View(rrd_path=args.rrd, spawn_viewer=args.viewer, routes={r.id: r.length_m for r in site.routes},
                    bridges=list(site.bridges), geometry={r.id: r.geometry for r in site.routes})
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    durability = None
    try:
        with zenoh.open(conf) as session:
            presence = Presence(session, args.net, "cloud", args.id, args.connect + args.listen, args.log_level)
            calib_prefix = keys.calib_key(args.net, "x")[:-1]

            def put(key, payload):
                session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

            group = GroupCommit(journal, put) if journal is not None else None

            def publish(key, payload):
                if durability is None:
                    put(key, payload)
                    return
                if durability.live and key.startswith(calib_prefix):
                    durability.record(CALIB, key, payload)  # the cloud's own decisions are state too
                group.publish(key, payload)  # nothing leaves that promises more than is on disk

            cloud = Cloud(args.net, site, publish, settings, view, clock=time.monotonic, node_id=args.id)
            if journal is not None:
                durability = Durability(journal, cloud)
                durability.recover()
                durability.live = True
                cloud.record = durability.record_own
            # What exists now (modules, numba and pyarrow internals, the session) lives as long as the
            # process: keep it out of full garbage collections, whose pause scans every tracked object
            # and would land in the middle of the stream.
            gc.collect()
            gc.freeze()
            try:
                serve(session, cloud, stop, args.export, durability, group)
            finally:
                presence.close()
            if durability is not None:
                durability.maybe_snapshot(force=True)  # a clean stop leaves a compact state: a fast restart
            if args.export:
                cloud.export(args.export)
    except zenoh.ZError as e:
        print(f"driveby cloud: zenoh: {zenoh_message(e)}", file=sys.stderr)
        return 1
    except JournalError as e:  # the state directory became unusable while running (or at recovery)
        print(f"driveby cloud: --state: {e}", file=sys.stderr)
        return 1
    except IdInUseError as e:
        print(f"driveby cloud: {e}", file=sys.stderr)
        return 1
    finally:
        if durability is not None:
            durability.close()
        if view is not None:
            view.close()
    return 0
