"""A cloud rebuilt from its journal (and snapshot) is the cloud that never stopped.

In-process tests use the transport-free cores with a real journal on disk; the system test kills
the cloud daemon with SIGKILL in the middle of a `driveby run` and lets the run's supervisor
restart it.
"""

from __future__ import annotations

import os
import signal
import threading

import numpy as np
import pyarrow.parquet as pq
import pytest
import zenoh

from cloud.daemon.durable import AP, DONE, Durability
from cloud.daemon.journal import Journal
from cloud.daemon.core import Cloud
from cloud.daemon.settings import CloudSettings
from edge.node import Edge
from shared import keys
from shared.registry import load_site
from shared.schema import decode_ack, decode_ap
from shared.transport import run_router, zenoh_config
from simfleet.harness import Harness
from simfleet.run import run
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

from tests.support import drive, drive_logs, edge_messages

NET = "t"


@pytest.fixture(scope="module")
def road(tmp_path_factory):
    out = tmp_path_factory.mktemp("road")
    generate(SCENARIOS["road-qc"], out, seed=11, passes=4, workers=1, progress=False)
    return out


def _feed(cloud, msgs, durability=None):
    for key, payload in msgs:
        kind = AP if "/ap/" in key else DONE
        if durability is not None:
            durability.record(kind, key, payload)
        (cloud.on_segment if kind == AP else cloud.on_done)(key, payload)


@pytest.fixture(scope="module")
def messages(road) -> tuple[tuple[str, bytes], ...]:
    """The edge's messages for the road's passes, made once for the module (a tuple: no test changes them)."""
    return tuple(edge_messages(load_site(road / "site.toml"), drive_logs(road), NET))


def _cloud(road):
    return Cloud(NET, load_site(road / "site.toml"), lambda k, p: None, CloudSettings(calibration="nominal"))


def _same(a: Cloud, b: Cloud):
    sa, sb = a.profile.snapshot()["R1"], b.profile.snapshot()["R1"]
    assert np.array_equal(sa.n_passes, sb.n_passes)
    for f in ("elevation_m", "lo95_m", "hi95_m"):
        x, y = getattr(sa, f), getattr(sb, f)
        scale = np.nanstd(x)
        # Summation order differs after a compaction: equal to rounding, nothing more.
        assert np.nanmax(np.abs(x - y)) <= 1e-9 * scale, f
    assert a.aggregator.stats() == b.aggregator.stats()
    assert a.completed == b.completed


@pytest.mark.parametrize("snapshot_at", [None, 0.5])
def test_recovery_rebuilds_the_same_state(road, messages, tmp_path, snapshot_at):
    msgs = list(messages)
    msgs = msgs[:5] + [("driveby/t/ap/R1/0/veh-x", b"garbage")] + msgs[5:]  # a rejection is state too
    ref = _cloud(road)
    _feed(ref, msgs)
    crashed = _cloud(road)
    d = Durability(Journal(tmp_path), crashed)
    d.recover()
    cut = int(len(msgs) * (snapshot_at or 0.0))
    _feed(crashed, msgs[:cut], d)
    if snapshot_at is not None:
        d.maybe_snapshot(force=True)
    _feed(crashed, msgs[cut:], d)
    # no close(): the process "dies" here with its journal as written
    restarted = _cloud(road)
    Durability(Journal(tmp_path), restarted).recover()
    _same(ref, restarted)


def test_duplicates_after_recovery_change_nothing(road, messages, tmp_path):
    msgs = messages
    ref = _cloud(road)
    _feed(ref, msgs)
    c = _cloud(road)
    d = Durability(Journal(tmp_path), c)
    d.recover()
    half = len(msgs) // 2
    _feed(c, msgs[:half], d)
    restarted = _cloud(road)
    d2 = Durability(Journal(tmp_path), restarted)
    d2.recover()
    _feed(restarted, msgs, d2)  # the edges resend everything unacknowledged, the first half included
    sa, sb = ref.profile.snapshot()["R1"], restarted.profile.snapshot()["R1"]
    assert np.allclose(sa.elevation_m, sb.elevation_m, rtol=0, atol=1e-9 * np.nanstd(sa.elevation_m),
                       equal_nan=True)
    assert restarted.aggregator.accepted == ref.aggregator.accepted
    resent = sum(len(decode_ap(p)) for k, p in msgs[:half] if "/ap/" in k)
    assert resent > 0 and restarted.aggregator.rejected["duplicate"] == resent


