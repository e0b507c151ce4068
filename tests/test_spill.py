"""The spill map (cloud.ingest.spill) behaves as a dict — order included — with a bounded number of values in
memory, the segment store built on it reads spilled segments back exactly, and an estimator's held
segments (:class:`HeldSegments`) spill the store's own segments as references, not a second copy."""

from __future__ import annotations

import os
import pickle
import random

import numpy as np
import pytest

from cloud.ingest.segment_store import HeldSegments, SegmentStore
from cloud.ingest.spill import SpillMap
from shared.schema import ApSegment


def _map(tmp_path, n, promote=False, group=None):
    return SpillMap(n, tmp_path, pickle.dumps, pickle.loads, tag=len, promote=promote, spill_group=group)


@pytest.mark.parametrize("bound,promote,group", [(None, False, None), (1, False, None), (3, True, None),
                                                 (7, False, None), (7, False, 4), (6, True, 3), (5, False, 5)])
def test_random_writes_reads_and_deletes_match_a_dict(tmp_path, bound, promote, group):
    """(``group``: values spilled at once, in one transaction.)"""
    rng = random.Random(bound or 0)
    m, ref = _map(tmp_path, bound, promote, group), {}
    keys = [("v", f"p{i}", i % 3) for i in range(25)]
    for step in range(1500):
        k = rng.choice(keys)
        op = rng.random()
        if op < 0.5:
            v = [step] * rng.randint(0, 4)
            m[k] = v
            ref[k] = v
        elif op < 0.7:
            assert m.get(k) == ref.get(k)
        elif op < 0.85:
            if k in ref:
                del m[k], ref[k]
            else:
                with pytest.raises(KeyError):
                    del m[k]
        else:
            assert (k in m) == (k in ref)
            if k in ref:
                assert m.tag_of(k) == len(ref[k])
        if bound is not None:
            assert m.resident <= bound
        if step % 100 == 0:  # order too: first insertion; a deleted key written again goes last
            assert list(m) == list(ref) and list(m.items()) == list(ref.items()) and len(m) == len(ref)
    assert [(k, pickle.loads(v)) for k, v in m.encoded()] == list(ref.items())
    if bound is not None:
        assert m.spilled_total > 0 and m.spilled == len(ref) - m.resident


def test_a_promoted_value_is_the_one_kept(tmp_path):
    """With ``promote`` a read brings the value back into memory: mutating what was read sticks, as
    with a dict (the aggregator updates the pass states it reads)."""
    m = _map(tmp_path, 2, promote=True)
    for i in range(5):
        m[i] = [i]
    assert m.peek(0) is None  # spilled
    m[0].append("x")
    for i in range(1, 5):
        m[i]  # the others back in memory: 0 spilled again, with its change
    assert m.peek(0) is None and m[0] == [0, "x"]


def test_the_index_leaves_no_file_behind(tmp_path):
    m = _map(tmp_path, 1)
    for i in range(10):
        m[i] = [i]
    assert m.disk_bytes() > 0 and os.listdir(tmp_path) == []  # unlinked at once: gone with the process
    m.close()


def test_spilled_segments_come_back_exactly(tmp_path):
    rng = np.random.default_rng(0)
    segs = {}
    for tile in range(6):
        segs[("v1", "p1", "R1", tile, 1)] = ApSegment.make(
            rng.normal(0, 1e-3, 1000), np.full(1000, 2e-4), vehicle_id="v1", pass_id="p1", route_id="R1",
            tile=tile, axle=1, start_index=tile * 1000, spacing_m=0.05, calib_version=tile % 3, speed_mps=10.0,
            t_first=0.0, t_last=5.0, seq=tile)
    store = SegmentStore(2, tmp_path)
    for slot, seg in segs.items():
        store[slot] = seg
    assert store.resident == 2 and store.spilled == 4
    for slot, seg in segs.items():
        back = store[slot]
        assert store.calib_version(slot) == seg.calib_version
        assert np.array_equal(back.values_q, seg.values_q) and np.array_equal(back.sigma_q, seg.sigma_q)
        assert back.encode() == seg.encode()
    assert store.reads == 4 and store.stats()["spill_bytes"] > 0


def test_flushed_values_spill_and_snapshot_without_encoding_again(tmp_path):
    """Idle-time flush writes resident values ahead of time; a later write makes one dirty again."""
    calls = []

    def encode(v):
        calls.append(v)
        return pickle.dumps(v)

    m = SpillMap(3, tmp_path, encode, pickle.loads, tag=len)
    for i in range(3):
        m[i] = [i]
    assert m.flush(1.0) == 3 and len(calls) == 3
    m[1] = [1, 1]  # dirty again
    assert [v for _, v in m.encoded()] == [pickle.dumps([0]), pickle.dumps([1, 1]), pickle.dumps([2])]
    assert len(calls) == 4  # only the dirty one encoded for the snapshot
    m[3] = [3]  # spills 0, which is clean: no encoding
    assert len(calls) == 4 and m.peek(0) is None and m[0] == [0] and m.tag_of(0) == 1
    assert m.flush(1.0) == 2  # 1 and 3


