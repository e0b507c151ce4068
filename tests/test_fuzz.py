"""Bad input: mutated and random payloads on every key the cloud and the edge subscribe to.

A seeded mutator works on valid encoded messages of every kind (byte flips, cuts, splices,
repeats, random bytes; and Arrow-level damage: nulls, NaN/inf, wrong types, out-of-range
values, extra rows, dropped or duplicated columns, wrong kind/version headers), plus oversize
and wrong-version payloads.  Every decoder must return a valid message or raise
``DecodeError`` with a known reason; nothing else.  Then the rejected ones go through a real
router into a real cloud process and a real edge process (their stats queryables count):
nothing crashes, every one is rejected and counted under the reason the
decoder gives, and the estimates do not move.

Size: ``DRIVEBY_FUZZ_PAYLOADS`` through the decoders (default 3000) and ``DRIVEBY_FUZZ_BUS`` per
daemon through Zenoh (default a tenth of that, at least 300).  The long run::

    DRIVEBY_FUZZ_PAYLOADS=100000 DRIVEBY_FUZZ_BUS=50000 python -m pytest tests/test_fuzz.py
"""

from __future__ import annotations

import collections
import itertools
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterable, Iterator

import numpy as np
import pyarrow as pa
import zenoh

from shared import keys, schema
from shared.schema import (
    REASONS,
    Ack,
    Alarm,
    ApBatch,
    ApSegment,
    Calibration,
    DecodeError,
    PassDone,
    SensorChunk,
)
from shared.transport import run_router, zenoh_config
from tests.cloud_status import fused_event

