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

The index belongs to one process lifetime (a restarted cloud rebuilds it from its journal).
"""

from __future__ import annotations

import collections
from pathlib import Path

from shared.schema import ApSegment, decode_ap

from cloud.ingest.spill import SpillMap
from cloud.ingest.wire import encode_segment

#: Default for the daemon: ~4 kB each, so ~80 MB of decoded segments at most.
DEFAULT_MAX_RESIDENT = 20_000


def _decode_one(payload: bytes) -> ApSegment:
    (seg,) = decode_ap(payload)
    return seg


#: Segments whose payload a :class:`SegmentEncoder` remembers: more than the stores sharing it spill
#: between two spills of the same segment (one each, in the same order).
ENCODER_MEMO = 64


class SegmentEncoder:
    """A segment's payload (:func:`encode_segment`), encoded once for every store that spills it.

    The aggregator's store and the profile estimator's hold the same segment objects, written in the
    same order, so each spills a segment soon after the other did: the second takes the payload the
    first encoded. Remembered by identity (the segment itself is kept with its payload, so its id is
    not reused while remembered), for the last :data:`ENCODER_MEMO` segments encoded.
    """

    def __init__(self, memo: int = ENCODER_MEMO):
        self.memo = memo
        self._recent: collections.OrderedDict[int, tuple[ApSegment, bytes]] = collections.OrderedDict()
        self.encoded = 0  # segments encoded (the rest of the calls were answered from the memo)

    def __call__(self, seg: ApSegment) -> bytes:
        hit = self._recent.get(id(seg))
        if hit is not None and hit[0] is seg:
            return hit[1]
        payload = encode_segment(seg)
        self.encoded += 1
        self._recent[id(seg)] = (seg, payload)
        if len(self._recent) > self.memo:
            self._recent.popitem(last=False)
        return payload


class SegmentStore(SpillMap):
    """``slot → ApSegment``, at most ``max_resident`` decoded in memory (None: all of them).

    ``encoder``: shared by stores that hold the same segments (:class:`SegmentEncoder`)."""

    def __init__(self, max_resident: int | None = None, spill_dir: str | Path | None = None,
                 encoder: SegmentEncoder | None = None):
        super().__init__(max_resident, spill_dir, encode=encoder if encoder is not None else SegmentEncoder(),
                         decode=_decode_one, tag=lambda seg: seg.calib_version, prefix="segments-")

    def calib_version(self, slot: tuple) -> int:
        """The slot's calibration version, without reading a spilled segment."""
        return self.tag_of(slot)

    def resident_bytes(self) -> int:
        """Bytes of the decoded segments' arrays in memory (their wire codes)."""
        return sum(s.values_q.nbytes + s.sigma_q.nbytes for s in self.resident_values())

    def stats(self) -> dict:
        return {"segments_resident": self.resident, "segments_spilled": self.spilled,
                "spill_bytes": self.disk_bytes(), "spill_reads": self.reads}