def test_no_disk_until_a_value_spills(tmp_path):
    """Keys get their rows when their values first leave memory: under the bound the map is a dict
    (the cloud's ingest writes three maps per segment), and order still spans both sides after."""
    m, ref = _map(tmp_path, 4), {}
    for i in range(4):
        m[("k", i)] = ref[("k", i)] = [i]
    del m[("k", 1)], ref[("k", 1)]
    m[("k", 1)] = ref[("k", 1)] = [1, 1]  # written again: goes last
    assert m.disk_bytes() == 0 and m.spilled == 0 and ("k", 9) not in m
    for i in range(4, 9):
        m[("k", i)] = ref[("k", i)] = [i]
    m[("k", 0)] = ref[("k", 0)] = [0, 0]  # a spilled key written again keeps its place
    assert m.disk_bytes() > 0 and m.spilled == len(ref) - 4
    assert list(m.items()) == list(ref.items()) and list(m) == list(ref)


def test_reading_while_iterating_sees_every_key_once_in_order(tmp_path):
    """A promoting read during iteration moves values between memory and disk under the walk."""
    m, ref = _map(tmp_path, 3, promote=True), {}
    for i in range(12):
        m[i] = ref[i] = [i]
    seen = []
    for k, v in m.items():
        seen.append((k, v))
        m[(k * 5) % 12]  # promote another key, spilling the oldest resident one
    assert seen == list(ref.items())


def _seg(rng, tile, calib_version=0, n=300):
    return ApSegment.make(rng.normal(0, 1e-3, n), np.full(n, 2e-4), vehicle_id="v1", pass_id=f"p{tile % 4}",
                          route_id="R1", tile=tile, axle=1, start_index=tile * n, spacing_m=0.05,
                          calib_version=calib_version, speed_mps=10.0, t_first=0.0, t_last=5.0, seq=tile)


@pytest.mark.parametrize("bound", [1, 3, 6])
def test_held_segments_spill_the_stores_segments_as_references(tmp_path, bound):
    """As the aggregator drives them: a segment stored, then held (the same object); some replaced
    by another object (an aligned or fused form), some superseded (released, then stored and held
    anew). The held map reads and iterates as a dict with the same writes, and of what it spilled
    only the replacements carry a payload."""
    rng = random.Random(bound)
    nprng = np.random.default_rng(bound)
    store, held, ref = SegmentStore(bound, tmp_path), HeldSegments(None, bound, tmp_path), {}
    held.store = store
    replaced = set()
    for step in range(200):
        tile = rng.randrange(30)
        slot = ("v1", f"p{tile % 4}", "R1", tile, 1)
        op = rng.random()
        if slot in store and op < 0.3:  # another object in its place (same identity)
            seg = store[slot]
            other = ApSegment.make(seg.values + 1e-4, seg.sigma, **{k: getattr(seg, k) for k in (
                "vehicle_id", "pass_id", "route_id", "tile", "axle", "start_index", "spacing_m", "calib_version",
                "speed_mps", "t_first", "t_last", "seq")})
            held[seg.identity] = ref[seg.identity] = other
            replaced.add(seg.identity)
            continue
        version = 0
        if slot in store:  # superseded: released from the estimator first, as the aggregator does
            old = store.calib_version(slot)
            identity = (*slot, old)
            del held[identity], ref[identity]
            replaced.discard(identity)
            version = old + 1
        seg = _seg(nprng, tile, version)
        store[slot] = seg
        held[seg.identity] = ref[seg.identity] = seg
    assert list(held) == list(ref) and held.spilled > 0
    for (key, value), (rkey, rvalue) in zip(held.items(), ref.items()):
        assert key == rkey and value.identity == key and value.encode() == rvalue.encode()
    for key, row in held.encoded():
        if held.peek(key) is None:  # spilled: its row is what was written when it left memory
            assert (row == b"\0") == (key not in replaced), key
    assert all(held[k].encode() == v.encode() for k, v in ref.items())


def test_held_segments_without_payload_are_much_smaller_on_disk(tmp_path):
    rng = np.random.default_rng(1)
    store, held = SegmentStore(2, tmp_path), None
    held = HeldSegments(store, 2, tmp_path)
    for tile in range(150):
        seg = _seg(rng, tile, n=1000)
        store[seg.identity[:5]] = seg
        held[seg.identity] = seg
    assert held.spilled == store.spilled == 148
    assert all(row == b"\0" for key, row in held.encoded() if held.peek(key) is None)
    assert held.disk_bytes() < store.disk_bytes() / 10  # (a row of ~50 bytes against ~4.6 kB)
