"""Bridge damage from bogie data (cloud.rail_bridge, thesis §3.5–3.6): a healthy and a 13 %-damaged
culvert span under quick batches (10 runs, 40 m approach instead of 50 runs over 120 m)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cloud.bridge.mril import damage_indicators
from cloud.rail_bridge import bogie_influence
from cloud.rail_calibration import RailRun, calibrate_batch
from shared.drivelog import MODEL_CHANNELS, list_drive_logs, read_drive_log
from shared.registry import load_site
from simfleet.rail import RailBridgeSpec
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

N_RUNS = 10


def influence(tmp_path, name, loss):
    scenario = dataclasses.replace(SCENARIOS["rail-bridge-state7-profile1"], route_length_m=70.0,
                                   bridge=RailBridgeSpec(start_m=40.2, global_loss=loss))
    generate(scenario, tmp_path / name, seed=3, passes=N_RUNS, workers=2, progress=False)
    site = load_site(tmp_path / name / "site.toml")
    cls, bridge = site.vehicle_class("carriage"), site.bridges[0]
    runs = []
    for path in list_drive_logs(tmp_path / name / "logs"):
        log = read_drive_log(path)
        z = np.stack([log.channels[c] for c in MODEL_CHANNELS["carriage"]], axis=1).astype(float)
        runs.append(RailRun(log.meta.pass_id, z, log.meta.dt, float(np.mean(log.speed)), float(log.chainage[0])))
    fit = calibrate_batch(runs, cls.mean, cls.std, window_m=(0.0, bridge.start_chainage_m - 2.0))  # off the bridge
    return bogie_influence(runs, fit, cls.mean, bridge.start_chainage_m, bridge.span_m)


def test_damage_level_from_a_healthy_and_a_damaged_batch(tmp_path):
    """Same track and runs, the span's E·I 13 % lower (and 5 % per-element scatter): measured
    D1 13.3 %, D2 13.4 % (seed 3); with 8 runs 19 %, with 16 runs 13.9 % — the spread of a small
    batch. The indicators' bounds are ±5 points here (the blind test's 50 runs: see the report)."""
    healthy = influence(tmp_path, "healthy", 0.0)
    damaged = influence(tmp_path, "damaged", 0.13)
    # Deflection per unit wheel load (m/N) of the order of a 10 m span plus its track: ~1e-8.
    assert 3e-9 < healthy.mril.midspan() < 3e-8
    assert healthy.mril.J[0] == pytest.approx(0.0, abs=0.1 * healthy.mril.midspan())  # zero at the supports
    d = damage_indicators(healthy.mril, damaged.mril)
    assert 8.0 < d.D1_pct < 18.0 and 8.0 < d.D2_pct < 18.0, d
    assert np.ptp(healthy.wheel_load_n) > 0.05 * healthy.wheel_load_n.mean()  # what separates the profile
