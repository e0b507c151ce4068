"""Batched ingest equals segment-by-segment ingest, bit for bit; the template encoder equals Arrow's.

These tests feed the same segments as ``ap_batch`` payloads and as one ``ap_segment`` each, through
each layer (the decoder, the aggregator, the cloud's export), and compare what comes out exactly:
the posterior is a sum of each segment's information, taken in the same order either way, so
nothing may differ, not even in the last bit. Segments (spilled by the store) and acknowledgements
encode through templates of a message's layout (``shared.schema``): byte for byte Arrow's payload.
"""

from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from cloud.daemon import journal
from cloud.daemon.core import Cloud
from cloud.daemon.durable import GroupCommit
from cloud.daemon.journal import Journal
from cloud.daemon.settings import CloudSettings
from cloud.ingest.aggregator import Aggregator
from cloud.road.gmrf_profile import GmrfProfile
from cloud.road.mean_profile import MeanProfile
from shared import keys
from shared.registry import parse_site
from shared import schema
from shared.schema import Ack, ApBatch, ApSegment, DecodeError, PassDone, decode_ack, decode_ap, decode_pass_done

ROUTE_M = 200.0
SPACING = 0.05


def _segment(rng, *, vehicle="v1", pass_id="p1", tile=0, axle=1, start=0, n=200, calib_version=0, seq=0,
             n_in_pass=-1, error_model=None):
    return ApSegment.make(rng.normal(0.0, 2e-3, n), rng.uniform(1e-4, 4e-4, n), vehicle_id=vehicle, pass_id=pass_id,
                          route_id="R1", tile=tile, axle=axle, start_index=start, spacing_m=SPACING,
                          calib_version=calib_version, speed_mps=15.0, t_first=0.1 * tile, t_last=0.1 * tile + 1.0,
                          seq=seq, n_segments_in_pass=n_in_pass, error_model=error_model)


def _mixed_segments(seed: int) -> list[ApSegment]:
    """Overlapping segments of several passes and axles, some with the edge's error model, one
    reaching past the route's end, one starting before it, one the same identity as another."""
    rng = np.random.default_rng(seed)
    em = np.array([1.3, 2.2, -0.6, 0.15])
    segs = []
    for k in range(12):
        segs.append(_segment(rng, pass_id=f"p{k % 3}", tile=k, axle=1 + k % 2, start=int(rng.integers(0, 3800)),
                             n=int(rng.integers(50, 600)), error_model=em if k % 4 == 1 else None))
    segs.append(_segment(rng, pass_id="p9", tile=20, start=3950, n=200))  # past the end (4001 points)
    segs.append(_segment(rng, pass_id="p9", tile=21, start=-30, n=100))  # before the start
    segs.append(_segment(rng, pass_id="p0", tile=0, axle=1, start=10, n=80))  # p0's tile 0 again: replaces it
    return segs


def _state(est) -> list[np.ndarray]:
    r = est.routes["R1"]
    return [r.q, r.b, r.cover, r.passes] if isinstance(est, GmrfProfile) else [r.sw, r.swy, r.swyy, r.count]


def test_batch_decode_equals_the_constructors_segments():
    segs = _mixed_segments(3)[:8]  # built by the constructor (ApSegment.make)
    decoded = decode_ap(ApBatch(tuple(segs)).encode())
    assert decoded == segs
    for a, b in zip(decoded, segs):
        assert list(vars(a)) == list(vars(b))  # (the fields in the constructor's order)
        assert a.values_q.dtype == np.int16 and not a.values_q.flags.writeable and not a.sigma_q.flags.writeable
        assert type(a.tile) is int and type(a.scale_m) is float and np.array_equal(a.values, b.values)
        assert a.encode() == b.encode()


@pytest.mark.parametrize("field, value, reason", [("speed_mps", 151.0, "bad_value"), ("axle", 0, "bad_value"),
                                                  ("pass_id", "", "bad_value"), ("t_last", -1.0, "bad_value"),
                                                  ("vehicle_id", "no spaces", "bad_value")])
def test_a_bad_row_rejects_the_batch_with_the_constructors_reason(field, value, reason):
    rng = np.random.default_rng(4)
    good = [_segment(rng, tile=k, start=200 * k) for k in range(3)]
    bad = good[1]
    object.__setattr__(bad, field, value)  # (what another writer could put on the wire)
    with pytest.raises(DecodeError) as e:
        decode_ap(_unchecked_batch(good).encode())
    assert e.value.reason == reason


