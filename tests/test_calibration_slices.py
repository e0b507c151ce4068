"""Calibration rounds in slices (``CloudSettings.round_budget_s``) give the rounds of one call.

A round's vehicle steps are taken ahead in bounded calls and the round applied with the last; the
view's vehicle table is built in slices after it from a snapshot. Neither may change a number: the
same small fleet (road-qc, 200 m, 8 quarter-cars, simfleet's world, seed 0) through the edge and
cloud cores in one process, once with whole rounds and once with a zero budget (every call one
vehicle's step or linearisation), must end in the same calibrator state, bit for bit, and the view
must log after each round the table the export would write at that moment. A real Rerun view
(an .rrd file) is attached to the sliced run. The export's table, built by the daemon outside its
lock from a snapshot (:meth:`cloud.daemon.core.Cloud.table_job`), is the direct one too.
"""

from __future__ import annotations

import dataclasses
import json
import math

import pytest

from cloud.daemon.settings import CloudSettings
from cloud.road.fleet_calibration import FleetCalibrator
from cloud.view import View
from shared.drivelog import list_drive_logs, read_drive_log
from shared.registry import load_site
from simfleet.harness import Harness
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

FLEET = 8


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    out = tmp_path_factory.mktemp("slices")
    sc = dataclasses.replace(SCENARIOS["road-qc"], route_length_m=200.0)
    generate(sc, out, seed=0, passes=FLEET, vehicles=FLEET, workers=1, progress=False)
    return load_site(out / "site.toml"), [read_drive_log(p) for p in list_drive_logs(out / "logs")], out


def _run(site, logs, budget_s: float, view=None):
    """The harness until it settles; (the harness, the rounds it counted, the calls that did calibration
    work, the vehicle tables: with a view, those it logged; without, the table built directly as each
    round was applied)."""
    h = Harness(site, CloudSettings(calibration="fleet", round_budget_s=budget_s))
    cloud = h.cloud
    calls, logged = [0], []
    if view is not None:
        cloud.view = view
        log_calibration = view.log_calibration

        def log_and_keep(rows):  # the real view logs them; the test keeps a copy
            logged.append([dict(r) for r in rows])
            log_calibration(rows)

        view.log_calibration = log_and_keep
    calibrate = cloud.maybe_calibrate

    def counted(*args, **kwargs):
        before = cloud.calibrator.rounds
        ran = calibrate(*args, **kwargs)
        calls[0] += ran
        if view is None and cloud.calibrator.rounds != before:
            logged.append(cloud.calibrator.table(cloud.fused_segments()))
        return ran

    cloud.maybe_calibrate = counted
    h.replay(logs)
    rounds = h.settle()
    return h, rounds, calls[0], logged


def test_sliced_rounds_and_view_tables_are_the_whole_ones(fleet, tmp_path):
    site, logs, _ = fleet
    whole, rounds, whole_calls, direct = _run(site, logs, math.inf)
    with View(tmp_path / "view.rrd", routes={r.id: r.length_m for r in site.routes}) as view:
        sliced, sliced_rounds, sliced_calls, logged = _run(site, logs, 0.0, view)
    a, b = whole.cloud.calibrator, sliced.cloud.calibrator
    assert a.rounds >= 2 and a.rounds == b.rounds and rounds == sliced_rounds, (a.rounds, b.rounds)
    assert sliced_calls > 2 * whole_calls  # the work was spread: a call per vehicle's step and linearisation
    assert json.dumps(a.state(), sort_keys=True) == json.dumps(b.state(), sort_keys=True)
    # one table per round, each the table built directly when its round was applied
    assert len(logged) == len(direct) == b.rounds
    assert all(rows for rows in direct) and logged == direct
    # the export's table, built from a snapshot by a job the daemon runs without its lock, is the
    # table built directly (the sliced cloud's: its view's table is out of date by then)
    job = whole.cloud.table_job()
    key, rows = job()
    whole.cloud.keep_table(key, rows)
    assert whole.cloud.table_job() is None  # nothing changed since: kept
    assert rows and whole.cloud.vehicle_rows() == rows == sliced.cloud.vehicle_rows()
    # every table above reused the vehicles' AP responses from the tables before; a calibrator
    # restored from the same state, with none to reuse, builds the same table
    c = whole.cloud.calibrator
    fresh = FleetCalibrator(site, None)
    fresh.load_state(c.state())
    fresh.continuous_aps, fresh.sample_intervals = c.continuous_aps, dict(c.sample_intervals)
    assert fresh.table(whole.cloud.fused_segments()) == rows
    assert (tmp_path / "view.rrd").stat().st_size > 0
