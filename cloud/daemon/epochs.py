"""Calibration epochs: which passes a fleet-calibration round sees, and waiting for recomputed ones.

An epoch is a fixed prefix of the passes in the order they were first acknowledged
(:class:`~cloud.daemon.settings.CloudSettings` says how its size grows). Its rounds see exactly
those passes, each at its vehicle's current calibration, so a round is a function of the data and
a restarted cloud replays the same rounds. A pass the edge finished with older parameters is
waited for; its vehicle's calibration is re-issued if the edge seems to have missed it, and a pass
that never comes back is left out of the rounds until it does.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable

from shared.schema import Calibration

from cloud.daemon.settings import CloudSettings

log = logging.getLogger("driveby.cloud")

PassKey = tuple[str, str]  # (vehicle, pass)


class Epochs:
    """The epochs of one cloud's fleet calibrator: completion order, current epoch, waits.

    ``calibrator`` is the cloud's :class:`~cloud.road.fleet_calibration.FleetCalibrator` (None:
    nominal calibration, no epochs: nothing here grows with the passes); ``clock`` gives
    monotonic seconds.
    """

    def __init__(self, calibrator, settings: CloudSettings, clock: Callable[[], float]):
        self.calibrator, self.settings, self.clock = calibrator, settings, clock
        self.order: list[PassKey] = []  # passes in first-acknowledgement order
        self._in_order: set[PassKey] = set()  # the same passes, for membership
        self.size = 0  # the current epoch: the first ``size`` passes of ``order``
        self.round0 = 0  # the calibrator's round count when it began
        self.tail = 0  # epochs closed by ``epoch_tail_s`` rather than a boundary (timing-dependent)
        self._new_pass_at = clock()
        #: when a recomputed pass was last acknowledged: while they keep coming the edge is working
        #: through its recomputations, and a pass not yet back is queued, not lost. (Not new passes'
        #: acks: under steady traffic those never stop, and an evicted pass would stall the rounds.)
        self._recomputed_at = clock()
        self._refreshed: dict[str, tuple[int, float]] = {}  # vehicle → (version re-issued, when)
        self._issued_at: dict[str, float] = {}  # vehicle → when its current calibration was published
        self._excluded: set[PassKey] = set()  # epoch passes that never came back (``refresh_wait_s``)

    # -- the passes ----------------------------------------------------------------------------
    def first_acknowledged(self, key: PassKey) -> None:
        """A pass was acknowledged for the first time: it joins the completion order."""
        self._new_pass_at = self.clock()
        if self.calibrator is not None and key not in self._in_order:
            self.order.append(key)
            self._in_order.add(key)

    def recomputed(self) -> None:
        """A pass was acknowledged again (recomputed under a newer calibration)."""
        self._recomputed_at = self.clock()

    def issued(self, vehicle_id: str) -> None:
        """The vehicle's calibration was just published."""
        self._issued_at[vehicle_id] = self.clock()

    def in_order(self, key: PassKey) -> bool:
        """Whether the pass is in the completion order."""
        return key in self._in_order

    def since_new_pass_s(self) -> float:
        """Seconds since a pass was first acknowledged (or since start)."""
        return self.clock() - self._new_pass_at

    # -- the epoch -----------------------------------------------------------------------------
    def finished(self) -> bool:
        """The current epoch's rounds are over: one ran and moved nobody, or its budget is spent."""
        c = self.calibrator
        if c is None or self.size == 0:
            return True
        ran = c.rounds - self.round0
        return ran > 0 and (not c.dirty or ran >= c.max_rounds)

    def pending(self) -> bool:
        """Completed passes wait for an epoch beyond the current one."""
        c = self.calibrator
        return c is not None and len(self.order) > self.size and len(self.order) >= c.min_passes

    def next_size(self, tail: bool | None) -> int | None:
        """The size of the epoch due now (None: none due), from the completed-pass count alone, or all
        completed passes when ``tail`` (when ``None``: at once, without boundaries)."""
        c = self.calibrator
        n = len(self.order)
        if c is None or n < c.min_passes or n <= self.size or not self.finished():
            return None
        if tail is None:
            return n
        boundary = self.boundary()
        if n >= boundary:
            return boundary
        return n if tail else None

    def boundary(self, size: int | None = None) -> int:
        """The completed-pass count at which the epoch after the current one (or after one of
        ``size`` passes) is due."""
        size = self.size if size is None else size
        first = max(self.calibrator.min_passes, self.settings.epoch_first)
        return first if size < first else size + min(size, self.settings.epoch_max_step)

    def rounds_left_max(self) -> int:
        """At most how many rounds the passes completed so far still take: what the current epoch's
        budget has left, and a full budget for each epoch still due for them (so a progress line can
        say "round k of ≤ N" once the passes are in)."""
        c = self.calibrator
        n = len(self.order)
        if c is None or n < c.min_passes:
            return 0
        left = 0 if self.finished() else max(0, c.max_rounds - (c.rounds - self.round0))
        size = self.size
        while size < n:
            size = min(n, self.boundary(size))
            left += c.max_rounds
        return left

    def start(self, size: int, round0: int) -> None:
        """Begin (or, replaying the journal, restore) the epoch of the first ``size`` completed passes."""
        c = self.calibrator
        self.size, self.round0 = size, round0
        if c is not None and c.rounds == round0:  # no round of it yet: it needs one
            c.dirty, c.settled, c.budget_from = True, False, round0

    def state(self, order: bool = False) -> dict:
        """The epoch as journalled; with ``order`` (a snapshot) the completion order too: a pass being
        recomputed when the snapshot is taken is acknowledged again only later, out of its place."""
        out = {"size": self.size, "round0": self.round0}
        if order:
            out["order"] = [list(k) for k in self.order]
        return out

    def restore_order(self, order: Iterable) -> None:
        """Replaying a snapshot: the passes' completion order as it was."""
        self.order = [(str(v), str(p)) for v, p in order]
        self._in_order = set(self.order)

    # -- waiting for recomputed passes -----------------------------------------------------------
    def segments(self, aggregator, owns: Callable[[str], bool]) -> tuple[dict | None, list[Calibration]]:
        """The epoch's held segments, pass by pass in completion order, each pass at its vehicle's
        current calibration — None while some pass is not (yet) recomputed — and the calibrations to
        publish again: those of vehicles whose edge finished a pass with older parameters and has not
        answered since (each under a new version, same parameters, so that the edge recomputes every
        spooled pass with exactly the parameters the calibrator holds)."""
        agg, c, s = aggregator, self.calibrator, self.settings
        out: dict = {}
        reissued: list[Calibration] = []
        waiting = False
        now = self.clock()
        for key in self.order[: self.size]:
            ps, st = agg.passes.get(key), c.vehicles.get(key[0])
            if ps is None or st is None or key in self._excluded:
                continue
            if not ps.acked or ps.calib_version != st.version:
                if not owns(key[0]):  # its owner's calibration is on its way: not waited for here
                    continue
                waiting = True
                # Waits count from the edge's last answer too: a slow edge returns a round's passes
                # one by one, seconds apart, and timed from the calibration alone they would be left out.
                if ps.acked and ps.calib_version < st.version and \
                        now - max(self._issued_at.get(key[0], -math.inf), self._recomputed_at) >= s.reissue_after_s:
                    version, at = self._refreshed.get(key[0], (-1, now))
                    if version != st.version:
                        reissued.append(self._reissue(key[0]))
                    elif now - max(at, self._recomputed_at) >= s.refresh_wait_s:
                        log.warning("pass %s/%s not recomputed at calibration v%d: left out of the rounds",
                                    key[0], key[1], st.version)
                        self._excluded.add(key)
                continue
            for sl in sorted(ps.slots):
                seg = agg.held.get(sl)
                if seg is not None:
                    out[sl] = seg
        return (None if waiting else out), reissued

    def _reissue(self, vehicle_id: str) -> Calibration:
        """The vehicle's calibration under a new version, same parameters."""
        st = self.calibrator.vehicles[vehicle_id]
        st.version += 1
        self._refreshed[vehicle_id] = (st.version, self.clock())
        self._issued_at[vehicle_id] = self.clock()
        return Calibration(vehicle_id=vehicle_id, version=st.version, vehicle_model=st.model,
                           params=dict(st.params), source="fleet")

    def rejoin(self, key: PassKey, ps) -> bool:
        """A pass left out of the rounds came back at its vehicle's current calibration: in the rounds
        again, with a fresh budget for the epoch if it is one of its passes (new data for it, as a
        new pass) — else its vehicle would keep the calibration of the round before it was left out.
        True if the epoch restarted (the daemon journals that)."""
        c = self.calibrator
        st = c.vehicles.get(key[0]) if c is not None else None
        if key not in self._excluded or st is None or ps.calib_version != st.version:
            return False
        self._excluded.discard(key)
        if key in self.order[: self.size]:
            self.start(self.size, c.rounds)
            return True
        return False
