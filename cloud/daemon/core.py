"""The cloud's transport-free core: message handlers and the idle work the daemon runs when the bus is quiet.

:class:`Cloud` takes payloads (``on_segment``, ``on_done``, ``on_calibration``) and publishes
through the ``publish`` callable it is given; its clock is given too, so every rule is testable
in process with a clock the test moves. The aggregator is the one writer of what the estimators
hold; alignment, the continuous-time correction and rail re-keying all go through it. Domains
return what changed (the bridge monitor and the rail batches return alarms, rail its re-keyed
segments), and the core applies and publishes it.
"""

from __future__ import annotations

import collections
import json
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow as pa

from shared import keys
from shared.registry import Site
from shared.schema import decode_alarm
from shared.vehicles import RAIL_MODELS

from cloud.bridge.estimator import BridgeSettings
from cloud.bridge.monitor import CLEARED, BridgeMonitor, catch_up_steps
from cloud.bridge.vehicle_error import class_log_sd, fit_log_sd
from cloud.daemon.chainage import ChainageAligner, Slice
from cloud.daemon.epochs import Epochs
from cloud.daemon.queries import TILE_M, bridge_state, tile_points, tile_state
from cloud.daemon.settings import CloudSettings
from cloud.daemon.sharding import Ownership, shard_site
from cloud.coordinates import bridges_with_coordinates, roughness_geojson, roughness_with_coordinates, write_geojson
from cloud.export import (FLEET_FRAME, REGISTRY_FRAME, bridge_bearings_table, bridge_elements_table,
                          bridge_summary_table, profile_draws, profile_table, roughness_table, track_quality_table,
                          vehicles_table, write_export)
from cloud.ingest.aggregator import Aggregator
from cloud.ingest.segment_store import HeldSegments, SegmentStore
from cloud.ingest.spill import SpillMap
from cloud.road.continuous import CONTINUOUS_MODELS, continuous_segments
from cloud.road.fleet_calibration import FleetCalibrator
from cloud.road.gmrf_profile import GmrfProfile
from cloud.road.long_wave import drift_of, with_long_wave_band
from cloud.road.mean_profile import MeanProfile

log = logging.getLogger("driveby.cloud")
VIEW_IRI_DRAWS = 20  # profile draws behind the view's IRI bars at every pass (the export's take 100)
AP_KEY_MEMO = 4096  # AP keys whose vehicle is remembered (a key repeats for every segment of its tile)



