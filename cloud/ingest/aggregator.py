"""The aggregator's state machine: validated segments in, estimator updates and pass acks out.

No transport here: the node hands it payloads and publishes what it returns, so every rule
(reject and count, supersede by calibration version, acknowledge a complete pass) is testable
without a network.

The aggregator is the one writer of what the estimators hold. Besides ingest, three things change
a held segment, each through a method here so that retraction stays exact: a re-keyed version in
place of the edge's (:meth:`Aggregator.replace_held`, :meth:`Aggregator.drop_held`: chainage
alignment, rail re-keying), the fused form one estimator takes in its place
(:meth:`Aggregator.fuse`: the continuous-time AP of the profile posterior) and a leave-one-out
view of an estimator (:meth:`Aggregator.left_out`).
"""

from __future__ import annotations

import collections
import collections.abc
import contextlib
import dataclasses
import logging
import math
import pickle
from pathlib import Path

from shared.registry import Site
from shared.schema import LEGACY_SAMPLE_INTERVAL_S, Ack, ApSegment, DecodeError, decode_ap, decode_pass_done

from cloud.ingest.estimator import Estimator
from cloud.ingest.segment_store import SegmentStore
from cloud.ingest.spill import SpillMap

log = logging.getLogger(__name__)

MAX_ROUTE_OVERHANG_M = 50.0  # a segment may start at most this far beyond the route's end
#: Rejections of a well-formed segment from its own vehicle: they still complete the pass.
PASS_ACCOUNTED = frozenset({"beyond_route", "impossible_speed", "grid_mismatch", "implausible_ap"})
#: Passes whose bookkeeping stays in memory (the daemon's default; a few kB each), and the least
#: allowed: a pass being updated must not be spilled while its caller still holds it.
DEFAULT_MAX_RESIDENT_PASSES = 5_000
MIN_RESIDENT_PASSES = 2


def on_route(seg: ApSegment) -> ApSegment | None:
    """The part of ``seg`` at chainage >= 0 (what the estimators fuse), None if there is none.

    Segments may start before the route (a rail vehicle's trailing wheels when its log starts):
    those points are kept in ``Aggregator.segments`` for re-running the pass, not fused."""
    if seg.start_index >= 0:
        return seg
    k = -seg.start_index
    if k >= seg.n:
        return None
    t_first = seg.t_first + (seg.t_last - seg.t_first) * k / max(seg.n - 1, 1)
    return dataclasses.replace(seg, values_q=seg.values_q[k:], sigma_q=seg.sigma_q[k:], start_index=0,
                               t_first=t_first)


@dataclasses.dataclass
class PassState:
    vehicle_id: str
    route_id: str
    calib_version: int = -1
    seqs: set = dataclasses.field(default_factory=set)
    expected: int | None = None
    acked: bool = False
    model: str = ""
    slots: set = dataclasses.field(default_factory=set)  # the pass's keys in Aggregator.segments
    refused: set = dataclasses.field(default_factory=set)  # seqs rejected as implausible (still counted)
    params: dict | None = None  # the vehicle parameters the edge computed the pass with (its pass-done says)
    sample_interval_s: float = LEGACY_SAMPLE_INTERVAL_S  # s: the step the edge inverted the pass at (ditto)
    done_payload: bytes | None = None  # the accepted pass-done, as received (the journal's compaction keeps it)
    times_acked: int = 0  # acknowledgements so far (1: its first; more: recomputed under new calibrations)


def _pickle(ps: PassState) -> bytes:
    return pickle.dumps(ps, protocol=pickle.HIGHEST_PROTOCOL)


class Held(collections.abc.MutableMapping):
    """What the estimators hold for each slot: the stored segment itself (nothing kept twice, and
    spilled with it) or, once replaced (chainage alignment), the replacement. A slot is briefly
    absent between a release and what replaces it; iteration follows the store's order."""

    def __init__(self, store: SegmentStore):
        self.store = store
        self.other: dict[tuple, ApSegment] = {}  # replacements (aligned versions), kept in memory
        self.absent: set[tuple] = set()

    def __getitem__(self, slot):
        if slot in self.absent or slot not in self.store:
            raise KeyError(slot)
        other = self.other.get(slot)
        return other if other is not None else self.store[slot]

    def __setitem__(self, slot, seg) -> None:
        self.absent.discard(slot)
        if seg is self.store.peek(slot):
            self.other.pop(slot, None)
        else:
            self.other[slot] = seg

    def __delitem__(self, slot) -> None:
        if slot in self.absent or slot not in self.store:
            raise KeyError(slot)
        self.other.pop(slot, None)
        self.absent.add(slot)

    def hide(self, slot) -> None:
        """Nothing held for ``slot`` (stored or not)."""
        self.other.pop(slot, None)
        self.absent.add(slot)

    def forget(self, slot) -> None:
        """The store dropped the slot."""
        self.absent.discard(slot)
        self.other.pop(slot, None)

    def __contains__(self, slot) -> bool:
        return slot in self.store and slot not in self.absent

    def __iter__(self):
        return (sl for sl in self.store if sl not in self.absent)

    def __len__(self) -> int:
        return len(self.store) - len(self.absent)


