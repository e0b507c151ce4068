"""A router restart mid-run is survived with nothing lost.

A real router process on a free loopback port carries a ``driveby run`` (edge and cloud daemons, the
run's own session). It is killed with SIGKILL mid-run and started again on the same endpoint after a
pause drawn from the test's fixed seed. Every Zenoh client reconnects by itself (zenoh's default
connect retry for clients: 1 s, doubling to 4 s), the edge sees the cloud's liveliness token go and
come back and sends its unacknowledged passes again, the cloud acknowledges them (again, if it had
them); the export must equal an uninterrupted run's.

A partitioned link: the router runs in its own network namespace behind a veth pair whose host end
is taken down for 1-3 s (shorter than zenoh's 10 s lease), as a cable pulled and put back; TCP holds
the sessions and delivers what waited, nothing is lost. Needs root (``ip netns``); skipped otherwise.

Raw sensor chunks published while the router is down are not lost either: the loggers publish
through Zenoh advanced publishers keeping each vehicle's last chunks (``simfleet.replay.ImuPublishers``),
the edge's advanced subscriber detects the gap (sequence numbers, heartbeats) and fetches them from
that cache, in order (``test_..._while_chunks_stream``). Chunks older than the cache are a real gap:
Zenoh reports the miss, the edge counts it and drops that pass, the vehicle's next pass goes through
(``test_chunks_beyond_the_vehicles_cache_are_a_counted_gap``).

Timing: every outage, pause and cut point is drawn from a fixed seed (printed with any failure); every
wait is for an event, bounded by a timeout that holds on a loaded 2-core machine. The run's own
limits are set so that its backstop (``RESEND_S``) fires well before it gives up (``IDLE_TIMEOUT_S``).
"""

from __future__ import annotations

import contextlib
import os
import random
import signal
import subprocess
import sys
import threading

import numpy as np
import pyarrow.parquet as pq
import pytest
import zenoh

import simfleet.run
from shared import keys
from shared.schema import decode_ack, decode_pass_done, decode_sensor_chunk
from shared.transport import free_port, start_router as _start_router, stop_router as _stop, zenoh_config
from simfleet.replay import chunks_of
from simfleet.run import run
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate
from shared.drivelog import list_drive_logs, read_drive_log

PASSES = 4
RATE = 20.0  # × real time: passes stream for ~2 s, so an outage can fall inside the stream
# No acknowledgement and no status for this long fails a run: a healthy run on a loaded 2-core machine
# never goes that long without either; a lost pass fails in a minute, not the default two.
IDLE_S = 60.0
# The run publishes a pass again from its log this long after its last chunk if still unacknowledged:
# well inside IDLE_S, so an acknowledgement missed while the run's own session reconnected is recovered.
RESEND_S = 5.0
EVENT_S = 60.0  # the longest one step of these scenarios (a router start, a recovery) may take under load


@pytest.fixture(scope="module")
def road(tmp_path_factory):
    out = tmp_path_factory.mktemp("road")
    generate(SCENARIOS["road-qc"], out, seed=11, passes=PASSES, workers=1, progress=False)
    return out


@pytest.fixture(scope="module")
def reference(road, tmp_path_factory):
    export = tmp_path_factory.mktemp("ref")
    return run(road / "logs", road / "site.toml", export, calibration="nominal", progress=False, rate=RATE), export


def _profile(export_dir):
    t = pq.read_table(export_dir / "profile.parquet").to_pydict()
    return {k: np.asarray(v) for k, v in t.items() if k != "route_id"}


def _assert_same_profile(ref_dir, cut_dir) -> None:
    """The same passes in every bin, the estimates equal but for the rounding of their fusion order."""
    a, b = _profile(ref_dir), _profile(cut_dir)
    assert np.array_equal(a["n_passes"], b["n_passes"])
    scale = np.std(a["elevation_m"])
    for f in ("elevation_m", "lo95_m", "hi95_m"):
        assert np.max(np.abs(a[f] - b[f])) <= 1e-9 * scale, f


