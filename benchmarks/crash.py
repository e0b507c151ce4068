"""Crash-consistency benchmark: the cloud daemon SIGKILLed at random moments of a `driveby run`,
restarted by the run's supervisor, and the final export compared with an uninterrupted run's.

Data: ``road-qc``, ``PASSES`` quarter-car passes (seed 11), replayed at ``RATE``× real time so a run
lasts a few seconds. One reference run, then ``DRIVEBY_CRASH_TRIALS`` (default 20) trials. In each,
the cloud is killed (SIGKILL, pid from ``<export>/.run/cloud.pid``) after a random number of
acknowledged passes plus a random delay; every ``TWO_KILLS_EVERY``-th trial kills the restarted cloud
a second time, a random delay after it is back (its liveliness token, or a later acknowledgement).
A kill that would land after every pass is acknowledged is not made (the run is winding down, not
replaying), and is reported as ``skipped``.

Per trial, against the reference (``--calibration nominal``: exact posteriors):

* ``profile.parquet`` elevation/lo95/hi95: max |difference| relative to the reference elevation std;
* ``n_passes`` per cell equal;
* the aggregator's ``accepted`` count (exported stats, ``RunResult.stats``) equal: fewer is a lost
  segment, more a double-counted one (segments are idempotent by vehicle, pass, tile and calibration
  version, so a resent segment is rejected as a duplicate instead);
* every pass acknowledged.

``DRIVEBY_CRASH_FLEET_TRIALS`` (default 3; 0 skips) repeats it with ``--calibration fleet``
(iterative self-calibration; the bound is 1e-6 relative after it settles), adding the
vehicles.parquet means to the comparison (on the cells both profiles have: the aligned extent can
move by a cell). Calibration rounds run in epochs, fixed prefixes of the passes in completion order
(:meth:`cloud.daemon.core.Cloud.maybe_calibrate`), journalled with the calibrator's state before a round's
calibrations are published, so an uninterrupted run and a killed-and-restarted one run the same
rounds on the same data. There ``accepted`` is not comparable (an edge resubmits every segment per
calibration version, and a restarted cloud may re-issue a calibration to get a pass recomputed that
an edge finished with older parameters); lost/double-counted segments are counted by
``segments_held`` instead, and further uninterrupted runs (as many as crash trials) give the noise
floor (``uninterrupted_spread``: since rounds run in epochs, not when the bus happens to be quiet, it
is the profile's summation order).

Timings are wall-clock on a shared machine (noisy). Data are simulated into
``$TMPDIR/driveby-bench-crash`` and the runs' exports are written there too.
"""

from __future__ import annotations

import os
import random
import shutil
import signal
import statistics
import tempfile
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import zenoh

from shared import keys
from shared.schema import decode_ack
from shared.transport import run_router, zenoh_config
from simfleet.run import RunError
from simfleet.run import run as run_daemons
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

SCENARIO = "road-qc"
PASSES = 8
SEED = 11
RATE = 20.0  # × real time: ~10 s passes → ~0.5 s each, a run of ~4 s of replay
TWO_KILLS_EVERY = 3  # trials 0, 3, 6, … kill twice
MAX_DELAY_S = 0.5  # random delay after the chosen acknowledgement / restart
NET = "net"  # `driveby run`'s default network name
TOLERANCE = {"nominal": 1e-9, "fleet": 1e-6}


@dataclass
class Killer:
    """Kills the run's cloud daemon at random moments, driven by acknowledgements and liveliness."""

    work: Path  # <export>/.run
    n_passes: int
    rng: random.Random
    kills_planned: int
    after_acks: int
    acked: set = field(default_factory=set)
    killed: list = field(default_factory=list)  # (pid, passes acknowledged when it was killed)
    skipped: int = 0
    armed: bool = False
    lock: threading.Lock = field(default_factory=threading.Lock)

    def _kill(self) -> None:
        with self.lock:
            if len(self.acked) >= self.n_passes:  # every pass is in; the run is exporting, not replaying
                self.skipped += 1
                return
            try:
                pid = int((self.work / "cloud.pid").read_text())
            except ValueError:  # caught mid-write by the supervisor: try again on the next event
                self.armed = False
                return
            if any(pid == p for p, _ in self.killed):  # not restarted yet: arm again on the next event
                self.armed = False
                return
            os.kill(pid, signal.SIGKILL)
            self.killed.append((pid, len(self.acked)))
            self.armed = False

    def _arm(self) -> None:
        """Schedule the next kill (at most one pending)."""
        with self.lock:
            if self.armed or len(self.killed) + self.skipped >= self.kills_planned:
                return
            self.armed = True
        timer = threading.Timer(self.rng.uniform(0.0, MAX_DELAY_S), self._kill)
        timer.daemon = True
        timer.start()

    def on_ack(self, vehicle_id: str, pass_id: str) -> None:
        self.acked.add((vehicle_id, pass_id))
        if not self.killed:
            if len(self.acked) >= self.after_acks:
                self._arm()
        else:  # a restarted cloud acknowledges: it is back
            self._arm()

    def on_cloud_alive(self) -> None:
        if self.killed:
            self._arm()


