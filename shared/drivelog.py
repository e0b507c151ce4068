"""Drive logs, the field-data input contract (interfaces.md §1, §5): one Parquet file per pass or per
whole drive, validated.

A *pass* (§1) is one route at a uniform sample step with chainage. A *drive* (§5) carries GNSS
positions (``lat``/``lon``, NaN between fixes) and may lack ``chainage``/``route_id``, run on a
logger's non-uniform timestamps, and carry the raw IMU in the logger's frame instead of the model's
channels; the edge cuts it into passes (`edge.trip`).
"""

from __future__ import annotations

import json
import math
import numbers
import os
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # pyarrow is imported lazily: edge start-up and registry users never need it
    import pyarrow as pa

FORMAT = "driveby-drive-log"
VERSION = 1
SUPPORTED_VERSIONS = (1,)
METADATA_KEY = "driveby"

MODEL_CHANNELS: dict[str, tuple[str, ...]] = {
    "sprung_mass": ("body_acc",),
    "quarter_car": ("body_acc",),
    "half_car": ("body_acc", "body_pitch_rate"),
    "bogie_half_car": ("body_acc", "body_pitch_rate"),
    "carriage": ("bogie1_acc", "bogie1_pitch_rate", "bogie2_acc", "bogie2_pitch_rate"),
}

MODEL_PARAMS: dict[str, tuple[str, ...]] = {
    "sprung_mass": ("m", "k"),
    "quarter_car": ("M", "m", "K", "k", "c"),
    "half_car": ("ms", "Is", "mu1", "mu2", "Ks1", "Ks2", "Cs1", "Cs2", "Kt1", "Kt2", "D1", "D2"),
    "bogie_half_car": ("ms", "Is", "K1", "K2", "C1", "C2", "D1", "D2"),
    "carriage": ("mv", "Iv", "mb", "Ib", "mw", "kp", "cp", "ks", "cs", "Lb", "Lv", "v"),
}

#: Optional GNSS columns of a drive (§5): WGS84 degrees and the receiver's 1σ, NaN between fixes.
POSITION_COLUMNS = ("lat", "lon", "gnss_accuracy_m")
#: Optional raw IMU in the logger's frame (§5): m/s² with gravity, rad/s.
ACC_COLUMNS = ("acc_x", "acc_y", "acc_z")
GYRO_COLUMNS = ("gyro_x", "gyro_y", "gyro_z")
IMU_COLUMNS = ACC_COLUMNS + GYRO_COLUMNS
_RESERVED = ("t", "chainage", "speed", *POSITION_COLUMNS, *IMU_COLUMNS)

# Relative and absolute tolerance on each step of `t` against 1/sample_rate_hz; a few ulps of the
# largest |t| are added so long logs stored as float64 are not rejected for rounding alone.
_STEP_RTOL = 1e-6
_STEP_ATOL = 1e-9

# Every character str.splitlines() treats as a line break: a message must stay one line even when
# it quotes a file name or a key taken from the input.
_LINE_BREAKS = "\n\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029"


def one_line(text: str) -> str:
    """``text`` with every line-break character replaced by its backslash escape."""
    for ch in _LINE_BREAKS:
        if ch in text:
            text = text.replace(ch, ch.encode("unicode_escape").decode("ascii"))
    return text


class DriveLogError(ValueError):
    """A drive log breaks the contract; ``str(err)`` is one line ``<file>: <column or key>: <problem>``."""

    def __init__(self, file: str | os.PathLike, where: str, problem: str):
        self.file = str(file)
        self.where = where
        self.problem = problem
        super().__init__(one_line(f"{self.file}: {where}: {problem}"))

    def __reduce__(self):  # keep picklable (multiprocessing) despite the 3-argument constructor
        return (type(self), (self.file, self.where, self.problem))


