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
                        replies = list(s.get(keys.state_profile_key("t", route, 1), timeout=60.0))  # a busy daemon on a loaded machine answers late, not never
                        assert len(replies) == 1 and replies[0].ok is not None, route
                        assert str(replies[0].ok.key_expr) == keys.state_profile_key("t", route, 1)
                        table = pa.ipc.open_stream(replies[0].ok.payload.to_bytes()).read_all()
                        assert table.column_names[:2] == ["chainage_m", "elevation_m"]
        finally:
            for p in procs:
                p.terminate()
                try:
                    p.wait(60)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(60)


def test_more_shards_than_routes_is_a_clear_error(two_routes, tmp_path):
    with pytest.raises(RunError, match="--shards: expected 1 to 2"):
        run(two_routes / "logs", two_routes / "site.toml", tmp_path / "x", shards=3, progress=False)


@pytest.fixture(scope="module")
def shared_vehicles(tmp_path_factory):
    """Four quarter-cars on two routes of the same road (R1, R2 are copies of one road-qc route), two
    of them on both: veh-0001 twice on R1 and once on R2, veh-0003 twice on R2 and once on R1."""
    out = tmp_path_factory.mktemp("shared")
    sim = out / "sim"
    generate(SCENARIOS["road-qc"], sim, seed=11, passes=4, workers=1, progress=False)
    logs = {read_drive_log(p).meta.vehicle_id: read_drive_log(p) for p in list_drive_logs(sim / "logs")}
    plan = [("R1", "veh-0001", ""), ("R1", "veh-0002", ""), ("R1", "veh-0003", "-b"), ("R1", "veh-0001", "-b"),
            ("R2", "veh-0003", ""), ("R2", "veh-0004", ""), ("R2", "veh-0001", "-c"), ("R2", "veh-0003", "-c")]
    (out / "logs").mkdir()
    for i, (route, vid, suffix) in enumerate(plan):
        log = logs[vid]
        meta = dataclasses.replace(log.meta, route_id=route, pass_id=log.meta.pass_id + suffix)
        write_drive_log(out / "logs" / f"{i:02d}-{route}-{vid}.parquet", dataclasses.replace(log, meta=meta))
    site = (sim / "site.toml").read_text()
    (out / "site.toml").write_text(site.replace("[[route]]", '[[route]]\nid = "R2"\nlength_m = 200.0\n\n[[route]]', 1))
    return out


def test_each_vehicle_is_calibrated_by_one_shard_and_the_others_apply_it(shared_vehicles):
    """Two shards (R1, R2) and the edge wired in memory as over Zenoh (segments to their route's
    owner, pass-dones and calibrations to everyone): a vehicle is calibrated by the shard with most
    of its passes only; the other applies its calibrations, so every pass ends current everywhere."""
    import collections

    from cloud.daemon.core import Cloud
    from cloud.daemon.settings import CloudSettings
    from edge.node import Edge
    from simfleet.replay import replay

    site = load_site(shared_vehicles / "site.toml")
    queue: collections.deque = collections.deque()
    issued: list[tuple[str, str]] = []  # (shard, vehicle) of every calibration published

    def publisher(name):
        def publish(key, payload):
            if "/calib/" in key:
                issued.append((name, key.rsplit("/", 1)[-1]))
            queue.append((key, payload))
        return publish

    clouds = {r: Cloud("t", site, publisher(r), CloudSettings(calibration="fleet", shard=frozenset({r})))
              for r in ("R1", "R2")}
    edge = Edge("t", publisher("edge"), site, "fleet")
    for c in clouds.values():
        c.calibrator.max_rounds = 3  # the protocol, not convergence, is under test: keep it quick

    def pump():
        while queue:
            key, payload = queue.popleft()
            kind = key.split("/")[2]
            if kind == "veh":
                edge.on_chunk(payload)
            elif kind == "ap":
                clouds[keys.parse_ap_key(key)[1]].on_segment(key, payload)
            elif kind == "done":
                for c in clouds.values():
                    c.on_done(key, payload)
            elif kind == "calib":
                edge.on_calibration(payload)
                for c in clouds.values():
                    c.on_calibration(key, payload)

    replay([read_drive_log(p) for p in list_drive_logs(shared_vehicles / "logs")], publisher("replay"), "t")
    pump()
    while True:
        for c in clouds.values():
            c.fuse_pending()  # the daemons' idle work when the bus is quiet
        if not any([c.maybe_align() or c.maybe_calibrate() for c in clouds.values()]):
            break
        pump()
    r1, r2 = clouds["R1"], clouds["R2"]
    vehicles = ["veh-0001", "veh-0002", "veh-0003", "veh-0004"]
    assert [v for v in vehicles if r1.owns(v)] == ["veh-0001", "veh-0002"]
    assert [v for v in vehicles if r2.owns(v)] == ["veh-0003", "veh-0004"]
    assert issued and all(clouds[shard].owns(vid) for shard, vid in issued)  # only owners calibrate
    assert {vid for _, vid in issued} == set(vehicles)
    # The shared vehicles: each shard holds the owner's calibration, and its passes are current at it.
    assert r2.calibrations_applied > 0 and r1.calibrations_applied > 0
    assert r1.calibration_conflicts == r2.calibration_conflicts == 0
    for vid in ("veh-0001", "veh-0003"):
        a, b = r1.calibrator.vehicles[vid], r2.calibrator.vehicles[vid]
        assert a.version == b.version > 0 and a.params == b.params
    for c in clouds.values():
        st = c.status()
        assert st["passes"] == st["passes_current"] == 4 and st["settled"]
    # The merged vehicles table has each vehicle once, from its owner.
    rows = [(r["vehicle_id"], r["param"]) for c in clouds.values() for r in c.vehicle_rows()]
    assert len(rows) == len(set(rows)) and {v for v, _ in rows} == set(vehicles)
