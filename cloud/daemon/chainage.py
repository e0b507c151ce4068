"""Chainage alignment of complete passes against the consensus of the others (GNSS bias, odometry stretch).

Each sweep estimates every road pass's alignment against a leave-one-out consensus, centres each
route's maps (the fleet's GNSS errors average out: the consensus frame is the mean of the passes'
frames, :func:`~cloud.road.alignment.centred`) and gives the estimators the re-gridded segments
through the aggregator (:meth:`~cloud.ingest.aggregator.Aggregator.replace_held`), so the next sweep
sees the improved consensus. Rail runs are not aligned: their batches re-key them
(:mod:`cloud.rail.batches`), and the aggregator has one writer per held slot.

Everything here is idle work: a pass recomputed under a new calibration is only noted on ingest
(:meth:`ChainageAligner.recomputed`) and re-gridded with its alignment when the bus is quiet
(:meth:`ChainageAligner.reapply_pending`).
"""

from __future__ import annotations

import numpy as np

from shared.schema import ApSegment
from shared.vehicles import RAIL_MODELS

from cloud.daemon.settings import CloudSettings
from cloud.road.alignment import Alignment, centred, damped, estimate_alignment, realign

PassKey = tuple[str, str]  # (vehicle, pass)


def _slot(s: ApSegment) -> tuple:
    return (s.vehicle_id, s.pass_id, s.route_id, s.tile, s.axle)


