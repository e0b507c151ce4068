"""``driveby import phone-csv``: a synthetic Sensor Logger export of a simulated drive round-trips to
the native drive log and to the same passes; malformed exports are refused in one line."""

import subprocess
import sys
import zipfile

import numpy as np
import pytest

from edge.mapmatch import build_network
from edge.trip import split_trip
from shared.drivelog import read_drive_log
from simfleet.importers.sensor_logger import ExportFormatError, import_sensor_logger, read_sensor_logger
from simfleet.network import TRIPS, NetworkScenario, geometries, route_surfaces, simulate_trip
from simfleet.scenarios import TABLE_4_1

T0_NS = 1_763_625_600_000_000_000  # 2025-11-20T08:00:00Z


@pytest.fixture(scope="module")
def drive():
    sc = NetworkScenario("t", "test", fleet_mean=tuple(TABLE_4_1["mean"].items()),
                         fleet_std=tuple(TABLE_4_1["std"].items()))
    geoms = geometries()
    log, _ = simulate_trip(sc, TRIPS[1], geoms, route_surfaces(geoms, "A", 0), dict(TABLE_4_1["mean"]), "veh-0001",
                           0, 7, None)
    return log, build_network(geoms)


def _csv(path, header, rows):
    with open(path, "w") as f:
        f.write(",".join(header) + "\n")
        for r in rows:
            f.write(",".join(repr(float(v)) if not isinstance(v, str) else v for v in r) + "\n")


def write_export(log, folder, platform="android", duplicate=True):
    """The Sensor Logger layout of ``log``: axes written z, y, x as the app does."""
    folder.mkdir(parents=True, exist_ok=True)
    t = log.t
    ns = [T0_NS + int(round(1e9 * x)) for x in t]
    f = np.column_stack([log.imu[f"acc_{a}"] for a in "xyz"]).astype(np.float64)
    w = np.column_stack([log.imu[f"gyro_{a}"] for a in "xyz"]).astype(np.float64)
    sign = -1.0 if platform == "ios" else 1.0
    acc_rows = [(ns[i], t[i], *(sign * f[i, ::-1])) for i in range(len(t))]
    if duplicate:
        acc_rows.insert(10, acc_rows[9])  # the app can repeat a row
    if platform == "android":
        _csv(folder / "TotalAcceleration.csv", ("time", "seconds_elapsed", "z", "y", "x"), acc_rows)
    else:
        g = np.tile(np.mean(f, axis=0), (len(t), 1))  # the app's gravity estimate; any split of f works
        user = f - g
        _csv(folder / "Accelerometer.csv", ("time", "seconds_elapsed", "z", "y", "x"),
             [(ns[i], t[i], *(sign * user[i, ::-1])) for i in range(len(t))])
        _csv(folder / "Gravity.csv", ("time", "seconds_elapsed", "z", "y", "x"),
             [(ns[i], t[i], *(sign * g[i, ::-1])) for i in range(len(t))])
    _csv(folder / "Gyroscope.csv", ("time", "seconds_elapsed", "z", "y", "x"),
         [(ns[i], t[i], *w[i, ::-1]) for i in range(len(t))])
    fix = np.flatnonzero(np.isfinite(log.lat))
    _csv(folder / "Location.csv", ("time", "seconds_elapsed", "bearingAccuracy", "speedAccuracy", "verticalAccuracy",
                                   "horizontalAccuracy", "speed", "bearing", "altitude", "longitude", "latitude"),
         [(ns[i], t[i], -1.0, -1.0, 3.0, float(log.gnss_accuracy_m[i]), 12.0, 90.0, 4.0, log.lon[i], log.lat[i])
          for i in fix])
    (folder / "Metadata.csv").write_text(f"version,device name,recording time,platform\n3,Pixel 7,2025-11-20,"
                                         f"{platform}\n")
    return folder


