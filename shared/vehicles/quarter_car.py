"""Quarter-car: body on a suspension, axle on a tyre (thesis §4.2, App. B.3, eq. B.22–B.25)."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np

from .base import Channel, Vehicle, VehicleSystem


@dataclasses.dataclass(frozen=True)
class QuarterCar(Vehicle):
    """Body ``M`` and axle ``m`` (kg), suspension ``K`` and tyre ``k`` (N/m), damping ``c`` (N·s/m).

    DOFs: body bounce, axle hop. (B.25) as printed swaps a term; the stiffness matrix used here is
    the correct ``[[K, −K], [−K, K + k]]`` (thesis-notes errata).
    """

    model: ClassVar[str] = "quarter_car"
    nonnegative: ClassVar[tuple[str, ...]] = ("c",)
    M: float
    m: float
    K: float
    k: float
    c: float

    def system(self) -> VehicleSystem:
        K, k, c = self.K, self.k, self.c
        return VehicleSystem(
            M=np.diag([self.M, self.m]),
            C=np.array([[c, -c], [-c, c]]),
            K=np.array([[K, -K], [-K, K + k]]),
            G=np.array([[0.0], [1.0]]),
            kc=np.array([k]),
            cc=np.zeros(1),
            offsets_m=np.zeros(1),
            translational=np.array([True, True]),
            channels=(Channel("body_acc", 0, "acc"),),
        )
