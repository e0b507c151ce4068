"""2-D 4-axle railway carriage: body, two bogies, four wheelsets (thesis §3.2.1, eq. 3.1–3.8, Table 3.1).

Ten DOFs; with the wheels following the rail (no separation) the wheelset displacements are the
apparent profile under each wheel, and the body and bogies form a 6-DOF system driven through the
primary suspensions (eq. 3.5) — the :class:`~shared.vehicles.VehicleSystem` the inverse works on.
The full 10-DOF matrices (:meth:`Carriage.full_matrices`) are what the train–track model couples to
the rail.

DOF order (ours; the thesis orders them u_v, u_b1, u_b2, θ_v, θ_b1, θ_b2):
``[u_v, θ_v, u_b1, θ_b1, u_b2, θ_b2]`` and, for the full model, then ``[w1, w2, w3, w4]``.
Bogie 1 leads, at +Lv ahead of the body's centre of gravity; wheel 1 leads (at +Lv + Lb). Pitch is
positive when the leading end rises (interfaces.md §1).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar, NamedTuple

import numpy as np

from .base import GRAVITY, Channel, Vehicle, VehicleSystem

#: Measured channels of a carriage (interfaces.md §1), in order: bogie accelerations and pitch rates.
CHANNELS = (
    Channel("bogie1_acc", 2, "acc"),
    Channel("bogie1_pitch_rate", 3, "vel"),
    Channel("bogie2_acc", 4, "acc"),
    Channel("bogie2_pitch_rate", 5, "vel"),
)


class FullMatrices(NamedTuple):
    """The 10-DOF carriage: M q̈ + C q̇ + K q = E (λ − P), q from static equilibrium on a flat rigid rail.

    λ (4,) is the upward contact force on each wheel and P (4,) its static value (N), so the
    right-hand side is the dynamic part of the wheel–rail force.
    """

    M: np.ndarray  # (10, 10)
    C: np.ndarray  # (10, 10)
    K: np.ndarray  # (10, 10)
    E: np.ndarray  # (10, 4): wheel i's DOF is 6 + i
    static_wheel_loads_n: np.ndarray  # (4,) P, N, positive pushing down on the rail
    offsets_m: np.ndarray  # (4,) wheel position ahead of the body's centre of gravity, m


@dataclasses.dataclass(frozen=True)
class Carriage(Vehicle):
    """Parameters of Table 3.1 (SI units), with symmetric suspensions and bogies.

    ``mv, Iv``: body mass (kg) and pitch inertia (kg·m²); ``mb, Ib``: each bogie; ``mw``: each
    wheelset (kg); ``kp, cp``: primary suspension per wheelset (N/m, N·s/m); ``ks, cs``: secondary
    suspension per bogie; ``Lb``: bogie centre to wheelset (m); ``Lv``: body centre to bogie pivot
    (m); ``v``: speed (m/s), a run property carried with the vehicle (interfaces.md §1).
    """

    model: ClassVar[str] = "carriage"
    nonnegative: ClassVar[tuple[str, ...]] = ("cp", "cs")
    mv: float
    Iv: float
    mb: float
    Ib: float
    mw: float
    kp: float
    cp: float
    ks: float
    cs: float
    Lb: float
    Lv: float
    v: float

    def _body_bogie(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """M, C, K of body and bogies with the wheels held still, and G (6, 4) to the wheel points."""
        Lv, Lb = self.Lv, self.Lb
        # Secondary suspension j joins the body point u_v ± Lv·θ_v to bogie j's centre.
        s1 = np.array([1.0, Lv, -1.0, 0.0, 0.0, 0.0])
        s2 = np.array([1.0, -Lv, 0.0, 0.0, -1.0, 0.0])
        K = self.ks * (np.outer(s1, s1) + np.outer(s2, s2))
        C = self.cs * (np.outer(s1, s1) + np.outer(s2, s2))
        # Primary suspension i joins a bogie point (u_b ± Lb·θ_b) to wheelset i.
        G = np.zeros((6, 4))
        G[2, 0], G[3, 0] = 1.0, Lb
        G[2, 1], G[3, 1] = 1.0, -Lb
        G[4, 2], G[5, 2] = 1.0, Lb
        G[4, 3], G[5, 3] = 1.0, -Lb
        K += self.kp * (G @ G.T)
        C += self.cp * (G @ G.T)
        M = np.diag([self.mv, self.Iv, self.mb, self.Ib, self.mb, self.Ib])
        return M, C, K, G

    def wheel_offsets_m(self) -> np.ndarray:
        """Wheel positions ahead of the body's centre of gravity, m (wheel 1 leads)."""
        Lv, Lb = self.Lv, self.Lb
        return np.array([Lv + Lb, Lv - Lb, -Lv + Lb, -Lv - Lb])

    def system(self) -> VehicleSystem:
        """The 6-DOF system with the wheels on the rail (eq. 3.1–3.8): contacts are the primary
        suspensions, so the apparent profile enters through its elevation and its rate."""
        M, C, K, G = self._body_bogie()
        return VehicleSystem(
            M=M,
            C=C,
            K=K,
            G=G,
            kc=np.full(4, self.kp),
            cc=np.full(4, self.cp),
            offsets_m=self.wheel_offsets_m(),
            translational=np.array([True, False, True, False, True, False]),
            channels=CHANNELS,
        )

    def axle_loads_n(self) -> np.ndarray:
        """Static wheelset loads on the rail, N (body and bogie share by the lever rule, plus mw·g)."""
        return self.system().static_contact_forces() + self.mw * GRAVITY

    def full_matrices(self) -> FullMatrices:
        """The 10-DOF matrices with the wheelsets as DOFs 6..9 (for coupling to a flexible track)."""
        M6, C6, K6, G = self._body_bogie()
        M = np.zeros((10, 10))
        C = np.zeros((10, 10))
        K = np.zeros((10, 10))
        M[:6, :6], C[:6, :6], K[:6, :6] = M6, C6, K6
        M[6:, 6:] = self.mw * np.eye(4)
        # The primary spring's other end is the wheelset rather than the prescribed profile.
        K[:6, 6:], K[6:, :6], K[6:, 6:] = -self.kp * G, -self.kp * G.T, self.kp * np.eye(4)
        C[:6, 6:], C[6:, :6], C[6:, 6:] = -self.cp * G, -self.cp * G.T, self.cp * np.eye(4)
        E = np.zeros((10, 4))
        E[6:, :] = np.eye(4)
        return FullMatrices(M, C, K, E, self.axle_loads_n(), self.wheel_offsets_m())


#: Table 3.1 of the thesis (Iwnicki, 1998).
TABLE_3_1 = dict(
    mv=32.4e3, Iv=1.99e6, mb=2615.0, Ib=1476.0, mw=1813.0, kp=2.4e6, cp=7e3, ks=0.86e6, cs=16e3,
    Lb=1.28, Lv=9.5, v=33.0,
)


def table_3_1(**changes: float) -> Carriage:
    """The Table 3.1 carriage, with optional changes (e.g. a run's ``mv``, ``Iv``, ``v``)."""
    return Carriage(**{**TABLE_3_1, **changes})
