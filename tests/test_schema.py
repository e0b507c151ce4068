"""Codec tests for shared.schema: round trips, quantisation bounds, every malformed payload."""

from __future__ import annotations

import json
import math

import numpy as np
import pyarrow as pa
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from shared import schema
from shared.schema import (
    Ack,
    Alarm,
    ApBatch,
    ApSegment,
    Calibration,
    DecodeError,
    InvalidMessage,
    PassDone,
    SensorChunk,
    decode,
    decode_ack,
    decode_alarm,
    decode_ap,
    decode_ap_segment,
    decode_calibration,
    decode_pass_done,
    decode_sensor_chunk,
)

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])

ids = st.from_regex(r"[A-Za-z0-9_.-]{1,24}", fullmatch=True)
pass_ids = st.text(st.characters(min_codepoint=32, max_codepoint=0x2FF, blacklist_categories=("Cc", "Cs")), min_size=1, max_size=40).filter(str.isprintable)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
models = st.sampled_from(sorted(schema.VEHICLE_MODELS))
param_names = st.from_regex(r"[A-Za-z0-9_./-]{1,12}", fullmatch=True)
params = st.dictionaries(param_names, st.floats(-1e9, 1e9, allow_nan=False), max_size=12)
small_int = st.integers(0, 10_000)


def _floats(n: int, lo: float, hi: float, dtype=np.float64):
    return hnp.arrays(dtype, n, elements=st.floats(lo, hi, allow_nan=False, width=np.dtype(dtype).itemsize * 8))


@st.composite
def sensor_chunks(draw) -> SensorChunk:
    n = draw(st.integers(0, 64))
    names = draw(st.lists(st.from_regex(r"[a-z_][a-z0-9_]{0,15}", fullmatch=True), max_size=4, unique=True))
    return SensorChunk(
        vehicle_id=draw(ids),
        pass_id=draw(pass_ids),
        route_id=draw(ids),
        vehicle_model=draw(models),
        seq=draw(small_int),
        t0=draw(st.floats(0, 1e6)),
        sample_rate_hz=draw(st.floats(1.0, 1e4)),
        chainage=draw(_floats(n, -1e6, 1e6)),
        speed=draw(_floats(n, -schema.MAX_SPEED_MPS, schema.MAX_SPEED_MPS)),
        channels={c: draw(_floats(n, -1e4, 1e4, np.float32)) for c in names},
        final=draw(st.booleans()),
        nominal_params=draw(st.none() | params),
        lane_offset_m=draw(st.none() | st.floats(-10, 10)),
    )


@st.composite
def ap_segments(draw) -> ApSegment:
    n = draw(st.integers(1, 200))
    seq = draw(st.integers(0, 100))
    t_first = draw(st.floats(0, 1e5))
    return ApSegment.make(
        draw(_floats(n, -1.0, 1.0)),
        draw(_floats(n, 1e-6, 1.0)),
        vehicle_id=draw(ids),
        pass_id=draw(pass_ids),
        route_id=draw(ids),
        tile=draw(small_int),
        axle=draw(st.integers(1, 4)),
        start_index=draw(st.integers(0, 10**9)),
        spacing_m=draw(st.floats(1e-3, 1.0)),
        calib_version=draw(small_int),
        speed_mps=draw(st.floats(0, 100)),
        t_first=t_first,
        t_last=t_first + draw(st.floats(0, 100)),
        seq=seq,
        n_segments_in_pass=draw(st.just(-1) | st.integers(seq + 1, seq + 50)),
        flags=draw(st.integers(0, 7)),
    )


pass_dones = st.builds(PassDone, ids, pass_ids, ids, small_int, small_int)
calibrations = st.builds(Calibration, ids, small_int, models, params, st.text(max_size=30).filter(str.isprintable))
alarms = st.builds(
    Alarm,
    ids,
    st.datetimes(timezones=st.timezones()).map(lambda t: t.isoformat()),
    ids,
    st.integers(-1, 100),
    finite,
    st.floats(0, 1e3),
    st.floats(0, 1),
    st.text(max_size=200).filter(lambda s: "\x00" not in s),
)
acks = st.builds(Ack, pass_ids, ids, small_int, small_int)

