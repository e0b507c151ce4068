"""Zenoh plumbing: configs from plain values, free loopback ports, a router from PyPI only.

zenoh-python opens a session in ``router`` mode (config ``mode: "router"``), and
clients or peers connected to it route pub/sub, queries and liveliness between
processes, so no ``zenohd`` binary is needed::

    python -m shared.transport router --listen tcp/127.0.0.1:7447

prints one ``ready <zid>`` line on stdout once listening and runs until SIGTERM or
SIGINT (or, with ``--exit-on-stdin-eof``, until its parent closes its stdin).
:func:`run_router` starts it as a subprocess for tests and for ``driveby run``.

Secured (``shared.security``): ``--security DIR --id ROUTER --net NET`` makes the router
listen on TLS only, require every peer's certificate (mTLS) and apply the access control
of DIR's identities; it counts the messages Zenoh refuses and answers the counts on
``driveby/<net>/control/<ROUTER>/denials``.  Daemons connect with
``--connect tls/HOST:PORT --tls-ca DIR/ca.pem --tls-cert DIR/<id>.pem --tls-key DIR/<id>.key``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import typing
from collections.abc import Iterator, Sequence
from pathlib import Path

import zenoh

from shared.keys import MAX_ID_LEN, alive_key, alive_keyexpr, check_id, parse_alive_key
from shared.security import (ACL_LOG_DIRECTIVE, DenialCounter, SecurityDir, SecurityError, TlsFiles, denials_key,
                             router_config, tls_config)

log = logging.getLogger(__name__)

MODES = ("peer", "client", "router")
READY = "ready"
ANSI = re.compile(r"\x1b\[[0-9;]*m")  # terminal colour codes in Zenoh's log lines
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")  # the daemons' --log-level choices
ALL_ALIVE = "driveby/*/alive/*/*"  # every daemon's liveliness token, on every net (the router's log)
PRESENCE_CHECK_S = 3.0  # how long a starting daemon asks whether its id is already live

__all__ = ["MODES", "free_port", "zenoh_config", "run_router", "serve_router", "add_zenoh_arguments",
           "config_from_args", "default_id", "zenoh_message", "IdInUseError", "Presence", "LOG_LEVELS", "main"]

#: The logger of the daemons' start, connection and peer lines: on at INFO whatever ``--log-level``
#: says (unless it asks for less than warnings), so a deployed daemon tells what it is doing.
PRESENCE_LOG = "driveby.presence"


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free on ``host`` a moment ago (bind port 0, read it, close)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def zenoh_message(e: Exception) -> str:
    """A Zenoh error as one line for a user: without the Rust source location it ends with."""
    return re.sub(r"\s+at \S+:\d+\.?\s*$", "", str(e).strip()) or type(e).__name__


def default_id(role: str) -> str:
    """``<role>-<host>``: a daemon id unique per machine (one daemon of a role per host); a second
    one on the same host, or a secured one (its id is its certificate's name), passes ``--id``."""
    host = re.sub(r"[^A-Za-z0-9_-]+", "-", socket.gethostname().split(".")[0]).strip("-") or "host"
    return check_id(f"{role}-{host}"[:MAX_ID_LEN], "id")


class IdInUseError(RuntimeError):
    """Another live daemon of the role holds this id on the net (one line, exit 1)."""


class Presence:
    """What a daemon says about its place on the bus: one log line when it starts, when it is
    connected (or not) to a router, and when another daemon's liveliness token appears or goes.

    ``Presence(session, net, role, node_id, endpoints)`` refuses (:class:`IdInUseError`) an id another live
    daemon of the role already holds on ``net``; the daemon declares its own token after this.
    :meth:`close` stops watching.
    """

    def __init__(self, session: zenoh.Session, net: str, role: str, node_id: str, endpoints: Sequence[str] = (),
                 log_level: str = "INFO"):
        self.log = logging.getLogger(PRESENCE_LOG)
        if logging.getLevelName(log_level.upper()) in (logging.DEBUG, logging.INFO, logging.WARNING):
            self.log.setLevel(logging.INFO)
        self.me = f"{role}/{node_id}"
        own = alive_key(net, role, node_id)
        if any(r.ok is not None for r in session.liveliness().get(own, timeout=PRESENCE_CHECK_S)):
            raise IdInUseError(f"--id {node_id}: a {role} with this id is already live on net {net!r} "
                             "(give each daemon its own --id)")
        routers = [str(z) for z in session.info.routers_zid()]
        self.log.info("%s started: net %s, zenoh id %s, endpoints %s", self.me, net, session.info.zid(),
                      ", ".join(endpoints) or "(none: peer mode)")
        if routers:
            self.log.info("%s connected to router %s", self.me, ", ".join(routers))
        elif endpoints:
            self.log.warning("%s not connected to %s yet: zenoh keeps trying", self.me, ", ".join(endpoints))
        self._peers = session.liveliness().declare_subscriber(alive_keyexpr(net), self._on_peer, history=True)

    def _on_peer(self, sample) -> None:
        try:
            _, role, ident = parse_alive_key(str(sample.key_expr))
        except ValueError:
            return
        if f"{role}/{ident}" == self.me:
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self.log.info("%s: peer %s/%s is up", self.me, role, ident)
        else:
            self.log.info("%s: peer %s/%s is gone", self.me, role, ident)

    def close(self) -> None:
        self._peers.undeclare()


def _endpoints(name: str, values: Sequence[str] | str) -> list[str]:
    if isinstance(values, str):
        values = [values]
    out = list(values)
    for e in out:
        if not isinstance(e, str) or "/" not in e:
            raise ValueError(f"{name} endpoint {e!r} is not of the form proto/address, e.g. tcp/127.0.0.1:7447")
    return out


def zenoh_config(
    mode: str | None = "peer",
    connect: Sequence[str] | str = (),
    listen: Sequence[str] | str = (),
    config_file: str | os.PathLike[str] | None = None,
    no_multicast: bool = True,
    tls: TlsFiles | None = None,
) -> zenoh.Config:
    """Build a ``zenoh.Config`` from plain values.

    Parameters
    ----------
    mode : {"peer", "client", "router"} or None
        Session mode; ``None`` keeps the mode of ``config_file`` (or zenoh's default, peer).
    connect, listen : endpoints
        Such as ``"tcp/127.0.0.1:7447"``; given ones replace those of ``config_file``.
    config_file : path, optional
        A zenoh JSON5 config (TLS, access control, ...) to start from.
    no_multicast : bool
        Turn multicast scouting off (the default), so that sessions on one machine
        never find each other by accident: they meet only through explicit endpoints.
    tls : TlsFiles, optional
        The CA (and this session's certificate and key) for ``tls/...`` endpoints; a session
        that listens (a router, or given ``listen``) requires its peers' certificates.
    """
    if mode is not None and mode not in MODES:
        raise ValueError(f"mode {mode!r} not in {MODES}")
    connect = _endpoints("connect", connect)
    listen = _endpoints("listen", listen)
    conf = zenoh.Config.from_file(os.fspath(config_file)) if config_file is not None else zenoh.Config()
    if mode is not None:
        conf.insert_json5("mode", json.dumps(mode))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if no_multicast:
        conf.insert_json5("scouting/multicast/enabled", "false")
    if tls is not None:
        conf.insert_json5("transport/link/tls", json.dumps(tls_config(tls, listen=bool(listen) or mode == "router")))
    return conf


def serve_router(conf: zenoh.Config, stop: threading.Event, ready=None) -> None:
    """Open a router-mode session on ``conf``, call ``ready(session)``, block until ``stop`` is set."""
    conf.insert_json5("mode", '"router"')
    with zenoh.open(conf) as session:
        if ready is not None:
            ready(session)
        stop.wait()


def _drain(stream, first_line: list[str], got_first: threading.Event) -> None:
    """Read the router's stdout: keep its first line, then discard so the pipe never fills."""
    with stream:  # closed here, at EOF, not under this reader's feet
        for i, line in enumerate(stream):
            if i == 0:
                first_line.append(line)
                got_first.set()
    got_first.set()  # EOF: the router died before (or after) saying ready


@contextlib.contextmanager
def run_router(
    port: int | None = None,
    *,
    host: str = "127.0.0.1",
    config_file: str | os.PathLike[str] | None = None,
    timeout_s: float = 60.0,
    security: str | os.PathLike[str] | None = None,
    net: str = "net",
    router_id: str = "router",
    connect: Sequence[str] = (),
) -> Iterator[str]:
    """Run a zenoh router in a subprocess; yields its endpoint ``tcp/<host>:<port>``.

    With ``security`` (a ``shared.security`` directory holding ``router_id``'s certificate)
    the router is secured (TLS, mTLS, access control on network ``net``) and the endpoint
    is ``tls/<host>:<port>``.

    Waits (at most ``timeout_s``) for the router's ``ready`` line; on exit sends
    SIGTERM and waits, then kills.  The router also exits if this process dies, since
    it watches its stdin.  ``port=None`` picks a free port (and retries on another
    one if it was taken in between).  ``connect``: endpoints of routers to join.
    """
    attempts = 3 if port is None else 1
    for attempt in range(attempts):
        proto = "tcp" if security is None else "tls"
        endpoint = f"{proto}/{host}:{free_port(host) if port is None else port}"
        extra = [] if security is None else ["--security", os.fspath(security), "--net", net, "--id", router_id]
        for other in connect:  # join other routers: one Zenoh network across router processes
            extra += ["--connect", other]
        proc, error = start_router(endpoint, config_file, timeout_s, extra)
        if error is None:
            break
        if attempt == attempts - 1:
            raise RuntimeError(f"zenoh router on {endpoint} did not start within {timeout_s} s: {error}")
        log.warning("zenoh router on %s did not start, retrying: %s", endpoint, error)
    try:
        yield endpoint
    finally:
        stop_router(proc)


def start_router(
    endpoint: str, config_file: str | os.PathLike[str] | None, timeout_s: float, extra: Sequence[str] = ()
) -> tuple[subprocess.Popen, str | None]:
    """Start a router subprocess listening on ``endpoint``; returns it and None once it is ready, or
    it (stopped) and its error output if it is not ready within ``timeout_s``.

    The lower-level half of :func:`run_router`, for callers that stop and restart a router
    themselves (:func:`stop_router`). ``extra``: more ``python -m shared.transport router`` options.
    """
    cmd = [sys.executable, "-m", "shared.transport", "router", "--listen", endpoint, "--exit-on-stdin-eof", *extra]
    if config_file is not None:
        cmd += ["--config", os.fspath(config_file)]
    with tempfile.TemporaryFile(mode="w+") as errors:
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=errors, text=True)
        first: list[str] = []
        got_first = threading.Event()
        threading.Thread(target=_drain, args=(proc.stdout, first, got_first), daemon=True).start()
        if got_first.wait(timeout_s) and first and first[0].startswith(READY):
            log.debug("zenoh router %s up on %s", first[0].split()[-1], endpoint)
            return proc, None
        stop_router(proc)
        errors.seek(0)
        return proc, errors.read()[-2000:].strip() or "no output"


