"""The issue-19 goals that hold on the second (ivp) world as on simfleet's, on small fast versions.

Each case is simulated in both worlds from the same scenario and seed and run through the same edge
and cloud code (in process, default fleet calibration, 2 % noise); the second world's figure is
held to simfleet's, or to the project's stated target (the vehicle ratio intervals' coverage with an
exact odometer: one fleet in ``tests/test_second_world_fleet.py`` with the bridge, a module apart so
the two run side by side; small fleets over seeds in ``tests/test_ratio_coverage.py``). Goals
that do not hold on the second world yet (the 95 % band's coverage, the ratio intervals' under an
odometer scale error, the default run under it) are reported by ``driveby reproduce robustness``,
not pinned here.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from cloud.road.calibration import PassAp, class_prior, fit_vehicle, to_calibration
from cloud.road.continuous import continuous_ap
from shared.drivelog import list_drive_logs, read_drive_log
from shared.dynamics.inverse import InverseStream, build_inverse, edge_gamma
from shared.vehicles import QuarterCar
from simfleet import sim
from simfleet.reproduce_robustness import run_and_score
from simfleet.scenarios import SCENARIOS, TABLE_4_1
from simfleet.worlds import ivp

SEED = 0
# 30 passes as the figures: with fewer, the fleet calibration's common mode (how far all
# ratios move together) scatters from seed to seed in either world, and the profile error with it.
PASSES = 30
# A 120 m road: the 0.5–50 m profile band after the 10 m trims, and ten 10 m IRI segments.
ROAD = dataclasses.replace(SCENARIOS["road-qc"], name="road-qc", route_length_m=120.0)
# The odometer's per-run scale error stretches each pass's chainage (1 % is 1.2 m over the road):
# the default run does not align passes yet, so the road goals are checked with an exact odometer.
EXACT_ODOMETER = ivp.WorldSettings(speed_error_sd=0.0)


@pytest.fixture(scope="module")
def road(tmp_path_factory):
    out = {}
    for world, generate, kw in (("simfleet", sim.generate, {}), ("ivp", ivp.generate, {"settings": EXACT_ODOMETER})):
        d = tmp_path_factory.mktemp(world)
        generate(ROAD, d, seed=SEED, passes=PASSES, noise_pct=2.0, progress=False, workers=1, **kw)
        out[world] = run_and_score(d, d / "export")
    return out


def test_road_profile_error_is_within_1_2x_of_simfleets_world(road):
    a, b = road["simfleet"]["profile"]["rel_error"], road["ivp"]["profile"]["rel_error"]
    print(f"profile error: simfleet {a:.4f}, ivp {b:.4f}")
    assert b <= 1.2 * max(a, 0.005)  # below 0.5 % both are at the noise floor of 30 passes


def test_vehicle_ratios_are_as_accurate_as_on_simfleets_world(road):
    a, b = road["simfleet"]["vehicles"]["median_error"], road["ivp"]["vehicles"]["median_error"]
    print(f"ratio median |error|: simfleet {a}, ivp {b}")
    for param in ("K/M", "k/M", "c/M", "m/M"):
        # The project's target for the median ratio error (docs/results.md). The tighter figure the
        # issue quotes is one reading: seed by seed, the fleet calibration's common mode moves every
        # ratio together by more than that in either world.
        assert b[param] <= 0.03, param


def test_iri_is_as_accurate_as_on_simfleets_world(road):
    a, b = road["simfleet"]["iri10"], road["ivp"]["iri10"]
    print(f"IRI (10 m): simfleet {a}, ivp {b}")
    assert b["n_segments"] >= 10
    # simfleet's world and the independent ones read the 100 m IRI within 0.5 %; a 10 m
    # segment averages a tenth of the road, so its error is up to ~√10 × larger (≈ 1.6 %): 2 %.
    assert b["median_rel_error"] <= 0.02


def test_the_vehicle_step_is_unbiased_on_the_second_worlds_physics(tmp_path):
    """The second world's physics and logger (RK4 at 20 kHz, the anti-alias FIR and its resampling on
    the logger's own clock, a start mid-motion) against the edge's discretised inverse, the cloud's
    continuous-time correction and the vehicle step: noise-free, one pass, the true profile as the
    consensus and the true parameters as the start, what the step finds is the model error every
    vehicle would share. A fleet-common ratio error on that world therefore comes from the consensus
    the fleet fits against, not from this chain (nor from the logger's filter)."""
    sc = dataclasses.replace(SCENARIOS["road-qc"], route_length_m=200.0)
    # No speed wobble: the step's time base is one speed per pass, and this test is about the physics.
    ivp.generate(sc, tmp_path, seed=3, passes=1, vehicles=1, noise_pct=0.0, nominal="true", progress=False, workers=1,
                 settings=ivp.WorldSettings(speed_error_sd=0.0, wobble=0.0))
    truth = json.loads((tmp_path / "truth.json").read_text())
    log = read_drive_log(list_drive_logs(tmp_path / "logs")[0])
    params = truth["vehicles"][log.meta.vehicle_id]
    inverse = build_inverse(QuarterCar(**params).system(), 1.0 / log.meta.sample_rate_hz,
                            gamma=edge_gamma("quarter_car"))
    ap = InverseStream(inverse).update(np.asarray(log.channels["body_acc"], float)[:, None])[:, 0]
    h = 0.05
    grid = np.arange(int(round(20.0 / h)), int(round(190.0 / h)))  # past the inverse's warm-up
    speed = float(np.mean(log.speed))
    edge = PassAp(int(grid[0]), h, np.interp(grid * h, log.chainage, ap)[:, None], speed)
    fixed = PassAp(edge.start_index, h, continuous_ap("quarter_car", params, edge), speed)
    p = truth["profile"]
    road = np.interp(grid * h, p["start_m"] + p["spacing_m"] * np.arange(len(p["elevation_m"])), p["elevation_m"])
    prior = class_prior("quarter_car", TABLE_4_1["mean"], TABLE_4_1["std"])
    fit = fit_vehicle("quarter_car", params, [(fixed, road[:, None])], prior, params["M"], ap_gamma=0.5)
    want = to_calibration("quarter_car", params)
    bias = {n: m / want[n] - 1.0 for n, m in zip(fit.names, fit.mean)}
    print(f"vehicle step on the ivp world's physics, noise-free, true profile: {bias}")
    # The same bound as on simfleet's physics (tests/test_discretisation.py): the chain's own error.
    assert max(abs(e) for e in bias.values()) < 0.005, bias
