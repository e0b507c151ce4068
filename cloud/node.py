"""The cloud aggregator daemon: AP segments in over Zenoh, estimates out (queries, Rerun, Parquet)."""

from __future__ import annotations

import argparse
import collections
import json
import logging
import queue
import signal
import sys
import threading
from pathlib import Path

import numpy as np
import pyarrow as pa
import zenoh

from shared import keys
from shared.registry import RegistryError, Site, load_site
from shared.transport import add_zenoh_arguments, config_from_args

from .aggregator import Aggregator
from .estimators.mean_profile import MeanProfile
from .export import profile_table, write_export

log = logging.getLogger("driveby.cloud")

TILE_M = 50.0


class Cloud:
    """Transport-free core of the daemon: the aggregator, its estimators and the view."""

    def __init__(self, net: str, site: Site, publish, view=None, spacing_m: float = 0.05):
        self.net, self.site, self.publish, self.view = net, site, publish, view
        self.profile = MeanProfile({r.id: r.length_m for r in site.routes}, spacing_m)
        self.aggregator = Aggregator(site, [self.profile])
        self.vehicles: dict[str, dict] = collections.defaultdict(
            lambda: {"passes": 0, "last_pass": "", "calib_version": 0, "segments": 0})
        self.passes_complete = 0

    def on_segment(self, key: str, payload: bytes) -> None:
        try:
            _, _, _, vehicle = keys.parse_ap_key(key)
        except ValueError:
            self.aggregator.rejected["bad_key"] += 1
            return
        self._acks(self.aggregator.on_segment(payload, vehicle))

    def on_done(self, key: str, payload: bytes) -> None:
        self._acks(self.aggregator.on_pass_done(payload))

    def _acks(self, acks) -> None:
        for ack in acks:
            self.passes_complete += 1
            v = self.vehicles[ack.vehicle_id]
            v["passes"] += 1
            v["last_pass"] = ack.pass_id
            v["calib_version"] = ack.calib_version
            v["segments"] += ack.n_segments_accepted
            self.publish(keys.ack_key(self.net, ack.vehicle_id), ack.encode())
            if self.view is not None:
                self._log_view()

    def _log_view(self) -> None:
        try:
            self.view.set_pass(self.passes_complete)
            for snap in self.profile.snapshot().values():
                self.view.log_profile(snap)
                P = int(round(TILE_M / self.profile.spacing_m))
                counts = [int(snap.n_passes[i : i + P].max(initial=0)) for i in range(0, snap.n_passes.size, P)]
                self.view.log_tile_counts(snap.route_id, TILE_M, np.asarray(counts))
            self.view.log_vehicle_status(dict(self.vehicles))
            self.view.log_stats(self.aggregator.stats())
        except Exception:  # the view is a side subscriber: never let it take the daemon down
            log.exception("rerun view update failed")

    def tile_state(self, route_id: str, tile: int) -> bytes | None:
        snaps = self.profile.snapshot(route_id)
        if route_id not in snaps:
            return None
        s = snaps[route_id]
        P = int(round(TILE_M / self.profile.spacing_m))
        sl = slice(tile * P, (tile + 1) * P)
        table = pa.table({"chainage_m": s.chainage_m[sl], "elevation_m": s.elevation_m[sl],
                          "lo95_m": s.lo95_m[sl], "hi95_m": s.hi95_m[sl], "n_passes": s.n_passes[sl]})
        sink = pa.BufferOutputStream()
        with pa.ipc.new_stream(sink, table.schema) as w:
            w.write_table(table)
        return sink.getvalue().to_pybytes()

    def export(self, out_dir: Path) -> list[Path]:
        written = write_export(out_dir, {"profile": profile_table(self.profile.snapshot())})
        if self.view is not None:
            self.view.flush()
        return written


