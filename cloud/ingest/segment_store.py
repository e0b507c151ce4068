"""The aggregator's segments with a bounded number in memory: the rest spilled to disk, exact.

The aggregator keeps every accepted segment because a later recalibration of its pass must retract
it from the estimators exactly (and the long-wave band, alignment and bridges read them). Memory
must not grow with the passes, so at most ``max_resident`` segments stay decoded in memory; older
ones are written, as their wire payload (Arrow IPC, lossless: the estimators work on the wire
codes), to an on-disk index (:class:`cloud.ingest.spill.SpillMap`), and a read of such a slot decodes it
back — the same values, so retraction stays exact and every export equals the unbounded store's.

Nothing per spilled slot stays in memory: its key, its calibration version (kept beside the payload
so that superseding a slot needs no read) and its place in the iteration order are on disk too.
Iteration order is that of a ``dict`` with the same writes, so anything summed over the segments
sums in the same order whether they are resident or not.

An estimator that keeps the segments it holds (the profile posterior: exact retraction, the per-pass
drift) keeps them in a :class:`HeldSegments` over the store: bounded the same way, and on disk only
where it holds something other than the stored segment itself (one payload per segment on disk).

The index belongs to one process lifetime (a restarted cloud rebuilds it from its journal).
"""

from __future__ import annotations

from pathlib import Path

from shared.schema import ApSegment, decode_ap

from cloud.ingest.spill import SpillMap

#: Default for the daemon: ~4 kB each, so ~80 MB of decoded segments at most.
DEFAULT_MAX_RESIDENT = 20_000


def _decode_one(payload: bytes) -> ApSegment:
    (seg,) = decode_ap(payload)
    return seg


def _encode_one(seg: ApSegment) -> bytes:
    return seg.encode()


def _code_bytes(segments) -> int:
    return sum(s.values_q.nbytes + s.sigma_q.nbytes for s in segments)


class SegmentStore(SpillMap):
    """``slot → ApSegment``, at most ``max_resident`` decoded in memory (None: all of them)."""

    def __init__(self, max_resident: int | None = None, spill_dir: str | Path | None = None):
        super().__init__(max_resident, spill_dir, encode=_encode_one, decode=_decode_one,
                         tag=lambda seg: seg.calib_version, prefix="segments-")

    def calib_version(self, slot: tuple) -> int:
        """The slot's calibration version, without reading a spilled segment."""
        return self.tag_of(slot)

    def resident_bytes(self) -> int:
        """Bytes of the decoded segments' arrays in memory (their wire codes)."""
        return _code_bytes(self.resident_values())

    def stats(self) -> dict:
        return {"segments_resident": self.resident, "segments_spilled": self.spilled,
                "spill_bytes": self.disk_bytes(), "spill_reads": self.reads}


#: What a :class:`HeldSegments` row holds for a value that is the store's own segment of its slot.
_IN_STORE = b"\0"


class HeldSegments(SpillMap):
    """``identity → ApSegment``: the segments an estimator holds (``GmrfProfile.segments``), bounded
    like the aggregator's ``store``, with nothing the store holds written twice.

    The aggregator is the one writer of held segments: almost every value here is the very segment
    the store holds for its slot (``identity[:5]``). Such a value spills as a reference (its row:
    its key, its place in this map's order and a one-byte marker, no payload) and is read back from
    the store, which keeps it until the aggregator releases the slot, and the estimator with it
    (:meth:`cloud.ingest.aggregator.Aggregator.apply` releases before it replaces). Any other value
    (a chainage-aligned replacement, a fused form, the on-route part of a segment) spills whole.
    Iteration follows this map's own writes, as a ``dict``'s would: the estimator's sums keep their order.
    """

    def __init__(self, store: SegmentStore, max_resident: int | None = None, spill_dir: str | Path | None = None):
        super().__init__(max_resident, spill_dir, encode=_encode_one, decode=_decode_one, prefix="held-")
        self.store = store
        # Resident keys whose value was the store's segment of its slot when written (until their
        # row is written: a later write decides afresh).
        self._in_store: set = set()

    def __setitem__(self, key, value) -> None:
        if value is self.store.peek(key[:5]):
            self._in_store.add(key)
        else:
            self._in_store.discard(key)
        super().__setitem__(key, value)

    def __delitem__(self, key) -> None:
        self._in_store.discard(key)
        super().__delitem__(key)

    def encode_entry(self, key, value) -> bytes:
        if key in self._in_store:
            self._in_store.discard(key)
            return _IN_STORE
        return super().encode_entry(key, value)

    def resident_bytes(self) -> int:
        """Bytes of the resident segments' arrays (their wire codes; shared with the store where it holds them too)."""
        return _code_bytes(self.resident_values())

    def decode_entry(self, key, blob: bytes):
        if blob != _IN_STORE:
            return super().decode_entry(key, blob)
        seg = self.store[key[:5]]
        if seg.identity != key:  # the store replaced the slot while this map held it: a broken rule
            raise RuntimeError(f"held segment {key}: the store holds {seg.identity} in its place")
        return seg
