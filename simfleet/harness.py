"""The lab harness: edge and cloud cores on one in-memory bus, in one process, for reports, benchmarks and tests.

The same code as the daemons (:class:`edge.node.Edge`, :class:`cloud.daemon.core.Cloud`), wired by a
queue instead of Zenoh: chunks in, segments, pass-dones and calibrations routed by key, and whenever
the queue is empty what the cloud daemon does when the bus is quiet (an alignment sweep, else a
calibration round). One thread, and every message is delivered before the cloud's next idle work,
so a run is a function of its logs.
"""

from __future__ import annotations

import collections
import time
from collections.abc import Callable, Iterable
from pathlib import Path

from cloud.daemon.core import Cloud
from cloud.daemon.settings import CloudSettings
from edge.node import Edge
from shared.drivelog import DriveLog
from shared.registry import Site

from .replay import replay


class Harness:
    """One edge and one cloud on an in-memory bus.

    Parameters
    ----------
    site : the registry both sides read.
    settings : the cloud's; the edge calibrates as ``settings.calibration`` says.
    net : the key space's network name.
    clock : the cloud's monotonic clock (a test passes one it moves).
    on_publish : sees every message as it is published; True takes it off the bus (the caller
        delivers it later, e.g. a slow edge's calibrations), False leaves it on.
    on_deliver : sees every message just before it is delivered (e.g. to journal it).
    """

    def __init__(self, site: Site, settings: CloudSettings = CloudSettings(calibration="fleet"), *, net: str = "net",
                 clock: Callable[[], float] = time.monotonic,
                 on_publish: Callable[[str, bytes], bool] | None = None,
                 on_deliver: Callable[[str, bytes], None] | None = None):
        self.site, self.net = site, net
        self.queue: collections.deque[tuple[str, bytes]] = collections.deque()
        self.on_publish, self.on_deliver = on_publish, on_deliver
        self.edge = Edge(net, self.publish, site, settings.calibration)
        self.cloud = Cloud(net, site, self.publish, settings, clock=clock)

    def publish(self, key: str, payload: bytes) -> None:
        """Put a message on the bus (every publisher here: the replay, the edge, the cloud)."""
        if self.on_publish is None or not self.on_publish(key, payload):
            self.queue.append((key, payload))

    def deliver(self, key: str, payload: bytes) -> None:
        """Hand one message to its subscriber, by the key's kind (``driveby/<net>/<kind>/…``)."""
        if self.on_deliver is not None:
            self.on_deliver(key, payload)
        kind = key.split("/")[2]
        if kind == "veh":
            self.edge.on_chunk(payload)
        elif kind == "ap":
            self.cloud.on_segment(key, payload)
        elif kind == "done":
            self.cloud.on_done(key, payload)
        elif kind == "calib":
            self.edge.on_calibration(payload)

    def pump(self) -> None:
        """Deliver until the bus is empty (what is published meanwhile included)."""
        while self.queue:
            self.deliver(*self.queue.popleft())

    def replay(self, logs: Iterable[DriveLog]) -> None:
        """Publish the logs' chunks, as ``driveby run`` replays them, and deliver everything."""
        replay(logs, self.publish, self.net)
        self.pump()

    def idle(self) -> bool:
        """The cloud daemon's work when the bus is quiet: fuse the corrected passes, then an alignment
        sweep, else a calibration round. True if either ran (then the bus has new messages)."""
        self.cloud.fuse_pending()
        return self.cloud.maybe_align() or self.cloud.maybe_calibrate()

    def settle(self) -> int:
        """Idle work and delivery until nothing more happens; returns the rounds (sweeps included)."""
        rounds = 0
        c = self.cloud.calibrator
        while True:  # (idle's work, told apart: a slice of a sweep, a round or its view table is not a round)
            self.cloud.fuse_pending()
            if self.cloud.maybe_align():
                rounds += not self.cloud.aligner.sweeping
            else:
                before = c.rounds if c is not None else 0
                if not self.cloud.maybe_calibrate():
                    return rounds
                rounds += c.rounds - before
            self.pump()


def run_in_process(logs: Iterable[DriveLog], site: Site, export_dir: Path | None,
                   settings: CloudSettings = CloudSettings(calibration="fleet")) -> tuple[Cloud, int]:
    """The logs through the harness until it settles, exported to ``export_dir`` (None: not);
    returns (the cloud, its rounds)."""
    h = Harness(site, settings)
    h.replay(logs)
    rounds = h.settle()
    if export_dir is not None:
        h.cloud.export(Path(export_dir))
    return h.cloud, rounds
