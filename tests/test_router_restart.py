"""Issue 7: a router restart mid-run is survived with nothing lost.

A real router process on a fixed port carries a ``driveby run`` (edge and cloud daemons, the run's
own session). It is killed with SIGKILL mid-run and started again on the same endpoint after a
random pause. Every Zenoh client reconnects by itself (zenoh's default connect retry for clients:
1 s, doubling to 4 s), the edge sees the cloud's liveliness token go and come back and sends its
unacknowledged passes again, the cloud acknowledges a pass it already had again; the export must
equal an uninterrupted run's.

A partitioned link: the router runs in its own network namespace behind a veth pair whose host end
is taken down for 1-3 s (shorter than zenoh's 10 s lease), as a cable pulled and put back; TCP holds
the sessions and delivers what waited, nothing is lost. Needs root (``ip netns``); skipped otherwise.

What is not survived yet: raw sensor chunks published while the router is down. The simulated
loggers (``simfleet.replay`` through ``driveby run``'s session) publish into the void and keep no
copy, so the edge sees a sequence gap and drops the pass (``test_..._while_chunks_stream``).
"""

from __future__ import annotations

import contextlib
import os
import random
import subprocess
import sys
import threading

import numpy as np
import pyarrow.parquet as pq
import pytest
import zenoh

import simfleet.run
from shared import keys
from shared.schema import decode_ack, decode_pass_done
from shared.transport import _start_router, _stop, free_port, zenoh_config
from simfleet.run import RunError, run
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

PASSES = 4
RATE = 20.0  # × real time: passes stream for ~2 s, so an outage can fall inside the stream


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


def _router(endpoint: str):
    proc, error = _start_router(endpoint, None, 15.0)
    assert error is None, f"router on {endpoint} did not start: {error}"
    return proc


def _run_with_outage(road, export, kill_on: str, seed: int):
    """``driveby run`` through a router of ours, SIGKILLed at ``kill_on`` ("last_done": once the edge
    has sent every pass's pass-done, i.e. had every raw chunk; "first_ack": after the first
    acknowledgement, at a random moment up to 0.3 s later) and restarted on the same endpoint after
    a random pause. Returns the run's result (or its exception) and what the outage caught."""
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
        if kill_on == "first_ack" and len(acked) == 1:
            threading.Timer(rng.uniform(0.0, 0.3), kill).start()

    def on_done(sample):
        done_passes.add(decode_pass_done(sample.payload.to_bytes()).pass_id)
        if kill_on == "last_done" and len(done_passes) == PASSES:
            kill()  # at once, in the callback: before the cloud's acknowledgements get back

    def drive():
        try:
            result["run"] = run(road / "logs", road / "site.toml", export, calibration="nominal", progress=False,
                                rate=RATE, connect=endpoint)
        except Exception as e:  # judged by the test
            result["error"] = e

    try:
        with zenoh.open(zenoh_config("client", connect=[endpoint])) as s:
            subs = [s.declare_subscriber(keys.ack_keyexpr("net"), on_ack),
                    s.declare_subscriber(keys.done_keyexpr("net"), on_done)]
            runner = threading.Thread(target=drive, daemon=True)
            runner.start()
            assert killed.wait(120.0), f"the router was never killed ({kill_on}, seed {seed})"
            router[0].wait(10.0)
            outage["run_alive"] = runner.is_alive()
            threading.Event().wait(rng.uniform(0.3, 1.5))  # the outage: a timed pause, not a wait for an event
            router[0] = _router(endpoint)
            runner.join(180.0)
            assert not runner.is_alive(), f"run did not finish after the router restart (seed {seed})"
            for sub in subs:
                sub.undeclare()
    finally:
        _stop(router[0])
    return result, outage


