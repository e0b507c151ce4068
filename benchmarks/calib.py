"""Fleet calibration's hold on the cloud daemon's lock: a round's longest quiet-bus call, and the cost of
the vehicle table (``vehicles.parquet``'s rows with their intervals, which the Rerun view logs after
every round and the export writes), at N vehicles.

In process (:class:`simfleet.harness.Harness`, no Zenoh): road-qc on a 200 m route, N quarter-cars
one pass each (simfleet's world, seed 0). The cloud's idle work runs as the harness runs it; each
:meth:`cloud.daemon.core.Cloud.maybe_calibrate` call is timed with the wall clock until
``DRIVEBY_BENCH_CALIB_ROUNDS`` rounds have run, then :meth:`~cloud.daemon.core.Cloud.vehicle_rows`
once (process CPU time and wall).

* ``calib.round_lock_hold_max_ms.<N>``: the longest ``maybe_calibrate`` call (ms) with the default
  ``round_budget_s``; the context has the calls, the rounds and the whole rounds' time;
  ``ratio_to.whole_round`` is the longest round's total over the longest call, in this run.
* ``calib.table_cpu_ms.<N>``: ``vehicle_rows()`` CPU time (ms), its wall time in the context.

``DRIVEBY_BENCH_CALIB_VEHICLES=30,90`` chooses the fleets, ``DRIVEBY_BENCH_CALIB_ROUNDS=2`` the rounds
(a round's cost hardly changes from the first on). Timings on a shared machine are noisy.
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from shared.drivelog import list_drive_logs, read_drive_log
from shared.registry import load_site
from simfleet.harness import Harness
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

VEHICLES = tuple(int(n) for n in os.environ.get("DRIVEBY_BENCH_CALIB_VEHICLES", "30,90").split(","))
ROUNDS = int(os.environ.get("DRIVEBY_BENCH_CALIB_ROUNDS", "2"))


def measure(n: int, rounds: int, work_dir: Path) -> dict:
    """Calls' hold (s) and rounds of the first ``rounds`` rounds of an ``n``-vehicle fleet, then the table."""
    sc = dataclasses.replace(SCENARIOS["road-qc"], route_length_m=200.0)
    generate(sc, work_dir, seed=0, passes=n, vehicles=n, workers=1, progress=False)
    h = Harness(load_site(work_dir / "site.toml"))
    cloud = h.cloud
    holds, per_round = [], []
    calibrate = cloud.maybe_calibrate

    def timed(*args, **kwargs):
        t0 = time.perf_counter()
        ran = calibrate(*args, **kwargs)
        if ran:
            holds.append(time.perf_counter() - t0)
            if not cloud.calibrating:  # the round was applied with this call
                per_round.append(sum(holds) - sum(per_round))
        return ran

    cloud.maybe_calibrate = timed
    h.replay([read_drive_log(p) for p in list_drive_logs(work_dir / "logs")])
    while len(per_round) < rounds and h.idle():
        h.pump()
    t0, c0 = time.perf_counter(), time.process_time()
    rows = cloud.vehicle_rows()
    return {"holds": holds, "rounds": per_round, "table_cpu_s": time.process_time() - c0,
            "table_wall_s": time.perf_counter() - t0, "rows": len(rows),
            "round_budget_s": cloud.settings.round_budget_s}


def run() -> Iterator[dict]:
    for n in VEHICLES:
        with tempfile.TemporaryDirectory(prefix="driveby-bench-calib-") as tmp:
            m = measure(n, ROUNDS, Path(tmp))
        hold_ms = 1e3 * max(m["holds"])
        yield {"name": f"calib.round_lock_hold_max_ms.{n}", "value": round(hold_ms, 1), "unit": "ms",
               "ratio_to": {"whole_round": round(1e3 * max(m["rounds"]) / hold_ms, 1)},
               "context": {"vehicles": n, "calls": len(m["holds"]), "rounds": len(m["rounds"]),
                           "round_s": [round(r, 2) for r in m["rounds"]], "round_budget_s": m["round_budget_s"]}}
        yield {"name": f"calib.table_cpu_ms.{n}", "value": round(1e3 * m["table_cpu_s"], 1), "unit": "ms",
               "context": {"vehicles": n, "rows": m["rows"], "wall_ms": round(1e3 * m["table_wall_s"], 1)}}
