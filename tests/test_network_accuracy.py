"""The network's field drives through ``driveby run`` (Zenoh, the real daemons) against the same roads
driven as clean single-route passes with the same coverage.

The reference is fair: the clean pass of each field pass's vehicle and route, cropped to the
chainage the field pass covers (`tests.network_diagnosis.matched_clean`), so what differs is what
field data costs — map-matched chainage, the logger's orientation, speed changes, resampling — not
how many passes cover a point. Both with the vehicles' true parameters (nominal calibration), so the
fleet calibration's own error stays out. Truth is read here only, to score.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from shared.registry import load_site
from simfleet.harness import run_in_process
from simfleet.run import run
from cloud.daemon.settings import CloudSettings
from tests.network_diagnosis import matched_clean, network_passes, score_routes

SEED = 0
RATIO = 1.2  # the goal: within 1.2x of the clean passes


@pytest.fixture(scope="module")
def scores(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("network_accuracy")
    for name, out in (("network", tmp / "net"), ("network-clean", tmp / "clean")):
        r = subprocess.run([sys.executable, "-m", "simfleet", "sim", name, "--out", str(out), "--seed", str(SEED),
                            "--nominal", "true"], capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr
    res = run(tmp / "net" / "logs", tmp / "net" / "site.toml", tmp / "export", calibration="nominal", progress=False)
    assert res.passes >= 8 and res.acked == res.passes
    _, passes, _ = network_passes(tmp / "net")  # the passes driveby run cut, for their coverage
    run_in_process(matched_clean(tmp / "clean", passes), load_site(tmp / "clean" / "site.toml"), tmp / "matched",
                   CloudSettings(calibration="nominal"))
    truth = json.loads((tmp / "net" / "truth.json").read_text())
    return score_routes(tmp / "export", truth), score_routes(tmp / "matched", truth)


@pytest.mark.xfail(strict=True, reason=(
    "open: R1's profile. With the logger's vertical from the gyro and gravity from the standstills, R2-R4 "
    "and both IRIs are within 1.2x of the clean passes; on R1 the truth's chainage alone already misses "
    "1.2x with sensor noise but not without it (this seed's noise over 2-3 partial passes, not a "
    "systematic field step), and the edge's chainage beyond a shift and a stretch (R1 holds the drives' "
    "GNSS dropout) adds the rest"))
def test_field_drives_are_within_1p2x_of_the_same_coverage_driven_clean(scores):
    field, clean = scores
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
