"""The streaming spine's fast paths against their references: batched AP messages, the estimators'
compiled updates, the aggregator's incremental counts, the edge's growable grid, batching and shards."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import numpy as np
import pyarrow as pa
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cloud.ingest.aggregator import Aggregator
from cloud.road.gmrf_profile import GmrfProfile, segment_information
from cloud.road.mean_profile import MeanProfile
from cloud.daemon.core import Cloud
from cloud.daemon.settings import CloudSettings
from edge.node import Edge, in_shard, parse_shard
from edge.pipeline import EdgeConfig, PassProcessor, AxleGrid
from shared import keys, schema
from shared.drivelog import list_drive_logs, read_drive_log
from shared.dynamics.inverse import build_inverse, edge_gamma
from shared.registry import load_site
from shared.schema import (
    MAX_BATCH_SEGMENTS,
    SIGMA_SCALE,
    ApBatch,
    ApSegment,
    DecodeError,
    InvalidMessage,
    PassDone,
    decode,
    decode_ap,
    decode_ap_batch,
    decode_ap_segment,
)
from shared.vehicles import vehicle_from_params
from simfleet.replay import chunks_of
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

from tests.support import drive, drive_logs

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
NET = "t"


def _segment(tile: int = 0, n: int = 50, *, seed: int = 0, **over) -> ApSegment:
    rng = np.random.default_rng(seed + 1000 * tile)
    fields = dict(vehicle_id="veh-1", pass_id="p1", route_id="R1", tile=tile, axle=1, start_index=tile * 1000 + 3,
                  spacing_m=0.05, calib_version=0, speed_mps=15.0, t_first=float(tile), t_last=tile + 1.0, seq=tile,
                  n_segments_in_pass=-1, flags=0)
    fields.update(over)
    sigma = rng.uniform(1e-5, 1e-3, n) * np.exp(rng.normal(0.0, 2.0, n))
    return ApSegment.make(rng.normal(0.0, 2e-3, n), sigma, **fields)


# -- the ap_batch message ---------------------------------------------------------------------


@SETTINGS
@given(sizes=st.lists(st.integers(1, 120), min_size=1, max_size=12), axle=st.integers(1, 4))
def test_batch_round_trip(sizes, axle):
    segments = tuple(_segment(i, n, axle=axle, seq=i) for i, n in enumerate(sizes))
    batch = ApBatch(segments)
    payload = batch.encode()
    back = decode_ap_batch(payload)
    assert back == batch and decode(payload) == batch
    assert back.encode() == payload  # deterministic
    assert decode_ap(payload) == list(segments)
    assert (back.vehicle_id, back.route_id, back.tile) == ("veh-1", "R1", 0)


def test_decode_ap_takes_both_kinds_and_nothing_else():
    seg = _segment()
    assert decode_ap(seg.encode()) == [seg]
    assert decode_ap(ApBatch((seg,)).encode()) == [seg]
    with pytest.raises(DecodeError) as info:
        decode_ap(PassDone("veh-1", "p1", "R1", 0, 1).encode())
    assert info.value.reason == "wrong_kind"
    with pytest.raises(DecodeError) as info:  # a single-segment decoder names what it got
        decode_ap_segment(ApBatch((seg, _segment(1))).encode())
    assert info.value.reason == "wrong_kind"


def test_single_segments_keep_their_one_row_form():
    payload = _segment(n=7).encode()
    batch = pa.ipc.open_stream(payload).read_next_batch()
    assert batch.num_rows == 1 and batch.schema.metadata[b"driveby"] == b'{"kind": "ap_segment", "version": 1}'
    assert batch.schema.names == [name for name, _ in schema._AP_COLUMNS]


@pytest.mark.parametrize(
    "make, reason",
    [
        (lambda: ApBatch(()), "bad_shape"),
        (lambda: ApBatch(tuple(_segment(i, 2) for i in range(MAX_BATCH_SEGMENTS + 1))), "bad_shape"),
        (lambda: ApBatch((_segment(0), _segment(1, vehicle_id="veh-2"))), "bad_value"),
        (lambda: ApBatch((_segment(0), _segment(1, route_id="R2"))), "bad_value"),
        (lambda: ApBatch((_segment(0), "not a segment")), "bad_type"),
        (lambda: ApBatch(_segment(0)), "bad_type"),
    ],
)
def test_batch_constructor_rejects(make, reason):
    with pytest.raises(InvalidMessage) as info:
        make()
    assert info.value.reason == reason


def _rewrite(payload: bytes, **columns) -> bytes:
    batch = pa.ipc.open_stream(payload).read_next_batch()
    for name, col in columns.items():
        batch = batch.set_column(batch.schema.get_field_index(name), name, col)
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, batch.schema) as w:
        w.write_batch(batch)
    return sink.getvalue().to_pybytes()


def test_malformed_batches_are_rejected_whole_with_a_reason():
    payload = ApBatch(tuple(_segment(i, 5) for i in range(3))).encode()
    bad_axle = _rewrite(payload, axle=pa.array([1, 0, 1]))
    assert _reason(bad_axle) == "bad_value"
    nan = _rewrite(payload, offset_m=pa.array([0.0, math.nan, 0.0]))
    assert _reason(nan) == "non_finite"
    other_vehicle = _rewrite(payload, vehicle_id=pa.array(["veh-1", "veh-2", "veh-1"]))
    assert _reason(other_vehicle) == "bad_value"
    nulls = _rewrite(payload, values_q=pa.array([[1, 2, 3, 4, 5], None, [1, 2, 3, 4, 5]], pa.list_(pa.int16())))
    assert _reason(nulls) == "missing_field"
    short = _rewrite(payload, sigma_q=pa.array([[0] * 5, [0] * 4, [0] * 5], pa.list_(pa.int16())))
    assert _reason(short) == "bad_shape"


def test_a_batch_over_the_row_cap_is_rejected_before_building():
    seg = _segment(0, 2)
    table = pa.Table.from_batches([pa.ipc.open_stream(ApBatch((seg,)).encode()).read_next_batch()] *
                                  (MAX_BATCH_SEGMENTS + 1)).combine_chunks()
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as w:
        w.write_table(table)
    assert _reason(sink.getvalue().to_pybytes()) == "bad_shape"


def _reason(payload: bytes) -> str:
    with pytest.raises(DecodeError) as info:
        decode_ap(payload)
    assert info.value.reason in schema.REASONS
    return info.value.reason


@settings(SETTINGS, max_examples=200)
@given(st.data())
def test_batch_bit_flips_never_escape(data):
    payload = bytearray(ApBatch(tuple(_segment(i, 20) for i in range(3))).encode())
    i = data.draw(st.integers(0, len(payload) - 1))
    payload[i] ^= data.draw(st.integers(1, 255))
    try:
        segments = decode_ap(bytes(payload))
    except DecodeError as e:
        assert e.reason in schema.REASONS
    else:
        assert all(isinstance(s, ApSegment) for s in segments)


# -- decoding the wire codes --------------------------------------------------------------------


def test_sigma_table_is_the_exp2_of_every_code():
    codes = -np.arange(SIGMA_SCALE.size)
    assert np.array_equal(SIGMA_SCALE, np.exp2(codes.astype(np.float64) / schema.SIGMA_CODES_PER_OCTAVE))
    assert not SIGMA_SCALE.flags.writeable


def test_decoded_arrays_are_cached_and_read_only():
    seg = decode_ap_segment(_segment(n=30).encode())
    assert seg.values is seg.values and seg.sigma is seg.sigma
    for a in (seg.values, seg.sigma):
        with pytest.raises(ValueError):
            a[0] = 1.0
    assert seg.value_range == (seg.values.min(), seg.values.max())


@pytest.mark.parametrize("rho", [0.0, 0.35, -0.6])
@pytest.mark.parametrize("n", [1, 2, 3, 257])
def test_gmrf_update_is_bit_identical_to_segment_information(rho, n):
    seg = _segment(n=n, seed=n)
    g = GmrfProfile({"R1": 100.0}, rho=rho)
    g.update(seg)
    diag, off, rhs = segment_information(seg.values, seg.sigma, rho)
    r, lo = g.routes["R1"], seg.start_index
    assert np.array_equal(r.q[0, lo : lo + n], diag)
    assert np.array_equal(r.q[1, lo : lo + n - 1], off)
    assert np.array_equal(r.b[lo : lo + n], rhs)
    assert r.cover[lo : lo + n].tolist() == [1] * n and r.passes.sum() == n
    g.retract(seg)
    assert not r.cover.any() and not r.passes.any()
    assert np.allclose(r.q, 0.0, atol=1e-9 * diag.max()) and np.allclose(r.b, 0.0, atol=1e-9 * np.abs(rhs).max())


def test_mean_profile_update_is_bit_identical_to_its_formulas():
    seg = _segment(n=400, axle=2)
    m = MeanProfile({"R1": 100.0})
    m.update(seg)
    y, w = seg.values, 1.0 / seg.sigma**2
    s, lo = m.routes["R1"], seg.start_index
    assert np.array_equal(s.sw[lo : lo + 400], w)
    assert np.array_equal(s.swy[lo : lo + 400], w * y)
    assert np.array_equal(s.swyy[lo : lo + 400], w * y * y)
    assert not s.count.any()  # axle 2 is not a pass of its own


# -- the aggregator and the cloud's status ----------------------------------------------------------


@pytest.fixture(scope="module")
def road(tmp_path_factory):
    out = tmp_path_factory.mktemp("road")
    generate(SCENARIOS["road-qc"], out, seed=5, passes=2, workers=1, progress=False)
    return out


def test_a_batch_is_fused_like_its_segments_one_by_one(road):
    site = load_site(road / "site.toml")
    segments = [_segment(i, 200, n_segments_in_pass=4) for i in range(4)]
    a = Aggregator(site, [GmrfProfile({"R1": 200.0}, tau=1e6)])
    b = Aggregator(site, [GmrfProfile({"R1": 200.0}, tau=1e6)])
    done = PassDone("veh-1", "p1", "R1", 0, 4).encode()
    assert a.on_segment(ApBatch(tuple(segments)).encode(), "veh-1") == [] and a.accepted == 4
    for seg in segments:
        b.on_segment(seg.encode(), "veh-1")
    (ack_a,), (ack_b,) = a.on_pass_done(done), b.on_pass_done(done)
    assert ack_a == ack_b and ack_a.n_segments_accepted == 4
    assert np.array_equal(a.estimators[0].routes["R1"].q, b.estimators[0].routes["R1"].q)
    # Redelivery changes nothing; a batch under another vehicle's key is rejected segment by segment.
    a.on_segment(ApBatch(tuple(segments)).encode(), "veh-1")
    a.on_segment(ApBatch(tuple(segments)).encode(), "veh-9")
    assert a.accepted == 4 and a.rejected["duplicate"] == 4 and a.rejected["key_mismatch"] == 4


def test_status_counts_current_passes_incrementally(road):
    site = load_site(road / "site.toml")
    published = []
    # A clock that stands still: every ack after the first falls within status_interval_s of it.
    cloud = Cloud(NET, site, lambda k, p: published.append(k), CloudSettings(calibration="nominal"),
                  clock=lambda: 0.0)
    key = keys.ap_key(NET, "R1", 0, "veh-1")
    for k, pass_id in enumerate(["p1", "p2", "p3"]):
        cloud.on_segment(key, _segment(0, 20, pass_id=pass_id, n_segments_in_pass=1).encode())
        cloud.on_done(keys.done_key(NET, "veh-1"), PassDone("veh-1", pass_id, "R1", 0, 1).encode())
    # A recomputed pass (new calibration version) is no longer complete until its marker arrives.
    cloud.on_segment(key, _segment(0, 20, pass_id="p2", calib_version=1, n_segments_in_pass=1).encode())
    agg = cloud.aggregator
    brute = sum(1 for ps in agg.passes.values() if ps.acked and ps.calib_version == 0)
    assert cloud.status()["passes_current"] == brute == 2 and agg.stats()["passes_complete"] == 2
    cloud.on_done(keys.done_key(NET, "veh-1"), PassDone("veh-1", "p2", "R1", 1, 1).encode())
    assert agg.stats()["passes_complete"] == 3 and cloud.status()["passes_current"] == 2  # p2 is at v1
    # Status follows acks at most every status_interval_s; a forced flush publishes what is held back.
    status_key = keys.status_key(NET, cloud.node_id)
    assert published.count(status_key) == 1 and cloud.status_due  # the first ack's; the rest held back
    cloud.flush_status(force=True)
    assert published.count(status_key) == 2 and not cloud.status_due


# -- the edge ----------------------------------------------------------------------------------


def _grid_by_concatenation(chunks, spacing):
    """Reference: the grid grown by concatenation, as the edge did before it preallocated."""
    base, values, valid, times, last = None, np.zeros(0), np.zeros(0, bool), np.zeros(0), None
    for x, ap, t, rel in chunks:
        if last is not None:
            x, ap, t, rel = (np.concatenate([[v], a]) for v, a in zip(last, (x, ap, t, rel)))
        if x.size == 0:
            continue
        last = (x[-1], ap[-1], t[-1], rel[-1])
        if x.size < 2:
            continue
        end = (base or 0) + values.size
        first = max(int(math.floor(x[0] / spacing)) + 1, end, 0) if base is not None else max(
            int(math.ceil(x[0] / spacing)), 0)
        hi = int(math.floor(x[-1] / spacing))
        if hi < first:
            continue
        xg = np.arange(first, hi + 1) * spacing
        pos = np.clip(np.searchsorted(x, xg, side="left"), 1, x.size - 1)
        base = first if base is None else base
        gap = first - (base + values.size)
        values = np.concatenate([values, np.zeros(gap), np.interp(xg, x, ap)])
        times = np.concatenate([times, np.zeros(gap), np.interp(xg, x, t)])
        valid = np.concatenate([valid, np.zeros(gap, bool), rel[pos] & rel[pos - 1]])
    return base, values, valid, times


@SETTINGS
@given(st.data())
def test_growable_grid_equals_concatenation(data):
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    n = data.draw(st.integers(2, 3000))
    steps = rng.uniform(0.0, 0.2, n)
    steps[rng.random(n) < 0.02] = 3.0  # jumps leave gaps of invalid points
    steps[rng.random(n) < 0.05] = 0.0  # a stop: repeated chainage
    steps[rng.random(n) < 0.02] = 0.05  # samples exactly on grid points, now and then
    x = data.draw(st.sampled_from([7.3, 0.0, 0.05])) + np.cumsum(steps)
    ap, t, rel = rng.normal(size=n), np.arange(n) * 0.002, rng.random(n) > 0.05
    cuts = np.sort(rng.choice(np.arange(1, n), size=min(n - 1, data.draw(st.integers(0, 40))), replace=False))
    chunks = [tuple(a[i:j] for a in (x, ap, t, rel)) for i, j in zip([0, *cuts], [*cuts, n])]
    grid = AxleGrid()
    for chunk in chunks:
        grid.add(*chunk, 0.05)
    base, values, valid, times = _grid_by_concatenation(chunks, 0.05)
    assert grid.base == base and grid.size == values.size
    assert np.array_equal(grid.values, values) and np.array_equal(grid.valid, valid)
    assert np.array_equal(grid.t, times)


def _pass_segments(log, chunk_s: float) -> list[ApSegment]:
    m = log.meta
    model = build_inverse(vehicle_from_params(m.vehicle_model, m.nominal_params).system(), 1.0 / m.sample_rate_hz,
                          gamma=edge_gamma(m.vehicle_model))
    proc = PassProcessor(model, m.vehicle_id, m.pass_id, m.route_id, 0, EdgeConfig(), m.vehicle_model)
    out = []
    for chunk in chunks_of(log, chunk_s):
        out.extend(proc.feed(chunk))
    out.extend(proc.finish()[0])
    return out


def test_pass_segments_do_not_depend_on_chunking(road):
    log = read_drive_log(list_drive_logs(road / "logs")[0])
    a, b = _pass_segments(log, 0.1), _pass_segments(log, 0.0314)
    assert len(a) == len(b) >= 4
    # speed_mps is the mean of the chunks' mean speeds so far, and sample times are t0 + i / rate per
    # chunk: the AP itself is the same to the bit.
    free = dict(speed_mps=0.0, t_first=0.0, t_last=0.0)
    assert all(dataclasses.replace(x, **free) == dataclasses.replace(y, **free) for x, y in zip(a, b))
    assert all(abs(x.t_first - y.t_first) < 1e-9 and abs(x.t_last - y.t_last) < 1e-9 for x, y in zip(a, b))


def _run_edge(road, **kw) -> tuple[list[tuple[str, bytes]], Edge]:
    site = load_site(road / "site.toml")
    published: list[tuple[str, bytes]] = []
    edge = drive(Edge(NET, lambda k, p: published.append((k, p)), site, "nominal", **kw), drive_logs(road))
    return published, edge


def test_edge_batches_what_a_chunk_releases(road):
    batched, edge = _run_edge(road)
    single, _ = _run_edge(road, ap_batch=1)
    segs_b = [s for k, p in batched if "/ap/" in k for s in decode_ap(p)]
    segs_s = [s for k, p in single if "/ap/" in k for s in decode_ap(p)]
    assert segs_b == segs_s and edge.segments_published == len(segs_b)
    n_b, n_s = (sum("/ap/" in k for k, _ in msgs) for msgs in (batched, single))
    assert n_s == len(segs_s) and n_b < n_s  # the road's last chunk releases every tile at once
    for k, p in batched:  # a batch travels under its first segment's key
        if "/ap/" in k:
            first = decode_ap(p)[0]
            assert k == keys.ap_key(NET, first.route_id, first.tile, first.vehicle_id)


def test_shards_partition_the_fleet(road):
    vehicles = [f"veh-{i:04d}" for i in range(300)]
    for n in (1, 2, 3, 7):
        owners = [[i for i in range(n) if in_shard(v, (i, n))] for v in vehicles]
        assert all(len(o) == 1 for o in owners)
        if n > 1:
            assert len({o[0] for o in owners}) == n  # every shard gets some
    counts = [len(_run_edge(road, shard=(i, 2))[1].tasks) for i in range(2)]
    assert sum(counts) == len(list_drive_logs(road / "logs"))


@pytest.mark.parametrize("text", ["", "1", "2/2", "-1/2", "a/b", "1/0"])
def test_parse_shard_rejects(text):
    with pytest.raises(ValueError):
        parse_shard(text)


@pytest.mark.parametrize("args", [["--shard", "3/2"], ["--ap-batch", "0"], ["--ap-batch", str(MAX_BATCH_SEGMENTS + 1)]])
def test_edge_cli_rejects_bad_options_with_one_line(args):
    res = subprocess.run([sys.executable, "-m", "edge", "--connect", "tcp/127.0.0.1:1", *args], capture_output=True,
                         text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert res.returncode == 2 and res.stderr.strip().count("\n") == 0 and "driveby edge" in res.stderr
