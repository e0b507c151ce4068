"""Bridge monitoring in the cloud: the site's bridges fed from completed passes, estimated, alarmed.

Transport-free, like :class:`cloud.daemon.core.Cloud` which owns it. One
:class:`~cloud.bridge.estimator.BridgeEstimator` per bridge of the registry. The daemon calls
:meth:`BridgeMonitor.sync` and :meth:`BridgeMonitor.estimate` when the bus is quiet, never per
segment: a pass's bridge data costs a forward simulation of the vehicle (~50 ms) and an estimate
of the whole bridge ~0.5 s.

``sync`` reconciles what each estimator holds with the aggregator: every acknowledged pass at its
vehicle's current calibration is (re-)added with the segments the road estimators hold for it
(chainage-aligned where alignment moved it) and the parameters the edge computed it with; a pass
recomputed under a new calibration, or re-aligned, replaces its old version (mirroring the road
side's retract/re-add); a pass that no longer crosses the bridge is removed. A pass whose vehicle
has been recalibrated since is kept as it is until its recomputation is acknowledged.

The alarm is a state: :meth:`BridgeMonitor.estimate` returns an :class:`~shared.schema.Alarm` only
when a bridge's damage decision changes — raised (``kind`` = the damage hypothesis: crack,
global, bearings) or cleared (``kind`` = ``"cleared"``) — or when a standing alarm's diagnosis
(its kind or element) changes, e.g. a crack first seen somewhere on the span is located as passes
come in; never once per pass.
"""

from __future__ import annotations

import dataclasses
import datetime
import logging
from collections import Counter
from collections.abc import Callable, Mapping

from shared.registry import Bridge, Site
from shared.schema import Alarm, ApSegment

from cloud.bridge.estimator import BridgeEstimate, BridgeEstimator, BridgeSettings, class_weight_prior

log = logging.getLogger(__name__)

CLEARED = "cleared"  # Alarm.kind of the message that ends an alarm
CATCH_UP_ESTIMATES = 4  # at most this many estimates when many passes arrive at once (one each step)
CATCH_UP_LEAST = 8  # passes per step at least: a few passes at once are one estimate