def _router(endpoint: str):
    proc, error = _start_router(endpoint, None, EVENT_S)
    assert error is None, f"router on {endpoint} did not start: {error}"
    return proc


def total_chunks(road) -> int:
    return sum(len(list(chunks_of(read_drive_log(p)))) for p in list_drive_logs(road / "logs"))


def _run_with_outage(road, export, kill_on: str, seed: int):
    """``driveby run`` through a router of ours, SIGKILLed at ``kill_on`` and restarted on the same
    endpoint after a pause drawn from ``seed``. ``kill_on``: "last_done", once the edge has sent every
    pass's pass-done (i.e. had every raw chunk), with the cloud frozen (SIGSTOP) from half-way through
    the raw chunks until the router is dead, so the passes still streaming then cannot be acknowledged
    before it dies (half a stream is a wide margin for this process to stop the cloud in time);
    "last_ack", once every pass is acknowledged; "chunks", once 20-70 % of the raw chunks (drawn from
    ``seed``) have been published, i.e. while they stream. Returns the run's result (or its
    exception) and what the outage caught."""
    rng = random.Random(seed)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = [_router(endpoint)]
    killed = threading.Event()
    acked: set[str] = set()
    done_passes: set[str] = set()
    outage: dict = {}
    result: dict = {}

    def kill():
        if not killed.is_set():
            router[0].kill()
            outage["acked_before"] = len(acked)
            killed.set()

    def on_ack(sample):
        acked.add(decode_ack(sample.payload.to_bytes()).pass_id)
        if kill_on == "last_ack" and len(acked) == PASSES:
            kill()

    seen: set[tuple[str, int]] = set()
    total = total_chunks(road)
    kill_at = int(rng.uniform(0.2, 0.7) * total)
    frozen: list[int] = []

    def freeze_cloud():  # its pid file is the run's interface for a service manager (simfleet.run.Daemon)
        pid = int((export / ".run" / "cloud.pid").read_text())
        os.kill(pid, signal.SIGSTOP)
        frozen.append(pid)

    def thaw_cloud():
        while frozen:
            with contextlib.suppress(ProcessLookupError):
                os.kill(frozen.pop(), signal.SIGCONT)

    def on_imu(sample):  # a plain subscriber: what a subscriber without recovery gets
        chunk = decode_sensor_chunk(sample.payload.to_bytes())
        seen.add((chunk.vehicle_id, chunk.seq))
        if kill_on == "chunks" and len(seen) == kill_at:
            kill()
        if kill_on == "last_done" and len(seen) == total // 2 and not frozen:
            freeze_cloud()

    def on_done(sample):
        done_passes.add(decode_pass_done(sample.payload.to_bytes()).pass_id)
        if kill_on == "last_done" and len(done_passes) == PASSES:
            kill()  # at once, in the callback; the frozen cloud has acknowledged none of the passes since

    def drive():
        try:
            result["run"] = run(road / "logs", road / "site.toml", export, calibration="nominal", progress=False,
                                rate=RATE, connect=endpoint)
        except Exception as e:  # judged by the test
            result["error"] = e

    try:
        with zenoh.open(zenoh_config("client", connect=[endpoint])) as s:
            subs = [s.declare_subscriber(keys.ack_keyexpr("net"), on_ack),
                    s.declare_subscriber(keys.done_keyexpr("net"), on_done),
                    s.declare_subscriber(keys.imu_keyexpr("net"), on_imu)]
            runner = threading.Thread(target=drive, daemon=True)
            runner.start()
            # The daemons' first start loads the numba cache: allow for it on a loaded machine.
            assert killed.wait(simfleet.run.STARTUP_TIMEOUT_S + EVENT_S), \
                f"the router was never killed ({kill_on}, seed {seed}, chunks seen {len(seen)}/{total})"
            router[0].wait(EVENT_S)
            outage["acked_at_death"] = len(acked)  # what got out before the router died
            thaw_cloud()
            outage["run_alive"] = runner.is_alive()
            threading.Event().wait(rng.uniform(0.3, 1.5))  # the outage: a timed pause, not a wait for an event
            router[0] = _router(endpoint)
            runner.join(IDLE_S + 2 * EVENT_S)  # past the run's own limit: it fails by itself first
            assert not runner.is_alive(), f"run did not finish after the router restart (seed {seed}, {outage})"
            for sub in subs:
                sub.undeclare()
            outage["chunks_seen"] = len(seen)
    finally:
        thaw_cloud()
        _stop(router[0])
    return result, outage


