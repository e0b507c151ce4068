"""Scale-out: routes split among cloud daemons behind two routers, each answering for its own routes."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import threading

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import zenoh

from shared import keys
from shared.drivelog import list_drive_logs, read_drive_log, write_drive_log
from shared.registry import load_site
from shared.transport import run_router, zenoh_config
from simfleet.run import RunError, run
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate


@pytest.fixture(scope="module")
def two_routes(tmp_path_factory):
    """Two road-qc simulations as two routes of one site (R1, R2), each driven by its own vehicles."""
    out = tmp_path_factory.mktemp("two")
    logs = out / "logs"
    logs.mkdir()
    for i, route in enumerate(("R1", "R2")):
        sim = out / route
        generate(SCENARIOS["road-qc"], sim, seed=20 + i, passes=2, workers=1, progress=False)
        for path in list_drive_logs(sim / "logs"):
            log = read_drive_log(path)
            meta = dataclasses.replace(log.meta, route_id=route, vehicle_id=f"{route}-{log.meta.vehicle_id}")
            write_drive_log(logs / f"{route}-{path.name}", dataclasses.replace(log, meta=meta))
    site = (out / "R1" / "site.toml").read_text()
    (out / "site.toml").write_text(site.replace('id = "R1"', 'id = "R1"', 1).replace(
        "[[route]]", '[[route]]\nid = "R2"\nlength_m = 200.0\n\n[[route]]', 1))
    assert {r.id for r in load_site(out / "site.toml").routes} == {"R1", "R2"}
    return out


def _profile(path):
    t = pq.read_table(path).to_pydict()
    return {r: np.asarray(t["elevation_m"])[np.asarray(t["route_id"]) == r] for r in set(t["route_id"])}


def test_two_shards_give_the_single_cloud_export(two_routes, tmp_path):
    site = two_routes / "site.toml"
    one = run(two_routes / "logs", site, tmp_path / "one", calibration="nominal", progress=False)
    two = run(two_routes / "logs", site, tmp_path / "two", calibration="nominal", progress=False, shards=2)
    assert one.acked == two.acked == 4
    a, b = _profile(tmp_path / "one" / "profile.parquet"), _profile(tmp_path / "two" / "profile.parquet")
    assert set(a) == set(b) == {"R1", "R2"}
    for r in a:
        assert np.allclose(a[r], b[r], rtol=0, atol=1e-9 * np.std(a[r])), r
    assert two.stats["accepted"] == one.stats["accepted"]
    assert two.stats["foreign_passes"] == 4  # each shard saw the other's pass-dones and left them alone
    # each shard wrote only its own routes
    for cid, route in (("cloud-1", "R1"), ("cloud-2", "R2")):
        t = pq.read_table(tmp_path / "two" / ".run" / f"export-{cid}" / "profile.parquet").to_pydict()
        assert set(t["route_id"]) == {route}


def test_a_tile_query_is_answered_by_its_owner(two_routes, tmp_path):
    """Two cloud daemons, each on its own router, own one route each: a client on either router asks
    for a tile of either route and gets exactly one answer, the owner's."""
    common = ["--net", "t", "--site", str(two_routes / "site.toml"), "--calibration", "nominal"]
    with run_router() as r1, run_router(connect=[r1]) as r2:
        procs = [subprocess.Popen([sys.executable, "-m", "cloud", "--connect", ep, "--id", f"c{i}", "--routes", route,
                                  *common], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                 stderr=open(tmp_path / f"c{i}.log", "wb"))
                 for i, (ep, route) in enumerate(((r1, "R1"), (r2, "R2")))]
        try:
            with zenoh.open(zenoh_config("client", connect=[r1])) as a, \
                    zenoh.open(zenoh_config("client", connect=[r2])) as b:
                up, seen = threading.Event(), set()

                def on_alive(sample):
                    seen.add(str(sample.key_expr))
                    if {keys.alive_key("t", "cloud", "c0"), keys.alive_key("t", "cloud", "c1")} <= seen:
                        up.set()

                a.liveliness().declare_subscriber(keys.alive_keyexpr("t", "cloud"), on_alive, history=True)
                assert up.wait(120), "cloud daemons did not come up"
                for s in (a, b):
                    for route in ("R1", "R2"):
                        replies = list(s.get(keys.state_profile_key("t", route, 1), timeout=10.0))
                        assert len(replies) == 1 and replies[0].ok is not None, route
                        assert str(replies[0].ok.key_expr) == keys.state_profile_key("t", route, 1)
                        table = pa.ipc.open_stream(replies[0].ok.payload.to_bytes()).read_all()
                        assert table.column_names[:2] == ["chainage_m", "elevation_m"]
        finally:
            for p in procs:
                p.terminate()
                p.wait(30)


def test_more_shards_than_routes_is_a_clear_error(two_routes, tmp_path):
    with pytest.raises(RunError, match="--shards: expected 1 to 2"):
        run(two_routes / "logs", two_routes / "site.toml", tmp_path / "x", shards=3, progress=False)