@dataclass(frozen=True)
class DriveLogMeta:
    """The ``driveby`` key-value metadata of a drive log (interfaces.md §1).

    ``sample_rate_hz`` in Hz (nominal for a drive with logger timestamps), ``lane_offset_m`` in m
    (None when unknown), ``nominal_params`` maps every parameter name of ``vehicle_model``
    (``MODEL_PARAMS``) to a positive SI value, or is None. ``route_id`` is None only for a drive
    with positions (§5), which the edge matches to the network.
    """

    format: str
    version: int
    vehicle_id: str
    route_id: str | None
    vehicle_model: str
    sample_rate_hz: float
    start_time_utc: str
    lane_offset_m: float | None
    nominal_params: dict[str, float] | None
    pass_id: str

    @property
    def dt(self) -> float:
        """Sample step, s."""
        return 1.0 / self.sample_rate_hz


@dataclass(frozen=True, eq=False)
class DriveLog:
    """One vehicle pass or drive: time (s), chainage (m), speed (m/s) and the model's channels (float32).

    ``speed_measured`` is False when the file had no ``speed`` column and ``speed`` was derived
    from ``chainage`` by a centred gradient. ``channels`` holds the channels ``vehicle_model`` needs
    (``MODEL_CHANNELS``); other columns of the file are ignored.

    A drive (§5) may also carry ``lat``/``lon`` (float64 degrees) and ``gnss_accuracy_m`` (float32,
    m, 1σ), NaN between fixes, and ``imu`` (``IMU_COLUMNS`` → float32, logger frame; the three
    accelerations, optionally with the three rates). With positions, ``chainage`` and ``speed`` may
    be None, ``t`` may be non-uniform, and with ``imu`` the model's channels may be absent.
    """

    meta: DriveLogMeta
    t: np.ndarray
    chainage: np.ndarray | None
    speed: np.ndarray | None
    channels: dict[str, np.ndarray]
    speed_measured: bool = True
    lat: np.ndarray | None = None
    lon: np.ndarray | None = None
    gnss_accuracy_m: np.ndarray | None = None
    imu: dict[str, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self.t)

    @property
    def has_positions(self) -> bool:
        """True when the log carries GNSS positions (§5)."""
        return self.lat is not None

    @property
    def is_pass(self) -> bool:
        """True when the edge can process the log as it is: one route, chainage, a uniform step and
        the model's channels. Otherwise it is a drive for the trip splitter (`edge.trip`)."""
        if self.chainage is None or self.meta.route_id is None:
            return False
        if any(ch not in self.channels for ch in MODEL_CHANNELS[self.meta.vehicle_model]):
            return False
        return _time_grid_problem(np.asarray(self.t, np.float64), self.meta.sample_rate_hz) is None


# --- public functions -------------------------------------------------------------------------


def read_drive_log(path: str | os.PathLike) -> DriveLog:
    """Read and validate one drive log.

    Parameters
    ----------
    path : str or PathLike
        A Parquet file following interfaces.md §1.

    Returns
    -------
    DriveLog
        ``t`` (s), ``chainage`` (m) and ``speed`` (m/s) as float64, channels as float32.

    Raises
    ------
    DriveLogError
        If the file is unreadable, not Parquet, or breaks the contract in any way.
    """
    import pyarrow as pa  # pyarrow only where a file is read or written (see the module top)
    import pyarrow.parquet as pq

    name = str(path)
    if not Path(path).is_file():
        problem = "not a regular file" if Path(path).exists() else "does not exist"
        raise DriveLogError(name, "file", problem)
    try:
        table = pq.ParquetFile(path).read()
    except (OSError, pa.ArrowException, ValueError) as exc:
        raise DriveLogError(name, "file", f"cannot read as Parquet ({_reason(exc)})") from None
    return drive_log_from_table(table, name, default_pass_id=Path(path).stem)