def test_a_router_killed_mid_run_is_restarted_and_nothing_is_lost(road, reference, tmp_path, monkeypatch):
    monkeypatch.setattr(simfleet.run, "IDLE_TIMEOUT_S", IDLE_S)
    monkeypatch.setattr(simfleet.run, "RESEND_S", RESEND_S)
    ref, ref_dir = reference
    seed = 1
    result, outage = _run_with_outage(road, tmp_path / "cut", "last_done", seed)
    if "error" in result:
        raise AssertionError(f"run failed after the router restart (seed {seed}, {outage})") from result["error"]
    cut = result["run"]
    # The outage fell inside the run: passes were unacknowledged when the router died, and the run
    # (whose export query needs the router) finished only through the restarted one. Every pass
    # acknowledged at the end was therefore sent again through it (by the edge when the cloud's
    # liveliness came back, or by the run's backstop) and acknowledged by the cloud there.
    assert outage["run_alive"] and outage["acked_at_death"] < PASSES, (outage, seed)
    _assert_same_profile(ref_dir, tmp_path / "cut")
    assert cut.acked == ref.acked == PASSES, (cut, outage, seed)
    assert cut.stats["accepted"] == ref.stats["accepted"], (cut.stats, seed)  # nothing lost, nothing counted twice


def test_a_router_killed_after_the_last_acknowledgement_lets_the_run_finish(road, reference, tmp_path,
                                                                            monkeypatch):
    """The outage falls between the last acknowledgement and the cloud's settled status: nothing is
    left to send again, so the run finishes only because the quiet cloud repeats its status
    (``CloudSettings.status_heartbeat_s``) through the restarted router, well inside the run's idle limit."""
    monkeypatch.setattr(simfleet.run, "IDLE_TIMEOUT_S", 20.0)  # the failure this pins down is a 20 s wait
    monkeypatch.setattr(simfleet.run, "RESEND_S", RESEND_S)
    ref, ref_dir = reference
    seed = 4
    result, outage = _run_with_outage(road, tmp_path / "cut", "last_ack", seed)
    if "error" in result:
        raise AssertionError(f"run failed after the router restart (seed {seed}, {outage})") from result["error"]
    cut = result["run"]
    assert cut.acked == PASSES and cut.stats["accepted"] == ref.stats["accepted"], (cut, seed)
    _assert_same_profile(ref_dir, tmp_path / "cut")


def test_a_router_killed_while_chunks_stream_loses_nothing(road, reference, tmp_path, monkeypatch):
    monkeypatch.setattr(simfleet.run, "IDLE_TIMEOUT_S", IDLE_S)
    # The vehicles' caches recover the chunks (the deterministic proof is in test_security and the gap test
    # below); a resend backstops an acknowledgement lost while the run's session was reconnecting.
    monkeypatch.setattr(simfleet.run, "RESEND_S", RESEND_S)
    seed = 2
    result, outage = _run_with_outage(road, tmp_path / "cut", "chunks", seed)
    assert outage["run_alive"] and outage["acked_before"] < PASSES, (outage, seed)
    if "error" in result:
        raise AssertionError(f"run failed after the router restart (seed {seed})") from result["error"]
    ref, ref_dir = reference
    cut = result["run"]
    # The outage fell while raw chunks streamed: a plain subscriber missed some of them for good, unless
    # the run's backstop published their passes again ...
    assert cut.resent_passes > 0 or outage["chunks_seen"] < total_chunks(road), (outage, cut, seed)
    # ... the edge's advanced subscriber fetched them from the vehicles' caches: no gap, no pass lost.
    assert cut.acked == PASSES
    assert cut.stats["accepted"] == ref.stats["accepted"]
    _assert_same_profile(ref_dir, tmp_path / "cut")


