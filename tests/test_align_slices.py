"""Chainage alignment in bounded slices: the same result as whole sweeps on a quiet bus, each slice
within its budget plus one pass's work, and passes that change between slices never given an
estimate made from segments they no longer hold."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pyarrow.parquet as pq
import pytest

import cloud.daemon.chainage as chainage
from benchmarks.align import SITE, fleet_alignments, road, send_pass
from cloud.daemon.core import Cloud
from cloud.daemon.settings import CloudSettings
from cloud.ingest.aggregator import MIN_RESIDENT_PASSES
from cloud.road.alignment import centred, realign
from shared.drivelog import list_drive_logs, read_drive_log
from shared.registry import load_site
from simfleet.harness import run_in_process
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

PASSES = 7
#: continuous_aps off: the correction is separate idle work (fuse_pending), and the held segments
#: compared here are then exactly what alignment gave the estimators.
BASE = CloudSettings(calibration="nominal", continuous_aps=False)


class FakeClock:
    """The core's clock, moved by the test (and by the work it wraps): never the wall clock."""

    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _fleet(budget_s: float, n: int = PASSES, **changes) -> tuple[Cloud, FakeClock, list]:
    clock = FakeClock()
    cloud = Cloud("t", SITE, lambda k, p: None, dataclasses.replace(BASE, align_budget_s=budget_s, **changes),
                  clock=clock)
    truth = fleet_alignments(n)
    rng = np.random.default_rng(11)
    for i, al in enumerate(truth):
        send_pass(cloud, i, al, 0, road(), rng)
    return cloud, clock, truth


def _settle(cloud: Cloud) -> int:
    """maybe_align until the series ends, as the daemon's quiet ticks call it; returns the calls."""
    calls = 0
    while cloud.maybe_align() or cloud.aligning:
        calls += 1
        assert calls < 10_000
    return calls


def _held(cloud: Cloud) -> dict:
    agg = cloud.aggregator
    return {sl: (agg.held[sl].start_index, agg.held[sl].values.tobytes(), agg.held[sl].sigma.tobytes())
            for sl in sorted(agg.held)}


def _until_sweeping(cloud: Cloud) -> None:
    """Slices until a sweep has begun (re-gridding recomputed passes first): at budget 0, that slice
    estimated one pass."""
    while not cloud.aligner.sweeping:
        assert cloud.maybe_align()


def test_the_budget_is_a_validated_setting():
    assert CloudSettings().align_budget_s < 1.0  # idle work answers input well within a second
    assert CloudSettings(align_budget_s=math.inf).align_budget_s == math.inf  # a whole sweep per call
    for bad in (-0.1, float("nan")):
        with pytest.raises(ValueError, match="align_budget_s"):
            CloudSettings(align_budget_s=bad)


@pytest.mark.parametrize("memory", [{}, {"max_resident": 5, "max_resident_passes": MIN_RESIDENT_PASSES}],
                         ids=["resident", "spilled"])
def test_slices_give_exactly_the_alignments_and_held_segments_of_whole_sweeps(memory, tmp_path):
    """On a quiet bus, a series run one pass per slice (budget 0) ends where whole sweeps (budget
    inf) do: the same alignments, the same segments held, the same frames, bit for bit — and it
    took many calls, so it was sliced. Also with segments and passes spilled to disk between slices."""
    memory = {**memory, "spill_dir": tmp_path} if memory else {}
    whole, _, truth = _fleet(math.inf, **memory)
    sliced, _, _ = _fleet(0.0, **memory)
    whole_calls, sliced_calls = _settle(whole), _settle(sliced)
    assert whole_calls <= BASE.align_iterations
    assert sliced_calls >= 2 * PASSES * whole_calls  # every estimate and every apply a slice of its own
    assert whole.alignments == sliced.alignments and len(whole.alignments) == PASSES
    assert _held(whole) == _held(sliced)
    assert whole.aligner.frames == sliced.aligner.frames == {"R1": True}
    assert whole.aligner.framed == sliced.aligner.framed
    # …and that common result is the fleet's mean frame (test_alignment's accuracy, 2 cm).
    x = np.linspace(10.0, 190.0, 5)
    for i, want in enumerate(centred(truth)):
        got = sliced.alignments[(f"v{i}", f"p{i}")]
        assert np.max(np.abs(got.true_to_reported(x) - want.true_to_reported(x))) < 0.02, i


