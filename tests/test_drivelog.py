"""Drive-log contract (interfaces.md §1): round trips, and every corruption rejected in one line."""

import json
import math
import pickle
from datetime import datetime

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from shared.drivelog import (
    FORMAT,
    MODEL_CHANNELS,
    MODEL_PARAMS,
    VERSION,
    DriveLog,
    DriveLogError,
    DriveLogMeta,
    drive_log_from_table,
    drive_log_to_table,
    list_drive_logs,
    read_drive_log,
    validate_drive_log,
    write_drive_log,
)

MODELS = sorted(MODEL_CHANNELS)
PROPERTY = settings(max_examples=25, deadline=None)
models = st.sampled_from(MODELS)
names = st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,6}", fullmatch=True)


def make_meta(model="quarter_car", fs=100.0, nominal=True, lane=0.12, pass_id="p1"):
    params = {k: 1.0 + 10.0 * i for i, k in enumerate(MODEL_PARAMS[model])} if nominal else None
    return DriveLogMeta(
        FORMAT, VERSION, "veh-0007", "R1", model, fs, "2026-11-20T08:15:00Z", lane, params, pass_id
    )


def make_log(model="quarter_car", n=20, fs=100.0, seed=0, speed_measured=True, **meta):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    chainage = 3.0 + 12.0 * t + rng.normal(0.0, 0.01, n)
    speed = 12.0 + rng.normal(0.0, 0.1, n) if speed_measured else np.gradient(chainage, 1.0 / fs)
    channels = {ch: rng.normal(0.0, 1.0, n).astype(np.float32) for ch in MODEL_CHANNELS[model]}
    return DriveLog(make_meta(model, fs, **meta), t, chainage, speed, channels, speed_measured)


def assert_logs_equal(a: DriveLog, b: DriveLog) -> None:
    assert a.meta == b.meta
    assert a.speed_measured == b.speed_measured
    for x, y in ((a.t, b.t), (a.chainage, b.chainage), (a.speed, b.speed)):
        assert x.dtype == y.dtype == np.float64
        np.testing.assert_array_equal(x, y)
    assert a.channels.keys() == b.channels.keys()
    for ch in a.channels:
        assert b.channels[ch].dtype == np.float32
        np.testing.assert_array_equal(a.channels[ch], b.channels[ch])


def assert_rejected(path, *fragments) -> str:
    with pytest.raises(DriveLogError) as info:
        read_drive_log(path)
    msg = str(info.value)
    assert len(msg.splitlines()) == 1, msg
    assert msg.startswith(f"{path}: "), msg
    rest = msg[len(f"{path}: "):]  # so a fragment cannot match the file's own name
    for fragment in fragments:
        assert fragment in rest, (fragment, msg)
    return msg


def with_column(table: pa.Table, name: str, array) -> pa.Table:
    """``table`` with column ``name`` replaced by ``array``, metadata kept."""
    i = table.schema.get_field_index(name)
    out = table.set_column(i, name, array)
    return out.replace_schema_metadata(table.schema.metadata)


def with_meta(table: pa.Table, value) -> pa.Table:
    """``table`` with the ``driveby`` metadata replaced (bytes, str, or a JSON-able object)."""
    if not isinstance(value, (bytes, str)):
        value = json.dumps(value)
    return table.replace_schema_metadata({"driveby": value})


def meta_doc(table: pa.Table) -> dict:
    return json.loads(table.schema.metadata[b"driveby"])


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    # Module-scoped: hypothesis re-runs a test body many times within one function-scoped fixture.
    return tmp_path_factory.mktemp("logs")


# --- round trips ------------------------------------------------------------------------------


@PROPERTY
@given(
    model=models,
    n=st.integers(2, 60),
    fs=st.sampled_from([50.0, 100.0, 333.3, 500.0, 1000.0]),
    speed_measured=st.booleans(),
    nominal=st.booleans(),
    lane=st.none() | st.floats(-2.0, 2.0),
    pass_id=st.text(min_size=1, max_size=8).filter(str.strip),
    seed=st.integers(0, 2**32 - 1),
)
def test_write_then_read_is_identity(workdir, model, n, fs, speed_measured, nominal, lane, pass_id, seed):
    log = make_log(model, n, fs, seed, speed_measured, nominal=nominal, lane=lane, pass_id=pass_id)
    path = workdir / "pass.parquet"
    write_drive_log(path, log)
    assert_logs_equal(log, read_drive_log(path))


