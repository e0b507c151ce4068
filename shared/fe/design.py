"""A registry bridge as a finite-element beam: its design, as the drawings give it."""

from __future__ import annotations

import numpy as np

from ..registry import Bridge
from .beam import Beam


def design_beam(bridge: Bridge, ei_factor: np.ndarray | None = None,
                krot: tuple[float, float] | None = None) -> Beam:
    """The registry bridge as an FE :class:`~shared.fe.beam.Beam`: its span, elements, E·I (times
    ``ei_factor`` per element, design stiffness if None), mass, damping and depth; simply supported,
    or on rotational springs ``krot`` (left, right; N·m/rad) if given."""
    supports = "simply_supported" if krot is None else "rotational_springs"
    return Beam(span_m=bridge.span_m, n_elements=bridge.n_elements, E_pa=bridge.E_pa, I_m4=bridge.I_m4,
                mass_per_m=bridge.mass_per_m, damping_ratio=bridge.damping_ratio, supports=supports,
                krot_nm_per_rad=krot, ei_factor=ei_factor, depth_m=bridge.depth_m)


def registry_krot(bridge: Bridge) -> tuple[float, float] | None:
    """The bearings' rotational stiffness (left, right; N·m/rad) the registry declares: None for
    simple supports. ValueError for ``rotational_springs`` without ``krot_nm_per_rad``."""
    if bridge.supports != "rotational_springs":
        return None
    if bridge.krot_nm_per_rad is None:
        raise ValueError(f"bridge {bridge.id!r}: krot_nm_per_rad: needed to simulate rotational_springs bearings")
    return (bridge.krot_nm_per_rad, bridge.krot_nm_per_rad)
