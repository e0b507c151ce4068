"""The forward model (shared.dynamics.forward): the inverse returns the AP it was driven by, a batch
is each profile alone, and the contact rate and forces against slow references."""

from __future__ import annotations

import numpy as np
import pytest

from shared.dynamics.forward import (ap_response, channels_from_ap, contact_forces, static_equilibrium,
                                     trapezoid_rate)
from shared.dynamics.inverse import InverseState, InverseStream, build_inverse
from shared.dynamics.newmark import newmark_constants
from shared.vehicles import HalfCar, QuarterCar, SprungMass
from shared.vehicles.bogie import table_3_2
from shared.vehicles.carriage import table_3_1
from shared.vehicles.half_car import TABLE_2_1

DT = 0.002
VEHICLES = {
    "sprung_mass": SprungMass(m=15000.0, k=3.5e6),
    "quarter_car": QuarterCar(M=4450.0, m=420.0, K=5e5, k=1.95e6, c=2e4),
    "half_car": HalfCar(**TABLE_2_1),
    "bogie_half_car": table_3_2(),  # damped contacts: the trapezoidal contact rate matters
    "carriage": table_3_1(),
}


def rough_ap(n: int, n_contacts: int, seed: int) -> np.ndarray:
    """A random-walk profile under each contact (m): rough at every wavelength."""
    return np.cumsum(np.random.default_rng(seed).standard_normal((n, n_contacts)), axis=0) * 1e-4


@pytest.mark.parametrize("name", sorted(VEHICLES))
@pytest.mark.parametrize("gamma", [0.5, 0.6, 0.8])
def test_the_inverse_returns_the_ap_the_forward_model_was_driven_by(name, gamma):
    system = VEHICLES[name].system()
    ap = rough_ap(2000, system.n_contacts, 1)
    c = newmark_constants(DT, gamma)
    state = ap_response(system, ap, c)
    z = channels_from_ap(system, ap, c)
    start = InverseState(state.u[0], state.v[0], state.a[0], ap[0], np.zeros(system.n_contacts))
    back = InverseStream(build_inverse(system, DT, gamma=gamma), start).update(z)
    # The round trip is exact up to rounding, amplified by the inverse's neutral integrators.
    assert np.max(np.abs(back - ap)) <= 1e-8 * np.max(np.abs(ap))


@pytest.mark.parametrize("name", sorted(VEHICLES))
def test_a_batch_of_profiles_is_each_profile_alone_bit_for_bit(name):
    system = VEHICLES[name].system()
    aps = np.stack([rough_ap(500, system.n_contacts, seed) for seed in range(3)])
    c = newmark_constants(DT, 0.5, 0.25)
    batch = ap_response(system, aps, c)
    for k in range(len(aps)):
        alone = ap_response(system, aps[k], c)
        for got, want in zip(batch, alone):
            assert np.array_equal(got[k], want)
    assert np.array_equal(channels_from_ap(system, aps, c)[1], channels_from_ap(system, aps[1], c))


def test_the_vehicle_starts_at_rest_in_static_equilibrium_on_the_first_sample():
    system = VEHICLES["half_car"].system()
    ap = np.full((200, 2), 0.01)  # a level surface 1 cm up: nothing moves
    state = ap_response(system, ap, newmark_constants(DT))
    # Rounding only (relative 1e-10 of the 1 cm offset, after it has gone round the recursion).
    assert np.allclose(state.u, static_equilibrium(system, ap[0]), rtol=0, atol=1e-12)
    assert np.max(np.abs(state.a)) < 1e-9
    assert np.max(np.abs(contact_forces(system, ap, state, DT))) < 1e-6  # N, against a 17.5 kN spring force


def test_trapezoid_rate_is_the_recursion_it_names():
    y = rough_ap(300, 3, 2)
    ydot0 = np.array([0.1, -0.2, 0.3])
    want = np.empty_like(y)
    want[0] = ydot0
    for k in range(1, len(y)):
        want[k] = 2.0 * (y[k] - y[k - 1]) / DT - want[k - 1]
    assert np.array_equal(trapezoid_rate(y, ydot0, DT), want)
    assert np.array_equal(trapezoid_rate(y[:, 0], ydot0[0], DT), want[:, 0])


def test_contact_forces_are_the_springs_and_dampers_between_profile_and_vehicle():
    system = VEHICLES["bogie_half_car"].system()
    ap = rough_ap(400, 2, 3)
    state = ap_response(system, ap, newmark_constants(DT))
    ydot = trapezoid_rate(ap, 0.0, DT)
    want = np.empty_like(ap)
    for k in range(len(ap)):
        for i in range(2):
            stretch = ap[k, i] - system.G[:, i] @ state.u[k]
            rate = ydot[k, i] - system.G[:, i] @ state.v[k]
            want[k, i] = system.kc[i] * stretch + system.cc[i] * rate
    assert np.allclose(contact_forces(system, ap, state, DT), want, rtol=1e-12, atol=1e-9)