def stop_router(proc: subprocess.Popen, timeout_s: float = 5.0) -> None:
    """Stop a router subprocess of :func:`start_router`: SIGTERM, then SIGKILL after ``timeout_s``."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout_s)
    if proc.stdin is not None:
        with contextlib.suppress(OSError):
            proc.stdin.close()


def _watch_stdin(stop: threading.Event) -> None:
    for _ in sys.stdin:
        pass
    stop.set()


def _add_tls_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--tls-ca", help="PEM of the CA that signs every peer (for tls/... endpoints)")
    p.add_argument("--tls-cert", help="this session's certificate (PEM; its CN is its identity)")
    p.add_argument("--tls-key", help="this session's private key (PEM)")


def _tls_from_args(args: argparse.Namespace) -> TlsFiles | None:
    """TlsFiles from ``--secure DIR`` (the certificate of identity ``--id`` in a ``shared.security``
    directory) or ``--tls-ca/--tls-cert/--tls-key``; raises ValueError (one line) if incomplete."""
    secure = getattr(args, "secure", None)
    if secure is not None:
        if args.tls_ca or args.tls_cert or args.tls_key:
            raise ValueError("--secure DIR or --tls-ca/--tls-cert/--tls-key, not both")
        name = getattr(args, "id", None)
        if not name:
            raise ValueError("--secure DIR needs --id NAME: the identity whose certificate DIR holds")
        return SecurityDir(Path(secure)).tls(name)
    if args.tls_ca is None:
        if args.tls_cert or args.tls_key:
            raise ValueError("--tls-cert/--tls-key need --tls-ca")
        return None
    return TlsFiles(Path(args.tls_ca), args.tls_cert and Path(args.tls_cert), args.tls_key and Path(args.tls_key))


def add_zenoh_arguments(p: argparse.ArgumentParser, default_mode: str = "client") -> None:
    """The ``--mode/--connect/--listen/--config`` and ``--tls-*`` options every daemon shares."""
    p.add_argument("--mode", choices=MODES, default=None, help=f"zenoh session mode (default {default_mode})")
    p.add_argument("--connect", action="append", default=[], help="zenoh endpoint to connect to (repeatable)")
    p.add_argument("--listen", action="append", default=[], help="zenoh endpoint to listen on (repeatable)")
    p.add_argument("--config", help="zenoh JSON5 config file (TLS, access control, ...)")
    p.add_argument("--secure", metavar="DIR", help="TLS with the certificate of this process's --id from the "
                   "security directory DIR (python -m shared.security; the same CA on every machine)")
    _add_tls_arguments(p)
    p.set_defaults(_default_mode=default_mode)


def config_from_args(args: argparse.Namespace) -> zenoh.Config:
    """A ``zenoh.Config`` from :func:`add_zenoh_arguments` options (ValueError if they are invalid)."""
    mode = args.mode or (None if args.config else args._default_mode)
    if mode == "client" and not args.connect and not args.config:
        mode = "peer"  # a client needs a router to connect to; alone, be a peer
    return zenoh_config(mode, connect=args.connect, listen=args.listen, config_file=args.config,
                        tls=_tls_from_args(args))


DENIALS_LOGGED = 20  # each of the first refusals is logged; then one line per this many


def _capture_zenoh_log(counter: DenialCounter) -> typing.TextIO:
    """Turn on Zenoh's access-control trace and count the refusals in it (:class:`DenialCounter`).

    Zenoh logs to this process's stdout (fd 1): fd 1 becomes a pipe read by a thread here,
    which counts refusals and passes every other non-trace line on to stderr. Returns a
    text file on the original stdout (for the ``ready`` line).
    """
    sys.stdout.flush()
    original = os.fdopen(os.dup(1), "w", buffering=1)
    read_fd, write_fd = os.pipe()
    os.dup2(write_fd, 1)
    os.close(write_fd)
    sys.stdout = original
    os.environ["RUST_LOG"] = f"{os.environ.get('RUST_LOG') or 'warn'},{ACL_LOG_DIRECTIVE}"
    zenoh.init_log_from_env_or("warn")

    def read() -> None:
        with os.fdopen(read_fd, "r", errors="replace") as lines:
            for line in lines:
                denial = counter.feed(line)
                if denial is not None:
                    if counter.total <= DENIALS_LOGGED or counter.total % (DENIALS_LOGGED * 50) == 0:
                        who, message, flow, key = denial
                        log.warning("access denied (%d so far): %s %s %s on %s", counter.total, who, message,
                                    flow, key)
                elif " TRACE " not in ANSI.sub("", line):  # (Zenoh colours its level even into a pipe)
                    sys.stderr.write(line)

    threading.Thread(target=read, daemon=True, name="zenoh-log").start()
    return original


def build_parser(prog: str = "python -m shared.transport") -> argparse.ArgumentParser:
    """The router's options."""
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    router = sub.add_parser("router", help="run a zenoh router until SIGTERM/SIGINT")
    router.add_argument("--listen", "-l", action="append", default=[], help="endpoint, e.g. tcp/127.0.0.1:7447")
    router.add_argument("--connect", "-e", action="append", default=[], help="another router to join")
    router.add_argument("--config", "-c", help="zenoh JSON5 config file")
    router.add_argument("--security", metavar="DIR", help="secure the router from a shared.security directory: "
                        "TLS only, mutual authentication, access control of DIR's identities")
    router.add_argument("--id", default="router", help="with --security: the router's identity in DIR")
    router.add_argument("--net", default="net", help="with --security: the network the access control covers")
    router.add_argument("--no-count-denials", action="store_true",
                        help="with --security: do not count refusals (their trace costs about half the throughput)")
    _add_tls_arguments(router)
    router.add_argument("--multicast", action="store_true", help="enable multicast scouting")
    router.add_argument("--exit-on-stdin-eof", action="store_true", help="also stop when stdin closes")
    return parser


