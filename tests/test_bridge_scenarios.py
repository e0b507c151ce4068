"""Bridge estimation end to end on simulated fleets: simfleet → edge (in-process) → cloud.bridge.

The scenarios are small versions of the thesis's (§4.2: 30 quarter-cars, 20 m span, smooth deck):
24 passes of 24 vehicles. Three things are deliberately easier than the thesis's 2 % case, so that
a fast test has the information to check ±1.5 points (measured information limits are in the
module docstrings of :mod:`cloud.bridge.static` and in the report):

* sensor noise 0.25 % instead of 2 % (at 2 % one pass pins the global stiffness to ±27 %, so ±1.5
  points needs ~1000 passes);
* the edge uses each vehicle's TRUE parameters (drive logs written with ``nominal="true"``) —
  fleet calibration is tested elsewhere;
* the wheel-load prior is centred on the fleet's true mean static wheel load — the thesis's
  "known fleet-mean mass" (§4.5.5). With the class mean instead, the global scale also carries the
  fleet's sampling error, 9.2 %/√24 ≈ 1.9 % for 24 vehicles;
* the estimator is told the simulator's vehicle integrator (Newmark γ = 0.8 at 2 kHz,
  :class:`~cloud.bridge.passdata.EdgeSettings`): with the continuous-time default the simulator's
  own 0.4 % error at the body mode, excited by the 9 mm ramp onto the deck, biases passes by up to
  ±25 % (see ``test_bridge_passdata.py``).
"""

from __future__ import annotations

import functools
import json
import tempfile
from pathlib import Path

import numpy as np
import pytest

from cloud.bridge.estimator import BridgeEstimator, BridgeSettings
from cloud.bridge.passdata import EdgeSettings, group_segments
from cloud.bridge.static import WeightPrior
from shared.drivelog import list_drive_logs, read_drive_log
from shared.registry import load_site
from shared.vehicles import vehicle_from_params
from simfleet import sim
from simfleet.replay import chunks_of
from simfleet.scenarios import SCENARIOS

#: the simulated vehicles' true dynamics: Newmark γ = 0.8 at SUBSTEPS × the logger rate
SIM_EDGE = EdgeSettings(vehicle_dt_s=1.0 / (500.0 * sim.SUBSTEPS), vehicle_gamma=0.8)
PASSES = 24
NOISE_PCT = 0.25


@functools.lru_cache(maxsize=None)
def scenario(name: str, passes: int = PASSES, noise_pct: float = NOISE_PCT, seed: int = 3) -> dict:
    """Simulate a scenario, run the edge in-process, and return the segments, site and truth."""
    from edge.node import Edge
    from shared.schema import decode_ap

    out = Path(tempfile.mkdtemp(prefix=f"bridge-{name}-"))
    truth = sim.generate(SCENARIOS[name], out, seed=seed, passes=passes, noise_pct=noise_pct, nominal="true",
                         workers=2, progress=False)
    site = load_site(out / "site.toml")
    segments = []

    def publish(key, payload):
        if "/ap/" in key:
            segments.extend(decode_ap(payload))

    edge = Edge("net", publish, site, "nominal")
    for path in list_drive_logs(out / "logs"):
        for chunk in chunks_of(read_drive_log(path)):
            edge.on_chunk(chunk.encode())
    return {"segments": segments, "site": site, "truth": truth}


def true_mean_prior(case: dict) -> WeightPrior:
    """Wheel-load prior: the fleet's true mean (M + m)·g, sd the class's."""
    truth = case["truth"]
    loads = [float(vehicle_from_params("quarter_car", p).system().static_contact_forces()[0])
             for p in truth["vehicles"].values()]
    vc = case["site"].vehicle_class("quarter_car")
    return WeightPrior(float(np.mean(loads)), float(np.hypot(vc.std["M"], vc.std["m"]) * 9.81))


@functools.lru_cache(maxsize=None)
def estimate(name: str):
    """The bridge estimate of a scenario after all its passes (dynamic model, hypotheses)."""
    case = scenario(name)
    bridge = case["site"].bridges[0]
    est = BridgeEstimator(bridge, true_mean_prior(case), BridgeSettings(edge=SIM_EDGE))
    for (vid, _), segs in group_segments(case["segments"]).items():
        assert est.add_segments(segs, "quarter_car", case["truth"]["vehicles"][vid])
    return est.estimate(), case["truth"]


