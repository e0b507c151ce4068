"""The one-channel error model fitted once per inverse, speed bucket and axle, scaled per segment,
against the fit of each segment's own spectrum."""

from __future__ import annotations

import math

import numpy as np
import pytest

from edge.error_model import fit_error_band, unit_error_band, unit_spectra, white_equivalent
from shared.dynamics.inverse import build_inverse, edge_gamma
from shared.vehicles import QuarterCar

SPACING, DRIFT = 0.05, 3000


@pytest.fixture(scope="module")
def model():
    return build_inverse(QuarterCar(M=4450.0, m=420.0, K=5e5, k=1.95e6, c=2e4).system(), 1 / 500,
                         gamma=edge_gamma("quarter_car"))


@pytest.mark.parametrize("speed", [8.0, 14.3, 22.0])
@pytest.mark.parametrize("sd", [3e-4, 0.02, 1.7])
def test_the_scaled_unit_fit_is_the_segment_fit(model, speed, sd):
    omega, S = unit_spectra(model, speed, SPACING, DRIFT)
    sd1, band1, white1, level = unit_error_band(model, speed, SPACING, DRIFT, 1)
    ceiling = 2.0 * sd * sd * level  # above the long-wave level: the fill does not bind
    sd_m, band = fit_error_band(omega, sd * sd * S[0, 0], SPACING, fill_ceiling=ceiling)
    # The same least squares solved at another scale: equal up to rounding (relative 1e-12 leaves
    # room for the six reweighting steps; the values themselves are O(1) after normalisation).
    assert sd * sd1 == pytest.approx(sd_m, rel=1e-12)
    assert np.allclose(band1, band, rtol=1e-12, atol=1e-12 * np.abs(band).max())
    assert sd * sd1 * white1 == pytest.approx(white_equivalent(sd_m, band), rel=1e-12)


def test_a_binding_ceiling_changes_the_fit(model):
    """Why the pipeline fits a segment on its own when the AP's white level lies below the long-wave
    level: the fill then depends on that level, not only on the channel's noise."""
    omega, S = unit_spectra(model, 14.3, SPACING, DRIFT)
    sd1, band1, _, level = unit_error_band(model, 14.3, SPACING, DRIFT, 1)
    _, band = fit_error_band(omega, S[0, 0], SPACING, fill_ceiling=0.01 * level)
    assert not np.allclose(band, band1, rtol=1e-3)
    assert math.isfinite(sd1) and level > 0


def test_median_abs_deviations_are_numpys_to_the_bit():
    from edge.error_model import median_abs_deviations

    rng = np.random.default_rng(1)
    for trial in range(600):
        n, c = int(rng.integers(1, 400)), int(rng.integers(1, 4))  # odd and even counts
        x = rng.standard_normal((n, c)) * 10.0 ** rng.uniform(-8, 3)
        if trial % 3 == 0:
            x = np.round(x, 1)  # ties
        want = np.median(np.abs(x - np.median(x, axis=0)), axis=0)
        assert median_abs_deviations(x).tobytes() == want.tobytes()
