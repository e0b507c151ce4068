"""The network's field drives against the same roads driven as clean single-route passes with the same
coverage.

The reference is fair: the clean pass of each field pass's vehicle and route, cropped to the
chainage the field pass covers (`tests.network_diagnosis.matched_clean`), so what differs is what
field data costs — map-matched chainage, the logger's orientation, speed changes, resampling — not
how many passes cover a point nor how fast they drive (each clean pass cruises at its vehicle's field
trip's cruise speed). Both with the vehicles' true parameters (nominal calibration), so the
fleet calibration's own error stays out. Truth is read here only, to score.

With 2–3 passes per route one noise draw moves a route's error by tens of per cent on either side, so
a ratio of two single draws says little about what field data cost. The comparison is therefore of
the mean error over several noise draws, each added alike to the field passes (as the edge cut them
from the drives) and to the clean ones, run in process; the drives themselves go once through
``driveby run`` over Zenoh, end to end.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from shared.registry import load_site
from simfleet.run import run
from tests.network_diagnosis import DRAWS, draw_scores, matched_clean, mean_scores, network_passes, score_routes

SEED = 0
RATIO = 1.2  # the goal: within 1.2x of the clean passes


@pytest.fixture(scope="module")
def sims(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("network_accuracy")
    # The two worlds side by side: independent simulations, one process each.
    procs = [subprocess.Popen([sys.executable, "-m", "simfleet", "sim", name, "--out", str(out), "--seed", str(SEED),
                               "--nominal", "true"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for name, out in (("network", tmp / "net"), ("network-clean", tmp / "clean"))]
    for p in procs:
        _, err = p.communicate(timeout=600)
        assert p.returncode == 0, err
    return tmp


def test_clean_passes_drive_at_their_vehicles_field_cruise(sims):
    """The reference differs from the field in what a drive brings, not in speed: every clean pass
    drives at the cruise speed of its vehicle's field trip of the same seed."""
    field = json.loads((sims / "net" / "truth.json").read_text())
    clean = json.loads((sims / "clean" / "truth.json").read_text())
    cruise = {}
    for trip in field["passes"]:
        cruise.setdefault(trip["vehicle_id"], trip["cruise_mps"])
    assert len(set(cruise.values())) == len(cruise) > 1  # distinct speeds: a mix-up of vehicles would show
    assert {p["vehicle_id"] for p in clean["passes"]} == set(cruise)
    for p in clean["passes"]:
        assert p["speed_mps"] == cruise[p["vehicle_id"]], p["pass_id"]


@pytest.fixture(scope="module")
def draws(sims):
    """Per noise draw (:data:`tests.network_diagnosis.DRAWS` of them, each added on top of the
    simulation's own 2 % noise, the same process on both sides), the scores of the field passes as
    the edge cut them from the drives and of the coverage-matched clean passes, run in process."""
    tmp = sims
    site, passes, _ = network_passes(tmp / "net")
    truth = json.loads((tmp / "net" / "truth.json").read_text())
    return draw_scores(passes, site, matched_clean(tmp / "clean", passes), load_site(tmp / "clean" / "site.toml"),
                       truth, tmp / "draws", DRAWS), passes


def test_field_drives_run_end_to_end_over_zenoh(sims, draws):
    """Every pass the drives hold goes through ``driveby run`` and every route the clean passes score
    is scored from the field drives too."""
    tmp = sims
    runs, passes = draws
    res = run(tmp / "net" / "logs", tmp / "net" / "site.toml", tmp / "export", calibration="nominal", progress=False)
    assert res.passes == len(passes) >= 8 and res.acked == res.passes
    truth = json.loads((tmp / "net" / "truth.json").read_text())
    field = score_routes(tmp / "export", truth)
    for rid, ref in runs["clean"][0].items():  # the first draw's clean passes: the same coverage
        print(f"{rid}: field {field.get(rid)}\n    clean {ref}")
        if "profile_stretch_frame" in ref:
            assert np.isfinite(field.get(rid, {}).get("profile_stretch_frame", np.nan)), rid


@pytest.fixture(scope="module")
def mean_scores_(draws):
    """Per route, the mean over the noise draws of each score, field and clean."""
    runs, _ = draws
    return mean_scores(runs["field"]), mean_scores(runs["clean"])


@pytest.mark.xfail(strict=True, reason=(
    "open: R1's profile: the drive's accelerometer bias, known from the GNSS track to millimetres per second "
    "squared, still bends a long pass's chainage by centimetres beyond a shift and a stretch. R2's, R3's and "
    "R4's profile and both IRIs are within it (R1's IRI barely)"))
def test_field_drives_are_within_1p2x_of_the_same_coverage_driven_clean(mean_scores_):
    field, clean = mean_scores_
    for rid in sorted(clean):
        print(f"{rid}: field {field.get(rid)}\n    clean {clean[rid]}")
    worse = []
    for rid, ref in clean.items():
        got = field.get(rid, {})
        if "profile_stretch_frame" not in ref:
            continue
        # The fleet's frame: no data place a route in the registry's frame better than the mean of
        # its passes' GNSS errors (metres/sqrt(passes)); the comparison is of the road's shape. Where
        # no pass links two stretches of a route, each has its own passes' frame, so the frame is
        # fitted to the scored stretch alone.
        if not got.get("profile_stretch_frame", float("inf")) <= RATIO * ref["profile_stretch_frame"]:
            worse.append(f"{rid} profile {got.get('profile_stretch_frame')} vs {ref['profile_stretch_frame']:.3f}")
        if "iri_median" in ref and not got.get("iri_median", float("inf")) <= max(RATIO * ref["iri_median"], 0.02):
            # 2 %: below it the 100 m IRI of 2-3 partial passes is within the clean fleet's own scatter
            worse.append(f"{rid} IRI {got.get('iri_median')} vs {ref['iri_median']:.3f}")
    assert not worse, "; ".join(worse)
