"""Rail batches in the cloud daemon: a carriage's runs over a route, calibrated together.

The cloud holds each carriage pass as AP segments under its four wheels (the edge's inverse with the
class-mean properties, keyed on GNSS chainage; the trailing bogie's wheels from before chainage 0 on,
see ``shared.vehicles.RAIL_MODELS``). What :func:`cloud.rail.calibration.calibrate_batch` needs — each
run's bogie channels in time — is rebuilt from them: the carriage's forward model under the
parameters the edge used, driven by the four APs. The edge's inverse is the exact inverse of that
discretisation (Newmark γ = 0.8, trapezoidal contact rate), so the calibration's inverse under trial
properties sees what it would have seen from the raw channels, up to the edge's quantisation and
drift control (slow: the calibration removes a cubic anyway). The rebuilt step is the cloud's own
(``RESYNTH_DT_S``): the edge's is not on the wire, and the forward–inverse pair is exact at any step.

After a batch fit, each run's AP is recomputed under its calibrated properties and re-keyed in
chainage with its calibrated speed (x = x₀ + v·t + offset), and the estimators are given that in
place of the edge's version — the cloud re-maps, as it does for chainage alignment
(:func:`cloud.road.alignment.realign`), rather than asking the edge to recompute: a run's mass and speed
belong to that run alone (a ``calib/<vehicle>`` message sets the properties of passes to come), and
the cloud has everything it needs.

A registry bridge on the route gets, from every fitted batch, the leading bogie's MR-IL per unit
wheel load (:func:`cloud.rail.bridge.influence_of_aps`, wheel loads from the calibrated masses,
every run registered on the wheels' difference beside the span) and, from it, the span's stiffness
against its design drawings: one factor for the whole span (:func:`cloud.rail.bridge.design_scale`;
the bogie's line on a short span does not resolve elements), with a 95 % interval from resampling
the runs. The bridge's healthy baseline is the set of runs of the first session (daemon run) that
crossed it: while that session lasts it grows with every fit; restored from the cloud's state in a
later session (:meth:`RailBatches.restore_baseline`; the daemon journals
:attr:`RailStep.baselines`) it is fixed, and the runs that are not in it are the current batch, read
against it (a daemon restarted mid-session is a later session too: the state does not say whether a
batch was complete): D1/D2 (eq. 3.24) from the change of the batch means with the healthy line pooled over
both batches (:func:`cloud.rail.bridge.damage_from_batch_means`, :func:`~cloud.rail.bridge.pooled_healthy`),
and the alarm. (The bridge element posterior of :mod:`cloud.bridge.monitor` models single-contact
vehicles on a rigid deck, not a carriage on ballasted track: the rail readings take its place in
the bridge summary, elements and alarm.)

Transport-free, like :class:`~cloud.bridge.monitor.BridgeMonitor`: :meth:`RailBatches.step` takes the
aggregator's passes and stored segments and returns a :class:`RailStep` — the re-keyed segments
the estimators are to hold, and the rail bridges' alarms whose state changed — which the daemon
applies through the aggregator and publishes. Results besides: ``vehicles.parquet`` rows per run
(``pass_id``), ``bridge_summary.parquet`` rows of rail bridges, and the rows of the view's rail
panels (:meth:`RailBatches.view_rows`: run estimates, EN 13848 D1 track quality, bridges' MR-IL
and D1/D2).
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import logging
import math
from collections.abc import Callable, Mapping

import numpy as np
from scipy.interpolate import make_interp_spline

from shared.dynamics.forward import channels_from_ap
from shared.dynamics.newmark import newmark_constants
from shared.dynamics.population import population_aps
from shared.schema import Alarm, ApSegment
from shared.track_quality import (ALERT_ISOLATED_MM, ALERT_SD_MM, d1_longitudinal_level, isolated_defects,
                                  segment_quality)
from shared.vehicles import vehicle_from_params

from cloud.bridge.mril import MrIl, damage_indicators
from cloud.bridge.monitor import CLEARED
from cloud.rail.bridge import (BogieInfluence, damage_from_batch_means, design_scale, influence_of_aps, pooled_healthy,
                               readable_line, registered_runs, resampled_runs, run_aps)
from cloud.rail.calibration import FIXED, RUN_NAMES, BatchFit, calibrate_batch
from cloud.rail.records import RailRun

log = logging.getLogger("driveby.cloud.rail")

CALIBRATED_MODELS = ("carriage",)  # the batch method is the carriage's (4 wheels, bogie spacing)
MIN_RUNS = 4  # fewer runs do not calibrate a batch (speed, masses and globals from their agreement)
REFIT_GROWTH = 1.5  # while streaming, a batch is fitted again once it has this many times the runs
#: Bridges: the fewest runs a bridge reading is made from (a load regression over the runs'
#: masses; the thesis's batches are of 50).
BRIDGE_MIN_RUNS = MIN_RUNS
#: Resamples of a batch's runs for its stiffness interval (:meth:`RailBatches._bridge`).
STIFFNESS_RESAMPLES = 40
Z95 = 1.959963984540054
#: D1 (% stiffness loss, eq. 3.24) at which a rail bridge is alarmed: the thesis's blind test finds
#: damage levels within ~2 points, so 5 % is well clear of its error and below its damaged states'.
BRIDGE_ALARM_PCT = 5.0
CALIBRATION_CLEARANCE_M = 10.0  # the batch calibration compares track this far off any bridge
RESYNTH_DT_S = 0.002  # the step of the rebuilt channels, s
GAMMA = 0.8  # the edge's inverse (and the calibration's): Newmark γ


@dataclasses.dataclass(frozen=True)
class RebuiltPass:
    """One run rebuilt in time from its held AP: channels under the edge's parameters."""

    run: RailRun
    params: dict  # the parameters the edge computed the AP with
    t0_s: float  # time of the first rebuilt sample (the pass's clock)
    slots: dict  # axle → the pass's raw segments of that axle, by start index


