"""Vehicle parameter sets: validation at the boundary and the matrices of the thesis."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.vehicles import MODELS, BogieHalfCar, HalfCar, QuarterCar, SprungMass, vehicle_from_params
from shared.vehicles.base import GRAVITY
from shared.vehicles.bogie import table_3_2
from shared.vehicles.carriage import table_3_1
from shared.vehicles.half_car import TABLE_2_1

QC = dict(M=4450.0, m=420.0, K=5.0e5, k=1.95e6, c=2.0e4)


@pytest.mark.parametrize("field", list(QC))
@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf, "x"])
def test_invalid_parameters_name_the_field(field, bad):
    if field == "c" and bad == -1.0:
        pass  # damping may be zero but not negative: still rejected below
    with pytest.raises(ValueError, match=rf"quarter_car\.{field}"):
        QuarterCar(**{**QC, field: bad})


def test_zero_mass_rejected_zero_damping_allowed():
    with pytest.raises(ValueError, match="quarter_car.M: must be > 0"):
        QuarterCar(**{**QC, "M": 0.0})
    assert QuarterCar(**{**QC, "c": 0.0}).c == 0.0


def test_from_params_rejects_unknown_and_missing():
    with pytest.raises(ValueError, match="unknown parameter"):
        vehicle_from_params("quarter_car", {**QC, "zz": 1.0})
    with pytest.raises(ValueError, match="missing parameter"):
        vehicle_from_params("quarter_car", {k: v for k, v in QC.items() if k != "k"})
    with pytest.raises(ValueError, match="vehicle_model: unknown model"):
        vehicle_from_params("tricycle", QC)


def test_quarter_car_matrices_match_b23_b25_with_errata():
    s = QuarterCar(**QC).system()
    assert np.allclose(s.M, np.diag([4450, 420]))
    assert np.allclose(s.C, [[2e4, -2e4], [-2e4, 2e4]])
    assert np.allclose(s.K, [[5e5, -5e5], [-5e5, 5e5 + 1.95e6]])  # (B.25) corrected


def test_half_car_matrices_match_eq_2_4_to_2_6():
    h = HalfCar(**TABLE_2_1)
    s = h.system()
    D1, D2 = h.D1, h.D2
    K = np.array([
        [h.Ks1 + h.Ks2, D1 * h.Ks1 - D2 * h.Ks2, -h.Ks1, -h.Ks2],
        [D1 * h.Ks1 - D2 * h.Ks2, D1**2 * h.Ks1 + D2**2 * h.Ks2, -D1 * h.Ks1, D2 * h.Ks2],
        [-h.Ks1, -D1 * h.Ks1, h.Ks1 + h.Kt1, 0],
        [-h.Ks2, D2 * h.Ks2, 0, h.Ks2 + h.Kt2],
    ])
    C = np.array([
        [h.Cs1 + h.Cs2, D1 * h.Cs1 - D2 * h.Cs2, -h.Cs1, -h.Cs2],
        [D1 * h.Cs1 - D2 * h.Cs2, D1**2 * h.Cs1 + D2**2 * h.Cs2, -D1 * h.Cs1, D2 * h.Cs2],
        [-h.Cs1, -D1 * h.Cs1, h.Cs1, 0],
        [-h.Cs2, D2 * h.Cs2, 0, h.Cs2],
    ])
    assert np.allclose(s.K, K) and np.allclose(s.C, C)
    assert np.allclose(s.M, np.diag([h.ms, h.Is, h.mu1, h.mu2]))


@pytest.mark.parametrize("vehicle", [SprungMass(m=15000, k=3.5e6), QuarterCar(**QC), HalfCar(**TABLE_2_1), table_3_2()])
def test_static_wheel_loads_carry_the_weight(vehicle):
    s = vehicle.system()
    total = GRAVITY * float(np.sum(np.diag(s.M) * s.translational))
    loads = s.static_contact_forces()
    assert np.all(loads > 0)
    assert loads.sum() == pytest.approx(total, rel=1e-12)
    if isinstance(vehicle, HalfCar):  # lever rule for the body, axle masses on their own axles
        share = vehicle.ms * GRAVITY / (vehicle.D1 + vehicle.D2)
        assert loads[0] == pytest.approx(share * vehicle.D2 + vehicle.mu1 * GRAVITY, rel=1e-12)
        assert loads[1] == pytest.approx(share * vehicle.D1 + vehicle.mu2 * GRAVITY, rel=1e-12)


def test_every_model_round_trips_its_params():
    for name, cls in MODELS.items():
        v = {"sprung_mass": SprungMass(m=1.0, k=2.0), "quarter_car": QuarterCar(**QC),
             "half_car": HalfCar(**TABLE_2_1), "bogie_half_car": table_3_2(), "carriage": table_3_1()}[name]
        assert vehicle_from_params(name, v.params()) == v
        assert isinstance(v, cls)
    assert isinstance(table_3_2(), BogieHalfCar)
    assert table_3_2(30e3).Is == pytest.approx(61.6 * 30e3)