def test_written_file_is_exactly_the_contract(tmp_path):
    path = tmp_path / "p.parquet"
    write_drive_log(path, make_log("half_car", n=10))
    schema = pq.read_schema(path)
    assert {f.name: str(f.type) for f in schema} == {
        "t": "double",
        "chainage": "double",
        "speed": "double",
        "body_acc": "float",
        "body_pitch_rate": "float",
    }
    doc = json.loads(schema.metadata[b"driveby"])
    assert doc["format"] == "driveby-drive-log" and doc["version"] == 1
    assert doc["vehicle_model"] == "half_car" and doc["sample_rate_hz"] == 100.0
    assert set(doc["nominal_params"]) == set(MODEL_PARAMS["half_car"])
    assert not list(tmp_path.glob("*.tmp"))


def test_contract_example_metadata_is_read(tmp_path):
    example = {
        "format": "driveby-drive-log", "version": 1, "vehicle_id": "veh-0007", "route_id": "R1",
        "vehicle_model": "quarter_car", "sample_rate_hz": 500.0, "start_time_utc": "2026-11-20T08:15:00Z",
        "lane_offset_m": 0.12, "nominal_params": {"M": 4450, "m": 420, "K": 5.0e5, "k": 1.95e6, "c": 2.0e4},
    }
    n = 8
    table = pa.table({
        "t": np.arange(n) / 500.0,
        "chainage": np.linspace(0.0, 1.0, n),
        "body_acc": np.zeros(n, np.float32),
    })
    path = tmp_path / "run 3.parquet"
    pq.write_table(with_meta(table, example), path)
    log = read_drive_log(path)
    assert log.meta.pass_id == "run 3"  # no pass_id: the file's stem
    assert log.meta.nominal_params == {"M": 4450.0, "m": 420.0, "K": 5.0e5, "k": 1.95e6, "c": 2.0e4}
    assert isinstance(log.meta.nominal_params["M"], float)
    assert log.meta.dt == pytest.approx(0.002)
    assert not log.speed_measured


def test_speed_is_derived_from_chainage_when_absent(tmp_path):
    fs, n = 200.0, 50
    t = np.arange(n) / fs
    chainage = 5.0 + 12.5 * t + 0.5 * 0.8 * t**2  # constant acceleration: centred gradient is exact
    log = make_log(n=n, fs=fs)
    table = drive_log_to_table(log).drop_columns(["speed"])
    table = with_column(table, "chainage", pa.array(chainage))
    path = tmp_path / "p.parquet"
    pq.write_table(table, path)
    back = read_drive_log(path)
    assert back.speed_measured is False
    np.testing.assert_allclose(back.speed[1:-1], 12.5 + 0.8 * t[1:-1], rtol=1e-9)
    np.testing.assert_allclose(back.speed[[0, -1]], 12.5 + 0.8 * t[[0, -1]], atol=0.8 / fs)


def test_float64_channels_are_accepted_and_converted(tmp_path):
    log = make_log("carriage")
    table = drive_log_to_table(log)
    for ch in MODEL_CHANNELS["carriage"]:
        table = with_column(table, ch, pa.array(log.channels[ch].astype(np.float64)))
    path = tmp_path / "p.parquet"
    pq.write_table(table, path)
    assert_logs_equal(log, read_drive_log(path))


def test_unknown_columns_and_keys_are_tolerated(tmp_path):
    log = make_log("sprung_mass")
    table = drive_log_to_table(log)
    table = table.append_column("temperature_c", pa.array(["warm"] * len(log)))
    table = table.append_column("body_pitch_rate", pa.array([math.nan] * len(log)))  # not needed by the model
    doc = meta_doc(table) | {"firmware": "2.1", "future": {"x": [1, 2]}}
    path = tmp_path / "p.parquet"
    pq.write_table(with_meta(table, doc), path)
    assert_logs_equal(log, read_drive_log(path))


