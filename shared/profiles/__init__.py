"""Road profiles: ISO 8608 random profiles, the tyre-contact filter and the 3-D lane 'carpet'."""

from .carpet import (
    LANE_SPACING_M,
    N_LANES,
    SD_LANES,
    Carpet,
    carpet_profile,
    draw_lane,
    lane_probabilities,
)
from .iso8608 import (
    ISO8608_GD0,
    N0,
    TYRE_WINDOW_M,
    WAVINESS,
    RoadProfile,
    iso8608_profile,
    iso8608_psd,
    tyre_filter,
)

__all__ = [
    "ISO8608_GD0",
    "LANE_SPACING_M",
    "N0",
    "N_LANES",
    "SD_LANES",
    "TYRE_WINDOW_M",
    "WAVINESS",
    "Carpet",
    "RoadProfile",
    "carpet_profile",
    "draw_lane",
    "iso8608_profile",
    "iso8608_psd",
    "lane_probabilities",
    "tyre_filter",
]
