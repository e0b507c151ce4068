"""J⁰ by the matrix method from a bogie's two wheels (cloud.rail.fundamental): the area of
J⁰ (what D2 compares) from a batch-mean wheel difference with known noise.

The line is the exact J⁰(x) − J⁰(x − d) of a Hermite FE beam (10.2 m, simply supported, 5 % per-
element E·I scatter: a different discretisation from the estimator's sine modes), plus white noise
per grid point at the blind test's batch-mean level and a random linear drift (the inverses'); the
estimates are compared with the FE line's own area and mid-span ordinate, low-passed as the reading's
lines are (the low-pass alone moves the area by ~2 %, the same for every batch, so D2 does not feel it).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import butter, sosfiltfilt

from cloud.bridge.mril import MrIl
from cloud.rail.fundamental import registered_fundamental, smooth_operator
from shared.fe.beam import Beam, influence_line

SPAN_M, WHEELBASE_M, GRID_M, MIN_WAVELENGTH_M = 10.2, 2.5, 0.05, 4.0
DRAWS = 200


def _beam(rng) -> Beam:
    return Beam(span_m=SPAN_M, n_elements=20, E_pa=3.5e10, I_m4=0.06, mass_per_m=1.0e4,
                ei_factor=1.0 + 0.05 * rng.standard_normal(20))


def _lines(rng, beam, noise_sd, draws):
    """The FE beam's J⁰ on the estimator's span grid (low-passed as the reading's), and ``draws`` noisy wheel-difference lines
    (x from the first support, m; m/N)."""
    x = np.arange(-10.0, SPAN_M + WHEELBASE_M + 10.0 + 1e-9, GRID_M)
    j0 = lambda xx: influence_line(beam, np.clip(xx, 0.0, SPAN_M)) * ((xx >= 0) & (xx <= SPAN_M))
    g = j0(x) - j0(x - WHEELBASE_M)
    scale = float(np.max(g))
    lines = []
    for _ in range(draws):
        drift = scale * 0.2 * rng.standard_normal(2)
        noisy = g + noise_sd * scale * rng.standard_normal(x.size) + drift[0] + drift[1] * x / x[-1]
        lines.append(MrIl(x, noisy, 50))
    c = round(WHEELBASE_M / GRID_M)
    h = WHEELBASE_M / c
    xs = h * np.arange(int(np.floor(SPAN_M / h + 1e-9)) + 1)
    target = sosfiltfilt(butter(4, h / (0.5 * MIN_WAVELENGTH_M), output="sos"), j0(xs))
    return xs, target, lines


DEFAULT = "default"  # the reading's own estimator (registered_fundamental's default)


def _read(lines, modes):
    kw = {} if modes == DEFAULT else {"modes": modes}
    return np.array([registered_fundamental(line, 0.0, SPAN_M, WHEELBASE_M, grid_m=GRID_M,
                                            min_wavelength_m=MIN_WAVELENGTH_M, **kw) for line in lines])


def test_noise_free_line_gives_the_beams_area_and_midspan():
    beam = _beam(np.random.default_rng(1))
    xs, true, lines = _lines(np.random.default_rng(2), beam, 0.0, 1)
    lines = [MrIl(lines[0].x_m, lines[0].J, 50)]
    for modes in (None, DEFAULT):
        J = _read(lines, modes)[0]
        area, true_area = np.trapezoid(J, xs), np.trapezoid(true, xs)
        mid = np.abs(xs - xs[-1] / 2) <= 0.025 * xs[-1]
        assert area == pytest.approx(true_area, rel=0.01), modes
        assert J[mid].mean() == pytest.approx(true[mid].mean(), rel=0.01), modes


def test_area_sd_well_below_the_grid_point_least_squares_and_unbiased():
    """The reading's J⁰ (sine modes) against the thesis's grid-point least squares (``modes=None``) on
    the same 200 noisy lines: the area's sd less than half (measured 0.40×), the mean area and mid-span
    ordinate unbiased, the mid-span ordinate's sd (D1) not larger."""
    rng = np.random.default_rng(3)
    beam = _beam(rng)
    xs, true, lines = _lines(rng, beam, 0.05, DRAWS)
    true_area = np.trapezoid(true, xs)
    mid = np.abs(xs - xs[-1] / 2) <= 0.025 * xs[-1]
    J = {m: _read(lines, m) for m in (None, DEFAULT)}
    areas = {m: np.trapezoid(j, xs, axis=1) for m, j in J.items()}
    mids = {m: j[:, mid].mean(axis=1) for m, j in J.items()}
    sd_pinv, sd_new = areas[None].std(ddof=1), areas[DEFAULT].std(ddof=1)
    print(f"area sd / true area: grid points {sd_pinv / true_area:.4f}, sine modes {sd_new / true_area:.4f}")
    assert sd_new < 0.5 * sd_pinv
    assert abs(areas[DEFAULT].mean() - true_area) < max(3 * sd_new / np.sqrt(DRAWS), 0.01 * true_area)
    assert mids[DEFAULT].std(ddof=1) <= mids[None].std(ddof=1)  # D1 does not lose
    assert abs(mids[DEFAULT].mean() - true[mid].mean()) < max(3 * mids[DEFAULT].std(ddof=1) / np.sqrt(DRAWS),
                                                              0.01 * true[mid].mean())


def test_more_modes_than_the_grid_holds_is_refused():
    with pytest.raises(ValueError, match="smooth_operator: modes must be 1..5 for 11 grid points"):
        smooth_operator(11, 3, 6)
