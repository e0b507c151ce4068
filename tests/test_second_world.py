"""The issue-19 goals that hold on the second (ivp) world as on simfleet's, on small fast versions.

Each case is simulated in both worlds from the same scenario and seed and run through the same edge
and cloud code (in process, default fleet calibration, 2 % noise); the second world's figure is
held to simfleet's, or to the project's stated target. Goals that do not hold on the second world
yet (the 95 % band and intervals' coverage, the default run under an odometer scale error) are
reported by ``driveby reproduce robustness``, not pinned here.
"""

from __future__ import annotations

import dataclasses

import pytest

from simfleet import sim
from simfleet.reproduce_robustness import run_and_score
from simfleet.scenarios import SCENARIOS
from simfleet.worlds import ivp

SEED = 1
PASSES = 12
# A 120 m road: one 100 m IRI segment and the 0.5–50 m profile band after the 10 m trims.
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
    assert b <= 1.2 * max(a, 0.005)  # below 0.5 % both are at the noise floor of 12 passes


def test_vehicle_ratios_are_as_accurate_as_on_simfleets_world(road):
    a, b = road["simfleet"]["vehicles"]["median_error"], road["ivp"]["vehicles"]["median_error"]
    print(f"ratio median |error|: simfleet {a}, ivp {b}")
    for param in ("K/M", "k/M", "c/M", "m/M"):
        # The independent worlds read every ratio within 1.2 % (30 passes); 12 passes of
        # as many vehicles calibrate each from one pass, so 2 % holds the same goal at this size.
        assert b[param] <= 0.02, param


def test_iri_is_as_accurate_as_on_simfleets_world(road):
    a, b = road["simfleet"]["iri10"], road["ivp"]["iri10"]
    print(f"IRI (10 m): simfleet {a}, ivp {b}")
    assert b["n_segments"] >= 10
    # The independent worlds read IRI within 0.4 % (100 m); 10 m segments of 12 passes
    # carry more noise, so the median is held to 1 % and to simfleet's own within 1.5×.
    assert b["median_rel_error"] <= max(0.01, 1.5 * a["median_rel_error"])