def _profile(export_dir):
    t = pq.read_table(export_dir / "profile.parquet").to_pydict()
    return {k: np.asarray(v) for k, v in t.items() if k != "route_id"}


def test_a_cloud_killed_mid_run_is_restarted_and_the_export_is_unchanged(road, tmp_path):
    site = road / "site.toml"
    ref = run(road / "logs", site, tmp_path / "ref", calibration="nominal", progress=False, rate=20.0)
    with run_router() as endpoint:
        kills: list[int] = []
        acks_seen = threading.Event()
        n_acks = [0]
        with zenoh.open(zenoh_config("client", connect=[endpoint])) as s:
            work = tmp_path / "crash" / ".run"

            def kill():
                if n_acks[0] >= 4:  # every pass is in: the run is exporting, and a kill now loses the
                    return  # export request (no replay left to show recovery); fails below instead
                pid = int((work / "cloud.pid").read_text())
                os.kill(pid, signal.SIGKILL)
                kills.append(pid)

            def on_ack(sample):
                ack = decode_ack(sample.payload.to_bytes())
                n_acks[0] += 1
                if n_acks[0] == 1 and not kills:  # on the first acknowledged pass, whatever the load: a
                    threading.Thread(target=kill).start()  # delay after it would race the other three
                acks_seen.set()

            sub = s.declare_subscriber(keys.ack_keyexpr("net"), on_ack)
            # 10× real time: ~1 s per pass, so the kill lands while passes are still being replayed
            # (at 20× a loaded machine acknowledged all four within the kill's delay of the first).
            crash = run(road / "logs", site, tmp_path / "crash", calibration="nominal", progress=False,
                        rate=10.0, connect=endpoint)
            sub.undeclare()
    assert len(kills) == 1, "the kill came after every pass was acknowledged"
    assert int((work / "cloud.pid").read_text()) != kills[0]  # the supervisor started a new cloud
    a, b = _profile(tmp_path / "ref"), _profile(tmp_path / "crash")
    assert np.array_equal(a["n_passes"], b["n_passes"])
    scale = np.std(a["elevation_m"])
    for f in ("elevation_m", "lo95_m", "hi95_m"):
        assert np.max(np.abs(a[f] - b[f])) <= 1e-9 * scale, f
    assert crash.acked == ref.acked == 4
    assert crash.stats["accepted"] == ref.stats["accepted"]  # nothing lost, nothing counted twice


def _fleet_loop(road, state_dir, crash_after_rounds=None, max_resident=None, snapshot=False, max_resident_passes=None):
    """Edge and cloud cores on the harness's in-memory bus (:class:`simfleet.harness.Harness`), the
    cloud with a journal; optionally the cloud "dies" after some calibration rounds and is rebuilt from it."""
    site = load_site(road / "site.toml")
    settings = CloudSettings(calibration="fleet", max_resident=max_resident, spill_dir=state_dir,
                             max_resident_passes=max_resident_passes)
    state = {"durability": None}

    def on_publish(key, payload):  # as the daemon's publish: the cloud's own calibrations are journalled
        d = state["durability"]
        if d is not None and d.live and "/calib/" in key:
            d.record("calib", key, payload)
        return False

    def on_deliver(key, payload):  # as the daemon: input is journalled before it is applied
        kind = key.split("/")[2]
        if kind in ("ap", "done"):
            state["durability"].record(AP if kind == "ap" else DONE, key, payload)

    def recovered(cloud):
        cloud.calibrator.max_rounds = 5  # enough rounds to crash between; the suite stays quick
        d = Durability(Journal(state_dir), cloud)
        d.recover()
        d.live = True
        cloud.record = d.record_own  # as the daemon: epochs and rounds journalled before publishing
        state["durability"] = d
        return cloud

    h = Harness(site, settings, net=NET, on_publish=on_publish, on_deliver=on_deliver)
    recovered(h.cloud)
    h.replay(drive_logs(road))
    rounds = 0
    while h.idle():  # the daemon's idle work when the bus is quiet
        rounds += 1
        if rounds == crash_after_rounds:
            if snapshot:  # compacted first: the restart reads a snapshot (epoch, calibrator, passes in order)
                state["durability"].maybe_snapshot(force=True)
            h.cloud = recovered(Cloud(NET, site, h.publish, settings))  # in flight messages are still delivered
        h.pump()
    return h.cloud


