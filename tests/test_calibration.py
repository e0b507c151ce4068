"""Fleet self-calibration: the vehicle step's pieces, and the whole loop through the real system."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from cloud.calibration import (PassAp, PassRemap, calibration_names, class_prior, fit_vehicle,
                               from_calibration, to_calibration)
from shared.dynamics.forward import simulate_on_profile
from shared.dynamics.inverse import InverseStream, build_inverse
from shared.profiles import iso8608_profile, tyre_filter
from shared.vehicles import QuarterCar
from simfleet.scenarios import SCENARIOS, TABLE_4_1
from simfleet.sim import generate

QC = dict(M=4450.0, m=420.0, K=5.0e5, k=1.95e6, c=2.0e4)


def test_ratios_round_trip_and_names():
    assert calibration_names("quarter_car") == ["m/M", "K/M", "k/M", "c/M"]
    assert calibration_names("half_car")[-2:] == ["D1", "D2"]
    cal = to_calibration("quarter_car", QC)
    assert cal["K/M"] == pytest.approx(5e5 / 4450)
    back = from_calibration("quarter_car", cal, 4450.0)
    assert back == pytest.approx(QC)
    mu, sd = class_prior("quarter_car", TABLE_4_1["mean"], TABLE_4_1["std"])
    assert np.all(sd > 0.1) and mu.shape == (4,)


def _pass_ap(params, profile, speed=20.0):
    """One noise-free pass of a quarter-car: its AP on a 0.05 m grid under ``params``."""
    truth = QuarterCar(**QC)
    r = simulate_on_profile(truth.system(), profile.at, profile.slope, 5.0, speed, 8.0, 0.002)
    ap = InverseStream(build_inverse(QuarterCar(**params).system(), 0.002),
                       r.initial_inverse_state()).update(r.channels)[:, 0]
    grid = np.arange(200, 3000)
    vals = np.interp(grid * 0.05, r.x_cg, ap)
    return PassAp(200, 0.05, vals[:, None], speed), profile.at(grid * 0.05)[:, None]


def test_vehicle_step_recovers_true_ratios_from_a_wrong_start():
    profile = tyre_filter(iso8608_profile(300.0, 0.01, "A", seed=4))
    wrong = {**QC, "K": 5.5e5, "k": 1.8e6, "c": 2.3e4, "m": 450.0}
    ap, consensus = _pass_ap(wrong, profile)
    # Remap exactness: under the parameters the AP was made with, it reproduces itself.
    remap = PassRemap("quarter_car", wrong, ap, ap.values)
    assert np.sqrt(np.mean(remap.residual(wrong) ** 2)) < 1e-6
    prior = class_prior("quarter_car", TABLE_4_1["mean"], TABLE_4_1["std"])
    fit = fit_vehicle("quarter_car", wrong, [(ap, consensus)], prior, QC["M"])
    true = to_calibration("quarter_car", QC)
    for name, mean, lo, hi in zip(fit.names, fit.mean, fit.lo95, fit.hi95):
        assert mean == pytest.approx(true[name], rel=0.01), name
        assert lo <= mean <= hi


@pytest.fixture(scope="module")
def small_fleet(tmp_path_factory):
    out = tmp_path_factory.mktemp("fleet")
    generate(SCENARIOS["road-qc"], out, seed=11, passes=10, vehicles=10, workers=1, progress=False)
    return out


def test_fleet_calibration_through_the_system_beats_the_class_prior(small_fleet, tmp_path):
    res = subprocess.run([sys.executable, "-m", "shared.cli", "run", "--logs", str(small_fleet / "logs"),
                          "--site", str(small_fleet / "site.toml"), "--export", str(tmp_path / "out"),
                          "--calibration", "fleet"], capture_output=True, text=True, timeout=900,
                         stdin=subprocess.DEVNULL)
    assert res.returncode == 0, res.stderr
    truth = json.loads((small_fleet / "truth.json").read_text())
    from simfleet.evaluate import score_profile, score_vehicles

    scores = score_vehicles(tmp_path / "out", truth)
    assert set(scores) == {"m/M", "K/M", "k/M", "c/M"}
    prior = {n: float(np.median([abs(to_calibration("quarter_car", TABLE_4_1["mean"])[n]
                                     / to_calibration("quarter_car", v)[n] - 1) for v in truth["vehicles"].values()]))
             for n in scores}
    for name, (median, worst) in scores.items():
        assert median < 0.6 * prior[name], (name, median, prior[name])
        assert worst < 0.15, (name, worst)
    assert score_profile(tmp_path / "out", truth).rel_error < 0.05
