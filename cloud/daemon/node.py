"""The cloud aggregator daemon: AP segments in over Zenoh, estimates out (queries, Rerun, Parquet)."""

from __future__ import annotations

import argparse
import collections
import dataclasses
import gc
import json
import logging
import math
import signal
import struct
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import zenoh

from shared import keys
from shared.registry import RegistryError, Site, load_site
from shared.schema import Calibration, DecodeError, decode_alarm, decode_calibration
from shared.transport import add_zenoh_arguments, config_from_args

from cloud.ingest.aggregator import DEFAULT_MAX_RESIDENT_PASSES, MIN_RESIDENT_PASSES, Aggregator
from cloud.road.alignment import Alignment, estimate_alignment, realign
from cloud.bridge.estimator import BridgeSettings
from cloud.bridge.vehicle_error import class_log_sd, fit_log_sd
from cloud.daemon.durable import AP, CALIB, DONE, Durability, restore_calibration
from cloud.bridge.monitor import CLEARED, BridgeMonitor
from cloud.road.gmrf_profile import GmrfProfile
from cloud.road.long_wave import drift_of, with_long_wave_band
from cloud.road.mean_profile import MeanProfile
from cloud.daemon.journal import Journal, JournalError
from cloud.export import (bridge_bearings_table, bridge_elements_table, bridge_summary_table, profile_draws,
                     profile_table, roughness_table, track_quality_table, vehicles_table, write_export)
from cloud.road.calibration import CONTINUOUS_MODELS, continuous_segments
from cloud.road.fleet_calibration import FleetCalibrator
from cloud.ingest.segment_store import DEFAULT_MAX_RESIDENT, SegmentStore
from cloud.rail.batches import RailBatches

log = logging.getLogger("driveby.cloud")

TILE_M = 50.0
#: Knot spacing (m) of each pass's own drift, a nuisance of the profile posterior (cloud.road.pass_drift);
#: None leaves the drift to the band's measured long-wave term. The posterior, its τ and drift level are a
#: function of the held segments alone, not of their history (tests/test_pass_drift.py), so replays agree.
DRIFT_KNOT_M: float | None = 25.0
#: Fuse road passes as continuous-time APs: the edge's inverse (Newmark γ 0.6 / 0.8, for stability)
#: distorts every AP of a vehicle class alike, so the profile, its IRI and the fleet calibration would
#: all carry that bias. Each complete pass is corrected in the cloud under the parameters the edge
#: computed it with (cloud.road.calibration.continuous_segments): the cloud has the whole pass (the
#: correction is non-causal), and the edge's AP stays the inverse's exact output, which the remap,
#: the bridge (its own correction, cloud/bridge/passdata.py) and rail rebuild the channels from.
#: A recalibrated pass is recomputed by the edge, acknowledged again and corrected again. The correction
#: (~0.5 ms a segment, 5× the rest of ingest) is idle work (Cloud.fuse_pending): done when the bus is
#: quiet, and before a calibration round or an export, never on the ingest path.
CONTINUOUS_APS = True
ALIGN_MIN_SCORE = 0.5  # correlation below this: the pass and the consensus do not overlap well enough
ALIGN_MIN_PASSES = 3  # fewer passes do not define a frame worth centring on
ALIGN_ITERATIONS = 6
ALIGN_MAX_STRETCH = 0.06  # odometry scale errors beyond 6 % are a fault, not an error to align
ALIGN_TOL_M = 0.02
ALIGN_APPLY_M = 0.10  # a pass is re-gridded only if alignment moves it by more than this somewhere

#: Latency tracing (benchmarks): a raw chunk published with this zenoh attachment (its publication
#: time, Unix s, little-endian float64) passes it, via the edge, to the segments it releases; the
#: cloud records (sent, applied) for each such segment it accepts and answers ``control/<id>/latency``.
TRACE = struct.Struct("<d")
TRACE_RECORDS = 100_000
STATUS_INTERVAL_S = 0.1  # status is published at most this often (and this late) while acks stream in
QUIET_S = 0.2  # calibration rounds run once no input has arrived for this long
#: Calibration epochs (reproducible rounds): an epoch is a fixed prefix of the passes in the order they
#: were first acknowledged, and its rounds see exactly those passes, each at its vehicle's current
#: calibration. Epoch sizes are boundaries of the completed-pass count: ``EPOCH_FIRST`` (a cold start
#: on fewer passes costs a full round budget and is soon redone), then doubling, the step capped at
#: ``EPOCH_MAX_STEP``. So which passes a round sees is a function of the data, not
#: of when the bus happened to be quiet. Passes beyond the last boundary join a (tail) epoch once no
#: new pass has completed for ``EPOCH_TAIL_S``: the one timing-dependent decision, there for liveness.
EPOCH_FIRST = 8
EPOCH_MAX_STEP = 64
EPOCH_TAIL_S = 1.0
#: A pass of the epoch still at an older calibration once the bus is quiet (the edge finished it with
#: the old parameters after the new ones arrived) is recomputed by re-issuing its vehicle's calibration
#: under a new version, same parameters; a pass that still does not come back within this long (its
#: raw data evicted from the edge's spool) is left out of the epoch's rounds.
REFRESH_WAIT_S = 5.0
#: …and only this long after the vehicle's current calibration was published: before that, the edge
#: may simply not have started recomputing (a pass finished just before it heard the calibration).
REISSUE_AFTER_S = 1.0
#: While segments stream in, bridge estimates (0.2–1.5 s each) may take at most this share of the
#: cloud's time, so the bridge view still updates pass by pass during a fast replay.
BRIDGE_DUTY = 0.2
#: Per quiet tick (every STATUS_INTERVAL_S), at most this long encoding resident segments into the
#: spill index (Cloud.flush_spill): a snapshot then copies stored payloads instead of encoding ~1 000
#: segments (~1 s) with the serve loop held.
FLUSH_BUDGET_S = 0.01
RAIL_MODELS = ("carriage", "bogie_half_car")  # vehicle models whose passes are rail runs (issue #6)


