"""``driveby sim network``: whole drives with positions and a raw IMU, a registry with geometry."""

import json
import subprocess
import sys

import numpy as np
import pyarrow.parquet as pq

from shared.drivelog import list_drive_logs, read_drive_log
from shared.registry import load_site
from simfleet.network import speed_profile
from simfleet.run import run


def test_sim_network_writes_drives_a_geometry_registry_and_truth(tmp_path):
    out = tmp_path / "net"
    r = subprocess.run([sys.executable, "-m", "simfleet", "sim", "network", "--out", str(out), "--passes", "2"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    site = load_site(out / "site.toml")
    assert {rt.id for rt in site.routes} == {"R1", "R2", "R3", "R4"}
    assert all(rt.geometry is not None for rt in site.routes)
    assert site.bridges[0].route == "R4"
    logs = list_drive_logs(out / "logs")
    assert len(logs) == 2
    for p in logs:
        names = pq.read_schema(p).names
        assert "chainage" not in names and "body_acc" not in names and {"lat", "lon", "acc_z", "gyro_z"} <= set(names)
        log = read_drive_log(p)
        assert log.meta.route_id is None and not log.is_pass
        fixes = np.isfinite(log.lat)
        steps = np.diff(log.t)
        assert steps.max() > 0.5  # the IMU gap
        assert np.diff(log.t[fixes]).max() > 7.0  # the GNSS dropout
        assert np.std(steps[steps < 0.1]) > 0.1 / log.meta.sample_rate_hz  # jittered stamps
        acc = np.column_stack([log.imu[c] for c in ("acc_x", "acc_y", "acc_z")])
        up = acc.mean(axis=0) / np.linalg.norm(acc.mean(axis=0))
        assert np.degrees(np.arccos(abs(up[2]))) > 10.0  # a tilted logger
    truth = json.loads((out / "truth.json").read_text())
    assert set(truth["routes"]) == {"R1", "R2", "R3", "R4"} and len(truth["passes"]) == 2
    assert min(truth["passes"][0]["speed"]) == 0.0


def test_speed_profile_starts_and_ends_at_rest_and_stops_where_told():
    dt = 0.01
    s, v, a = speed_profile(800.0, [300.0], 14.0, 1.5, 2.5, 4.0, dt, brake_at=600.0)
    assert v[0] == 0.0 and v[-1] == 0.0 and abs(s[-1] - 800.0) < 1.5  # stands still within the last metre
    stopped = s[(v == 0.0) & (s > 1.0) & (s < 799.0)]
    assert stopped.size > 3.0 / dt and np.all(np.abs(stopped - 300.0) < 1.5)  # waits ~4 s at the light
    assert a.min() >= -2.5 - 1e-9 and a.max() <= 1.5 + 1e-9 and v.max() <= 14.0 * 1.02  # the driver's lag overshoots a little
    mid = (s > 560) & (s < 600)
    assert v[mid].min() < 0.6 * 14.0  # the mid-route braking


def test_drives_with_positions_only_run_end_to_end_over_zenoh(tmp_path, network_one_trip):
    """``driveby run`` on logs without chainage or route: cut into passes, processed by the real edge
    and cloud daemons over Zenoh, exported with coordinates."""
    out = network_one_trip
    res = run(out / "logs", out / "site.toml", tmp_path / "export", calibration="nominal", progress=False)
    assert res.passes >= 4 and res.acked == res.passes  # one drive became several single-route passes
    rough = pq.read_table(tmp_path / "export" / "roughness.parquet").to_pydict()
    assert {"R1", "R2", "R3"} <= set(rough["route_id"])  # trip 1 drives R1, R2 and R3
    assert np.isfinite(rough["start_lat"]).all() and np.isfinite(rough["end_lon"]).all()
    features = json.loads((tmp_path / "export" / "roughness.geojson").read_text())["features"]
    assert len(features) == len(rough["route_id"])
