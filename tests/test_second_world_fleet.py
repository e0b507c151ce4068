"""The second (ivp) world's goals that take a calibrated fleet of 30 passes each: the bridge's global
loss read within a point and alarmed, and one 30-vehicle fleet's ratio intervals holding the truth
with an exact odometer and with the world's own odometer error (their coverage over seeds is
``tests/test_ratio_coverage.py``'s). The road's goals on the same world are
``tests/test_second_world.py``'s; a module apart so the two run side by side.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cloud.road.calibration import to_calibration
from shared.drivelog import list_drive_logs, read_drive_log
from shared.registry import load_site
from simfleet.harness import Harness
from simfleet.reproduce_robustness import run_and_score
from simfleet.scenarios import SCENARIOS
from simfleet.worlds import ivp

from tests.test_second_world import EXACT_ODOMETER


# The figure: with a dozen passes the bridge's own sd of its global level is above the
# 1-point bound, which then tests whether calibration and bridge errors happen to cancel.
BRIDGE_PASSES = 30


@pytest.fixture(scope="module")
def bridges(tmp_path_factory):
    out = {}
    for name in ("bridge-healthy", "bridge-global10"):
        d = tmp_path_factory.mktemp(name)
        ivp.generate(SCENARIOS[name], d, seed=0, passes=BRIDGE_PASSES, noise_pct=2.0, progress=False, workers=1,
                     settings=EXACT_ODOMETER)
        out[name] = run_and_score(d, d / "export")["bridge"]
    return out


def test_bridge_global_loss_is_read_within_a_point_and_alarmed(bridges):
    """The issue's goal at its 30 passes (loss read within 1 point, an alarm on the 10 % loss and none on
    the healthy deck) on the modal bridge of the second world."""
    healthy, lossy = bridges["bridge-healthy"], bridges["bridge-global10"]
    print(f"bridge: healthy {healthy}, 10 % loss {lossy}")
    assert abs(healthy["mean_error_pts"]) < 1.0 and not healthy["alarm"]
    assert abs(lossy["mean_error_pts"]) < 1.0 and lossy["alarm"]


@pytest.mark.parametrize("odometer", ["exact", "1 %"])
def test_ratio_intervals_carry_how_far_the_rounds_stop_from_their_fixed_point(tmp_path, odometer):
    """A 30-vehicle fleet on the second world (road-qc, 200 m) whose rounds stop while the fleet's
    slow modes are still far from settled: each vehicle moves only by more than a fraction of its
    posterior spread, and all the vehicles' ratios moving together contract by a few per cent a
    round, so every vehicle keeps a common error many times the last round's change. The intervals
    carry that distance (the fleet's coupling through the consensus, linearised, solved in its slow
    subspace), divided by the contraction the coupling gives: read off the rounds' trend instead, the
    distance is a fraction of the actual one (exact odometer), and with the world's own odometer
    scale error the rounds' gated, clipped common changes fall along a line that reads K/M as
    contracting by 0.9 a round — a fleet at its fixed point — while its K/M stands several tenths of
    a per cent off, all vehicles alike; either way this fleet's K/M intervals hold the truth for few
    of its vehicles. One fleet is one draw of its common error: the seed is the case both were found
    on, and the coverage over seeds is in the report (``tests/test_ratio_coverage.py`` pins it on
    small fleets)."""
    sc = dataclasses.replace(SCENARIOS["road-qc"], route_length_m=200.0)
    settings = EXACT_ODOMETER if odometer == "exact" else ivp.WorldSettings()
    truth = ivp.generate(sc, tmp_path, seed=6, passes=30, noise_pct=2.0, progress=False, workers=1,
                         settings=settings)
    h = Harness(load_site(tmp_path / "site.toml"))
    h.replay([read_drive_log(p) for p in list_drive_logs(tmp_path / "logs")])
    h.settle()
    rows = h.cloud.vehicle_rows()
    z = {}
    for r in rows:
        true = to_calibration(truth["vehicle_model"], truth["vehicles"][r["vehicle_id"]])[r["param"]]
        z.setdefault(r["param"], []).append(np.log(r["mean"] / true) / (np.log(r["hi95"] / r["lo95"]) / (2 * 1.96)))
    covered = {p: float(np.mean(np.abs(v) <= 1.96)) for p, v in z.items()}
    rms = float(np.sqrt(np.mean(np.square(np.concatenate(list(z.values()))))))
    print(f"ratio interval coverage, ivp seed 6, {odometer} odometer: {covered}, rms error/sd {rms:.2f}")
    assert len(covered) == 4
    for p, c in covered.items():
        # 30 vehicles sharing one common error: a covering interval holds nearly all of them or few
        assert c >= 0.9, (p, c)
    assert rms >= 0.3  # not huge: as tests/test_ratio_coverage.py
