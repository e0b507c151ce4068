"""The cloud's durable state: what goes into the journal, how a restart rebuilds from it, and compaction.

These kinds of record rebuild the whole state, because everything else is a function of them:

* ``ap`` — an AP payload as received (one segment or a batch),
* ``done`` — a pass-done as received,
* ``calib`` — a calibration the cloud itself issued (its own decisions are inputs to its future),
  journalled before it is published,
* ``calibrator`` — the calibrator's whole state after a round (fits, step damping, round count),
  journalled before the round's calibrations are published,
* ``epoch`` — the start of a calibration epoch (its size in completed passes and first round:
  :mod:`cloud.daemon.epochs`),
* ``alarm`` — a bridge alarm (raised or cleared) the cloud published: a restarted cloud knows which
  alarms stand and does not raise them again.
* ``rail_baseline`` — a rail bridge's healthy baseline (the runs it was read from,
  :meth:`cloud.rail.batches.RailBatches.restore_baseline`): a later session compares its runs with it.

Replaying them in order through the same handlers (:meth:`~cloud.daemon.core.Cloud.on_segment`,
:meth:`~cloud.daemon.core.Cloud.on_done`, the calibrator's ``restore``) gives the same aggregator state and the same exact posteriors (up to
floating-point summation order after a compaction). A snapshot is the compacted record set: the
segments the aggregator holds now, the latest pass-done of each pass and each vehicle's current
calibration — so recovery costs one pass over live state, never over history.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator

from shared import keys
from shared.schema import Calibration, DecodeError, decode_calibration

from cloud.daemon.journal import Journal, Record

log = logging.getLogger("driveby.cloud.durable")

AP, DONE, CALIB, CALIBRATOR, EPOCH, ALARM = "ap", "done", "calib", "calibrator", "epoch", "alarm"
RAIL_BASELINE = "rail_baseline"
#: Compaction policy (the defaults of :class:`Durability`). A snapshot rewrites the whole live state
#: (every held segment), holding the serve loop for the while, and only pays where records have
#: become garbage (superseded segments, rejected or duplicate input). So the daemon compacts when the
#: records on disk (the last snapshot's and the journal since) reach ``COMPACT_RATIO`` × the live
#: state and at least ``SNAPSHOT_MIN_RECORDS`` came since the last: restart replays at most that many
#: times the live state, disk holds at most that, and the pauses cost O(1) per record. (A time
#: trigger would rewrite the same live state for nothing when nothing is superseded.)
COMPACT_RATIO = 2.0
SNAPSHOT_MIN_RECORDS = 10_000
#: Group commit (:class:`GroupCommit`): what the cloud publishes waits at most this long (s) to leave
#: after one fsync with the rest of its group, and at most this many messages are held.
GROUP_COMMIT_S = 0.005
GROUP_COMMIT_MAX = 256


def replay(cloud, records: Iterable[Record]) -> int:
    """Feed journal records back through the cloud's handlers; returns how many were applied."""
    n = 0
    for r in records:
        if r.kind == AP:
            cloud.on_segment(r.key, r.payload)
        elif r.kind == DONE:
            cloud.on_done(r.key, r.payload)
        elif r.kind == CALIB:
            if cloud.calibrator is not None:
                try:
                    restore_calibration(cloud.calibrator, decode_calibration(r.payload))
                except (DecodeError, KeyError, ValueError) as e:  # written by us: only a version skew
                    log.warning("journal: calibration record %d not restored: %s", r.seq, e)
        elif r.kind == CALIBRATOR:
            if cloud.calibrator is not None:
                try:
                    cloud.calibrator.load_state(json.loads(r.payload))
                except (ValueError, KeyError, TypeError) as e:
                    log.warning("journal: calibrator state %d not restored: %s", r.seq, e)
        elif r.kind == ALARM:
            try:
                cloud.restore_alarm(r.payload)
            except (DecodeError, ValueError) as e:
                log.warning("journal: alarm record %d not restored: %s", r.seq, e)
        elif r.kind == RAIL_BASELINE:
            if cloud.rail is not None:
                try:
                    cloud.rail.restore_baseline(r.payload)
                except (ValueError, KeyError, TypeError) as e:
                    log.warning("journal: rail baseline %d not restored: %s", r.seq, e)
        elif r.kind == EPOCH:
            if cloud.calibrator is not None:
                try:
                    e = json.loads(r.payload)
                    if "order" in e:
                        cloud.restore_order(e["order"])
                    cloud.start_epoch(int(e["size"]), int(e["round0"]))
                except (ValueError, KeyError, TypeError) as e:
                    log.warning("journal: epoch record %d not restored: %s", r.seq, e)
        else:
            log.warning("journal: unknown record kind %r (seq %d) skipped", r.kind, r.seq)
            continue
        n += 1
    return n


