"""What the edge has sent but the cloud has not yet acknowledged, per pass, optionally on disk.

A pass's messages (its AP segments and its pass-done, under one calibration version) stay here
until the cloud acknowledges the pass under that version or a newer one. While no aggregator is
alive they are only stored; when one appears (a restart, the end of an outage) every pending pass
is sent again. Redelivery is harmless: the cloud treats segments as idempotent by vehicle, pass,
tile and calibration version.

Each message keeps the trace it was first published with (the zenoh attachment a benchmark times
a segment by, :attr:`edge.node.Edge.trace`): a resend carries the message's own, not whatever
the edge is processing when it resends.

On disk each pending pass is one Arrow IPC stream ``<dir>/<vehicle>/<pass>.arrows`` written
through to the OS message by message, so an edge killed and restarted still delivers what it
had not got acknowledged. The store is bounded: past ``max_bytes`` the oldest passes are dropped
with a counted warning (``evicted``), because a vehicle that cannot reach the cloud for days
must keep measuring rather than stop.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import urllib.parse
from pathlib import Path

import pyarrow as pa

log = logging.getLogger("driveby.edge.outbox")

SCHEMA = pa.schema([("calib_version", pa.int64()), ("key", pa.string()), ("payload", pa.binary()),
                    ("trace", pa.binary())])  # (trace: null when untraced, absent in older spools)
DEFAULT_MAX_BYTES = 512 * 2**20


@dataclasses.dataclass
class _Pending:
    calib_version: int
    messages: list[tuple[str, bytes]] = dataclasses.field(default_factory=list)
    traces: list[bytes | None] = dataclasses.field(default_factory=list)  # each message's, in order
    nbytes: int = 0
    file: object = None
    writer: object = None


def _name(text: str) -> str:
    return urllib.parse.quote(text, safe="-_.") or "_"


class Outbox:
    """Unacknowledged passes, oldest first; ``directory`` None keeps them in memory only."""

    def __init__(self, directory: str | Path | None = None, max_bytes: int = DEFAULT_MAX_BYTES):
        if max_bytes <= 0:
            raise ValueError(f"outbox max_bytes: expected > 0, got {max_bytes}")
        self.dir = None if directory is None else Path(directory)
        self.max_bytes = max_bytes
        self.pending: collections.OrderedDict[tuple[str, str], _Pending] = collections.OrderedDict()
        self.nbytes = 0
        self.evicted = 0  # passes dropped unacknowledged to stay within max_bytes
        self.acked = 0
        if self.dir is not None:
            if self.dir.exists() and not self.dir.is_dir():
                raise ValueError(f"{self.dir}: spool path exists and is not a directory")
            self.dir.mkdir(parents=True, exist_ok=True)
            self._load()

    # -- disk ------------------------------------------------------------------------------------
    def _path(self, vehicle: str, pass_id: str) -> Path:
        return self.dir / _name(vehicle) / f"{_name(pass_id)}.arrows"

    def _load(self) -> None:
        files = sorted(self.dir.glob("*/*.arrows"), key=lambda p: p.stat().st_mtime_ns)
        for path in files:
            vehicle = urllib.parse.unquote(path.parent.name)
            pass_id = urllib.parse.unquote(path.stem)
            rows: list[tuple[int, str, bytes, bytes | None]] = []
            try:
                reader = pa.ipc.open_stream(pa.memory_map(str(path)))
                while True:
                    try:
                        cols = reader.read_next_batch().to_pydict()
                    except StopIteration:
                        break
                    traces = cols.get("trace", [None] * len(cols["key"]))
                    rows.extend(zip(cols["calib_version"], cols["key"], cols["payload"], traces))
            except (pa.ArrowInvalid, OSError):  # a torn tail (killed mid-write): keep what is complete
                pass
            if not rows:
                path.unlink(missing_ok=True)
                continue
            version = max(r[0] for r in rows)
            p = _Pending(version, [(k, v) for c, k, v, _ in rows if c == version],
                         [t for c, _, _, t in rows if c == version])
            p.nbytes = sum(len(v) for _, v in p.messages)
            self.pending[(vehicle, pass_id)] = p
            self.nbytes += p.nbytes
        if self.pending:
            log.warning("outbox: %d unacknowledged passes recovered from %s", len(self.pending), self.dir)

    def _write(self, vehicle: str, pass_id: str, p: _Pending, key: str, payload: bytes,
               trace: bytes | None) -> None:
        if self.dir is None:
            return
        todo = [(key, payload, trace)]
        if p.writer is None:  # a new pass, or one recovered from disk: (re)write all it holds
            path = self._path(vehicle, pass_id)
            path.parent.mkdir(parents=True, exist_ok=True)
            p.file = open(path, "wb", buffering=0)  # write-through: a killed edge keeps what it wrote
            p.writer = pa.ipc.new_stream(p.file, SCHEMA)
            todo = [(k, v, t) for (k, v), t in zip(p.messages, p.traces)]
        n = len(todo)
        p.writer.write_batch(pa.record_batch(
            [pa.array([p.calib_version] * n, pa.int64()), pa.array([k for k, _, _ in todo], pa.string()),
             pa.array([v for _, v, _ in todo], pa.binary()), pa.array([t for _, _, t in todo], pa.binary())],
            schema=SCHEMA))

    def _drop(self, k: tuple[str, str]) -> None:
        p = self.pending.pop(k)
        self.nbytes -= p.nbytes
        if p.file is not None:
            p.file.close()
        if self.dir is not None:
            self._path(*k).unlink(missing_ok=True)

    # -- use -------------------------------------------------------------------------------------
    def add(self, vehicle: str, pass_id: str, calib_version: int, key: str, payload: bytes,
            trace: bytes | None = None) -> None:
        """Keep one message of a pass until the pass is acknowledged under ``calib_version``, with the
        trace it is published with (None: untraced)."""
        k = (vehicle, pass_id)
        p = self.pending.get(k)
        if p is not None and calib_version < p.calib_version:
            return  # older than what is pending: superseded already
        if p is not None and calib_version > p.calib_version:
            self._drop(k)  # a recomputation under a newer calibration replaces the pass
            p = None
        if p is None:
            p = self.pending[k] = _Pending(calib_version)
        p.messages.append((key, payload))
        p.traces.append(trace)
        p.nbytes += len(payload)
        self.nbytes += len(payload)
        self._write(vehicle, pass_id, p, key, payload, trace)
        while self.nbytes > self.max_bytes and len(self.pending) > 1:
            old = next(iter(self.pending))
            if old == k:
                break
            self._drop(old)
            self.evicted += 1
            log.warning("outbox full (%d bytes): dropped unacknowledged pass %s/%s", self.max_bytes, *old)

    def ack(self, vehicle: str, pass_id: str, calib_version: int) -> None:
        p = self.pending.get((vehicle, pass_id))
        if p is not None and calib_version >= p.calib_version:
            self._drop((vehicle, pass_id))
            self.acked += 1

    def messages(self) -> list[tuple[str, bytes]]:
        """Every pending message, oldest pass first, in the order it was sent."""
        return [m for p in self.pending.values() for m in p.messages]

    def traced(self) -> list[tuple[str, bytes, bytes | None]]:
        """:meth:`messages` with the trace each was first published with: ``(key, payload, trace)``."""
        return [(k, v, t) for p in self.pending.values() for (k, v), t in zip(p.messages, p.traces)]

    def stats(self) -> dict:
        return {"pending_passes": len(self.pending), "pending_bytes": self.nbytes,
                "evicted": self.evicted, "acked": self.acked}

    def close(self) -> None:
        for p in self.pending.values():
            if p.file is not None:
                p.file.close()
                p.file = p.writer = None