class Aggregator:
    """Keeps the accepted segments (latest calibration version of each) and the estimators fed."""

    def __init__(self, site: Site, estimators: list[Estimator], foreign_routes: frozenset[str] = frozenset(),
                 store: SegmentStore | None = None, max_resident_passes: int | None = None,
                 spill_dir: str | Path | None = None, fused: Estimator | None = None):
        self.site = site
        self.estimators = estimators
        # The estimator that may hold a held segment's fused form (same identity) in its place; it
        # keeps what it holds by identity in ``segments``, as GmrfProfile does.
        if fused is not None and not any(fused is est for est in estimators):
            raise ValueError("fused: expected one of the estimators")
        self.fused = fused
        self.routes = {r.id: r.length_m for r in site.routes}
        self.foreign_routes = foreign_routes  # other shards' routes: their pass-dones are ignored here
        self.foreign = 0
        self.vehicle_routes: dict[str, collections.Counter] = {}  # sharded: vehicle → route → passes
        # Sharded: every pass-done seen, own routes' and others' ((vehicle, pass) → route), so that a
        # repeated one is not counted twice; on disk beyond the window, as the passes below.
        self._pass_route = SpillMap(max_resident_passes, spill_dir, str.encode, bytes.decode, prefix="routes-")
        # (vehicle, pass, route, tile, axle) → segment; a bounded store spills the oldest to disk.
        self.segments: SegmentStore = store if store is not None else SegmentStore()
        # What the estimators hold for each slot: the segment itself, or its chainage-aligned version.
        self.held = Held(self.segments)
        # (vehicle, pass) → its state, for every pass ever seen (idempotence, exact retraction on a
        # recalibration): at most ``max_resident_passes`` in memory (the most recently used; a read
        # brings a pass back), the rest on disk, so memory does not grow with the passes.
        if max_resident_passes is not None and max_resident_passes < MIN_RESIDENT_PASSES:
            raise ValueError(f"max_resident_passes: expected >= {MIN_RESIDENT_PASSES} or None, "
                             f"got {max_resident_passes}")
        self.passes: SpillMap = SpillMap(max_resident_passes, spill_dir, _pickle, pickle.loads, promote=True,
                                         prefix="passes-")
        self.models: set[str] = set()  # vehicle models of the passes (e.g. whether any is a rail run)
        # Acknowledged passes per (vehicle, calibration version), kept as passes change state, so a
        # status ("how many passes are current") costs O(vehicles), not O(passes), per acknowledgement.
        self.acked: collections.Counter[tuple[str, int]] = collections.Counter()
        self.rejected: collections.Counter[str] = collections.Counter()
        self.accepted = 0
        self.updates = 0  # estimator updates applied (for views: "something changed")
        self._grids: dict[tuple[str, float], bool] = {}  # (route, spacing) → every estimator accepts it

    # -- input ---------------------------------------------------------------------------------
    def on_segment(self, payload: bytes, key_vehicle: str | None = None) -> list[Ack]:
        """An AP payload: one segment or a batch of them (``ap_batch``), each applied on its own."""
        try:
            segments = decode_ap(payload)
        except DecodeError as e:
            return self._reject(e.reason, str(e))
        acks = []
        for seg in segments:
            acks.extend(self.apply(seg, key_vehicle))
        return acks

    def apply(self, seg: ApSegment, key_vehicle: str | None = None) -> list[Ack]:
        """Check a decoded segment and fuse it (or count why not); returns the acks it completes."""
        reason = self._check(seg, key_vehicle)
        if reason:
            self._reject(reason, f"{seg.vehicle_id}/{seg.pass_id} tile {seg.tile}")
            if reason in PASS_ACCOUNTED and seg.route_id in self.routes:
                # The vehicle did send it: the pass can complete without it (acknowledged with fewer
                # accepted segments) instead of waiting forever for a segment that will not be fused.
                ps = self._pass_of(seg)
                if seg.calib_version == ps.calib_version:
                    ps.refused.add(seg.seq)
                return self._maybe_ack(seg.vehicle_id, seg.pass_id)
            return []
        slot = (seg.vehicle_id, seg.pass_id, seg.route_id, seg.tile, seg.axle)
        if slot in self.segments:
            old_version = self.segments.calib_version(slot)  # (no read of a spilled segment)
            if old_version > seg.calib_version:
                return self._reject("stale_calibration", f"{slot} v{seg.calib_version} < v{old_version}")
            if old_version == seg.calib_version:
                self.rejected["duplicate"] += 1  # idempotent: a redelivery changes nothing
                return self._maybe_ack(seg.vehicle_id, seg.pass_id)
            self._release(slot)
        self.segments[slot] = seg
        held = on_route(seg)
        if held is not None:
            self.held[slot] = held
            for est in self.estimators:
                est.update(held)
        else:
            self.held.hide(slot)  # the estimators hold nothing of it
        self.accepted += 1
        self.updates += 1
        ps = self._pass_of(seg)
        ps.slots.add(slot)
        if seg.calib_version == ps.calib_version:
            ps.seqs.add(seg.seq)
        return self._maybe_ack(seg.vehicle_id, seg.pass_id, ps)

    def _pass_of(self, seg: ApSegment) -> PassState:
        """The pass ``seg`` belongs to; a segment under a newer calibration starts the pass afresh
        (unacknowledged, its segments counted again from that version)."""
        ps = self._pass(seg.vehicle_id, seg.pass_id, seg.route_id)
        if seg.calib_version > ps.calib_version:
            self._unack(ps)
            ps.calib_version, ps.seqs, ps.refused, ps.expected = seg.calib_version, set(), set(), None
        return ps

    def _pass(self, vehicle_id: str, pass_id: str, route_id: str) -> PassState:
        """The pass's state, new if it has none (made only then: a state is a few sets)."""
        key = (vehicle_id, pass_id)
        ps = self.passes.get(key)
        if ps is None:
            ps = self.passes[key] = PassState(vehicle_id, route_id)
        return ps

    def on_pass_done(self, payload: bytes) -> list[Ack]:
        try:
            done = decode_pass_done(payload)
        except DecodeError as e:
            return self._reject(e.reason, str(e))
        if self.foreign_routes and (done.vehicle_id, done.pass_id) not in self._pass_route:
            # A shard counts every vehicle's passes per route, its own and the others': the shard
            # with most of a vehicle's passes calibrates it (cloud.daemon.sharding).
            self._pass_route[(done.vehicle_id, done.pass_id)] = done.route_id
            self.vehicle_routes.setdefault(done.vehicle_id, collections.Counter())[done.route_id] += 1
        if done.route_id in self.foreign_routes:
            self.foreign += 1
            return []
        if done.route_id not in self.routes:
            return self._reject("unknown_route", done.route_id)
        ps = self._pass(done.vehicle_id, done.pass_id, done.route_id)
        if done.calib_version < ps.calib_version:
            return self._reject("stale_calibration", f"done {done.pass_id} v{done.calib_version}")
        if done.calib_version > ps.calib_version:
            self._unack(ps)
            ps.calib_version, ps.seqs, ps.refused = done.calib_version, set(), set()
        ps.expected = done.n_segments
        ps.model = done.vehicle_model or ps.model
        self.models.add(ps.model)
        ps.done_payload = bytes(payload)
        ps.params = dict(done.params) if done.params is not None else None
        ps.sample_interval_s = done.sample_interval_s
        return self._maybe_ack(done.vehicle_id, done.pass_id, ps)

    def repeat_ack(self, payload: bytes) -> Ack | None:
        """The acknowledgement again, if ``payload`` is the pass-done of a pass acknowledged already.

        An edge sends a pass again only while it has not heard its acknowledgement (one published
        while a router was down is lost), so the acknowledgement is sent again, changing nothing."""
        try:
            done = decode_pass_done(payload)
        except DecodeError:
            return None
        ps = self.passes.get((done.vehicle_id, done.pass_id))
        if ps is None or not ps.acked or ps.calib_version != done.calib_version:
            return None
        return Ack(vehicle_id=done.vehicle_id, pass_id=done.pass_id, n_segments_accepted=len(ps.seqs),
                   calib_version=ps.calib_version)

    # -- rules ---------------------------------------------------------------------------------
    def _check(self, seg: ApSegment, key_vehicle: str | None) -> str | None:
        if key_vehicle is not None and key_vehicle != seg.vehicle_id:
            return "key_mismatch"
        length = self.routes.get(seg.route_id)
        if length is None:
            return "unknown_route"
        if not -MAX_ROUTE_OVERHANG_M <= seg.start_index * seg.spacing_m <= length + MAX_ROUTE_OVERHANG_M:
            return "beyond_route"
        if not (0.5 <= seg.speed_mps <= 100.0):
            return "impossible_speed"
        if not self._accepted_grid(seg):
            return "grid_mismatch"
        lo, hi = seg.value_range
        if not (math.isfinite(hi) and max(-lo, hi) < 1.0):
            return "implausible_ap"
        return None

    def _accepted_grid(self, seg: ApSegment) -> bool:
        """Whether every estimator accepts the segment's route and grid (a function of the two alone:
        remembered per pair)."""
        grid = (seg.route_id, seg.spacing_m)
        ok = self._grids.get(grid)
        if ok is None:
            ok = self._grids[grid] = all(getattr(est, "accepts", lambda s: True)(seg) for est in self.estimators)
        return ok

    def _reject(self, reason: str, detail: str) -> list[Ack]:
        n = self.rejected[reason] = self.rejected[reason] + 1
        if not n & (n - 1):  # logged at the 1st, 2nd, 4th, 8th … of a reason: a flood costs no log per message
            log.warning("rejected segment (%s, %d so far): %s", reason, n, detail)
        return []

    def _release(self, slot: tuple) -> None:
        held = self.held.pop(slot, None)
        if held is not None:
            for est in self.estimators:
                est.retract(held)

    def drop_held(self, slot: tuple) -> None:
        """The estimators stop holding ``slot`` (the stored segment stays: e.g. re-keyed off the route)."""
        self._release(slot)

    def replace_held(self, slot: tuple, seg: ApSegment) -> None:
        """Give the estimators ``seg`` (a chainage-aligned or re-keyed version, or the stored segment
        again) in place of what they hold; a ``seg`` off the route leaves them as they are."""
        if not all(getattr(est, "accepts", lambda s: True)(seg) for est in self.estimators) or \
                seg.start_index * seg.spacing_m > self.routes.get(seg.route_id, 0.0):
            return  # moved off the route: keep what the estimators hold
        seg = on_route(seg)
        self._release(slot)
        if seg is None:
            return
        self.held[slot] = seg
        for est in self.estimators:
            est.update(seg)

    def fuse(self, slot: tuple, seg: ApSegment) -> None:
        """The fused estimator takes ``seg``, the fused form of what is held for ``slot`` (same
        identity), in its place; the others keep the held segment. A later release retracts it
        exactly, by identity, as it would the held segment."""
        if self.fused is None:
            raise ValueError("fuse: this aggregator has no fused estimator")
        if slot not in self.held:
            raise KeyError(slot)
        self.fused.update(seg)

    def as_fused(self, segs) -> list[ApSegment]:
        """``segs`` (held segments) as the fused estimator holds them: the fused form where one was
        given (:meth:`fuse`), else the segment itself."""
        if self.fused is None:
            return list(segs)
        store = self.fused.segments
        return [store.get(seg.identity) if seg.identity in store else seg for seg in segs]

    @contextlib.contextmanager
    def left_out(self, estimator: Estimator, slots):
        """``estimator`` without what it holds for ``slots`` while the block runs (a leave-one-out
        view), then holding it again."""
        held = [self.held[sl] for sl in slots if sl in self.held]
        for h in held:
            estimator.retract(h)
        try:
            yield estimator
        finally:
            for h in held:
                estimator.update(h)

    def _maybe_ack(self, vehicle_id: str, pass_id: str, ps: PassState | None = None) -> list[Ack]:
        """The pass's acknowledgement if it has just become complete (``ps``: its state, if the
        caller has it at hand)."""
        if ps is None:
            ps = self.passes.get((vehicle_id, pass_id))
        if ps is None or ps.acked or ps.expected is None or \
                (len(ps.seqs | ps.refused) if ps.refused else len(ps.seqs)) < ps.expected:
            return []
        ps.acked = True
        ps.times_acked += 1
        self.acked[(vehicle_id, ps.calib_version)] += 1
        # The pass is complete under its newest calibration: any of its segments still held from an
        # older one (a tile the recomputation no longer produces) is superseded too.
        for slot in [sl for sl in ps.slots if self.segments.calib_version(sl) < ps.calib_version]:
            self._release(slot)
            del self.segments[slot]
            self.held.forget(slot)
            ps.slots.discard(slot)
        return [Ack(vehicle_id=vehicle_id, pass_id=pass_id, n_segments_accepted=len(ps.seqs),
                    calib_version=ps.calib_version)]

    def _unack(self, ps: PassState) -> None:
        if ps.acked:
            ps.acked = False
            key = (ps.vehicle_id, ps.calib_version)
            self.acked[key] -= 1
            if not self.acked[key]:
                del self.acked[key]

    def stats(self) -> dict:
        return {
            "accepted": self.accepted,
            "rejected": dict(self.rejected),
            "segments_held": len(self.segments),
            **self.segments.stats(),
            "passes": len(self.passes),
            "passes_complete": self.acked.total(),
            "foreign_passes": self.foreign,
        }