def restore_calibration(calibrator, cal: Calibration) -> None:
    """Make ``cal`` the calibrator's current state of its vehicle (as when it was issued)."""
    st = calibrator.initial(cal.vehicle_id, cal.vehicle_model)
    if cal.version >= st.version:
        st.model, st.version, st.params = cal.vehicle_model, cal.version, dict(cal.params)


def current_calibrations(calibrator) -> list[Calibration]:
    """Each calibrated vehicle's current calibration, as the edges hold it."""
    return [Calibration(vehicle_id=vid, version=st.version, vehicle_model=st.model, params=dict(st.params),
                        source="fleet")
            for vid, st in sorted(calibrator.vehicles.items()) if st.version > 0]


def compacted(cloud) -> Iterator[tuple[str, str, bytes]]:
    """The records that rebuild the cloud's current state, in an order replay accepts."""
    if cloud.calibrator is not None:
        yield CALIBRATOR, "", json.dumps(cloud.calibrator.state()).encode()
        yield EPOCH, "", json.dumps(cloud.epoch_state(order=True)).encode()
    for payload in cloud.alarms.values():
        yield ALARM, "", payload
    if cloud.rail is not None:
        for payload in cloud.rail.baseline_records():
            yield RAIL_BASELINE, "", payload
    agg = cloud.aggregator
    # Streamed: spilled segments go out as the wire payloads they are stored as (no decoding), and
    # nothing here holds more than one record at a time.
    for (vehicle, pass_id, route, tile, _axle), payload in agg.segments.encoded():
        yield AP, keys.ap_key(cloud.net, route, tile, vehicle), payload
    # Pass-dones in the order the passes were first acknowledged (fleet calibration: the epoch record
    # above carries that order too, for passes being recomputed now, which are acknowledged again only
    # later), then the others in the order they were first seen.
    for key in cloud.completion_order:
        ps = agg.passes.get(key)
        if ps is not None and ps.done_payload is not None:
            yield DONE, keys.done_key(cloud.net, key[0]), ps.done_payload
    for key, ps in agg.passes.items():
        if not cloud.in_completion_order(key) and ps.done_payload is not None:
            yield DONE, keys.done_key(cloud.net, key[0]), ps.done_payload


class Durability:
    """The journal, wired to one cloud: append before apply, sync before publishing, compact when due
    (``compact_ratio``, ``min_records``: see :data:`COMPACT_RATIO`)."""

    def __init__(self, journal: Journal, cloud, compact_ratio: float = COMPACT_RATIO,
                 min_records: int = SNAPSHOT_MIN_RECORDS):
        if not compact_ratio > 1.0 or min_records < 0:
            raise ValueError(f"Durability: expected compact_ratio > 1 and min_records >= 0, "
                             f"got {compact_ratio}, {min_records}")
        self.journal, self.cloud = journal, cloud
        self.compact_ratio, self.min_records = compact_ratio, min_records
        self.live = False  # False while recovering: replayed input is not journalled again
        self.since_snapshot = 0  # records journalled since the last snapshot (replayed ones included)
        self.snapshot_records = 0  # records the last snapshot holds
        self._snapshot_at = time.monotonic()
        self.snapshots = 0
        self.snapshot_s_last = self.snapshot_s_max = 0.0  # how long the serve loop was held by one

    def recover(self) -> int:
        meta, records = self.journal.recover()
        first_tail = int(meta.get("next_seq", 0))  # records before it are the snapshot's
        agg = self.cloud.aggregator
        n = replay(self.cloud, (r for r in records if r.seq < first_tail))
        self.snapshot_records = n
        if meta:
            # Counters are state too, and compaction keeps only what is held: restore them as they were.
            agg.rejected.clear()
            agg.rejected.update(meta.get("rejected", {}))
            agg.accepted = int(meta.get("accepted", agg.accepted))
        tail = replay(self.cloud, (r for r in records if r.seq >= first_tail))
        self.since_snapshot = tail  # still on disk: they count towards the next compaction
        n += tail
        if n:
            log.warning("recovered %d journal records (%d passes complete)", n, self.cloud.passes_complete)
        return n

    def record(self, kind: str, key: str, payload: bytes) -> None:
        self.journal.append(kind, key, payload)
        self.since_snapshot += 1

    def record_own(self, kind: str, payload: bytes) -> None:
        """A decision of the cloud itself (``epoch``, ``calibrator``, ``alarm``): journalled, written
        through (the daemon sets it as the cloud's ``record``)."""
        if self.live:
            self.record(kind, "", payload)

    def before_publish(self) -> None:
        self.journal.sync()

    def maybe_snapshot(self, force: bool = False) -> bool:
        due = self.since_snapshot >= self.min_records and \
            self.snapshot_records + self.since_snapshot >= self.compact_ratio * self.live_records()
        if not (force or due):
            return False
        t0 = time.monotonic()
        agg = self.cloud.aggregator
        meta = {"rejected": dict(agg.rejected), "accepted": agg.accepted, "written_utc": time.time()}
        seq0 = self.journal.next_seq
        self.journal.write_snapshot(compacted(self.cloud), meta)
        self.snapshot_records = self.journal.next_seq - seq0
        self.since_snapshot = 0
        self._snapshot_at = time.monotonic()
        self.snapshots += 1
        self.snapshot_s_last = self._snapshot_at - t0
        self.snapshot_s_max = max(self.snapshot_s_max, self.snapshot_s_last)
        log.info("snapshot %d written in %.3f s", self.snapshots, self.snapshot_s_last)
        return True

    def live_records(self) -> int:
        """About how many records a snapshot now would hold (a segment each, a pass-done per pass)."""
        agg = self.cloud.aggregator
        return len(agg.segments) + len(agg.passes)

    def stats(self) -> dict:
        return {"snapshots": self.snapshots, "snapshot_records": self.snapshot_records,
                "journal_records_since": self.since_snapshot, "snapshot_s_last": round(self.snapshot_s_last, 4),
                "snapshot_s_max": round(self.snapshot_s_max, 4), "journal_generation": self.journal.generation}

    def close(self) -> None:
        self.journal.close()


