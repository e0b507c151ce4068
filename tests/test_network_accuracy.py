"""The network's field drives against the same roads driven as clean single-route passes with the same
coverage.

The reference is fair: the clean pass of each field pass's vehicle and route, cropped to the
chainage the field pass covers (`tests.network_diagnosis.matched_clean`), so what differs is what
field data costs — map-matched chainage, the logger's orientation, speed changes, resampling — not
how many passes cover a point. Both with the vehicles' true parameters (nominal calibration), so the
fleet calibration's own error stays out. Truth is read here only, to score.

With 2–3 passes per route one noise draw moves a route's error by tens of per cent on either side, so
a ratio of two single draws says little about what field data cost. The comparison is therefore of
the mean error over several noise draws, each added alike to the field passes (as the edge cut them
from the drives) and to the clean ones, run in process; the drives themselves go once through
``driveby run`` over Zenoh, end to end.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from shared.registry import load_site
from shared.sensors import add_noise
from simfleet.harness import run_in_process
from simfleet.run import run
from cloud.daemon.settings import CloudSettings
from tests.network_diagnosis import matched_clean, network_passes, score_routes

SEED = 0
RATIO = 1.2  # the goal: within 1.2x of the clean passes
#: Noise draws the mean error is taken over. Each is added on top of the simulation's own 2 % noise,
#: the same process on both sides (2 % of each pass channel's std), so the comparison is at ~2.8 %.
DRAWS = 4
NOISE_PCT = 2.0


@pytest.fixture(scope="module")
def sims(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("network_accuracy")
    for name, out in (("network", tmp / "net"), ("network-clean", tmp / "clean")):
        r = subprocess.run([sys.executable, "-m", "simfleet", "sim", name, "--out", str(out), "--seed", str(SEED),
                            "--nominal", "true"], capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr
    return tmp


def test_field_drives_run_end_to_end_over_zenoh(sims):
    """Every pass the drives hold goes through ``driveby run`` and every route the clean passes score
    is scored from the field drives too."""
    tmp = sims
    res = run(tmp / "net" / "logs", tmp / "net" / "site.toml", tmp / "export", calibration="nominal", progress=False)
    assert res.passes >= 8 and res.acked == res.passes
    _, passes, _ = network_passes(tmp / "net")  # the passes driveby run cut, for their coverage
    run_in_process(matched_clean(tmp / "clean", passes), load_site(tmp / "clean" / "site.toml"), tmp / "matched",
                   CloudSettings(calibration="nominal"))
    truth = json.loads((tmp / "net" / "truth.json").read_text())
    field, clean = score_routes(tmp / "export", truth), score_routes(tmp / "matched", truth)
    for rid, ref in clean.items():
        print(f"{rid}: field {field.get(rid)}\n    clean {ref}")
        if "profile_stretch_frame" in ref:
            assert np.isfinite(field.get(rid, {}).get("profile_stretch_frame", np.nan)), rid


def _noisy(passes, rng):
    return [dataclasses.replace(p, channels={k: add_noise(v, NOISE_PCT, rng).astype(np.float32)
                                             for k, v in p.channels.items()}) for p in passes]


@pytest.fixture(scope="module")
def mean_scores(sims):
    """Per route, the mean over :data:`DRAWS` noise draws of each score, field and clean."""
    tmp = sims
    site, passes, _ = network_passes(tmp / "net")
    clean_passes = matched_clean(tmp / "clean", passes)
    clean_site = load_site(tmp / "clean" / "site.toml")
    truth = json.loads((tmp / "net" / "truth.json").read_text())
    runs = {"field": [], "clean": []}
    for d in range(DRAWS):
        for name, ps, st in (("field", passes, site), ("clean", clean_passes, clean_site)):
            out = tmp / f"{name}-draw{d}"
            run_in_process(_noisy(ps, np.random.default_rng(1000 + d)), st, out, CloudSettings(calibration="nominal"))
            runs[name].append(score_routes(out, truth))
    out = {}
    for name, rs in runs.items():
        out[name] = {rid: {key: float(np.mean([r.get(rid, {}).get(key, np.inf) for r in rs]))
                           for key in ("profile_stretch_frame", "iri_median") if key in rs[0][rid]}
                     for rid in rs[0]}
    return out["field"], out["clean"]


@pytest.mark.xfail(strict=True, reason=(
    "open: R1's and R3's profile. Over noise draws the field drives' mean profile error on R1 (the drives' "
    "GNSS dropout: chainage beyond a shift and a stretch) and on R3 exceeds 1.2x the clean passes'; R2's and "
    "R4's profile and both IRIs are within it"))
def test_field_drives_are_within_1p2x_of_the_same_coverage_driven_clean(mean_scores):
    field, clean = mean_scores
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
