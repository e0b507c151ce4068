"""Chainage alignment of complete passes against the consensus of the others (GNSS bias, odometry stretch).

Each sweep estimates every road pass's alignment against a leave-one-out consensus, centres each
route's maps (the fleet's GNSS errors average out: the consensus frame is the mean of the passes'
frames, :func:`~cloud.road.alignment.centred`) and gives the estimators the re-gridded segments
through the aggregator (:meth:`~cloud.ingest.aggregator.Aggregator.replace_held`), so the next sweep
sees the improved consensus. Rail runs are not aligned: their batches re-key them
(:mod:`cloud.rail.batches`), and the aggregator has one writer per held slot.

Everything here is idle work, done in bounded slices (:class:`Slice`) so that the daemon takes
input between them: a sweep estimates its passes a few at a time, centres each route once every
estimate is in (the frame needs them all), then applies the centred maps a few passes at a time.
A pass recomputed under a new calibration is only noted on ingest (:meth:`ChainageAligner.recomputed`)
and re-gridded with its alignment when the bus is quiet (:meth:`ChainageAligner.reapply_pending`).
A pass that changes between its estimate and its apply (recomputed, or no longer complete) keeps
what it holds: its estimate was made from segments it no longer has, and the acknowledgement that
changed it starts a new series, whose next sweep estimates it afresh among all the others.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from collections.abc import Callable

import numpy as np

from shared.schema import ApSegment
from shared.vehicles import RAIL_MODELS

from cloud.daemon.settings import CloudSettings
from cloud.road.alignment import Alignment, centred, damped, estimate_alignment, realign

PassKey = tuple[str, str]  # (vehicle, pass)


def _slot(s: ApSegment) -> tuple:
    return (s.vehicle_id, s.pass_id, s.route_id, s.tile, s.axle)


class Slice:
    """One bounded piece of idle work: units of work (a pass estimated, applied or re-gridded) go on
    while less than ``budget_s`` of ``clock`` has passed since the slice began, and the first always
    runs, so a slice overruns its budget by at most one unit and every slice makes progress."""

    def __init__(self, clock: Callable[[], float], budget_s: float = math.inf):
        self.clock, self.budget_s = clock, budget_s
        self.t0 = clock() if math.isfinite(budget_s) else 0.0
        self.units = 0

    def more(self) -> bool:
        """Whether another unit fits (the clock is read only for a finite budget)."""
        return self.units == 0 or not math.isfinite(self.budget_s) or self.clock() - self.t0 < self.budget_s

    def spent(self) -> None:
        """A unit of work was done."""
        self.units += 1


def _no_clock() -> float:
    return 0.0  # an unbounded slice never reads its clock


@dataclasses.dataclass(frozen=True)
class _Estimate:
    """A pass's alignment this sweep, and the state of the pass it was estimated from."""

    alignment: Alignment
    slots: list
    extent: tuple[float, float]  # its consensus-frame start and end (m), for centring
    version: tuple[int, int]  # (calibration version, acknowledgements): any recomputation changes it


@dataclasses.dataclass
class _Sweep:
    """A sweep in progress: passes still to estimate, estimates found, then centred maps to apply."""

    todo: collections.deque  # pass keys still to estimate (the passes as the sweep began)
    found: dict = dataclasses.field(default_factory=dict)  # route → {pass: _Estimate}
    new_passes: bool = False  # some complete road pass had no alignment when the sweep looked at it
    apply: collections.deque | None = None  # (route, pass, centred alignment, estimate); None: estimating
    moved: float = 0.0
    regridded: dict = dataclasses.field(default_factory=dict)  # route → whether a pass of it is re-gridded
    stale: int = 0  # passes changed between their estimate and their apply, left to the next sweep


@dataclasses.dataclass(frozen=True)
class SweepResult:
    """What a finished sweep did: the largest change of any pass's implied position (m), or None when
    too few passes align (nothing changed then); whether it found passes with no alignment yet; how
    many passes changed between their estimate and their apply (left to the next sweep)."""

    moved: float | None
    new_passes: bool
    stale: int = 0


def _version(ps) -> tuple[int, int]:
    return (ps.calib_version, ps.times_acked)