class GroupCommit:
    """What a journalling cloud publishes (acknowledgements, calibrations, status, alarms), held
    until the input it follows is on disk, then published in order: a group after one fsync.

    An acknowledgement still implies fsync'd input: each message held remembers how many journal
    records had been written when it was published (its input among them), and leaves only once
    :meth:`Journal.sync` has put that many on disk. An fsync costs milliseconds; one per
    acknowledgement bounded a durable cloud to a few hundred passes per second, one per group
    costs at most ``window_s`` of latency. The fsync runs outside the cloud's lock (the serve loop's
    flusher thread, :meth:`wait` then :meth:`flush`), so input goes on being applied meanwhile.

    Until :attr:`grouping` is set (recovery, and after the serve loop ends) a message is synced and
    published at once.
    """

    def __init__(self, journal: Journal, put: Callable[[str, bytes], None], clock: Callable[[], float] = time.monotonic,
                 window_s: float = GROUP_COMMIT_S, max_pending: int = GROUP_COMMIT_MAX):
        if not window_s >= 0 or max_pending < 1:
            raise ValueError(f"GroupCommit: expected window_s >= 0 and max_pending >= 1, got {window_s}, {max_pending}")
        self.journal, self.put, self.clock = journal, put, clock
        self.window_s, self.max_pending = window_s, max_pending
        self.grouping = False
        self._pending: list[tuple[str, bytes]] = []
        self._upto = 0  # journal records the pending messages follow
        self._first_at = 0.0  # when the oldest pending message was published
        self._cond = threading.Condition()
        self._flush_lock = threading.Lock()  # groups leave one at a time, in order
        self.groups = 0  # fsyncs that published something
        self.published = 0

    def publish(self, key: str, payload: bytes) -> None:
        if not self.grouping:
            with self._flush_lock:
                self.journal.sync()
                self.put(key, payload)
            self.groups += 1
            self.published += 1
            return
        with self._cond:
            if not self._pending:
                self._first_at = self.clock()
                self._cond.notify()
            self._pending.append((key, payload))
            self._upto = self.journal.written

    def full(self) -> bool:
        """Whether the held messages reach ``max_pending`` (the caller flushes: memory stays bounded)."""
        return len(self._pending) >= self.max_pending

    def wait(self, stop: threading.Event) -> None:
        """Until the oldest held message has waited ``window_s`` (or ``stop`` is set)."""
        with self._cond:
            while not self._pending and not stop.is_set():
                self._cond.wait(0.1)
            first = self._first_at
        stop.wait(max(0.0, first + self.window_s - self.clock()))

    def flush(self) -> None:
        """Sync the journal as far as the held messages need, then publish them, in order."""
        with self._flush_lock:
            with self._cond:
                batch, upto = self._pending, self._upto
                self._pending = []
            if not batch:
                return
            self.journal.sync(upto)
            for key, payload in batch:
                self.put(key, payload)
            self.groups += 1
            self.published += len(batch)

    def stats(self) -> dict:
        return {"group_commits": self.groups, "published": self.published}
