"""The second world's vehicles: equations of motion written from the parameters, as first-order-ready matrices.

Displacements are measured from static equilibrium on a flat rigid surface, up positive, so the
equations read M q̈ + C q̇ + K q = G (kc ⊙ y), y the surface under each tyre. They are assembled
here from free-body diagrams (suspension forces between attachment points and axles), not taken
from ``shared.vehicles``; a test checks both derivations agree.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

GRAVITY_MPS2 = 9.81


class Eom(NamedTuple):
    """One vehicle's linear equations of motion and what its logger measures."""

    M: np.ndarray  # (n, n) diagonal mass / inertia
    C: np.ndarray  # (n, n)
    K: np.ndarray  # (n, n) tyres included
    G: np.ndarray  # (n, n_tyres): tyre i's spring joins DOF row G[:, i] to the surface
    kc: np.ndarray  # (n_tyres,) tyre stiffness, N/m
    offsets_m: np.ndarray  # (n_tyres,) tyre position ahead of the centre of gravity, m
    static_loads_n: np.ndarray  # (n_tyres,) weight on each tyre, N (pushing down)
    channels: tuple[tuple[str, int, str], ...]  # (name, dof, 'acc' | 'vel')


def quarter_car_eom(p: dict[str, float]) -> Eom:
    """Body bounce zb and axle hop za. Suspension force F = K(zb − za) + c(żb − ża):
    M z̈b = −F;  m z̈a = F − k(za − y)."""
    M, m, K, k, c = p["M"], p["m"], p["K"], p["k"], p["c"]
    return Eom(
        M=np.diag([M, m]),
        C=c * np.array([[1.0, -1.0], [-1.0, 1.0]]),
        K=np.array([[K, -K], [-K, K + k]]),
        G=np.array([[0.0], [1.0]]),
        kc=np.array([k]),
        offsets_m=np.zeros(1),
        static_loads_n=np.array([GRAVITY_MPS2 * (M + m)]),
        channels=(("body_acc", 0, "acc"),),
    )


def half_car_eom(p: dict[str, float]) -> Eom:
    """Body bounce u and pitch θ (leading end up positive), axle hops a1 (front, +D1) and a2 (rear, −D2).

    Suspension i joins body point zi (z1 = u + D1 θ, z2 = u − D2 θ) to axle ai with force
    Fi = Ksi (zi − ai) + Csi (żi − ȧi):  ms ü = −F1 − F2;  Is θ̈ = −D1 F1 + D2 F2;
    mui äi = Fi − Kti (ai − yi).
    """
    D1, D2 = p["D1"], p["D2"]
    # Each suspension's extension as a row over (u, θ, a1, a2); its stiffness adds Ks·rowᵀrow.
    r1 = np.array([1.0, D1, -1.0, 0.0])
    r2 = np.array([1.0, -D2, 0.0, -1.0])
    K = p["Ks1"] * np.outer(r1, r1) + p["Ks2"] * np.outer(r2, r2) + np.diag([0.0, 0.0, p["Kt1"], p["Kt2"]])
    C = p["Cs1"] * np.outer(r1, r1) + p["Cs2"] * np.outer(r2, r2)
    G = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    # Body weight shared by lever rule between the suspensions, plus each axle's own.
    front = GRAVITY_MPS2 * (p["ms"] * D2 / (D1 + D2) + p["mu1"])
    rear = GRAVITY_MPS2 * (p["ms"] * D1 / (D1 + D2) + p["mu2"])
    return Eom(
        M=np.diag([p["ms"], p["Is"], p["mu1"], p["mu2"]]),
        C=C,
        K=K,
        G=G,
        kc=np.array([p["Kt1"], p["Kt2"]]),
        offsets_m=np.array([D1, -D2]),
        static_loads_n=np.array([front, rear]),
        channels=(("body_acc", 0, "acc"), ("body_pitch_rate", 1, "vel")),
    )


EOMS = {"quarter_car": quarter_car_eom, "half_car": half_car_eom}


def vehicle_eom(model: str, params: dict[str, float]) -> Eom:
    """The equations of motion of a road vehicle ``model`` with ``params`` (interfaces.md §1 names)."""
    if model not in EOMS:
        raise ValueError(f"the ivp world simulates {', '.join(EOMS)}; got vehicle model {model!r}")
    return EOMS[model](params)
