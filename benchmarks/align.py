"""Chainage alignment's hold on the cloud daemon's lock: the longest quiet-bus call at 500 and 2 500
passes, a whole sweep per call (``align_budget_s = inf``, the daemon before slicing) against slices
of the default ``align_budget_s``, in one run.

In process (no Zenoh): a GNSS-biased fleet on one 200 m route (every pass 180 m of an ISO 8608 class A
road, bias ~2 m, stretch ~1 %) goes into :class:`cloud.daemon.core.Cloud`, then the daemon's quiet-bus
work runs tick by tick as ``serve`` runs it under its lock (``fuse_pending(flush_budget_s)``,
``maybe_align()``, ``flush_spill()``), each tick timed with the wall clock, until the alignment series
ends (``align_iterations = 1``: one sweep, whose longest piece is what the lock waits on; the
series' end, which marks every pass's continuous-time AP due again, is in the last tick).

* ``align.lock_hold_max_ms.<passes>.whole_sweep|sliced``: the longest tick (ms); the context has the
  ticks, the idle work's total (s) and the 99th-percentile tick; ``ratio_to.whole_sweep`` (sliced
  lines) is the whole sweep's longest tick over the sliced one's, measured in this run.

``DRIVEBY_BENCH_ALIGN_PASSES=500,2500`` chooses the fleets. Timings on a shared machine are noisy; a
tick's hold is the core's work only (the daemon adds its status publication).
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Iterator

import numpy as np

from cloud.daemon.core import Cloud
from cloud.daemon.settings import CloudSettings
from cloud.road.alignment import Alignment
from shared import keys
from shared.profiles import iso8608_profile, tyre_filter
from shared.registry import Route, Site, VehicleClass
from shared.schema import ApSegment, PassDone

NET = "bench"
SPACING_M = 0.05
TILE_POINTS = 1000
PASSES = tuple(int(n) for n in os.environ.get("DRIVEBY_BENCH_ALIGN_PASSES", "500,2500").split(","))
#: A quarter car's class mean (kg, N/m, N·s/m): the parameters the continuous-time correction uses.
CAR = {"M": 400.0, "m": 40.0, "K": 2.0e4, "k": 2.0e5, "c": 1.5e3}
SITE = Site(routes=(Route(id="R1", length_m=200.0),),
            vehicle_classes=(VehicleClass(model="quarter_car", mean=CAR, std={n: 0.1 * v for n, v in CAR.items()}),))


def road(seed: int = 5):
    """The route's true profile (a little longer than the route: passes biased past its end)."""
    return tyre_filter(iso8608_profile(220.0, 0.01, "A", seed=seed))


def fleet_alignments(n: int, seed: int = 3) -> list[Alignment]:
    """``n`` passes' true chainage errors (true → reported): bias ~2 m, stretch ~1 %."""
    rng = np.random.default_rng(seed)
    return [Alignment(float(rng.normal(0, 2.0)), float(rng.normal(0, 0.01)), 10.0, 1.0) for _ in range(n)]


def send_pass(cloud: Cloud, i: int, al: Alignment, version: int, profile, rng, net: str = "t") -> None:
    """Pass ``i`` (vehicle ``v<i>``, pass ``p<i>``) of a GNSS-biased fleet into the core at calibration
    ``version``: its AP on the grid of its reported chainage (``al``: true → reported), cut into
    tiles of ``TILE_POINTS``, then its pass-done."""
    h = SPACING_M
    x_true = np.arange(10.0, 190.0, h)
    x_rep = al.true_to_reported(x_true)
    i0, i1 = int(np.ceil(x_rep[0] / h)), int(np.floor(x_rep[-1] / h))
    ap = np.interp(np.arange(i0, i1) * h, x_rep, profile.at(x_true)) + rng.normal(0, 2e-5, i1 - i0)
    starts = list(range(i0, i1, TILE_POINTS))
    for k, a in enumerate(starts):
        z = min(a + TILE_POINTS, i1)
        seg = ApSegment.make(ap[a - i0 : z - i0], np.full(z - a, 1e-4), vehicle_id=f"v{i}", pass_id=f"p{i}",
                             route_id="R1", tile=k, axle=1, start_index=a, spacing_m=h, calib_version=version,
                             speed_mps=20.0, t_first=a * h / 20, t_last=(z - 1) * h / 20, seq=k)
        cloud.on_segment(keys.ap_key(net, "R1", k, f"v{i}"), seg.encode())
    done = PassDone(f"v{i}", f"p{i}", "R1", version, len(starts), "quarter_car")
    cloud.on_done(keys.done_key(net, f"v{i}"), done.encode())


def idle_ticks(cloud: Cloud) -> list[float]:
    """The daemon's quiet-bus ticks until the alignment series ends: each tick's wall time (s)."""
    s, holds = cloud.settings, []
    while True:
        t0 = time.perf_counter()
        cloud.fuse_pending(s.flush_budget_s)
        cloud.maybe_align()
        cloud.flush_spill()
        holds.append(time.perf_counter() - t0)
        if not cloud.aligning:
            return holds


def run() -> Iterator[dict]:
    profile = road()
    sliced_budget = CloudSettings().align_budget_s
    for n in PASSES:
        truth = fleet_alignments(n)
        whole_ms = None
        for name, budget in (("whole_sweep", math.inf), ("sliced", sliced_budget)):
            settings = dataclasses.replace(CloudSettings(), align_iterations=1, align_budget_s=budget)
            cloud = Cloud(NET, SITE, lambda k, p: None, settings)
            rng = np.random.default_rng(11)
            t0 = time.perf_counter()
            for i, al in enumerate(truth):
                send_pass(cloud, i, al, 0, profile, rng, NET)
            ingest_s = time.perf_counter() - t0
            holds = np.array(idle_ticks(cloud))
            hold_ms = float(holds.max() * 1e3)
            line = {"name": f"align.lock_hold_max_ms.{n}.{name}", "value": round(hold_ms, 1), "unit": "ms",
                    "context": {"passes": n, "align_budget_s": budget if math.isfinite(budget) else "inf",
                                "ticks": int(holds.size), "idle_s": round(float(holds.sum()), 2),
                                "p99_tick_ms": round(float(np.quantile(holds, 0.99) * 1e3), 1),
                                "aligned_passes": len(cloud.alignments), "ingest_s": round(ingest_s, 2)}}
            if name == "whole_sweep":
                whole_ms = hold_ms
            else:
                line["ratio_to"] = {"whole_sweep": round(whole_ms / hold_ms, 1)}
            yield line
