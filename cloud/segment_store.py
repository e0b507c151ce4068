"""The aggregator's segments with a bounded number in memory: the rest spilled to disk, exact.

The aggregator keeps every accepted segment because a later recalibration of its pass must retract
it from the estimators exactly (and the long-wave band, alignment and bridges read them). Memory
must not grow with the passes, so at most ``max_resident`` segments stay decoded in memory; older
ones are written, as their wire payload (Arrow IPC, lossless: the estimators work on the wire
codes), to an append-only spill file, and a read of such a slot decodes it back — the same values,
so retraction stays exact and every export equals the unbounded store's.

What stays in memory per spilled slot is its key and ``(offset, length, calib_version)`` (~200 B
against ~4 kB for a decoded segment of 1 000 points); the calibration version is kept so that
superseding a slot needs no read. Iteration order is that of a ``dict`` with the same writes
(a write to an existing key keeps its place), so anything summed over the segments sums in the
same order whether they are resident or not.

The spill file belongs to one process lifetime (a restarted cloud rebuilds it from its journal);
replaced and deleted slots leave garbage in it, reclaimed by :meth:`SegmentStore.compact` (the
daemon calls it with each journal snapshot).
"""

from __future__ import annotations

import collections
import os
import tempfile
from collections.abc import Iterator, MutableMapping
from pathlib import Path

from shared.schema import ApSegment, decode_ap

#: Default for the daemon: ~4 kB each, so ~80 MB of decoded segments at most.
DEFAULT_MAX_RESIDENT = 20_000


class _Spilled(tuple):
    """Where a spilled segment is: ``(offset, length, calib_version)``."""

    __slots__ = ()


class SegmentStore(MutableMapping):
    """``slot → ApSegment``, at most ``max_resident`` decoded in memory (None: all of them)."""

    def __init__(self, max_resident: int | None = None, spill_dir: str | Path | None = None):
        if max_resident is not None and max_resident < 1:
            raise ValueError(f"max_resident: expected >= 1 or None, got {max_resident}")
        self.max_resident = max_resident
        self._spill_dir = Path(spill_dir) if spill_dir is not None else None
        self._slots: dict[tuple, ApSegment | _Spilled] = {}
        self._resident: collections.OrderedDict[tuple, None] = collections.OrderedDict()  # oldest first
        self._file = None
        self._end = 0  # bytes written to the spill file
        self._live_bytes = 0  # bytes of it still referenced
        self.spilled_total = 0  # segments written out over the store's life
        self.reads = 0  # spilled segments read back

    # -- mapping -------------------------------------------------------------------------------
    def __getitem__(self, slot: tuple) -> ApSegment:
        v = self._slots[slot]
        if isinstance(v, _Spilled):
            return self._read(v)
        return v

    def __setitem__(self, slot: tuple, seg: ApSegment) -> None:
        old = self._slots.get(slot)
        if isinstance(old, _Spilled):
            self._live_bytes -= old[1]
        self._slots[slot] = seg
        self._resident[slot] = None
        self._resident.move_to_end(slot)
        if self.max_resident is not None:
            while len(self._resident) > self.max_resident:
                self._spill(next(iter(self._resident)))

    def __delitem__(self, slot: tuple) -> None:
        v = self._slots.pop(slot)
        if isinstance(v, _Spilled):
            self._live_bytes -= v[1]
        else:
            del self._resident[slot]

    def __iter__(self) -> Iterator[tuple]:
        return iter(self._slots)

    def __len__(self) -> int:
        return len(self._slots)

    def __contains__(self, slot) -> bool:
        return slot in self._slots

    def peek(self, slot: tuple) -> ApSegment | None:
        """The decoded segment if it is in memory (no read), else None."""
        v = self._slots.get(slot)
        return None if v is None or isinstance(v, _Spilled) else v

    def calib_version(self, slot: tuple) -> int:
        """The slot's calibration version, without reading a spilled segment."""
        v = self._slots[slot]
        return v[2] if isinstance(v, _Spilled) else v.calib_version

    # -- spill ---------------------------------------------------------------------------------
    @property
    def resident(self) -> int:
        return len(self._resident)

    def resident_bytes(self) -> int:
        """Bytes of the decoded segments' arrays in memory (their wire codes)."""
        return sum(self._slots[s].values_q.nbytes + self._slots[s].sigma_q.nbytes for s in self._resident)

    @property
    def spilled(self) -> int:
        return len(self._slots) - len(self._resident)

    def _open(self) -> None:
        if self._spill_dir is not None:
            self._spill_dir.mkdir(parents=True, exist_ok=True)
        fd, path = tempfile.mkstemp(prefix="spill-", suffix=".arrows", dir=self._spill_dir)
        os.unlink(path)  # anonymous: gone with the process, never read by another lifetime
        self._file = os.fdopen(fd, "w+b", buffering=0)
        self._end = 0

    def _spill(self, slot: tuple) -> None:
        seg = self._slots[slot]
        if self._file is None:
            self._open()
        payload = seg.encode()
        self._file.seek(self._end)
        self._file.write(payload)
        self._slots[slot] = _Spilled((self._end, len(payload), seg.calib_version))
        self._end += len(payload)
        self._live_bytes += len(payload)
        del self._resident[slot]
        self.spilled_total += 1

    def _read(self, where: _Spilled) -> ApSegment:
        offset, length, _ = where
        self._file.seek(offset)
        data = self._file.read(length)
        self.reads += 1
        (seg,) = decode_ap(data)
        return seg

    def compact(self) -> None:
        """Rewrite the spill file with the referenced segments only (when over half is garbage)."""
        if self._file is None or self._end <= 2 * self._live_bytes:
            return
        old, self._file = self._file, None
        self._open()
        for slot, v in self._slots.items():
            if isinstance(v, _Spilled):
                old.seek(v[0])
                data = old.read(v[1])
                self._file.write(data)
                self._slots[slot] = _Spilled((self._end, v[1], v[2]))
                self._end += v[1]
        old.close()
        self._live_bytes = self._end

    def stats(self) -> dict:
        return {"segments_resident": self.resident, "segments_spilled": self.spilled,
                "spill_bytes": self._end, "spill_reads": self.reads}

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
