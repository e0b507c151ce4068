"""The Cramér–Rao machinery: sensitivities by finite differences of the coupled simulation, and the
Fisher information with the wheel loads marginalised."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from cloud.bridge.information import (FD_STEP, PassCase, PassSensitivity, crack_jacobian, fleet_information,
                                      noise_sd_of, pass_sensitivity)
from shared.fe.beam import Beam, crack_ei_factor
from shared.vbi import simulate_vbi
from shared.vehicles import QuarterCar

QC = dict(M=4450.0, m=420.0, K=5.0e5, k=1.95e6, c=2.0e4)
BEAM = Beam(20.0, 4, 35e9, 1.25, 37500.0)  # coarse: the test is about the bookkeeping


def _channel(beam, params, speed=18.0):
    flat = lambda x: np.zeros_like(np.asarray(x, dtype=float))  # noqa: E731
    s = QuarterCar(**params).system()
    return simulate_vbi(s, flat, flat, 0.0, speed, 50.0 / speed, 1 / 500.0, beam=beam, bridge_start_m=5.0,
                        gamma=0.5).channels[:, 0]


def test_element_sensitivities_add_up_to_the_global_one_and_the_load_is_a_scale():
    case = PassCase("v1", "quarter_car", QC, 18.0, 1e-3)
    s = pass_sensitivity(case, BEAM)
    g = 2 * FD_STEP  # the response is far from linear over 1 % (the phase of the vibration moves)
    stiff = _channel(dataclasses.replace(BEAM, ei_factor=np.full(4, math.exp(g))), QC)
    base = _channel(BEAM, QC)
    direct = (stiff - base) / g / case.noise_sd
    summed = s.S.sum(axis=1)
    assert np.linalg.norm(summed - direct) < 0.02 * np.linalg.norm(direct)
    # Heavier vehicle, same dynamics: the bridge part of the response scales with the load.
    heavy = {k: v * 1.01 for k, v in QC.items()}
    diff = (_channel(BEAM, heavy) - base) / math.log(1.01) / case.noise_sd
    assert np.linalg.norm(diff - s.s_w) < 0.02 * np.linalg.norm(s.s_w)
    assert FD_STEP < 0.01


def test_marginalising_the_loads_costs_information_and_the_prior_bounds_the_cost():
    rng = np.random.default_rng(0)
    n, ne = 200, 4
    sens = []
    for p in range(6):
        S = rng.standard_normal((n, ne))
        s_w = S.sum(axis=1) * -1.0 + 0.3 * rng.standard_normal(n)  # load and stiffness nearly confounded
        sens.append(PassSensitivity(PassCase(f"v{p % 3}", "quarter_car", QC, 18.0, 1.0), S, s_w))
    known = fleet_information(sens, 1e-9).F  # loads known: no loss
    free = fleet_information(sens, 1e9).F  # loads unknown
    mid = fleet_information(sens, 0.09).F
    raw = sum(s.S.T @ s.S for s in sens)
    assert np.allclose(known, raw, rtol=1e-6)
    one = np.ones(ne)
    assert one @ free @ one < one @ mid @ one < one @ known @ one
    info = fleet_information(sens, 0.09)
    assert math.isclose(info.scaled(12).global_sd(), info.global_sd() / math.sqrt(2), rel_tol=1e-9)


def test_crack_jacobian_matches_the_crack_factor():
    T = crack_jacobian(20, 20.0, 1.0, 10.0, 0.1)
    assert np.allclose(T[:, 2], 1.0)
    th = lambda x, p: np.log(crack_ei_factor(20, 20.0, 1.0, x, p))  # noqa: E731
    d = th(10.0, 0.101) - th(10.0, 0.1)
    assert np.allclose(T[:, 1] * 0.001, d, atol=2e-4)
    assert np.count_nonzero(np.abs(T[:, 1]) > 1e-6) == 4  # ±1.5 depths around a node: four elements


def test_noise_sd_is_the_percentage_of_the_clean_signal():
    rng = np.random.default_rng(1)
    clean = np.sin(np.linspace(0, 60, 20000))
    noisy = clean + 0.02 * np.std(clean) * rng.standard_normal(clean.size)
    assert math.isclose(noise_sd_of(noisy, 2.0), 0.02 * np.std(clean), rel_tol=0.01)