def test_fleet_calibration_resumes_from_the_journal(road, tmp_path):
    """…and, the crashed cloud keeping at most 5 segments and 2 passes in memory, recalibrated passes
    retract segments spilled long before and update passes read back from disk: retracted exactly (what
    the posterior holds to the bit, the profile to rounding)."""
    ref = _fleet_loop(road, tmp_path / "ref")
    crashed = _fleet_loop(road, tmp_path / "crash", crash_after_rounds=2, max_resident=5, max_resident_passes=2)
    store = crashed.aggregator.segments
    assert store.reads > 0 and store.resident <= 5
    passes = crashed.aggregator.passes
    assert passes.reads > 0 and passes.resident <= 2 and len(passes) == 4
    held_a, held_b = ref.profile.segments, crashed.profile.segments
    assert held_a.keys() == held_b.keys() and held_a
    for k, seg in held_a.items():
        assert seg.calib_version == held_b[k].calib_version, k
        assert np.array_equal(seg.values, held_b[k].values) and np.array_equal(seg.sigma, held_b[k].sigma), k
    sa, sb = ref.profile.snapshot()["R1"], crashed.profile.snapshot()["R1"]
    # Every segment the two posteriors hold is the same to the bit (above); their τ is solved warm-started from
    # each one's previous snapshot to 1e-10, and the two made their snapshots at different moments:
    # ~1e-14 of the profile's scale apart (a segment retracted inexactly would be ≥ 1e-3).
    scale = np.nanstd(sa.elevation_m)
    assert np.array_equal(sa.n_passes, sb.n_passes)
    for f in ("elevation_m", "lo95_m", "hi95_m"):
        a, b = getattr(sa, f), getattr(sb, f)
        assert np.array_equal(np.isnan(a), np.isnan(b)), f
        assert np.nanmax(np.abs(a - b)) <= 1e-12 * scale, f
    a = {(r["vehicle_id"], r["param"]): r["mean"] for r in ref.calibrator.table()}
    b = {(r["vehicle_id"], r["param"]): r["mean"] for r in crashed.calibrator.table()}
    assert a.keys() == b.keys() and a
    worst = max(abs(b[k] / a[k] - 1.0) for k in a)
    # A round sees its epoch's passes against a consensus of them summed afresh in a fixed order, so
    # the rebuilt cloud's rounds are the uninterrupted one's to the bit (measured 0.0 after crashes at
    # rounds 1, 2, 3, 5; before epochs, running sums carried rounding amplified to ~1e-6).
    assert worst <= 1e-12, worst
    assert {v: st.version for v, st in crashed.calibrator.vehicles.items()} == \
        {v: st.version for v, st in ref.calibrator.vehicles.items()}
    compacted = _fleet_loop(road, tmp_path / "compacted", crash_after_rounds=3, snapshot=True)
    c = {(r["vehicle_id"], r["param"]): r["mean"] for r in compacted.calibrator.table()}
    assert c == a  # the same rounds from a snapshot too (the profile: to its summation order, below)
    _same(ref, compacted)