class ChainageAligner:
    """The alignment found for each pass, and whether passes completed since the last sweep."""

    def __init__(self, settings: CloudSettings):
        self.settings = settings
        self.alignments: dict[PassKey, Alignment] = {}
        self.due = False  # passes completed since the last series of sweeps, or the series goes on
        self.sweeps = 0  # sweeps run in the current series
        self.sweep_limit = 0  # the current series' most sweeps
        self.swept = False  # some sweep of the current series placed passes
        self.pending: dict[PassKey, None] = {}  # recomputed passes whose alignment is still to re-apply
        #: route → whether its held passes are re-gridded into the fleet's consensus frame (export)
        self.frames: dict[str, bool] = {}
        self.framed: set[str] = set()  # routes where the last sweep aligned enough passes for a frame
        self.looked_at: set[PassKey] = set()  # passes a sweep has tried to align

    @staticmethod
    def aligned_model(model: str) -> bool:
        """Whether passes of this vehicle model are aligned (road vehicles; rail runs are re-keyed)."""
        return model not in RAIL_MODELS

    def placed(self, key: PassKey, model: str, route_id: str) -> bool:
        """Whether a pass may teach the calibration: aligned, of a model that is never aligned, or
        looked at by a sweep on a route where too few passes align to define a fleet frame (there the
        reported chainage is all there is: too short, too smooth or too few passes yet)."""
        return key in self.alignments or not self.aligned_model(model) or (
            key in self.looked_at and route_id not in self.framed)

    def recomputed(self, key: PassKey) -> None:
        """Ingest path: a pass came back (recomputed); its alignment is re-applied when idle."""
        if key in self.alignments:
            self.pending[key] = None

    def reapply_pending(self, aggregator) -> list[PassKey]:
        """Idle work: every recomputed pass re-gridded with the alignment found for it; returns them."""
        done = list(self.pending)
        self.pending.clear()
        for key in done:
            self.reapply(aggregator, key)
        return done

    def _within(self, al: Alignment, raw: list[ApSegment]) -> bool:
        """Whether ``al`` moves the pass by less than ``align_apply_m`` everywhere: within what
        alignment can resolve, where re-gridding would only blur the pass."""
        x_span = np.array([al.x_ref_m, max(r.end_index for r in raw) * raw[0].spacing_m])
        return np.max(np.abs(al.true_to_reported(x_span) - x_span)) < self.settings.align_apply_m

    def reapply(self, aggregator, key: PassKey) -> None:
        """A recomputed pass keeps the alignment found for it (until the next sweep): the estimators
        get its stored segments re-gridded."""
        al = self.alignments.get(key)
        ps = aggregator.passes.get(key)
        if al is None or ps is None:
            return
        slots = sorted(ps.slots)
        raw = [aggregator.segments[sl] for sl in slots]
        if self._within(al, raw):
            return
        aligned = {_slot(s): s for s in realign(raw, al)}
        for sl in slots:
            if sl in aligned:
                aggregator.replace_held(sl, aligned[sl])

    def has_new_passes(self, aggregator) -> bool:
        """Some acknowledged road pass has no alignment yet."""
        return any(key not in self.alignments for key, ps in aggregator.passes.items()
                   if ps.acked and self.aligned_model(ps.model))

    def sweep(self, aggregator, consensus) -> float | None:
        """One sweep, the estimators given the re-gridded segments (a pass alignment moves too little
        gets its stored segments back); the largest change of any pass's implied position (m), or
        None when too few passes align (nothing changed then)."""
        s, agg = self.settings, aggregator
        found: dict[str, dict[PassKey, tuple[Alignment, list]]] = {}
        for key, ps in agg.passes.items():
            if not ps.acked or not ps.slots or not self.aligned_model(ps.model):
                continue
            self.looked_at.add(key)
            slots = sorted(ps.slots)
            with agg.left_out(consensus, slots):
                snap = consensus.snapshot(ps.route_id).get(ps.route_id)
            raw = [agg.segments[sl] for sl in slots]
            lead = [r for r in raw if r.axle == 1]
            if snap is None or not lead:
                continue
            lo, hi = min(r.start_index for r in lead), max(r.end_index for r in lead)
            ap = np.full(hi - lo, np.nan)
            for r in lead:
                ap[r.start_index - lo : r.end_index - lo] = r.values
            al = estimate_alignment(np.arange(lo, hi) * lead[0].spacing_m, ap, snap.chainage_m, snap.elevation_m,
                                    max_stretch=s.align_max_stretch)
            if al is not None and al.score >= s.align_min_score:
                al = damped(self.alignments.get(key), al, snap.chainage_m, snap.n_passes, lo * lead[0].spacing_m,
                            hi * lead[0].spacing_m)
                extent = (float(al.reported_to_true(lo * lead[0].spacing_m)),
                          float(al.reported_to_true(hi * lead[0].spacing_m)))
                found.setdefault(ps.route_id, {})[key] = (al, slots, extent)
        # Each route has its own frame: the mean of its own passes' errors.
        found = {rid: f for rid, f in found.items() if len(f) >= s.align_min_passes}
        self.framed = set(found)
        if not found:
            return None
        moved = 0.0
        for rid, f in found.items():
            regridded = False
            for (key, (_, slots, _)), al in zip(f.items(), centred([al for al, _, _ in f.values()],
                                                                   [extent for _, _, extent in f.values()])):
                step, moves = self._apply(agg, key, al, slots)
                moved, regridded = max(moved, step), regridded or moves
            self.frames[rid] = regridded
        return moved

    def _apply(self, agg, key: PassKey, al: Alignment, slots: list) -> tuple[float, bool]:
        """Hold the pass re-gridded by ``al`` (or as stored, if ``al`` moves it too little); returns
        how far its implied position moved since the last sweep (m) and whether it is re-gridded."""
        old = self.alignments.get(key)
        x_probe = np.array([al.x_ref_m, al.x_ref_m + 100.0])
        moved = float(np.max(np.abs(al.true_to_reported(x_probe) - (
            old.true_to_reported(x_probe) if old is not None else x_probe))))
        self.alignments[key] = al
        raw = [agg.segments[sl] for sl in slots]
        if self._within(al, raw):
            for sl, r in zip(slots, raw):
                if agg.held.get(sl) is not r:
                    agg.replace_held(sl, r)
            return moved, False
        aligned = {_slot(r): r for r in realign(raw, al)}
        for sl in slots:
            new = aligned.get(sl)
            if new is not None:
                agg.replace_held(sl, new)
        return moved, True