def test_a_slice_overruns_its_budget_by_at_most_one_passs_work(monkeypatch):
    """The clock moves only with work: each estimate and each re-gridding costs ``cost`` of it. A
    slice of budget 2.5·cost does at most three of them (the third starts before 2.5·cost), and
    every slice does at least one."""
    cost, budget = 1.0, 2.5
    cloud, clock, _ = _fleet(budget)
    estimate, regrid = chainage.estimate_alignment, chainage.realign

    def costly(f):
        def run(*args, **kwargs):
            clock.now += cost
            return f(*args, **kwargs)
        return run

    monkeypatch.setattr(chainage, "estimate_alignment", costly(estimate))
    monkeypatch.setattr(chainage, "realign", costly(regrid))
    spent = []
    while True:
        t0 = clock.now
        more = cloud.maybe_align()
        spent.append(clock.now - t0)
        if not (more or cloud.aligning):
            break
    assert max(spent) <= budget + cost  # at most one unit beyond the budget
    assert min(spent[:-1]) >= cost  # every slice made progress (the last call: the series had ended)
    assert spent.count(3 * cost) >= len(spent) // 2  # the budget was used, not one unit per call
    assert len(cloud.alignments) == PASSES


def test_a_pass_recomputed_mid_sweep_keeps_its_alignment_until_the_next_sweep():
    """A pass recomputed (a new calibration version) after this sweep estimated it and before the
    sweep applies it: the estimate is of segments it no longer holds, so it is not applied. The pass
    keeps the alignment found for it before (re-applied to its new segments, as any recomputed
    pass), and the acknowledgement starts a new series, whose next sweep estimates it afresh."""
    cloud, _, truth = _fleet(0.0)
    _settle(cloud)
    key = ("v0", "p0")
    agg = cloud.aggregator
    # A new series (a pass came back recomputed); its first sweep estimates one pass per slice…
    send_pass(cloud, 1, truth[1], 1, road(), np.random.default_rng(12))
    _until_sweeping(cloud)
    for _ in range(PASSES - 1):
        assert cloud.maybe_align()
    before = dict(cloud.alignments)
    # …every pass is estimated, none applied yet: then p0 comes back recomputed.
    send_pass(cloud, 0, truth[0], 1, road(), np.random.default_rng(13))
    assert cloud.aligner.renewed
    while cloud.aligner.sweeping:  # the rest of this sweep
        assert cloud.maybe_align()
    assert cloud.alignments[key] is before[key]  # not this sweep's estimate (made from its old segments)
    assert all(cloud.alignments[k] is not before[k] for k in before if k != key)  # the others applied
    slots = sorted(agg.passes[key].slots)
    again = {(s.vehicle_id, s.pass_id, s.route_id, s.tile, s.axle): s
             for s in realign([agg.segments[sl] for sl in slots], before[key])}
    assert all(agg.segments[sl].calib_version == 1 for sl in slots)
    for sl in slots:  # its new segments, re-gridded with the alignment it had
        assert np.array_equal(agg.held[sl].values, again[sl].values)
    assert cloud.aligning and cloud.aligner.sweeps == 0  # a new series follows
    _settle(cloud)
    assert cloud.alignments[key] is not before[key]  # estimated afresh, from its new segments
    x = np.linspace(10.0, 190.0, 5)
    want = centred(truth)[0]
    assert np.max(np.abs(cloud.alignments[key].true_to_reported(x) - want.true_to_reported(x))) < 0.02


def test_a_pass_completed_mid_sweep_is_aligned_by_the_series_that_follows():
    """A pass that completes while a sweep is part-done was not among the passes that sweep
    compares: the sweep does not count towards the series its acknowledgement starts, so the pass
    is aligned even when one sweep would otherwise end the series (``align_iterations=1``). The
    status is not "settled" while a sweep is part-done."""
    cloud, _, _ = _fleet(0.0, align_iterations=1)
    _until_sweeping(cloud)
    assert not cloud.status()["settled"]
    late = (f"v{PASSES}", f"p{PASSES}")
    send_pass(cloud, PASSES, fleet_alignments(PASSES + 1)[PASSES], 0, road(), np.random.default_rng(14))
    while cloud.aligner.sweeping:
        cloud.maybe_align()
        assert not cloud.status()["settled"]
    assert late not in cloud.alignments and len(cloud.alignments) == PASSES and cloud.aligning
    _settle(cloud)
    assert late in cloud.alignments
    assert cloud.status()["settled"]


def test_a_calibrated_fleet_exports_the_same_whatever_the_slices(tmp_path):
    """Through calibration rounds (passes recomputed, re-gridded, their continuous-time APs fused): the
    idle work runs in one order however it is sliced, so one pass per slice and whole sweeps export
    the same tables bit for bit. (The corrections used to be fused between the re-gridding and the
    sweep when the two fell in different slices, which moved the estimates by rounding.)"""
    sim = tmp_path / "sim"
    generate(SCENARIOS["road-qc"], sim, seed=3, passes=3, vehicles=3)
    site = load_site(sim / "site.toml")
    logs = [read_drive_log(p) for p in list_drive_logs(sim / "logs")]
    for budget in (0.0, math.inf):
        run_in_process(logs, site, tmp_path / str(budget), CloudSettings(calibration="fleet", align_budget_s=budget))
    for table in ("profile", "roughness", "vehicles"):
        a, b = (pq.read_table(tmp_path / str(budget) / f"{table}.parquet") for budget in (0.0, math.inf))
        assert a.equals(b), table
