"""``driveby run``: replay drive logs through edge and cloud daemons over Zenoh, then export.

Everything real: a Zenoh router in its own process (unless ``--connect`` names one), the edge and
the cloud as separate OS processes, chunks published as a logger would. Completion is by events:
the run waits for the cloud's acknowledgement of every pass, never for a fixed time.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import zenoh

from shared import keys
from shared.drivelog import DriveLog, DriveLogError, list_drive_logs, read_drive_log
from shared.progress import Progress
from shared.registry import RegistryError, Site, load_site
from shared.schema import DecodeError, decode_ack
from shared.transport import run_router, zenoh_config
from shared.vehicles import MODELS

from .replay import replay

STARTUP_TIMEOUT_S = 120.0  # first start compiles numba kernels into the cache
IDLE_TIMEOUT_S = 120.0  # no acknowledgement for this long → something is wrong


class RunError(Exception):
    """A user-facing failure: one line, non-zero exit."""


@dataclass(frozen=True)
class RunResult:
    passes: int
    acked: int
    export: list[str]
    stats: dict
    seconds: float
    calibration_rounds: int = 0


def load_inputs(logs_dir: Path, site_path: Path) -> tuple[Site, list[DriveLog]]:
    """Validate the registry and every drive log up front; raise RunError with one clear line."""
    try:
        site = load_site(site_path)
    except RegistryError as e:
        raise RunError(str(e)) from None
    try:
        paths = list_drive_logs(logs_dir)
        logs = [read_drive_log(p) for p in paths]
    except DriveLogError as e:
        raise RunError(str(e)) from None
    if not logs:
        raise RunError(f"{logs_dir}: no drive logs (*.parquet) found")
    routes = {r.id for r in site.routes}
    seen = set()
    for path, log in zip(paths, logs):
        if log.meta.route_id not in routes:
            raise RunError(f"{path}: key 'driveby.route_id': route {log.meta.route_id!r} is not in {site_path}")
        if log.meta.vehicle_model not in MODELS:
            raise RunError(f"{path}: key 'driveby.vehicle_model': {log.meta.vehicle_model!r} is not supported yet")
        key = (log.meta.vehicle_id, log.meta.pass_id)
        if key in seen:
            raise RunError(f"{path}: key 'driveby.pass_id': pass {log.meta.pass_id!r} of {log.meta.vehicle_id} "
                           "appears twice")
        seen.add(key)
    return site, logs


def _spawn(module: str, args: list[str], log_dir: Path) -> subprocess.Popen:
    out = open(log_dir / f"{module}.log", "wb")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", module, *args], stdout=out, stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL, env=env)


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
    deadline = time.monotonic() + 15.0
    for p in procs:
        try:
            p.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def run(logs_dir: Path, site_path: Path, export_dir: Path, rrd: Path | None = None, calibration: str = "fleet",
        connect: str | None = None, net: str = "net", viewer: bool = False, progress: bool | None = None,
        rate: float | None = None, align: bool = False) -> RunResult:
    t0 = time.monotonic()
    site, logs = load_inputs(Path(logs_dir), Path(site_path))
    export_dir = Path(export_dir)
    export_dir.mkdir(parents=True, exist_ok=True)
    work = export_dir / ".run"
    work.mkdir(exist_ok=True)
    router = run_router() if connect is None else contextlib.nullcontext(connect)
    with router as endpoint:
        common = ["--connect", endpoint, "--net", net, "--site", str(Path(site_path).resolve())]
        cloud_args = [*common, "--id", "cloud-1", "--calibration", calibration] + (["--align"] if align else [])
        if rrd is not None:
            cloud_args += ["--rrd", str(Path(rrd).resolve())]
        if viewer:
            cloud_args += ["--viewer"]
        procs = [_spawn("cloud", cloud_args, work),
                 _spawn("edge", [*common, "--id", "edge-1", "--calibration", calibration], work)]
        try:
            return _drive(endpoint, net, logs, procs, work, export_dir, progress, rate, t0)
        finally:
            _stop(procs)


def _drive(endpoint, net, logs, procs, work, export_dir, progress, rate, t0) -> RunResult:
    with zenoh.open(zenoh_config("client", connect=[endpoint])) as session:
        alive: set[str] = set()
        ready = threading.Event()
        acked: set[tuple[str, str]] = set()
        progressed = threading.Event()
        expected = {(log.meta.vehicle_id, log.meta.pass_id) for log in logs}
        all_done = threading.Event()
        status: dict = {}

        def check_done():
            if expected <= acked and status.get("settled") and status.get("passes_current", 0) >= len(expected):
                all_done.set()

        def on_status(sample):
            try:
                status.update(json.loads(sample.payload.to_bytes()))
            except ValueError:
                return
            progressed.set()
            check_done()

        def on_alive(sample):
            try:
                _, role, ident = keys.parse_alive_key(str(sample.key_expr))
            except ValueError:
                return
            if sample.kind == zenoh.SampleKind.PUT:
                alive.add(f"{role}/{ident}")
            if {"cloud/cloud-1", "edge/edge-1"} <= alive:
                ready.set()

        def on_ack(sample):
            try:
                ack = decode_ack(sample.payload.to_bytes())
            except DecodeError:
                return
            acked.add((ack.vehicle_id, ack.pass_id))
            progressed.set()
            check_done()

        live = session.liveliness().declare_subscriber(keys.alive_keyexpr(net), on_alive, history=True)
        acks = session.declare_subscriber(keys.ack_keyexpr(net), on_ack)
        stat = session.declare_subscriber(keys.status_key(net, "cloud-1"), on_status)
        _wait(ready, STARTUP_TIMEOUT_S, procs, work, "edge and cloud daemons to start")
        publisher_opts = dict(congestion_control=zenoh.CongestionControl.BLOCK)

        def publish(key, payload):
            session.put(key, payload, **publisher_opts)

        stop = threading.Event()
        feeder = threading.Thread(target=replay, args=(logs, publish, net, rate, stop), daemon=True)
        feeder.start()
        with Progress(len(expected), "passes", enabled=progress) as bar:
            while not all_done.is_set():
                progressed.clear()
                if not progressed.wait(IDLE_TIMEOUT_S) and not all_done.is_set():
                    _check_alive(procs, work)
                    stop.set()
                    missing = sorted(p for _, p in expected - acked)
                    raise RunError(f"timed out: no pass acknowledged for {IDLE_TIMEOUT_S:.0f} s; "
                                   f"{len(missing)} pass(es) missing, e.g. {missing[:3]}")
                _check_alive(procs, work)
                bar.advance(len(acked & expected) - bar.done)
                if status.get("calibration_rounds"):
                    bar.label = f"passes (calibration round {status['calibration_rounds']})"
        feeder.join(timeout=10.0)
        replies = list(session.get(keys.control_key(net, "cloud-1", "export") + f"?dir={export_dir.resolve()}",
                                   timeout=60.0))
        acks.undeclare()
        stat.undeclare()
        live.undeclare()
    body = None
    for r in replies:
        if r.ok is not None:
            body = json.loads(r.ok.payload.to_bytes())
        else:
            raise RunError(f"cloud export failed: {r.err.payload.to_bytes().decode(errors='replace')}")
    if body is None:
        raise RunError("cloud did not answer the export request")
    return RunResult(len(expected), len(acked & expected), body["written"], body["stats"], time.monotonic() - t0,
                     int(status.get("calibration_rounds", 0)))


def _check_alive(procs, work) -> None:
    for p in procs:
        if p.poll() is not None:
            name = p.args[2]
            tail = (work / f"{name}.log").read_text(errors="replace").strip().splitlines()[-1:] or ["(no output)"]
            raise RunError(f"{name} daemon exited with code {p.returncode}: {tail[0]}")


def _wait(event: threading.Event, timeout: float, procs, work, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not event.wait(0.5):
        _check_alive(procs, work)
        if time.monotonic() > deadline:
            raise RunError(f"timed out after {timeout:.0f} s waiting for {what}")