@contextlib.contextmanager
def _router_behind_veth():
    """A router in its own network namespace, reached over a veth pair; yields its endpoint and a
    function taking the host end of the link down (False) or up (True)."""
    tag = f"drv{os.getpid() % 100000}"
    ns, host_if, ns_if = f"{tag}ns", f"{tag}a", f"{tag}b"
    net = f"10.{(os.getpid() >> 8) % 200 + 20}.{os.getpid() % 250}"
    try:
        subprocess.run(["ip", "netns", "add", ns], check=True, capture_output=True)
    except (OSError, subprocess.CalledProcessError) as e:
        pytest.skip(f"no network namespaces here (needs root and iproute2): {e}")

    def sh(*cmd):
        subprocess.run(cmd, check=True, capture_output=True)

    proc = None
    try:
        sh("ip", "link", "add", host_if, "type", "veth", "peer", "name", ns_if)
        sh("ip", "link", "set", ns_if, "netns", ns)
        sh("ip", "addr", "add", f"{net}.1/30", "dev", host_if)
        sh("ip", "link", "set", host_if, "up")
        sh("ip", "netns", "exec", ns, "ip", "addr", "add", f"{net}.2/30", "dev", ns_if)
        sh("ip", "netns", "exec", ns, "ip", "link", "set", ns_if, "up")
        endpoint = f"tcp/{net}.2:7447"
        proc = subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, "-m", "shared.transport", "router",
                                 "--listen", endpoint, "--exit-on-stdin-eof"],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        ready = threading.Event()
        threading.Thread(target=lambda: (proc.stdout.readline(), ready.set()), daemon=True).start()
        assert ready.wait(EVENT_S), "router in the namespace did not start"
        yield endpoint, lambda up: sh("ip", "link", "set", host_if, "up" if up else "down")
    finally:
        if proc is not None:
            _stop(proc)
        subprocess.run(["ip", "link", "del", host_if], capture_output=True)
        subprocess.run(["ip", "netns", "del", ns], capture_output=True)


LEASE_S = 10.0  # zenoh's default transport lease: a link silent this long is declared dead