def catch_up_steps(pending: int) -> list[int | None]:
    """The ``limit`` of each :meth:`BridgeMonitor.sync` that feeds ``pending`` passes arriving at
    once (a calibration epoch ending, a restart) in steps, the last without a limit: estimated after
    each step, the record shows P(damage) and the decision as the passes came in, not one point at
    the end, for at most :data:`CATCH_UP_ESTIMATES` estimates (each costs less than the one before
    it made cheaper: the fit starts from the last)."""
    step = max(CATCH_UP_LEAST, -(-pending // CATCH_UP_ESTIMATES))
    return [step] * ((pending - 1) // step) + [None]


def _utc_now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="milliseconds")


@dataclasses.dataclass
class _Fed:
    calib_version: int
    segments: tuple[ApSegment, ...]  # the held segment objects the pass was last built from


@dataclasses.dataclass
class BridgeState:
    """One bridge: its estimator, what was fed to it, its latest estimate and alarm state."""

    bridge: Bridge
    estimator: BridgeEstimator
    fed: dict[tuple[str, str], _Fed] = dataclasses.field(default_factory=dict)
    dirty: bool = False  # passes changed since the last estimate
    latest: BridgeEstimate | None = None
    alarmed: bool = False
    diagnosis: tuple[str, int] | None = None  # (kind, element) of the standing alarm as last published
    version: int = 0  # estimates made so far


def _diagnosis_moved(old: tuple[str, int] | None, new: tuple[str, int]) -> bool:
    """Whether a standing alarm's diagnosis changed enough to say so again: another kind of damage,
    a place found (or lost), or an element more than one away (neighbours trade places as passes
    come in; an alarm repeated for each would be noise). ``old`` None: not known (a restart)."""
    if old is None:
        return False
    (kind0, e0), (kind1, e1) = old, new
    return kind0 != kind1 or (e0 > 0) != (e1 > 0) or abs(e0 - e1) > 1


def raised_alarm(bridge_id: str, est: BridgeEstimate, time_utc: str) -> Alarm:
    """The alarm an estimate whose assessment alarms raises: the damage, where, its largest element
    loss with the 95 % band, the probability behind the decision."""
    a = est.assessment
    if a.element > 0:
        where = f"element {a.element} (x = {a.location_m:.1f} m)"
    elif a.kind == "crack":  # the passes say the span is damaged, not where
        where = f"an unresolved place (x 95 %: {a.location_lo95:.1f}–{a.location_hi95:.1f} m)"
    else:
        where = "whole bridge"
    return Alarm(bridge_id=bridge_id, time_utc=time_utc, kind=a.kind, element=a.element, x_m=a.location_m,
                 severity=a.severity, probability=min(max(a.loss_probability, 0.0), 1.0),
                 message=f"{a.kind} damage at {where}: largest element loss {100 * a.severity:.1f} % "
                         f"(95 %: {100 * a.severity_lo95:.1f}–{100 * a.severity_hi95:.1f} %), "
                         f"P(loss > alarm threshold) = {a.loss_probability:.3f} after {est.n_passes} passes")


class BridgeMonitor:
    """The bridges of a site. ``settings``: how every bridge is estimated (deck, dynamics, alarm)."""

    def __init__(self, site: Site, settings: BridgeSettings = BridgeSettings(), clock: Callable[[], str] = _utc_now):
        self.site, self.settings, self.clock = site, settings, clock
        self.skipped: Counter[str] = Counter()  # passes not used, by reason
        self.model, prior = self._weight_prior(site)
        self.bridges: dict[str, BridgeState] = {}
        if prior is None:
            if site.bridges:
                log.warning("no single-contact vehicle class in the registry: bridges are not estimated")
            return
        for b in site.bridges:  # each bridge's deck is the registry's word on it
            self.bridges[b.id] = BridgeState(b, BridgeEstimator(b, prior, dataclasses.replace(settings, deck=b.deck)))

    @staticmethod
    def _weight_prior(site: Site):
        """The wheel-load prior of the first single-contact vehicle class (the estimator's fleet)."""
        for vc in site.vehicle_classes:
            try:
                return vc.model, class_weight_prior(site, vc.model)
            except (ValueError, KeyError):
                continue
        return None, None

    @property
    def due(self) -> bool:
        return any(st.dirty for st in self.bridges.values())

    # -- data ------------------------------------------------------------------------------
    def _changed(self, passes: Mapping, held: Mapping[tuple, ApSegment]):
        """The (key, pass state, its held segments, bridge) pairs a sync would (re-)feed, in the
        aggregator's order: acknowledged passes on a bridge's route that the bridge does not hold
        as they are now."""
        for key, ps in passes.items():
            if not ps.acked or not ps.slots:
                continue
            bridges = [st for st in self.bridges.values() if st.bridge.route == ps.route_id]
            if not bridges:
                continue
            segs = tuple(held[sl] for sl in sorted(ps.slots) if sl in held)
            for st in bridges:
                fed = st.fed.get(key)
                if fed is not None and fed.calib_version == ps.calib_version and len(fed.segments) == len(segs) \
                        and all(a is b for a, b in zip(fed.segments, segs)):
                    continue  # unchanged
                yield key, ps, segs, st

    def unfed(self, passes: Mapping, held: Mapping[tuple, ApSegment]) -> int:
        """How many passes a sync would (re-)feed now (a pass counted once per bridge it is on)."""
        return sum(1 for _ in self._changed(passes, held)) if self.bridges else 0

    def sync(self, passes: Mapping, held: Mapping[tuple, ApSegment],
             params_of: Callable[[str, str, int], dict | None],
             uncertainty_of: Callable[[str, str, int], dict | None] | None = None, limit: int | None = None) -> int:
        """Bring every estimator up to date with the aggregator; returns the passes (re-)added.

        ``passes``: ``Aggregator.passes`` ((vehicle, pass) → PassState); ``held``: the segments the
        estimators hold per slot; ``params_of(vehicle, model, calib_version)``: the parameters the
        edge used for that calibration version, or None if it is not the vehicle's current one;
        ``uncertainty_of(vehicle, model, calib_version)``: the log-sd of those parameters' calibration
        quantities (None: the estimator's default); ``limit``: feed at most this many passes, the
        earliest first (a caller catching up estimates after each such step, so that its record
        shows the estimate as the passes came in).
        """
        if not self.bridges:
            return 0
        changed = 0
        for n, (key, ps, segs, st) in enumerate(list(self._changed(passes, held))):
            if limit is not None and n >= limit:
                break
            fed = st.fed.get(key)
            if ps.model and ps.model != self.model:  # the estimator models single-contact vehicles
                self.skipped["unsupported_model"] += 1
                st.fed[key] = _Fed(ps.calib_version, segs)
                continue
            # What the edge says it used (pass-done v1.2), else what the cloud knows it sent.
            params = ps.params if ps.params is not None else \
                params_of(ps.vehicle_id, ps.model or self.model, ps.calib_version)
            if params is None:
                continue  # a newer calibration is on its way: wait for the recomputed pass
            sd = None if uncertainty_of is None else \
                uncertainty_of(ps.vehicle_id, ps.model or self.model, ps.calib_version)
            try:
                crosses = st.estimator.add_segments(segs, ps.model or self.model, params, params_log_sd=sd,
                                                    sample_interval_s=ps.sample_interval_s)
            except (ValueError, KeyError, FloatingPointError, ArithmeticError) as e:
                log.warning("bridge %s: pass %s/%s not usable: %s", st.bridge.id, *key, e)
                self.skipped["unusable"] += 1
                crosses = False
            if not crosses and fed is not None:
                st.estimator.remove(*key)
            st.fed[key] = _Fed(ps.calib_version, segs)
            st.dirty = st.dirty or crosses or fed is not None
            changed += crosses
        return changed

    # -- estimation --------------------------------------------------------------------------
    def estimate(self) -> list[Alarm]:
        """Estimate every bridge with new data; the alarms whose state changed."""
        alarms = []
        for st in self.bridges.values():
            if not st.dirty:
                continue
            st.dirty = False
            est = st.estimator.estimate()
            if est is None:
                continue
            st.latest, st.version = est, st.version + 1
            alarm = self._alarm(st, est)
            if alarm is not None:
                alarms.append(alarm)
        return alarms

    def _alarm(self, st: BridgeState, est: BridgeEstimate) -> Alarm | None:
        a = est.assessment
        raised = bool(a is not None and a.alarm)
        diagnosis = (a.kind, int(a.element)) if raised else None
        if raised == st.alarmed and (not raised or not _diagnosis_moved(st.diagnosis, diagnosis)):
            return None
        st.alarmed, st.diagnosis = raised, diagnosis
        if raised:
            return raised_alarm(st.bridge.id, est, self.clock())
        p = 0.0 if a is None else min(max(a.loss_probability, 0.0), 1.0)
        return Alarm(bridge_id=st.bridge.id, time_utc=self.clock(), kind=CLEARED, element=-1, x_m=0.0, severity=0.0,
                     probability=p, message=f"alarm cleared after {est.n_passes} passes")

    def final(self) -> dict[str, BridgeEstimate | None]:
        """The latest estimate of every bridge (None before it has enough passes)."""
        return {bid: st.latest for bid, st in self.bridges.items()}

    # -- export rows (interfaces.md §3) --------------------------------------------------------
    def element_rows(self) -> list[dict]:
        return [r for st in self.bridges.values() if st.latest is not None for r in st.latest.element_rows()]

    def bearing_rows(self) -> list[dict]:
        return [r for st in self.bridges.values() if st.latest is not None for r in st.latest.bearing_rows()]

    def summary_rows(self) -> list[dict]:
        """One row per bridge of the registry; a bridge without an estimate yet has NaN indicators."""
        nan = float("nan")
        rows = []
        for bid, st in self.bridges.items():
            if st.latest is not None:
                rows.append(st.latest.summary_row())
            else:
                rows.append(dict(bridge_id=bid, n_passes=st.estimator.n_passes, D1_pct=nan, D2_pct=nan,
                                 midspan_mril=nan, damaged=False))
        return rows
