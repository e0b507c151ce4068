"""4-DOF half-car: body bounce and pitch, two axles on tyres (thesis §2.2.1.2, eq. 2.3–2.9, Table 2.1)."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np

from .base import Channel, Vehicle, VehicleSystem


def two_point_matrix(k1: float, k2: float, d1: float, d2: float) -> np.ndarray:
    """Stiffness (or damping) of two vertical springs at +d1 and −d2 on a body with DOFs (u, θ)."""
    return np.array([[k1 + k2, d1 * k1 - d2 * k2], [d1 * k1 - d2 * k2, d1 * d1 * k1 + d2 * d2 * k2]])


@dataclasses.dataclass(frozen=True)
class HalfCar(Vehicle):
    """Parameters of Table 2.1; pitch positive when the leading end (axle 1, at +D1) rises.

    DOFs: body bounce u, body pitch θ, axle 1 hop, axle 2 hop.
    """

    model: ClassVar[str] = "half_car"
    nonnegative: ClassVar[tuple[str, ...]] = ("Cs1", "Cs2")
    ms: float
    Is: float
    mu1: float
    mu2: float
    Ks1: float
    Ks2: float
    Cs1: float
    Cs2: float
    Kt1: float
    Kt2: float
    D1: float
    D2: float

    def system(self) -> VehicleSystem:
        D1, D2 = self.D1, self.D2
        # Each suspension joins body point (u ± Dθ) to its axle: assemble from the attachment vectors.
        e1 = np.array([1.0, D1, -1.0, 0.0])
        e2 = np.array([1.0, -D2, 0.0, -1.0])
        K = self.Ks1 * np.outer(e1, e1) + self.Ks2 * np.outer(e2, e2)
        C = self.Cs1 * np.outer(e1, e1) + self.Cs2 * np.outer(e2, e2)
        K[2, 2] += self.Kt1
        K[3, 3] += self.Kt2
        G = np.zeros((4, 2))
        G[2, 0] = G[3, 1] = 1.0
        return VehicleSystem(
            M=np.diag([self.ms, self.Is, self.mu1, self.mu2]),
            C=C,
            K=K,
            G=G,
            kc=np.array([self.Kt1, self.Kt2]),
            cc=np.zeros(2),
            offsets_m=np.array([D1, -D2]),
            translational=np.array([True, False, True, True]),
            channels=(Channel("body_acc", 0, "acc"), Channel("body_pitch_rate", 1, "vel")),
        )


#: Table 2.1 of the thesis.
TABLE_2_1 = dict(
    ms=16200.0, Is=93457.0, mu1=700.0, mu2=1100.0, Ks1=4e5, Ks2=1e6, Cs1=1e4, Cs2=2e4,
    Kt1=1.75e6, Kt2=3.5e6, D1=2.375, D2=2.375,
)