def test_list_drive_logs_sorted_parquet_only(tmp_path):
    for name in ("b.parquet", "a.parquet", "c.txt", "a.parquet.tmp"):
        (tmp_path / name).write_bytes(b"")
    (tmp_path / "d.parquet").mkdir()
    assert list_drive_logs(tmp_path) == [tmp_path / "a.parquet", tmp_path / "b.parquet"]
    with pytest.raises(DriveLogError, match="nope: directory: does not exist"):
        list_drive_logs(tmp_path / "nope")
    with pytest.raises(DriveLogError, match="c.txt: directory: not a directory"):
        list_drive_logs(tmp_path / "c.txt")


def test_error_is_a_value_error_and_pickles():
    err = DriveLogError("logs/p3.parquet", "column 't'", "not strictly increasing at row 17")
    assert isinstance(err, ValueError)
    assert str(err) == "logs/p3.parquet: column 't': not strictly increasing at row 17"
    assert str(pickle.loads(pickle.dumps(err))) == str(err)
    assert len(str(DriveLogError("a\nb.parquet", "key 'x\r\u2028'", "bad\nthing")).splitlines()) == 1


# --- columns ----------------------------------------------------------------------------------


@PROPERTY
@given(model=models, data=st.data())
def test_missing_channel_is_rejected(workdir, model, data):
    ch = data.draw(st.sampled_from(MODEL_CHANNELS[model]))
    table = drive_log_to_table(make_log(model)).drop_columns([ch])
    path = workdir / "missing.parquet"
    pq.write_table(table, path)
    assert_rejected(path, f"column '{ch}'", "missing", model)


@PROPERTY
@given(model=models, data=st.data())
def test_missing_time_or_chainage_is_rejected(workdir, model, data):
    col = data.draw(st.sampled_from(["t", "chainage"]))
    table = drive_log_to_table(make_log(model)).drop_columns([col])
    path = workdir / "missing.parquet"
    pq.write_table(table, path)
    assert_rejected(path, f"column '{col}'", "missing")


BAD_TYPES = {
    "string": lambda a: pa.array([str(x) for x in a]),
    "int64": lambda a: pa.array(np.round(a).astype(np.int64)),
    "bool": lambda a: pa.array(a > 0),
    "float16": lambda a: pa.array(a.astype(np.float16)),
    "timestamp": lambda a: pa.array((a * 1e6).astype("datetime64[us]")),
}


@PROPERTY
@given(model=models, bad=st.sampled_from([*BAD_TYPES, "float32"]), data=st.data())
def test_wrong_column_type_is_rejected(workdir, model, bad, data):
    col = data.draw(st.sampled_from(["t", "chainage", "speed", *MODEL_CHANNELS[model]]))
    if bad == "float32":
        if col not in ("t", "chainage", "speed"):
            bad = "int64"  # float32 is the channels' own type

    log = make_log(model)
    values = getattr(log, col) if col in ("t", "chainage", "speed") else log.channels[col]
    values = np.asarray(values, np.float64)
    array = pa.array(values.astype(np.float32)) if bad == "float32" else BAD_TYPES[bad](values)
    path = workdir / "dtype.parquet"
    pq.write_table(with_column(drive_log_to_table(log), col, array), path)
    assert_rejected(path, f"column '{col}'", "type")


@PROPERTY
@given(
    model=models,
    n=st.integers(2, 40),
    value=st.sampled_from([math.nan, math.inf, -math.inf]),
    speed_measured=st.booleans(),
    data=st.data(),
)
def test_non_finite_values_are_rejected(workdir, model, n, value, speed_measured, data):
    log = make_log(model, n=n, speed_measured=speed_measured)
    cols = ["t", "chainage", *(["speed"] if speed_measured else []), *MODEL_CHANNELS[model]]
    col = data.draw(st.sampled_from(cols))
    row = data.draw(st.integers(0, n - 1))
    table = drive_log_to_table(log)
    values = table.column(col).to_numpy().copy()
    values[row] = value
    path = workdir / "nonfinite.parquet"
    pq.write_table(with_column(table, col, pa.array(values)), path)
    assert_rejected(path, f"column '{col}'", f"row {row}")


