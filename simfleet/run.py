"""``driveby run``: replay drive logs through edge and cloud daemons over Zenoh, then export.

Everything real: a Zenoh router in its own process (unless ``--connect`` names one), the edge and
the cloud as separate OS processes, chunks published as a logger would (each vehicle through an
advanced publisher keeping its recent chunks, so an edge recovers what a router outage made it
miss). Completion is by events: the run waits for the cloud's acknowledgement of every pass, never
for a fixed time. ``secure``: TLS, mutual authentication and access control, every process with its
own identity (``shared.security``).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import zenoh

from edge.trip import TripError, split_drives
from shared import keys
from shared.drivelog import DriveLog, DriveLogError, list_drive_logs, read_drive_log
from shared.progress import Progress
from shared.registry import RegistryError, Site, load_site
from shared.schema import DecodeError, decode_ack
from shared.security import SecurityDir, SecurityError, init_ca, issue
from shared.transport import run_router, zenoh_config
from shared.vehicles import MODELS

from . import replay as replay_module
from .control import sum_stats
from .replay import ImuPublishers, replay

STARTUP_TIMEOUT_S = 120.0  # first start compiles numba kernels into the cache
IDLE_TIMEOUT_S = 120.0  # no acknowledgement for this long → something is wrong
SUPERVISE_S = 0.5  # how often the run checks that its daemons are alive
MAX_RESTARTS = 5  # a daemon that dies more often than this in one run is broken, not unlucky
# A pass still unacknowledged this long after its last chunk went out (and the replay is over) is
# published again from its log, as a logger keeps its files until the cloud has them. The loggers'
# publication caches recover most outages; this catches what they cannot (chunks older than the
# cache, a recovery query that found no cache, e.g. right after a lease expiry). A resend of a pass
# that was only slow costs duplicates, which the cloud recognises (idempotent segments).
RESEND_S = 30.0


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
    resent_passes: int = 0  # passes published again because they were not acknowledged (RESEND_S)


def load_inputs(logs_dir: Path, site_path: Path) -> tuple[Site, list[DriveLog]]:
    """Validate the registry and every drive log up front; raise RunError with one clear line."""
    try:
        site = load_site(site_path)
    except RegistryError as e:
        raise RunError(str(e)) from None
    try:
        paths = list_drive_logs(logs_dir)
        logs = [read_drive_log(p) for p in paths]
        paths, logs, _ = split_drives(paths, logs, site)  # whole drives with positions → passes (§5)
    except (DriveLogError, TripError) as e:
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


class Daemon:
    """A supervised daemon process: restarted (up to ``MAX_RESTARTS`` times) when it dies.

    Its pid is kept in ``<work>/<name>.pid`` (as a service manager would), its output appended to
    ``<work>/<name>.log`` (``name`` defaults to the module). A restarted daemon resumes from its durable state (the cloud's journal,
    the edge's spool of unacknowledged passes), so a crash costs time, not data.
    """

    def __init__(self, module: str, args: list[str], work: Path, name: str | None = None):
        self.module, self.args, self.work = module, args, work
        self.name = name or module
        self.restarts = 0
        self.proc = self._start("wb")

    def _start(self, mode: str) -> subprocess.Popen:
        out = open(self.work / f"{self.name}.log", mode)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        proc = subprocess.Popen([sys.executable, "-m", self.module, *self.args], stdout=out,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        out.close()
        (self.work / f"{self.name}.pid").write_text(f"{proc.pid}\n")
        return proc

    def supervise(self) -> None:
        """Restart the daemon if it has exited; RunError once it keeps dying."""
        code = self.proc.poll()
        if code is None:
            return
        tail = (self.work / f"{self.name}.log").read_text(errors="replace").strip().splitlines()[-1:] or [""]
        # 2: bad arguments; a one-line "driveby <daemon>: ..." refusal: bad input (its site, its
        # state, its id taken). Restarting cannot help either; a crash (a traceback) it can. Except
        # an id still held by this daemon's own previous process (the router has not yet seen it
        # go): that passes.
        refused = code == 1 and tail[0].startswith(("driveby cloud:", "driveby edge:"))
        refused = refused and not (self.restarts > 0 and "already live" in tail[0])
        if code == 2 or refused or self.restarts >= MAX_RESTARTS:
            raise RunError(f"{self.name} daemon exited with code {code}: {tail[0] or '(no output)'}")
        self.restarts += 1
        print(f"driveby run: {self.name} daemon exited with code {code}; restarting "
              f"({self.restarts}/{MAX_RESTARTS})", file=sys.stderr)
        self.proc = self._start("ab")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()

    def wait(self, timeout: float) -> None:
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def _stop(procs: list[Daemon]) -> None:
    for p in procs:
        p.stop()
    deadline = time.monotonic() + 15.0
    for p in procs:
        p.wait(max(0.1, deadline - time.monotonic()))


RUN_ID = "run"  # the run's own session (replays the loggers, asks for the export): an operator


def _security_dir(secure: bool | str | Path, work: Path, connect: str | None, cloud_ids: list[str],
                  routers: int) -> SecurityDir:
    """The run's certificates: ``secure=True`` makes a fresh CA and every identity's certificate in
    ``<work>/security`` (at the start of each run); a path uses that security directory as it is
    (it must hold the run's identities: routers, clouds, ``edge-1`` and ``run``)."""
    needed = {RUN_ID: "operator", "edge-1": "edge", **{c: "aggregator" for c in cloud_ids}}
    if connect is None:
        needed.update({f"router-{i + 1}": "router" for i in range(routers)})
    try:
        if secure is True:
            if connect is not None:
                raise RunError("--secure with --connect: give the router's security directory (--secure DIR); "
                               "certificates made here would not be trusted by it")
            path = work / "security"
            shutil.rmtree(path, ignore_errors=True)
            sec = init_ca(path)
            for name, role in needed.items():
                issue(sec, name, role)
            return sec
        sec = SecurityDir(Path(secure))
        have = sec.identities()
        for name, role in needed.items():
            if have.get(name) != role:
                raise RunError(f"{sec.path}: identity {name!r} with role {role!r} needed "
                               f"(`python -m shared.security issue {sec.path} {name} --role {role}`)")
            sec.tls(name)  # its certificate and key are there
        return sec
    except SecurityError as e:
        raise RunError(str(e)) from None


def _tls_args(sec: SecurityDir | None, name: str) -> list[str]:
    if sec is None:
        return []
    files = sec.tls(name)
    return ["--tls-ca", str(files.ca), "--tls-cert", str(files.cert), "--tls-key", str(files.key)]


def run(logs_dir: Path, site_path: Path, export_dir: Path, rrd: Path | None = None, calibration: str = "fleet",
        connect: str | None = None, net: str = "net", viewer: bool = False, progress: bool | None = None,
        rate: float | None = None, align: bool = True, shards: int = 1,
        secure: bool | str | Path = False, cloud_args: tuple[str, ...] = (), state: Path | None = None) -> RunResult:
    """Replay ``logs_dir`` through edge and cloud daemons; ``shards`` > 1 splits the routes among that
    many cloud daemons behind two routers (as on separate machines) and merges their exports.

    ``secure``: the routers listen on TLS only, require certificates (mTLS) and apply the roles'
    access control (``shared.security``); every daemon and the run's own session connect with
    their own identity. ``True`` makes the certificates (see :func:`_security_dir`); a path names a
    security directory to use (required with ``connect``: the router's CA must sign them).
    ``cloud_args``: further options of every cloud daemon (``driveby cloud --help``).
    ``state``: the clouds' durable state (``driveby cloud --state``) is kept there instead of in the
    export's ``.run``, and not cleared at the start: a run with the same ``state`` continues from what
    the earlier one left (its passes, calibration, a rail bridge's healthy baseline), and its export
    covers both. One cloud keeps it in ``state`` itself; shards each in ``state/<cloud id>``.
    """
    t0 = time.monotonic()
    site, logs = load_inputs(Path(logs_dir), Path(site_path))
    routes = sorted(r.id for r in site.routes)
    if not 1 <= shards <= len(routes):
        raise RunError(f"--shards: expected 1 to {len(routes)} (the site's routes), got {shards}")
    export_dir = Path(export_dir)
    work = export_dir / ".run"
    try:
        work.mkdir(parents=True, exist_ok=True)
    except OSError as e:  # e.g. a path through a file, or a read-only place
        raise RunError(f"--export {export_dir}: cannot create the directory: {e.strerror or e}") from e
    cloud_ids = ["cloud-1"] if shards == 1 else [f"cloud-{i + 1}" for i in range(shards)]
    sec = _security_dir(secure, work, connect, cloud_ids, 1 if shards == 1 else 2) if secure else None
    with contextlib.ExitStack() as stack:
        if connect is not None:
            endpoints = [connect]
        else:
            def router(i: int, joins: list[str]) -> str:
                if sec is None:
                    return stack.enter_context(run_router(connect=joins))
                return stack.enter_context(run_router(security=sec.path, net=net, router_id=f"router-{i}",
                                                      connect=joins))

            endpoints = [router(1, [])]
            if shards > 1:  # a second router joined to the first: shard traffic crosses routers, as between machines
                endpoints.append(router(2, endpoints[:1]))
        site_arg = ["--net", net, "--site", str(Path(site_path).resolve())]
        # Without ``state`` a run starts from nothing: state left by an earlier run into this
        # directory is not this run's. The edge's spool is the run's alone either way: every pass it
        # held was acknowledged before the earlier run ended.
        kept = None if state is None else Path(state).resolve()
        for stale in work.glob("*-state"):
            if kept is None or not kept.is_relative_to(stale.resolve()):  # never the state asked for
                shutil.rmtree(stale, ignore_errors=True)
        shutil.rmtree(work / "edge-spool", ignore_errors=True)
        state_dirs = _state_dirs(state, work, cloud_ids)
        clouds = []
        for i, cid in enumerate(cloud_ids):
            args = ["--connect", endpoints[i % len(endpoints)], *site_arg, "--id", cid, "--calibration", calibration,
                    "--state", str(state_dirs[cid]), *_tls_args(sec, cid)]
            args += ["--align"] if align else ["--no-align"]
            args += list(cloud_args)
            if shards > 1:
                args += ["--routes", ",".join(routes[i::shards])]
            if rrd is not None:
                path = Path(rrd).resolve()
                args += ["--rrd", str(path if shards == 1 else path.with_name(f"{path.stem}-{cid}{path.suffix}"))]
            if viewer:
                args += ["--viewer"]
            clouds.append(Daemon("cloud", args, work, name=cid if shards > 1 else "cloud"))
        edge = Daemon("edge", ["--connect", endpoints[0], *site_arg, "--id", "edge-1", "--calibration", calibration,
                               "--spool", str(work / "edge-spool"), *_tls_args(sec, "edge-1")], work)
        procs = [*clouds, edge]
        try:
            conf = zenoh_config("client", connect=[endpoints[0]], tls=None if sec is None else sec.tls(RUN_ID))
            return _drive(conf, net, logs, procs, work, export_dir, progress, rate, t0, cloud_ids)
        finally:
            _stop(procs)


def _state_dirs(state: Path | None, work: Path, cloud_ids: list[str]) -> dict[str, Path]:
    """Each cloud's ``--state`` directory: under the run's work directory, or the caller's ``state``
    (created here, so that a path that cannot be one fails with one line before any daemon starts)."""
    if state is None:
        return {cid: work / f"{cid}-state" for cid in cloud_ids}
    state = Path(state).resolve()
    dirs = {cloud_ids[0]: state} if len(cloud_ids) == 1 else {cid: state / cid for cid in cloud_ids}
    try:
        for d in dirs.values():
            d.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise RunError(f"--state {state}: cannot create the directory: {e.strerror or e}") from e
    return dirs


def _merge_exports(parts: list[Path], export_dir: Path) -> list[str]:
    """One export from the shards' exports: each table is the concatenation of the shards' rows."""
    names = sorted({p.name for d in parts for p in d.glob("*.parquet")})
    written = []
    for name in names:
        tables = [pq.read_table(d / name) for d in parts if (d / name).exists()]
        out = export_dir / name
        pq.write_table(pa.concat_tables(tables, promote_options="default"), out)
        written.append(str(out))
    return written


def _drive(conf, net, logs, procs, work, export_dir, progress, rate, t0, cloud_ids) -> RunResult:
    with zenoh.open(conf) as session:
        alive: set[str] = set()
        ready = threading.Event()
        acked: set[tuple[str, str]] = set()
        progressed = threading.Event()
        expected = {(log.meta.vehicle_id, log.meta.pass_id) for log in logs}
        all_done = threading.Event()
        statuses: dict[str, dict] = {cid: {} for cid in cloud_ids}

        def check_done():
            current = sum(st.get("passes_current", 0) for st in statuses.values())
            if expected <= acked and all(st.get("settled") for st in statuses.values()) and current >= len(expected):
                all_done.set()

        def on_status(sample):
            try:
                cid = str(sample.key_expr).rsplit("/", 1)[-1]
                body = json.loads(sample.payload.to_bytes())
            except ValueError:
                return
            if cid in statuses:
                statuses[cid] = body
            progressed.set()
            check_done()

        wanted = {f"cloud/{cid}" for cid in cloud_ids} | {"edge/edge-1"}

        def on_alive(sample):
            try:
                _, role, ident = keys.parse_alive_key(str(sample.key_expr))
            except ValueError:
                return
            if sample.kind == zenoh.SampleKind.PUT:
                alive.add(f"{role}/{ident}")
            if wanted <= alive:
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
        stats_subs = [session.declare_subscriber(keys.status_key(net, cid), on_status) for cid in cloud_ids]
        # A first start compiles the kernels (a minute or two): say so while it lasts.
        with Progress(len(wanted), "daemons", enabled=progress, unit="live") as bar:
            _wait(ready, STARTUP_TIMEOUT_S, procs, work, "edge and cloud daemons to start",
                  lambda: bar.update(len(alive & wanted)))
            bar.update(len(alive & wanted))
        # The loggers keep their recent chunks (publication cache): what a router restart or a
        # partition made the edge miss is fetched again, not lost.
        publish = ImuPublishers(session, cache_chunks=replay_module.CACHE_CHUNKS)
        stop = threading.Event()
        sent_at: dict[tuple[str, str], float] = {}  # (vehicle, pass) -> when its last chunk went out

        def on_chunk(chunk):
            if chunk.final:
                sent_at[(chunk.vehicle_id, chunk.pass_id)] = time.monotonic()

        feeder = threading.Thread(target=replay, args=(logs, publish, net, rate, stop, on_chunk), daemon=True)
        feeder.start()
        by_pass = {(log.meta.vehicle_id, log.meta.pass_id): log for log in logs}
        resent = 0
        eta = Eta()
        with Progress(len(expected), "passes", enabled=progress, unit="acked") as bar:
            idle_since = time.monotonic()
            while not all_done.is_set():
                # Wake at least every SUPERVISE_S: a dead daemon is restarted promptly, not at the idle limit.
                if progressed.wait(SUPERVISE_S):
                    progressed.clear()
                    idle_since = time.monotonic()
                _check_alive(procs, work)
                if time.monotonic() - idle_since > IDLE_TIMEOUT_S and not all_done.is_set():
                    stop.set()
                    missing = sorted(p for _, p in expected - acked)
                    raise RunError(f"timed out: no pass acknowledged for {IDLE_TIMEOUT_S:.0f} s; "
                                   f"{len(missing)} pass(es) missing, e.g. {missing[:3]}")
                if not feeder.is_alive():  # one stream per vehicle: resend only once the replay is over
                    now = time.monotonic()
                    late = sorted(p for p, t in sent_at.items() if now - t > RESEND_S and p not in acked)
                    if late:
                        feeder = threading.Thread(target=replay, daemon=True,
                                                  args=([by_pass[p] for p in late], publish, net, rate, stop, on_chunk))
                        feeder.start()
                        resent += len(late)
                done = len(acked & expected)
                rounds = max(st.get("calibration_rounds", 0) for st in statuses.values())
                rounds_left = max(st.get("calibration_rounds_left_max", 0) for st in statuses.values())
                note, left_s = eta.update(time.monotonic(), done, len(expected), rounds, rounds_left)
                bar.update(done, note, left_s)
        feeder.join(timeout=10.0)
        publish.close()
        sharded = len(cloud_ids) > 1
        bodies = []
        for cid in cloud_ids:
            target = (work / f"export-{cid}") if sharded else export_dir
            replies = list(session.get(keys.control_key(net, cid, "export") + f"?dir={target.resolve()}",
                                       timeout=60.0))
            body = None
            for r in replies:
                if r.ok is not None:
                    body = json.loads(r.ok.payload.to_bytes())
                else:
                    raise RunError(f"{cid} export failed: {r.err.payload.to_bytes().decode(errors='replace')}")
            if body is None:
                raise RunError(f"{cid} did not answer the export request")
            bodies.append(body)
        acks.undeclare()
        for sub in stats_subs:
            sub.undeclare()
        live.undeclare()
    written = _merge_exports([work / f"export-{cid}" for cid in cloud_ids], export_dir) if sharded \
        else bodies[0]["written"]
    stats = bodies[0]["stats"] if not sharded else sum_stats([b["stats"] for b in bodies])
    rounds = max(st.get("calibration_rounds", 0) for st in statuses.values())
    return RunResult(len(expected), len(acked & expected), written, stats, time.monotonic() - t0, int(rounds),
                     resent)


class Eta:
    """The progress line's note and estimate of the time left: the passes still to be acknowledged at
    the rate so far, then the calibration rounds still possible (the cloud's bound: a budget per
    epoch, ``calibration_rounds_left_max``) at the rounds' mean duration so far. Rounds usually stop
    before their budget (a round that moves no vehicle ends its epoch), so once the passes are in
    the estimate is an upper bound, and the line says so ("round k of ≤ N")."""

    def __init__(self):
        self.t0: float | None = None
        self.first_round_at: float | None = None  # when the first round was seen
        self.rounds_seen = 0

    def update(self, now: float, done: int, total: int, rounds: int, rounds_left: int) -> tuple[str, float | None]:
        if self.t0 is None:
            self.t0 = now
        if rounds > self.rounds_seen:
            if self.first_round_at is None:
                self.first_round_at = now
            self.rounds_seen = rounds
        left = None
        if 0 < done < total:
            left = (now - self.t0) * (total - done) / done
        round_s = None
        if self.first_round_at is not None and self.rounds_seen > 1:
            round_s = (now - self.first_round_at) / (self.rounds_seen - 1)
        if done >= total and rounds_left and round_s is not None:
            left = rounds_left * round_s
        if done >= total and rounds_left:
            note = f"calibration round {rounds} of ≤ {rounds + rounds_left}"
        elif done >= total:
            note = "calibration rounds done, finishing estimates" if rounds else "finishing estimates"
        else:
            note = f"{rounds} calibration round{'s' if rounds != 1 else ''}"
        return note, left


def _check_alive(procs, work) -> None:
    for p in procs:
        p.supervise()


def _wait(event: threading.Event, timeout: float, procs, work, what: str, tick=lambda: None) -> None:
    deadline = time.monotonic() + timeout
    while not event.wait(0.5):
        tick()
        _check_alive(procs, work)
        if time.monotonic() > deadline:
            raise RunError(f"timed out after {timeout:.0f} s waiting for {what}")
