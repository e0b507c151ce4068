"""Scale-out: a cloud that owns some of the routes, and who calibrates a vehicle seen by several.

A shard subscribes to its own routes' segments only (Zenoh routes each segment to its owner), so
it sees the site as its routes and their bridges. Every shard sees every pass-done, so all agree on
which one calibrates a vehicle — the shard with most of its passes — once the same pass-dones have
arrived; the others apply the calibrations the owner publishes.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
from collections.abc import Mapping

from shared import keys
from shared.registry import Site
from shared.schema import DecodeError, decode_calibration

from cloud.daemon.durable import restore_calibration

log = logging.getLogger("driveby.cloud")


def shard_site(site: Site, shard: frozenset[str] | None) -> tuple[Site, frozenset[str]]:
    """The site as a shard owning ``shard`` (None: every route) sees it, and the other shards' routes."""
    if shard is None:
        return site, frozenset()
    foreign = frozenset(r.id for r in site.routes) - shard
    return dataclasses.replace(site, routes=tuple(r for r in site.routes if r.id in shard),
                               bridges=tuple(b for b in site.bridges if b.route in shard)), foreign


class Ownership:
    """Which vehicles this cloud calibrates, and the calibrations it took from other shards.

    ``vehicle_routes``: vehicle → route → passes, as the aggregator counts them from every pass-done.
    """

    def __init__(self, shard: frozenset[str] | None, vehicle_routes: Mapping[str, collections.Counter]):
        self.shard, self.vehicle_routes = shard, vehicle_routes
        self.applied = 0  # calibrations of vehicles another shard owns, applied here
        self.conflicts = 0  # …and ones at a version this shard had issued differently

    def owns(self, vehicle_id: str) -> bool:
        """Always unsharded; a shard when the route with most of the vehicle's passes (ties: the
        first route id) is one of its own."""
        if self.shard is None:
            return True
        counts = self.vehicle_routes.get(vehicle_id)
        if not counts:
            return False
        route = min(counts, key=lambda r: (-counts[r], r))
        return route in self.shard

    def take(self, calibrator, key: str, payload: bytes) -> bool | None:
        """A calibration on the bus made the calibrator's state of the vehicle, if it is newer: its
        passes here are then current at that version and its bridges fed with those parameters. A
        cloud's own calibrations come back too: no change. True if applied, False if not newer,
        None if malformed (or of a vehicle class the registry does not know)."""
        try:
            cal = decode_calibration(payload)
            if keys.parse_vehicle_key(key, "calib")[1] != cal.vehicle_id:
                raise ValueError("key names another vehicle")
        except (DecodeError, ValueError):
            return None
        st = calibrator.vehicles.get(cal.vehicle_id)
        if st is not None and cal.version <= st.version:
            if cal.version == st.version and dict(cal.params) != st.params:
                self.conflicts += 1  # two shards issued this version: ownership disagreed
                log.warning("calibration of %s v%d issued differently by another shard", cal.vehicle_id, cal.version)
            return False
        if self.owns(cal.vehicle_id):
            self.conflicts += 1
            log.warning("calibration of %s v%d issued by another shard, though this one owns it",
                        cal.vehicle_id, cal.version)
        try:
            restore_calibration(calibrator, cal)
        except KeyError:  # no vehicle class for it in the registry
            return None
        self.applied += 1
        return True
