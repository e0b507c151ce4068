"""ApSegment.make validates once: it checks the float values and sigmas, quantises them, and
validates every other field as the constructor does, without checking the codes it has just made a
second time. Its segments must be the constructor's (the public quantisers' codes validated in
``__post_init__``), refuse what the constructor refuses, and decode on the cloud's side."""

from __future__ import annotations

import math

import dataclasses

import numpy as np
import pyarrow as pa
import pytest

from shared.schema import (
    ApBatch,
    ApSegment,
    InvalidMessage,
    decode_ap,
    quantize_sigma,
    quantize_values,
)

FIELDS = dict(vehicle_id="veh-1", pass_id="p-7", route_id="R1", tile=3, axle=2, start_index=-4,
              spacing_m=0.05, calib_version=1, speed_mps=12.5, t_first=10.0, t_last=12.0, seq=5, flags=1)
ERROR_MODEL = np.array([1.3, 2.0, -0.6, 0.1])


def _inputs(rng: np.random.Generator, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Values and sigmas of the shapes the edge makes, and the corners of the codes."""
    n = int(rng.integers(1, 300))
    values = rng.normal(0.0, 10.0 ** rng.uniform(-6, 1), n)
    sigma = 10.0 ** rng.uniform(-9, 0, n)  # ratios below 2⁻¹⁶ take the clipped code
    match i % 5:
        case 1:
            values[:] = values[0]  # constant: scale 1
        case 2:
            values *= 1e-300  # a half-range below the smallest normal float
        case 3:
            sigma[:] = 1e-3  # every code 0
        case 4:
            values[0], values[-1] = -1e3, 1e3  # the extremes allowed
    return values, sigma


def _by_constructor(values, sigma, **fields) -> ApSegment:
    q, scale, offset = quantize_values(values)
    sq, ref = quantize_sigma(sigma)
    return ApSegment(values_q=q, scale_m=scale, offset_m=offset, sigma_q=sq, sigma_ref_m=ref, **fields)


def test_make_equals_the_validating_constructor():
    rng = np.random.default_rng(22)
    for i in range(400):
        values, sigma = _inputs(rng, i)
        error_model = ERROR_MODEL if i % 2 else None
        fields = {**FIELDS, "seq": i % 7, "error_model": error_model}
        made = ApSegment.make(values, sigma, **fields)
        built = _by_constructor(values, sigma, **{**fields, "error_model": made.error_model})
        assert made == built, i
        assert made.encode() == built.encode(), i
        assert not made.values_q.flags.writeable and not made.sigma_q.flags.writeable


def test_make_keeps_no_reference_to_its_inputs():
    values, sigma = np.linspace(-1e-3, 1e-3, 50), np.full(50, 2e-4)
    seg = ApSegment.make(values, sigma, **FIELDS)
    before = seg.encode()
    values[:] = 0.5
    sigma[:] = 1.0
    assert seg.encode() == before


def test_made_segments_decode_on_the_clouds_side():
    rng = np.random.default_rng(5)
    segments = []
    for axle in (1, 2):
        values, sigma = _inputs(rng, axle)
        seg = ApSegment.make(values, sigma, **{**FIELDS, "axle": axle, "seq": axle, "error_model": ERROR_MODEL})
        assert decode_ap(seg.encode()) == [seg]
        segments.append(seg)
    assert decode_ap(ApBatch(tuple(segments)).encode()) == segments


def test_other_input_types_take_the_general_path():
    values = [0.0, 1e-3, -2e-3]
    sigma = np.full(3, 1e-4, dtype=np.float32)
    made = ApSegment.make(values, sigma, **FIELDS)
    assert made == _by_constructor(np.array(values), sigma.astype(np.float64), **FIELDS)


@pytest.mark.parametrize(("values", "sigma", "over", "reason"), [
    (np.array([0.0, math.nan]), np.ones(2), {}, "non_finite"),
    (np.array([0.0, math.inf]), np.ones(2), {}, "non_finite"),
    (np.zeros(2), np.array([1e-3, math.nan]), {}, "non_finite"),
    (np.zeros(2), np.array([-math.inf, 1e-3]), {}, "non_finite"),
    (np.zeros(0), np.zeros(0), {}, "bad_shape"),
    (np.zeros(2), np.ones(3), {}, "bad_shape"),
    (np.zeros((2, 2)), np.ones(2), {}, "bad_shape"),
    (np.array([0.0, -1000.5]), np.ones(2), {}, "bad_value"),
    (np.zeros(2), np.array([1e-3, 0.0]), {}, "bad_value"),
    (np.zeros(2), np.array([1e-3, 1001.0]), {}, "bad_value"),
    (np.zeros(2), np.ones(2), {"vehicle_id": "a b"}, "bad_value"),
    (np.zeros(2), np.ones(2), {"pass_id": ""}, "bad_value"),
    (np.zeros(2), np.ones(2), {"tile": -1}, "bad_value"),
    (np.zeros(2), np.ones(2), {"axle": 0}, "bad_value"),
    (np.zeros(2), np.ones(2), {"axle": 1.0}, "bad_type"),
    (np.zeros(2), np.ones(2), {"spacing_m": 0.0}, "bad_value"),
    (np.zeros(2), np.ones(2), {"speed_mps": math.nan}, "non_finite"),
    (np.zeros(2), np.ones(2), {"t_last": 9.0}, "bad_value"),
    (np.zeros(2), np.ones(2), {"seq": 3, "n_segments_in_pass": 3}, "bad_value"),
    (np.zeros(2), np.ones(2), {"flags": -1}, "bad_value"),
    (np.zeros(2), np.ones(2), {"error_model": np.array([1.0, 1.0, 0.6])}, "bad_value"),
    (np.zeros(2), np.ones(2), {"error_model": np.array([1.0])}, "bad_shape"),
])
def test_make_refuses_what_the_constructor_refuses(values, sigma, over, reason):
    with pytest.raises(InvalidMessage) as made:
        ApSegment.make(values, sigma, **{**FIELDS, **over})
    assert made.value.reason == reason
    if values.ndim == 1 and values.size == sigma.size > 0 and np.isfinite(values).all() \
            and np.isfinite(sigma).all() and np.abs(values).max() <= 1e3 and sigma.min() > 0 and sigma.max() <= 1e3:
        with pytest.raises(InvalidMessage) as built:  # the same fields by the constructor: the same reason
            _by_constructor(values, sigma, **{**FIELDS, **over})
        assert built.value.reason == reason


def _arrow_writes(segments: list[ApSegment], payload: bytes) -> bytes:
    """What Arrow's stream writer writes for the segments' fields as columns (one row per segment),
    under ``payload``'s schema (names, types and header)."""
    schema = pa.ipc.open_stream(payload).schema
    columns = [pa.array([getattr(s, f.name) for s in segments], type=schema.field(f.name).type)
               for f in dataclasses.fields(ApSegment)]
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, schema) as w:
        w.write_batch(pa.RecordBatch.from_arrays(columns, schema=schema))
    return sink.getvalue().to_pybytes()