@PROPERTY
@given(model=models, n=st.integers(2, 30), data=st.data())
def test_null_values_are_rejected(workdir, model, n, data):
    log = make_log(model, n=n)
    table = drive_log_to_table(log)
    col = data.draw(st.sampled_from(table.schema.names))
    row = data.draw(st.integers(0, n - 1))
    values = table.column(col).to_pylist()
    values[row] = None
    path = workdir / "null.parquet"
    pq.write_table(with_column(table, col, pa.array(values, table.schema.field(col).type)), path)
    assert_rejected(path, f"column '{col}'", f"row {row}", "null")


@PROPERTY
@given(n=st.integers(3, 40), kind=st.sampled_from(["swap", "repeat", "reverse"]), data=st.data())
def test_non_monotonic_time_is_rejected(workdir, n, kind, data):
    table = drive_log_to_table(make_log(n=n))
    t = table.column("t").to_numpy().copy()
    i = data.draw(st.integers(1, n - 1))
    if kind == "swap":
        t[i - 1], t[i] = t[i], t[i - 1]
    elif kind == "repeat":
        t[i] = t[i - 1]
    else:
        t = t[::-1].copy()
    path = workdir / "time.parquet"
    pq.write_table(with_column(table, "t", pa.array(t)), path)
    assert_rejected(path, "column 't'", "not strictly increasing")


@PROPERTY
@given(
    n=st.integers(2, 40),
    fs=st.sampled_from([10.0, 100.0, 500.0, 2000.0]),
    shift=st.floats(1e-4, 0.45) | st.floats(-0.45, -1e-4),
    data=st.data(),
)
def test_irregular_time_is_rejected(workdir, n, fs, shift, data):
    table = drive_log_to_table(make_log(n=n, fs=fs))
    t = table.column("t").to_numpy().copy()
    t[data.draw(st.integers(0, n - 1))] += shift / fs  # one sample off the grid by a fraction of a step
    path = workdir / "time.parquet"
    pq.write_table(with_column(table, "t", pa.array(t)), path)
    assert_rejected(path, "column 't'", "irregular step")


@PROPERTY
@given(factor=st.floats(0.5, 2.0).filter(lambda f: abs(f - 1.0) > 1e-3))
def test_time_step_must_match_the_declared_sample_rate(workdir, factor):
    table = drive_log_to_table(make_log(fs=100.0))
    path = workdir / "rate.parquet"
    pq.write_table(with_meta(table, meta_doc(table) | {"sample_rate_hz": 100.0 * factor}), path)
    assert_rejected(path, "column 't'", "1/sample_rate_hz")


def test_time_on_grid_far_from_zero_is_accepted(tmp_path):
    log = make_log(n=30, fs=500.0)
    table = drive_log_to_table(log)
    t = 86_400.0 * 30 + np.arange(30) / 500.0  # a month into a log, stored in float64
    path = tmp_path / "p.parquet"
    pq.write_table(with_column(table, "t", pa.array(t)), path)
    np.testing.assert_array_equal(read_drive_log(path).t, t)


@pytest.mark.parametrize("n", [0, 1])
def test_too_few_rows_is_rejected(tmp_path, n):
    path = tmp_path / "short.parquet"
    pq.write_table(drive_log_to_table(make_log(n=5)).slice(0, n), path)
    assert_rejected(path, "column 't'", "at least 2 rows")


def test_duplicate_column_is_rejected(tmp_path):
    table = drive_log_to_table(make_log())
    table = table.append_column("body_acc", table.column("body_acc"))
    path = tmp_path / "dup.parquet"
    pq.write_table(table, path)
    assert_rejected(path, "column 'body_acc'", "2 times")


# --- the file itself --------------------------------------------------------------------------


@PROPERTY
@given(content=st.binary(max_size=200))
def test_non_parquet_file_is_rejected(workdir, content):
    path = workdir / "garbage.parquet"
    path.write_bytes(content)
    assert_rejected(path, "file", "Parquet")


def test_missing_file_and_directory_are_rejected(tmp_path):
    assert_rejected(tmp_path / "absent.parquet", "file", "does not exist")
    (tmp_path / "dir.parquet").mkdir()
    assert_rejected(tmp_path / "dir.parquet", "file", "not a regular file")


# --- metadata ---------------------------------------------------------------------------------