N_PAYLOADS = int(os.environ.get("DRIVEBY_FUZZ_PAYLOADS", "3000"))
N_BUS = int(os.environ.get("DRIVEBY_FUZZ_BUS", max(300, N_PAYLOADS // 10)))  # per daemon, through Zenoh
SEED = int(os.environ.get("DRIVEBY_FUZZ_SEED", "20261122"))
NET = "fz"
TIMEOUT_S = 60.0  # a delivery or a query answered by a busy daemon on a loaded 2-core machine
DAEMON_TIMEOUT_S = 120.0  # the first daemon start may compile numba kernels into the cache
SITE = """
[[route]]
id = "R1"
length_m = 240.0

[[vehicle_class]]
model = "quarter_car"
mean = {M = 4450, m = 420, K = 5.0e5, k = 1.95e6, c = 2.0e4}
std  = {M = 445,  m = 42,  K = 5.0e4, k = 1.95e5, c = 2.0e3}
"""

DECODERS = {
    "any": schema.decode,
    "ap": schema.decode_ap,
    "sensor_chunk": schema.decode_sensor_chunk,
    "ap_segment": schema.decode_ap_segment,
    "ap_batch": schema.decode_ap_batch,
    "pass_done": schema.decode_pass_done,
    "calibration": schema.decode_calibration,
    "alarm": schema.decode_alarm,
    "ack": schema.decode_ack,
}


def _segment(vehicle: str = "V1", seq: int = 0, tile: int = 0, n: int = 40) -> ApSegment:
    x = np.arange(n) * 0.05
    return ApSegment.make(0.005 * np.sin(x), np.full(n, 2e-4), vehicle_id=vehicle, pass_id="p1", route_id="R1",
                          tile=tile, axle=1, start_index=tile * 1000 + 100, spacing_m=0.05, calib_version=0,
                          speed_mps=20.0, t_first=float(seq), t_last=float(seq) + 1.0, seq=seq)


def valid_messages() -> list:
    """One valid message of every kind (and a multi-row batch)."""
    n = 64
    chunk = SensorChunk("V1", "p1", "R1", "quarter_car", 0, 0.0, 500.0, np.linspace(0, 3, n), np.full(n, 20.0),
                        {"az_body": np.zeros(n, np.float32), "az_axle": np.ones(n, np.float32)},
                        nominal_params={"M": 4450.0, "K": 5e5}, lane_offset_m=0.1)
    return [
        chunk,
        _segment(),
        ApBatch((_segment(seq=0, tile=0), _segment(seq=1, tile=1), _segment(seq=2, tile=2))),
        PassDone("V1", "p1", "R1", 0, 3, "quarter_car"),
        Calibration("V1", 3, "quarter_car", {"K/M": 112.0, "k/M": 438.0}, "fleet"),
        Alarm("B1", "2026-11-22T00:00:00+00:00", "crack", 4, 12.5, 0.2, 0.9, "suspected"),
        Ack("p1", "V1", 3, 0),
    ]


# -- the mutator ----------------------------------------------------------------------------------

_DAMAGE = ("null", "nan", "inf", "type", "huge", "negative", "empty_list", "drop", "duplicate", "rows0",
           "rows2", "version", "kind", "header")


def _ipc(batch: pa.RecordBatch, compression: str | None = None) -> bytes:
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, batch.schema, options=pa.ipc.IpcWriteOptions(compression=compression)) as w:
        w.write_batch(batch)
    return sink.getvalue().to_pybytes()


def _damage(payload: bytes, rng: np.random.Generator) -> bytes:
    """Arrow-level damage to one column (or the header) of a valid payload."""
    batch = pa.ipc.open_stream(payload).read_next_batch()
    batch.validate(full=True)  # a compounded mutation may be corrupt already: touching it would abort
    how = _DAMAGE[rng.integers(len(_DAMAGE))]
    i = int(rng.integers(batch.num_columns))
    name, col = batch.schema.names[i], batch.column(i)
    meta = dict(batch.schema.metadata)
    header = json.loads(meta[b"driveby"])
    n = batch.num_rows
    if how in ("null", "nan", "inf", "type", "huge", "negative", "empty_list"):
        t = col.type
        if how == "null":
            new = pa.nulls(n, t)
        elif how == "type":
            new = pa.array([f"x{rng.integers(100)}"] * n) if not pa.types.is_string(t) else pa.array([1.5] * n)
        elif pa.types.is_list(t) or pa.types.is_large_list(t):
            v = {"nan": np.nan, "inf": np.inf, "huge": 1e30, "negative": -1e30}.get(how)
            vt = t.value_type
            if how == "empty_list" or v is None:
                new = pa.array([[]] * n, type=t)
            elif pa.types.is_integer(vt):
                new = pa.array([[32767, -32768, 0]] * n, type=t)
            else:
                new = pa.array([[v, 0.0]] * n, type=t)
        elif pa.types.is_floating(t):
            new = pa.array([{"nan": np.nan, "inf": np.inf, "huge": 1e300, "negative": -1e300,
                             "empty_list": 0.0}[how]] * n, type=t)
        elif pa.types.is_integer(t):
            new = pa.array([{"huge": 2**62, "negative": -(2**62)}.get(how, -1)] * n, type=t)
        elif pa.types.is_string(t):
            new = pa.array([{"huge": "x" * 5000, "negative": "a/b*"}.get(how, "\x00")] * n)
        else:
            new = pa.nulls(n, t)
        batch = batch.set_column(i, pa.field(name, new.type), new)
    elif how == "drop":
        batch = batch.remove_column(i)
    elif how == "duplicate":
        batch = pa.RecordBatch.from_arrays([*batch.columns, col], schema=pa.schema(
            [*batch.schema, batch.schema.field(i)], metadata=batch.schema.metadata))
    elif how == "rows0":
        batch = batch.slice(0, 0)
    elif how == "rows2":
        batch = pa.concat_batches([batch] * int(rng.integers(2, 300)))
    elif how == "version":
        header["version"] = int(rng.choice([0, 2, -1, 99, 2**40]))
    elif how == "kind":
        header["kind"] = str(rng.choice([*schema.KINDS, "nope", ""]))
    elif how == "header":
        meta[b"driveby"] = rng.choice([b"", b"{", b"[]", b'{"kind": 1, "version": "1"}', b"\xff\xfe"])
    if how in ("version", "kind"):
        meta[b"driveby"] = json.dumps(header).encode()
    batch = batch.replace_schema_metadata(meta)
    return _ipc(batch)


_WORDS = (0xFFFFFFFF, 0x7FFFFFFF, 2**63 - 1, 2**64 - 1, 0x80000000, 2**40)


def mutate(payload: bytes, rng: np.random.Generator, others: list[bytes]) -> bytes:
    """One random mutation of a valid payload (byte-level, Arrow-level or a replacement)."""
    b = bytearray(payload)
    op = int(rng.integers(12))  # 7..10: Arrow-level damage, so that most mutants get past the framing
    if op == 0:  # flip bits
        for _ in range(int(rng.integers(1, 9))):
            j = int(rng.integers(len(b)))
            b[j] ^= 1 << int(rng.integers(8))
    elif op == 1:  # overwrite a run with random bytes
        j = int(rng.integers(len(b)))
        k = int(rng.integers(1, 64))
        b[j:j + k] = rng.bytes(k)
    elif op == 2:  # cut short
        b = b[: int(rng.integers(len(b)))]
    elif op == 3:  # insert bytes
        j = int(rng.integers(len(b) + 1))
        b[j:j] = rng.bytes(int(rng.integers(1, 64)))
    elif op == 4:  # splice two messages
        other = others[int(rng.integers(len(others)))]
        b = b[: int(rng.integers(len(b)))] + other[int(rng.integers(len(other))):]
    elif op == 5:  # repeat a stretch (a second batch, a doubled buffer)
        j = int(rng.integers(len(b)))
        b = b[:j] + b[j // 2:]
    elif op == 6:  # extreme integers in the little-endian words (lengths, offsets, counts)
        for _ in range(int(rng.integers(1, 5))):
            j = int(rng.integers(0, max(1, len(b) - 8)))
            b[j:j + 8] = _WORDS[int(rng.integers(len(_WORDS)))].to_bytes(8, "little")
    elif op < 11:
        try:
            return _damage(payload, rng)
        except Exception:  # noqa: BLE001 - whatever a corrupt stream raises in the mutator itself
            return bytes(b[: len(b) // 2])  # not a valid Arrow stream already (a compounded mutation)
    else:  # random bytes, sometimes with the Arrow stream's continuation marker
        b = bytearray(rng.bytes(int(rng.integers(0, 2048))))
        if rng.random() < 0.5:
            b[:4] = b"\xff\xff\xff\xff"
    return bytes(b)


def payloads(n: int, seed: int) -> list[bytes]:
    """``n`` payloads: mutants of every kind's valid encoding, after the oversize and wrong-version ones."""
    return list(itertools.islice(iter_payloads(seed), n))


def iter_payloads(seed: int) -> Iterator[bytes]:
    """Endless :func:`payloads`."""
    rng = np.random.default_rng(seed)
    valid = [m.encode() for m in valid_messages()]
    special = [b"", b"\x00", b"x" * (schema.MAX_PAYLOAD_BYTES + 1), valid[1] + b"\x00" * schema.MAX_PAYLOAD_BYTES]
    for p in valid:
        batch = pa.ipc.open_stream(p).read_next_batch()
        meta = dict(batch.schema.metadata)
        for version in (0, schema.SCHEMA_VERSION + 1):
            header = {**json.loads(meta[b"driveby"]), "version": version}
            special.append(_ipc(batch.replace_schema_metadata({**meta, b"driveby": json.dumps(header).encode()})))
        for codec in ("zstd", "lz4"):  # compressed bodies: never ours, refused before inflating
            special.append(_ipc(batch, codec))
        i = [j for j, f in enumerate(batch.schema) if pa.types.is_string(f.type)][0]
        special.append(_ipc(batch.set_column(i, batch.schema.names[i], batch.column(i).dictionary_encode())))
    yield from special
    while True:
        base = valid[int(rng.integers(len(valid)))]
        p = mutate(base, rng, valid)
        if rng.random() < 0.2:  # mutations compound
            p = mutate(p, rng, valid) if len(p) > 8 else p
        yield p


def classify(decode, payload: bytes) -> str | None:
    """The reason ``decode`` rejects ``payload`` (None if it is a valid message); fails on anything
    but a DecodeError with a known reason."""
    try:
        msg = decode(payload)
    except DecodeError as e:
        assert e.reason in REASONS, f"unknown reason {e.reason!r}"
        return e.reason
    # A mutant may still be a valid message: then it survives a round trip unchanged.
    for m in (msg if isinstance(msg, list) else [msg]):
        assert schema.decode(m.encode()) == m
    return None


# -- decoders -------------------------------------------------------------------------------------


def test_every_decoder_rejects_bad_payloads_with_a_reason():
    outcomes: dict[str, collections.Counter] = {name: collections.Counter() for name in DECODERS}
    for p in payloads(N_PAYLOADS, SEED):
        for name, decode in DECODERS.items():
            outcomes[name][classify(decode, p) or "valid"] += 1
    total = {name: sum(c.values()) for name, c in outcomes.items()}
    assert all(t == N_PAYLOADS for t in total.values())
    for name, c in outcomes.items():
        # a mutant that is still a valid message is rare; every other one is rejected with a reason
        assert c["valid"] < 0.1 * N_PAYLOADS, (name, c)
        assert {"not_arrow", "oversize", "wrong_version"} <= set(c), (name, c)
    print({name: dict(c) for name, c in outcomes.items()})


_INFLATE = """
import re, sys
from shared import schema

def peak_mb():  # this process's peak resident memory (VmHWM: unlike ru_maxrss, not inherited at exec)
    with open("/proc/self/status") as f:
        return int(re.search(r"VmHWM:\\s*(\\d+)", f.read()).group(1)) // 1024

payload = open(sys.argv[1], "rb").read()
before = peak_mb()
try:
    schema.decode_ap(payload)
    reason = "accepted"
except schema.DecodeError as e:
    reason = e.reason
print(reason, peak_mb() - before)
"""


def test_a_compression_bomb_is_refused_before_it_inflates(tmp_path):
    """9 kB of zstd holding 200 MB of zeros: refused from the message header, in a fresh process whose
    peak memory shows that nothing was inflated (it would add 200 MB; Linux's /proc)."""
    seg = _segment()
    batch = pa.ipc.open_stream(seg.encode()).read_next_batch()
    n = 100_000_000  # int16 zeros: 200 MB decoded
    values = pa.ListArray.from_arrays(pa.array(np.array([0, n], np.int32)), pa.array(np.zeros(n, np.int16)))
    i = batch.schema.get_field_index("values_q")
    bomb = _ipc(batch.set_column(i, batch.schema.field(i), values), "zstd")
    del values
    assert len(bomb) < schema.MAX_PAYLOAD_BYTES // 100
    (tmp_path / "bomb").write_bytes(bomb)
    res = subprocess.run([sys.executable, "-c", _INFLATE, str(tmp_path / "bomb")], capture_output=True, text=True,
                         timeout=120, stdin=subprocess.DEVNULL)
    reason, grown_mb = res.stdout.split()
    assert reason == "oversize", res.stderr
    assert int(grown_mb) < 50, f"decoding grew the peak memory by {grown_mb} MB: the bomb was inflated"


# -- through Zenoh into the daemons ---------------------------------------------------------------


def _rejected_subset(decode, candidates: Iterable[bytes], n: int) -> tuple[list[bytes], collections.Counter]:
    chosen, reasons = [], collections.Counter()
    for p in candidates:
        reason = classify(decode, p)
        if reason is not None:
            chosen.append(p)
            reasons[reason] += 1
            if len(chosen) == n:
                break
    return chosen, reasons


def _get_json(session: zenoh.Session, key: str) -> dict:
    replies = list(session.get(key, timeout=TIMEOUT_S))
    assert replies and replies[0].ok is not None, f"no answer on {key}"
    return json.loads(replies[0].ok.payload.to_bytes())


def _tile(session: zenoh.Session, tile: int) -> bytes:
    replies = list(session.get(keys.state_profile_key(NET, "R1", tile), timeout=TIMEOUT_S))
    assert replies and replies[0].ok is not None
    return replies[0].ok.payload.to_bytes()


def test_bad_payloads_through_zenoh_are_counted_and_change_nothing(tmp_path):
    # Per key, the rejected ones among fresh mutants (each list opens with the oversize and wrong-version ones).
    ap_bad, ap_reasons = _rejected_subset(schema.decode_ap, iter_payloads(SEED + 1), N_BUS // 2)
    done_bad, done_reasons = _rejected_subset(schema.decode_pass_done, iter_payloads(SEED + 2),
                                              N_BUS - len(ap_bad))
    imu_bad, imu_reasons = _rejected_subset(schema.decode_sensor_chunk, iter_payloads(SEED + 3), N_BUS // 3)
    calib_bad, calib_reasons = _rejected_subset(schema.decode_calibration, iter_payloads(SEED + 4),
                                                N_BUS // 3)
    ack_bad, ack_reasons = _rejected_subset(schema.decode_ack, iter_payloads(SEED + 5),
                                            N_BUS - len(imu_bad) - len(calib_bad))
    assert len(ap_bad) + len(done_bad) == N_BUS and len(imu_bad) + len(calib_bad) + len(ack_bad) == N_BUS
    for reasons in (ap_reasons, done_reasons, imu_reasons, calib_reasons, ack_reasons):
        assert {"oversize", "wrong_version", "not_arrow"} <= set(reasons), reasons

    site = tmp_path / "site.toml"
    site.write_text(SITE)
    with run_router(timeout_s=TIMEOUT_S) as endpoint:
        log = open(tmp_path / "cloud.log", "wb")
        cloud = subprocess.Popen([sys.executable, "-m", "cloud", "--connect", endpoint, "--net", NET, "--id", "c1",
                                  "--site", str(site), "--calibration", "nominal"],
                                 env=dict(os.environ, PYTHONUNBUFFERED="1"), stdin=subprocess.DEVNULL, stdout=log,
                                 stderr=subprocess.STDOUT)
        edge_log = open(tmp_path / "edge.log", "wb")
        edge = subprocess.Popen([sys.executable, "-m", "edge", "--connect", endpoint, "--net", NET, "--id", "e1",
                                 "--calibration", "nominal"],
                                env=dict(os.environ, PYTHONUNBUFFERED="1"), stdin=subprocess.DEVNULL, stdout=edge_log,
                                stderr=subprocess.STDOUT)
        try:
            with zenoh.open(zenoh_config("client", connect=[endpoint])) as s:

                up, acked = threading.Event(), threading.Event()
                alive: set[str] = set()

                def on_alive(sample):
                    if sample.kind == zenoh.SampleKind.PUT:
                        alive.add(str(sample.key_expr))
                    if {keys.alive_key(NET, "cloud", "c1"), keys.alive_key(NET, "edge", "e1")} <= alive:
                        up.set()

                s.liveliness().declare_subscriber(keys.alive_keyexpr(NET), on_alive, history=True)
                s.declare_subscriber(keys.ack_keyexpr(NET), lambda sample: acked.set())
                settled = fused_event(s, NET, "c1", 1)  # the estimate is final once the pass is fused
                assert up.wait(DAEMON_TIMEOUT_S), f"daemons did not come up: {(tmp_path / 'cloud.log').read_text()}"

                # Some state first: a complete pass of three segments.
                put = lambda k, p: s.put(k, p, congestion_control=zenoh.CongestionControl.BLOCK)  # noqa: E731
                for seq in range(3):
                    put(keys.ap_key(NET, "R1", seq, "V1"), _segment(seq=seq, tile=seq).encode())
                put(keys.done_key(NET, "V1"), PassDone("V1", "p1", "R1", 0, 3, "quarter_car").encode())
                assert acked.wait(TIMEOUT_S), "the seeding pass was not acknowledged"
                assert settled.wait(TIMEOUT_S), "the cloud did not settle after the seeding pass"
                before = _get_json(s, keys.control_key(NET, "c1", "stats"))["stats"]
                tiles = [_tile(s, t) for t in range(3)]

                for p in ap_bad:
                    put(keys.ap_key(NET, "R1", 0, "V1"), p)
                for p in done_bad:
                    put(keys.done_key(NET, "V1"), p)
                for p in imu_bad:
                    put(keys.imu_key(NET, "V1"), p)
                for p in calib_bad:
                    put(keys.calib_key(NET, "V1"), p)
                for p in ack_bad:
                    put(keys.ack_key(NET, "V1"), p)

                expected = collections.Counter(before["rejected"]) + ap_reasons + done_reasons
                deadline = time.monotonic() + TIMEOUT_S
                while True:  # each answer is an event; bounded in time
                    after = _get_json(s, keys.control_key(NET, "c1", "stats"))["stats"]
                    if sum(after["rejected"].values()) >= expected.total():
                        break
                    assert time.monotonic() < deadline, f"cloud counted {after['rejected']}, expected {expected}"
                assert collections.Counter(after["rejected"]) == expected
                assert after["accepted"] == before["accepted"] and after["passes_complete"] == before["passes_complete"]
                assert [_tile(s, t) for t in range(3)] == tiles  # estimates unchanged
                assert cloud.poll() is None, "the cloud died"

                # the edge counts a bad acknowledgement as ack_<reason> (apart from its own inputs)
                ack_counted = collections.Counter({f"ack_{r}": n for r, n in ack_reasons.items()})
                edge_expected = imu_reasons + calib_reasons + ack_counted
                deadline = time.monotonic() + TIMEOUT_S
                while True:  # each answer is an event; bounded in time
                    edge_stats = _get_json(s, keys.control_key(NET, "e1", "stats"))
                    if sum(edge_stats["rejected"].values()) >= edge_expected.total():
                        break
                    assert time.monotonic() < deadline, f"edge counted {edge_stats['rejected']}"
                assert collections.Counter(edge_stats["rejected"]) == edge_expected
                assert edge_stats["segments_published"] == 0 and edge_stats["vehicles"] == 0
                assert edge.poll() is None, "the edge died"
                print({"cloud": dict(collections.Counter(after["rejected"]) - collections.Counter(before["rejected"])),
                       "edge": edge_stats["rejected"]})
        finally:
            for proc in (cloud, edge):
                proc.terminate()
                try:
                    proc.wait(15)
                except subprocess.TimeoutExpired:
                    proc.kill()
            log.close()
            edge_log.close()
