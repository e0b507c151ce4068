"""The streaming spine with real parts: separate OS processes, a Zenoh router on a free loopback
port, real Parquet logs and exports, real .rrd recordings read back. Every wait is on an event
with a timeout; no fixed ports, no sleeps.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import zenoh

from shared import keys
from tests.cloud_status import fused_event
from shared.drivelog import list_drive_logs, read_drive_log
from shared.schema import ApSegment, decode_ack
from shared.transport import run_router, zenoh_config
from simfleet.replay import replay
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

TIMEOUT_S = 120.0  # generous: the first daemon start compiles numba kernels into the cache
QUERY_S = 60.0  # a query answered by a busy daemon on a loaded 2-core machine
NET = "t"


@pytest.fixture(scope="module")
def road(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("road")
    generate(SCENARIOS["road-qc"], out, seed=3, passes=3, workers=1, progress=False)
    return out


def _driveby(*args: str, timeout: float = 600.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "simfleet.cli", *args], capture_output=True, text=True,
                          timeout=timeout, stdin=subprocess.DEVNULL)


def test_run_end_to_end_writes_export_and_recording(road, tmp_path):
    rrd = tmp_path / "run.rrd"
    res = _driveby("run", "--logs", str(road / "logs"), "--site", str(road / "site.toml"),
                   "--export", str(tmp_path / "export"), "--rrd", str(rrd), "--calibration", "nominal")
    assert res.returncode == 0, res.stderr
    assert "3/3 passes processed" in res.stdout
    table = pq.read_table(tmp_path / "export" / "profile.parquet")
    assert table.column_names == ["route_id", "chainage_m", "elevation_m", "lo95_m", "hi95_m", "n_passes",
                                  "chainage_frame"]
    assert max(table.column("n_passes").to_pylist()) == 3
    truth = json.loads((road / "truth.json").read_text())
    from simfleet.evaluate import score_profile

    assert score_profile(tmp_path / "export", truth).rel_error < 0.15  # 3 passes, class-mean calibration
    from rerun.chunk import RrdReader

    rows = []
    for chunk in RrdReader(str(rrd)).stream():
        if chunk.entity_path == "/profile/R1/mean" and not chunk.is_static:
            rows.extend(chunk.to_record_batch().column("pass").to_pylist())
    assert sorted(rows) == [1, 2, 3]  # one profile update per pass


def test_bad_inputs_exit_nonzero_with_one_line(road, tmp_path):
    bad_site = tmp_path / "site.toml"
    bad_site.write_text((road / "site.toml").read_text().replace("length_m = 200.0", "length_m = -1.0"))
    res = _driveby("run", "--logs", str(road / "logs"), "--site", str(bad_site), "--export", str(tmp_path / "x"))
    assert res.returncode != 0
    assert res.stderr.strip().count("\n") == 0 and "length_m" in res.stderr and "site.toml" in res.stderr

    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "broken.parquet").write_bytes(b"not parquet at all")
    res = _driveby("run", "--logs", str(logs), "--site", str(road / "site.toml"), "--export", str(tmp_path / "y"))
    assert res.returncode != 0
    assert res.stderr.strip().count("\n") == 0 and "broken.parquet" in res.stderr


class Deployment:
    """A router, a cloud daemon and an edge daemon in separate processes, joined by endpoints only."""

    def __init__(self, endpoint: str, site: Path, workdir: Path):
        self.endpoint = endpoint
        common = ["--connect", endpoint, "--net", NET, "--site", str(site)]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.procs = [
            subprocess.Popen([sys.executable, "-m", mod, *common, *extra], env=env, stdin=subprocess.DEVNULL,
                             stdout=open(workdir / f"{mod}.log", "wb"), stderr=subprocess.STDOUT)
            for mod, extra in (("cloud", ["--id", "c1"]), ("edge", ["--id", "e1", "--calibration", "nominal"]))
        ]

    def stop(self):
        for p in self.procs:
            p.terminate()
        for p in self.procs:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()


def _stats(session) -> dict:
    replies = list(session.get(keys.control_key(NET, "c1", "stats"), timeout=QUERY_S))
    assert replies and replies[0].ok is not None, "the cloud did not answer its statistics"
    return json.loads(replies[0].ok.payload.to_bytes())


def _tile(session, tile: int) -> bytes:
    replies = list(session.get(keys.state_profile_key(NET, "R1", tile), timeout=QUERY_S))
    assert replies and replies[0].ok is not None, f"the cloud did not answer for tile {tile}"
    return replies[0].ok.payload.to_bytes()


def test_deployment_shape_and_bad_payloads(road, tmp_path):
    with run_router(timeout_s=QUERY_S) as endpoint:
        dep = Deployment(endpoint, road / "site.toml", tmp_path)
        try:
            with zenoh.open(zenoh_config("client", connect=[endpoint])) as s:
                up, acked = threading.Event(), threading.Event()
                seen: set[str] = set()

                def on_alive(sample):
                    if sample.kind == zenoh.SampleKind.PUT:
                        seen.add(str(sample.key_expr))
                    if {keys.alive_key(NET, "cloud", "c1"), keys.alive_key(NET, "edge", "e1")} <= seen:
                        up.set()

                s.liveliness().declare_subscriber(keys.alive_keyexpr(NET), on_alive, history=True)
                s.declare_subscriber(keys.ack_keyexpr(NET), lambda sm: decode_ack(sm.payload.to_bytes()) and acked.set())
                fused = fused_event(s, NET, "c1", 1)  # the estimate is final once the pass is fused
                assert up.wait(TIMEOUT_S), "daemons did not come up"

                log = read_drive_log(list_drive_logs(road / "logs")[0])
                replay([log], lambda k, p: s.put(k, p, congestion_control=zenoh.CongestionControl.BLOCK), NET)
                assert acked.wait(TIMEOUT_S), "pass was not acknowledged"
                assert fused.wait(TIMEOUT_S), "the acknowledged pass was not fused"
                before = _stats(s)["stats"]
                tile1 = _tile(s, 1)
                assert pa.ipc.open_stream(tile1).read_all().num_rows == 1000

                # Bad input on the AP key: garbage, NaN values, a wrong schema version, wrong vehicle.
                good = ApSegment.make(np.zeros(10), np.full(10, 1e-4), vehicle_id="veh-0001", pass_id="x",
                                      route_id="R1", tile=1, axle=1, start_index=1000, spacing_m=0.05,
                                      calib_version=0, speed_mps=20.0, t_first=0.0, t_last=1.0, seq=0)
                key = keys.ap_key(NET, "R1", 1, "veh-0001")
                batch = pa.ipc.open_stream(good.encode()).read_next_batch()
                nan = batch.set_column(batch.schema.get_field_index("offset_m"), "offset_m",
                                       pa.array([float("nan")]))
                meta = dict(batch.schema.metadata)
                wrong_version = batch.replace_schema_metadata(
                    {**meta, b"driveby": json.dumps({"kind": "ap_segment", "version": 99}).encode()})
                bad = [b"\x00garbage", _ipc(nan), _ipc(wrong_version)]
                for payload in bad:
                    s.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
                s.put(keys.ap_key(NET, "R1", 1, "veh-9999"), good.encode(),
                      congestion_control=zenoh.CongestionControl.BLOCK)
                # Ask until the daemon has counted all four (each answer is an event; bounded in time).
                deadline = time.monotonic() + QUERY_S
                while True:
                    after = _stats(s)["stats"]
                    if sum(after["rejected"].values()) - sum(before["rejected"].values()) >= 4:
                        break
                    assert time.monotonic() < deadline, f"rejections not counted: {after}"
                assert sum(after["rejected"].values()) - sum(before["rejected"].values()) == 4
                assert after["rejected"].get("key_mismatch", 0) >= 1
                assert after["accepted"] == before["accepted"]
                assert _tile(s, 1) == tile1  # estimates unchanged
                assert all(p.poll() is None for p in dep.procs)  # still running
        finally:
            dep.stop()


def _ipc(batch: pa.RecordBatch) -> bytes:
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, batch.schema) as w:
        w.write_batch(batch)
    return sink.getvalue().to_pybytes()