class Cloud:
    """Transport-free core of the daemon: the aggregator, its estimators and the view."""

    def __init__(self, net: str, site: Site, publish, view=None, spacing_m: float = 0.05,
                 calibration: str = "nominal", node_id: str = "cloud-1", align: bool = False,
                 bridge_settings: BridgeSettings = BridgeSettings(), shard: frozenset[str] | None = None,
                 max_resident: int | None = None, spill_dir: Path | None = None,
                 max_resident_passes: int | None = None):
        # A shard (``shard``: the routes this aggregator owns) sees the site as its routes and their
        # bridges only; pass-dones for the other shards' routes are not its business (counted apart).
        foreign = frozenset()
        self.shard = shard
        if shard is not None:
            foreign = frozenset(r.id for r in site.routes) - shard
            site = dataclasses.replace(site, routes=tuple(r for r in site.routes if r.id in shard),
                                       bridges=tuple(b for b in site.bridges if b.route in shard))
        self.net, self.site, self.publish, self.view, self.node_id = net, site, publish, view, node_id
        routes = {r.id: r.length_m for r in site.routes}
        self.profile = GmrfProfile(routes, spacing_m, drift_knot_m=DRIFT_KNOT_M)
        # The vehicle step compares against the data alone (the flat-prior limit of the posterior):
        # the random-walk prior's smoothing of the shortest wavelengths would bias tyre stiffness.
        self.consensus = MeanProfile(routes, spacing_m)
        # At most ``max_resident`` segments decoded in memory (None: all) and ``max_resident_passes``
        # passes' bookkeeping; the rest on disk under ``spill_dir`` (default: the system's temporary
        # directory), read back when needed, so memory does not grow with the passes.
        self.aggregator = Aggregator(site, [self.profile, self.consensus], foreign_routes=foreign,
                                     store=SegmentStore(max_resident, spill_dir),
                                     max_resident_passes=max_resident_passes, spill_dir=spill_dir)
        if max_resident is not None and isinstance(getattr(self.profile, "segments", None), dict):
            # The profile estimator keeps each segment it holds too (exact retraction, the per-pass
            # drift assembled at snapshot time): bounded the same way.
            self.profile.segments = SegmentStore(max_resident, spill_dir)
        self.calibrator = FleetCalibrator(site, self.consensus) if calibration == "fleet" else None
        if self.calibrator is not None:
            self.calibrator.continuous_aps = CONTINUOUS_APS
        self._unfused: dict[tuple[str, str], None] = {}  # acknowledged passes whose correction is due (ordered)
        self.calibrations_applied = 0  # sharded: calibrations of vehicles another shard owns, applied here
        self.calibration_conflicts = 0  # …and ones at a version this shard had issued differently
        self.align = align  # chainage alignment of passes (GNSS error); costs ~30 ms per pass per sweep
        self.align_due = False  # passes completed since the last alignment
        self.alignments: dict[tuple[str, str], Alignment] = {}
        # Calibration epochs (see EPOCH_MAX_STEP): passes in first-acknowledgement order, the current
        # epoch's size and the calibrator's round count when it began. Kept under fleet calibration only
        # (its rounds see every pass anyway); without it nothing here grows with the passes.
        self.completion_order: list[tuple[str, str]] = []
        self._ordered: set[tuple[str, str]] = set()  # the same passes, for membership
        self.epoch_size = 0
        self.epoch_round0 = 0
        self.epochs_tail = 0  # epochs closed by EPOCH_TAIL_S rather than a boundary (timing-dependent)
        self._new_pass_at = time.monotonic()
        #: monotonic s of the last acknowledgement of a recomputed pass: while they keep coming the edge is
        #: working through its recomputations, and a pass not yet back is queued, not lost. (Not new
        #: passes' acks: under steady traffic those never stop, and an evicted pass would stall the rounds.)
        self._recomputed_at = time.monotonic()
        self._refreshed: dict[str, tuple[int, float]] = {}  # vehicle → (version re-issued, monotonic s)
        self._issued_at: dict[str, float] = {}  # vehicle → monotonic s its current calibration was published
        self._excluded: set[tuple[str, str]] = set()  # epoch passes that never came back (REFRESH_WAIT_S)
        #: ``record(kind, payload)``: the daemon's journal for the cloud's own decisions (an epoch's start,
        #: the calibrator's state after a round, journalled before its calibrations are published).
        self.record = None
        self.vehicles: dict[str, dict] = collections.defaultdict(
            lambda: {"passes": 0, "last_pass": "", "calib_version": 0, "segments": 0})
        self.passes_complete = 0
        self.status_due = False  # acks were published since the last status
        # Bridges are fed and estimated when the bus is quiet (maybe_estimate_bridges), never per segment.
        self.bridges = BridgeMonitor(site, bridge_settings)
        self.rail = RailBatches(site)  # carriage runs: batch calibration, re-keying (issue #6)
        self.bridge_sync_due = False  # passes were acknowledged (or re-aligned) since the last sync
        self.alarms: dict[str, bytes] = {}  # bridge → the last alarm message published (raised or cleared)
        self._bridge_cost_s = 0.0  # how long the last bridge update took
        self._bridge_done_at = -math.inf  # monotonic s when it ended
        self._status_at = -math.inf  # monotonic s of the last status publication

    def on_segment(self, key: str, payload: bytes) -> None:
        try:
            _, _, _, vehicle = keys.parse_ap_key(key)
        except ValueError:
            self.aggregator.rejected["bad_key"] += 1
            return
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

    def _reapply_alignment(self, key: tuple[str, str]) -> None:
        """A recomputed pass keeps the chainage alignment found for it (until the next sweep)."""
        al = self.alignments.get(key)
        ps = self.aggregator.passes.get(key)
        if al is None or ps is None:
            return
        slots = sorted(ps.slots)
        raw = [self.aggregator.segments[sl] for sl in slots]
        x_span = np.array([al.x_ref_m, max(r.end_index for r in raw) * raw[0].spacing_m])
        if np.max(np.abs(al.true_to_reported(x_span) - x_span)) < ALIGN_APPLY_M:
            return
        aligned = {(s.vehicle_id, s.pass_id, s.route_id, s.tile, s.axle): s for s in realign(raw, al)}
        for sl in slots:
            if sl in aligned:
                self.aggregator.replace_held(sl, aligned[sl])

    def _acks(self, acks) -> None:
        if acks and self.align:
            self.align_due = True
        if acks:
            self.bridge_sync_due = True
        for ack in acks:
            if self.align:
                self._reapply_alignment((ack.vehicle_id, ack.pass_id))
            if CONTINUOUS_APS:
                self._unfused[(ack.vehicle_id, ack.pass_id)] = None
            ps = self.aggregator.passes.get((ack.vehicle_id, ack.pass_id))
            first = ps is not None and ps.times_acked == 1
            if ps is not None and ps.times_acked > 1:
                self._recomputed_at = time.monotonic()
                self._rejoin((ack.vehicle_id, ack.pass_id), ps)
            if self.calibrator is not None and ps is not None and ps.model:
                try:
                    self.calibrator.initial(ack.vehicle_id, ps.model)  # rounds: see maybe_calibrate
                except KeyError:  # no vehicle class for this model in the registry: not calibrated
                    pass
            if first:
                self._new_pass_at = time.monotonic()
                if self.calibrator is not None and (ack.vehicle_id, ack.pass_id) not in self._ordered:
                    self.completion_order.append((ack.vehicle_id, ack.pass_id))
                    self._ordered.add((ack.vehicle_id, ack.pass_id))
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

    def _continuous_pass(self, key: tuple[str, str]) -> dict | None:
        """A complete road pass's held segments as continuous-time APs, {slot: segment}, or None (not
        a corrected model, no parameters). Computed afresh (~12 ms a 200 m pass): nothing kept per pass."""
        agg = self.aggregator
        ps = agg.passes.get(key)
        if not CONTINUOUS_APS or ps is None or not ps.acked or ps.model not in CONTINUOUS_MODELS:
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
        the edge's (same identities: an update replaces, and the aggregator's later retraction removes
        them), in acknowledgement order, within ``budget_s`` (None: all). Returns how many remain."""
        t0 = time.monotonic()
        self.status_due = self.status_due or bool(self._unfused)  # "settled" waits for these
        while self._unfused and (budget_s is None or time.monotonic() - t0 < budget_s):
            key = next(iter(self._unfused))
            del self._unfused[key]
            for seg in (self._continuous_pass(key) or {}).values():
                self.profile.update(seg)
        return len(self._unfused)

    def fused_segments(self) -> list:
        """The held segments as the profile posterior holds them (continuous-time where corrected)."""
        return self._as_fused(self.aggregator.held.values())

    def _as_fused(self, segs) -> list:
        if not CONTINUOUS_APS:
            return list(segs)
        store = self.profile.segments
        return [store.get(seg.identity) if seg.identity in store else seg for seg in segs]

    def flush_spill(self, budget_s: float = FLUSH_BUDGET_S) -> None:
        """Idle work: encode resident segments into the spill index ahead of time, so that neither
        spilling them under load nor a snapshot (every segment) has to."""
        for store in (self.aggregator.segments, self.profile.segments):
            if isinstance(store, SegmentStore):
                store.flush(budget_s / 2)

    @property
    def completed(self) -> set[tuple[str, str]]:
        """Every pass acknowledged at least once (reads every pass: for tests and tools)."""
        return {key for key, ps in self.aggregator.passes.items() if ps.times_acked}

    def has_rail(self) -> bool:
        """Whether any pass is a rail run: the batches look at every pass, so not without one."""
        return not self.aggregator.models.isdisjoint(RAIL_MODELS)

    def current_version(self, vehicle_id: str) -> int:
        st = self.calibrator.vehicles.get(vehicle_id) if self.calibrator is not None else None
        return st.version if st is not None else 0

    def status(self) -> dict:
        passes = self.aggregator.passes
        current = sum(n for (vid, version), n in self.aggregator.acked.items() if version == self.current_version(vid))
        busy = False
        if self.calibrator is not None:
            c = self.calibrator
            pending = len(self.completion_order) > self.epoch_size and len(self.completion_order) >= c.min_passes
            busy = pending or not self.epoch_finished()
        busy = busy or self.align_due or bool(self._unfused)  # (estimates still to take their corrected passes)
        return {"passes": len(passes), "passes_current": current, "settled": not busy and current == len(passes),
                "calibration_rounds": self.calibrator.rounds if self.calibrator is not None else 0,
                "calibration_epoch_passes": self.epoch_size,
                "unfused_passes": len(self._unfused),  # acknowledged, their corrected APs not yet in the estimates
                **({"calibrations_applied": self.calibrations_applied,
                    "calibration_conflicts": self.calibration_conflicts} if self.shard is not None else {})}

    def publish_status(self) -> None:
        self.status_due = False
        self._status_at = time.monotonic()
        self.publish(keys.status_key(self.net, self.node_id), json.dumps(self.status()).encode())

    def flush_status(self, force: bool = False) -> None:
        """Publish the status if acks changed it, at most every ``STATUS_INTERVAL_S`` unless ``force``.

        Computing it costs O(vehicles); after every acknowledged pass of a busy fleet that was most
        of the cloud's time. A status held back is published by the next call after the interval
        (the daemon calls with ``force`` whenever the bus goes quiet).
        """
        if self.status_due and (force or time.monotonic() - self._status_at >= STATUS_INTERVAL_S):
            self.publish_status()

    def maybe_align(self) -> bool:
        """Align every complete pass in chainage against the consensus of the others (GNSS bias and
        odometry stretch), centre the fleet's shifts, and give the estimators the aligned segments.
        Runs when passes completed since the last time; True if it ran."""
        if not self.align_due:
            return False
        self.align_due = False
        new_passes = any(key not in self.alignments for key, ps in self.aggregator.passes.items() if ps.acked)
        swept = False
        for _ in range(ALIGN_ITERATIONS if new_passes else 2):  # against the others' improving consensus
            moved = self._align_once(max_stretch=ALIGN_MAX_STRETCH)
            if moved is None:
                break
            swept = True
            if moved < ALIGN_TOL_M:
                break
        if swept and CONTINUOUS_APS:  # re-gridded (or restored) passes: their continuous-time APs afresh
            self._unfused.update(dict.fromkeys(self.aggregator.passes))
        if moved is None:
            self.publish_status()
            return False
        if self.calibrator is not None:
            self.calibrator.dirty = True  # the consensus moved: the vehicles may need another round
        self.publish_status()
        return True

    def _align_once(self, max_stretch: float) -> float | None:
        """One alignment sweep; the largest change of any pass's implied position (m), or None."""
        agg = self.aggregator
        found: dict[tuple, tuple[Alignment, list]] = {}
        for key, ps in agg.passes.items():
            if not ps.acked or not ps.slots:
                continue
            slots = sorted(ps.slots)
            held = [agg.held[sl] for sl in slots if sl in agg.held]
            for h in held:
                self.consensus.retract(h)
            try:
                snap = self.consensus.snapshot(ps.route_id).get(ps.route_id)
            finally:
                for h in held:
                    self.consensus.update(h)
            raw = [agg.segments[sl] for sl in slots]
            lead = [r for r in raw if r.axle == 1]
            if snap is None or not lead:
                continue
            lo, hi = min(r.start_index for r in lead), max(r.end_index for r in lead)
            ap = np.full(hi - lo, np.nan)
            for r in lead:
                ap[r.start_index - lo : r.end_index - lo] = r.values
            al = estimate_alignment(np.arange(lo, hi) * lead[0].spacing_m, ap, snap.chainage_m, snap.elevation_m,
                                    max_stretch=max_stretch)
            if al is not None and al.score >= ALIGN_MIN_SCORE:
                found[key] = (al, slots)
        if len(found) < ALIGN_MIN_PASSES:
            return None
        # The fleet's GNSS errors average out: the consensus frame is the mean of the passes' frames.
        mean_shift = float(np.mean([a.shift_m for a, _ in found.values()]))
        mean_stretch = float(np.mean([a.stretch for a, _ in found.values()]))
        moved = 0.0
        for key, (al, slots) in found.items():
            al = Alignment(al.shift_m - mean_shift, al.stretch - mean_stretch, al.x_ref_m, al.score)
            old = self.alignments.get(key)
            x_probe = np.array([al.x_ref_m, al.x_ref_m + 100.0])
            moved = max(moved, float(np.max(np.abs(al.true_to_reported(x_probe) - (
                old.true_to_reported(x_probe) if old is not None else x_probe)))))
            self.alignments[key] = al
            raw = [agg.segments[sl] for sl in slots]
            x_span = np.array([al.x_ref_m, max(r.end_index for r in raw) * raw[0].spacing_m])
            if np.max(np.abs(al.true_to_reported(x_span) - x_span)) < ALIGN_APPLY_M:
                # Within what alignment can resolve: re-gridding would only blur the pass.
                for sl, r in zip(slots, raw):
                    if agg.held.get(sl) is not r:
                        agg.replace_held(sl, r)
                continue
            aligned = {(s.vehicle_id, s.pass_id, s.route_id, s.tile, s.axle): s for s in realign(raw, al)}
            for sl in slots:
                new = aligned.get(sl)
                if new is not None:
                    agg.replace_held(sl, new)
        return moved

    # -- sharded calibration -----------------------------------------------------------------------
    def owns(self, vehicle_id: str) -> bool:
        """Whether this cloud calibrates the vehicle: always unsharded; a shard when the route with most
        of the vehicle's passes (ties: the first route id) is one of its own. Every shard sees every
        pass-done, so they agree once the same pass-dones have arrived."""
        if self.shard is None:
            return True
        counts = self.aggregator.vehicle_routes.get(vehicle_id)
        if not counts:
            return False
        route = min(counts, key=lambda r: (-counts[r], r))
        return route in self.shard

    def on_calibration(self, key: str, payload: bytes) -> None:
        """A calibration on the bus (a shard: the owner's, for a vehicle another shard calibrates):
        made this cloud's state of the vehicle, so its passes here are current at that version and
        its bridges are fed with those parameters. Its own calibrations come back too: no change."""
        c = self.calibrator
        if c is None:
            return
        try:
            cal = decode_calibration(payload)
            if keys.parse_vehicle_key(key, "calib")[1] != cal.vehicle_id:
                raise ValueError("key names another vehicle")
        except (DecodeError, ValueError):
            self.aggregator.rejected["bad_calibration"] += 1
            return
        st = c.vehicles.get(cal.vehicle_id)
        if st is not None and cal.version <= st.version:
            if cal.version == st.version and dict(cal.params) != st.params:
                self.calibration_conflicts += 1  # two shards issued this version: ownership disagreed
                log.warning("calibration of %s v%d issued differently by another shard", cal.vehicle_id, cal.version)
            return
        if self.owns(cal.vehicle_id):
            self.calibration_conflicts += 1
            log.warning("calibration of %s v%d issued by another shard, though this one owns it",
                        cal.vehicle_id, cal.version)
        try:
            restore_calibration(c, cal)
        except KeyError:  # no vehicle class for it in the registry
            self.aggregator.rejected["bad_calibration"] += 1
            return
        self.calibrations_applied += 1
        self.status_due = True

    # -- calibration epochs ----------------------------------------------------------------------
    def since_new_pass_s(self) -> float:
        """Seconds since a pass was first acknowledged (or since start)."""
        return time.monotonic() - self._new_pass_at

    def epoch_finished(self) -> bool:
        """The current epoch's rounds are over: one ran and moved nobody, or its budget is spent."""
        c = self.calibrator
        if c is None or self.epoch_size == 0:
            return True
        ran = c.rounds - self.epoch_round0
        return ran > 0 and (not c.dirty or ran >= c.max_rounds)

    def next_epoch_size(self, tail: bool | None) -> int | None:
        """The size of the epoch due now (None: none due), from the completed-pass count alone, or all
        completed passes when ``tail`` (when ``None``: at once, without boundaries)."""
        c = self.calibrator
        n = len(self.completion_order)
        if c is None or n < c.min_passes or n <= self.epoch_size or not self.epoch_finished():
            return None
        if tail is None:
            return n
        boundary = self._boundary()
        if n >= boundary:
            return boundary
        return n if tail else None

    def _boundary(self) -> int:
        """The completed-pass count at which the epoch after the current one is due."""
        first = max(self.calibrator.min_passes, EPOCH_FIRST)
        return first if self.epoch_size < first else self.epoch_size + min(self.epoch_size, EPOCH_MAX_STEP)

    def start_epoch(self, size: int, round0: int) -> None:
        """Begin (or, replaying the journal, restore) the epoch of the first ``size`` completed passes."""
        c = self.calibrator
        self.epoch_size, self.epoch_round0 = size, round0
        if c is not None and c.rounds == round0:  # no round of it yet: it needs one
            c.dirty, c.settled, c.budget_from = True, False, round0

    def epoch_state(self, order: bool = False) -> dict:
        """The epoch as journalled; with ``order`` (a snapshot) the completion order too: a pass being
        recomputed when the snapshot is taken is acknowledged again only later, out of its place."""
        out = {"size": self.epoch_size, "round0": self.epoch_round0}
        if order:
            out["order"] = [list(k) for k in self.completion_order]
        return out

    def restore_order(self, order: list) -> None:
        """Replaying a snapshot: the passes' completion order as it was."""
        self.completion_order = [(str(v), str(p)) for v, p in order]
        self._ordered = set(self.completion_order)

    def _epoch_segments(self, refresh: bool) -> dict | None:
        """The epoch's held segments, pass by pass in completion order, each pass at its vehicle's
        current calibration; None while some pass is not (yet) recomputed (then, with ``refresh``,
        re-issue the calibration of vehicles whose edge finished a pass with older parameters)."""
        agg, c = self.aggregator, self.calibrator
        out: dict = {}
        waiting = False
        now = time.monotonic()
        for key in self.completion_order[: self.epoch_size]:
            ps, st = agg.passes.get(key), c.vehicles.get(key[0])
            if ps is None or st is None or key in self._excluded:
                continue
            if not ps.acked or ps.calib_version != st.version:
                if not self.owns(key[0]):  # its owner's calibration is on its way: not waited for here
                    continue
                waiting = True
                # (Waits count from the edge's last answer too: a slow edge returns a round's passes
                # one by one, seconds apart; timed from the calibration alone, road-qc under a heavier
                # error model left 23-30 of 30 passes out, their vehicles at their first round's values.)
                if refresh and ps.acked and ps.calib_version < st.version and \
                        now - max(self._issued_at.get(key[0], -math.inf), self._recomputed_at) >= REISSUE_AFTER_S:
                    version, at = self._refreshed.get(key[0], (-1, now))
                    if version != st.version:
                        self._reissue(key[0])
                    elif now - max(at, self._recomputed_at) >= REFRESH_WAIT_S:
                        log.warning("pass %s/%s not recomputed at calibration v%d: left out of the rounds",
                                    key[0], key[1], st.version)
                        self._excluded.add(key)
                continue
            for sl in sorted(ps.slots):
                seg = agg.held.get(sl)
                if seg is not None:
                    out[sl] = seg
        return None if waiting else out

    def _rejoin(self, key: tuple[str, str], ps) -> None:
        """A pass left out of the rounds (REFRESH_WAIT_S) came back at its vehicle's current calibration:
        in the rounds again, with a fresh budget for the epoch (new data for it, as a new pass) — else
        its vehicle would keep the calibration of the round before it was left out."""
        c = self.calibrator
        st = c.vehicles.get(key[0]) if c is not None else None
        if key not in self._excluded or st is None or ps.calib_version != st.version:
            return
        self._excluded.discard(key)
        if key in self.completion_order[: self.epoch_size]:
            self.start_epoch(self.epoch_size, c.rounds)
            if self.record is not None:
                self.record("epoch", json.dumps(self.epoch_state()).encode())

    def _reissue(self, vehicle_id: str) -> None:
        """The vehicle's calibration again under a new version (same parameters): its edge recomputes
        every spooled pass with exactly the parameters the calibrator holds."""
        st = self.calibrator.vehicles[vehicle_id]
        st.version += 1
        self._refreshed[vehicle_id] = (st.version, time.monotonic())
        self._issued_at[vehicle_id] = time.monotonic()
        cal = Calibration(vehicle_id=vehicle_id, version=st.version, vehicle_model=st.model,
                          params=dict(st.params), source="fleet")
        self.publish(keys.calib_key(self.net, vehicle_id), cal.encode())

    def maybe_calibrate(self, tail: bool | None = None) -> bool:
        """Run one calibration round if one is due; publish what changed. True if a round ran.

        A round is due when the current epoch has not finished and all of its passes are at their
        vehicle's current calibration; it sees those passes only, against a consensus of them alone
        built afresh in a fixed order, so it is a function of the data. A new epoch starts when the
        last has finished and the completed passes reach the next boundary (or, ``tail``, whenever
        some have completed beyond the epoch: the daemon passes ``tail`` once no new pass has
        completed for ``EPOCH_TAIL_S``). ``tail=None`` (an in-process caller that has given all of
        its input) skips the boundaries: one epoch of every completed pass.
        """
        c = self.calibrator
        if c is None:
            return False
        size = self.next_epoch_size(tail)
        if size is not None:
            self.epochs_tail += tail is not None and size != self._boundary()
            self.start_epoch(size, c.rounds)
            if self.record is not None:
                self.record("epoch", json.dumps(self.epoch_state()).encode())
        if self.epoch_finished() or not c.dirty:
            return False
        segs = self._epoch_segments(refresh=True)
        if segs is None:
            return False
        if self.align:  # a pass not (yet) placed in chainage would teach the vehicles a shifted road
            # (Too few placed passes: the round fits nothing and waits for new data, never spins.)
            segs = {sl: s for sl, s in segs.items() if (s.vehicle_id, s.pass_id) in self.alignments}
        # The vehicle step sees what the posterior fuses: continuous-time APs (FleetCalibrator.continuous_aps).
        self.fuse_pending()
        segs = dict(zip(segs, self._as_fused(segs.values())))
        # The leave-one-out consensus of the round: the epoch's passes only, summed in a fixed order
        # (the running consensus holds passes beyond the epoch and rounding from its history).
        consensus = MeanProfile({r.id: r.length_m for r in self.site.routes}, self.consensus.spacing_m)
        for seg in segs.values():
            consensus.update(seg)
        if self.shard is not None:  # the others' vehicles inform the consensus; their owners calibrate them
            segs = {sl: seg for sl, seg in segs.items() if self.owns(seg.vehicle_id)}
        c.estimator = consensus
        # each round pass's sample interval at the edge (its pass-done's), for the models of the passes
        c.sample_intervals = {key: ps.sample_interval_s for key in {(s.vehicle_id, s.pass_id) for s in segs.values()}
                              if (ps := self.aggregator.passes.get(key)) is not None}
        try:
            cals = c.round(segs)
        finally:
            c.estimator = self.consensus
        if self.record is not None:  # the round's outcome is on disk before any of it is published
            self.record("calibrator", json.dumps(c.state()).encode())
        for cal in cals:
            self.publish(keys.calib_key(self.net, cal.vehicle_id), cal.encode())
            self._issued_at[cal.vehicle_id] = time.monotonic()
        if self.view is not None:
            self._log_view()  # the profile as the round left it, at the current pass count
        self.publish_status()
        return True

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
        """Feed the bridges the passes completed (or recomputed, re-aligned) since the last time,
        estimate those with new data, publish alarms whose state changed and log the view.
        True if any bridge was estimated."""
        if not self.bridges.bridges or not (self.bridge_sync_due or force):
            return False
        t0 = time.monotonic()
        self.bridge_sync_due = False
        self.bridges.sync(self.aggregator.passes, self.aggregator.held, self._bridge_params, self._bridge_uncertainty)
        if not self.bridges.due:
            return False
        alarms = self.bridges.estimate()
        for alarm in alarms:
            payload = alarm.encode()
            # The alarm state is durable: a restarted cloud does not raise a standing alarm again.
            self.alarms[alarm.bridge_id] = payload
            if self.record is not None:
                self.record("alarm", payload)
            self.publish(keys.alarm_key(self.net, alarm.bridge_id), payload)
            log.warning("bridge %s: %s", alarm.bridge_id, alarm.message)
        if self.view is not None:
            self._log_bridges(alarms)
        self._bridge_done_at = time.monotonic()
        self._bridge_cost_s = self._bridge_done_at - t0
        return True

    def vehicle_rows(self) -> list[dict]:
        """Rows of ``vehicles.parquet`` from the calibrator: a shard's own vehicles only (a vehicle it
        calibrated before its passes elsewhere made another shard its owner is that one's now)."""
        if self.calibrator is None:
            return []
        return [r for r in self.calibrator.table() if self.owns(r["vehicle_id"])]

    def restore_alarm(self, payload: bytes) -> None:
        """Replaying the journal: the bridge's alarm state as the alarm last published left it."""
        alarm = decode_alarm(payload)
        st = self.bridges.bridges.get(alarm.bridge_id)
        if st is not None:
            st.alarmed = alarm.kind != CLEARED
            self.alarms[alarm.bridge_id] = bytes(payload)

    def bridges_may_run(self) -> bool:
        """Whether a bridge update now keeps bridges within ``BRIDGE_DUTY`` of the cloud's time."""
        wait = self._bridge_cost_s * (1.0 - BRIDGE_DUTY) / BRIDGE_DUTY
        return self.bridge_sync_due and time.monotonic() - self._bridge_done_at >= wait

    def _log_bridges(self, alarms) -> None:
        try:
            self.view.set_pass(self.passes_complete)
            for st in self.bridges.bridges.values():
                if st.latest is not None:
                    baseline = getattr(getattr(st.estimator, "baseline", None), "mril", None)
                    self.view.log_bridge_estimate(st.latest, baseline)
            for alarm in alarms:
                self.view.log_alarm(alarm.bridge_id, alarm.message,
                                    "INFO" if alarm.kind == "cleared" else "ERROR")
        except Exception:  # the view is a side subscriber: never let it take the daemon down
            log.exception("rerun bridge view update failed")

    def bridge_state(self, bridge_id: str) -> bytes:
        """The answer to ``state/bridge/<bridge>``: JSON of the bridge's export rows
        (``summary``, ``elements``, ``bearings``: interfaces.md §3) and its ``assessment`` (the
        hypotheses' probabilities, the decision, location and severity; null when off). Not-a-number
        is null. As of the last estimate (made when the bus was quiet)."""
        summary = next(r for r in self.bridges.summary_rows() if r["bridge_id"] == bridge_id)
        st = self.bridges.bridges[bridge_id]
        est = st.latest
        a = est.assessment if est is not None else None
        body = {
            "summary": summary,
            "elements": est.element_rows() if est is not None else [],
            "bearings": est.bearing_rows() if est is not None else [],
            "assessment": None if a is None else {
                "probabilities": a.probabilities, "best": a.best, "alarm": a.alarm,
                "loss_probability": a.loss_probability, "kind": a.kind, "element": a.element,
                "location_m": a.location_m, "severity": a.severity},
        }
        return json.dumps(_finite_or_null(body), allow_nan=False).encode()

    def _log_view(self) -> None:
        try:
            self.view.set_pass(self.passes_complete)
            for snap in self.snapshot().values():
                self.view.log_profile(snap)
                P = int(round(TILE_M / self.profile.spacing_m))
                counts = [int(snap.n_passes[i : i + P].max(initial=0)) for i in range(0, snap.n_passes.size, P)]
                self.view.log_tile_counts(snap.route_id, TILE_M, np.asarray(counts))
            self.view.log_vehicle_status(dict(self.vehicles))
            self.view.log_stats(self.aggregator.stats())
        except Exception:  # the view is a side subscriber: never let it take the daemon down
            log.exception("rerun view update failed")

    def tile_state(self, route_id: str, tile: int) -> bytes | None:
        snaps = self.profile.snapshot(route_id)
        if route_id not in snaps:
            return None
        s = snaps[route_id]
        P = int(round(TILE_M / self.profile.spacing_m))
        sl = slice(tile * P, (tile + 1) * P)
        table = pa.table({"chainage_m": s.chainage_m[sl], "elevation_m": s.elevation_m[sl],
                          "lo95_m": s.lo95_m[sl], "hi95_m": s.hi95_m[sl], "n_passes": s.n_passes[sl]})
        sink = pa.BufferOutputStream()
        with pa.ipc.new_stream(sink, table.schema) as w:
            w.write_table(table)
        return sink.getvalue().to_pybytes()

    def snapshot(self) -> dict:
        """The profile posterior per route; its band also holds the passes' non-white error (the
        drift and calibration error each pass adds beyond the likelihood's white noise, measured band
        by band from their disagreement: :mod:`cloud.road.long_wave`)."""
        segs = self.fused_segments()  # what the posterior holds (chainage-aligned, continuous-time)
        # With the drift nuisance on, the passes' scatter adds only what exceeds its learnt level.
        return {rid: with_long_wave_band(s, segs, drift=drift_of(self.profile, rid))
                for rid, s in self.profile.snapshot().items()}

    def export(self, out_dir: Path) -> list[Path]:
        self.fuse_pending()  # what the export holds is a function of the held segments, not of idle time
        if self.has_rail():
            self.rail.step(self, force=True)  # every acknowledged carriage run calibrated and re-keyed
        snaps = self.snapshot()
        tables = {"profile": profile_table(snaps)}
        segs = self.fused_segments()
        rough = [roughness_table(rid, s.chainage_m, profile_draws(self.profile, rid, s, segs, 100, 0), self.profile.spacing_m)
                 for rid, s in snaps.items() if np.isfinite(s.elevation_m).any()]
        if rough:
            tables["roughness"] = pa.concat_tables(rough)
        vehicle_rows = self.vehicle_rows() + self.rail.rows()
        if self.calibrator is not None or vehicle_rows:
            tables["vehicles"] = vehicles_table(vehicle_rows)
        # --- rail (issue #6): track geometry quality of routes that carriages ran on ---------------
        rail = {ps.route_id for ps in self.aggregator.passes.values() if ps.model in RAIL_MODELS} \
            if self.has_rail() else set()
        if rail:
            tables["track_quality"] = track_quality_table({r: s for r, s in snaps.items() if r in rail})
        # --- end rail -----------------------------------------------------------------------------
        if self.bridges.bridges:
            self.maybe_estimate_bridges(force=True)  # every acknowledged pass is in the export
            tables["bridge_elements"] = bridge_elements_table(self.bridges.element_rows())
            tables["bridge_bearings"] = bridge_bearings_table(self.bridges.bearing_rows())
            tables["bridge_summary"] = bridge_summary_table(self.bridges.summary_rows())
        if self.rail.bridge_rows():  # rail batches' D1/D2 (issue #6), in place of a bridge's road row
            tables["bridge_summary"] = bridge_summary_table(self.rail.bridge_rows(self.bridges.summary_rows()))
        written = write_export(out_dir, tables)
        if self.view is not None:
            self.view.flush()
        return written