def _run_with_partition(road, reference, tmp_path, during: str, seconds: tuple[float, float], seed: int):
    """``driveby run`` through a router behind a veth pair taken down for a stretch in ``seconds``,
    ``during`` "acks" (after the first acknowledgement) or "chunks" (once 20-70 % of the raw chunks
    have been published), both drawn from ``seed``; the export must equal the reference's."""
    ref, ref_dir = reference
    rng = random.Random(seed)
    cut_now, healed = threading.Event(), threading.Event()
    acked: set[str] = set()
    seen: set[tuple[str, int]] = set()
    cut_at = int(rng.uniform(0.2, 0.7) * total_chunks(road))
    result: dict = {}
    with _router_behind_veth() as (endpoint, link):
        def on_ack(sample):
            acked.add(decode_ack(sample.payload.to_bytes()).pass_id)
            if during == "acks":
                cut_now.set()

        def on_imu(sample):
            chunk = decode_sensor_chunk(sample.payload.to_bytes())
            seen.add((chunk.vehicle_id, chunk.seq))
            if during == "chunks" and len(seen) >= cut_at:
                cut_now.set()

        def drive():
            try:
                result["run"] = run(road / "logs", road / "site.toml", tmp_path / "cut", calibration="nominal",
                                    progress=False, rate=RATE, connect=endpoint)
            except Exception as e:  # judged below
                result["error"] = e

        with zenoh.open(zenoh_config("client", connect=[endpoint])) as s:
            subs = [s.declare_subscriber(keys.ack_keyexpr("net"), on_ack),
                    s.declare_subscriber(keys.imu_keyexpr("net"), on_imu)]
            runner = threading.Thread(target=drive, daemon=True)
            runner.start()
            assert cut_now.wait(simfleet.run.STARTUP_TIMEOUT_S + EVENT_S), \
                f"the partition never began ({during}, seed {seed})"
            link(False)
            try:
                before, alive = len(acked), runner.is_alive()
                healed.wait(rng.uniform(*seconds))  # the partition: a timed stretch, not a wait for an event
            finally:
                link(True)
            runner.join(seconds[1] + IDLE_S + 2 * EVENT_S)  # past the run's own limit: it fails by itself first
            assert not runner.is_alive(), f"run did not finish after the link came back (seed {seed})"
            for sub in subs:
                sub.undeclare()
    if "error" in result:
        raise AssertionError(f"run failed after the partition (seed {seed})") from result["error"]
    assert alive and before < PASSES, (before, seed)  # the partition cut the run in the middle
    cut = result["run"]
    _assert_same_profile(ref_dir, tmp_path / "cut")
    assert cut.acked == ref.acked == PASSES
    assert cut.stats["accepted"] == ref.stats["accepted"]
    return len(seen), cut


def test_a_partitioned_link_heals_and_nothing_is_lost(road, reference, tmp_path, monkeypatch):
    monkeypatch.setattr(simfleet.run, "IDLE_TIMEOUT_S", IDLE_S)
    monkeypatch.setattr(simfleet.run, "RESEND_S", RESEND_S)
    _run_with_partition(road, reference, tmp_path, "acks", (1.0, 3.0), seed=5)  # shorter than the lease: TCP holds


def test_a_partition_longer_than_the_lease_while_chunks_stream_loses_nothing(road, reference, tmp_path,
                                                                             monkeypatch):
    """Longer than the lease, every session through the link is closed and opened again when it heals:
    the raw chunks published meanwhile come back from the vehicles' caches."""
    monkeypatch.setattr(simfleet.run, "IDLE_TIMEOUT_S", IDLE_S)
    monkeypatch.setattr(simfleet.run, "RESEND_S", RESEND_S)  # the backstop, if a recovery query finds no cache
    seen, cut = _run_with_partition(road, reference, tmp_path, "chunks", (LEASE_S + 1.0, LEASE_S + 3.0), seed=6)
    # A plain subscriber lost chunks for good, unless the run's backstop published their passes again.
    assert cut.resent_passes > 0 or seen < total_chunks(road), (seen, cut)


def test_chunks_the_vehicles_caches_cannot_recover_are_sent_again(road, reference, tmp_path, monkeypatch):
    """The backstop: with caches of one chunk, a router outage while chunks stream loses chunks for good
    (Zenoh reports them missed, the edge drops the pass); the run publishes every unacknowledged pass
    again from its log, and the export still equals the uninterrupted run's."""
    import simfleet.replay

    monkeypatch.setattr(simfleet.run, "IDLE_TIMEOUT_S", IDLE_S)
    monkeypatch.setattr(simfleet.run, "RESEND_S", 3.0)
    monkeypatch.setattr(simfleet.replay, "CACHE_CHUNKS", 1)
    seed = 3
    result, outage = _run_with_outage(road, tmp_path / "cut", "chunks", seed)
    if "error" in result:
        raise AssertionError(f"run failed after the router restart (seed {seed})") from result["error"]
    ref, ref_dir = reference
    cut = result["run"]
    assert cut.resent_passes > 0, (outage, seed)
    assert cut.acked == PASSES and cut.stats["accepted"] == ref.stats["accepted"]
    _assert_same_profile(ref_dir, tmp_path / "cut")