def drive_log_from_table(
    table: pa.Table, name: str = "<drive log>", default_pass_id: str | None = None
) -> DriveLog:
    """Validate an Arrow table laid out as a drive log and turn it into a `DriveLog`.

    ``name`` labels error messages; ``default_pass_id`` (default: the stem of ``name``) is used when
    the metadata carry no ``pass_id``.
    """
    if default_pass_id is None:
        default_pass_id = Path(name).stem
    names = table.schema.names
    positions = "lat" in names or "lon" in names
    meta = _check_meta(_meta_from_schema(table.schema, name, default_pass_id, positions), name, positions)
    if table.num_rows < 2:
        raise DriveLogError(name, "column 't'", f"needs at least 2 rows, has {table.num_rows}")

    t = _column(table, "t", name, _FLOAT64)
    lat = lon = accuracy = imu = None
    if positions:
        lat = _column(table, "lat", name, _FLOAT64)
        lon = _column(table, "lon", name, _FLOAT64)
        if "gnss_accuracy_m" in names:
            accuracy = _column(table, "gnss_accuracy_m", name, _FLOAT32_OR_64).astype(np.float32, copy=False)
    if any(c in names for c in IMU_COLUMNS):
        present = ACC_COLUMNS + (GYRO_COLUMNS if any(c in names for c in GYRO_COLUMNS) else ())
        imu = {c: _column(table, c, name, _FLOAT32_OR_64).astype(np.float32, copy=False) for c in present}
    chainage = None
    if "chainage" in names or not positions:
        chainage = _column(table, "chainage", name, _FLOAT64)
    speed_measured = "speed" in names
    if speed_measured:
        speed = _column(table, "speed", name, _FLOAT64)
    elif chainage is not None:
        # A bad chainage must be blamed on chainage, not on the speed derived from it.
        _check_finite(chainage, "chainage", name)
        if positions:  # a logger's timestamps: the gradient over t itself
            _check_finite(t, "t", name)
            _check_increasing(t, name)
            speed = np.gradient(chainage, t)
        else:
            speed = np.gradient(chainage, meta.dt)
    else:
        speed = None
    channels = {}
    for ch in MODEL_CHANNELS[meta.vehicle_model]:
        if ch not in names:
            if imu is not None:
                continue  # derived from the raw IMU at the edge
            raise DriveLogError(
                name, f"column {ch!r}", f"missing (required by vehicle_model {meta.vehicle_model!r})"
            )
        channels[ch] = _column(table, ch, name, _FLOAT32_OR_64).astype(np.float32, copy=False)

    log = DriveLog(meta, t, chainage, speed, channels, speed_measured, lat, lon, accuracy, imu)
    _check_arrays(log, name)
    return log


def validate_drive_log(log: DriveLog, name: str = "<drive log>") -> None:
    """Check an in-memory `DriveLog` against the contract; raise `DriveLogError` naming ``name``."""
    _check_meta(log.meta, name, log.lat is not None)
    _check_arrays(log, name)


def drive_log_to_table(log: DriveLog, name: str = "<drive log>") -> pa.Table:
    """Validate ``log`` and encode it exactly as the contract lays it out.

    ``t``, ``chainage`` and (when ``speed_measured``) ``speed`` as float64, channels as float32, the
    metadata as JSON under the schema key ``driveby``. A derived speed is not written, so reading
    the table back derives it again.
    """
    import pyarrow as pa  # pyarrow only where a table is built (see the module top)

    meta = _check_meta(log.meta, name, log.lat is not None)
    _check_arrays(log, name)
    columns = {"t": np.asarray(log.t, np.float64)}
    if log.chainage is not None:
        columns["chainage"] = np.asarray(log.chainage, np.float64)
    if log.speed_measured and log.speed is not None:
        columns["speed"] = np.asarray(log.speed, np.float64)
    required = MODEL_CHANNELS[meta.vehicle_model]
    for ch in (*[c for c in required if c in log.channels], *sorted(set(log.channels) - set(required))):
        columns[ch] = np.asarray(log.channels[ch], np.float32)
    if log.lat is not None:
        columns["lat"] = np.asarray(log.lat, np.float64)
        columns["lon"] = np.asarray(log.lon, np.float64)
        if log.gnss_accuracy_m is not None:
            columns["gnss_accuracy_m"] = np.asarray(log.gnss_accuracy_m, np.float32)
    for c in IMU_COLUMNS:
        if log.imu is not None and c in log.imu:
            columns[c] = np.asarray(log.imu[c], np.float32)
    doc: dict[str, Any] = {
        "format": meta.format,
        "version": meta.version,
        "vehicle_id": meta.vehicle_id,
    }
    if meta.route_id is not None:
        doc["route_id"] = meta.route_id
    doc.update({
        "vehicle_model": meta.vehicle_model,
        "sample_rate_hz": meta.sample_rate_hz,
        "start_time_utc": meta.start_time_utc,
    })
    if meta.lane_offset_m is not None:
        doc["lane_offset_m"] = meta.lane_offset_m
    if meta.nominal_params is not None:
        doc["nominal_params"] = dict(meta.nominal_params)
    doc["pass_id"] = meta.pass_id
    table = pa.table({k: pa.array(v) for k, v in columns.items()})
    return table.replace_schema_metadata({METADATA_KEY: json.dumps(doc, allow_nan=False)})


