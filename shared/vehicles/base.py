"""What every vehicle model provides: validated parameters and its linear system (M, C, K, contacts)."""

from __future__ import annotations

import abc
import dataclasses
import math
from typing import ClassVar, NamedTuple

import numpy as np

GRAVITY = 9.81  # m/s²


class Channel(NamedTuple):
    """A measured channel: the ``kind`` ('acc' or 'vel') of degree of freedom ``dof``."""

    name: str
    dof: int
    kind: str


class VehicleSystem(NamedTuple):
    """A vehicle as a linear system driven by the profile under its contacts.

    Equation of motion (displacements from static equilibrium on a flat rigid surface, up positive):

        M q̈ + C q̇ + K q = G (kc ⊙ y + cc ⊙ ẏ)

    where y (n_contacts,) is the surface elevation under each contact and ``G[:, i]`` maps the
    vehicle's DOFs to the bottom of contact spring i (so K contains G diag(kc) Gᵀ).
    """

    M: np.ndarray  # (n, n) kg, kg·m²
    C: np.ndarray  # (n, n) N·s/m
    K: np.ndarray  # (n, n) N/m
    G: np.ndarray  # (n, n_contacts) dimensionless or m (for rotations)
    kc: np.ndarray  # (n_contacts,) contact spring stiffness, N/m
    cc: np.ndarray  # (n_contacts,) contact damping, N·s/m
    offsets_m: np.ndarray  # (n_contacts,) contact position ahead of the centre of gravity, m
    translational: np.ndarray  # (n,) bool: DOF moves vertically (feels gravity)
    channels: tuple[Channel, ...]  # what a logger measures, in order

    @property
    def n_dof(self) -> int:
        return self.M.shape[0]

    @property
    def n_contacts(self) -> int:
        return self.G.shape[1]

    def static_contact_forces(self) -> np.ndarray:
        """Static wheel loads (N, positive pushing down on the surface) under gravity."""
        f_g = -GRAVITY * np.diag(self.M) * self.translational
        q_static = np.linalg.solve(self.K, f_g)
        return -self.kc * (self.G.T @ q_static)  # the weight compresses the contact springs


@dataclasses.dataclass(frozen=True)
class Vehicle(abc.ABC):
    """Base of the vehicle parameter sets: every field is a positive finite number (SI units)."""

    model: ClassVar[str]
    #: Fields allowed to be zero (e.g. damping).
    nonnegative: ClassVar[tuple[str, ...]] = ()

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            try:
                x = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"{self.model}.{f.name}: must be a number, got {value!r}") from None
            if not math.isfinite(x):
                raise ValueError(f"{self.model}.{f.name}: must be finite, got {value!r}")
            if f.name in self.nonnegative:
                if x < 0:
                    raise ValueError(f"{self.model}.{f.name}: must be >= 0, got {value!r}")
            elif x <= 0:
                raise ValueError(f"{self.model}.{f.name}: must be > 0, got {value!r}")
            object.__setattr__(self, f.name, x)

    @classmethod
    def param_names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def from_params(cls, params: dict[str, float]) -> "Vehicle":
        """Build from a name → value mapping (interfaces.md §1 names); unknown or missing names raise."""
        names = set(cls.param_names())
        unknown = sorted(set(params) - names)
        if unknown:
            raise ValueError(f"{cls.model}: unknown parameter(s) {', '.join(unknown)}")
        missing = sorted(names - set(params))
        if missing:
            raise ValueError(f"{cls.model}: missing parameter(s) {', '.join(missing)}")
        return cls(**{k: params[k] for k in cls.param_names()})

    def params(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def replace(self, **changes: float) -> "Vehicle":
        return dataclasses.replace(self, **changes)

    @abc.abstractmethod
    def system(self) -> VehicleSystem:
        """The model's linear system (every model defines it)."""
