"""How one cloud aggregator behaves: a frozen, validated value the daemon builds once and passes in."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from cloud.bridge.estimator import BridgeSettings
from cloud.ingest.aggregator import MIN_RESIDENT_PASSES

CALIBRATIONS = ("fleet", "nominal")


@dataclasses.dataclass(frozen=True)
class CloudSettings:
    """Every knob of the cloud core. Times are seconds of the core's clock.

    Estimates
    ---------
    spacing_m : grid spacing (m) of the fused profile.
    calibration : ``"fleet"`` calibrates every vehicle from the fleet's consensus; ``"nominal"``
        trusts the parameters the edges computed with.
    drift_knot_m : knot spacing (m) of each pass's own drift, a nuisance of the profile posterior
        (:mod:`cloud.road.pass_drift`); None leaves the drift to the band's measured long-wave term.
        The posterior, its τ and drift level are a function of the held segments alone, not of
        their history, so replays agree.
    continuous_aps : fuse road passes as continuous-time APs. The edge's inverse (Newmark γ 0.6 /
        0.8, for stability) distorts every AP of a vehicle class alike, so the profile, its IRI and
        the fleet calibration would all carry that bias. The cloud has the whole pass, so it
        corrects each complete one under the parameters the edge computed it with
        (:func:`cloud.road.continuous.continuous_segments`, non-causal); the edge's AP stays the
        inverse's exact output, which the remap, the bridge and rail rebuild the channels from. The
        correction costs several times the rest of ingest, so it is idle work
        (:meth:`Cloud.fuse_pending`), never on the ingest path.
    bridge : how every bridge is estimated.

    Chainage alignment (GNSS bias, odometry stretch)
    ------------------------------------------------
    align : align road passes in chainage against the consensus of the others (on by default: a
        fleet's GNSS biases of metres smear the fused profile and teach the calibration a shifted
        road). On passes already in one frame it estimates shifts below ``align_apply_m`` and
        re-grids nothing. Rail runs are placed by their batches, never aligned. The sweeps are
        idle work (:meth:`Cloud.maybe_align`), never on the ingest path.
    align_min_score : correlation below this: the pass and the consensus overlap too little.
    align_min_passes : fewer aligned passes do not define a frame worth centring on.
    align_iterations : sweeps against the others' improving consensus when new passes came in.
    align_max_stretch : odometry scale errors beyond this are a fault, not an error to align.
    align_tol_m : sweeps stop once no pass's implied position moves more than this (m).
    align_apply_m : a pass is re-gridded only if alignment moves it more than this somewhere (m):
        below it, re-gridding would only blur the pass.
    align_budget_s : a sweep runs in slices of about this long (each overruns it by at most one
        pass's estimate or re-gridding), one per quiet tick, so the daemon's lock is never held for a
        whole sweep (whose cost grows with the passes) and input waits at most a slice; ``inf``: a
        whole sweep per call.

    Calibration epochs (reproducible rounds)
    ----------------------------------------
    An epoch is a fixed prefix of the passes in the order they were first acknowledged; its rounds
    see exactly those passes, each at its vehicle's current calibration. Epoch sizes are boundaries
    of the completed-pass count: ``epoch_first`` (a cold start on fewer passes costs a full round
    budget and is soon redone), then doubling, the step capped at ``epoch_max_step``, so which
    passes a round sees is a function of the data, not of when the bus happened to be quiet.

    epoch_first, epoch_max_step : see above.
    epoch_tail_s : passes beyond the last boundary join a (tail) epoch once no new pass has
        completed for this long: the one timing-dependent decision, there for liveness.
    refresh_wait_s : an epoch pass still at an older calibration (the edge finished it with the
        old parameters after the new ones arrived) is recomputed by re-issuing its vehicle's
        calibration under a new version; one that still does not come back within this long (its
        raw data evicted from the edge's spool) is left out of the epoch's rounds.
    reissue_after_s : …and only this long after the vehicle's current calibration was published:
        before that, the edge may simply not have started recomputing.
    round_budget_s : a round's vehicle steps are taken in slices of about this long (each overruns it
        by at most one vehicle's step), one per quiet tick, and the round applied with the last, so the
        daemon's lock is never held for a whole round (whose cost grows with the vehicles); the same
        result as one call. ``inf``: a whole round per call.

    Scheduling
    ----------
    quiet_s : rounds, alignment, rail and bridge estimates run once no input has arrived for this long.
    status_interval_s : the status is published at most this often (and this late) while acks stream in.
    status_heartbeat_s : while quiet, the status is published again this often, unchanged or not, so a
        subscriber that missed the last one (lost while a router restarted) has it within this long.
    bridge_duty : while segments stream in, bridge estimates take at most this share of the
        cloud's time, so the bridge view still updates pass by pass during a fast replay.
    flush_budget_s : per quiet tick, at most this long encoding resident segments into the spill
        index (:meth:`Cloud.flush_spill`), so a snapshot copies stored payloads instead of
        encoding every segment with the serve loop held; also the budget of one tick's fusion.

    Memory and ownership
    --------------------
    shard : the routes this aggregator owns (None: every route); it sees the site as those routes
        and their bridges, and ignores pass-dones of the other shards' routes.
    max_resident : segments kept decoded in memory (None: all); the rest spilled under ``spill_dir``.
    max_resident_passes : passes' bookkeeping kept in memory (None: all); the rest on disk.
    spill_dir : where spilled segments and passes go (None: the system's temporary directory).
    """

    spacing_m: float = 0.05
    calibration: str = "nominal"
    drift_knot_m: float | None = 25.0
    continuous_aps: bool = True
    bridge: BridgeSettings = BridgeSettings()

    align: bool = True
    align_min_score: float = 0.5
    align_min_passes: int = 2
    align_iterations: int = 6
    align_max_stretch: float = 0.06
    align_tol_m: float = 0.02
    align_apply_m: float = 0.10
    align_budget_s: float = 0.05

    epoch_first: int = 8
    epoch_max_step: int = 64
    epoch_tail_s: float = 1.0
    refresh_wait_s: float = 5.0
    reissue_after_s: float = 1.0
    round_budget_s: float = 0.25

    quiet_s: float = 0.2
    status_interval_s: float = 0.1
    status_heartbeat_s: float = 2.0
    bridge_duty: float = 0.2
    flush_budget_s: float = 0.01

    shard: frozenset[str] | None = None
    max_resident: int | None = None
    max_resident_passes: int | None = None
    spill_dir: Path | None = None

    def __post_init__(self):
        def require(ok: bool, name: str, expected: str) -> None:
            if not ok:
                raise ValueError(f"CloudSettings.{name}: expected {expected}, got {getattr(self, name)!r}")

        require(math.isfinite(self.spacing_m) and self.spacing_m > 0, "spacing_m", "a positive spacing (m)")
        require(self.calibration in CALIBRATIONS, "calibration", f"one of {CALIBRATIONS}")
        require(self.drift_knot_m is None or (math.isfinite(self.drift_knot_m) and self.drift_knot_m > 0),
                "drift_knot_m", "None or a positive spacing (m)")
        require(0.0 <= self.align_min_score <= 1.0, "align_min_score", "a correlation in [0, 1]")
        require(self.align_min_passes >= 1, "align_min_passes", ">= 1")
        require(self.align_iterations >= 1, "align_iterations", ">= 1")
        require(0.0 < self.align_max_stretch < 1.0, "align_max_stretch", "a fraction in (0, 1)")
        require(self.align_budget_s >= 0, "align_budget_s", "a duration >= 0 (s; inf: unbounded)")
        require(self.round_budget_s >= 0, "round_budget_s", "a duration >= 0 (s; inf: unbounded)")
        for name in ("align_tol_m", "align_apply_m", "epoch_tail_s", "refresh_wait_s", "reissue_after_s",
                     "quiet_s", "status_interval_s", "status_heartbeat_s", "flush_budget_s"):
            value = getattr(self, name)
            require(math.isfinite(value) and value >= 0, name, "a finite value >= 0")
        require(self.epoch_first >= 1, "epoch_first", ">= 1")
        require(self.epoch_max_step >= 1, "epoch_max_step", ">= 1")
        require(0.0 < self.bridge_duty <= 1.0, "bridge_duty", "a share in (0, 1]")
        if self.shard is not None:
            object.__setattr__(self, "shard", frozenset(self.shard))
        require(self.shard is None or len(self.shard) > 0, "shard", "None or a non-empty set of route ids")
        require(self.max_resident is None or self.max_resident >= 1, "max_resident", "None or >= 1")
        require(self.max_resident_passes is None or self.max_resident_passes >= MIN_RESIDENT_PASSES,
                "max_resident_passes", f"None or >= {MIN_RESIDENT_PASSES}")
        if self.spill_dir is not None:
            object.__setattr__(self, "spill_dir", Path(self.spill_dir))
