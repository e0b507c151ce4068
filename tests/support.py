"""What several test modules do alike: a simulation's drive logs through the real edge, in process,
and a simulation made once per test session for every worker that asks for it.

The edge is the transport-free :class:`edge.node.Edge`, fed each log's chunks as
:func:`simfleet.replay.chunks_of` cuts them (the replay's chunk length), one log after another, each
chunk under its vehicle's key as the edge daemon receives it from ``driveby/<net>/veh/<id>/imu``.
"""

from __future__ import annotations

import fcntl
import os
import shutil
from collections.abc import Callable, Iterable
from pathlib import Path

import pytest

from edge.node import Edge
from shared.drivelog import DriveLog, list_drive_logs, read_drive_log
from shared.registry import Site
from shared.schema import SensorChunk
from simfleet.replay import chunks_of

Message = tuple[str, bytes]


def drive_logs(sim_dir: str | Path) -> list[DriveLog]:
    """The drive logs under ``sim_dir/logs``, in :func:`shared.drivelog.list_drive_logs`'s order."""
    return [read_drive_log(p) for p in list_drive_logs(Path(sim_dir) / "logs")]


def drive(edge: Edge, logs: Iterable[DriveLog],
          trace: Callable[[DriveLog, SensorChunk], bytes | None] | None = None) -> Edge:
    """Every log through ``edge`` chunk by chunk, in order; ``trace(log, chunk)``, if given, is the
    edge's :attr:`~edge.node.Edge.trace` while it takes that chunk (as the daemon tags each chunk
    with its zenoh attachment). Returns ``edge``."""
    for log in logs:
        for chunk in chunks_of(log):
            if trace is not None:
                edge.trace = trace(log, chunk)
            edge.on_chunk(chunk.encode(), log.meta.vehicle_id)
    return edge


def edge_messages(site: Site, logs: Iterable[DriveLog], net: str = "t", **edge_options) -> list[Message]:
    """The messages ``(key, payload)`` an edge with nominal calibration (each log's own parameters)
    publishes for ``logs``, in the order it publishes them; ``edge_options`` go to :class:`Edge`."""
    out: list[Message] = []
    drive(Edge(net, lambda key, payload: out.append((key, payload)), site, "nominal", **edge_options), logs)
    return out


def made_once(d: Path, make: Callable[[Path], object]) -> Path:
    """``d``, made by ``make(d)`` once however many processes ask for it side by side: a lock keeps
    the others waiting until the first has made it. A ``done`` marker is written after ``make``
    returns, so a directory a failed ``make`` left half made is made again."""
    d.parent.mkdir(parents=True, exist_ok=True)
    with open(d.with_name(d.name + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (d / "done").exists():
            shutil.rmtree(d, ignore_errors=True)
            d.mkdir()
            make(d)
            (d / "done").write_text("")
    return d


def session_dir(tmp_path_factory: pytest.TempPathFactory, name: str, make: Callable[[Path], object]) -> Path:
    """``name``'s directory, made by ``make(dir)`` once per test session and read by every module
    (and every xdist worker) that asks for it: the workers share the session's temporary root
    (:func:`made_once`). Readers must not change what is in it."""
    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base  # xdist: a basetemp per worker
    return made_once(root / "shared" / name, make)