def test_a_restarted_cloud_does_not_raise_a_standing_alarm_again(tmp_path):
    """The alarm state is journalled (kind ``alarm``): a cloud rebuilt from it knows the bridge is
    alarmed, so re-estimating the same passes publishes nothing (a cloud rebuilt without it is the
    first one here, which raised the alarm from the same fed-but-unestimated monitor). The monitor is
    fed outside the cloud, as in test_bridge_system (nominal calibration cannot see the loss)."""
    import copy

    from cloud.ingest.aggregator import Aggregator
    from cloud.bridge.estimator import BridgeSettings
    from cloud.bridge.monitor import BridgeMonitor
    from tests.test_bridge_system import simulated

    # The real edge's passes over a bridge with 30 % stiffness loss, computed with each vehicle's own
    # parameters (as tests/test_bridge_system.py, with 4 passes: enough for a certain alarm).
    sim = simulated(0.30, 4, "true")
    site = load_site(sim / "site.toml")
    logs = drive_logs(sim)
    used = {log.meta.vehicle_id: dict(log.meta.nominal_params) for log in logs}
    agg = Aggregator(site, [])
    drive(Edge("net", lambda k, p: agg.on_segment(p) if "/ap/" in k else agg.on_pass_done(p), site, "nominal"), logs)
    monitor = BridgeMonitor(site, BridgeSettings(deck="smooth"), clock=lambda: "2026-01-01T00:00:00+00:00")
    assert monitor.sync(agg.passes, agg.held, lambda vid, model, version: used[vid]) == 4
    published: list[str] = []

    def cloud_on(state_dir):
        c = Cloud(NET, monitor.site, lambda k, p: published.append(k), CloudSettings(calibration="nominal"))
        c.bridges = copy.deepcopy(monitor)  # as a restarted cloud rebuilds it: fed, not yet estimated
        d = Durability(Journal(state_dir), c)
        d.recover()
        d.live = True
        c.record = d.record_own
        return c, d

    first, _ = cloud_on(tmp_path)
    assert not first.bridges.bridges["B1"].alarmed
    assert first.maybe_estimate_bridges(force=True)
    assert published == [keys.alarm_key(NET, "B1")]
    # no close(): killed; restarted on the same state directory (the journal's tail)
    restarted, d = cloud_on(tmp_path)
    assert restarted.bridges.bridges["B1"].alarmed
    assert restarted.maybe_estimate_bridges(force=True)  # estimated again, still damaged…
    assert published == [keys.alarm_key(NET, "B1")]  # …and the standing alarm is not raised twice
    d.maybe_snapshot(force=True)  # compaction keeps the alarm state
    again, _ = cloud_on(tmp_path)
    assert again.bridges.bridges["B1"].alarmed and again.alarms == first.alarms


def _export_tables(cloud, out) -> dict:
    return {p.name: pq.read_table(p) for p in cloud.export(out)}


def test_memory_stays_bounded_as_passes_accumulate_and_the_export_is_unchanged(road, messages, tmp_path):
    """At most ``max_resident`` segments stay decoded in memory; the rest are spilled and read back
    exactly, so the export is the unbounded cloud's, table for table."""
    msgs = messages
    unbounded = _cloud(road)
    _feed(unbounded, msgs)
    bound = 3
    cloud = Cloud(NET, load_site(road / "site.toml"), lambda k, p: None,
                  CloudSettings(calibration="nominal", max_resident=bound, spill_dir=tmp_path / "spill"))
    store = cloud.aggregator.segments
    kept = cloud.profile.segments  # the profile estimator's own (exact retraction, per-pass drift)
    seg_bytes = max(s.values_q.nbytes + s.sigma_q.nbytes for s in unbounded.aggregator.segments.values())
    peak = 0
    for key, payload in msgs:
        _feed(cloud, [(key, payload)])
        peak = max(peak, store.resident, kept.resident)
        assert store.resident_bytes() <= bound * seg_bytes and kept.resident_bytes() <= bound * seg_bytes
    total = len(unbounded.aggregator.segments)
    assert peak == bound and total > 4 * bound  # flat while the held segments grew past it
    assert store.spilled == total - bound and store.stats()["spill_bytes"] > 0
    a, b = _export_tables(unbounded, tmp_path / "a"), _export_tables(cloud, tmp_path / "b")
    assert a.keys() == b.keys() and "profile.parquet" in a
    for name in a:
        assert a[name].equals(b[name]), name


