"""The "Sensor Logger" phone app's CSV export (a zip or its unpacked folder) → one drive log (§5).

The export holds one CSV per sensor, each with ``time`` (ns since the epoch) and
``seconds_elapsed`` (s since the recording started): ``TotalAcceleration.csv`` (Android, gravity
included) or ``Accelerometer.csv`` (gravity removed) with ``Gravity.csv``, columns ``z, y, x`` in
m/s²; ``Gyroscope.csv`` ``z, y, x`` in rad/s; ``Location.csv`` with ``latitude``, ``longitude`` and
``horizontalAccuracy`` (m, ~1σ; negative = invalid). ``Metadata.csv`` names the ``platform``:
iOS reports acceleration and gravity with the opposite sign to Android (inertial vs accelerating
force), so iOS readings are negated into the contract's specific force (+9.81 m/s² up at rest).

The drive log has one row per accelerometer sample on its own timestamps; the gyroscope is
interpolated onto them and each GNSS fix lands on the nearest row (NaN elsewhere). Duplicated
rows, which the app can write, are dropped. The log has no ``chainage`` and no ``route_id``: the
edge matches it to the network.
"""

from __future__ import annotations

import csv
import io
import os
import zipfile
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from shared.drivelog import MODEL_CHANNELS, DriveLog, DriveLogError, DriveLogMeta, one_line, write_drive_log

AXES = ("x", "y", "z")


class ExportFormatError(ValueError):
    """A malformed export; ``str(err)`` is one line ``<file>: <problem>``."""

    def __init__(self, file: str, problem: str):
        self.file, self.problem = file, problem
        super().__init__(one_line(f"{file}: {problem}"))

    def __reduce__(self):
        return (type(self), (self.file, self.problem))