def _axle_series(segs: list[ApSegment]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t, chainage, AP, sigma) of one axle's segments in order (time runs linearly along each)."""
    segs = sorted(segs, key=lambda s: s.start_index)
    t = np.concatenate([np.linspace(s.t_first, s.t_last, s.n) for s in segs])
    x = np.concatenate([s.chainage_m for s in segs])
    ap = np.concatenate([s.values for s in segs])
    sigma = np.concatenate([s.sigma for s in segs])
    keep = np.concatenate([[True], np.diff(t) > 0])  # abutting segments never repeat a point; be safe
    return t[keep], x[keep], ap[keep], sigma[keep]


def rebuild_pass(pass_id: str, segments: list[ApSegment], model: str, params: dict,
                 dt: float = RESYNTH_DT_S) -> RebuiltPass | None:
    """A run for the batch calibration from its held AP segments (None if a wheel has none)."""
    by_axle: dict[int, list[ApSegment]] = {}
    for s in segments:
        by_axle.setdefault(s.axle, []).append(s)
    offsets = vehicle_from_params(model, params).system().offsets_m
    if sorted(by_axle) != list(range(1, len(offsets) + 1)):
        return None
    series = [_axle_series(by_axle[i + 1]) for i in range(len(offsets))]
    t_lo = max(s[0][0] for s in series)
    t_hi = min(s[0][-1] for s in series)  # every wheel measured in between
    if t_hi - t_lo < 20 * dt:
        return None
    t = t_lo + dt * np.arange(int(math.floor((t_hi - t_lo) / dt)) + 1)
    # Cubic, as cloud.road.alignment.realign: linear interpolation at fractional offsets low-passes short waves.
    ap = np.stack([make_interp_spline(ti, ai, k=3)(t) for ti, _, ai, _ in series], axis=1)
    x0 = float(np.mean([np.interp(t_lo, ti, xi) - offsets[i] for i, (ti, xi, _, _) in enumerate(series)]))
    speed = float(np.mean([s.speed_mps for s in segments]))
    z = channels_from_ap(vehicle_from_params(model, params).system(), ap, newmark_constants(dt, GAMMA))
    return RebuiltPass(RailRun(pass_id, z, dt, speed, x0), dict(params), float(t_lo),
                       {i: sorted(v, key=lambda s: s.start_index) for i, v in by_axle.items()})


