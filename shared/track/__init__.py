"""Railway track on discrete three-layer supports, random support stiffness, rail irregularity, bridge span."""

from .model import (
    BridgeSpan,
    Track,
    TrackParams,
    band_to_dense,
    beam_on_elastic_foundation,
    build_track,
    damaged_ei_factor,
    static_rail_deflection,
)
from .random_fields import GERMAN_HIGH, GERMAN_LOW, RailIrregularity, stiffness_factors

__all__ = [
    "BridgeSpan", "GERMAN_HIGH", "GERMAN_LOW", "RailIrregularity", "Track", "TrackParams", "band_to_dense",
    "beam_on_elastic_foundation", "build_track", "damaged_ei_factor", "static_rail_deflection",
    "stiffness_factors",
]
