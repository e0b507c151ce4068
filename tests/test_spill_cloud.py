"""A cloud whose held segments spill (bounded resident segments) exports what the unbounded cloud
exports, bit for bit, through the path that gives the profile estimator something other than the
stored segment on every pass: continuous-time APs (fused forms, spilled whole; the stored segments
the profile holds spill as references to the store)."""

from __future__ import annotations

import pyarrow.parquet as pq
import pytest

from cloud.daemon.core import Cloud
from cloud.daemon.settings import CloudSettings
from cloud.ingest.segment_store import HeldSegments
from shared.registry import load_site
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

from tests.support import drive_logs, edge_messages

NET = "t"


@pytest.fixture(scope="module")
def road(tmp_path_factory):
    out = tmp_path_factory.mktemp("road")
    generate(SCENARIOS["road-qc"], out, seed=11, passes=4, workers=1, progress=False)
    site = load_site(out / "site.toml")
    return site, tuple(edge_messages(site, drive_logs(out), NET))


def _settled(site, msgs, max_resident, spill_dir):
    cloud = Cloud(NET, site, lambda k, p: None,
                  CloudSettings(calibration="nominal", align=False, max_resident=max_resident, spill_dir=spill_dir))
    for key, payload in msgs:
        (cloud.on_segment if "/ap/" in key else cloud.on_done)(key, payload)
    assert cloud.passes_complete == 4 and cloud.fuse_pending() == 0  # (the daemon's idle work)
    return cloud


def test_a_spilling_cloud_exports_the_unbounded_clouds_tables_with_fused_passes(road, tmp_path):
    site, msgs = road
    unbounded = _settled(site, msgs, None, None)
    bounded = _settled(site, msgs, 3, tmp_path / "spill")
    held = bounded.profile.segments
    assert isinstance(held, HeldSegments) and held.spilled > 0 and bounded.aggregator.segments.spilled > 0
    # What the profile holds is not only the stored segments: the fused forms too.
    stored = {slot: seg.encode() for slot, seg in bounded.aggregator.segments.items()}
    assert any(seg.encode() != stored[key[:5]] for key, seg in held.items())
    whole = sum(row != b"\0" for key, row in held.encoded() if held.peek(key) is None)
    assert 0 < whole < held.spilled + held.resident
    a = {p.name: pq.read_table(p) for p in unbounded.export(tmp_path / "a")}
    b = {p.name: pq.read_table(p) for p in bounded.export(tmp_path / "b")}
    assert a.keys() == b.keys() and "profile.parquet" in a
    for name in a:
        assert a[name].equals(b[name]), name
