"""The vehicle parametrisation calibration works in: identifiable ratios to a reference mass.

Only ratios are identifiable (divide the equations of motion by the body mass): the AP depends on
``K/M, k/M, c/M, m/M`` of a quarter-car, not on ``M``. So each model is parametrised by its
reference mass, held at the class mean, and the ratios of every other mass, stiffness and damping
to it; lengths (axle positions) stay absolute. Fits work on their logarithms (scale-free steps,
positivity for free, and the class prior is log-normal).
"""

from __future__ import annotations

import math

import numpy as np

from . import MODELS

#: model → (reference mass, absolute length parameters)
REFERENCE = {
    "sprung_mass": ("m", ()),
    "quarter_car": ("M", ()),
    "half_car": ("ms", ("D1", "D2")),
    "bogie_half_car": ("ms", ("D1", "D2")),
}


def calibration_names(model: str) -> list[str]:
    """The identifiable quantities of a model, e.g. ``['m/M', 'K/M', 'k/M', 'c/M']``."""
    ref, lengths = REFERENCE[model]
    names = []
    for p in MODELS[model].param_names():
        if p == ref:
            continue
        names.append(p if p in lengths else f"{p}/{ref}")
    return names


def to_calibration(model: str, params: dict[str, float]) -> dict[str, float]:
    """The calibration quantities (ratios, lengths) of a full parameter set."""
    ref, lengths = REFERENCE[model]
    return {n: (params[n] if "/" not in n else params[n.split("/")[0]] / params[ref])
            for n in calibration_names(model)}


def from_calibration(model: str, cal: dict[str, float], ref_value: float) -> dict[str, float]:
    """The full parameter set of calibration quantities ``cal`` with the reference mass at ``ref_value``."""
    ref, _ = REFERENCE[model]
    params = {ref: ref_value}
    for n, v in cal.items():
        params[n.split("/")[0]] = v * ref_value if "/" in n else v
    return params


def class_prior(model: str, mean: dict[str, float], std: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """Prior on the log of each calibration quantity (delta method from the class's mean/std)."""
    ref, _ = REFERENCE[model]
    mu, sd = [], []
    for n in calibration_names(model):
        if "/" in n:
            p = n.split("/")[0]
            mu.append(math.log(mean[p] / mean[ref]))
            cv = math.hypot(std[p] / mean[p], std[ref] / mean[ref])
        else:
            mu.append(math.log(mean[n]))
            cv = std[n] / mean[n]
        sd.append(max(cv, 1e-3))
    return np.array(mu), np.array(sd)
