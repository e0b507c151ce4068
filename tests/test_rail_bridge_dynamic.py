"""The load regression with the carriage's dynamic wheel forces (cloud.rail.bridge.static_equivalent), on the
train–track–bridge simulator's own AP under each wheel (no inverse, no calibration: the physics alone), the
forces from the cloud's carriage model over that AP (cloud.rail.bridge.dynamic_wheel_forces). The
simulator's contact forces and its track are read here only, to score."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.linalg import cho_solve_banded, cholesky_banded
from scipy.signal import butter, sosfiltfilt

from cloud.bridge.mril import MrIl
from cloud.rail.bridge import (FORCE_MIN_WAVELENGTH_M, GRID_M, MIN_WAVELENGTH_M, RunAp, ap_compliance,
                               dynamic_wheel_forces, influence_of_aps)
from shared.dynamics.train_track import simulate_train_track
from shared.vehicles.carriage import Carriage
from simfleet.rail import SUBSTEPS, TRACK_BEFORE_M, draw_carriage, draw_runs, irregularity_of, track_of
from simfleet.reproduce_rail import scenario_of

SEED = 2
N_RUNS = 12


@pytest.fixture(scope="module")
def batch():
    """A quick blind-test world (40 m approach, the healthy 10.2 m span): each run's AP under the leading
    bogie's wheels as the simulator has it, with the cloud model's dynamic forces over it, and the
    simulator's own contact forces less the static loads."""
    scenario = scenario_of(7, 2, quick=True)
    track, irr = track_of(scenario, SEED), irregularity_of(scenario, SEED)
    carriage = draw_carriage(scenario, SEED)
    runs, contact = [], []
    for i, run in enumerate(draw_runs(scenario, N_RUNS, SEED)):
        car = Carriage(**carriage, mv=run["mv"], Iv=run["Iv"], v=run["v"])
        dt = 1.0 / (scenario.sample_rate_hz * SUBSTEPS)
        duration = (scenario.route_length_m + float(-car.wheel_offsets_m().min())) / car.v
        resp = simulate_train_track(car, track, irr.elevation, TRACK_BEFORE_M, duration, dt)
        ap, W = resp.ap[::SUBSTEPS], float(car.axle_loads_n()[0])
        runs.append(RunAp(f"r{i}", ap[:, :2], dt * SUBSTEPS, 0.0, car.wheel_offsets_m()[:2], car.v, W,
                          dynamic_wheel_forces(car, ap, dt * SUBSTEPS)[:, :2]))
        contact.append(resp.contact_force_n[::SUBSTEPS, :2] - W)
    return scenario, track, carriage, runs, contact


def static_line(scenario, track, carriage, x_m: np.ndarray) -> np.ndarray:
    """The track's and span's static line under the leading bogie's two static wheel loads, per unit load,
    each wheel relative to its chord between the supports, low-passed as the regression's (what the load
    regression should find), on ``x_m`` from the first support."""
    b = scenario.bridge
    car = Carriage(**carriage, mv=32.4e3, Iv=1.99e6, v=30.0)
    off, W = car.wheel_offsets_m(), car.axle_loads_n()
    L = cholesky_banded(track.K, lower=True)
    x = np.arange(-10.0, b.span_m + 10.0 + 1e-9, GRID_M)
    y = np.empty((len(x), 2))
    for k, xk in enumerate(x):
        dofs, vals = track.contact_entries(TRACK_BEFORE_M + b.start_m + xk + off - off[0])
        f = np.zeros(track.n_dof)
        np.add.at(f, dofs, -W[:, None] * vals)
        y[k] = ((cho_solve_banded((L, True), f)[dofs] * vals).sum(axis=1) / W)[:2]
    lines = []
    for i, behind in ((0, 0.0), (1, off[0] - off[1])):
        yi = np.interp(x, x - behind, y[:, i])  # at wheel i's own chainage
        y0, y1 = np.interp(0.0, x, yi), np.interp(b.span_m, x, yi)
        lines.append(yi - (y0 + (y1 - y0) * x / b.span_m))
    J = sosfiltfilt(butter(4, GRID_M / (0.5 * MIN_WAVELENGTH_M), output="sos"), -0.5 * (lines[0] + lines[1]))
    J = np.interp(x_m, x, J)
    return J - (J[0] + (J[-1] - J[0]) * x_m / x_m[-1])


