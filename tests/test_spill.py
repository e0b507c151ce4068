"""The spill map (cloud.ingest.spill) behaves as a dict — order included — with a bounded number of values in
memory, and the segment store built on it reads spilled segments back exactly."""

from __future__ import annotations

import os
import pickle
import random

import numpy as np
import pytest

from cloud.ingest.segment_store import SegmentStore
from cloud.ingest.spill import SpillMap
from shared.schema import ApSegment


def _map(tmp_path, n, promote=False):
    return SpillMap(n, tmp_path, pickle.dumps, pickle.loads, tag=len, promote=promote)


@pytest.mark.parametrize("bound,promote", [(None, False), (1, False), (3, True), (7, False)])
def test_random_writes_reads_and_deletes_match_a_dict(tmp_path, bound, promote):
    rng = random.Random(bound or 0)
    m, ref = _map(tmp_path, bound, promote), {}
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