class ChainageAligner:
    """The alignment found for each pass, whether passes completed since the last sweep, and the
    sweep in progress."""

    def __init__(self, settings: CloudSettings):
        self.settings = settings
        self.alignments: dict[PassKey, Alignment] = {}
        self.due = False  # passes completed since the last series of sweeps, or the series goes on
        self.sweeps = 0  # sweeps finished in the current series
        self.sweep_limit = 0  # the current series' most sweeps
        self.swept = False  # some sweep of the current series placed passes
        self.renewed = False  # passes were acknowledged during the sweep in progress: a new series follows it
        self.pending: dict[PassKey, None] = {}  # recomputed passes whose alignment is still to re-apply
        #: route → whether its held passes are re-gridded into the fleet's consensus frame (export)
        self.frames: dict[str, bool] = {}
        self.framed: set[str] = set()  # routes where the last sweep aligned enough passes for a frame
        self.looked_at: set[PassKey] = set()  # passes a sweep has tried to align
        self._sweep: _Sweep | None = None

    @property
    def sweeping(self) -> bool:
        """Whether a sweep is part-done (slices of it still to run)."""
        return self._sweep is not None

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

    def renew(self) -> None:
        """Ingest path: passes were acknowledged; a new series of sweeps, sized for new passes, starts
        (after the sweep in progress, if any: that one compared passes without them)."""
        self.due, self.sweeps = True, 0
        self.renewed = self.sweeping

    def recomputed(self, key: PassKey) -> None:
        """Ingest path: a pass came back (recomputed); its alignment is re-applied when idle."""
        if key in self.alignments:
            self.pending[key] = None

    def reapply_pending(self, aggregator, work: Slice | None = None) -> list[PassKey]:
        """Idle work: recomputed passes re-gridded with the alignment found for them, as many as
        ``work`` allows (None: all; the rest stay pending); returns those done."""
        work = work if work is not None else Slice(_no_clock)
        done = []
        while self.pending and work.more():
            key = next(iter(self.pending))
            del self.pending[key]
            self.reapply(aggregator, key)
            done.append(key)
            work.spent()
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

    def begin(self, aggregator) -> None:
        """A sweep starts (if none is in progress) over the passes held now; :meth:`step` runs it."""
        if self._sweep is None:
            self._sweep = _Sweep(todo=collections.deque(aggregator.passes))

    def step(self, aggregator, consensus, work: Slice | None = None) -> SweepResult | None:
        """One slice of a sweep (a new one if none is in progress), as much as ``work`` allows; the
        sweep's result once it has finished, None while it goes on.

        A sweep: every complete road pass's alignment estimated against the leave-one-out consensus,
        then each route's maps centred (once the route has ``align_min_passes``), then the
        estimators given the re-gridded segments (a pass alignment moves too little gets its stored
        segments back). Between slices the bus may change passes: one no longer as estimated when
        its turn to apply comes keeps what it holds (the module's docstring says why)."""
        agg, work = aggregator, work if work is not None else Slice(_no_clock)
        self.begin(agg)
        sw = self._sweep
        while sw.todo and work.more():
            if self._estimate(agg, consensus, sw, sw.todo.popleft()):
                work.spent()
        if sw.todo:
            return None
        if sw.apply is None:
            self._centre(agg, sw)
            if not sw.found:
                self._sweep = None
                return SweepResult(None, sw.new_passes, sw.stale)
        while sw.apply and work.more():
            rid, key, al, est = sw.apply.popleft()
            if not self._current(agg, key, est):
                sw.stale += 1
                continue
            step, moves = self._apply(agg, key, al, est.slots)
            sw.moved, sw.regridded[rid] = max(sw.moved, step), sw.regridded[rid] or moves
            work.spent()
        if sw.apply:
            return None
        self.frames.update(sw.regridded)
        self._sweep = None
        return SweepResult(sw.moved, sw.new_passes, sw.stale)

    def _estimate(self, agg, consensus, sw: _Sweep, key: PassKey) -> bool:
        """The pass's alignment against the consensus of the others, noted in ``sw`` if it is good
        enough; False if the pass is not one to align now (no estimate was made)."""
        s = self.settings
        ps = agg.passes.get(key)
        if ps is None or not ps.acked or not self.aligned_model(ps.model):
            return False
        sw.new_passes = sw.new_passes or key not in self.alignments
        if not ps.slots:
            return False
        self.looked_at.add(key)
        slots = sorted(ps.slots)
        with agg.left_out(consensus, slots):
            snap = consensus.snapshot(ps.route_id).get(ps.route_id)
        raw = [agg.segments[sl] for sl in slots]
        lead = [r for r in raw if r.axle == 1]
        if snap is None or not lead:
            return True
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
            sw.found.setdefault(ps.route_id, {})[key] = _Estimate(al, slots, extent, _version(ps))
        return True

    @staticmethod
    def _current(agg, key: PassKey, est: _Estimate) -> bool:
        """Whether the pass is still complete and holds the segments it was estimated from."""
        ps = agg.passes.get(key)
        return ps is not None and ps.acked and _version(ps) == est.version and sorted(ps.slots) == est.slots

    def _centre(self, agg, sw: _Sweep) -> None:
        """Each route's estimates still current centred on their mean (each route has its own frame:
        the mean of its own passes' errors), queued to apply; routes with fewer than
        ``align_min_passes`` estimates have no frame and are left as they are: they keep the maps
        their last frame applied (and the passes with no estimate in a framed route keep theirs).
        Reverting them instead would make a route whose estimates straddle the threshold alternate
        between re-gridded and stored from one sweep to the next (a reverted pass is estimated
        afresh, undamped), so its series would run to ``align_iterations`` and end on whichever
        state the last sweep happened to leave."""
        found = {rid: {key: est for key, est in f.items() if self._current(agg, key, est)}
                 for rid, f in sw.found.items()}
        sw.stale += sum(len(f) for f in sw.found.values()) - sum(len(f) for f in found.values())
        sw.found = {rid: f for rid, f in found.items() if len(f) >= self.settings.align_min_passes}
        self.framed = set(sw.found)
        sw.apply = collections.deque()
        for rid, f in sw.found.items():
            sw.regridded[rid] = False
            maps = centred([est.alignment for est in f.values()], [est.extent for est in f.values()])
            sw.apply.extend((rid, key, al, est) for (key, est), al in zip(f.items(), maps))

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