def main(argv: Sequence[str] | None = None, prog: str = "python -m shared.transport") -> int:
    """``python -m shared.transport router --listen ENDPOINT [--connect E] [--config FILE]`` (also
    ``driveby router ...``: ``prog`` names it in the help)."""
    parser = build_parser(prog)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s router %(levelname)s %(message)s")
    counter = None
    try:
        conf = zenoh_config("router", args.connect, args.listen, args.config, no_multicast=not args.multicast,
                            tls=_tls_from_args(args))
        if args.security is not None:
            check_id(args.net, "net")
            secured = router_config(SecurityDir(Path(args.security)), args.net, check_id(args.id, "id"))
            for section in ("transport/link/protocols", "transport/link/tls", "access_control"):
                value = secured
                for part in section.split("/"):
                    value = value[part]
                conf.insert_json5(section, json.dumps(value))
            counter = None if args.no_count_denials else DenialCounter()
    except SecurityError as e:  # a file of the security directory is missing or malformed
        print(f"{prog} router: {e}", file=sys.stderr)
        return 1
    except (ValueError, zenoh.ZError) as e:  # the endpoints or options themselves
        print(f"{prog} router: {e}", file=sys.stderr)
        return 2
    out = sys.stdout if counter is None else _capture_zenoh_log(counter)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    if args.exit_on_stdin_eof:
        threading.Thread(target=_watch_stdin, args=(stop,), daemon=True).start()

    declared = []  # the denial queryable, held for the session's lifetime

    def ready(session: zenoh.Session) -> None:
        if counter is not None:
            def on_denials(query):
                with query:
                    query.reply(denials_key(args.net, args.id), json.dumps(counter.snapshot()).encode())

            declared.append(session.declare_queryable(denials_key(args.net, args.id), on_denials))
        presence = logging.getLogger(PRESENCE_LOG)
        presence.setLevel(logging.INFO)
        presence.info("router started: zenoh id %s, listening on %s%s", session.zid(), ", ".join(args.listen),
                      f", joining {', '.join(args.connect)}" if args.connect else "")

        def on_daemon(sample) -> None:  # every daemon of every net that comes and goes through this router
            try:
                net, role, ident = parse_alive_key(str(sample.key_expr))
            except ValueError:
                return
            state = "is up" if sample.kind == zenoh.SampleKind.PUT else "is gone"
            presence.info("router: %s/%s on net %s %s", role, ident, net, state)

        declared.append(session.liveliness().declare_subscriber(ALL_ALIVE, on_daemon, history=True))
        out.write(f"{READY} {session.zid()}\n")
        out.flush()

    try:
        serve_router(conf, stop, ready)
    except zenoh.ZError as e:  # e.g. the port is taken
        print(f"{prog} router: {zenoh_message(e)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

