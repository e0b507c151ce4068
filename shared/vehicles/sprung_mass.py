"""Sprung mass on a spring (thesis §2.2.1.1, eq. 2.1–2.2)."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np

from .base import Channel, Vehicle, VehicleSystem


@dataclasses.dataclass(frozen=True)
class SprungMass(Vehicle):
    """Mass ``m`` (kg) on a spring ``k`` (N/m) that rests on the surface."""

    model: ClassVar[str] = "sprung_mass"
    m: float
    k: float

    def system(self) -> VehicleSystem:
        return VehicleSystem(
            M=np.array([[self.m]]),
            C=np.zeros((1, 1)),
            K=np.array([[self.k]]),
            G=np.ones((1, 1)),
            kc=np.array([self.k]),
            cc=np.zeros(1),
            offsets_m=np.zeros(1),
            translational=np.array([True]),
            channels=(Channel("body_acc", 0, "acc"),),
        )