CASES = [
    pytest.param(sensor_chunks(), decode_sensor_chunk, id="sensor_chunk"),
    pytest.param(ap_segments(), decode_ap_segment, id="ap_segment"),
    pytest.param(pass_dones, decode_pass_done, id="pass_done"),
    pytest.param(calibrations, decode_calibration, id="calibration"),
    pytest.param(alarms, decode_alarm, id="alarm"),
    pytest.param(acks, decode_ack, id="ack"),
]


# -- round trips ------------------------------------------------------------------------


@pytest.mark.parametrize("strategy, decoder", CASES)
@SETTINGS
@given(data=st.data())
def test_round_trip(strategy, decoder, data):
    msg = data.draw(strategy)
    payload = msg.encode()
    back = decoder(payload)
    assert type(back) is type(msg)
    assert back == msg
    assert decode(payload) == msg  # the kind-dispatching decoder agrees
    assert back.encode() == payload  # encoding is deterministic
    assert payload == _write(*_table(payload))  # byte for byte Arrow's stream writer (the encoder frames it itself)


def test_a_batch_is_framed_as_arrows_stream_writer_frames_it():
    segs = [_segment(tile=t, seq=t, start_index=1000 * t - 3, error_model=None if t % 2 else [1.5, 2.0, -0.4][: 2 + t % 2])
            for t in range(4)]
    payload = ApBatch(tuple(segs)).encode()
    assert payload == _write(*_table(payload))
    assert decode_ap(payload) == segs


def test_equality_sees_array_differences():
    a = _segment()
    b = ApSegment.make(np.array([0.0, 0.002, 0.001]), np.full(3, 1e-4), **_SEG_FIELDS)
    assert a == _segment() and a != b


def test_decoded_arrays_are_read_only():
    chunk = decode_sensor_chunk(_chunk().encode())
    for a in (chunk.chainage, chunk.speed, *chunk.channels.values()):
        with pytest.raises(ValueError):
            a[0] = 1.0


_SEG_FIELDS = dict(
    vehicle_id="veh-0007",
    pass_id="pass 1",
    route_id="R1",
    tile=2,
    axle=1,
    start_index=2000,
    spacing_m=0.05,
    calib_version=3,
    speed_mps=15.0,
    t_first=10.0,
    t_last=13.0,
    seq=0,
)


def _segment(**over) -> ApSegment:
    fields = {**_SEG_FIELDS, **over}
    return ApSegment.make(np.array([0.0, 0.001, 0.002]), np.full(3, 1e-4), **fields)


def _chunk(**over) -> SensorChunk:
    n = 5
    fields = dict(
        vehicle_id="veh-0007",
        pass_id="p1",
        route_id="R1",
        vehicle_model="quarter_car",
        seq=0,
        t0=0.0,
        sample_rate_hz=500.0,
        chainage=np.linspace(0, 0.1, n),
        speed=np.full(n, 20.0),
        channels={"body_acc": np.zeros(n, np.float32)},
        nominal_params={"M": 4450.0, "K/M": 112.0},
        lane_offset_m=0.12,
    )
    fields.update(over)
    return SensorChunk(**fields)


def test_ap_segment_geometry():
    seg = _segment()
    assert seg.n == 3 and seg.end_index == 2003
    np.testing.assert_allclose(seg.chainage_m, [100.0, 100.05, 100.1])
    assert seg.identity == ("veh-0007", "pass 1", "R1", 2, 1, 3)


# -- quantisation -----------------------------------------------------------------------


@SETTINGS
@given(
    values=hnp.arrays(np.float64, st.integers(1, 500), elements=st.floats(-1e3, 1e3)),
    shift=st.floats(-1e3, 1e3),
)
def test_values_within_half_a_step(values, shift):
    values = np.clip(values + shift, -1e3, 1e3)
    seg = _segment_from(values, np.ones_like(values))
    step = (values.max() - values.min()) / (2 * schema.Q_MAX)
    err = np.abs(seg.values - values)
    assert np.all(err <= 0.5 * step + 1e-12 * (1 + np.abs(values)))
    assert seg.values.dtype == np.float64


@SETTINGS
@given(sigma=hnp.arrays(np.float64, st.integers(1, 500), elements=st.floats(1e-6, 1e3)))
def test_sigma_rounded_up_within_a_code(sigma):
    seg = _segment_from(np.zeros_like(sigma), sigma)
    floor = sigma.max() * 2.0**-16
    kept = np.maximum(sigma, floor)  # sigmas below the floor are raised to it
    ratio = seg.sigma / kept
    assert np.all(ratio >= 1 - 1e-12)
    assert np.all(ratio <= 2.0 ** (1 / schema.SIGMA_CODES_PER_OCTAVE) * (1 + 1e-12))
    assert np.all(seg.sigma > 0)


