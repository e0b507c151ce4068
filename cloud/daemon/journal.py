"""The cloud's write-ahead journal: every input it acts on, in Arrow IPC, before it acts on it.

Layout of a state directory::

    journal-000001.arrows   one Arrow IPC stream per daemon lifetime (append-only, never rewritten)
    journal-000002.arrows
    snapshot-000002.arrow   the compacted state as of the start of journal 2 (Arrow IPC file)

A record is ``(seq, kind, key, payload)``: ``seq`` counts records over the directory's whole history,
``kind`` says which handler replays it (an AP payload, a pass-done, a calibration the cloud issued),
``key``/``payload`` are the message as it came off the bus. Replaying the records in ``seq`` order
through the same handlers rebuilds the same state: the aggregator is a deterministic state machine
and duplicates are idempotent by (vehicle, pass, tile, calibration version).

Durability policy (why these two steps):

* **Write-through before apply.** Each record is written to the OS (unbuffered ``write``) before the
  handler runs, so a process crash (SIGKILL, OOM) at any instant loses nothing the cloud acted on.
* **fsync before anything leaves the process that promises durability** — an acknowledgement or a
  calibration, held meanwhile so that one fsync releases a group of them
  (:class:`cloud.daemon.durable.GroupCommit`) — and at most every ``fsync_interval_s`` otherwise.
  An OS crash or power loss can lose only records written since the last fsync, none of them
  acknowledged; the edges keep their raw spool until a pass is acknowledged, so they resend
  exactly those.

A torn tail (a crash in the middle of a write) is detected on open and ignored: the stream reader
stops at the last complete record batch.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import threading
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
import pyarrow as pa

SCHEMA = pa.schema([
    ("seq", pa.uint64()),
    ("kind", pa.string()),
    ("key", pa.string()),
    ("payload", pa.binary()),
])
SNAPSHOT_BATCH = 1024  # records per batch of a snapshot file at most…
SNAPSHOT_BATCH_BYTES = 1 << 20  # …and about this many payload bytes: the transient memory of a snapshot


_STREAM_HEADER = SCHEMA.serialize().to_pybytes()  # a stream's schema message, as the stream writer writes it
_END_OF_STREAM = b"\xff\xff\xff\xff\x00\x00\x00\x00"
_SEQ, _KIND, _KEY, _PAYLOAD = (f.type for f in SCHEMA)


def _one(t: pa.DataType, raw: bytes) -> pa.Array:
    """A one-value string or binary array over ``raw`` (no copy, no conversion)."""
    return pa.Array.from_buffers(t, 1, [None, pa.py_buffer(np.array([0, len(raw)], np.int32)), pa.py_buffer(raw)])


def _record(seq: int, kind: str, key: str, payload: bytes) -> bytes:
    """One record as the stream writer writes it: an encapsulated record-batch message of one row."""
    seqs = pa.Array.from_buffers(_SEQ, 1, [None, pa.py_buffer(np.array([seq], np.uint64))])
    batch = pa.RecordBatch.from_arrays([seqs, _one(_KIND, kind.encode()), _one(_KEY, key.encode()),
                                        _one(_PAYLOAD, bytes(payload))], schema=SCHEMA)
    return batch.serialize().to_pybytes()


def _batch(seq0: int, rows: list[tuple[str, str, bytes]]) -> pa.RecordBatch:
    return pa.record_batch([pa.array(range(seq0, seq0 + len(rows)), pa.uint64()),
                            pa.array([r[0] for r in rows], pa.string()),
                            pa.array([r[1] for r in rows], pa.string()),
                            pa.array([r[2] for r in rows], pa.binary())], schema=SCHEMA)


_JOURNAL = re.compile(r"journal-(\d{6})\.arrows$")
_SNAPSHOT = re.compile(r"snapshot-(\d{6})\.arrow$")


@dataclasses.dataclass(frozen=True)
class Record:
    seq: int
    kind: str
    key: str
    payload: bytes


class JournalError(RuntimeError):
    """The state directory cannot be used (not a directory, unreadable snapshot, …)."""


def _read_stream(path: Path) -> Iterator[Record]:
    """Records of one journal file, stopping quietly at a torn tail."""
    try:
        reader = pa.ipc.open_stream(pa.memory_map(str(path)))
    except (pa.ArrowInvalid, OSError):  # crashed before the schema was complete: nothing in it
        return
    while True:
        try:
            batch = reader.read_next_batch()
        except StopIteration:
            return
        except (pa.ArrowInvalid, OSError):  # the record being written when the process died
            return
        cols = batch.to_pydict()
        for seq, kind, key, payload in zip(cols["seq"], cols["kind"], cols["key"], cols["payload"]):
            yield Record(int(seq), kind, key, payload)


class Journal:
    """An append-only record log in ``directory`` with periodic compacted snapshots.

    ``open`` reads what is there (newest snapshot, then the journals after it) and starts a new
    journal file for this lifetime; a journal file is never appended to by a second lifetime, so a
    torn tail can only ever be at the end of a finished file.
    """

    def __init__(self, directory: str | Path, fsync_interval_s: float = 0.1):
        self.dir = Path(directory)
        if self.dir.exists() and not self.dir.is_dir():
            raise JournalError(f"{self.dir}: state path exists and is not a directory")
        self.dir.mkdir(parents=True, exist_ok=True)
        self.fsync_interval_s = fsync_interval_s
        self._file = None
        self.written = 0  # records written through to the OS in this lifetime…
        self.synced = 0  # …and how many of them are known to be on disk
        self._synced_at = time.monotonic()
        self._sync_lock = threading.Lock()  # sync may run on another thread than append (group commit)
        # Past every file there (a snapshot may be newer than the last journal), so this lifetime's
        # journal is never older than the snapshot recovery starts from.
        numbers = self._numbers(_JOURNAL) + self._numbers(_SNAPSHOT)
        self.generation = (max(numbers) if numbers else 0) + 1
        self.next_seq = 0
        self.snapshot_generation = 0

    @staticmethod
    def _sorted(directory: Path, pattern: re.Pattern) -> list[tuple[int, Path]]:
        out = []
        for p in directory.iterdir():
            m = pattern.fullmatch(p.name)
            if m:
                out.append((int(m.group(1)), p))
        return sorted(out)

    def _numbers(self, pattern: re.Pattern) -> list[int]:
        return [n for n, _ in self._sorted(self.dir, pattern)]

    # -- recovery ------------------------------------------------------------------------------
    def recover(self) -> tuple[dict, list[Record]]:
        """The newest snapshot's metadata and records, then every journal record after it, in order.

        Call once, before :meth:`append`. Sets ``next_seq`` past everything seen.
        """
        meta: dict = {}
        records: list[Record] = []
        snaps = self._sorted(self.dir, _SNAPSHOT)
        start_gen = 1
        if snaps:
            gen, path = snaps[-1]
            try:
                table = pa.ipc.open_file(pa.memory_map(str(path))).read_all()
            except (pa.ArrowInvalid, OSError) as e:
                raise JournalError(f"{path}: unreadable snapshot ({e})") from None
            raw = (table.schema.metadata or {}).get(b"driveby")
            meta = json.loads(raw) if raw else {}
            if "seq0" in meta and "next_seq" not in meta:  # streamed: its rows say where it ends
                meta["next_seq"] = int(meta["seq0"]) + table.num_rows
            cols = table.to_pydict()
            records.extend(Record(int(s), k, key, p)
                           for s, k, key, p in zip(cols["seq"], cols["kind"], cols["key"], cols["payload"]))
            start_gen = gen
            self.snapshot_generation = gen
            self.next_seq = int(meta.get("next_seq", 0))
        for gen, path in self._sorted(self.dir, _JOURNAL):
            if gen < start_gen:
                continue
            for r in _read_stream(path):
                if r.seq >= self.next_seq:  # a snapshot taken mid-journal already holds the earlier ones
                    records.append(r)
                    self.next_seq = r.seq + 1
        return meta, records

    # -- writing -------------------------------------------------------------------------------
    def _open_writer(self) -> None:
        path = self.dir / f"journal-{self.generation:06d}.arrows"
        # buffering=0: every write goes straight to the OS, so a killed process loses nothing written.
        self._file = open(path, "ab", buffering=0)
        self._file.write(_STREAM_HEADER)
        # (the stream is written here, not by a stream writer: a whole record per write, one system call)

    def append(self, kind: str, key: str, payload: bytes) -> int:
        """Write one record through to the OS; returns its ``seq``."""
        if self._file is None:
            self._open_writer()
        seq = self.next_seq
        self.next_seq += 1
        self._file.write(_record(seq, kind, key, payload))
        self.written += 1
        if time.monotonic() - self._synced_at >= self.fsync_interval_s:
            self.sync()
        return seq

    def sync(self, upto: int | None = None) -> None:
        """fsync the current journal file (before anything durable-sounding leaves the process), so
        that the first ``upto`` records written (None: all so far) are on disk.

        Safe while another thread appends: what it writes meanwhile is synced by a later call."""
        with self._sync_lock:
            written = self.written
            if self.synced < (written if upto is None else min(upto, written)):
                if self._file is not None:
                    os.fsync(self._file.fileno())
                self.synced = written
            self._synced_at = time.monotonic()

    def write_snapshot(self, records: Iterable[tuple[str, str, bytes]], meta: dict) -> Path:
        """Compact: ``records`` (kind, key, payload) rebuild the current state; older files go.

        Records written after this call land in a new journal generation, so recovery reads this
        snapshot and then only journals of this generation or later. The snapshot is written to a
        temporary name, fsynced and renamed, so a crash leaves either the old state or the new one.
        """
        self.close()
        self.generation += 1
        seq0 = self.next_seq
        # Streamed in batches (memory: one batch, however large the state). The record count is not
        # known before the end, so the metadata says where the snapshot's seqs start and recovery
        # counts them (``next_seq`` = ``seq0`` + rows).
        schema = SCHEMA.with_metadata({"driveby": json.dumps({**meta, "seq0": seq0})})
        final = self.dir / f"snapshot-{self.generation:06d}.arrow"
        tmp = final.with_suffix(".tmp")
        seq = seq0
        with open(tmp, "wb") as f:
            with pa.ipc.new_file(f, schema) as w:
                batch: list[tuple[str, str, bytes]] = []
                size = 0
                for r in records:
                    batch.append(r)
                    size += len(r[2])
                    if len(batch) == SNAPSHOT_BATCH or size >= SNAPSHOT_BATCH_BYTES:
                        w.write_batch(_batch(seq, batch))
                        seq += len(batch)
                        batch, size = [], 0
                if batch or seq == seq0:
                    w.write_batch(_batch(seq, batch))
                    seq += len(batch)
            f.flush()
            os.fsync(f.fileno())
        self.next_seq = seq
        pa.default_memory_pool().release_unused()  # the batches' buffers: back to the OS, not kept
        os.replace(tmp, final)
        dfd = os.open(self.dir, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
        self.snapshot_generation = self.generation
        for gen, path in self._sorted(self.dir, _JOURNAL) + self._sorted(self.dir, _SNAPSHOT):
            if gen < self.generation:
                path.unlink(missing_ok=True)
        return final

    def close(self) -> None:
        if self._file is not None:
            try:
                self._file.write(_END_OF_STREAM)
            finally:
                with self._sync_lock:
                    os.fsync(self._file.fileno())
                    self.synced = self.written
                    self._file.close()
                    self._file = None

    def __enter__(self) -> "Journal":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
