"""Replay drive logs as live vehicle streams: sensor chunks on ``driveby/<net>/veh/<id>/imu``."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from shared import keys
from shared.drivelog import MODEL_CHANNELS, DriveLog
from shared.schema import SensorChunk

CHUNK_S = 0.1  # a logger's typical upload granularity


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
