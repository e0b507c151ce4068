"""The cloud's write-ahead journal: records survive a killed process, torn tails and compaction."""

import subprocess
import sys
import textwrap

import pytest

from cloud.daemon.journal import Journal, JournalError


def _payloads(n, tag=b"p"):
    return [("ap", f"driveby/t/ap/R1/{i}/veh-{i % 3}", tag + bytes([i % 256]) * (i % 17)) for i in range(n)]


def test_records_come_back_in_order_across_lifetimes(tmp_path):
    first, second = _payloads(5, b"a"), _payloads(4, b"b")
    with Journal(tmp_path) as j:
        assert j.recover() == ({}, [])
        for r in first:
            j.append(*r)
    with Journal(tmp_path) as j:
        meta, recs = j.recover()
        assert [(r.kind, r.key, r.payload) for r in recs] == first
        for r in second:
            j.append(*r)
    meta, recs = Journal(tmp_path).recover()
    assert [(r.kind, r.key, r.payload) for r in recs] == first + second
    assert [r.seq for r in recs] == list(range(9))


def test_a_killed_writer_loses_nothing_it_wrote(tmp_path):
    # A separate process appends and then dies by SIGKILL without closing: unbuffered writes
    # mean every record it returned from append() is readable.
    code = textwrap.dedent(f"""
        import os, signal, sys
        from cloud.daemon.journal import Journal
        j = Journal({str(tmp_path)!r}, fsync_interval_s=1e9)
        j.recover()
        for i in range(200):
            j.append("ap", "k%d" % i, b"x" * i)
        sys.stdout.write("written\\n"); sys.stdout.flush()
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.stdout == "written\n" and proc.returncode == -9
    _, recs = Journal(tmp_path).recover()
    assert [r.key for r in recs] == [f"k{i}" for i in range(200)]
    assert recs[-1].payload == b"x" * 199


@pytest.mark.parametrize("cut", [1, 7, 64, 300])
def test_a_torn_tail_is_ignored(tmp_path, cut):
    with Journal(tmp_path) as j:
        j.recover()
        for r in _payloads(20):
            j.append(*r)
    (path,) = tmp_path.glob("journal-*.arrows")
    size = path.stat().st_size
    with open(path, "r+b") as f:
        f.truncate(size - cut)
    _, recs = Journal(tmp_path).recover()
    assert 0 < len(recs) < 20 or cut <= 8  # the end-of-stream marker is 8 bytes: cutting it loses no record
    assert [(r.kind, r.key, r.payload) for r in recs] == _payloads(20)[: len(recs)]
    # and the next lifetime appends after what survived
    with Journal(tmp_path) as j:
        _, again = j.recover()
        seq = j.append("done", "k", b"z")
    assert seq == len(recs)
    assert [r.seq for r in Journal(tmp_path).recover()[1]] == list(range(len(recs) + 1))


def test_snapshot_compacts_and_recovery_resumes_after_it(tmp_path):
    with Journal(tmp_path) as j:
        j.recover()
        for r in _payloads(10):
            j.append(*r)
        j.write_snapshot([("ap", "kept", b"1"), ("calib", "c", b"2")], {"calibrator": {"veh-1": 3}})
        j.append("ap", "after", b"3")
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["journal-000002.arrows", "snapshot-000002.arrow"]
    meta, recs = Journal(tmp_path).recover()
    assert meta["calibrator"] == {"veh-1": 3}
    assert [(r.kind, r.key) for r in recs] == [("ap", "kept"), ("calib", "c"), ("ap", "after")]
    assert [r.seq for r in recs] == [10, 11, 12]
    # a snapshot with no journal after it: the next lifetime still writes a journal recovery reads
    with Journal(tmp_path) as j:
        j.recover()
        j.write_snapshot([("ap", "only", b"")], {})
    with Journal(tmp_path) as j:
        assert [r.key for r in j.recover()[1]] == ["only"]
        j.append("ap", "later", b"")
    assert [r.key for r in Journal(tmp_path).recover()[1]] == ["only", "later"]


def test_a_state_path_that_is_a_file_is_a_clear_error(tmp_path):
    f = tmp_path / "state"
    f.write_text("")
    with pytest.raises(JournalError, match="not a directory"):
        Journal(f)


def test_an_unreadable_snapshot_is_a_clear_error(tmp_path):
    (tmp_path / "snapshot-000003.arrow").write_bytes(b"garbage")
    with pytest.raises(JournalError, match="snapshot-000003.arrow: unreadable snapshot"):
        Journal(tmp_path).recover()
