"""``driveby status``'s answer and its text, from a real cloud core over a site with a bridge (the
transport is exercised by tests/test_deploy_recipe.py)."""

from __future__ import annotations

import json

from cloud.daemon.core import Cloud
from cloud.daemon.node import status_body
from cloud.daemon.settings import CloudSettings
from shared.registry import load_site
from simfleet.control import format_status, sum_stats
from simfleet.scenarios import SCENARIOS, fleet_class
from simfleet.sim import write_site


def test_a_clouds_status_names_its_passes_counters_vehicles_and_bridges(tmp_path):
    scenario = SCENARIOS["bridge-crack10-10m"]
    write_site(scenario, tmp_path / "site.toml", *fleet_class(scenario))
    cloud = Cloud("t", load_site(tmp_path / "site.toml"), lambda k, p: None, CloudSettings(calibration="fleet"),
                  node_id="c1")
    body = json.loads(json.dumps(status_body(cloud, "c1"), allow_nan=False))  # what travels: strict JSON
    assert body["id"] == "c1" and body["net"] == "t" and body["passes"] == 0 and body["vehicles"] == []
    assert body["stats"]["accepted"] == 0 and body["stats"]["rejected"] == {}
    assert list(body["bridges"]) == ["B1"] and body["bridges"]["B1"]["assessment"] is None
    text = format_status(body)
    assert text.splitlines()[0].startswith("cloud c1 (net t): 0 passes")
    assert "segments: 0 accepted, 0 rejected" in text and "vehicles: 0" in text
    assert "bridge B1: 0 passes, D1 n/a %, no alarm" in text

    # An assessed, alarmed bridge and rejections as the cloud reports them (queries.bridge_state's keys).
    b = body["bridges"]["B1"]
    b["summary"].update(n_passes=40, D1_pct=-3.2, damaged=True)
    b["assessment"] = {"probabilities": {"healthy": 0.01, "crack": 0.99}, "best": "crack", "alarm": True,
                       "loss_probability": 0.99, "kind": "crack", "element": 10, "location_m": 10.5,
                       "severity": 0.18}
    body["stats"]["rejected"] = {"bad_key": 2, "stale_calibration": 1}
    body["vehicles"] = [f"veh-{i:04d}" for i in range(1, 11)]
    text = format_status(body)
    assert "segments: 0 accepted, 3 rejected (bad_key 2, stale_calibration 1)" in text
    assert "vehicles: 10 (veh-0001," in text and ", …)" in text
    assert "bridge B1: 40 passes, D1 -3.20 %, DAMAGED; P(damage) 0.990, best crack, element 10" in text


def test_counters_of_several_clouds_add_up_by_reason():
    total = sum_stats([{"accepted": 3, "rejected": {"a": 1}}, {"accepted": 4, "rejected": {"a": 2, "b": 1}}])
    assert total == {"accepted": 7, "rejected": {"a": 3, "b": 1}}