def test_constant_segment_is_exact():
    seg = _segment_from(np.full(7, -0.25), np.full(7, 1e-3))
    assert np.array_equal(seg.values, np.full(7, -0.25))
    assert np.array_equal(seg.sigma, np.full(7, 1e-3))


def test_precision_claim_in_docstring():
    """A 50 m tile whose AP spans 40 mm is carried to better than 0.31 um."""
    x = np.arange(1000) * 0.05
    values = 0.02 * np.sin(2 * np.pi * x / 7.0)
    seg = decode_ap_segment(_segment_from(values, np.full(1000, 1e-4)).encode())
    assert np.max(np.abs(seg.values - values)) <= 0.31e-6


def _segment_from(values, sigma) -> ApSegment:
    return ApSegment.make(values, sigma, **{**_SEG_FIELDS, "tile": 0})


# -- malformed payloads -----------------------------------------------------------------


def _table(payload: bytes) -> tuple[dict[str, pa.Array], dict[bytes, bytes]]:
    reader = pa.ipc.open_stream(payload)
    batch = reader.read_next_batch()
    return {name: batch.column(name) for name in batch.schema.names}, dict(batch.schema.metadata)


def _write(columns: dict[str, pa.Array], metadata: dict[bytes, bytes] | None, batches: int = 1) -> bytes:
    schema_ = pa.schema([pa.field(k, v.type) for k, v in columns.items()], metadata=metadata)
    batch = pa.RecordBatch.from_arrays(list(columns.values()), schema=schema_)
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, schema_) as w:
        for _ in range(batches):
            w.write_batch(batch)
    return sink.getvalue().to_pybytes()


def _edit(payload: bytes, **changes) -> bytes:
    """Re-encode ``payload`` with some columns replaced (``None`` drops a column)."""
    cols, meta = _table(payload)
    for name, col in changes.items():
        if col is None:
            cols.pop(name)
        else:
            cols[name] = col
    return _write(cols, meta)


def _with_header(payload: bytes, header) -> bytes:
    cols, meta = _table(payload)
    if header is None:
        meta.pop(b"driveby")
    else:
        meta[b"driveby"] = header if isinstance(header, bytes) else json.dumps(header).encode()
    return _write(cols, meta)


def _reason(decoder, payload) -> str:
    with pytest.raises(DecodeError) as info:
        decoder(payload)
    assert info.value.reason in schema.REASONS
    assert isinstance(info.value, ValueError)
    return info.value.reason


AP = _segment().encode()
CHUNK = _chunk().encode()


def test_decode_error_is_a_countable_value_error():
    err = DecodeError("wrong_kind", "expected x")
    assert isinstance(err, ValueError) and err.reason == "wrong_kind" and "expected x" in str(err)


@SETTINGS
@given(st.binary(min_size=0, max_size=2048))
def test_random_bytes(payload):
    assert _reason(decode_ap_segment, payload) in ("not_arrow", "bad_header", "bad_shape")


def test_not_bytes():
    assert _reason(decode_ap_segment, "a string") == "not_arrow"
    assert _reason(decode_ap_segment, None) == "not_arrow"
    assert _reason(decode_ap_segment, 5) == "not_arrow"


def test_zenoh_payload_accepted_as_is():
    zenoh = pytest.importorskip("zenoh")
    assert decode_ap_segment(zenoh.ZBytes(AP)) == _segment()


def test_empty_and_garbage():
    assert _reason(decode_ap_segment, b"") == "not_arrow"
    assert _reason(decode_ap_segment, b"\xff" * 64) == "not_arrow"