def test_missing_metadata_is_rejected(tmp_path):
    path = tmp_path / "nometa.parquet"
    pq.write_table(drive_log_to_table(make_log()).replace_schema_metadata(None), path)
    assert_rejected(path, "key 'driveby'", "missing")
    pq.write_table(drive_log_to_table(make_log()).replace_schema_metadata({"other": "{}"}), path)
    assert_rejected(path, "key 'driveby'", "missing")


@PROPERTY
@given(raw=st.binary(max_size=80) | st.text(max_size=80) | st.just("[1, 2]"))
def test_garbled_metadata_is_rejected(workdir, raw):
    path = workdir / "garbled.parquet"
    pq.write_table(with_meta(drive_log_to_table(make_log()), raw), path)
    assert_rejected(path, "'driveby")


@PROPERTY
@given(key=st.sampled_from(
    ["format", "version", "vehicle_id", "route_id", "vehicle_model", "sample_rate_hz", "start_time_utc"]
))
def test_missing_required_metadata_key_is_rejected(workdir, key):
    table = drive_log_to_table(make_log())
    doc = meta_doc(table)
    del doc[key]
    path = workdir / "meta.parquet"
    pq.write_table(with_meta(table, doc), path)
    assert_rejected(path, f"key 'driveby.{key}'", "missing")


json_junk = st.one_of(
    st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=10),
    st.lists(st.integers(), max_size=3), st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
)


def acceptable(key: str, v) -> bool:
    """Would the contract accept ``v`` under metadata key ``key`` (for a 100 Hz quarter_car log)?"""
    number = isinstance(v, (int, float)) and not isinstance(v, bool)
    if key in ("vehicle_id", "route_id"):
        return isinstance(v, str) and bool(v.strip())
    if key == "pass_id":
        return v is None or (isinstance(v, str) and bool(v.strip()))
    if key == "start_time_utc":
        try:
            datetime.fromisoformat(v)
            return True
        except (TypeError, ValueError):
            return False
    if key == "lane_offset_m":
        return v is None or (number and math.isfinite(v))
    return {
        "format": lambda: v == FORMAT,
        "version": lambda: number and v == 1 and isinstance(v, int),
        "vehicle_model": lambda: isinstance(v, str) and v == "quarter_car",
        "sample_rate_hz": lambda: number and v == 100.0,
        "nominal_params": lambda: v is None,
    }[key]()


@PROPERTY
@given(
    key=st.sampled_from(["format", "version", "vehicle_model", "sample_rate_hz", "vehicle_id", "route_id",
                         "start_time_utc", "pass_id", "lane_offset_m", "nominal_params"]),
    value=json_junk,
)
def test_bad_metadata_value_is_rejected(workdir, key, value):
    assume(not acceptable(key, value))
    table = drive_log_to_table(make_log("quarter_car"))
    path = workdir / "meta.parquet"
    pq.write_table(with_meta(table, meta_doc(table) | {key: value}), path)
    msg = assert_rejected(path)
    rate_mismatch = key == "sample_rate_hz" and not isinstance(value, bool) and isinstance(value, (int, float))
    if rate_mismatch and value > 0 and math.isfinite(value):
        assert "column 't'" in msg  # a valid rate that disagrees with the time column
    elif key == "vehicle_model" and isinstance(value, str) and value in MODEL_CHANNELS:
        assert "column '" in msg  # another valid model: its channels are missing
    else:
        assert f"key 'driveby.{key}" in msg  # or a key beneath it (nominal_params.M)


@PROPERTY
@given(model=st.text(max_size=12).filter(lambda s: s not in MODEL_CHANNELS))
def test_unknown_model_is_rejected(workdir, model):
    table = drive_log_to_table(make_log())
    path = workdir / "model.parquet"
    pq.write_table(with_meta(table, meta_doc(table) | {"vehicle_model": model}), path)
    assert_rejected(path, "key 'driveby.vehicle_model'", "unknown model")