def _fleet_of(msgs, n_passes: int, vehicles: int) -> list[tuple[str, bytes]]:
    """``n_passes`` passes of ``vehicles`` vehicles, each a copy of one of the road's passes under a new
    vehicle and pass id (as a fleet that drives the same road for months)."""
    import dataclasses

    from shared.schema import decode_pass_done

    base: dict[str, list] = {}
    for key, payload in msgs:
        if "/ap/" in key:
            for seg in decode_ap(payload):
                base.setdefault(seg.pass_id, []).append(seg)
        else:
            done = decode_pass_done(payload)
            base.setdefault(done.pass_id, []).append(done)
    templates = list(base.values())
    out = []
    for k in range(n_passes):
        vid = f"f{k % vehicles:03d}"
        for m in templates[k % len(templates)]:
            m = dataclasses.replace(m, vehicle_id=vid, pass_id=f"{vid}-{k // vehicles}")
            key = keys.ap_key(NET, m.route_id, m.tile, vid) if hasattr(m, "tile") else keys.done_key(NET, vid)
            out.append((key, m.encode()))
    return out


def test_held_state_stays_bounded_as_passes_accumulate(road, messages, tmp_path):
    """The cloud's per-pass state (segments, pass bookkeeping: idempotence, exact retraction) lives
    on disk beyond a window, so what it holds in memory stops growing with the passes: measured
    with tracemalloc between the middle and the end of 120 passes, against an unbounded cloud that
    keeps everything (~20 kB a pass); and the export is the unbounded cloud's, table for table."""
    import gc
    import tracemalloc

    fleet = _fleet_of(messages, n_passes=120, vehicles=30)
    seg_bound, pass_bound = 24, 8

    def fed(cloud):
        at = []
        gc.collect()
        tracemalloc.start()
        try:
            for key, payload in fleet:
                _feed(cloud, [(key, payload)])
                agg = cloud.aggregator
                if agg.segments.max_resident is not None:
                    assert agg.segments.resident <= seg_bound and cloud.profile.segments.resident <= seg_bound
                    assert agg.passes.resident <= pass_bound
                if "/done/" in key and cloud.passes_complete in (60, 120):
                    gc.collect()
                    at.append(tracemalloc.get_traced_memory()[0])
        finally:
            tracemalloc.stop()
        return (at[1] - at[0]) / 60

    unbounded = _cloud(road)
    per_pass_unbounded = fed(unbounded)
    cloud = Cloud(NET, load_site(road / "site.toml"), lambda k, p: None,
                  CloudSettings(calibration="nominal", max_resident=seg_bound, max_resident_passes=pass_bound,
                                spill_dir=tmp_path / "spill"))
    per_pass = fed(cloud)
    assert cloud.passes_complete == unbounded.passes_complete == 120
    assert len(cloud.aggregator.passes) == 120 and cloud.aggregator.passes.spilled == 120 - pass_bound
    # Nothing else per pass: no completion order without fleet calibration, nothing hidden or replaced.
    assert not cloud.completion_order and not cloud.aggregator.held.other and not cloud.aggregator.held.absent
    assert per_pass_unbounded > 10_000  # what the measurement sees when everything is kept
    assert per_pass < 1_000, per_pass  # bytes per pass (measured ~0 ± 300): what is left is O(vehicles), not O(passes)
    a, b = _export_tables(unbounded, tmp_path / "a"), _export_tables(cloud, tmp_path / "b")
    assert a.keys() == b.keys() and "profile.parquet" in a
    for name in a:
        assert a[name].equals(b[name]), name


def test_compaction_runs_when_the_journal_is_mostly_garbage(road, messages, tmp_path):
    """A snapshot rewrites the live state: not due while every journalled record is live (a soak's
    steady stream), due once superseded or duplicate records make the journal twice the live state;
    the compacted state restarts to the same cloud."""
    msgs = messages
    cloud = _cloud(road)
    d = Durability(Journal(tmp_path), cloud, min_records=5)
    d.recover()
    d.live = True
    _feed(cloud, msgs, d)
    assert d.since_snapshot == len(msgs) >= 5 and not d.maybe_snapshot()  # nothing to gain yet
    resent = 0
    while d.since_snapshot < d.compact_ratio * d.live_records():
        assert not d.maybe_snapshot()
        _feed(cloud, msgs, d)  # the edges resend: duplicates, journalled and garbage
        resent += 1
    assert resent and d.maybe_snapshot() and d.snapshots == 1
    assert d.since_snapshot == 0 and d.snapshot_records == d.live_records() and not d.maybe_snapshot()
    restarted = _cloud(road)
    Durability(Journal(tmp_path), restarted).recover()
    _same(cloud, restarted)