def rekey_pass(rebuilt: RebuiltPass, model: str, params: dict, speed_mps: float,
               shift_m: float = 0.0) -> list[ApSegment]:
    """The run's AP under ``params`` (its calibrated properties), keyed in chainage with its
    calibrated speed and chainage shift (:attr:`~cloud.rail.calibration.RunEstimate.shift_m`), as replacements of its raw segments (same identities; each keeps the grid
    points from where it now starts to where the next one starts, as :func:`cloud.road.alignment.realign`)."""
    run = rebuilt.run
    aps, offs = population_aps(model, [params], run.channels, run.dt, gamma=GAMMA)
    ap, offsets = aps[0], offs[0]
    n = len(ap)
    tk = np.arange(n) * run.dt  # since the first rebuilt sample
    x0 = run.x0_m + shift_m
    out = []
    for i, segs in sorted(rebuilt.slots.items()):
        h = segs[0].spacing_m
        x = x0 + speed_mps * tk + offsets[i - 1]
        spline = make_interp_spline(x, ap[:, i - 1], k=3)
        t_raw, _, _, sigma_raw = _axle_series(segs)
        # Where each raw segment now starts: its first point's time, on the calibrated chainage.
        starts = []
        for s in segs:
            tf = max(s.t_first - rebuilt.t0_s, 0.0)
            starts.append(int(math.ceil((x0 + speed_mps * tf + offsets[i - 1]) / h - 1e-9)))
        starts[0] = int(math.ceil(x[0] / h - 1e-9))
        last = int(math.floor(x[-1] / h + 1e-9))
        for k, s in enumerate(segs):
            i0 = starts[k]
            i1 = starts[k + 1] - 1 if k + 1 < len(segs) else last
            if i1 - i0 < 1:
                continue
            xg = np.arange(i0, i1 + 1) * h
            tg = (xg - x0 - offsets[i - 1]) / speed_mps + rebuilt.t0_s
            sigma = np.interp(tg, t_raw, sigma_raw)
            out.append(ApSegment.make(spline(xg), sigma, vehicle_id=s.vehicle_id, pass_id=s.pass_id,
                                      route_id=s.route_id, tile=s.tile, axle=s.axle, start_index=i0, spacing_m=h,
                                      calib_version=s.calib_version, speed_mps=speed_mps, t_first=float(tg[0]),
                                      t_last=float(tg[-1]), seq=s.seq, flags=s.flags))
    return out


@dataclasses.dataclass
class BatchState:
    """The latest fit of one (vehicle, route) batch."""

    vehicle_id: str
    route_id: str
    passes: frozenset  # (pass_id, calib_version) of the runs it was fitted on
    fit: BatchFit | None = None
    error: str = ""


@dataclasses.dataclass
class RailBridgeState:
    """A registry bridge under a carriage's batches: its healthy baseline and latest bogie MR-IL,
    the span's stiffness against its design, D1/D2."""

    bridge_id: str
    vehicle_id: str = ""
    #: The baseline's runs (pass ids); ``sealed``: restored from an earlier session, so fixed (the
    #: session that sets it extends it with every fit).
    baseline: frozenset = frozenset()
    sealed: bool = False
    reference: MrIl | None = None  # the baseline's line
    latest: MrIl | None = None  # the current batch's line (the baseline's while there is no other)
    n_runs: int = 0  # runs of the latest reading
    d1_pct: float = float("nan")
    d2_pct: float = float("nan")
    damaged: bool = False
    #: The latest reading's span stiffness over its design E·I (mean, 95 % interval): one factor for
    #: every element.
    stiffness: tuple[float, float, float] | None = None
    error: str = ""

    def summary_row(self) -> dict:
        """A ``bridge_summary.parquet`` row (interfaces.md §3)."""
        mid = self.latest.midspan() if self.latest is not None else float("nan")
        return dict(bridge_id=self.bridge_id, n_passes=self.n_runs, D1_pct=self.d1_pct, D2_pct=self.d2_pct,
                    midspan_mril=mid, damaged=self.damaged)

    def baseline_record(self) -> bytes:
        """The baseline as the cloud's state keeps it (:meth:`RailBatches.restore_baseline`)."""
        return json.dumps({"bridge_id": self.bridge_id, "vehicle_id": self.vehicle_id,
                           "passes": sorted(self.baseline)}).encode()


