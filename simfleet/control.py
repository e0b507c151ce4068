"""The operator's commands against a deployed network (a router, its clouds and edges):
``driveby replay`` (the vehicles only), ``driveby status`` and ``driveby export``.

Each opens a client session to ``--connect ROUTER`` on ``--net NET`` and talks to the daemons
through their keys: raw chunks out and acknowledgements in (replay), the clouds' ``control/<id>/status``
and ``control/<id>/tables`` queryables (status, export). The clouds are found by their liveliness
tokens unless ``--cloud`` names them. An export's files travel over Zenoh and are written here, so
the command works from any machine that reaches the router.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import zenoh

from shared import keys
from shared.drivelog import DriveLogError, list_drive_logs, read_drive_log
from shared.security import SecurityError
from shared.transport import add_zenoh_arguments, config_from_args, zenoh_message

from .replay import ACK_IDLE_S, DAEMONS_WAIT_S, ReplayError, replay_to

QUERY_TIMEOUT_S = 10.0  # a cloud that does not answer a status query within this long is not there
SETTLE_POLL_S = 1.0  # between status queries while waiting for the clouds to settle
EXPORT_TIMEOUT_S = 300.0  # an export computes every estimate first: minutes on a large network
MANIFEST = "manifest.json"  # cloud.daemon.node.MANIFEST: the first reply of an export


class ControlError(Exception):
    """A user-facing failure: one line, exit 1."""


class UsageError(ControlError):
    """The command line itself is wrong (a malformed --net, --cloud, endpoint): one line, exit 2."""


def add_network_arguments(p: argparse.ArgumentParser) -> None:
    """``--connect``/``--net``/``--secure``/``--id`` (and the rest of the daemons' Zenoh options)."""
    add_zenoh_arguments(p)
    p.add_argument("--net", default="net", help="network name in the key space (the daemons'; default net)")
    p.add_argument("--id", default="operator",
                   help="this client's identity: with --secure DIR, whose certificate it presents (an operator "
                        "role; default operator)")


def add_cloud_arguments(p: argparse.ArgumentParser) -> None:
    add_network_arguments(p)
    p.add_argument("--cloud", action="append", metavar="ID",
                   help="ask this cloud (repeatable; default: every cloud live on the net)")
    p.add_argument("--timeout", type=float, default=None, metavar="S",
                   help=f"seconds to wait for the answers (default {QUERY_TIMEOUT_S:.0f} for status, "
                        f"{EXPORT_TIMEOUT_S:.0f} for export)")


def _config(args: argparse.Namespace) -> zenoh.Config:
    """The session's config from the command line, checked before anything is read or dialled."""
    if not args.connect and not args.config:
        raise UsageError("--connect ENDPOINT is required (the deployed router, e.g. tcp/hub:7447)")
    try:
        keys.check_id(args.net, "--net")
        for cloud in getattr(args, "cloud", None) or []:
            keys.check_id(cloud, "--cloud")
    except ValueError as e:
        raise UsageError(str(e)) from None
    try:
        return config_from_args(args)
    except SecurityError as e:  # a file of --secure DIR is missing
        raise ControlError(str(e)) from None
    except ValueError as e:
        raise UsageError(str(e)) from None


def _session(args: argparse.Namespace, conf: zenoh.Config | None = None) -> zenoh.Session:
    conf = _config(args) if conf is None else conf
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        hint = ""
        if any(c.startswith("tls/") for c in args.connect) and not (args.secure or args.tls_ca or args.config):
            hint = " (a tls/ endpoint: give --secure DIR)"
        raise ControlError(f"cannot reach {', '.join(args.connect) or args.config}: {zenoh_message(e)}{hint}") from None


def _clouds(session: zenoh.Session, args: argparse.Namespace, timeout_s: float) -> list[str]:
    if args.cloud:
        return list(args.cloud)
    found = set()
    for reply in session.liveliness().get(keys.alive_keyexpr(args.net, "cloud"), timeout=timeout_s):
        if reply.ok is not None:
            found.add(keys.parse_alive_key(str(reply.ok.key_expr))[2])
    if not found:
        raise ControlError(f"no cloud live on net {args.net!r} via {', '.join(args.connect) or args.config} "
                           f"within {timeout_s:.0f} s (is the cloud daemon running with the same --net?)")
    return sorted(found)


def _ask(session: zenoh.Session, net: str, cloud: str, verb: str, timeout_s: float) -> list:
    """The replies of ``cloud``'s ``control/<cloud>/<verb>``; ControlError if none (or an error)."""
    replies = list(session.get(keys.control_key(net, cloud, verb), timeout=timeout_s,
                               consolidation=zenoh.ConsolidationMode.NONE))
    oks = []
    for r in replies:
        if r.ok is None:
            raise ControlError(f"{cloud}: {r.err.payload.to_bytes().decode(errors='replace')}")
        oks.append(r.ok)
    if not oks:
        raise ControlError(f"{cloud} did not answer {verb} within {timeout_s:.0f} s (--timeout S waits longer)")
    return oks


# -- status -----------------------------------------------------------------------------------------------


def status(args: argparse.Namespace) -> list[dict]:
    """Every asked cloud's status (``control/<id>/status``); with ``args.wait`` (seconds), asked again
    until every cloud has settled (its calibration and estimates caught up with the passes it
    acknowledged), a ``ControlError`` if they have not within that long."""
    timeout = args.timeout or QUERY_TIMEOUT_S
    wait = getattr(args, "wait", None)
    with _session(args) as session:
        clouds = _clouds(session, args, timeout)
        deadline = time.monotonic() + (wait or 0.0)
        while True:
            bodies = [json.loads(_ask(session, args.net, c, "status", timeout)[0].payload.to_bytes()) for c in clouds]
            working = [b["id"] for b in bodies if not b["settled"]]
            if not wait or not working:
                return bodies
            if time.monotonic() >= deadline:
                raise ControlError(f"--wait {wait:g}: {', '.join(working)} still working after {wait:g} s")
            time.sleep(SETTLE_POLL_S)


def _num(v, fmt: str = ".3f") -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def format_status(body: dict) -> str:
    """A cloud's status as a few lines of text."""
    st = body["stats"]
    rejected = st.get("rejected", {})
    lines = [f"cloud {body['id']} (net {body['net']}): {body['passes']} passes, {body['passes_current']} at their "
             f"vehicle's current calibration, {'settled' if body['settled'] else 'working'}; "
             f"{body['calibration_rounds']} calibration round{'' if body['calibration_rounds'] == 1 else 's'}",
             f"  segments: {st['accepted']} accepted, {sum(rejected.values())} rejected"
             + (f" ({', '.join(f'{k} {v}' for k, v in sorted(rejected.items()))})" if rejected else ""),
             f"  vehicles: {len(body['vehicles'])}" + (f" ({', '.join(body['vehicles'][:8])}"
                                                      f"{', …' if len(body['vehicles']) > 8 else ''})"
                                                      if body["vehicles"] else "")]
    for bid, b in sorted(body["bridges"].items()):
        s, a = b["summary"], b["assessment"]
        line = f"  bridge {bid}: {s['n_passes']} passes, D1 {_num(s['D1_pct'], '.2f')} %, " \
               f"{'DAMAGED' if s['damaged'] else 'no alarm'}"
        if a is not None:
            line += f"; P(damage) {_num(a['loss_probability'])}, best {a['best']}"
            if a.get("element") is not None:
                line += f", element {a['element']}"
        lines.append(line)
    return "\n".join(lines)


# -- export -----------------------------------------------------------------------------------------------


def export(args: argparse.Namespace) -> tuple[list[Path], dict]:
    """Ask every asked cloud for its export, write it (the shards' tables concatenated) into
    ``args.out``; returns the files written and the clouds' counters added up."""
    timeout = args.timeout or EXPORT_TIMEOUT_S
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ControlError(f"--out {out}: cannot create the directory: {e.strerror or e}") from None
    tables: dict[str, list[pa.Table]] = {}
    stats: list[dict] = []
    with _session(args) as session:
        for cloud in _clouds(session, args, QUERY_TIMEOUT_S):
            files, manifest = {}, None
            for sample in _ask(session, args.net, cloud, "tables", timeout):
                name = sample.attachment.to_bytes().decode() if sample.attachment is not None else ""
                if name == MANIFEST:
                    manifest = json.loads(sample.payload.to_bytes())
                else:
                    files[name] = sample.payload.to_bytes()
            if manifest is None or set(manifest["files"]) != set(files):
                raise ControlError(f"{cloud}: incomplete export (got {sorted(files)}, "
                                   f"expected {manifest and manifest['files']})")
            stats.append(manifest["stats"])
            for name, data in files.items():
                tables.setdefault(name, []).append(pq.read_table(pa.BufferReader(data)))
    written = []
    for name, parts in sorted(tables.items()):
        path = out / name
        tmp = path.with_suffix(path.suffix + ".tmp")
        try:
            pq.write_table(pa.concat_tables(parts, promote_options="default"), tmp)
            tmp.replace(path)
        except OSError as e:
            raise ControlError(f"--out {out}: cannot write {name}: {e.strerror or e}") from None
        written.append(path)
    return written, sum_stats(stats)


def sum_stats(parts: list[dict]) -> dict:
    """Aggregator counters added up across clouds (nested counters by reason too)."""
    out: dict = {}
    for st in parts:
        for k, v in st.items():
            if isinstance(v, dict):
                sub = out.setdefault(k, {})
                for r, n in v.items():
                    sub[r] = sub.get(r, 0) + n
            elif isinstance(v, (int, float)):
                out[k] = out.get(k, 0) + v
    return out


# -- replay -----------------------------------------------------------------------------------------------


def add_replay_arguments(p: argparse.ArgumentParser) -> None:
    add_network_arguments(p)
    p.add_argument("--logs", required=True, help="directory of drive logs (*.parquet) to publish as their vehicles")
    p.add_argument("--rate", type=float, help="replay at X× real time (default: as fast as possible)")
    p.add_argument("--wait", type=float, default=DAEMONS_WAIT_S, metavar="S",
                   help=f"seconds to wait for an edge and a cloud to be live on the net (default {DAEMONS_WAIT_S:.0f})")
    p.add_argument("--timeout", type=float, default=ACK_IDLE_S, metavar="S",
                   help=f"give up when no pass is acknowledged for this long (default {ACK_IDLE_S:.0f})")


def replay_logs(args: argparse.Namespace, progress: bool | None = None):
    """Read and check every log, then publish them to the deployed network and wait for the acks."""
    conf = _config(args)
    try:
        logs = [read_drive_log(p) for p in list_drive_logs(Path(args.logs))]
    except DriveLogError as e:
        raise ControlError(str(e)) from None
    if not logs:
        raise ControlError(f"{args.logs}: no drive logs (*.parquet) found")
    with _session(args, conf) as session:
        try:
            return replay_to(session, args.net, logs, rate=args.rate, progress=progress, daemons_wait_s=args.wait,
                             idle_s=args.timeout)
        except ReplayError as e:
            raise ControlError(str(e)) from None