def area_error(line: MrIl, truth: np.ndarray) -> float:
    J = line.J - (line.J[0] + (line.J[-1] - line.J[0]) * line.x_m / line.x_m[-1])
    return float(np.trapezoid(J, line.x_m) / np.trapezoid(truth, line.x_m) - 1.0)


def test_dynamic_wheel_forces_are_the_simulators_contact_forces(batch):
    """The carriage model over the AP gives the contact forces the track felt: against the simulator's
    (low-passed alike, after the first second) measured 2.8–4.0 % rms of their dynamic part."""
    *_, runs, contact = batch
    for r, f in zip(runs, contact):
        sos = butter(4, r.speed_mps / FORCE_MIN_WAVELENGTH_M * 2.0 * r.dt_s, output="sos")
        true = sosfiltfilt(sos, f, axis=0)[int(1.0 / r.dt_s):]
        model = r.dynamic_force_n[int(1.0 / r.dt_s):]
        assert np.std(model - true) < 0.1 * np.std(true), r.pass_id


def test_load_regression_with_the_dynamic_forces_finds_the_static_line(batch):
    """The dynamic wheel force follows the run's masses and speed, not only its static load, and the
    chord through the supports takes the track's deflection under it (~0.6 mm under a wheel, more than
    the span's): on the static loads alone the regression's area is off the static line of track and span
    (measured +11.9 % here; +15…+22 % on the blind test's healthy batches of seeds 0/2), with the
    dynamic forces +1.1 %. The AP's compliance beside the span, fitted from the model's forces, is the
    one the simulator's contact forces give (measured −6.1e−9 m/N both ways)."""
    scenario, track, carriage, runs, contact = batch
    b = scenario.bridge
    dynamic = influence_of_aps(runs, b.start_m, b.span_m, dynamic=True)
    static = influence_of_aps(runs, b.start_m, b.span_m)
    truth = static_line(scenario, track, carriage, dynamic.mril.x_m)
    assert abs(area_error(dynamic.mril, truth)) < 0.03
    assert area_error(static.mril, truth) > 0.06  # what the dynamic forces are for, in this world
    with_contact = [dataclasses.replace(r, dynamic_force_n=sosfiltfilt(
        butter(4, r.speed_mps / FORCE_MIN_WAVELENGTH_M * 2.0 * r.dt_s, output="sos"), f, axis=0))
        for r, f in zip(runs, contact)]
    before = b.start_m - (runs[0].offsets_m[0] + 0.5)
    assert dynamic.track_compliance_m_per_n == pytest.approx(ap_compliance(with_contact, b.start_m, min(before, 40.0)), rel=0.1)
    assert -1e-8 < dynamic.track_compliance_m_per_n < -3e-9  # ~0.6 mm under a 97 kN wheel


def test_without_dynamic_force_the_regression_is_the_static_loads(batch):
    """Zero dynamic force leaves every line as the static-load regression has it (the model adds nothing
    of its own)."""
    scenario, *_, runs, _ = batch
    b = scenario.bridge
    zero = [dataclasses.replace(r, dynamic_force_n=np.zeros_like(r.dynamic_force_n)) for r in runs]
    a, s = influence_of_aps(zero, b.start_m, b.span_m, dynamic=True), influence_of_aps(runs, b.start_m, b.span_m)
    np.testing.assert_allclose(a.mril.J, s.mril.J, rtol=0, atol=1e-9 * np.abs(s.mril.J).max())
    np.testing.assert_allclose(a.approach_line.J, s.approach_line.J, rtol=0, atol=1e-9 * np.abs(s.approach_line.J).max())
    assert a.track_compliance_m_per_n == 0.0