def test_payloads_are_arrows_byte_for_byte_when_layouts_repeat():
    """Payloads of one layout (row count, text lengths, array sizes) reuse the first one's
    placement of buffers: every one must still be what Arrow writes, and decode to its segments."""
    rng = np.random.default_rng(9)
    layouts = [(1, 200, 0), (2, 200, 4), (2, 37, 0), (3, 1, 3), (1, 5, 10)]
    for i in range(60):
        rows, n, em = layouts[i % len(layouts)]
        segments = []
        for r in range(rows):
            values, sigma = rng.normal(0, 1e-3, n), 10.0 ** rng.uniform(-5, -3, n)
            error_model = np.r_[rng.uniform(0.5, 2), 3.0, rng.uniform(-0.3, 0.3, em - 2)] if em else None
            segments.append(ApSegment.make(
                values, sigma, **{**FIELDS, "vehicle_id": f"veh-{i % 3}", "pass_id": f"p-{rng.integers(10, 99)}",
                                  "tile": int(rng.integers(0, 1 << 20)), "axle": r + 1, "seq": r,
                                  "start_index": int(rng.integers(-50, 1 << 20)), "speed_mps": rng.uniform(0, 40),
                                  "t_first": rng.uniform(0, 1e4), "t_last": 1e4 + rng.uniform(0, 10),
                                  "flags": int(rng.integers(0, 4)), "error_model": error_model}))
        payload = segments[0].encode() if rows == 1 else ApBatch(tuple(segments)).encode()
        assert payload == _arrow_writes(segments, payload), i
        assert decode_ap(payload) == segments, i