def test_chunks_beyond_the_vehicles_cache_are_a_counted_gap(road):
    """Recovery is bounded by the vehicle's cache: chunks it no longer holds are a real gap, which
    the edge detects (Zenoh's miss detection and its own sequence check), counts, and survives."""
    import dataclasses

    from edge.node import Edge, serve
    from simfleet.replay import ImuPublishers

    cache, before, during = 5, 10, 20  # the outage swallows 20 chunks; the vehicle keeps only the last 5
    log = read_drive_log(list_drive_logs(road / "logs")[0])
    chunks = list(chunks_of(log))
    assert len(chunks) > before + during
    vehicle = log.meta.vehicle_id
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = _router(endpoint)
    got_before, recovered, second_done = threading.Event(), threading.Event(), threading.Event()
    second_handled, stop = threading.Event(), threading.Event()
    try:
        with zenoh.open(zenoh_config("client", connect=[endpoint])) as edge_s, \
                zenoh.open(zenoh_config("client", connect=[endpoint])) as veh_s:
            edge = Edge("net", lambda k, p: edge_s.put(k, p), calibration="nominal")
            feed = edge.on_chunk

            def on_chunk(payload, key_vehicle=None):  # the real handler, observed
                feed(payload, key_vehicle)
                chunk = decode_sensor_chunk(payload)
                if chunk.seq == before - 1:
                    got_before.set()
                if edge.rejected["sequence_gap"]:
                    recovered.set()
                if chunk.pass_id == "second" and chunk.final:
                    second_handled.set()  # the handler has returned: its last put on edge_s is over

            edge.on_chunk = on_chunk
            done_passes: list[str] = []

            def on_done(sample):
                done_passes.append(decode_pass_done(sample.payload.to_bytes()).pass_id)
                second_done.set()

            done_sub = edge_s.declare_subscriber(keys.done_keyexpr("net"), on_done)
            server = threading.Thread(target=serve, args=(edge_s, edge, "edge-gap", stop), daemon=True)
            server.start()
            edge_up = threading.Event()
            # The edge declares its liveliness token after its subscriptions, on the same link.
            watch = veh_s.liveliness().declare_subscriber(keys.alive_key("net", "edge", "edge-gap"),
                                                          lambda s: edge_up.set(), history=True)
            assert edge_up.wait(EVENT_S), "the edge never came up"
            watch.undeclare()
            with ImuPublishers(veh_s, cache_chunks=cache, heartbeat_s=0.2) as publish:
                key = keys.imu_key("net", vehicle)
                for c in chunks[:before]:
                    publish(key, c.encode())
                assert got_before.wait(EVENT_S), f"the edge did not get the first chunks: {edge.stats()}"
                router.kill()
                router.wait(EVENT_S)
                for c in chunks[before:before + during]:  # into the void: the vehicle's cache keeps the last 5
                    publish(key, c.encode())
                router = _router(endpoint)
                assert recovered.wait(EVENT_S), f"the edge never saw the gap: {edge.stats()}"
                # The vehicle's next pass goes through whole.
                for c in chunks:
                    publish(key, dataclasses.replace(c, pass_id="second").encode())
                assert second_done.wait(EVENT_S), f"the next pass was not processed: {edge.stats()}"
                # A session is closed only once no callback is inside one of its calls (zenoh refuses:
                # "Already borrowed"); the pass-done arrives while the edge's put of it is still returning.
                assert second_handled.wait(EVENT_S)
            done_sub.undeclare()
            stop.set()
            server.join(EVENT_S)
    finally:
        stop.set()
        _stop(router)
    assert done_passes == ["second"]
    assert edge.rejected["sequence_gap"] == 1
    # What the cache no longer held, reported by Zenoh's miss detection: the outage's chunks beyond the cache.
    assert edge.rejected["missed_chunks"] == during - cache, edge.stats()