def _finite_or_null(v):
    """JSON-safe: non-finite floats (and numpy scalars of them) become None."""
    if isinstance(v, dict):
        return {str(k): _finite_or_null(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_finite_or_null(x) for x in v]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    return v


class LatencyTrace:
    """The last ``n`` traced segments' (sent, applied) times, Unix s, in a ring allocated (and
    written, so resident) up front: the daemon's memory does not creep up as it fills."""

    def __init__(self, n: int = TRACE_RECORDS):
        self.rows = np.full((n, 2), np.nan)
        self.count = 0  # records ever added

    def add(self, sent: float, applied: float, times: int = 1) -> None:
        for _ in range(min(times, len(self.rows))):
            self.rows[self.count % len(self.rows)] = (sent, applied)
            self.count += 1

    def since(self, t: float) -> tuple[list[float], list[float]]:
        """(sent, applied) of the records whose raw chunk was published at ``t`` or later."""
        n = len(self.rows)
        order = np.arange(self.count - min(self.count, n), self.count) % n
        rows = self.rows[order]
        rows = rows[rows[:, 0] >= t]
        return rows[:, 0].tolist(), rows[:, 1].tolist()


def serve(session: zenoh.Session, cloud: Cloud, node_id: str, stop: threading.Event,
          default_export: Path | None = None, durability: Durability | None = None,
          shard: frozenset[str] | None = None) -> None:
    """Apply each message on the zenoh thread that delivers it, one at a time under a lock.

    No queue between the subscription and the aggregator: a hand-off per message cost as much as
    decoding it. While a message is being applied zenoh holds back the next one, so a busy cloud
    slows its publishers (they publish with ``CongestionControl.BLOCK``) instead of buffering
    without bound. Queries are answered under the same lock, from state that has applied every
    message delivered so far. The calling thread publishes a held-back status and runs calibration
    rounds once the bus has been quiet for ``QUIET_S``.
    """
    lock = threading.Lock()
    traced = LatencyTrace()
    # CPU of the message callbacks (thread time): in the cloud's own code (``apply_s``), and with
    # the hand-over from zenoh (``callback_s``); the process's total is the OS's (benchmarks).
    cpu = {"messages": 0, "apply_s": 0.0, "callback_s": 0.0}
    last_input = time.monotonic()

    def apply(on_message, sample, kind: str) -> None:
        nonlocal last_input
        t0 = time.thread_time()
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        trace = sample.attachment
        with lock:
            t1 = time.thread_time()
            try:
                if durability is not None:  # journalled before it can affect any state
                    durability.record(kind, key, payload)
                before = cloud.aggregator.accepted
                on_message(key, payload)
                accepted = cloud.aggregator.accepted - before  # segments: a batch holds several
                if trace is not None and accepted:
                    trace = trace.to_bytes()
                    if len(trace) == TRACE.size:
                        traced.add(TRACE.unpack(trace)[0], time.time(), accepted)
            except Exception:  # a daemon never dies of one message; it is counted and logged
                cloud.aggregator.rejected["internal_error"] += 1
                log.exception("failed to process %s", key)
            last_input = time.monotonic()
            t2 = time.thread_time()
            cpu["messages"] += 1
            cpu["apply_s"] += t2 - t1
            cpu["callback_s"] += t2 - t0

    def on_state(query):
        with query:
            try:
                parts = str(query.key_expr).split("/")
                if len(parts) != 6 or "*" in parts[4] or "*" in parts[5]:
                    raise ValueError
                route, tile_i = parts[4], int(parts[5])
            except ValueError:
                query.reply_err(b"expected driveby/<net>/state/profile/<route>/<tile>")
                return
            with lock:
                data = cloud.tile_state(route, tile_i)
            if data is None:
                query.reply_err(f"unknown route {route}".encode())
            else:
                query.reply(keys.state_profile_key(cloud.net, route, tile_i), data)

    def on_export(query):
        with query:
            params = dict(p.split("=", 1) for p in str(query.parameters).split(";") if "=" in p)
            target = params.get("dir") or (str(default_export) if default_export else None)
            if not target:
                query.reply_err(b"no export directory: pass ?dir=PATH or start the daemon with --export")
                return
            with lock:
                try:
                    written = cloud.export(Path(target))
                except OSError as e:
                    query.reply_err(f"export failed: {e}".encode())
                    return
                body = {"written": [str(p) for p in written], "stats": cloud.aggregator.stats()}
            query.reply(keys.control_key(cloud.net, node_id, "export"), json.dumps(body).encode())

    def on_stats(query):
        with query:
            with lock:
                body = {"stats": cloud.aggregator.stats(), "passes_complete": cloud.passes_complete, "cpu": cpu,
                        **({"durability": durability.stats()} if durability is not None else {})}
            query.reply(keys.control_key(cloud.net, node_id, "stats"), json.dumps(body).encode())

    def on_latency(query):  # ?since=T: the traced segments whose raw chunk was published at T or later
        with query:
            params = dict(p.split("=", 1) for p in str(query.parameters).split(";") if "=" in p)
            try:
                since = float(params.get("since", "-inf"))
            except ValueError:
                query.reply_err(b"since: expected Unix seconds")
                return
            with lock:
                sent, applied = traced.since(since)
            body = {"sent": sent, "applied": applied}
            query.reply(keys.control_key(cloud.net, node_id, "latency"), json.dumps(body).encode())

    decl = [
        session.declare_subscriber(keys.done_keyexpr(cloud.net), lambda sample: apply(cloud.on_done, sample, DONE)),
        session.declare_queryable(keys.control_key(cloud.net, node_id, "export"), on_export),
        session.declare_queryable(keys.control_key(cloud.net, node_id, "stats"), on_stats),
        session.declare_queryable(keys.control_key(cloud.net, node_id, "latency"), on_latency),
    ]
    # A shard subscribes to, and answers state queries for, its own routes only: Zenoh routes each
    # segment and each query to its owner, so scaling out needs no routing code of ours.
    for route in sorted(shard) if shard is not None else ["*"]:
        decl.append(session.declare_subscriber(keys.ap_keyexpr(cloud.net, route),
                                               lambda sample: apply(cloud.on_segment, sample, AP)))
        decl.append(session.declare_queryable(keys.state_profile_keyexpr(cloud.net, route), on_state))

    def on_bridge_state(query, bridge_id: str):
        with query:
            with lock:
                body = cloud.bridge_state(bridge_id)
            query.reply(keys.state_bridge_key(cloud.net, bridge_id), body)

    if shard is not None and cloud.calibrator is not None:
        # Each vehicle is calibrated by one shard (Cloud.owns); the others apply what it publishes.
        decl.append(session.declare_subscriber(keys.calib_keyexpr(cloud.net),
                                               lambda sample: apply(cloud.on_calibration, sample, CALIB)))
    for bid in cloud.bridges.bridges:  # this aggregator's bridges (a shard's: those on its routes)
        decl.append(session.declare_queryable(keys.state_bridge_key(cloud.net, bid),
                                              lambda query, bid=bid: on_bridge_state(query, bid)))
    token = session.liveliness().declare_token(keys.alive_key(cloud.net, "cloud", node_id))
    try:
        while not stop.wait(STATUS_INTERVAL_S):
            try:
                with lock:
                    quiet = time.monotonic() - last_input >= QUIET_S
                    cloud.flush_status(force=quiet)
                    if quiet:  # align, calibrate and estimate bridges when the bus is quiet
                        cloud.fuse_pending(FLUSH_BUDGET_S)  # bounded: the next input waits on the lock
                        if cloud.maybe_align():
                            cloud.bridge_sync_due = True  # the passes' held segments may have moved
                        else:
                            # (A round journals the calibrator through cloud.record before publishing.)
                            cloud.maybe_calibrate(tail=cloud.since_new_pass_s() >= EPOCH_TAIL_S)
                            if cloud.has_rail():
                                cloud.rail.step(cloud)  # carriage batches (issue #6)
                            # Bridges take passes at their vehicle's current calibration only, so a
                            # round just published leaves them as they are until recomputed.
                            cloud.maybe_estimate_bridges()
                        cloud.flush_spill()
                        if durability is not None:
                            durability.maybe_snapshot()
                    elif cloud.bridges_may_run():  # streaming: bridges within their share of the time
                        cloud.maybe_estimate_bridges()
            except Exception:
                log.exception("calibration round failed")
    finally:
        token.undeclare()
        for d in decl:
            d.undeclare()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="driveby cloud", description="cloud aggregator daemon")
    add_zenoh_arguments(p)
    p.add_argument("--net", default="net")
    p.add_argument("--id", default="cloud-1", help="this daemon's id (liveliness, control keys)")
    p.add_argument("--site", required=True, help="site registry TOML")
    p.add_argument("--routes", metavar="R1,R2,…",
                   help="own only these routes (a shard: segments, state queries, bridges; default: every route)")
    p.add_argument("--calibration", choices=("fleet", "nominal"), default="fleet",
                   help="fleet: calibrate every vehicle from the fleet's consensus; nominal: trust the edges")
    p.add_argument("--align", action="store_true",
                   help="align passes in chainage against the consensus (logs with GNSS bias / odometry error)")
    p.add_argument("--export", type=Path, help="default export directory")
    p.add_argument("--state", type=Path, metavar="DIR",
                   help="durable state (journal + snapshots): a restarted cloud resumes from it")
    p.add_argument("--max-resident-segments", type=int, default=DEFAULT_MAX_RESIDENT, metavar="N",
                   help="keep at most N segments decoded in memory, the rest spilled to disk (under --state, "
                        "else the temporary directory) and read back exactly when needed "
                        f"(default {DEFAULT_MAX_RESIDENT}, ~4 kB each)")
    p.add_argument("--max-resident-passes", type=int, default=DEFAULT_MAX_RESIDENT_PASSES, metavar="N",
                   help="keep the bookkeeping of at most N passes (the most recent) in memory, the rest on disk "
                        f"like spilled segments (default {DEFAULT_MAX_RESIDENT_PASSES}, a few kB each)")
    p.add_argument("--rrd", type=Path, help="save the Rerun recording to this file")
    p.add_argument("--viewer", action="store_true", help="spawn a Rerun viewer")
    p.add_argument("--log-level", default="WARNING")
    args = p.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s cloud %(levelname)s %(message)s")
    try:
        site = load_site(args.site)
        keys.check_id(args.net, "net")
        keys.check_id(args.id, "id")
        conf = config_from_args(args)
        if args.max_resident_segments < 1:
            raise ValueError(f"--max-resident-segments: expected >= 1, got {args.max_resident_segments}")
        if args.max_resident_passes < MIN_RESIDENT_PASSES:
            raise ValueError(f"--max-resident-passes: expected >= {MIN_RESIDENT_PASSES}, "
                             f"got {args.max_resident_passes}")
        journal = Journal(args.state) if args.state else None
        shard = None
        if args.routes:
            shard = frozenset(r.strip() for r in args.routes.split(",") if r.strip())
            unknown = sorted(shard - {r.id for r in site.routes})
            if unknown or not shard:
                raise ValueError(f"--routes: {', '.join(unknown) or 'empty'}: not a route of {args.site}")
    except (RegistryError, ValueError, JournalError) as e:
        print(f"driveby cloud: {e}", file=sys.stderr)
        return 2
    view = None
    if args.rrd or args.viewer:
        from cloud.view import View

        view = View(rrd_path=args.rrd, spawn_viewer=args.viewer, routes={r.id: r.length_m for r in site.routes},
                    bridges=list(site.bridges))
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    durability = None
    try:
        with zenoh.open(conf) as session:
            calib_prefix = keys.calib_key(args.net, "x")[:-1]

            def publish(key, payload):
                if durability is not None:
                    if durability.live and key.startswith(calib_prefix):
                        durability.record(CALIB, key, payload)  # the cloud's own decisions are state too
                    durability.before_publish()  # nothing leaves that promises more than is on disk
                session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

            cloud = Cloud(args.net, site, publish, view, calibration=args.calibration, node_id=args.id,
                          align=args.align, shard=shard, max_resident=args.max_resident_segments,
                          spill_dir=args.state, max_resident_passes=args.max_resident_passes)
            if journal is not None:
                durability = Durability(journal, cloud)
                durability.recover()
                durability.live = True
                cloud.record = durability.record_own
            # What exists now (modules, numba and pyarrow internals, the session) lives as long as the
            # process: keep it out of full garbage collections, whose pause scans every tracked object
            # (~0.1 s of them) and would land in the middle of the stream.
            gc.collect()
            gc.freeze()
            serve(session, cloud, args.id, stop, args.export, durability, shard)
            if durability is not None:
                durability.maybe_snapshot(force=True)  # a clean stop leaves a compact state: a fast restart
            if args.export:
                cloud.export(args.export)
    except zenoh.ZError as e:
        print(f"driveby cloud: zenoh: {e}", file=sys.stderr)
        return 1
    except JournalError as e:  # the state directory became unusable while running (or at recovery)
        print(f"driveby cloud: --state: {e}", file=sys.stderr)
        return 2
    finally:
        if durability is not None:
            durability.close()
        if view is not None:
            view.close()
    return 0