@PROPERTY
@given(
    model=models,
    kind=st.sampled_from(["unknown", "missing", "value"]),
    value=st.floats(max_value=0.0) | st.sampled_from([math.nan, math.inf, "1e3", True, None, [1.0]]),
    unknown=names,
    data=st.data(),
)
def test_bad_nominal_param_is_rejected(workdir, model, kind, value, unknown, data):
    table = drive_log_to_table(make_log(model))
    doc = meta_doc(table)
    params = doc["nominal_params"]
    if kind == "unknown":
        name = unknown if unknown not in params else unknown + "_x"
        params[name] = 1.0
    else:
        name = data.draw(st.sampled_from(MODEL_PARAMS[model]))
        if kind == "missing":
            del params[name]
        else:
            params[name] = value
    path = workdir / "params.parquet"
    pq.write_table(with_meta(table, doc), path)
    assert_rejected(path, f"'driveby.nominal_params.{name}'")


def test_unsupported_version_and_format_are_rejected(tmp_path):
    table = drive_log_to_table(make_log())
    path = tmp_path / "v.parquet"
    pq.write_table(with_meta(table, meta_doc(table) | {"version": 2}), path)
    assert_rejected(path, "key 'driveby.version'", "unsupported version 2")
    pq.write_table(with_meta(table, meta_doc(table) | {"format": "other-log"}), path)
    assert_rejected(path, "key 'driveby.format'", "driveby-drive-log")


# --- in-memory logs ---------------------------------------------------------------------------


def test_write_refuses_an_invalid_log_and_writes_nothing(tmp_path):
    log = make_log()
    log.channels["body_acc"][3] = np.nan
    path = tmp_path / "bad.parquet"
    with pytest.raises(DriveLogError, match=r"bad\.parquet: column 'body_acc': non-finite value nan at row 3"):
        write_drive_log(path, log)
    assert list(tmp_path.iterdir()) == []


def test_validate_in_memory_log():
    log = make_log("half_car")
    validate_drive_log(log, "sim")
    del log.channels["body_pitch_rate"]
    with pytest.raises(DriveLogError, match=r"^sim: column 'body_pitch_rate': missing"):
        validate_drive_log(log, "sim")
    short = make_log(n=5)
    bad = DriveLog(short.meta, short.t, short.chainage[:4], short.speed, short.channels)
    with pytest.raises(DriveLogError, match="column 'chainage': has 4 rows"):
        validate_drive_log(bad, "sim")


def test_table_round_trip_without_files():
    log = make_log("bogie_half_car", speed_measured=False)
    assert_logs_equal(log, drive_log_from_table(drive_log_to_table(log), "mem", default_pass_id="x"))


# --- whole drives (interfaces.md §5) ----------------------------------------------------------