@pytest.mark.parametrize("platform,zipped", [("android", True), ("ios", False)])
def test_export_round_trips_to_the_native_log_and_its_passes(drive, tmp_path, platform, zipped):
    log, net = drive
    folder = write_export(log, tmp_path / "rec", platform)
    src = folder
    if zipped:
        src = tmp_path / "rec.zip"
        with zipfile.ZipFile(src, "w") as z:
            for p in folder.iterdir():
                z.write(p, f"Recording 2025-11-20/{p.name}")
    written = import_sensor_logger(src, tmp_path / "out", sample_rate_hz=log.meta.sample_rate_hz)
    back = read_drive_log(written[0])
    assert back.meta.route_id is None and back.meta.vehicle_id == "Pixel 7"
    assert back.meta.start_time_utc == "2025-11-20T08:00:00Z"
    np.testing.assert_array_equal(back.t, log.t)  # repr() of a float64 reads back exactly; the duplicate is gone
    np.testing.assert_array_equal(back.lat, log.lat)
    np.testing.assert_array_equal(back.lon, log.lon)
    for c in log.imu:
        # iOS: (f − g) + g in float64, then float32: at most one float32 ulp of ~10 m/s² apart.
        np.testing.assert_allclose(back.imu[c], log.imu[c], rtol=0, atol=2e-6)
    a, b = split_trip(log, net), split_trip(back, net)
    assert len(a.passes) == len(b.passes) >= 2
    for p, q in zip(a.passes, b.passes):
        assert p.meta.route_id == q.meta.route_id
        np.testing.assert_array_equal(p.t, q.t)
        # One float32 ulp in the IMU moves the smoothed chainage by far less than a millimetre.
        np.testing.assert_allclose(q.chainage, p.chainage, rtol=0, atol=1e-3)
        np.testing.assert_allclose(q.channels["body_acc"], p.channels["body_acc"], rtol=0, atol=1e-4)


def _broken(tmp_path, log, how):
    folder = write_export(log, tmp_path / how, duplicate=False)
    if how == "no_location":
        (folder / "Location.csv").unlink()
        return folder, "Location.csv: missing from the export"
    if how == "no_latitude":
        text = (folder / "Location.csv").read_text().replace("latitude", "lat")
        (folder / "Location.csv").write_text(text)
        return folder, "Location.csv: column 'latitude' missing"
    if how == "garbage":
        lines = (folder / "Gyroscope.csv").read_text().splitlines()
        lines[5] = lines[5].split(",", 1)[0] + ",abc,1,2,3"
        (folder / "Gyroscope.csv").write_text("\n".join(lines) + "\n")
        return folder, "Gyroscope.csv: column 'seconds_elapsed': not a number at row 6"
    if how == "no_gravity":
        (folder / "TotalAcceleration.csv").rename(folder / "Accelerometer.csv")
        return folder, "Gravity.csv: missing"
    if how == "not_zip":
        bad = tmp_path / "x.zip"
        bad.write_text("hello")
        return bad, "not a zip file"
    if how == "platform":
        (folder / "Metadata.csv").write_text("platform\nwindows\n")
        return folder, "Metadata.csv: platform must be ios or android"
    raise AssertionError(how)


@pytest.mark.parametrize("how", ["no_location", "no_latitude", "garbage", "no_gravity", "not_zip", "platform"])
def test_malformed_export_is_refused_in_one_line(drive, tmp_path, how):
    log, _ = drive
    src, fragment = _broken(tmp_path, log, how)
    with pytest.raises(ExportFormatError) as info:
        read_sensor_logger(src)
    msg = str(info.value)
    assert "\n" not in msg and fragment in msg and msg.startswith(str(src))


def test_cli_import_writes_a_log_and_refuses_a_broken_export(drive, tmp_path):
    log, _ = drive
    folder = write_export(log, tmp_path / "rec")
    ok = subprocess.run([sys.executable, "-m", "simfleet", "import", "phone-csv", str(folder), "--out",
                         str(tmp_path / "out")], capture_output=True, text=True, timeout=300)
    assert ok.returncode == 0, ok.stderr
    back = read_drive_log(tmp_path / "out" / "rec.parquet")
    assert back.meta.sample_rate_hz == 200.0 and back.has_positions  # the median step of 200 Hz stamps
    (folder / "Location.csv").unlink()
    bad = subprocess.run([sys.executable, "-m", "simfleet", "import", "phone-csv", str(folder), "--out",
                          str(tmp_path / "out2")], capture_output=True, text=True, timeout=300)
    assert bad.returncode == 1
    assert bad.stderr.count("\n") == 1 and "Location.csv: missing from the export" in bad.stderr