def test_a_router_killed_mid_run_is_restarted_and_nothing_is_lost(road, reference, tmp_path, monkeypatch):
    monkeypatch.setattr(simfleet.run, "IDLE_TIMEOUT_S", 30.0)  # a lost pass or acknowledgement: fail in 30 s, not 120
    ref, ref_dir = reference
    seed = random.randrange(2**32)
    result, outage = _run_with_outage(road, tmp_path / "cut", "last_done", seed)
    if "error" in result:
        raise AssertionError(f"run failed after the router restart (seed {seed})") from result["error"]
    cut = result["run"]
    # The outage fell inside the run: passes were unacknowledged when the router died, and the run
    # (whose export query needs the router) finished only through the restarted one.
    assert outage["run_alive"] and outage["acked_before"] < PASSES, (outage, seed)
    # The edge sent unacknowledged passes again through the restarted router: the cloud saw them twice.
    assert cut.stats["rejected"].get("duplicate", 0) > 0, (cut.stats, seed)
    a, b = _profile(ref_dir), _profile(tmp_path / "cut")
    assert np.array_equal(a["n_passes"], b["n_passes"])
    scale = np.std(a["elevation_m"])
    for f in ("elevation_m", "lo95_m", "hi95_m"):
        assert np.max(np.abs(a[f] - b[f])) <= 1e-9 * scale, f
    assert cut.acked == ref.acked == PASSES
    assert cut.stats["accepted"] == ref.stats["accepted"]  # nothing lost, nothing counted twice


@pytest.mark.xfail(strict=True, raises=RunError,
                   reason="raw chunks published while the router is down are lost: the simulated loggers keep "
                          "no copy (no outbox / AdvancedPublisher cache on the vehicle side), the edge drops the "
                          "pass at the sequence gap and the run idles out")
def test_a_router_killed_while_chunks_stream_loses_nothing(road, reference, tmp_path, monkeypatch):
    monkeypatch.setattr(simfleet.run, "IDLE_TIMEOUT_S", 15.0)  # a lost pass is never acknowledged: fail fast
    seed = random.randrange(2**32)
    result, outage = _run_with_outage(road, tmp_path / "cut", "first_ack", seed)
    assert outage["run_alive"] and outage["acked_before"] < PASSES, (outage, seed)
    if "error" in result:
        raise result["error"]
    assert result["run"].acked == PASSES
    assert result["run"].stats["accepted"] == reference[0].stats["accepted"]


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
        assert ready.wait(15.0), "router in the namespace did not start"
        yield endpoint, lambda up: sh("ip", "link", "set", host_if, "up" if up else "down")
    finally:
        if proc is not None:
            _stop(proc)
        subprocess.run(["ip", "link", "del", host_if], capture_output=True)
        subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def test_a_partitioned_link_heals_and_nothing_is_lost(road, reference, tmp_path, monkeypatch):
    monkeypatch.setattr(simfleet.run, "IDLE_TIMEOUT_S", 30.0)
    ref, ref_dir = reference
    seed = random.randrange(2**32)
    rng = random.Random(seed)
    first_ack, healed = threading.Event(), threading.Event()
    acked: set[str] = set()
    result: dict = {}
    with _router_behind_veth() as (endpoint, link):
        def on_ack(sample):
            acked.add(decode_ack(sample.payload.to_bytes()).pass_id)
            first_ack.set()

        def drive():
            try:
                result["run"] = run(road / "logs", road / "site.toml", tmp_path / "cut", calibration="nominal",
                                    progress=False, rate=RATE, connect=endpoint)
            except Exception as e:  # judged below
                result["error"] = e

        with zenoh.open(zenoh_config("client", connect=[endpoint])) as s:
            sub = s.declare_subscriber(keys.ack_keyexpr("net"), on_ack)
            runner = threading.Thread(target=drive, daemon=True)
            runner.start()
            assert first_ack.wait(120.0), "no pass acknowledged before the partition"
            link(False)
            try:
                before, alive = len(acked), runner.is_alive()
                healed.wait(rng.uniform(1.0, 3.0))  # the partition: a timed stretch, not a wait for an event
            finally:
                link(True)
            runner.join(120.0)
            assert not runner.is_alive(), f"run did not finish after the link came back (seed {seed})"
            sub.undeclare()
    if "error" in result:
        raise AssertionError(f"run failed after the partition (seed {seed})") from result["error"]
    assert alive and before < PASSES, (before, seed)  # the partition cut the run in the middle
    cut = result["run"]
    a, b = _profile(ref_dir), _profile(tmp_path / "cut")
    assert np.array_equal(a["n_passes"], b["n_passes"])
    scale = np.std(a["elevation_m"])
    for f in ("elevation_m", "lo95_m", "hi95_m"):
        assert np.max(np.abs(a[f] - b[f])) <= 1e-9 * scale, f
    assert cut.acked == ref.acked == PASSES
    assert cut.stats["accepted"] == ref.stats["accepted"]