def write_drive_log(path: str | os.PathLike, log: DriveLog) -> None:
    """Validate ``log`` and write it to ``path`` as a contract Parquet file.

    The file appears atomically (written beside it, then renamed), so a directory watcher never
    sees half a log. Raises `DriveLogError` (and writes nothing) if ``log`` is invalid.
    """
    import pyarrow.parquet as pq  # pyarrow only where a file is written (see the module top)

    path = Path(path)
    table = drive_log_to_table(log, str(path))
    tmp = path.with_name(path.name + ".tmp")
    try:
        pq.write_table(table, tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def list_drive_logs(directory: str | os.PathLike) -> list[Path]:
    """The ``*.parquet`` files directly in ``directory``, sorted by name."""
    directory = Path(directory)
    if not directory.exists():
        raise DriveLogError(directory, "directory", "does not exist")
    if not directory.is_dir():
        raise DriveLogError(directory, "directory", "not a directory")
    return sorted(p for p in directory.glob("*.parquet") if p.is_file())


# --- metadata ---------------------------------------------------------------------------------

_REQUIRED_KEYS = (
    "format",
    "version",
    "vehicle_id",
    "route_id",
    "vehicle_model",
    "sample_rate_hz",
    "start_time_utc",
)


def _key(name: str) -> str:
    return f"key {METADATA_KEY + '.' + name if name else METADATA_KEY!r}"


def _meta_from_schema(schema: pa.Schema, file: str, default_pass_id: str, positions: bool = False) -> DriveLogMeta:
    """Parse the JSON under ``driveby`` into an unchecked `DriveLogMeta` (values as found).

    ``positions``: the table has GNSS positions, so ``route_id`` may be absent (§5)."""
    raw = (schema.metadata or {}).get(METADATA_KEY.encode())
    if raw is None:
        raise DriveLogError(file, _key(""), "metadata missing")
    try:
        doc = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise DriveLogError(file, _key(""), "metadata is not valid UTF-8") from None
    except json.JSONDecodeError as exc:
        raise DriveLogError(file, _key(""), f"metadata is not valid JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise DriveLogError(file, _key(""), f"metadata must be a JSON object, not {_jtype(doc)}")
    for k in _REQUIRED_KEYS:
        if k not in doc and not (k == "route_id" and positions):
            raise DriveLogError(file, _key(k), "missing")
    pass_id = doc.get("pass_id")
    return DriveLogMeta(
        format=doc["format"],
        version=doc["version"],
        vehicle_id=doc["vehicle_id"],
        route_id=doc.get("route_id"),
        vehicle_model=doc["vehicle_model"],
        sample_rate_hz=doc["sample_rate_hz"],
        start_time_utc=doc["start_time_utc"],
        lane_offset_m=doc.get("lane_offset_m"),
        nominal_params=doc.get("nominal_params"),
        pass_id=default_pass_id if pass_id is None else pass_id,
    )


def _check_meta(meta: DriveLogMeta, file: str, positions: bool = False) -> DriveLogMeta:
    """Validate ``meta``; return it with numbers normalised to ``float``/``int``.

    ``positions``: the log has GNSS positions, so ``route_id`` may be None (§5)."""
    if not isinstance(meta, DriveLogMeta):
        raise DriveLogError(file, _key(""), f"expected a DriveLogMeta, got {type(meta).__name__}")
    if meta.format != FORMAT:
        raise DriveLogError(file, _key("format"), f"must be {FORMAT!r}, got {meta.format!r}")
    if not _is_int(meta.version) or meta.version not in SUPPORTED_VERSIONS:
        raise DriveLogError(
            file, _key("version"), f"unsupported version {meta.version!r} (supported: {SUPPORTED_VERSIONS})"
        )
    for k in ("vehicle_id", "route_id", "pass_id"):
        if not (k == "route_id" and positions and meta.route_id is None):
            _check_id(getattr(meta, k), k, file)
    if not isinstance(meta.vehicle_model, str) or meta.vehicle_model not in MODEL_CHANNELS:
        raise DriveLogError(
            file,
            _key("vehicle_model"),
            f"unknown model {meta.vehicle_model!r} (expected one of {', '.join(MODEL_CHANNELS)})",
        )
    fs = meta.sample_rate_hz
    if not _is_real(fs) or not math.isfinite(fs) or fs <= 0:
        raise DriveLogError(file, _key("sample_rate_hz"), f"must be a positive finite number, got {fs!r}")
    if not isinstance(meta.start_time_utc, str):
        got = _jtype(meta.start_time_utc)
        raise DriveLogError(file, _key("start_time_utc"), f"must be a string, got {got}")
    try:
        datetime.fromisoformat(meta.start_time_utc)
    except ValueError:
        raise DriveLogError(
            file, _key("start_time_utc"), f"not an ISO 8601 time: {meta.start_time_utc!r}"
        ) from None
    lane = meta.lane_offset_m
    if lane is not None and (not _is_real(lane) or not math.isfinite(lane)):
        raise DriveLogError(file, _key("lane_offset_m"), f"must be a finite number or absent, got {lane!r}")
    params = meta.nominal_params
    if params is not None:
        params = _check_params(params, meta.vehicle_model, file)
    return DriveLogMeta(
        format=meta.format,
        version=int(meta.version),
        vehicle_id=meta.vehicle_id,
        route_id=meta.route_id,
        vehicle_model=meta.vehicle_model,
        sample_rate_hz=float(fs),
        start_time_utc=meta.start_time_utc,
        lane_offset_m=None if lane is None else float(lane),
        nominal_params=params,
        pass_id=meta.pass_id,
    )


def _check_id(value: Any, key: str, file: str) -> None:
    if not isinstance(value, str) or not value.strip():
        raise DriveLogError(file, _key(key), f"must be a non-empty string, got {value!r}")


def _check_params(params: Any, model: str, file: str) -> dict[str, float]:
    if not isinstance(params, dict):
        raise DriveLogError(file, _key("nominal_params"), f"must be an object, got {_jtype(params)}")
    names = MODEL_PARAMS[model]
    for k in params:
        if k not in names:
            raise DriveLogError(
                file,
                _key(f"nominal_params.{k}"),
                f"not a parameter of {model!r} (expected {', '.join(names)})",
            )
    out = {}
    for k in names:
        if k not in params:
            raise DriveLogError(file, _key(f"nominal_params.{k}"), f"missing (required for {model!r})")
        v = params[k]
        if not _is_real(v) or not math.isfinite(v) or v <= 0:
            raise DriveLogError(
                file, _key(f"nominal_params.{k}"), f"must be a positive finite number, got {v!r}"
            )
        out[k] = float(v)
    return out


# --- columns and arrays -----------------------------------------------------------------------

_FLOAT64 = ("double",)
_FLOAT32_OR_64 = ("float", "double")


def _column(table: pa.Table, name: str, file: str, allowed: tuple[str, ...]) -> np.ndarray:
    """Column ``name`` as a fresh numpy array, after checking presence, type and nulls."""
    where = f"column {name!r}"
    idx = table.schema.get_all_field_indices(name)
    if not idx:
        raise DriveLogError(file, where, "missing")
    if len(idx) > 1:
        raise DriveLogError(file, where, f"appears {len(idx)} times")
    col = table.column(idx[0])
    if str(col.type) not in allowed:
        expected = " or ".join({"double": "float64", "float": "float32"}[a] for a in allowed)
        raise DriveLogError(file, where, f"has type {col.type}, expected {expected}")
    if col.null_count:
        row = int(np.argmax(col.is_null().to_numpy(zero_copy_only=False)))
        raise DriveLogError(file, where, f"null value at row {row}")
    return np.array(col.to_numpy(), dtype=np.float64 if str(col.type) == "double" else np.float32)


def _check_finite(a: np.ndarray, name: str, file: str) -> None:
    bad = ~np.isfinite(a)
    if bad.any():
        row = int(np.argmax(bad))
        raise DriveLogError(file, f"column {name!r}", f"non-finite value {a[row]} at row {row}")


def _check_array(a: Any, name: str, n: int | None, file: str) -> None:
    where = f"column {name!r}"
    if not isinstance(a, np.ndarray) or a.dtype.kind not in "fiu":
        raise DriveLogError(file, where, f"must be a real numpy array, got {type(a).__name__}")
    if a.ndim != 1:
        raise DriveLogError(file, where, f"must be 1-D, has shape {a.shape}")
    if n is not None and len(a) != n:
        raise DriveLogError(file, where, f"has {len(a)} rows, 't' has {n}")
    _check_finite(a, name, file)


def _check_arrays(log: DriveLog, file: str) -> None:
    """Shapes, finiteness, the time grid and the model's channels of a log with checked metadata."""
    _check_array(log.t, "t", None, file)
    n = len(log.t)
    if n < 2:
        raise DriveLogError(file, "column 't'", f"needs at least 2 rows, has {n}")
    t = np.asarray(log.t, np.float64)
    positions = log.lat is not None or log.lon is not None
    if positions:
        _check_positions(log, n, file)
        _check_increasing(t, file)  # a logger's timestamps: the edge resamples them
    else:
        _check_time_grid(t, log.meta.sample_rate_hz, file)
    if log.chainage is not None or not positions:
        _check_array(log.chainage, "chainage", n, file)
    if log.speed is not None or log.chainage is not None:
        _check_array(log.speed, "speed", n, file)
    if not isinstance(log.speed_measured, bool):
        raise DriveLogError(file, "column 'speed'", "speed_measured must be a bool")
    if log.imu is not None:
        if not isinstance(log.imu, dict):
            raise DriveLogError(file, "imu", f"must be a dict, got {type(log.imu).__name__}")
        for c in log.imu:
            if c not in IMU_COLUMNS:
                raise DriveLogError(file, f"column {c!r}", f"not a raw IMU column ({', '.join(IMU_COLUMNS)})")
        for group in (ACC_COLUMNS, GYRO_COLUMNS):
            given = [c for c in group if c in log.imu]
            if given and len(given) < 3 or group is ACC_COLUMNS and not given:
                missing = next(c for c in group if c not in log.imu)
                raise DriveLogError(file, f"column {missing!r}", f"missing (the raw IMU needs all of {', '.join(group)})")
        for c, a in log.imu.items():
            _check_array(a, c, n, file)
    if not isinstance(log.channels, dict):
        raise DriveLogError(file, "channels", f"must be a dict, got {type(log.channels).__name__}")
    model = log.meta.vehicle_model
    for ch in MODEL_CHANNELS[model]:
        if ch not in log.channels and log.imu is None:
            raise DriveLogError(file, f"column {ch!r}", f"missing (required by vehicle_model {model!r})")
    for ch, a in log.channels.items():
        if not isinstance(ch, str) or ch in _RESERVED:
            raise DriveLogError(file, f"column {ch!r}", "not a valid channel name")
        _check_array(a, ch, n, file)


def _check_positions(log: DriveLog, n: int, file: str) -> None:
    """``lat``/``lon`` (and ``gnss_accuracy_m``): NaN together between fixes, in range at fixes."""
    for c in ("lat", "lon"):
        a = getattr(log, c)
        where = f"column {c!r}"
        if a is None:
            raise DriveLogError(file, where, "missing (lat and lon go together)")
        if not isinstance(a, np.ndarray) or a.dtype.kind != "f" or a.ndim != 1:
            raise DriveLogError(file, where, "must be a 1-D float numpy array")
        if len(a) != n:
            raise DriveLogError(file, where, f"has {len(a)} rows, 't' has {n}")
        if np.isinf(a).any():
            raise DriveLogError(file, where, f"infinite value at row {int(np.argmax(np.isinf(a)))}")
    fix = ~np.isnan(log.lat)
    differ = fix != ~np.isnan(log.lon)
    if differ.any():
        raise DriveLogError(file, "column 'lon'", f"NaN in one of lat/lon but not the other at row {int(np.argmax(differ))}")
    if fix.sum() < 2:
        raise DriveLogError(file, "column 'lat'", f"needs at least 2 GNSS fixes, has {int(fix.sum())}")
    for c, lim in (("lat", 90.0), ("lon", 180.0)):
        bad = fix & (np.abs(np.nan_to_num(getattr(log, c))) > lim)
        if bad.any():
            row = int(np.argmax(bad))
            raise DriveLogError(file, f"column {c!r}", f"{getattr(log, c)[row]:g} outside [-{lim:g}, {lim:g}] at row {row}")
    acc = log.gnss_accuracy_m
    if acc is not None:
        where = "column 'gnss_accuracy_m'"
        if not isinstance(acc, np.ndarray) or acc.dtype.kind != "f" or acc.ndim != 1 or len(acc) != n:
            raise DriveLogError(file, where, f"must be a 1-D float array of {n} rows")
        bad = fix & ~(np.isfinite(acc) & (acc > 0))
        if bad.any():
            row = int(np.argmax(bad))
            raise DriveLogError(file, where, f"must be positive and finite at a fix, got {acc[row]} at row {row}")


def _check_increasing(t: np.ndarray, file: str) -> None:
    back = np.diff(t) <= 0
    if back.any():
        row = int(np.argmax(back)) + 1
        raise DriveLogError(file, "column 't'", f"not strictly increasing at row {row}")


def _time_grid_problem(t: np.ndarray, fs: float) -> str | None:
    """Why ``t`` is not the uniform grid of step ``1/fs`` (None if it is)."""
    step = np.diff(t)
    back = step <= 0
    if back.any():
        return f"not strictly increasing at row {int(np.argmax(back)) + 1}"
    dt = 1.0 / fs
    tol = _STEP_RTOL * dt + _STEP_ATOL + 4.0 * float(np.spacing(np.max(np.abs(t))))
    off = np.abs(step - dt) > tol
    if off.any():
        row = int(np.argmax(off)) + 1
        return f"irregular step {step[row - 1]:.9g} s before row {row}, expected 1/sample_rate_hz = {dt:.9g} s"
    return None


def _check_time_grid(t: np.ndarray, fs: float, file: str) -> None:
    problem = _time_grid_problem(t, fs)
    if problem is not None:
        raise DriveLogError(file, "column 't'", problem)


# --- small helpers ----------------------------------------------------------------------------


def _is_real(x: Any) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, (bool, np.bool_))


def _is_int(x: Any) -> bool:
    return isinstance(x, numbers.Integral) and not isinstance(x, (bool, np.bool_))


def _jtype(x: Any) -> str:
    return {dict: "an object", list: "an array", str: "a string", bool: "a boolean", type(None): "null"}.get(
        type(x), type(x).__name__
    )


def _reason(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."