def _simulate(work: Path) -> Path:
    road = work / f"{SCENARIO}-{PASSES}"
    if not (road / "site.toml").exists():
        generate(SCENARIOS[SCENARIO], road, seed=SEED, passes=PASSES, workers=1, progress=False)
    return road


def _read(export: Path) -> dict:
    out = {k: np.asarray(v) for k, v in pq.read_table(export / "profile.parquet").to_pydict().items()
           if k != "route_id"}
    vehicles = export / "vehicles.parquet"
    if vehicles.exists():
        t = pq.read_table(vehicles).to_pydict()
        out["vehicles"] = {(v, p): m for v, p, m in zip(t["vehicle_id"], t["param"], t["mean"])}
    return out


def _cells(ref: dict, got: dict) -> tuple[np.ndarray, np.ndarray, bool]:
    """Indices of the cells both profiles have (by chainage), and whether the cells and their pass
    counts are the same (they must be for exact posteriors; fleet calibration moves the aligned
    extent by a cell when the calibrated parameters differ)."""
    ca, cb = np.round(ref["chainage_m"], 6), np.round(got["chainage_m"], 6)
    _, ia, ib = np.intersect1d(ca, cb, return_indices=True)
    same = ca.shape == cb.shape and len(ia) == len(ca) and np.array_equal(ref["n_passes"], got["n_passes"])
    return ia, ib, bool(same)


def _rel_diff(ref: dict, got: dict) -> float:
    """Max |difference| of the profile (elevation, bounds) on the common cells, relative to the
    reference elevation std, and of the vehicles' posterior means relative to each mean; inf when
    NaNs or the vehicles' parameters differ."""
    ia, ib, _ = _cells(ref, got)
    worst = 0.0
    scale = float(np.nanstd(ref["elevation_m"]))
    for f in ("elevation_m", "lo95_m", "hi95_m"):
        a, b = ref[f][ia], got[f][ib]
        if not np.array_equal(np.isnan(a), np.isnan(b)):
            return float("inf")
        worst = max(worst, float(np.nanmax(np.abs(a - b), initial=0.0)) / scale)
    if "vehicles" in ref:
        va, vb = ref["vehicles"], got.get("vehicles", {})
        if va.keys() != vb.keys():
            return float("inf")
        worst = max([worst, *(abs(vb[k] - va[k]) / abs(va[k]) for k in va if va[k] != 0)])
    return worst


def _crash_run(road: Path, export: Path, calibration: str, rng: random.Random, kills: int):
    shutil.rmtree(export, ignore_errors=True)
    killer = Killer(export / ".run", PASSES, rng, kills, after_acks=rng.randint(1, PASSES - 2))
    with run_router() as endpoint, zenoh.open(zenoh_config("client", connect=[endpoint])) as s:
        def on_ack(sample):
            ack = decode_ack(sample.payload.to_bytes())
            killer.on_ack(ack.vehicle_id, ack.pass_id)

        def on_alive(sample):
            if sample.kind == zenoh.SampleKind.PUT:
                killer.on_cloud_alive()

        subs = [s.declare_subscriber(keys.ack_keyexpr(NET), on_ack),
                s.liveliness().declare_subscriber(keys.alive_key(NET, "cloud", "cloud-1"), on_alive)]
        result = run_daemons(road / "logs", road / "site.toml", export, calibration=calibration, progress=False,
                     rate=RATE, connect=endpoint)
        for sub in subs:
            sub.undeclare()
    return result, killer