def make_drive(n=50, seed=0, chainage=False, route=False, imu=True, gyro=True, channels=False):
    """A drive: logger timestamps with jitter, GNSS every 10th row, raw IMU, no chainage/route."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(np.full(n, 0.01) + rng.uniform(-0.002, 0.002, n))
    lat = np.full(n, np.nan)
    lon = np.full(n, np.nan)
    acc = np.full(n, np.nan, np.float32)
    lat[::10] = 52.0 + 1e-5 * np.arange(0, n, 10)
    lon[::10] = 4.0
    acc[::10] = 3.0
    meta = make_meta()
    if not route:
        meta = DriveLogMeta(**{**meta.__dict__, "route_id": None})
    raw = None
    if imu:
        cols = ("acc_x", "acc_y", "acc_z") + (("gyro_x", "gyro_y", "gyro_z") if gyro else ())
        raw = {c: rng.normal(0.0, 1.0, n).astype(np.float32) for c in cols}
    ch = {"body_acc": rng.normal(0.0, 1.0, n).astype(np.float32)} if channels else {}
    x = 12.0 * t if chainage else None
    return DriveLog(meta, t, x, None if x is None else np.full(n, 12.0), ch, True, lat, lon, acc, raw)


@pytest.mark.parametrize("chainage,route,gyro,channels", [(False, False, True, False), (True, True, False, True)])
def test_drive_round_trip(tmp_path, chainage, route, gyro, channels):
    log = make_drive(chainage=chainage, route=route, gyro=gyro, channels=channels)
    path = tmp_path / "drive.parquet"
    write_drive_log(path, log)
    back = read_drive_log(path)
    assert back.meta == log.meta
    assert back.has_positions and not back.is_pass  # irregular timestamps: a drive for the trip splitter
    np.testing.assert_array_equal(back.t, log.t)
    np.testing.assert_array_equal(back.lat, log.lat)  # NaN between fixes survives
    np.testing.assert_array_equal(back.lon, log.lon)
    np.testing.assert_array_equal(back.gnss_accuracy_m, log.gnss_accuracy_m)
    assert back.imu.keys() == log.imu.keys()
    for c in log.imu:
        np.testing.assert_array_equal(back.imu[c], log.imu[c])
    assert (back.chainage is None) == (not chainage)
    assert back.channels.keys() == log.channels.keys()
    names = pq.read_schema(path).names
    assert ("chainage" in names) == chainage and "lat" in names and "acc_z" in names
    assert "route_id" in json.loads(pq.read_schema(path).metadata[b"driveby"]) or not route


def test_a_pass_is_a_pass_and_a_drive_is_not():
    assert make_log().is_pass and not make_log().has_positions
    assert not make_drive().is_pass


def test_a_pass_with_positions_reads_as_a_pass(tmp_path):
    log = make_log(n=30)
    lat = np.full(30, np.nan)
    lat[::5] = 52.0
    with_pos = DriveLog(log.meta, log.t, log.chainage, log.speed, log.channels, True, lat, lat * 0 + 4.0)
    write_drive_log(tmp_path / "p.parquet", with_pos)
    back = read_drive_log(tmp_path / "p.parquet")
    assert back.is_pass and back.has_positions


def test_drive_without_positions_still_needs_chainage_and_route(tmp_path):
    table = drive_log_to_table(make_drive(chainage=True, route=True, channels=True))
    plain = table.drop_columns(["lat", "lon", "gnss_accuracy_m"])
    doc = meta_doc(plain)
    pq.write_table(with_meta(plain.drop_columns(["chainage"]), doc), tmp_path / "a.parquet")
    assert_rejected(tmp_path / "a.parquet", "column 'chainage'", "missing")  # optional only with positions
    del doc["route_id"]
    pq.write_table(with_meta(plain, doc), tmp_path / "b.parquet")
    assert_rejected(tmp_path / "b.parquet", "key 'driveby.route_id'", "missing")


@pytest.mark.parametrize("corrupt,fragments", [
    (lambda tb: tb.drop_columns(["lon"]), ("column 'lon'", "missing")),
    (lambda tb: with_column(tb, "lat", pa.array(np.where(np.isnan(tb["lat"].to_numpy()), np.nan, 95.0))),
     ("column 'lat'", "outside [-90, 90] at row 0")),
    (lambda tb: with_column(tb, "lon", pa.array(np.where(np.arange(tb.num_rows) == 10, np.nan, tb["lon"].to_numpy()))),
     ("column 'lon'", "NaN in one of lat/lon", "row 10")),
    (lambda tb: with_column(tb, "gnss_accuracy_m", pa.array(np.zeros(tb.num_rows, np.float32))),
     ("column 'gnss_accuracy_m'", "positive", "row 0")),
    (lambda tb: tb.drop_columns(["acc_y"]), ("column 'acc_y'", "missing")),
    (lambda tb: tb.drop_columns(["gyro_z"]), ("column 'gyro_z'", "missing")),
    (lambda tb: with_column(tb, "acc_z", pa.array(np.full(tb.num_rows, np.inf, np.float32))),
     ("column 'acc_z'", "non-finite", "row 0")),
    (lambda tb: with_column(with_column(tb, "lat", pa.array(np.full(tb.num_rows, np.nan))), "lon",
                            pa.array(np.full(tb.num_rows, np.nan))), ("column 'lat'", "2 GNSS fixes")),
    (lambda tb: with_column(tb, "t", pa.array(tb["t"].to_numpy()[::-1].copy())), ("column 't'", "not strictly increasing")),
    (lambda tb: tb.drop_columns(["acc_x", "acc_y", "acc_z", "gyro_x", "gyro_y", "gyro_z"]),
     ("column 'body_acc'", "missing")),
])
def test_corrupt_drive_is_rejected_in_one_line(tmp_path, corrupt, fragments):
    table = drive_log_to_table(make_drive())
    path = tmp_path / "drive.parquet"
    pq.write_table(corrupt(table), path)
    assert_rejected(path, *fragments)
