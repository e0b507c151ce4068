"""2-DOF bogie half-car: a rigid bogie on two spring–dampers resting on the rail (§3.5.3, App. A.3)."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np

from .base import Channel, Vehicle, VehicleSystem
from .half_car import two_point_matrix


@dataclasses.dataclass(frozen=True)
class BogieHalfCar(Vehicle):
    """Body ``ms`` (kg), pitch inertia ``Is`` (kg·m²), springs ``K1, K2`` (N/m) and dampers
    ``C1, C2`` (N·s/m) at ``D1`` ahead of / ``D2`` behind the centre of gravity (Table 3.2).

    The springs and dampers act directly between body and surface, so the profile enters through
    both its elevation and its rate: the inverse solves a first-order ODE per wheel.
    """

    model: ClassVar[str] = "bogie_half_car"
    nonnegative: ClassVar[tuple[str, ...]] = ("C1", "C2")
    ms: float
    Is: float
    K1: float
    K2: float
    C1: float
    C2: float
    D1: float
    D2: float

    def system(self) -> VehicleSystem:
        return VehicleSystem(
            M=np.diag([self.ms, self.Is]),
            C=two_point_matrix(self.C1, self.C2, self.D1, self.D2),
            K=two_point_matrix(self.K1, self.K2, self.D1, self.D2),
            G=np.array([[1.0, 1.0], [self.D1, -self.D2]]),
            kc=np.array([self.K1, self.K2]),
            cc=np.array([self.C1, self.C2]),
            offsets_m=np.array([self.D1, -self.D2]),
            translational=np.array([True, False]),
            channels=(Channel("body_acc", 0, "acc"), Channel("body_pitch_rate", 1, "vel")),
        )


def table_3_2(ms: float = 32e3) -> "BogieHalfCar":
    """The Table 3.2 vehicle for a given body mass (Is = 61.6·ms kg·m², thesis-notes errata)."""
    return BogieHalfCar(ms=ms, Is=61.6 * ms, K1=0.73e6, K2=0.73e6, C1=7.5e3, C2=7.5e3, D1=8.5, D2=8.5)