def serve(session: zenoh.Session, cloud: Cloud, node_id: str, keyexpr: str, stop: threading.Event,
          default_export: Path | None = None) -> None:
    """Subscriptions feed one worker thread; queries are answered from the worker's state under a lock."""
    inbox: queue.Queue = queue.Queue(maxsize=65536)
    lock = threading.Lock()

    def on_ap(sample):
        inbox.put(("ap", str(sample.key_expr), sample.payload.to_bytes()))

    def on_done(sample):
        inbox.put(("done", str(sample.key_expr), sample.payload.to_bytes()))

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
            # Everything already received must be applied before exporting.
            inbox.join()
            with lock:
                try:
                    written = cloud.export(Path(target))
                except OSError as e:
                    query.reply_err(f"export failed: {e}".encode())
                    return
                body = {"written": [str(p) for p in written], "stats": cloud.aggregator.stats()}
            query.reply(keys.control_key(cloud.net, node_id, "export"), json.dumps(body).encode())

    def on_stats(query):
        with query:
            with lock:
                body = {"stats": cloud.aggregator.stats(), "passes_complete": cloud.passes_complete}
            query.reply(keys.control_key(cloud.net, node_id, "stats"), json.dumps(body).encode())

    decl = [
        session.declare_subscriber(keyexpr, on_ap),
        session.declare_subscriber(keys.done_keyexpr(cloud.net), on_done),
        session.declare_queryable(keys.state_profile_keyexpr(cloud.net), on_state),
        session.declare_queryable(keys.control_key(cloud.net, node_id, "export"), on_export),
        session.declare_queryable(keys.control_key(cloud.net, node_id, "stats"), on_stats),
    ]
    token = session.liveliness().declare_token(keys.alive_key(cloud.net, "cloud", node_id))
    try:
        while not stop.is_set():
            try:
                kind, key, payload = inbox.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                with lock:
                    (cloud.on_segment if kind == "ap" else cloud.on_done)(key, payload)
            except Exception:  # a daemon never dies of one message; it is counted and logged
                cloud.aggregator.rejected["internal_error"] += 1
                log.exception("failed to process %s", key)
            finally:
                inbox.task_done()
    finally:
        token.undeclare()
        for d in decl:
            d.undeclare()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="driveby cloud", description="cloud aggregator daemon")
    add_zenoh_arguments(p)
    p.add_argument("--net", default="net")
    p.add_argument("--id", default="cloud-1", help="this daemon's id (liveliness, control keys)")
    p.add_argument("--site", required=True, help="site registry TOML")
    p.add_argument("--keyexpr", help="the shard of AP segments to own (default: all routes)")
    p.add_argument("--export", type=Path, help="default export directory")
    p.add_argument("--rrd", type=Path, help="save the Rerun recording to this file")
    p.add_argument("--viewer", action="store_true", help="spawn a Rerun viewer")
    p.add_argument("--log-level", default="WARNING")
    args = p.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s cloud %(levelname)s %(message)s")
    try:
        site = load_site(args.site)
        keys.check_id(args.net, "net")
        keys.check_id(args.id, "id")
        conf = config_from_args(args)
    except (RegistryError, ValueError) as e:
        print(f"driveby cloud: {e}", file=sys.stderr)
        return 2
    view = None
    if args.rrd or args.viewer:
        from .view import View

        view = View(rrd_path=args.rrd, spawn_viewer=args.viewer, routes={r.id: r.length_m for r in site.routes},
                    bridges=list(site.bridges))
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    try:
        with zenoh.open(conf) as session:
            def publish(key, payload):
                session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

            cloud = Cloud(args.net, site, publish, view)
            serve(session, cloud, args.id, args.keyexpr or keys.ap_keyexpr(args.net), stop, args.export)
            if args.export:
                cloud.export(args.export)
    except zenoh.ZError as e:
        print(f"driveby cloud: zenoh: {e}", file=sys.stderr)
        return 1
    finally:
        if view is not None:
            view.close()
    return 0
