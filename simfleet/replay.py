"""Replay drive logs as live vehicle streams: sensor chunks on ``driveby/<net>/veh/<id>/imu``.

A vehicle keeps what it sent: :class:`ImuPublishers` publishes each vehicle's chunks through a
Zenoh *advanced publisher* (``zenoh.ext``) with a bounded cache of its last ``cache_chunks``
chunks and a periodic heartbeat carrying its last sequence number. An edge's advanced
subscriber (``edge.node``) that missed chunks (a router restarted, a link partitioned) learns of
the gap from the next chunk or heartbeat and fetches the missing chunks from that cache, in
order. The cache covers an outage of ``cache_chunks × CHUNK_S`` seconds of a vehicle's data
(60 s at the default, i.e. 60 s of wall time in real time, 60/X s replayed at X×); chunks
older than that are gone, and the edge still sees, counts and survives the gap (``driveby run``
then publishes the unacknowledged pass again from its log: ``simfleet.run.RESEND_S``).

``driveby replay --connect ROUTER`` (:func:`replay_to`) is the vehicles alone: it publishes the logs to
a deployed network's router and waits for the cloud's acknowledgement of every pass, with no edge or
cloud of its own.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np
import zenoh
import zenoh.ext as zx

from shared import keys
from shared.drivelog import MODEL_CHANNELS, DriveLog
from shared.progress import Progress
from shared.schema import DecodeError, SensorChunk, decode_ack

CHUNK_S = 0.1  # a logger's typical upload granularity
CACHE_CHUNKS = 600  # per vehicle: 60 s of its data (~3.4 KB a chunk at 500 Hz: ~2 MB)
HEARTBEAT_S = 1.0  # how soon a subscriber learns of chunks lost at the end of a stream
DAEMONS_WAIT_S = 30.0  # how long `driveby replay` waits for an edge and a cloud to be live on the net
ACK_IDLE_S = 120.0  # no acknowledgement for this long: the deployment is not answering
# A pass still unacknowledged this long after its last chunk went out (and the replay is over) is
# published again, as a logger keeps its files until the cloud has them (simfleet.run.RESEND_S).
ACK_RESEND_S = 30.0


class ReplayError(Exception):
    """A user-facing failure of ``driveby replay``: one line, exit 1."""


@dataclass(frozen=True)
class ReplayResult:
    passes: int
    acked: int
    seconds: float
    resent_passes: int


class ImuPublishers:
    """Publish raw chunks as the vehicles' loggers would: one advanced publisher per vehicle's
    imu key (declared on first use) keeping its last ``cache_chunks`` chunks for recovery.

    Callable as ``publish(key, payload, attachment=None)``; :meth:`close` (or ``with``)
    undeclares them. Memory is bounded by vehicles × ``cache_chunks`` × chunk size.
    Heartbeats are periodic, not sporadic: a sporadic one announces a new last chunk only once,
    and if that announcement falls in the outage, the lost final chunk is never asked for.
    """

    def __init__(self, session: zenoh.Session, cache_chunks: int = CACHE_CHUNKS, heartbeat_s: float = HEARTBEAT_S):
        if cache_chunks < 1 or heartbeat_s <= 0:
            raise ValueError(f"ImuPublishers: cache_chunks >= 1 and heartbeat_s > 0, got {cache_chunks}, "
                             f"{heartbeat_s}")
        self.session, self.cache_chunks, self.heartbeat_s = session, cache_chunks, heartbeat_s
        self._pubs: dict[str, zx.AdvancedPublisher] = {}
        self._lock = threading.Lock()

    def _publisher(self, key: str) -> zx.AdvancedPublisher:
        with self._lock:
            pub = self._pubs.get(key)
            if pub is None:
                pub = zx.declare_advanced_publisher(
                    self.session, key, congestion_control=zenoh.CongestionControl.BLOCK,
                    cache=zx.CacheConfig(max_samples=self.cache_chunks),
                    sample_miss_detection=zx.MissDetectionConfig(heartbeat=self.heartbeat_s, sporadic_heartbeat=None))
                self._pubs[key] = pub
            return pub

    def __call__(self, key: str, payload: bytes, attachment: bytes | None = None) -> None:
        self._publisher(key).put(payload, attachment=attachment)

    def close(self) -> None:
        with self._lock:
            pubs, self._pubs = list(self._pubs.values()), {}
        for pub in pubs:
            pub.undeclare()

    def __enter__(self) -> ImuPublishers:
        return self

    def __exit__(self, *_exc) -> None:
        self.close()


def chunks_of(log: DriveLog, chunk_s: float = CHUNK_S) -> Iterator[SensorChunk]:
    """The pass cut into chunks of ``chunk_s`` seconds, the last one marked final."""
    m = log.meta
    n = len(log.t)
    step = max(1, int(round(chunk_s * m.sample_rate_hz)))
    names = MODEL_CHANNELS[m.vehicle_model]
    starts = list(range(0, n, step)) or [0]
    for seq, i in enumerate(starts):
        sl = slice(i, min(i + step, n))
        yield SensorChunk(
            vehicle_id=m.vehicle_id, pass_id=m.pass_id, route_id=m.route_id, vehicle_model=m.vehicle_model,
            seq=seq, t0=float(log.t[i]) if n else 0.0, sample_rate_hz=m.sample_rate_hz,
            chainage=log.chainage[sl], speed=log.speed[sl],
            channels={c: np.asarray(log.channels[c][sl], dtype=np.float32) for c in names},
            final=seq == len(starts) - 1, nominal_params=m.nominal_params, lane_offset_m=m.lane_offset_m,
        )


def replay(logs: Iterable[DriveLog], publish: Callable[[str, bytes], None], net: str, rate: float | None = None,
           stop: threading.Event | None = None, on_chunk: Callable[[SensorChunk], None] | None = None) -> int:
    """Publish every log's chunks in turn; ``rate`` X paces at X× real time (None: as fast as possible).

    Pacing waits on ``stop`` until each chunk's due time, so a stop request ends the replay at once.
    Returns the number of chunks published.
    """
    stop = stop or threading.Event()
    n = 0
    t_start = time.monotonic()
    clock = 0.0  # replayed seconds of data so far
    for log in logs:
        for chunk in chunks_of(log):
            if rate is not None:
                due = t_start + clock / rate
                if stop.wait(max(0.0, due - time.monotonic())):
                    return n
            elif stop.is_set():
                return n
            publish(keys.imu_key(net, chunk.vehicle_id), chunk.encode())
            if on_chunk is not None:
                on_chunk(chunk)
            clock += chunk.n / chunk.sample_rate_hz
            n += 1
    return n


def replay_to(session: zenoh.Session, net: str, logs: list[DriveLog], rate: float | None = None,
              progress: bool | None = None, daemons_wait_s: float = DAEMONS_WAIT_S, idle_s: float = ACK_IDLE_S,
              resend_s: float = ACK_RESEND_S) -> ReplayResult:
    """Publish ``logs`` as their vehicles would, on ``session`` (connected to a deployed network), and
    wait until the cloud has acknowledged every pass.

    Waits first (at most ``daemons_wait_s``) for an edge and a cloud to be live on ``net``: chunks
    published to nobody would be lost. A pass unacknowledged ``resend_s`` after its last chunk, once
    the replay is over, is published again (the cloud recognises duplicates). Raises
    :class:`ReplayError` when no edge or cloud is live, or no acknowledgement comes for ``idle_s``.
    """
    t0 = time.monotonic()
    expected = {(log.meta.vehicle_id, log.meta.pass_id) for log in logs}
    acked: set[tuple[str, str]] = set()
    progressed = threading.Event()
    roles: set[str] = set()
    both = threading.Event()

    def on_alive(sample):
        try:
            _, role, _ident = keys.parse_alive_key(str(sample.key_expr))
        except ValueError:
            return
        if sample.kind == zenoh.SampleKind.PUT:
            roles.add(role)
        if {"edge", "cloud"} <= roles:
            both.set()

    def on_ack(sample):
        try:
            ack = decode_ack(sample.payload.to_bytes())
        except DecodeError:
            return
        acked.add((ack.vehicle_id, ack.pass_id))
        progressed.set()

    live = session.liveliness().declare_subscriber(keys.alive_keyexpr(net), on_alive, history=True)
    acks = session.declare_subscriber(keys.ack_keyexpr(net), on_ack)
    stop = threading.Event()
    publish = ImuPublishers(session)
    feeder = None
    try:
        if not both.wait(daemons_wait_s):
            missing = " and ".join(r for r in ("edge", "cloud") if r not in roles)
            raise ReplayError(f"no {missing} live on net {net!r} after {daemons_wait_s:.0f} s "
                              "(is the router reachable, are the daemons started with the same --net?)")
        sent_at: dict[tuple[str, str], float] = {}

        def on_chunk(chunk):
            if chunk.final:
                sent_at[(chunk.vehicle_id, chunk.pass_id)] = time.monotonic()

        by_pass = {(log.meta.vehicle_id, log.meta.pass_id): log for log in logs}
        feeder = threading.Thread(target=replay, args=(logs, publish, net, rate, stop, on_chunk), daemon=True)
        feeder.start()
        resent = 0
        with Progress(len(expected), "passes", enabled=progress, unit="acknowledged") as bar:
            idle_since = time.monotonic()
            while not expected <= acked:
                if progressed.wait(0.5):
                    progressed.clear()
                    idle_since = time.monotonic()
                now = time.monotonic()
                if now - idle_since > idle_s:
                    missing = sorted(p for _, p in expected - acked)
                    raise ReplayError(f"timed out: no pass acknowledged for {idle_s:.0f} s; {len(missing)} "
                                      f"pass(es) missing, e.g. {missing[:3]}")
                if not feeder.is_alive():
                    late = sorted(p for p, t in sent_at.items() if now - t > resend_s and p not in acked)
                    if late:
                        for p in late:
                            sent_at[p] = now
                        feeder = threading.Thread(target=replay, daemon=True,
                                                  args=([by_pass[p] for p in late], publish, net, rate, stop, on_chunk))
                        feeder.start()
                        resent += len(late)
                bar.update(len(acked & expected))
        return ReplayResult(len(expected), len(acked & expected), time.monotonic() - t0, resent)
    finally:
        stop.set()
        if feeder is not None:
            feeder.join(timeout=10.0)
        publish.close()
        acks.undeclare()
        live.undeclare()
