"""``driveby fleet``: pacing and determinism of the publishers, clear errors for a bad site, and a live
fleet against real daemons (router, cloud, edge and fleet each in its own process, joined by a
free loopback port). Every wait is on an event with a timeout; no sleeps.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from shared import keys
from shared.registry import Bridge, Route, Site, VehicleClass, dump_site
from shared.schema import decode_ack, decode_sensor_chunk
from shared.transport import run_router, zenoh_config
from simfleet import fleet
from simfleet.scenarios import TABLE_4_1, BridgeSpec

TIMEOUT_S = 120.0  # generous: a cold numba cache compiles kernels on first start
NET = "tf"


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """A road route with a healthy 20 m bridge, a plain road route, and the Table 4.1 quarter-car class."""
    b = BridgeSpec()
    path = tmp_path_factory.mktemp("fleet") / "site.toml"
    dump_site(Site(routes=(Route("R1", 140.0), Route("R2", 100.0)),
                   bridges=(Bridge("B1", "R1", b.start_m, b.span_m, b.n_elements, b.E_pa, b.I_m4, b.mass_per_m,
                                   b.depth_m, b.damping_ratio, b.supports),),
                   vehicle_classes=(VehicleClass("quarter_car", TABLE_4_1["mean"], TABLE_4_1["std"]),)), path)
    return path


def _streams(dues: list[list[float]]):
    return [iter([(d, f"s{i}", f"{i}:{k}".encode()) for k, d in enumerate(ds)]) for i, ds in enumerate(dues)]


def test_interleave_orders_by_due_time_then_stream():
    got = []
    res = fleet.interleave(_streams([[0.1, 0.2, 0.3], [0.1, 0.15], []]), lambda k, p: got.append(p.decode()))
    assert got == ["0:0", "1:0", "1:1", "0:1", "0:2"]
    assert res.items == 5 and res.max_late_s == 0.0


def test_interleave_paces_and_stops():
    stamps = []
    t0 = time.monotonic()
    fleet.interleave(_streams([[0.05, 0.10], [0.15]]), lambda k, p: stamps.append(time.monotonic() - t0), rate=2.0)
    assert len(stamps) == 3
    assert all(s >= due / 2.0 - 1e-3 for s, due in zip(stamps, (0.05, 0.10, 0.15)))  # never early
    stop = threading.Event()
    stop.set()
    assert fleet.interleave(_streams([[100.0]]), lambda k, p: None, rate=1.0, stop=stop).items == 0


def test_fleet_streams_are_valid_and_deterministic(site):
    from shared.registry import load_site

    def collect():
        out = []
        res = fleet.run_fleet(lambda k, p: out.append((k, p)), load_site(site), 2, net=NET, rate=None, passes=2,
                              seed=5, run_id="r")
        return res, out

    res, out = collect()
    assert res.passes == 4 and res.published.items == len(out)
    chunks = [(k, decode_sensor_chunk(p)) for k, p in out]
    assert {k for k, _ in chunks} == {keys.imu_key(NET, "veh-0001"), keys.imu_key(NET, "veh-0002")}
    assert all(keys.parse_vehicle_key(k, "imu")[1] == c.vehicle_id for k, c in chunks)
    assert all(c.nominal_params is None and c.sample_rate_hz == 500.0 for _, c in chunks)
    finals = [c for _, c in chunks if c.final]
    assert len(finals) == 4 and {c.pass_id for c in finals} == {"r-00000", "r-00001"}
    assert {c.route_id for _, c in chunks} <= {"R1", "R2"}
    assert collect()[1] == out  # same seed, same bytes


@pytest.mark.parametrize("edit, expect", [
    (None, "does not exist"),
    (lambda t: t.replace("length_m = 140.0", "length_m = -1.0"), "route[0].length_m"),
    (lambda t: t[: t.index("[[vehicle_class]]")], "no vehicle_class"),
    (lambda t: t.replace('"simply_supported"', '"rotational_springs"'), "krot_nm_per_rad"),
    (lambda t: "[[route]\n" + t, "invalid TOML"),
])
def test_bad_site_is_one_clear_line(site, tmp_path, capsys, edit, expect):
    bad = tmp_path / "bad.toml"
    if edit is not None:
        bad.write_text(edit(site.read_text()))
    assert fleet.main(["--site", str(bad), "--vehicles", "2"]) == 1  # a bad input file: 1 (bad usage: 2)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"driveby fleet: {bad}: ") and expect in err


@pytest.mark.parametrize("args, expect", [
    (["--vehicles", "0"], "--vehicles"),
    (["--vehicles", "2", "--rate", "0"], "--rate"),
    (["--vehicles", "2", "--passes", "0"], "--passes"),
    (["--vehicles", "2", "--net", "a/b"], "--net"),
    (["--vehicles", "2", "--speed-range", "30", "20"], "--speed-range"),
])
def test_bad_arguments_are_one_clear_line(site, capsys, args, expect):
    from simfleet import node  # what `driveby fleet` dispatches to

    assert node.main(["--site", str(site), *args]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("driveby fleet: ") and expect in err


def _spawn(args: list[str], log: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, *args], env=dict(os.environ, PYTHONUNBUFFERED="1"),
                            stdin=subprocess.DEVNULL, stdout=open(log, "wb"), stderr=subprocess.STDOUT)


def test_live_fleet_through_edge_and_cloud(site, tmp_path):
    with run_router(timeout_s=TIMEOUT_S) as endpoint:
        common = ["--connect", endpoint, "--net", NET, "--site", str(site)]
        daemons = [_spawn(["-m", "cloud", *common, "--id", "c1"], tmp_path / "cloud.log"),
                   _spawn(["-m", "edge", *common, "--id", "e1"], tmp_path / "edge.log")]  # fleet calibration
        procs = list(daemons)
        try:
            with zenoh.open(zenoh_config("client", connect=[endpoint])) as s:
                up, acked = threading.Event(), threading.Event()
                seen: set[str] = set()
                acks: dict[str, object] = {}

                def on_alive(sample):
                    if sample.kind == zenoh.SampleKind.PUT:
                        seen.add(str(sample.key_expr))
                    if {keys.alive_key(NET, "cloud", "c1"), keys.alive_key(NET, "edge", "e1")} <= seen:
                        up.set()

                def on_ack(sample):
                    ack = decode_ack(sample.payload.to_bytes())
                    acks[ack.vehicle_id] = ack
                    if len(acks) >= 2:
                        acked.set()

                s.liveliness().declare_subscriber(keys.alive_keyexpr(NET), on_alive, history=True)
                s.declare_subscriber(keys.ack_keyexpr(NET), on_ack)
                assert up.wait(TIMEOUT_S), "daemons did not come up"

                run = _spawn(["-m", "simfleet", "fleet", *common, "--vehicles", "2", "--passes", "1",
                              "--rate", "50", "--seed", "1"], tmp_path / "fleet.log")
                procs.append(run)
                assert acked.wait(TIMEOUT_S), f"acks {sorted(acks)}; fleet: {(tmp_path / 'fleet.log').read_text()}"
                assert run.wait(TIMEOUT_S) == 0
                assert "2 passes" in (tmp_path / "fleet.log").read_text()
                assert sorted(acks) == ["veh-0001", "veh-0002"]
                assert all(a.n_segments_accepted >= 2 for a in acks.values())

                replies = list(s.get(keys.control_key(NET, "c1", "stats"), timeout=TIMEOUT_S))
                assert replies and replies[0].ok is not None, "the cloud did not answer its statistics"
                stats = json.loads(replies[0].ok.payload.to_bytes())["stats"]
                assert stats["rejected"] == {} and stats["passes_complete"] == 2
                assert stats["accepted"] == sum(a.n_segments_accepted for a in acks.values())
                assert all(p.poll() is None for p in daemons)
        finally:
            for p in procs:
                if p.poll() is None:
                    p.terminate()
            for p in procs:
                try:
                    p.wait(15)
                except subprocess.TimeoutExpired:
                    p.kill()