class Cloud:
    """One cloud aggregator: the aggregator, its estimators, calibration, bridges, rail and the view.

    Parameters
    ----------
    net : the Zenoh key space's network name (keys of what is published).
    site : the registry.
    publish : ``publish(key, payload)``, called for acks, status, calibrations and alarms.
    settings : how it behaves.
    view : a :class:`cloud.view.View` to log to, or None.
    clock : monotonic seconds (scheduling and calibration waits only: estimates never read it).
    node_id : this cloud's id (its status key).
    """

    def __init__(self, net: str, site: Site, publish: Callable[[str, bytes], None],
                 settings: CloudSettings = CloudSettings(), view=None, clock: Callable[[], float] = time.monotonic,
                 node_id: str = "cloud-1"):
        s = self.settings = settings
        site, foreign = shard_site(site, s.shard)
        self.net, self.site, self.publish, self.view, self.clock, self.node_id = net, site, publish, view, clock, node_id
        routes = {r.id: r.length_m for r in site.routes}
        self.profile = GmrfProfile(routes, s.spacing_m, drift_knot_m=s.drift_knot_m)
        # The vehicle step compares against the data alone (the flat-prior limit of the posterior):
        # the random-walk prior's smoothing of the shortest wavelengths would bias tyre stiffness.
        self.consensus = MeanProfile(routes, s.spacing_m)
        # Segments and passes beyond the resident bounds live on disk, read back when needed, so
        # memory does not grow with the passes.
        self.aggregator = Aggregator(site, [self.profile, self.consensus], foreign_routes=foreign,
                                     store=SegmentStore(s.max_resident, s.spill_dir),
                                     max_resident_passes=s.max_resident_passes, spill_dir=s.spill_dir,
                                     fused=self.profile if s.continuous_aps else None)
        if s.max_resident is not None and isinstance(getattr(self.profile, "segments", None), dict):
            # The profile estimator keeps each segment it holds too (exact retraction, the per-pass
            # drift assembled at snapshot time): bounded the same way, and on disk only where it is
            # not the aggregator's stored segment itself (which the store keeps, once).
            self.profile.segments = HeldSegments(self.aggregator.segments, s.max_resident, s.spill_dir)
        self.calibrator = FleetCalibrator(site, self.consensus) if s.calibration == "fleet" else None
        if self.calibrator is not None:
            self.calibrator.continuous_aps = s.continuous_aps
        self.epochs = Epochs(self.calibrator, s, clock)
        self.ownership = Ownership(s.shard, self.aggregator.vehicle_routes)
        self.aligner = ChainageAligner(s)
        self._unfused: dict[tuple[str, str], None] = {}  # acknowledged passes whose correction is due (ordered)
        #: the round whose vehicle steps are being taken in slices: (its segments' key, its consensus)
        self._round: tuple[str, MeanProfile] | None = None
        #: the vehicle table of the last round for the view, being built in slices: (its key, the steps)
        self._view_table: tuple[tuple, object] | None = None
        self._table: tuple[tuple, list[dict]] | None = None  # the last vehicle table built: (its key, rows)
        #: ``record(kind, payload)``: the daemon's journal for the cloud's own decisions (an epoch's start,
        #: the calibrator's state after a round, an alarm), written before what they cause is published.
        self.record: Callable[[str, bytes], None] | None = None
        self.vehicles: dict[str, dict] = collections.defaultdict(
            lambda: {"passes": 0, "last_pass": "", "calib_version": 0, "segments": 0})
        self.passes_complete = 0
        self._ap_keys: dict[str, str] = {}  # valid AP key → its vehicle (parsed once: up to AP_KEY_MEMO)
        self.status_due = False  # acks were published since the last status
        # Bridges are fed and estimated when the bus is quiet (maybe_estimate_bridges), never per segment.
        self.bridges = BridgeMonitor(site, s.bridge)
        self.bridge_sync_due = False  # passes were acknowledged (or re-keyed) since the last sync
        self.alarms: dict[str, bytes] = {}  # bridge → the last alarm message published (raised or cleared)
        self._bridge_cost_s = 0.0  # how long the last bridge update took
        self._bridge_done_at = -math.inf  # when it ended
        self._status_at = -math.inf  # when the status was last published
        self.rail = None
        if any(vc.model in RAIL_MODELS for vc in site.vehicle_classes):
            # Imported here, not at module top: rail is numba-heavy code that a road-only daemon
            # (no rail vehicle class in its registry) never needs to load or compile.
            from cloud.rail.batches import RailBatches

            self.rail = RailBatches(site)

    # -- input -----------------------------------------------------------------------------------
    def on_segment(self, key: str, payload: bytes) -> None:
        vehicle = self._ap_keys.get(key)
        if vehicle is None:
            try:
                _, _, _, vehicle = keys.parse_ap_key(key)
            except ValueError:
                self.aggregator.rejected["bad_key"] += 1
                return
            if len(self._ap_keys) >= AP_KEY_MEMO:
                self._ap_keys.clear()
            self._ap_keys[key] = vehicle
        self._acks(self.aggregator.on_segment(payload, vehicle))

    def on_done(self, key: str, payload: bytes) -> None:
        acks = self.aggregator.on_pass_done(payload)
        if acks:
            self._acks(acks)
            return
        again = self.aggregator.repeat_ack(payload)
        if again is not None:  # a pass sent again: its acknowledgement was lost (e.g. a router restart)
            self.publish(keys.ack_key(self.net, again.vehicle_id), again.encode())
            self.status_due = True  # the status published with it may be lost too

    def on_calibration(self, key: str, payload: bytes) -> None:
        """A calibration on the bus (sharded: the owner's, for a vehicle another shard calibrates),
        made this cloud's state of the vehicle if newer (:meth:`Ownership.take`)."""
        if self.calibrator is None:
            return
        taken = self.ownership.take(self.calibrator, key, payload)
        if taken is None:
            self.aggregator.rejected["bad_calibration"] += 1
        elif taken:
            self.status_due = True

    def _acks(self, acks) -> None:
        if acks and self.settings.align:
            self.aligner.renew()  # a new series of sweeps, sized for new passes
        if acks:
            self.bridge_sync_due = True
        for ack in acks:
            key = (ack.vehicle_id, ack.pass_id)
            if self.settings.align:
                self.aligner.recomputed(key)  # re-gridded when idle (maybe_align), not on the ingest path
            if self.settings.continuous_aps:
                self._unfused[key] = None
            ps = self.aggregator.passes.get(key)
            first = ps is not None and ps.times_acked == 1
            if ps is not None and ps.times_acked > 1:
                self.epochs.recomputed()
                if self.epochs.rejoin(key, ps):
                    self._record_epoch()
            if self.calibrator is not None and ps is not None and ps.model:
                try:
                    self.calibrator.initial(ack.vehicle_id, ps.model)  # rounds: see maybe_calibrate
                except KeyError:  # no vehicle class for this model in the registry: not calibrated
                    pass
            if first:
                self.epochs.first_acknowledged(key)
            v = self.vehicles[ack.vehicle_id]
            v["passes"] += first
            v["last_pass"] = ack.pass_id
            v["calib_version"] = ack.calib_version
            v["segments"] += ack.n_segments_accepted
            self.publish(keys.ack_key(self.net, ack.vehicle_id), ack.encode())
            if first:  # the `pass` timeline counts distinct passes; recalibrated ones update in place
                self.passes_complete += 1
                if self.view is not None:
                    self._log_view()
        if acks:
            self.status_due = True
            self.flush_status()

    # -- what the estimators hold ----------------------------------------------------------------
    def _continuous_pass(self, key: tuple[str, str]) -> dict | None:
        """A complete road pass's held segments as continuous-time APs, {slot: segment}, or None (not
        a corrected model, no parameters). Computed afresh: nothing kept per pass."""
        agg = self.aggregator
        ps = agg.passes.get(key)
        if not self.settings.continuous_aps or ps is None or not ps.acked or ps.model not in CONTINUOUS_MODELS:
            return None
        slots = [sl for sl in sorted(ps.slots) if sl in agg.held]
        params = ps.params or self._bridge_params(key[0], ps.model, ps.calib_version)
        if not slots or params is None:
            return None
        try:
            fixed = continuous_segments(ps.model, params, [agg.held[sl] for sl in slots], ps.sample_interval_s)
        except (ValueError, np.linalg.LinAlgError) as e:
            log.warning("continuous-time AP of %s/%s failed: %s", key[0], key[1], e)
            return None
        return dict(zip(slots, fixed))

    def fuse_pending(self, budget_s: float | None = None) -> int:
        """Idle work: the profile posterior takes acknowledged passes' continuous-time APs in place of
        the edge's (:meth:`Aggregator.fuse`), in acknowledgement order, within ``budget_s`` (None:
        all). Returns how many passes remain.

        Nothing is fused while chainage alignment has recomputed passes to re-grid or a sweep
        part-done: a sweep compares every pass against one consensus, and a re-gridded pass takes its
        correction after. So the work happens in one order however the idle time is sliced, and the
        estimates do not depend on the clock."""
        self.status_due = self.status_due or bool(self._unfused)  # "settled" waits for these
        if self.aligner.pending or self.aligner.sweeping:
            return len(self._unfused)
        t0 = self.clock()
        while self._unfused and (budget_s is None or self.clock() - t0 < budget_s):
            key = next(iter(self._unfused))
            del self._unfused[key]
            for slot, seg in (self._continuous_pass(key) or {}).items():
                self.aggregator.fuse(slot, seg)
        return len(self._unfused)

    def fused_segments(self) -> list:
        """The held segments as the profile posterior holds them (continuous-time where corrected)."""
        return self.aggregator.as_fused(self.aggregator.held.values())

    def flush_spill(self, budget_s: float | None = None) -> None:
        """Idle work: encode resident segments into the spill index ahead of time, so that neither
        spilling them under load nor a snapshot (every segment) has to. ``budget_s`` defaults to
        the settings' ``flush_budget_s``."""
        budget_s = self.settings.flush_budget_s if budget_s is None else budget_s
        for store in (self.aggregator.segments, self.profile.segments):
            if isinstance(store, SpillMap):
                store.flush(budget_s / 2)

    def maybe_align(self) -> bool:
        """One slice of chainage alignment, if passes completed since the last series: every complete
        road pass against the consensus of the others, each route's maps centred on its fleet's mean
        (:class:`~cloud.daemon.chainage.ChainageAligner`). A series of sweeps against the others'
        improving consensus runs until no pass moves more than ``align_tol_m``, up to
        ``align_iterations`` when new passes came in (2 otherwise); each sweep runs in slices of about
        ``align_budget_s`` of the core's clock, one per call (idle work: the serve loop takes input
        between them, and holds its lock no longer than a slice). True while a sweep goes on, and at
        the end of one that placed passes (a calibration round waits until the series ends)."""
        aligner, s = self.aligner, self.settings
        if not aligner.due:
            return False
        work = Slice(self.clock, s.align_budget_s)
        # Recomputed passes first: the sweep compares against them.
        if not self._reapply_alignments(work):
            return True  # more of them at the next call
        # The sweep starts now, even if it runs only at the next call: nothing is fused between the
        # re-gridding and the sweep (fuse_pending), as when both fit in one slice.
        aligner.begin(self.aggregator)
        if not work.more():
            return True  # the sweep starts (or goes on) at the next call
        result = aligner.step(self.aggregator, self.consensus, work)
        if result is None:
            return True
        moved = result.moved
        if aligner.sweeps == 0:  # the series' first sweep sizes it
            aligner.sweep_limit = s.align_iterations if result.new_passes else 2
        aligner.sweeps += 1
        aligner.swept = aligner.swept or moved is not None
        if aligner.renewed:  # passes completed during this sweep: a new series, sized for them, follows
            aligner.renewed, aligner.sweeps = False, 0
        elif moved is None or moved < s.align_tol_m or aligner.sweeps >= aligner.sweep_limit:
            aligner.due, aligner.sweeps = False, 0
            if aligner.swept and s.continuous_aps:  # re-gridded (or restored) passes: their continuous-time APs afresh
                # (Keys only: the corrections themselves are fused in bounded slices, fuse_pending.)
                self._unfused.update(dict.fromkeys(self.aggregator.passes))
            aligner.swept = False
        self.publish_status()
        if moved is None:
            return aligner.due  # (a series renewed by passes completed meanwhile goes on)
        if self.calibrator is not None:
            self.calibrator.dirty = True  # the consensus moved: the vehicles may need another round
        return True

    def _reapply_alignments(self, work: Slice | None = None) -> bool:
        """Idle work: recomputed passes re-gridded with the alignment found for them, as many as
        ``work`` allows (None: all), their continuous-time APs then due afresh. True if none is left."""
        reapplied = self.aligner.reapply_pending(self.aggregator, work)
        if self.settings.continuous_aps:
            self._unfused.update(dict.fromkeys(reapplied))
        return not self.aligner.pending

    @property
    def aligning(self) -> bool:
        """Whether chainage alignment has slices still to run (a series of sweeps goes on)."""
        return self.aligner.due

    def _placed(self, key: tuple[str, str]) -> bool:
        """Whether a pass is placed in chainage (:meth:`ChainageAligner.placed`)."""
        ps = self.aggregator.passes.get(key)
        return ps is not None and self.aligner.placed(key, ps.model, ps.route_id)

    @property
    def alignments(self) -> dict:
        """(vehicle, pass) → the chainage alignment found for it."""
        return self.aligner.alignments

    # -- passes, status --------------------------------------------------------------------------
    @property
    def completed(self) -> set[tuple[str, str]]:
        """Every pass acknowledged at least once (reads every pass: for tests and tools)."""
        return {key for key, ps in self.aggregator.passes.items() if ps.times_acked}

    @property
    def completion_order(self) -> list[tuple[str, str]]:
        """Passes in the order they were first acknowledged (kept under fleet calibration only)."""
        return self.epochs.order

    def in_completion_order(self, key: tuple[str, str]) -> bool:
        return self.epochs.in_order(key)

    def has_rail(self) -> bool:
        """Whether any pass is a rail run: the batches look at every pass, so not without one."""
        return not self.aggregator.models.isdisjoint(RAIL_MODELS)

    def current_version(self, vehicle_id: str) -> int:
        st = self.calibrator.vehicles.get(vehicle_id) if self.calibrator is not None else None
        return st.version if st is not None else 0

    @property
    def calibrations_applied(self) -> int:
        """Sharded: calibrations of vehicles another shard owns, applied here."""
        return self.ownership.applied

    @property
    def calibration_conflicts(self) -> int:
        """Sharded: calibrations at a version this shard had issued differently, or of a vehicle it owns."""
        return self.ownership.conflicts

    def owns(self, vehicle_id: str) -> bool:
        """Whether this cloud calibrates the vehicle (:meth:`Ownership.owns`)."""
        return self.ownership.owns(vehicle_id)

    def status(self) -> dict:
        passes = self.aggregator.passes
        current = sum(n for (vid, version), n in self.aggregator.acked.items() if version == self.current_version(vid))
        busy = self.calibrator is not None and (self.epochs.pending() or not self.epochs.finished())
        # (a sweep part-done keeps ``due``; estimates still to take their corrected passes)
        busy = busy or self.aligner.due or self.aligner.sweeping or bool(self._unfused)
        return {"passes": len(passes), "passes_current": current, "settled": not busy and current == len(passes),
                "calibration_rounds": self.calibrator.rounds if self.calibrator is not None else 0,
                "calibration_epoch_passes": self.epochs.size,
                "calibration_rounds_left_max": self.epochs.rounds_left_max(),
                "unfused_passes": len(self._unfused),  # acknowledged, their corrected APs not yet in the estimates
                **({"calibrations_applied": self.calibrations_applied,
                    "calibration_conflicts": self.calibration_conflicts} if self.settings.shard is not None else {})}

    def publish_status(self) -> None:
        self.status_due = False
        self._status_at = self.clock()
        self.publish(keys.status_key(self.net, self.node_id), json.dumps(self.status()).encode())

    def flush_status(self, force: bool = False) -> None:
        """Publish the status if acks changed it, at most every ``status_interval_s`` unless ``force``.

        Computing it costs O(vehicles), after every acknowledged pass of a busy fleet: so a status
        held back is published by the next call after the interval (the daemon calls with ``force``
        whenever the bus goes quiet). While quiet, the status is also repeated every
        ``status_heartbeat_s``: a status is published once, and one lost on the way (a router
        restarting) would otherwise leave a subscriber waiting on it for good.
        """
        since = self.clock() - self._status_at
        if self.status_due and (force or since >= self.settings.status_interval_s):
            self.publish_status()
        elif force and since >= self.settings.status_heartbeat_s:
            self.publish_status()

    # -- calibration -----------------------------------------------------------------------------
    def since_new_pass_s(self) -> float:
        """Seconds since a pass was first acknowledged (or since start)."""
        return self.epochs.since_new_pass_s()

    def epoch_finished(self) -> bool:
        return self.epochs.finished()

    def start_epoch(self, size: int, round0: int) -> None:
        """Begin (or, replaying the journal, restore) the epoch of the first ``size`` completed passes."""
        self.epochs.start(size, round0)

    def epoch_state(self, order: bool = False) -> dict:
        return self.epochs.state(order)

    def restore_order(self, order: list) -> None:
        """Replaying a snapshot: the passes' completion order as it was."""
        self.epochs.restore_order(order)

    def _record_epoch(self) -> None:
        if self.record is not None:
            self.record("epoch", json.dumps(self.epochs.state()).encode())

    def maybe_calibrate(self, tail: bool | None = None) -> bool:
        """Run one calibration round if one is due; publish what changed. True if a round ran, or a
        slice of one: its vehicle steps are taken in slices of about ``round_budget_s``
        (:meth:`FleetCalibrator.prepare`), as long as its segments stay the same, and the round is
        applied with the last (the same round as in one call).

        A round is due when the current epoch has not finished and all of its passes are at their
        vehicle's current calibration; it sees those passes only, against a consensus of them alone
        built afresh in a fixed order, so it is a function of the data. A new epoch starts when the
        last has finished and the completed passes reach the next boundary (or, ``tail``, whenever
        some have completed beyond the epoch: the daemon passes ``tail`` once no new pass has
        completed for ``epoch_tail_s``). ``tail=None`` (an in-process caller that has given all of
        its input) skips the boundaries: one epoch of every completed pass.
        """
        c = self.calibrator
        if c is None:
            return False
        if self._view_table is not None:  # the last round's table for the view first, in slices
            self._step_view_table()
            return True
        epochs = self.epochs
        size = epochs.next_size(tail)
        if size is not None:
            epochs.tail += tail is not None and size != epochs.boundary()
            epochs.start(size, c.rounds)
            self._record_epoch()
        if epochs.finished() or not c.dirty:
            return False
        segs, reissued = epochs.segments(self.aggregator, self.owns)
        for cal in reissued:  # the edge recomputes every spooled pass of the vehicle with these
            self.publish(keys.calib_key(self.net, cal.vehicle_id), cal.encode())
        if segs is None:
            return False
        if self.settings.align:  # a pass not (yet) placed in chainage would teach the vehicles a shifted road
            # (Too few placed passes: the round fits nothing and waits for new data, never spins.)
            self._reapply_alignments()  # (maybe_align, which runs first when idle, has normally done it)
            segs = {sl: s for sl, s in segs.items() if self._placed((s.vehicle_id, s.pass_id))}
        # The vehicle step sees what the posterior fuses: continuous-time APs (FleetCalibrator.continuous_aps).
        self.fuse_pending()
        segs = dict(zip(segs, self.aggregator.as_fused(segs.values())))
        # each round pass's sample interval at the edge (its pass-done's), for the models of the passes
        intervals = {key: ps.sample_interval_s for key in {(s.vehicle_id, s.pass_id) for s in segs.values()}
                     if (ps := self.aggregator.passes.get(key)) is not None}
        # The leave-one-out consensus of the round: the epoch's passes only, summed in a fixed order
        # (the running consensus holds passes beyond the epoch and rounding from its history). Kept
        # while the round's vehicle steps are taken in slices, for as long as its segments are the same.
        key = c.round_key(segs, intervals)
        if self._round is None or self._round[0] != key:
            consensus = MeanProfile({r.id: r.length_m for r in self.site.routes}, self.consensus.spacing_m)
            for seg in segs.values():
                consensus.update(seg)
            self._round = (key, consensus)
        consensus = self._round[1]
        if self.settings.shard is not None:  # the others' vehicles inform the consensus; their owners calibrate them
            segs = {sl: seg for sl, seg in segs.items() if self.owns(seg.vehicle_id)}
        c.estimator = consensus
        own = {(s.vehicle_id, s.pass_id) for s in segs.values()}
        c.sample_intervals = {k: v for k, v in intervals.items() if k in own}
        try:
            # The vehicle steps in slices of about round_budget_s (idle work, as alignment's): the
            # serve loop takes input between them; the round then only applies them.
            if not c.prepare(segs, Slice(self.clock, self.settings.round_budget_s)):
                return True
            cals = c.round(segs)
        finally:
            c.estimator = self.consensus
        self._round = None
        if self.record is not None:  # the round's outcome is on disk before any of it is published
            self.record("calibrator", json.dumps(c.state()).encode())
        for cal in cals:
            self.publish(keys.calib_key(self.net, cal.vehicle_id), cal.encode())
            epochs.issued(cal.vehicle_id)
        if self.view is not None:
            # This round's vehicles with their intervals: the table of the calibrator and the held
            # segments as they are now, built in slices by the next calls (its cost grows with the fleet).
            segments = self.fused_segments()
            self._view_table = (self._table_key(segments), c.snapshot().table_steps(segments))
            self._log_view()  # the profile as the round left it, at the current pass count
        self.publish_status()
        return True

    @property
    def calibrating(self) -> bool:
        """A round's vehicle steps, or its table for the view, are being taken in slices
        (:meth:`maybe_calibrate`)."""
        return self._round is not None or self._view_table is not None

    def _step_view_table(self) -> None:
        """One slice (``round_budget_s``) of the view's vehicle table; logged when it is complete."""
        key, steps = self._view_table
        work = Slice(self.clock, self.settings.round_budget_s)
        try:
            while work.more():
                next(steps)
                work.spent()
        except StopIteration as done:
            self._view_table = None
            self._table = (key, done.value)
            try:
                self.view.log_calibration([r for r in done.value if self.owns(r["vehicle_id"])])
            except Exception:  # the view is a side subscriber: never let it take the daemon down
                log.exception("rerun calibration view update failed")
        except Exception:
            self._view_table = None
            log.exception("rerun calibration view update failed")

    def _table_key(self, segments: list) -> tuple:
        """What the vehicle table is a function of: the calibrator's rounds and versions, its passes'
        sample intervals, and the held segments."""
        c = self.calibrator
        return (c.rounds, tuple(sorted((vid, st.version) for vid, st in c.vehicles.items())),
                tuple(sorted(c.sample_intervals.items())), c.round_key(dict(enumerate(segments)), {}))

    def _export_ready(self) -> None:
        """The pending idle work an export does first: every held segment where it will stay."""
        self._reapply_alignments()
        self.fuse_pending()
        self.step_rail(force=True)  # every acknowledged carriage run calibrated and re-keyed

    def table_job(self) -> Callable[[], tuple[tuple, list[dict]]] | None:
        """The vehicle table of an export, to build without the daemon's lock (its cost grows with the
        fleet): called under the lock, it does the export's pending idle work and returns a job that
        builds the table from a snapshot of the calibrator and the held segments, touching nothing of
        the cloud's; hand its result to :meth:`keep_table` (under the lock) before :meth:`export`.
        None if there is no calibrator, or the table is built already."""
        if self.calibrator is None:
            return None
        self._export_ready()
        segments = self.fused_segments()
        key = self._table_key(segments)
        if self._table is not None and self._table[0] == key:
            return None
        calibrator = self.calibrator.snapshot()
        return lambda: (key, calibrator.table(segments))

    def keep_table(self, key: tuple, rows: list[dict]) -> None:
        """A table a :meth:`table_job` built: :meth:`vehicle_rows` uses it while its key holds."""
        self._table = (key, rows)

    def vehicle_rows(self) -> list[dict]:
        """Rows of ``vehicles.parquet`` from the calibrator: a shard's own vehicles only (a vehicle it
        calibrated before its passes elsewhere made another shard its owner is that one's now). The
        table the view's slices built is used while nothing it depends on has changed."""
        if self.calibrator is None:
            return []
        segments = self.fused_segments()
        key = self._table_key(segments)
        if self._table is None or self._table[0] != key:
            self._table = (key, self.calibrator.table(segments))
        return [r for r in self._table[1] if self.owns(r["vehicle_id"])]

    # -- bridges ---------------------------------------------------------------------------------
    def _bridge_uncertainty(self, vehicle_id: str, model: str, calib_version: int) -> dict | None:
        """How well the parameters of a pass are known, as log-sd per calibration quantity (the bridge
        likelihood integrates that error out): under fleet calibration, the class prior's spread for a
        vehicle still at the class mean (version 0), else the calibrator's interval, floored at the
        estimator's default (the interval does not see the fleet-common error); None (the default)
        for parameters the edge brought itself (nominal calibration)."""
        if self.calibrator is None:
            return None
        st = self.calibrator.vehicles.get(vehicle_id)
        try:
            if calib_version == 0 and (st is None or st.fit is None):
                return class_log_sd(self.site, model)
        except KeyError:
            return None
        if st is None or st.fit is None or st.version != calib_version:
            return None
        floor = BridgeSettings().calibration_log_sd or 0.0
        return {n: max(v, floor) for n, v in fit_log_sd(st.fit).items()}

    def _bridge_params(self, vehicle_id: str, model: str, calib_version: int) -> dict | None:
        """The parameters the edge computed a pass with: its calibration ``calib_version``.

        Fleet calibration: the calibrator's current parameters when the pass is at the vehicle's
        current version (None while a newer calibration is on its way: wait for the recomputed
        pass); version 0 is the class mean, the edge's cold start. Only a fallback: edges say in each
        pass-done which parameters they used (e.g. a log's nominal ones), and those come first.
        """
        st = self.calibrator.vehicles.get(vehicle_id) if self.calibrator is not None else None
        if st is not None:
            return dict(st.params) if st.version == calib_version and st.model == model else None
        if calib_version != 0:
            return None
        try:
            return dict(self.site.vehicle_class(model).mean)
        except KeyError:
            return None

    def maybe_estimate_bridges(self, force: bool = False) -> bool:
        """Feed the bridges the passes completed (or recomputed, re-keyed) since the last time,
        estimate those with new data, publish alarms whose state changed and log the view.
        True if any bridge was estimated."""
        if not self.bridges.bridges or not (self.bridge_sync_due or force):
            return False
        if not force and not self.epochs.finished():
            # A calibration epoch is moving its vehicles: every estimate now is redone once its passes
            # come back recomputed, and one costs more than a round. Estimated when the epoch ends.
            return False
        t0 = self.clock()
        self.bridge_sync_due = False
        passes, held = self.aggregator.passes, self.aggregator.held
        estimated = False
        for limit in catch_up_steps(self.bridges.unfed(passes, held)):
            self.bridges.sync(passes, held, self._bridge_params, self._bridge_uncertainty, limit=limit)
            if not self.bridges.due:
                continue
            alarms = self.bridges.estimate()
            estimated = True
            for alarm in alarms:
                payload = alarm.encode()
                # The alarm state is durable: a restarted cloud does not raise a standing alarm again.
                self.alarms[alarm.bridge_id] = payload
                if self.record is not None:
                    self.record("alarm", payload)
                self.publish(keys.alarm_key(self.net, alarm.bridge_id), payload)
                log.warning("bridge %s: %s", alarm.bridge_id, alarm.message)
            if self.view is not None:
                # A step of a catch-up is drawn at the pass count it stands for.
                behind = 0 if limit is None else self.bridges.unfed(passes, held)
                self._log_bridges(alarms, max(0, self.passes_complete - behind))
        if not estimated:
            return False
        self._bridge_done_at = self.clock()
        self._bridge_cost_s = self._bridge_done_at - t0
        return True

    def bridges_may_run(self) -> bool:
        """Whether a bridge update now keeps bridges within ``bridge_duty`` of the cloud's time."""
        duty = self.settings.bridge_duty
        wait = self._bridge_cost_s * (1.0 - duty) / duty
        return self.bridge_sync_due and self.clock() - self._bridge_done_at >= wait

    def restore_alarm(self, payload: bytes) -> None:
        """Replaying the journal: the bridge's alarm state as the alarm last published left it."""
        alarm = decode_alarm(payload)
        st = self.bridges.bridges.get(alarm.bridge_id)
        if st is not None:
            st.alarmed = alarm.kind != CLEARED
            st.diagnosis = (alarm.kind, alarm.element) if st.alarmed else None
            self.alarms[alarm.bridge_id] = bytes(payload)

    def bridge_state(self, bridge_id: str) -> bytes:
        """The answer to ``state/bridge/<bridge>`` (:func:`cloud.daemon.queries.bridge_state`), as of
        the last estimate (made when the bus was quiet)."""
        return bridge_state(self.bridges, bridge_id)

    # -- rail ------------------------------------------------------------------------------------
    def step_rail(self, force: bool = False) -> bool:
        """Fit the carriage batches that are due (``force``: every one that changed), give the
        estimators their re-keyed runs, publish the rail bridges' alarms and log the view. True if
        any batch was fitted."""
        if self.rail is None or not self.has_rail():
            return False
        agg = self.aggregator
        step = self.rail.step(agg.passes, agg.segments, force)
        for slot, seg in step.replacements.items():
            if seg is None:
                agg.drop_held(slot)
            else:
                agg.replace_held(slot, seg)
        for payload in step.baselines:  # durable: a later session reads its runs against it
            if self.record is not None:
                self.record("rail_baseline", payload)
        for alarm in step.alarms:
            self.publish(keys.alarm_key(self.net, alarm.bridge_id), alarm.encode())
            log.warning("bridge %s: %s", alarm.bridge_id, alarm.message)
            if self.view is not None:
                self.view.log_alarm(alarm.bridge_id, alarm.message, "INFO" if alarm.kind == CLEARED else "ERROR")
        if not step.fitted:
            return False
        self.bridge_sync_due = True
        if self.view is not None:
            try:
                self.view.set_pass(self.passes_complete)
                self.view.log_rail(self.rail.view_rows(self.snapshot()))
            except Exception:  # the view is a side subscriber: never let it take the daemon down
                log.exception("rerun rail view update failed")
        return True

    # -- estimates out ---------------------------------------------------------------------------
    def tile_state(self, route_id: str, tile: int) -> bytes | None:
        """The answer to ``state/profile/<route>/<tile>`` (:func:`cloud.daemon.queries.tile_state`)."""
        return tile_state(self.profile, route_id, tile)

    def snapshot(self) -> dict:
        """The profile posterior per route; its band also holds the passes' non-white error (the
        drift and calibration error each pass adds beyond the likelihood's white noise, measured band
        by band from their disagreement: :mod:`cloud.road.long_wave`)."""
        segs = self.fused_segments()  # what the posterior holds (chainage-aligned, continuous-time)
        # With the drift nuisance on, the passes' scatter adds only what exceeds its learnt level;
        # the long waves the edges' drift control removed are restored (the road up to level and slope).
        return {rid: with_long_wave_band(s, segs, drift=drift_of(self.profile, rid), restore_trend=True)
                for rid, s in self.profile.snapshot().items()}

    def export(self, out_dir: Path) -> list[Path]:
        """Every estimate as Parquet tables in ``out_dir`` (interfaces.md §3), a function of the held
        segments: pending idle work (fusion, rail batches, bridge estimates) is done first. The
        vehicle table is the one :meth:`table_job` built if nothing it depends on changed since."""
        self._export_ready()
        snaps = self.snapshot()
        frames = {rid: FLEET_FRAME if self.aligner.frames.get(rid) else REGISTRY_FRAME for rid in snaps}
        tables = {"profile": profile_table(snaps, frames)}
        segs = self.fused_segments()
        rough = [roughness_table(rid, s.chainage_m, profile_draws(self.profile, rid, s, segs, 100, 0),
                                 self.profile.spacing_m, frame=frames[rid])
                 for rid, s in snaps.items() if np.isfinite(s.elevation_m).any()]
        if rough:
            tables["roughness"] = roughness_with_coordinates(pa.concat_tables(rough), self.site)
        rail_rows = self.rail.rows() if self.rail is not None else []
        vehicle_rows = self.vehicle_rows() + rail_rows
        if self.calibrator is not None or vehicle_rows:
            tables["vehicles"] = vehicles_table(vehicle_rows)
        # Track geometry quality of the routes carriages ran on.
        rail = {ps.route_id for ps in self.aggregator.passes.values() if ps.model in RAIL_MODELS} \
            if self.has_rail() else set()
        if rail:
            tables["track_quality"] = track_quality_table({r: s for r, s in snaps.items() if r in rail})
        if self.bridges.bridges:
            self.maybe_estimate_bridges(force=True)  # every acknowledged pass is in the export
            tables["bridge_elements"] = bridge_elements_table(self.bridges.element_rows())
            tables["bridge_bearings"] = bridge_bearings_table(self.bridges.bearing_rows())
            tables["bridge_summary"] = bridge_summary_table(self.bridges.summary_rows())
        if self.rail is not None and self.rail.bridge_rows():  # rail batches' D1/D2 in place of a bridge's road row
            tables["bridge_summary"] = bridge_summary_table(self.rail.bridge_rows(self.bridges.summary_rows()))
        if self.rail is not None and self.rail.element_rows():  # and their span stiffness in place of its elements
            tables["bridge_elements"] = bridge_elements_table(self.rail.element_rows(self.bridges.element_rows()))
        if "bridge_summary" in tables:
            tables["bridge_summary"] = bridges_with_coordinates(tables["bridge_summary"], self.site)
        written = write_export(out_dir, tables)
        if "roughness" in tables and (doc := roughness_geojson(tables["roughness"], self.site)) is not None:
            written.append(write_geojson(out_dir, doc))
        if self.view is not None:
            self.view.flush()
        return written

    # -- the view --------------------------------------------------------------------------------
    def _log_view(self) -> None:
        try:
            self.view.set_pass(self.passes_complete)
            P = tile_points(self.profile.spacing_m)
            snaps = self.snapshot()
            segs = self.fused_segments() if snaps else []
            for snap in snaps.values():
                self.view.log_profile(snap)
                counts = [int(snap.n_passes[i : i + P].max(initial=0)) for i in range(0, snap.n_passes.size, P)]
                self.view.log_tile_counts(snap.route_id, TILE_M, np.asarray(counts))
                if np.isfinite(snap.elevation_m).any():  # the export's IRI, from fewer draws
                    draws = profile_draws(self.profile, snap.route_id, snap, segs, VIEW_IRI_DRAWS, 0)
                    rough = roughness_table(snap.route_id, snap.chainage_m, draws, self.profile.spacing_m).to_pydict()
                    for length in sorted(set(rough["length_m"])):
                        rows = [i for i, v in enumerate(rough["length_m"]) if v == length]
                        self.view.log_roughness(snap.route_id, length, np.take(rough["start_m"], rows),
                                                np.take(rough["iri_m_per_km"], rows), np.take(rough["end_m"], rows))
            self.view.log_vehicle_status(dict(self.vehicles))
            self.view.log_stats(self.aggregator.stats())
        except Exception:  # the view is a side subscriber: never let it take the daemon down
            log.exception("rerun view update failed")

    def _log_bridges(self, alarms, at_pass: int) -> None:
        try:
            self.view.set_pass(at_pass)
            for st in self.bridges.bridges.values():
                if st.latest is not None:
                    baseline = getattr(getattr(st.estimator, "baseline", None), "mril", None)
                    self.view.log_bridge_estimate(st.latest, baseline, hypotheses=self.settings.bridge.hypotheses)
            for alarm in alarms:
                self.view.log_alarm(alarm.bridge_id, alarm.message, "INFO" if alarm.kind == CLEARED else "ERROR")
        except Exception:  # the view is a side subscriber: never let it take the daemon down
            log.exception("rerun bridge view update failed")