@dataclasses.dataclass(frozen=True)
class RailStep:
    """What one :meth:`RailBatches.step` changed, for the daemon to apply and publish.

    ``replacements``: slot → the run's re-keyed segment for the estimators to hold in place of the
    edge's, or None where nothing of it is left on the route (in the order they are to be applied);
    ``alarms``: rail bridges whose alarm state changed; ``fitted``: the (vehicle, route) batches
    fitted (their passes' held segments and the view's rows changed).
    """

    replacements: dict = dataclasses.field(default_factory=dict)
    alarms: tuple[Alarm, ...] = ()
    fitted: tuple[tuple[str, str], ...] = ()
    #: Rail bridges' baselines that changed (:meth:`RailBridgeState.baseline_record`), for the cloud's
    #: durable state.
    baselines: tuple[bytes, ...] = ()


@dataclasses.dataclass(frozen=True)
class TrackQualityRows:
    """A rail route's EN 13848 D1 longitudinal level for the view: level (m) against chainage (m),
    its quality per 200 m and the isolated defects."""

    route_id: str
    chainage_m: np.ndarray
    d1_m: np.ndarray
    segments: list  # shared.track_quality.SegmentQuality
    defects: list  # (chainage m, D1 mm) beyond the isolated-defect alert limit
    alert_isolated_mm: float = ALERT_ISOLATED_MM
    alert_sd_mm: float = ALERT_SD_MM


@dataclasses.dataclass(frozen=True)
class RailBridgeRows:
    """A rail bridge for the view: its latest and reference bogie MR-IL and D1/D2."""

    bridge_id: str
    x_m: np.ndarray
    J: np.ndarray
    reference_J: np.ndarray
    d1_pct: float
    d2_pct: float
    damaged: bool


@dataclasses.dataclass(frozen=True)
class RailViewRows:
    """What the rail panels of :class:`cloud.view.View` show (:meth:`~cloud.view.View.log_rail`)."""

    runs: tuple  # (vehicle, route, [RunEstimate]) per fitted batch, sorted
    bridges: tuple[RailBridgeRows, ...]
    track: tuple[TrackQualityRows, ...]
    run_names: tuple[str, ...] = RUN_NAMES

    @property
    def routes(self) -> list[str]:
        """The rail routes (those of some batch)."""
        return sorted({route for _, route, _ in self.runs} | {t.route_id for t in self.track})

    @property
    def vehicles(self) -> list[str]:
        """The carriages with a fitted batch."""
        return sorted({vid for vid, _, _ in self.runs})


def span_stiffness(bridge, influence: BogieInfluence, aps: list, span: tuple[float, float],
               resamples: int = STIFFNESS_RESAMPLES) -> tuple[float, float, float]:
    """The span's E·I over its design (one factor): the design's static line of the bogie
    (:func:`cloud.rail.bridge.design_scale`) over the batch's load-regression line, by area; the 95 %
    interval from the runs resampled (a fixed seed: the same batch reads the same interval)."""
    def ratio(inf: BogieInfluence) -> float:
        # relative to the supports after its low-pass, as the design line is
        x, J = inf.mril.x_m, inf.mril.J
        line = readable_line(MrIl(x, J - (J[0] + (J[-1] - J[0]) * x / x[-1]), inf.mril.n_passes), "the batch's line")
        return float(1.0 - damage_indicators(design_scale(bridge, inf).mril, line).D2_pct / 100.0)

    rng = np.random.default_rng(len(aps))
    draws = []
    for _ in range(resamples):
        try:
            draws.append(ratio(influence_of_aps(resampled_runs(aps, rng), *span)))
        except (ValueError, np.linalg.LinAlgError):  # a resample without load spread
            continue
    mean = ratio(influence)
    sd = float(np.std(np.log(draws))) if len(draws) > 2 else float("nan")
    return mean, mean * math.exp(-Z95 * sd), mean * math.exp(Z95 * sd)