def _unchecked_batch(segs):
    b = ApBatch.__new__(ApBatch)
    object.__setattr__(b, "segments", tuple(segs))
    return b


SITE = parse_site({"route": [{"id": "R1", "length_m": ROUTE_M}]})


def _passes(seed: int, n_passes: int = 6, tiles: int = 4):
    """Per pass: its segments (two axles on every tile) and its pass-done."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n_passes):
        vehicle, pass_id = f"veh-{k % 3}", f"pass-{k}"
        segs = [_segment(rng, vehicle=vehicle, pass_id=pass_id, tile=t, axle=a, start=t * 1000 + a, n=1000,
                         seq=2 * t + a - 1, n_in_pass=2 * tiles) for t in range(tiles) for a in (1, 2)]
        done = PassDone(vehicle_id=vehicle, pass_id=pass_id, route_id="R1", calib_version=0, n_segments=2 * tiles)
        out.append((segs, done))
    return out


def test_aggregator_batches_equal_single_segments():
    one = Aggregator(SITE, [GmrfProfile({"R1": ROUTE_M}, SPACING, tau=1e6), MeanProfile({"R1": ROUTE_M}, SPACING)])
    many = Aggregator(SITE, [GmrfProfile({"R1": ROUTE_M}, SPACING, tau=1e6), MeanProfile({"R1": ROUTE_M}, SPACING)])
    acks_one, acks_many = [], []
    for segs, done in _passes(5):
        for s in segs:
            acks_one += one.on_segment(s.encode(), s.vehicle_id)
        acks_one += one.on_pass_done(done.encode())
        acks_many += many.on_segment(ApBatch(tuple(segs[:5])).encode(), segs[0].vehicle_id)
        acks_many += many.on_segment(ApBatch(tuple(segs[5:])).encode(), segs[0].vehicle_id)
        acks_many += many.on_pass_done(done.encode())
    # a pass recomputed under a newer calibration, batched: its old segments are retracted mid-batch
    segs, done = _passes(6, n_passes=1)[0]
    newer = [dataclasses.replace(s, calib_version=1, pass_id="pass-0", vehicle_id="veh-0") for s in segs]
    for s in newer:
        acks_one += one.on_segment(s.encode(), s.vehicle_id)
    acks_many += many.on_segment(ApBatch(tuple(newer)).encode(), "veh-0")
    assert acks_one == acks_many and len(acks_one) == 6
    assert one.stats() == many.stats()
    for e1, e2 in zip(one.estimators, many.estimators):
        assert all(np.array_equal(a, b) for a, b in zip(_state(e1), _state(e2)))


def test_cloud_exports_equal_bit_for_bit(tmp_path):
    """The whole cloud, its exports (profile with its band, roughness) as Parquet, read back."""
    exports = {}
    for mode in ("single", "batch"):
        cloud = Cloud("t", SITE, lambda k, p: None, CloudSettings(calibration="nominal", align=False))
        for segs, done in _passes(7):
            if mode == "single":
                for s in segs:
                    cloud.on_segment(keys.ap_key("t", "R1", s.tile, s.vehicle_id), s.encode())
            else:
                cloud.on_segment(keys.ap_key("t", "R1", 0, segs[0].vehicle_id), ApBatch(tuple(segs)).encode())
            cloud.on_done(keys.done_key("t", done.vehicle_id), done.encode())
        assert cloud.passes_complete == 6
        written = cloud.export(tmp_path / mode)
        exports[mode] = {p.name: pq.read_table(p) for p in written if p.suffix == ".parquet"}
    assert exports["single"].keys() == exports["batch"].keys() >= {"profile.parquet", "roughness.parquet"}
    for name, table in exports["single"].items():
        assert table.equals(exports["batch"][name]), name


def test_spill_encoding_is_the_encoders_byte_for_byte():
    """The template encoder (shared.schema) against Arrow's, over layouts: lengths, error models,
    multi-byte text, negative start, one-point segments; from a batch (no payload of its own)."""
    rng = np.random.default_rng(9)
    for k in range(120):
        m = 1 if k % 11 == 0 else int(rng.integers(2, 1200))
        em = None if k % 3 else np.array([1.1, 2.0, -0.5, 0.1, 0.02])[: 2 + k % 4]
        seg = ApSegment.make(rng.normal(0, 1e-3 * (1 + k % 5), m), rng.uniform(1e-4, 1e-3, m), vehicle_id=f"v-{k % 4}",
                             pass_id=["p", "pässe", "pass 2"][k % 3] + str(k % 7), route_id="R1",
                             tile=int(rng.integers(0, 1 << 20)), axle=1 + k % 3, start_index=int(rng.integers(-99, 1 << 30)),
                             spacing_m=0.05, calib_version=k % 9, speed_mps=float(rng.uniform(1, 40)), t_first=float(k),
                             t_last=float(k) + 2.0, seq=k % 4, n_segments_in_pass=[-1, 4][k % 2], flags=k % 2,
                             error_model=em)
        for s in (seg, decode_ap(ApBatch((seg, seg)).encode())[1]):
            arrow = schema._encode(ApSegment.KIND, schema._ap_columns((s,)))
            assert s.encode() == arrow and s.encode() == arrow  # (the first of a layout, then its template)
            assert decode_ap(s.encode()) == [seg]
        pair = (seg, decode_ap(ApBatch((seg, seg)).encode())[1])
        assert ApBatch(pair).encode() == schema._encode(ApBatch.KIND, schema._ap_columns(pair))


def test_ack_encoding_is_the_encoders_byte_for_byte():
    for k in range(40):
        ack = Ack(pass_id=["p", "pässe", "a pass"][k % 3] + "x" * (k % 9), vehicle_id=f"veh-{k}",
                  n_segments_accepted=k * 7919 % 1000, calib_version=k % 5)
        arrow = schema._encode(Ack.KIND, schema._ack_columns((ack,)))
        assert ack.encode() == arrow and ack.encode() == arrow and decode_ack(ack.encode()) == ack


def _general(payload):
    """decode_ap by the general path alone (pyarrow arrays, each segment's constructor)."""
    kind, version, batch = schema._read_batch(payload)
    if kind == ApSegment.KIND:
        return [schema._build(kind, version, batch, schema._build_ap_segment)]
    if kind == ApBatch.KIND:
        return list(schema._build(kind, version, batch, schema._build_ap_batch).segments)
    raise DecodeError("wrong_kind", f"expected {ApSegment.KIND} or {ApBatch.KIND}, got {kind}")


def _outcome(decode, payload):
    try:
        return decode(payload)
    except DecodeError as e:
        return (e.reason, e.detail)


def test_the_column_reader_equals_the_general_path():
    """decode_ap reads payloads laid out as ours from their buffers (schema._columns_of); every
    payload gives what the general path gives: the same segments, or the same reason and detail."""
    segs = _mixed_segments(11)
    payloads = [ApBatch(tuple(segs[:6])).encode(), ApBatch(tuple(segs[6:9])).encode(), segs[12].encode(),
                segs[13].encode(), ApBatch((segs[1],)).encode()]
    for p in payloads:  # our encoder's payloads take the fast path
        assert schema._columns_of(p) is not None and schema._ap_segments_of(*schema._columns_of(p)[1:]) is not None
        assert decode_ap(p) == _general(p)
    rng = np.random.default_rng(12)
    bad = [("speed_mps", 151.0), ("speed_mps", float("nan")), ("t_first", float("inf")), ("axle", 17),
           ("tile", -1), ("pass_id", "a\x01b"), ("pass_id", ""), ("vehicle_id", "no spaces"), ("spacing_m", 0.0),
           ("seq", 5), ("sigma_q", np.array([0, 1, -2], np.int16)), ("values_q", np.zeros(0, np.int16)),
           ("error_model", np.array([1.0, -2.0, 0.1]))]
    for field, value in bad:
        seg = dataclasses.replace(segs[0], n_segments_in_pass=5)
        if field.endswith("_q"):
            seg = dataclasses.replace(seg, values_q=seg.values_q[:3], sigma_q=seg.sigma_q[:3])
        object.__setattr__(seg, field, value)  # (what another writer could put on the wire)
        payloads.append(_unchecked_batch([segs[1], seg]).encode())
    for p in list(payloads):  # and damaged bytes: a flipped byte anywhere, a cut
        for _ in range(60):
            b = bytearray(p)
            b[int(rng.integers(len(b)))] ^= 1 << int(rng.integers(8))
            payloads.append(bytes(b))
        payloads.append(p[: int(rng.integers(len(p)))])
    fast = 0
    for p in payloads:
        assert _outcome(decode_ap, p) == _outcome(_general, p)
        fast += schema._columns_of(p) is not None
    assert fast > len(payloads) // 4  # (most damage lands in the values: read by the fast path)


def test_pass_done_column_reader_equals_the_general_path():
    """decode_pass_done reads one laid out as ours (no parameters: a null map) from its buffers; every
    payload, damaged or not, gives what the general path gives."""
    dones = [PassDone(vehicle_id="veh-1", pass_id=f"pass {k}", route_id="R1", calib_version=k, n_segments=4 * k,
                      vehicle_model=["", "quarter_car", "half_car"][k % 3], sample_interval_s=0.002 * (1 + k % 2))
             for k in range(6)]
    with_params = PassDone(vehicle_id="v", pass_id="p", route_id="R1", calib_version=1, n_segments=2,
                           vehicle_model="quarter_car", params={"K": 1.0})
    payloads = [d.encode() for d in dones]
    for p in payloads:
        assert schema._columns_of(p) is not None
    assert schema._columns_of(with_params.encode()) is None  # (parameters: the general path)
    payloads.append(with_params.encode())
    general = lambda p: schema._decoding(PassDone.KIND, p, schema._build_pass_done)  # noqa: E731
    rng = np.random.default_rng(13)
    for p in list(payloads):
        for _ in range(150):
            b = bytearray(p)
            b[int(rng.integers(len(b)))] ^= 1 << int(rng.integers(8))
            payloads.append(bytes(b))
    for p in payloads:
        assert _outcome(decode_pass_done, p) == _outcome(general, p)
    assert [decode_pass_done(d.encode()) for d in dones] == dones


def test_journal_writes_what_the_stream_writer_writes(tmp_path):
    """The journal writes each record itself, whole, in one system call: byte for byte what Arrow's
    stream writer writes for the same records, and read back the same."""
    records = [("ap", keys.ap_key("t", "R1", k, "v-1"), bytes(range(k % 7)) * (k * 37 % 500)) for k in range(40)]
    records += [("done", "driveby/t/done/v-é", b"x"), ("calib", "", b"")]
    j = Journal(tmp_path / "j")
    for r in records:
        j.append(*r)
    j.close()
    (path,) = (tmp_path / "j").glob("journal-*.arrows")
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, journal.SCHEMA) as w:
        for seq, (kind, key, payload) in enumerate(records):
            w.write_batch(pa.record_batch([pa.array([seq], pa.uint64()), pa.array([kind]), pa.array([key]),
                                           pa.array([payload], pa.binary())], schema=journal.SCHEMA))
    assert path.read_bytes() == sink.getvalue().to_pybytes()
    _, back = Journal(tmp_path / "j").recover()
    assert [(r.kind, r.key, r.payload) for r in back] == records


