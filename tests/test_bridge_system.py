"""Bridge monitoring as part of the running system: cloud daemon, Parquet export, Rerun, alarms.

End to end through ``driveby run`` (a Zenoh router on a free loopback port, edge and cloud as
separate processes, real drive logs, real Parquet and .rrd read back): a small healthy smooth-deck
bridge, with nominal calibration so the run takes seconds. The alarm's *decision* on a damaged
bridge is not checked through that path: with the cloud's stand-in parameters (nominal mode: the
class mean: the cloud's fallback parameters) the estimator cannot see a stiffness loss, and fleet
self-calibration, which gives it the vehicles' parameters, takes minutes (12 rounds, measured ~160 s
for 12 passes on this machine). The alarm logic is checked instead on the cloud's transport-free
:class:`~cloud.bridge.monitor.BridgeMonitor`, fed by the real edge with the parameters the edge itself used
(each log's nominal parameters) — that is where the state machine (raise once, clear once) lives.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import threading
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import zenoh

from shared import keys
from shared.registry import load_site
from shared.schema import decode_alarm
from shared.transport import run_router, zenoh_config
from simfleet.scenarios import SCENARIOS, BridgeSpec
from simfleet.sim import generate

from tests.bridge_cache import kept
from tests.support import drive, drive_logs

NET = "tb"
ELEMENT_COLUMNS = ["bridge_id", "element", "x_start_m", "x_end_m", "EI_mean", "EI_lo95", "EI_hi95", "stiffness_ratio"]
BEARING_COLUMNS = ["bridge_id", "support", "log10_krot_mean", "log10_krot_lo95", "log10_krot_hi95"]
SUMMARY_COLUMNS = ["bridge_id", "n_passes", "D1_pct", "D2_pct", "midspan_mril", "damaged"]


def _scenario(global_loss: float):
    """The thesis bridge (20 m span, 2 % noise, smooth deck) with a uniform stiffness loss."""
    return dataclasses.replace(SCENARIOS["bridge-healthy"], name=f"bridge-loss{round(100 * global_loss)}",
                               bridge=BridgeSpec(global_loss=global_loss))


@functools.lru_cache(maxsize=None)
def simulated(global_loss: float, passes: int, nominal: str) -> Path:
    """The drive logs (read only), kept between sessions while the code making them is unchanged."""
    return kept(f"system-{global_loss}-{passes}-{nominal}",
                lambda out: generate(_scenario(global_loss), out, seed=5, passes=passes, nominal=nominal,
                                     workers=2, progress=False))


def test_run_exports_bridge_tables_and_recording_and_no_alarm_on_a_healthy_bridge(tmp_path):
    from rerun.chunk import RrdReader

    from simfleet.run import run

    passes = 8
    # The logs carry the vehicles' true parameters, which the edge uses and reports in each pass-done:
    # the bridge is estimated with the right vehicles. (Class-mean vehicles need the class-wide
    # calibration uncertainty integrated out, which tests/test_bridge_dynamic.py checks in process;
    # the daemon gives every pass the default log-sd, ``BridgeSettings.calibration_log_sd``.)
    sim = simulated(0.0, passes, "true")
    site = load_site(sim / "site.toml")
    bridge = site.bridges[0]
    rrd = tmp_path / "run.rrd"
    alarms = []
    with run_router() as endpoint, zenoh.open(zenoh_config("client", connect=[endpoint])) as session:
        sub = session.declare_subscriber(keys.alarm_keyexpr(NET),
                                         lambda s: alarms.append(decode_alarm(s.payload.to_bytes())))
        res = run(sim / "logs", sim / "site.toml", tmp_path / "export", rrd=rrd, calibration="nominal",
                  connect=endpoint, net=NET, progress=False)
        sub.undeclare()
    assert res.acked == passes
    # Alarms are published before the export is answered (the export estimates what is pending).
    assert alarms == []

    elements = pq.read_table(tmp_path / "export" / "bridge_elements.parquet")
    assert elements.column_names == ELEMENT_COLUMNS
    rows = elements.to_pylist()
    assert [r["element"] for r in rows] == list(range(1, bridge.n_elements + 1))
    assert {r["bridge_id"] for r in rows} == {bridge.id}
    np.testing.assert_allclose([r["x_start_m"] for r in rows], np.arange(bridge.n_elements) * 1.0)
    np.testing.assert_allclose([r["x_end_m"] for r in rows], np.arange(1, bridge.n_elements + 1) * 1.0)
    for r in rows:
        assert 0 < r["EI_lo95"] <= r["EI_mean"] <= r["EI_hi95"]
        assert math.isclose(r["stiffness_ratio"], r["EI_mean"] / (bridge.E_pa * bridge.I_m4), rel_tol=1e-9)
        assert 0.7 < r["stiffness_ratio"] < 1.3  # a healthy bridge; 8 passes at 2 % noise
    bearings = pq.read_table(tmp_path / "export" / "bridge_bearings.parquet")
    assert bearings.column_names == BEARING_COLUMNS and bearings.num_rows == 0  # simply supported
    summary = pq.read_table(tmp_path / "export" / "bridge_summary.parquet")
    assert summary.column_names == SUMMARY_COLUMNS
    (row,) = summary.to_pylist()
    assert row["bridge_id"] == bridge.id and row["n_passes"] == passes and row["damaged"] is False
    design = bridge.span_m**3 / (48 * bridge.E_pa * bridge.I_m4)  # m/N, mid-span of the design beam
    assert 0.3 * design < row["midspan_mril"] < 3.0 * design
    assert math.isfinite(row["D1_pct"]) and math.isfinite(row["D2_pct"])

    chunks = list(RrdReader(str(rrd)).stream())
    seen = {c.entity_path for c in chunks}
    for entity in ("span/mean", "span/whiskers", "mril/current", "mril/baseline", "indicators", "summary"):
        assert f"/bridge/B1/{entity}" in seen, (entity, sorted(seen))
    stiffness_passes = [p for c in chunks if c.entity_path == "/bridge/B1/span/mean" and not c.is_static
                        for p in c.to_record_batch().column("pass").to_pylist()]
    assert stiffness_passes and max(stiffness_passes) == passes
    assert all(3 <= p <= passes for p in stiffness_passes)  # the estimator needs 3 passes


@functools.lru_cache(maxsize=None)
def fed_monitor(global_loss: float):
    return new_fed_monitor(global_loss)


def new_fed_monitor(global_loss: float):
    """A BridgeMonitor fed by the real edge (in-process) with 12 passes whose logs carry each
    vehicle's own parameters: the edge computes with them, and so does the monitor."""
    from cloud.ingest.aggregator import Aggregator
    from cloud.bridge.estimator import BridgeSettings
    from cloud.bridge.monitor import BridgeMonitor
    from edge.node import Edge

    sim = simulated(global_loss, 12, "true")
    site = load_site(sim / "site.toml")
    logs = drive_logs(sim)
    used = {log.meta.vehicle_id: dict(log.meta.nominal_params) for log in logs}
    agg = Aggregator(site, [])

    def publish(key, payload):
        if "/ap/" in key:
            agg.on_segment(payload)
        elif "/done/" in key:
            agg.on_pass_done(payload)

    drive(Edge("net", publish, site, "nominal"), logs)
    monitor = BridgeMonitor(site, BridgeSettings(deck="smooth"), clock=lambda: "2026-01-01T00:00:00+00:00")
    added = monitor.sync(agg.passes, agg.held, lambda vid, model, version: used[vid])
    return monitor, added, agg, used


