"""A rail run's record as the rail estimators take it: the four bogie channels, their step, the
reported speed and the chainage of the first sample."""

from __future__ import annotations

import dataclasses
import math

import numpy as np


@dataclasses.dataclass(frozen=True)
class RailRun:
    """One run's measured bogie channels (n, 4) in ``bogie1_acc, bogie1_pitch_rate, bogie2_acc,
    bogie2_pitch_rate`` order at step ``dt`` (s), its reported speed (m/s) and the chainage of the
    body's centre of gravity at the first sample (m)."""

    pass_id: str
    channels: np.ndarray
    dt: float
    speed_mps: float
    x0_m: float = 0.0

    def __post_init__(self) -> None:
        z = np.asarray(self.channels)
        if z.ndim != 2 or z.shape[1] != 4 or len(z) < 16:
            raise ValueError(f"RailRun {self.pass_id}: channels must be (n >= 16, 4), got {z.shape}")
        if not (self.dt > 0 and self.speed_mps > 0 and math.isfinite(self.x0_m)):
            raise ValueError(f"RailRun {self.pass_id}: need dt > 0, speed_mps > 0 and a finite x0_m")
