"""Bridge estimation end to end under the issue's conditions: simfleet → edge + cloud cores
(fleet self-calibration, in process) → cloud.bridge.

Conditions (issue #5, "Show"): 30 quarter-car passes (Table 4.1 fleet, 15–22 m/s), 2 % sensor
noise, smooth deck as the thesis; the drive logs carry the class-mean parameters and each pass's AP
is computed with the vehicle's *fleet calibration* (the parameters the bridge estimator is given);
the wheel-load prior is the registry's class (its mean mass fixes the scale, §4.5.5). No truth
reaches the estimator; it is read here only to score.
"""

from __future__ import annotations

import functools
import tempfile
from pathlib import Path

import numpy as np
import pytest

from simfleet.reproduce_bridge import estimate_case, simulate_case, true_effective, true_ratio

PASSES = 30
WORK = Path(tempfile.mkdtemp(prefix="test-bridge-"))


@functools.lru_cache(maxsize=None)
def estimate(name: str):
    case = simulate_case(name, WORK, passes=PASSES, seed=0)
    e, _ = estimate_case(case)
    return e, case


def test_healthy_bridge_reads_within_one_and_a_half_points_and_raises_no_alarm():
    """Issue: mean stiffness ratio within ±1.5 points, no alarm. (Every element within ±5 points
    does not hold yet: measured up to 10–11 points, a smooth bump along the span that the
    calibrated vehicles' residual model error leaves; with the vehicles' true ratios it is ~3
    points. Some elements' 95 % intervals miss the truth by a little.)"""
    e, case = estimate("bridge-healthy")
    post = e.posterior
    truth = true_ratio(case)
    assert post.n_passes == PASSES
    assert abs(np.mean(post.stiffness_ratio) - np.mean(truth)) < 0.015, post.stiffness_ratio
    assert abs(post.effective_ratio - true_effective(case)) < 0.015, post.effective_ratio
    assert not e.assessment.alarm, (e.assessment.best, e.assessment.loss_probability)


def test_global_loss_is_measured_within_one_and_a_half_points():
    """Issue: mean stiffness loss within ±1.5 points (measured 10.5 % for 10 %). The area-weighted
    'effective' loss and D2 read 7.7 % (±2.2 %, 1σ): inside its 95 % interval, not within ±1.5."""
    e, case = estimate("bridge-global10")
    post = e.posterior
    assert abs(np.mean(post.stiffness_ratio) - np.mean(true_ratio(case))) < 0.015, post.stiffness_ratio
    eff_true = true_effective(case)
    assert abs(post.effective_ratio - eff_true) < 1.96 * post.effective_ratio_sd
    assert e.assessment.alarm


def test_the_dynamics_carry_the_information_the_quasi_static_model_misses():
    """The profile likelihood of the global level (dynamic excess recomputed at every level) is
    several times sharper than the quasi-static posterior, and closer to the truth."""
    e, case = estimate("bridge-global10")
    qs = e.quasi_static
    assert e.level is not None
    assert e.level.sd < 0.6 * qs.effective_ratio_sd
    truth = true_effective(case)
    assert abs(e.posterior.effective_ratio - truth) < abs(qs.effective_ratio - truth)


@pytest.mark.parametrize("name", ["bridge-healthy"])
def test_estimate_rows_follow_the_export_contract(name):
    import json

    e, _ = estimate(name)
    rows = e.element_rows()
    assert len(rows) == e.bridge.n_elements
    assert set(rows[0]) == {"bridge_id", "element", "x_start_m", "x_end_m", "EI_mean", "EI_lo95", "EI_hi95",
                            "stiffness_ratio"}
    assert all(r["EI_lo95"] <= r["EI_mean"] <= r["EI_hi95"] for r in rows)
    assert set(e.summary_row()) == {"bridge_id", "n_passes", "D1_pct", "D2_pct", "midspan_mril", "damaged"}
    assert e.bearing_rows() == []
    json.dumps(e.summary_row())