def _utc_now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="milliseconds")


class RailBatches:
    """Carriage runs per (vehicle, route): calibrated as a batch when the bus is quiet, re-keyed;
    the registry's bridges on the route get the batches' bogie MR-IL and D1/D2. ``clock`` stamps
    alarms (ISO 8601 UTC)."""

    def __init__(self, site, min_runs: int = MIN_RUNS, bridge_min_runs: int = BRIDGE_MIN_RUNS,
                 alarm_pct: float = BRIDGE_ALARM_PCT, clock: Callable[[], str] = _utc_now):
        self.site = site
        self.min_runs = min_runs
        self.bridge_min_runs = bridge_min_runs
        self.alarm_pct = alarm_pct
        self.clock = clock
        self.batches: dict[tuple[str, str], BatchState] = {}
        self.bridges: dict[str, RailBridgeState] = {}
        self.failed = 0

    def _groups(self, passes) -> dict[tuple[str, str], list]:
        groups: dict[tuple[str, str], list] = {}
        for (vid, pid), ps in passes.items():
            if ps.acked and ps.model in CALIBRATED_MODELS:
                groups.setdefault((vid, ps.route_id), []).append((pid, ps))
        return groups

    def due(self, passes, force: bool = False) -> list[tuple[str, str]]:
        """Batches whose acknowledged runs changed since their last fit (and are enough): while
        runs stream in, only once a batch has grown by ``REFIT_GROWTH`` (a fit's cost grows with its
        runs, and it runs under the daemon's lock); with ``force`` (the export) on any change."""
        out = []
        for key, items in self._groups(passes).items():
            runs = frozenset((pid, ps.calib_version) for pid, ps in items)
            st = self.batches.get(key)
            if len(items) < self.min_runs or (st is not None and st.passes == runs):
                continue
            if force or st is None or len(runs) >= REFIT_GROWTH * len(st.passes):
                out.append(key)
        return out

    def step(self, passes: Mapping, segments: Mapping, force: bool = False) -> RailStep:
        """Fit every batch that is due; return its runs' re-keyed segments and the bridges' alarms.

        ``passes``: the aggregator's passes ((vehicle, pass) → PassState); ``segments``: the stored
        segments by slot (the edge's, not what the estimators hold); ``force``: fit every batch that
        changed at all (:meth:`due`)."""
        due = self.due(passes, force)
        replacements: dict = {}
        alarms: list[Alarm] = []
        baselines: list[bytes] = []
        for key in due:
            self._fit(key, passes, segments, replacements, alarms, baselines)
        return RailStep(replacements, tuple(alarms), tuple(due), tuple(baselines))

    def restore_baseline(self, payload: bytes) -> None:
        """A bridge's baseline from the cloud's state (an earlier session's): fixed from now on."""
        d = json.loads(payload)
        self.bridges[d["bridge_id"]] = RailBridgeState(d["bridge_id"], d["vehicle_id"], frozenset(d["passes"]), True)

    def baseline_records(self) -> list[bytes]:
        """Every rail bridge's baseline, as the cloud's state keeps them."""
        return [bs.baseline_record() for _, bs in sorted(self.bridges.items()) if bs.baseline]

    def _fit(self, key: tuple[str, str], passes, segments, replacements: dict, alarms: list,
             baselines: list) -> None:
        vid, route = key
        items = self._groups(passes)[key]  # in the order the passes first arrived
        st = BatchState(vid, route, frozenset((pid, ps.calib_version) for pid, ps in items))
        self.batches[key] = st
        model = items[0][1].model
        try:
            cls = self.site.vehicle_class(model)
        except KeyError:
            st.error = f"no vehicle class {model!r} in the registry"
            return
        rebuilt = []
        for pid, ps in items:
            params = ps.params if ps.params is not None else (dict(cls.mean) if ps.calib_version == 0 else None)
            if params is None:
                continue
            segs = [segments[sl] for sl in ps.slots if sl in segments]
            rb = rebuild_pass(pid, segs, model, params)
            if rb is not None:
                rebuilt.append(rb)
        if len(rebuilt) < self.min_runs:
            st.error = f"{len(rebuilt)} runs rebuilt, fewer than {self.min_runs}"
            return
        bridges = [b for b in self.site.bridges if b.route == route]
        window = None
        if bridges:  # the bridge's deflection differs run to run (their loads): compare off it
            end = min(b.start_chainage_m for b in bridges) - CALIBRATION_CLEARANCE_M
            window = (-math.inf, end) if end > 40.0 else None  # (else too little track before it)
        try:
            st.fit = calibrate_batch([rb.run for rb in rebuilt], cls.mean, cls.std, window_m=window)
        except (ValueError, np.linalg.LinAlgError) as e:
            self.failed += 1
            st.error = str(e)
            log.warning("rail batch %s/%s: %s", vid, route, e)
            return
        log.info("rail batch %s/%s: %d runs calibrated in %.1f s", vid, route, len(rebuilt), st.fit.seconds)
        fixed = {k: float(cls.mean[k]) for k in FIXED}
        length = {r.id: r.length_m for r in self.site.routes}[route]
        for rb, est in zip(rebuilt, st.fit.runs):
            params = {**fixed, **st.fit.globals_, **est.mean}
            new = {(s.vehicle_id, s.pass_id, s.route_id, s.tile, s.axle): s
                   for s in rekey_pass(rb, model, params, est.mean["v"], est.shift_m)}
            for slot in sorted(passes[(vid, rb.run.pass_id)].slots):
                seg = new.get(slot)
                # None: nothing of it left on the route under the calibrated chainage
                replacements[slot] = seg if seg is not None and seg.start_index * seg.spacing_m <= length else None
        for b in bridges:
            alarm = self._bridge(b, vid, rebuilt, st.fit, cls, baselines)
            if alarm is not None:
                alarms.append(alarm)

    def _bridge(self, bridge, vid: str, rebuilt: list[RebuiltPass], fit: BatchFit, cls,
                baselines: list) -> Alarm | None:
        """The bridge's readings from this fit (module docstring): the baseline's line (extended
        while its session lasts), the current batch's line (the runs not in a sealed baseline), the
        latest one's stiffness against the design, D1/D2; the alarm when its state changes."""
        bs = self.bridges.setdefault(bridge.id, RailBridgeState(bridge.id, vid))
        if bs.vehicle_id != vid:
            return None  # one carriage's batches per bridge (another's loads and calibration differ)
        ids = [r.pass_id for r in fit.runs]
        if not bs.sealed and bs.baseline != frozenset(ids):
            bs.baseline = frozenset(ids)
            baselines.append(bs.baseline_record())
        base = [i for i, p in enumerate(ids) if p in bs.baseline]
        current = [i for i, p in enumerate(ids) if p not in bs.baseline]
        if len(base) < self.bridge_min_runs:
            bs.error = f"{len(base)} baseline runs over the bridge, fewer than {self.bridge_min_runs}"
            return None
        span = (bridge.start_chainage_m, bridge.span_m)
        try:
            aps = run_aps([rb.run for rb in rebuilt], fit, cls.mean, "carriage")
            healthy = influence_of_aps(registered_runs([aps[i] for i in base], *span), *span)
            bs.reference = healthy.mril
            if len(current) < self.bridge_min_runs:
                bs.latest, bs.n_runs = healthy.mril, len(base)
                bs.stiffness = span_stiffness(bridge, healthy, [aps[i] for i in base], span)
                return None
            reg = registered_runs([aps[i] for i in current], *span, reference=healthy.difference_line)
            latest = influence_of_aps(reg, *span)
            ind = damage_from_batch_means(pooled_healthy(healthy, [healthy, latest]), latest)
            bs.latest, bs.n_runs = latest.mril, len(current)
            bs.stiffness = span_stiffness(bridge, latest, reg, span)
        except (ValueError, np.linalg.LinAlgError) as e:
            bs.error = str(e)
            log.warning("rail bridge %s: %s", bridge.id, e)
            return None
        bs.error = ""
        bs.d1_pct, bs.d2_pct = ind.D1_pct, ind.D2_pct
        damaged = bool(ind.D1_pct > self.alarm_pct)
        if damaged == bs.damaged:
            return None
        bs.damaged = damaged
        return Alarm(bridge_id=bridge.id, time_utc=self.clock(), kind="global" if damaged else CLEARED, element=-1,
                     x_m=0.5 * bridge.span_m, severity=max(ind.D1_pct, 0.0) / 100.0,
                     probability=1.0 if damaged else 0.0,
                     message=f"rail batch D1 {ind.D1_pct:.1f} %, D2 {ind.D2_pct:.1f} % against the healthy baseline")

    def bridge_rows(self, road_rows: list[dict] = ()) -> list[dict]:
        """``bridge_summary.parquet`` rows: the road estimator's, with the rail batches' in place of
        a bridge's row where they have one."""
        rail = {bid: bs.summary_row() for bid, bs in self.bridges.items() if bs.reference is not None}
        rows = [rail.pop(r["bridge_id"], r) for r in road_rows]
        return rows + [rail[k] for k in sorted(rail)]

    def element_rows(self, road_rows: list[dict] = ()) -> list[dict]:
        """``bridge_elements.parquet`` rows: the road estimator's, with a rail bridge's in place of
        its rows where the batches read its stiffness (one factor for every element)."""
        out, done = [], set()
        by_id = {b.id: b for b in self.site.bridges}
        for bid, bs in sorted(self.bridges.items()):
            b = by_id.get(bid)
            if bs.stiffness is None or b is None:
                continue
            done.add(bid)
            mean, lo, hi = bs.stiffness
            ei = b.E_pa * b.I_m4
            h = b.span_m / b.n_elements
            out.extend(dict(bridge_id=bid, element=e, x_start_m=e * h, x_end_m=(e + 1) * h, EI_mean=mean * ei,
                            EI_lo95=lo * ei, EI_hi95=hi * ei, stiffness_ratio=mean) for e in range(b.n_elements))
        return [r for r in road_rows if r["bridge_id"] not in done] + out

    def rows(self) -> list[dict]:
        """``vehicles.parquet`` rows: each run's mv, Iv, v with 95 % intervals and its ``pass_id``."""
        out = []
        for (vid, _), st in sorted(self.batches.items()):
            if st.fit is not None:
                out.extend(st.fit.rows(vid))
        return out

    def view_rows(self, snapshots: Mapping) -> RailViewRows:
        """What the view shows: every fitted batch's run estimates, the rail bridges' MR-IL and D1/D2,
        and each rail route's D1 track quality from its profile snapshot (``snapshots``: route →
        :class:`~cloud.road.mean_profile.ProfileSnapshot`)."""
        runs = tuple((vid, route, list(st.fit.runs)) for (vid, route), st in sorted(self.batches.items())
                     if st.fit is not None)
        bridges = tuple(RailBridgeRows(bid, bs.latest.x_m, bs.latest.J, bs.reference.J, bs.d1_pct, bs.d2_pct,
                                       bs.damaged)
                        for bid, bs in sorted(self.bridges.items()) if bs.latest is not None)
        track = []
        for route in sorted({route for _, route in self.batches}):
            snap = snapshots.get(route)
            if snap is None:
                continue
            x = np.asarray(snap.chainage_m, float)
            spacing = float(x[1] - x[0]) if x.size > 1 else 0.05
            d1 = d1_longitudinal_level(snap.elevation_m, spacing)
            track.append(TrackQualityRows(route, x, d1, segment_quality(x, d1), isolated_defects(x, d1, ALERT_ISOLATED_MM)))
        return RailViewRows(runs, bridges, tuple(track))
