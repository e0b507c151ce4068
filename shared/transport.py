"""Zenoh plumbing: configs from plain values, free loopback ports, a router from PyPI only.

zenoh-python opens a session in ``router`` mode (config ``mode: "router"``), and
clients or peers connected to it route pub/sub, queries and liveliness between
processes, so no ``zenohd`` binary is needed::

    python -m shared.transport router --listen tcp/127.0.0.1:7447

prints one ``ready <zid>`` line on stdout once listening and runs until SIGTERM or
SIGINT (or, with ``--exit-on-stdin-eof``, until its parent closes its stdin).
:func:`run_router` starts it as a subprocess for tests and for ``driveby run``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator, Sequence

import zenoh

log = logging.getLogger(__name__)

MODES = ("peer", "client", "router")
READY = "ready"

__all__ = ["MODES", "free_port", "zenoh_config", "run_router", "serve_router", "add_zenoh_arguments",
           "config_from_args", "main"]


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free on ``host`` a moment ago (bind port 0, read it, close)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


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
    timeout_s: float = 10.0,
) -> Iterator[str]:
    """Run a zenoh router in a subprocess; yields its endpoint ``tcp/<host>:<port>``.

    Waits (at most ``timeout_s``) for the router's ``ready`` line; on exit sends
    SIGTERM and waits, then kills.  The router also exits if this process dies, since
    it watches its stdin.  ``port=None`` picks a free port (and retries on another
    one if it was taken in between).
    """
    attempts = 3 if port is None else 1
    for attempt in range(attempts):
        endpoint = f"tcp/{host}:{free_port(host) if port is None else port}"
        proc, error = _start_router(endpoint, config_file, timeout_s)
        if error is None:
            break
        if attempt == attempts - 1:
            raise RuntimeError(f"zenoh router on {endpoint} did not start within {timeout_s} s: {error}")
        log.warning("zenoh router on %s did not start, retrying: %s", endpoint, error)
    try:
        yield endpoint
    finally:
        _stop(proc)


def _start_router(
    endpoint: str, config_file: str | os.PathLike[str] | None, timeout_s: float
) -> tuple[subprocess.Popen, str | None]:
    """Start the router subprocess; returns it and None once ready, or its error (stopped)."""
    cmd = [sys.executable, "-m", "shared.transport", "router", "--listen", endpoint, "--exit-on-stdin-eof"]
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
        _stop(proc)
        errors.seek(0)
        return proc, errors.read()[-2000:].strip() or "no output"


def _stop(proc: subprocess.Popen, timeout_s: float = 5.0) -> None:
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


def add_zenoh_arguments(p: argparse.ArgumentParser, default_mode: str = "client") -> None:
    """The ``--mode/--connect/--listen/--config`` options every daemon shares."""
    p.add_argument("--mode", choices=MODES, default=None, help=f"zenoh session mode (default {default_mode})")
    p.add_argument("--connect", action="append", default=[], help="zenoh endpoint to connect to (repeatable)")
    p.add_argument("--listen", action="append", default=[], help="zenoh endpoint to listen on (repeatable)")
    p.add_argument("--config", help="zenoh JSON5 config file (TLS, access control, ...)")
    p.set_defaults(_default_mode=default_mode)


def config_from_args(args: argparse.Namespace) -> zenoh.Config:
    """A ``zenoh.Config`` from :func:`add_zenoh_arguments` options."""
    mode = args.mode or (None if args.config else args._default_mode)
    if mode == "client" and not args.connect and not args.config:
        mode = "peer"  # a client needs a router to connect to; alone, be a peer
    return zenoh_config(mode, connect=args.connect, listen=args.listen, config_file=args.config)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m shared.transport router --listen ENDPOINT [--connect E] [--config FILE]``."""
    parser = argparse.ArgumentParser(prog="python -m shared.transport", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    router = sub.add_parser("router", help="run a zenoh router until SIGTERM/SIGINT")
    router.add_argument("--listen", "-l", action="append", default=[], help="endpoint, e.g. tcp/127.0.0.1:7447")
    router.add_argument("--connect", "-e", action="append", default=[], help="another router to join")
    router.add_argument("--config", "-c", help="zenoh JSON5 config file")
    router.add_argument("--multicast", action="store_true", help="enable multicast scouting")
    router.add_argument("--exit-on-stdin-eof", action="store_true", help="also stop when stdin closes")
    args = parser.parse_args(argv)

    try:
        conf = zenoh_config("router", args.connect, args.listen, args.config, no_multicast=not args.multicast)
    except (ValueError, zenoh.ZError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    if args.exit_on_stdin_eof:
        threading.Thread(target=_watch_stdin, args=(stop,), daemon=True).start()

    def ready(session: zenoh.Session) -> None:
        sys.stdout.write(f"{READY} {session.zid()}\n")
        sys.stdout.flush()

    try:
        serve_router(conf, stop, ready)
    except zenoh.ZError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