@pytest.mark.parametrize("cut", [1, 7, 8, 100, 300, len(AP) // 2, len(AP) - 9])
def test_truncated(cut):
    # Cut inside the schema or the batch: Arrow cannot read it; cut after the
    # schema message: there is no batch.
    assert _reason(decode_ap_segment, AP[:cut]) in ("not_arrow", "bad_shape")


def test_truncated_everywhere_never_escapes():
    eos = 8  # the stream's end-of-stream marker: losing all of it loses no data
    for cut in [*range(0, len(AP) - eos, 13), *range(len(AP) - eos + 1, len(AP))]:
        with pytest.raises(DecodeError):
            decode_ap_segment(AP[:cut])
    assert decode_ap_segment(AP[: len(AP) - eos]) == _segment()


@settings(SETTINGS, max_examples=300)
@given(st.data())
def test_bit_flips_never_escape(data):
    """Any single corrupted byte yields a DecodeError or a valid message, nothing else."""
    payload = bytearray(data.draw(st.sampled_from([AP, CHUNK])))
    i = data.draw(st.integers(0, len(payload) - 1))
    payload[i] ^= data.draw(st.integers(1, 255))
    try:
        msg = decode(bytes(payload))
    except DecodeError as e:
        assert e.reason in schema.REASONS
    else:
        assert isinstance(msg, ApSegment | SensorChunk)


@pytest.mark.parametrize("payload", [CHUNK, AP], ids=["sensor_chunk", "ap_segment"])
def test_huge_words_in_the_batch_never_escape(payload):
    """Regression: reading a batch's size before validating it followed a corrupt
    list offset out of bounds and killed the process (found by fuzzing).  Set every
    aligned 32-bit word after the schema message to a huge value, one at a time."""
    body = payload.index(b"\xff\xff\xff\xff", 8)  # continuation marker of the batch message
    huge = np.array([15_335_424], np.int32).tobytes()
    for i in range(body, len(payload) - 4, 4):
        corrupt = payload[:i] + huge + payload[i + 4 :]
        try:
            decode(corrupt)
        except DecodeError as e:
            assert e.reason in schema.REASONS


def test_duplicate_columns():
    cols, meta = _table(AP)
    names = list(cols) + ["tile"]
    arrays = list(cols.values()) + [pa.array([9])]
    schema_ = pa.schema([pa.field(n, a.type) for n, a in zip(names, arrays)], metadata=meta)
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, schema_) as w:
        w.write_batch(pa.RecordBatch.from_arrays(arrays, schema=schema_))
    assert _reason(decode_ap_segment, sink.getvalue().to_pybytes()) == "bad_shape"


def test_wrong_kind():
    done = PassDone("veh-1", "p1", "R1", 0, 3).encode()
    assert _reason(decode_ap_segment, done) == "wrong_kind"
    assert _reason(decode_pass_done, AP) == "wrong_kind"
    assert _reason(decode, _with_header(AP, {"kind": "mystery", "version": 1})) == "wrong_kind"


def test_wrong_version():
    assert _reason(decode_ap_segment, _with_header(AP, {"kind": "ap_segment", "version": 2})) == "wrong_version"
    assert _reason(decode, _with_header(AP, {"kind": "ap_segment", "version": 0})) == "wrong_version"


@pytest.mark.parametrize(
    "header", [None, b"not json", b"[1, 2]", {"kind": "ap_segment"}, {"kind": 3, "version": 1}, {"kind": "ap_segment", "version": True}]
)
def test_bad_header(header):
    assert _reason(decode_ap_segment, _with_header(AP, header)) == "bad_header"


def test_nan_and_inf():
    bad_chainage = pa.array([[0.0, math.nan, 0.2, 0.3, 0.4]], pa.list_(pa.float64()))
    assert _reason(decode_sensor_chunk, _edit(CHUNK, chainage=bad_chainage)) == "non_finite"
    bad_channel = pa.array([[0, 0, math.inf, 0, 0]], pa.list_(pa.float32()))
    assert _reason(decode_sensor_chunk, _edit(CHUNK, **{"ch.body_acc": bad_channel})) == "non_finite"
    assert _reason(decode_ap_segment, _edit(AP, scale_m=pa.array([math.nan]))) == "non_finite"
    assert _reason(decode_ap_segment, _edit(AP, t_first=pa.array([-math.inf]))) == "non_finite"
    params = pa.array([[("M", math.nan)]], pa.map_(pa.string(), pa.float64()))
    assert _reason(decode_sensor_chunk, _edit(CHUNK, nominal_params=params)) == "non_finite"


def test_mismatched_lengths():
    short = pa.array([[20.0, 20.0]], pa.list_(pa.float64()))
    assert _reason(decode_sensor_chunk, _edit(CHUNK, speed=short)) == "bad_shape"
    long_channel = pa.array([[0.0] * 6], pa.list_(pa.float32()))
    assert _reason(decode_sensor_chunk, _edit(CHUNK, **{"ch.body_acc": long_channel})) == "bad_shape"
    assert _reason(decode_ap_segment, _edit(AP, sigma_q=pa.array([[0, 0]], pa.list_(pa.int16())))) == "bad_shape"
    empty = pa.array([[]], pa.list_(pa.int16()))
    assert _reason(decode_ap_segment, _edit(AP, values_q=empty, sigma_q=empty)) == "bad_shape"


def test_not_one_row_of_one_batch():
    cols, meta = _table(AP)
    assert _reason(decode_ap_segment, _write(cols, meta, batches=2)) == "bad_shape"
    assert _reason(decode_ap_segment, _write(cols, meta, batches=0)) == "bad_shape"
    doubled = {k: pa.concat_arrays([v, v]) for k, v in cols.items()}
    assert _reason(decode_ap_segment, _write(doubled, meta)) == "bad_shape"


def test_oversize():
    assert _reason(decode_ap_segment, b"\x00" * (schema.MAX_PAYLOAD_BYTES + 1)) == "oversize"
    n = 300_000  # 300k samples of float64 chainage + speed + 2 float32 channels > 4 MiB
    big = _chunk(
        chainage=np.zeros(n),
        speed=np.zeros(n),
        channels={"a": np.zeros(n, np.float32), "b": np.zeros(n, np.float32)},
    )
    with pytest.raises(InvalidMessage) as info:
        big.encode()
    assert info.value.reason == "oversize"


def test_missing_field():
    assert _reason(decode_ap_segment, _edit(AP, calib_version=None)) == "missing_field"
    assert _reason(decode_ap_segment, _edit(AP, calib_version=pa.array([None], pa.int64()))) == "missing_field"
    assert _reason(decode_sensor_chunk, _edit(CHUNK, chainage=None)) == "missing_field"
    with_null = pa.array([[0.0, None, 0.2, 0.3, 0.4]], pa.list_(pa.float64()))
    assert _reason(decode_sensor_chunk, _edit(CHUNK, chainage=with_null)) == "missing_field"
    # optional fields may be absent or null
    chunk = decode_sensor_chunk(_edit(CHUNK, lane_offset_m=None, nominal_params=None))
    assert chunk.lane_offset_m is None and chunk.nominal_params is None


def test_bad_type():
    assert _reason(decode_ap_segment, _edit(AP, tile=pa.array(["2"]))) == "bad_type"
    assert _reason(decode_ap_segment, _edit(AP, spacing_m=pa.array([True]))) == "bad_type"
    as_float = pa.array([[0.0, 1.0, 2.0]], pa.list_(pa.float64()))
    assert _reason(decode_ap_segment, _edit(AP, values_q=as_float)) == "bad_type"
    assert _reason(decode_sensor_chunk, _edit(CHUNK, final=pa.array([1]))) == "bad_type"


def test_bad_values():
    assert _reason(decode_ap_segment, _edit(AP, axle=pa.array([0]))) == "bad_value"
    assert _reason(decode_ap_segment, _edit(AP, spacing_m=pa.array([0.0]))) == "bad_value"
    assert _reason(decode_ap_segment, _edit(AP, scale_m=pa.array([-1e-6]))) == "bad_value"
    assert _reason(decode_ap_segment, _edit(AP, sigma_q=pa.array([[0, 5, 0]], pa.list_(pa.int16())))) == "bad_value"
    assert _reason(decode_ap_segment, _edit(AP, t_last=pa.array([1.0]))) == "bad_value"
    assert _reason(decode_ap_segment, _edit(AP, vehicle_id=pa.array(["veh/1"]))) == "bad_value"
    assert _reason(decode_ap_segment, _edit(AP, n_segments_in_pass=pa.array([0]))) == "bad_value"
    assert _reason(decode_sensor_chunk, _edit(CHUNK, vehicle_model=pa.array(["tricycle"]))) == "bad_value"
    fast = pa.array([[20.0, 20.0, 900.0, 20.0, 20.0]], pa.list_(pa.float64()))
    assert _reason(decode_sensor_chunk, _edit(CHUNK, speed=fast)) == "bad_value"
    dup = pa.array([[("M", 1.0), ("M", 2.0)]], pa.map_(pa.string(), pa.float64()))
    assert _reason(decode_sensor_chunk, _edit(CHUNK, nominal_params=dup)) == "bad_value"


def test_unknown_columns_are_ignored():
    """Messages may grow optional columns without a version bump."""
    assert decode_ap_segment(_edit(AP, future_field=pa.array([1.5]))) == _segment()


# -- constructors validate too ------------------------------------------------------------


@pytest.mark.parametrize(
    "make, reason",
    [
        (lambda: _segment(vehicle_id="a b"), "bad_value"),
        (lambda: _segment(vehicle_id=7), "bad_type"),
        (lambda: _segment(tile=-1), "bad_value"),
        (lambda: _segment(tile=True), "bad_type"),
        (lambda: _segment(speed_mps=math.inf), "non_finite"),
        (lambda: _segment(pass_id=""), "bad_value"),
        (lambda: _segment(pass_id="a\nb"), "bad_value"),
        (lambda: ApSegment.make(np.array([0.0, math.nan]), np.ones(2), **_SEG_FIELDS), "non_finite"),
        (lambda: ApSegment.make(np.zeros(2), np.array([1e-3, 0.0]), **_SEG_FIELDS), "bad_value"),
        (lambda: ApSegment.make(np.zeros(2), np.ones(3), **_SEG_FIELDS), "bad_shape"),
        (lambda: ApSegment.make(np.zeros((2, 2)), np.ones(2), **_SEG_FIELDS), "bad_shape"),
        (lambda: ApSegment.make(np.array(["a", "b"]), np.ones(2), **_SEG_FIELDS), "bad_type"),
        (lambda: _chunk(channels={"bad name": np.zeros(5)}), "bad_value"),
        (lambda: _chunk(channels={"x": np.full(5, 1e39)}), "non_finite"),  # overflows float32
        (lambda: _chunk(sample_rate_hz=0.0), "bad_value"),
        (lambda: _chunk(nominal_params={"M": "heavy"}), "bad_type"),
        (lambda: Calibration("v1", 1, "quarter_car", {"k": math.inf}, "fleet"), "non_finite"),
        (lambda: Alarm("B1", "2026-11-20T08:15:00", "crack", 3, 5.0, 0.1, 0.5), "bad_value"),
        (lambda: Alarm("B1", "yesterday", "crack", 3, 5.0, 0.1, 0.5), "bad_value"),
        (lambda: Alarm("B1", "2026-11-20T08:15:00Z", "crack", 3, 5.0, 0.1, 1.5), "bad_value"),
        (lambda: Ack("p1", "veh-1", -1), "bad_value"),
        (lambda: PassDone("veh-1", "p1", "R1", 0, 10**12), "bad_value"),
    ],
)
def test_constructor_rejects(make, reason):
    with pytest.raises(InvalidMessage) as info:
        make()
    assert info.value.reason == reason
    assert not isinstance(info.value, DecodeError)


def _outcome(payload):
    try:
        return ("ok", decode(payload))
    except DecodeError as e:
        return (e.reason, str(e))


def test_the_fast_read_agrees_with_the_general_read(monkeypatch):
    """`_read_batch` reads payloads laid out as ours through a cached-schema fast path and
    everything else through Arrow's stream reader: both give the same message or the same error."""
    assert schema._read_our_batch(CHUNK) is not None and schema._read_our_batch(AP) is not None
    cols, meta = _table(CHUNK)
    batch = pa.RecordBatch.from_arrays(list(cols.values()), schema=pa.schema(
        [pa.field(k, v.type) for k, v in cols.items()], metadata=meta))
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, batch.schema, options=pa.ipc.IpcWriteOptions(compression="zstd")) as w:
        w.write_batch(batch)
    payloads = [CHUNK, AP, CHUNK[:-8], CHUNK + b"\0" * 8, CHUNK[:-8] + CHUNK[-16:], _write(cols, meta, batches=2),
                _write({k: pa.concat_arrays([v, v]) for k, v in cols.items()}, meta),
                sink.getvalue().to_pybytes(), _with_header(CHUNK, {"kind": "sensor_chunk", "version": 2})]
    rng = np.random.default_rng(3)
    for _ in range(150):  # single-byte damage anywhere
        p = bytearray(CHUNK)
        p[rng.integers(len(p))] ^= int(rng.integers(1, 256))
        payloads.append(bytes(p))
    fast = [_outcome(p) for p in payloads]
    monkeypatch.setattr(schema, "_read_our_batch", lambda payload: None)
    general = [_outcome(p) for p in payloads]
    assert fast == general
    assert sum(f[0] == "ok" for f in fast) >= 2 and sum(f[0] != "ok" for f in fast) >= 5