def test_a_damaged_bridge_raises_one_alarm_with_location_and_severity():
    monitor, added, agg, used = fed_monitor(0.30)
    assert added == 12
    (alarm,) = monitor.estimate()
    assert alarm.bridge_id == "B1" and alarm.kind in ("global", "crack")
    assert alarm.probability > 0.95 and 0.1 < alarm.severity < 0.6  # true loss 30 % everywhere
    assert alarm.element == -1 or 1 <= alarm.element <= 20
    assert 0.0 <= alarm.x_m <= 20.0
    assert decode_alarm(alarm.encode()).message == alarm.message
    (row,) = monitor.summary_rows()
    assert row["damaged"] is True and row["n_passes"] == 12
    # Once per state change: nothing new, nothing published; re-estimated, still alarmed: silent.
    assert monitor.sync(agg.passes, agg.held, lambda vid, model, version: used[vid]) == 0
    assert monitor.estimate() == []
    monitor.bridges["B1"].dirty = True
    assert monitor.estimate() == []


def test_a_healthy_bridge_raises_none_and_an_alarm_clears_once():
    monitor, added, healthy_agg, used = fed_monitor(0.0)
    assert added == 12
    assert monitor.estimate() == []
    assert monitor.summary_rows()[0]["damaged"] is False
    # The damaged bridge's monitor when the same passes (same fleet, same pass ids, same design)
    # come back recomputed over the healthy bridge: each replaces its old version, the alarm clears, once.
    damaged, *_ = fed_monitor(0.30)
    if not damaged.bridges["B1"].alarmed:
        assert len(damaged.estimate()) == 1
    assert damaged.sync(healthy_agg.passes, healthy_agg.held, lambda vid, model, version: used[vid]) == 12
    assert damaged.bridges["B1"].estimator.n_passes == 12
    (cleared,) = damaged.estimate()
    assert cleared.kind == "cleared" and cleared.severity == 0.0
    assert damaged.estimate() == []