def test_group_commit_publishes_only_what_is_on_disk_in_order(tmp_path):
    """Acknowledgements held by the group commit leave in order, each only once the journal records
    written before it was published are fsync'd, and many share one fsync."""
    j = Journal(tmp_path / "j", fsync_interval_s=1e9)  # (no periodic sync: only the group's)
    fsyncs = []
    sync = j.sync

    def counted(upto=None):
        before = j.synced
        sync(upto)
        fsyncs.extend([1] * (j.synced > before))

    j.sync = counted
    out = []
    group = GroupCommit(j, lambda key, payload: out.append((key, payload, j.synced)), window_s=0.002)
    group.grouping = True
    stop = threading.Event()

    def flusher():
        while not stop.is_set():
            group.wait(stop)
            group.flush()

    thread = threading.Thread(target=flusher)
    thread.start()
    sent = []
    for k in range(300):
        j.append("ap", f"k{k}", b"x" * 100)  # the input, journalled before it is applied…
        written = j.written
        group.publish(f"ack{k}", str(written).encode())  # …and what it causes, published after
        sent.append(f"ack{k}")
        if k % 50 == 0:
            time.sleep(0.01)  # (a quiet moment: the held group leaves)
    time.sleep(0.05)
    stop.set()
    thread.join()
    group.flush()
    j.close()
    assert [key for key, _, _ in out] == sent
    assert all(synced >= int(payload) for _, payload, synced in out)  # on disk before it left
    # Grouped: one fsync per acknowledgement would be 300; the six quiet moments each let a group leave,
    # so more than one; fewer than half the messages is what grouping must give at the least.
    assert 1 < len(fsyncs) < 150 and group.published == 300