def test_healthy_bridge_is_recovered_and_raises_no_alarm():
    """Measured: effective stiffness ratio 0.984 ± 0.021. The residual error is the fleet-weight
    scale: the wheel-load prior fixes the *unweighted* fleet mean, but the passes pin each vehicle's
    W·compliance with different precision, so the scale follows a precision-weighted mean of the
    24 true weights (sd ≈ 9 %/√24 ≈ 1.9 %); with the exact weights the same data give 1.009."""
    e, truth = estimate("bridge-healthy")
    post = e.posterior
    assert post.n_passes == PASSES
    assert abs(post.effective_ratio - 1.0) < 0.02, post.effective_ratio
    assert abs(post.effective_ratio - 1.0) < 2.0 * post.effective_ratio_sd
    # Every element's 95 % interval holds the design stiffness (the truth).
    assert np.all(post.ei_lo95 <= post.ei_design) and np.all(post.ei_hi95 >= post.ei_design)
    assert not e.assessment.alarm
    assert e.assessment.loss_probability < 0.5
    # Wheel loads (prior sd 9 %): a few per cent off, and most inside their 95 % intervals.
    loads = {v: vehicle_from_params("quarter_car", p).system().static_contact_forces()[0]
             for v, p in truth["vehicles"].items()}
    rel = [post.weights[v][0] / loads[v] - 1 for v in post.weights]
    assert np.sqrt(np.mean(np.square(rel))) < 0.06
    inside = [abs(post.weights[v][0] - loads[v]) < 1.96 * post.weights[v][1] for v in post.weights]
    assert np.mean(inside) >= 0.8
    assert abs(e.indicators.D2_pct) < 3.0


def test_global_loss_is_measured_within_one_and_a_half_points():
    e, truth = estimate("bridge-global10")
    assert abs((1 - e.posterior.effective_ratio) - 0.10) < 0.015, e.posterior.effective_ratio
    a = e.assessment
    assert a.best == "global"
    lo, hi = a.results["global"].parameters["loss"][1:]
    assert lo <= 0.10 <= hi
    assert a.alarm and a.element == -1


def test_crack_is_located_within_one_element():
    e, truth = estimate("bridge-crack10-10m")
    crack_x, n_e = 10.0, e.bridge.n_elements
    le = e.bridge.span_m / n_e
    weakest = int(np.argmin(e.posterior.stiffness_ratio))  # 0-based element index
    centre = (weakest + 0.5) * le
    assert abs(centre - crack_x) <= 1.5 * le, (weakest, e.posterior.stiffness_ratio)
    a = e.assessment
    assert a.best == "crack" and a.alarm
    assert abs(a.location_m - crack_x) <= le
    assert 0.05 < a.severity < 0.35  # true peak element loss 18 %


def test_the_quasi_static_model_is_biased_where_the_dynamic_one_is_not():
    """Per-element freedom lets the bridge's dynamics masquerade as stiffness variations."""
    e, _ = estimate("bridge-global10")
    qs, dyn = e.quasi_static, e.posterior
    truth = np.full(e.bridge.n_elements, 0.9)
    err = lambda p: float(np.sqrt(np.mean((p.stiffness_ratio - truth) ** 2)))  # noqa: E731
    assert err(dyn) < err(qs)
    assert dyn.chi2_per_point < qs.chi2_per_point


@pytest.mark.parametrize("name", ["bridge-healthy"])
def test_estimate_rows_follow_the_export_contract(name):
    e, _ = estimate(name)
    rows = e.element_rows()
    assert len(rows) == e.bridge.n_elements
    assert set(rows[0]) == {"bridge_id", "element", "x_start_m", "x_end_m", "EI_mean", "EI_lo95", "EI_hi95",
                            "stiffness_ratio"}
    assert all(r["EI_lo95"] <= r["EI_mean"] <= r["EI_hi95"] for r in rows)
    assert set(e.summary_row()) == {"bridge_id", "n_passes", "D1_pct", "D2_pct", "midspan_mril", "damaged"}
    assert e.bearing_rows() == []
    json.dumps(e.summary_row())