def test_export_tables_refuse_rows_off_the_contract():
    from cloud.export import bridge_elements_table, bridge_summary_table

    row = dict(bridge_id="B1", n_passes=3, D1_pct=1.0, D2_pct=2.0, midspan_mril=3e-9, damaged=False)
    assert bridge_summary_table([row]).column_names == SUMMARY_COLUMNS
    with pytest.raises(ValueError, match="bridge_summary"):
        bridge_summary_table([{**row, "extra": 1}])
    assert bridge_elements_table([]).num_rows == 0


def test_the_cloud_publishes_an_alarm_over_zenoh_once():
    """Cloud.maybe_estimate_bridges publishes on driveby/<net>/alarm/<bridge> (a real Zenoh session
    on a loopback router) — here with the monitor fed above, the Cloud's own being unable to see
    the loss in nominal mode (module docstring)."""
    from cloud.daemon.core import Cloud
    from cloud.daemon.settings import CloudSettings

    monitor, *_ = new_fed_monitor(0.30)
    got, arrived, marker = [], threading.Event(), threading.Event()
    with run_router() as endpoint, zenoh.open(zenoh_config("client", connect=[endpoint])) as session:
        def on_alarm(sample):
            key = str(sample.key_expr)
            if key == keys.alarm_key(NET, "B0"):
                marker.set()  # the end marker: everything published before it has arrived
                return
            got.append((key, decode_alarm(sample.payload.to_bytes())))
            arrived.set()

        session.declare_subscriber(keys.alarm_keyexpr(NET), on_alarm)
        cloud = Cloud(NET, monitor.site, lambda k, p: session.put(k, p), CloudSettings(calibration="nominal"))
        cloud.bridges = monitor
        assert cloud.maybe_estimate_bridges(force=True)
        assert arrived.wait(60.0), "no alarm arrived"  # bounded for a loaded 2-core machine
        assert not cloud.maybe_estimate_bridges(force=True)  # nothing new: no estimate, no alarm
        session.put(keys.alarm_key(NET, "B0"), b"end")
        assert marker.wait(60.0)
    ((key, alarm),) = got
    assert key == keys.alarm_key(NET, "B1") and alarm.kind in ("global", "crack") and alarm.probability > 0.95
    # What state/bridge/B1 answers: the export rows and the assessment, strict JSON.
    state = json.loads(cloud.bridge_state("B1"))
    assert state["summary"]["damaged"] is True and len(state["elements"]) == 20 and state["bearings"] == []
    assert state["assessment"]["alarm"] is True and state["assessment"]["kind"] == alarm.kind
