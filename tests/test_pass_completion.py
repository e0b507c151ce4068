"""A pass completes even when some of its segments are refused as implausible (no hang)."""

from __future__ import annotations

import numpy as np

from cloud.ingest.aggregator import Aggregator
from cloud.road.mean_profile import MeanProfile
from shared.registry import Route, Site
from shared.schema import ApSegment, PassDone


def _seg(seq: int, tile: int, value: float) -> ApSegment:
    return ApSegment.make(np.full(100, value), np.full(100, 1e-4), vehicle_id="v1", pass_id="p1", route_id="R1",
                          tile=tile, axle=1, start_index=tile * 1000, spacing_m=0.05, calib_version=0,
                          speed_mps=20.0, t_first=0.0, t_last=1.0, seq=seq)


def test_refused_segment_still_completes_its_pass():
    site = Site(routes=(Route(id="R1", length_m=200.0),))
    est = MeanProfile({"R1": 200.0})
    agg = Aggregator(site, [est])
    assert agg.on_segment(_seg(0, 0, 1e-3).encode(), "v1") == []
    assert agg.on_segment(_seg(1, 1, 5.0).encode(), "v1") == []  # |AP| ≥ 1 m: implausible, refused
    acks = agg.on_pass_done(PassDone(vehicle_id="v1", pass_id="p1", route_id="R1", calib_version=0,
                                     n_segments=2).encode())
    assert len(acks) == 1 and acks[0].n_segments_accepted == 1
    assert agg.rejected["implausible_ap"] == 1
    assert np.isnan(est.snapshot()["R1"].elevation_m[1000])  # the refused values were not fused
    # A segment under another vehicle's key is not the vehicle's own: it never completes anything.
    assert agg.on_segment(_seg(2, 2, 1e-3).encode(), "v2") == []