def _variant(work: Path, road: Path, calibration: str, trials: int, seed: int):
    ref_dir = work / f"ref-{calibration}"
    shutil.rmtree(ref_dir, ignore_errors=True)
    ref = run_daemons(road / "logs", road / "site.toml", ref_dir, calibration=calibration, progress=False, rate=RATE)
    reference = _read(ref_dir)
    exact = calibration == "nominal"
    # Segments held = distinct (vehicle, pass, tile) the estimator holds. With exact posteriors every
    # segment is accepted once, so ``accepted`` must equal the reference's (a resend is a rejected
    # duplicate). Under fleet calibration an edge resubmits each segment per calibration version, so
    # ``accepted`` grows with the number of rounds, which is timing-dependent even without a crash.
    count = "accepted" if exact else "segments_held"
    spread = spread_cells = None
    if not exact:  # the noise floor: as many uninterrupted runs as crash trials, against the first
        spreads = []
        for _ in range(trials):
            again = work / f"ref2-{calibration}"
            shutil.rmtree(again, ignore_errors=True)
            run_daemons(road / "logs", road / "site.toml", again, calibration=calibration, progress=False, rate=RATE)
            spreads.append((_rel_diff(reference, _read(again)), not _cells(reference, _read(again))[2]))
        spread = max(d for d, _ in spreads)
        spread_cells = sum(bad for _, bad in spreads)
    rng = random.Random(seed)
    diffs, seconds, lost, double, unacked, n_passes_bad, failures = [], [], 0, 0, 0, 0, []
    kills = skipped = two_kill_trials = duplicates = restarts_seen = 0
    for i in range(trials):
        planned = 2 if i % TWO_KILLS_EVERY == 0 else 1
        try:
            res, killer = _crash_run(road, work / f"crash-{calibration}", calibration, rng, planned)
        except RunError as e:
            failures.append(f"trial {i}: {e}")
            continue
        got = _read(work / f"crash-{calibration}")
        seconds.append(res.seconds)
        diffs.append(_rel_diff(reference, got))
        n_passes_bad += int(not _cells(reference, got)[2])
        lost += max(0, ref.stats[count] - res.stats[count])
        double += max(0, res.stats[count] - ref.stats[count])
        unacked += res.passes - res.acked
        duplicates += res.stats["rejected"].get("duplicate", 0)
        kills += len(killer.killed)
        skipped += killer.skipped
        two_kill_trials += int(len(killer.killed) == 2)
        now = int((killer.work / "cloud.pid").read_text())
        restarts_seen += int(bool(killer.killed) and now not in {p for p, _ in killer.killed})
    prefix = "crash" if calibration == "nominal" else f"crash.{calibration}"
    tol = TOLERANCE[calibration]
    context = {"scenario": SCENARIO, "passes": PASSES, "calibration": calibration, "rate": RATE,
               "kills": kills, "two_kill_trials": two_kill_trials, "kills_skipped_after_last_ack": skipped,
               "trials_with_restarted_cloud": restarts_seen, "duplicates_rejected": duplicates,
               "reference_accepted": ref.stats["accepted"], "segments_counted_by": count, "failed_trials": failures}
    worst = max(diffs, default=float("nan"))
    yield {"name": f"{prefix}.trials", "value": len(diffs), "unit": "trials", "context": context}
    ratios = {f"tolerance_{tol:g}": worst / tol}
    if spread is not None:
        ratios["uninterrupted_spread"] = worst / spread if spread > 0 else (0.0 if worst == 0 else float("inf"))
    yield {"name": f"{prefix}.max_rel_diff", "value": worst, "unit": "relative", "ratio_to": ratios,
           "context": {"median": statistics.median(diffs) if diffs else None,
                       "trials_over_tolerance": sum(d > tol for d in diffs),
                       "uninterrupted_spread": spread}}
    yield {"name": f"{prefix}.n_passes_mismatch", "value": n_passes_bad, "unit": "trials",
           **({"context": {"uninterrupted_runs_mismatching": spread_cells}} if spread_cells is not None else {})}
    yield {"name": f"{prefix}.lost_segments", "value": lost, "unit": "segments"}
    yield {"name": f"{prefix}.double_counted", "value": double, "unit": "segments"}
    yield {"name": f"{prefix}.unacknowledged_passes", "value": unacked, "unit": "passes"}
    if seconds:
        yield {"name": f"{prefix}.seconds_per_trial", "value": statistics.median(seconds), "unit": "s",
               "ratio_to": {"uninterrupted_run": statistics.median(seconds) / ref.seconds},
               "context": {"max_s": max(seconds), "uninterrupted_s": ref.seconds}}


def run(work: Path | None = None):
    work = Path(work or Path(tempfile.gettempdir()) / "driveby-bench-crash")
    work.mkdir(parents=True, exist_ok=True)
    road = _simulate(work)
    yield from _variant(work, road, "nominal", int(os.environ.get("DRIVEBY_CRASH_TRIALS", "20")), seed=1)
    fleet_trials = int(os.environ.get("DRIVEBY_CRASH_FLEET_TRIALS", "3"))
    if fleet_trials > 0:
        yield from _variant(work, road, "fleet", fleet_trials, seed=2)