class _Export:
    """The CSV files of an export, from a zip or a folder (files may sit in one subfolder)."""

    def __init__(self, path: Path):
        self.path = path
        self.files: dict[str, object] = {}
        if path.is_dir():
            for p in sorted(path.rglob("*.csv")):
                self.files.setdefault(p.name, p)
        elif path.is_file():
            try:
                self._zip = zipfile.ZipFile(path)
            except (zipfile.BadZipFile, OSError) as e:
                raise ExportFormatError(str(path), f"not a zip file or folder of CSV files ({e})") from None
            for info in self._zip.infolist():
                name = info.filename.rsplit("/", 1)[-1]
                if name.endswith(".csv") and not info.is_dir():
                    self.files.setdefault(name, info)
        else:
            raise ExportFormatError(str(path), "does not exist")

    def label(self, name: str) -> str:
        return str(self.path / name)

    def has(self, name: str) -> bool:
        return name in self.files

    def read(self, name: str) -> list[dict[str, str]]:
        src = self.files.get(name)
        if src is None:
            raise ExportFormatError(self.label(name), "missing from the export")
        try:
            if isinstance(src, Path):
                text = src.read_text(encoding="utf-8-sig")
            else:
                text = self._zip.read(src).decode("utf-8-sig")
        except (OSError, UnicodeDecodeError, zipfile.BadZipFile) as e:
            raise ExportFormatError(self.label(name), f"cannot read ({e})") from None
        return list(csv.DictReader(io.StringIO(text)))

    def columns(self, name: str, cols: tuple[str, ...], optional: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
        """Numeric columns of a table (rows with an empty optional value become NaN there)."""
        rows = self.read(name)
        if not rows:
            raise ExportFormatError(self.label(name), "has no rows")
        header = rows[0].keys()
        for c in cols:
            if c not in header:
                raise ExportFormatError(self.label(name), f"column {c!r} missing (has {', '.join(header)})")
        out = {}
        for c in (*cols, *[o for o in optional if o in header]):
            vals = np.empty(len(rows))
            for i, r in enumerate(rows):
                v = (r.get(c) or "").strip()
                if v == "" and c in optional:
                    vals[i] = np.nan
                    continue
                try:
                    vals[i] = float(v)
                except ValueError:
                    raise ExportFormatError(self.label(name), f"column {c!r}: not a number at row {i + 2}: {v!r}") from None
            if c not in optional and not np.isfinite(vals).all():
                i = int(np.argmax(~np.isfinite(vals)))
                raise ExportFormatError(self.label(name), f"column {c!r}: non-finite value at row {i + 2}")
            out[c] = vals
        return out


def _clean_time(name: str, cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Rows sorted by ``seconds_elapsed`` with duplicated timestamps dropped (the first kept)."""
    t = cols["seconds_elapsed"]
    order = np.argsort(t, kind="stable")
    t = t[order]
    keep = np.concatenate(([True], np.diff(t) > 0))
    return {k: v[order][keep] for k, v in cols.items()}


def read_sensor_logger(path: str | os.PathLike, vehicle_model: str = "quarter_car", vehicle_id: str | None = None,
                       sample_rate_hz: float | None = None) -> DriveLog:
    """The drive log of a Sensor Logger export at ``path`` (zip or folder); see the module docstring.

    ``sample_rate_hz`` is the nominal rate (default: the accelerometer's median step, rounded to
    the nearest Hz). Raises `ExportFormatError` (one line naming the file) on a malformed export.
    """
    if vehicle_model not in MODEL_CHANNELS:
        raise ValueError(f"vehicle_model: unknown model {vehicle_model!r} (expected one of {', '.join(MODEL_CHANNELS)})")
    path = Path(path)
    ex = _Export(path)
    meta_rows = ex.read("Metadata.csv") if ex.has("Metadata.csv") else [{}]
    platform = (meta_rows[0].get("platform") or "android").strip().lower() if meta_rows else "android"
    if platform not in ("android", "ios"):
        raise ExportFormatError(ex.label("Metadata.csv"), f"platform must be ios or android, got {platform!r}")
    sign = -1.0 if platform == "ios" else 1.0
    need = ("time", "seconds_elapsed", *AXES)
    if ex.has("TotalAcceleration.csv"):
        acc_name = "TotalAcceleration.csv"
        acc = _clean_time(acc_name, ex.columns(acc_name, need))
        f = np.column_stack([acc[a] for a in AXES])
    elif ex.has("Accelerometer.csv"):
        acc_name = "Accelerometer.csv"
        if not ex.has("Gravity.csv"):
            raise ExportFormatError(ex.label("Gravity.csv"), "missing: Accelerometer.csv has gravity removed and "
                                    "the export has no TotalAcceleration.csv to replace it")
        acc = _clean_time(acc_name, ex.columns(acc_name, need))
        grav = _clean_time("Gravity.csv", ex.columns("Gravity.csv", ("seconds_elapsed", *AXES)))
        _overlap(ex, "Gravity.csv", grav["seconds_elapsed"], acc["seconds_elapsed"])
        f = np.column_stack([acc[a] + np.interp(acc["seconds_elapsed"], grav["seconds_elapsed"], grav[a])
                             for a in AXES])
    else:
        raise ExportFormatError(ex.label("TotalAcceleration.csv"), "missing (and no Accelerometer.csv either): "
                                "the export has no accelerometer")
    f = sign * f
    t = acc["seconds_elapsed"]
    if len(t) < 2:
        raise ExportFormatError(ex.label(acc_name), f"needs at least 2 samples, has {len(t)}")
    gyro = None
    if ex.has("Gyroscope.csv"):
        gy = _clean_time("Gyroscope.csv", ex.columns("Gyroscope.csv", ("seconds_elapsed", *AXES)))
        _overlap(ex, "Gyroscope.csv", gy["seconds_elapsed"], t)
        gyro = np.column_stack([np.interp(t, gy["seconds_elapsed"], gy[a]) for a in AXES])
    loc = _clean_time("Location.csv", ex.columns("Location.csv", ("seconds_elapsed", "latitude", "longitude"),
                                                 optional=("horizontalAccuracy",)))
    lat = np.full(len(t), np.nan)
    lon = np.full(len(t), np.nan)
    ts = loc["seconds_elapsed"]
    inside = (ts >= t[0]) & (ts <= t[-1])
    rows = np.clip(np.searchsorted(t, ts[inside]), 0, len(t) - 1)
    prev = np.clip(rows - 1, 0, None)
    rows = np.where(np.abs(t[prev] - ts[inside]) < np.abs(t[rows] - ts[inside]), prev, rows)  # the nearest row
    lat[rows] = loc["latitude"][inside]
    lon[rows] = loc["longitude"][inside]
    accm = None
    if "horizontalAccuracy" in loc:
        h = loc["horizontalAccuracy"][inside]
        if np.all(h > 0):  # negative or empty is the app's "invalid"; the contract wants all fixes or none
            accm = np.full(len(t), np.nan, np.float32)
            accm[rows] = h
    if len(rows) < 2:
        raise ExportFormatError(ex.label("Location.csv"), f"needs at least 2 fixes during the accelerometer's "
                                f"recording, has {len(rows)}")
    if sample_rate_hz is None:
        sample_rate_hz = float(max(1, round(1.0 / float(np.median(np.diff(t))))))
    start_ns = float(acc["time"][0]) - 1e9 * float(t[0])
    start = datetime.fromtimestamp(start_ns / 1e9, tz=timezone.utc).isoformat().replace("+00:00", "Z")
    vid = vehicle_id or (meta_rows[0].get("device name") or meta_rows[0].get("deviceName") or "").strip() or path.stem
    imu = {f"acc_{a}": f[:, i].astype(np.float32) for i, a in enumerate(AXES)}
    if gyro is not None:
        imu |= {f"gyro_{a}": gyro[:, i].astype(np.float32) for i, a in enumerate(AXES)}
    meta = DriveLogMeta("driveby-drive-log", 1, vid, None, vehicle_model, sample_rate_hz, start, None, None,
                        path.stem.removesuffix(".zip"))
    return DriveLog(meta, t.copy(), None, None, {}, True, lat, lon, accm, imu)


def _overlap(ex: _Export, name: str, t_other: np.ndarray, t_acc: np.ndarray) -> None:
    if len(t_other) < 2 or t_other[-1] < t_acc[0] or t_other[0] > t_acc[-1]:
        raise ExportFormatError(ex.label(name), "does not overlap the accelerometer's recording in time")


def import_sensor_logger(path: str | os.PathLike, out_dir: str | os.PathLike, vehicle_model: str = "quarter_car",
                         vehicle_id: str | None = None, sample_rate_hz: float | None = None) -> list[Path]:
    """Read the export at ``path`` and write its drive log into ``out_dir``; returns the file written."""
    log = read_sensor_logger(path, vehicle_model, vehicle_id, sample_rate_hz)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    target = out / f"{log.meta.pass_id}.parquet"
    try:
        write_drive_log(target, log)
    except DriveLogError as e:  # the export's content breaks the contract: say which export
        raise ExportFormatError(str(path), f"does not make a valid drive log ({e.where}: {e.problem})") from None
    return [target]


__all__ = ["ExportFormatError", "import_sensor_logger", "read_sensor_logger"]
