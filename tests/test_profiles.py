"""Tests for shared.profiles: ISO 8608 synthesis, tyre filter, RoadProfile and the 3-D carpet."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import integrate, signal, special, stats

from shared.profiles import (
    ISO8608_GD0,
    N0,
    Carpet,
    RoadProfile,
    carpet_profile,
    draw_lane,
    iso8608_profile,
    iso8608_psd,
    lane_probabilities,
    tyre_filter,
)
from shared.profiles.carpet import lateral_correlation

CLASSES = tuple("ABCDE")
SPACING = 0.01  # m, the default grid
# Octave bands (cycles/m) well inside n_min = 0.01 … Nyquist = 50 for the default grid.
BANDS = [(0.1 * 2**j, 0.2 * 2**j) for j in range(8)]  # 0.1 … 25.6


def band_ratios(rows: np.ndarray, spacing_m: float, road_class: str) -> np.ndarray:
    """Estimated / target power in each of BANDS for Welch PSDs averaged over ``rows``.

    Power in a band is the integral of the PSD between the first and last Welch bin inside it:
    trapezoid rule on the estimate, exact integral of ``Gd0 (n/n0)^-2`` for the target.
    """
    f, psd = signal.welch(rows, fs=1.0 / spacing_m, nperseg=8192, axis=-1)
    psd = psd.reshape(-1, f.size).mean(axis=0)
    gd0 = ISO8608_GD0[road_class]
    ratios = []
    for lo, hi in BANDS:
        sel = (f >= lo) & (f <= hi)
        fb = f[sel]
        estimate = integrate.trapezoid(psd[sel], fb)
        target = gd0 * N0**2 * (1.0 / fb[0] - 1.0 / fb[-1])
        ratios.append(estimate / target)
    return np.array(ratios)


# --- ISO 8608 ------------------------------------------------------------------------------------


@pytest.mark.parametrize("road_class", CLASSES)
def test_psd_of_generated_profiles_matches_class_in_every_octave(road_class):
    rows = np.stack(
        [iso8608_profile(1000.0, SPACING, road_class, seed=s).elevation_m for s in range(4)]
    )
    ratios = band_ratios(rows, SPACING, road_class)
    np.testing.assert_array_less(np.abs(ratios - 1.0), 0.2, err_msg=f"ratios {ratios}")


def test_psd_test_tells_classes_apart():
    rows = iso8608_profile(1000.0, SPACING, "B", seed=1).elevation_m[None]
    ratios = band_ratios(rows, SPACING, "A")
    assert np.all(ratios > 3.0) and np.all(ratios < 5.0)  # B is 4x A


def test_variance_equals_integral_of_target_psd():
    # Over a record much longer than 1/n_min the sample variance is the sum of the harmonic
    # powers Gd(n_k) Δn, i.e. the integral of Gd over [n_min, Nyquist] to within Δn / n_min.
    spacing, n_min = 0.05, 0.1
    for seed in (3, 4):
        y = iso8608_profile(2000.0, spacing, "C", seed=seed, n_min=n_min).elevation_m
        expected = ISO8608_GD0["C"] * N0**2 * (1.0 / n_min - 2.0 * spacing)
        assert np.var(y) == pytest.approx(expected, rel=0.01)


def test_band_limits_are_respected():
    y = iso8608_profile(200.0, SPACING, "A", seed=0, n_min=0.5, n_max=5.0).elevation_m
    f, psd = signal.welch(y, fs=1.0 / SPACING, nperseg=8192)
    inside = psd[(f > 1.0) & (f < 4.0)].mean()
    assert inside == pytest.approx(float(iso8608_psd(2.0, "A")), rel=0.5)
    # Outside the band only window leakage remains, orders of magnitude below the ISO level.
    assert psd[f > 10.0].max() < 1e-4 * iso8608_psd(10.0, "A")
    assert psd[(f > 0.0) & (f < 0.1)].max() < 1e-4 * iso8608_psd(0.1, "A")


def test_short_profile_still_contains_long_waves():
    # 20 m is shorter than 1/n_min = 100 m; the lowest harmonics must still be there.
    y = iso8608_profile(20.0, SPACING, "A", seed=0).elevation_m
    assert np.ptp(y) > 1e-3
    assert iso8608_profile(20.0, SPACING, "A", seed=0).end_m == pytest.approx(20.0)


def test_psd_formula():
    assert iso8608_psd(N0, "A") == pytest.approx(16e-6)
    assert iso8608_psd(2 * N0, "a") == pytest.approx(4e-6)
    levels = [float(iso8608_psd(1.0, c)) for c in CLASSES]
    np.testing.assert_allclose(np.diff(np.log(levels)), np.log(4.0))
    assert iso8608_psd(np.ones((2, 3)), "E").shape == (2, 3)


@pytest.mark.parametrize("n", [0.0, -1.0, np.nan, np.inf])
def test_psd_rejects_bad_frequency(n):
    with pytest.raises(ValueError, match="n "):
        iso8608_psd(n, "A")


def test_seeded_reproducibility():
    a = iso8608_profile(50.0, seed=7)
    b = iso8608_profile(50.0, seed=7)
    c = iso8608_profile(50.0, seed=8)
    np.testing.assert_array_equal(a.elevation_m, b.elevation_m)
    assert not np.allclose(a.elevation_m, c.elevation_m)
    g = iso8608_profile(50.0, seed=np.random.default_rng(7))
    np.testing.assert_array_equal(a.elevation_m, g.elevation_m)


@pytest.mark.parametrize("road_class", ["F", "", "AB", None, 3])
def test_invalid_class(road_class):
    with pytest.raises(ValueError, match="road_class"):
        iso8608_profile(10.0, road_class=road_class)
    with pytest.raises(ValueError, match="road_class"):
        iso8608_psd(1.0, road_class)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"length_m": 0.0}, "length_m"),
        ({"length_m": -5.0}, "length_m"),
        ({"length_m": np.nan}, "length_m"),
        ({"length_m": np.inf}, "length_m"),
        ({"length_m": 0.005}, "length_m"),
        ({"length_m": 10.0, "spacing_m": 0.0}, "spacing_m"),
        ({"length_m": 10.0, "n_min": 0.0}, "n_min"),
        ({"length_m": 10.0, "n_max": 60.0}, "n_max"),
        ({"length_m": 10.0, "n_min": 2.0, "n_max": 1.0}, "n_min"),
    ],
)
def test_invalid_synthesis_arguments(kwargs, field):
    with pytest.raises(ValueError, match=field):
        iso8608_profile(**kwargs)


# --- tyre filter ---------------------------------------------------------------------------------


def _grid(spacing, length=20.0):
    return np.arange(int(round(length / spacing)) + 1) * spacing


@pytest.mark.parametrize("spacing", [0.01, 0.02, 0.08])  # k = 24, 12 (even), 3 (odd)
def test_tyre_filter_keeps_constant_and_linear_everywhere(spacing):
    x = _grid(spacing)
    for y in (np.full_like(x, 0.3), 0.02 * x - 0.1):
        out = tyre_filter(RoadProfile(0.0, spacing, y))
        np.testing.assert_allclose(out.elevation_m, y, atol=1e-14)


@pytest.mark.parametrize("spacing", [0.01, 0.02, 0.08])
def test_tyre_filter_annihilates_its_own_wavelength(spacing):
    x = _grid(spacing)
    y = np.sin(2 * np.pi * x / 0.24 + 0.3)
    out = tyre_filter(RoadProfile(0.0, spacing, y)).elevation_m
    inner = slice(20, -20)
    assert np.max(np.abs(out[inner])) < 1e-9


def test_tyre_filter_passes_long_waves():
    x = _grid(SPACING)
    y = np.sin(2 * np.pi * x / 10.0)
    out = tyre_filter(RoadProfile(0.0, SPACING, y)).elevation_m
    np.testing.assert_allclose(out, y, atol=0.01)


def test_tyre_filter_is_mean_of_interpolant_over_window():
    # Slow reference: average the linear interpolant over [x - 0.12, x + 0.12] by dense sampling.
    profile = iso8608_profile(5.0, SPACING, "C", seed=2)
    out = tyre_filter(profile)
    for i in (30, 211, 377):
        x = profile.chainage_m[i]
        s = np.linspace(x - 0.12, x + 0.12, 24 * 400 + 1)
        assert out.elevation_m[i] == pytest.approx(integrate.trapezoid(profile.at(s), s) / 0.24)
    assert out.start_m == profile.start_m and out.n_points == profile.n_points


def test_tyre_filter_rejects_bad_windows():
    p = RoadProfile(0.0, 0.1, np.zeros(5))
    with pytest.raises(ValueError, match="window_m"):
        tyre_filter(p, window_m=0.01)
    with pytest.raises(ValueError, match="window_m"):
        tyre_filter(p, window_m=2.0)
    with pytest.raises(ValueError, match="window_m"):
        tyre_filter(p, window_m=-0.24)


# --- RoadProfile ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"spacing_m": 0.0}, "spacing_m"),
        ({"spacing_m": -0.1}, "spacing_m"),
        ({"spacing_m": np.nan}, "spacing_m"),
        ({"spacing_m": "x"}, "spacing_m"),
        ({"start_m": np.inf}, "start_m"),
        ({"elevation_m": [1.0]}, "elevation_m"),
        ({"elevation_m": [[1.0, 2.0]]}, "elevation_m"),
        ({"elevation_m": [0.0, np.nan, 1.0]}, "elevation_m"),
        ({"elevation_m": [0.0, np.inf]}, "elevation_m"),
    ],
)
def test_road_profile_validation(kwargs, field):
    args = {"start_m": 0.0, "spacing_m": 0.1, "elevation_m": [0.0, 1.0, 2.0]} | kwargs
    with pytest.raises(ValueError, match=field):
        RoadProfile(**args)


def test_road_profile_is_immutable_copy():
    y = np.array([0.0, 1.0, 4.0])
    p = RoadProfile(2, 0.5, y)
    y[0] = 99.0
    assert p.elevation_m[0] == 0.0 and isinstance(p.start_m, float)
    with pytest.raises(ValueError):
        p.elevation_m[0] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.spacing_m = 1.0


def test_at_interpolates_linearly():
    p = RoadProfile(2.0, 0.5, [0.0, 1.0, 4.0, 9.0])  # nodes at 2, 2.5, 3, 3.5
    assert p.end_m == 3.5
    np.testing.assert_allclose(p.at(p.chainage_m), p.elevation_m)
    np.testing.assert_allclose(p.at([2.25, 2.75, 3.125]), [0.5, 2.5, 5.25])
    x = np.array([[2.0, 3.5], [2.1, 3.4]])
    assert p.at(x).shape == (2, 2)
    assert np.ndim(p.at(3.0)) == 0 and p.at(3.0) == 4.0


@pytest.mark.parametrize("x", [1.99, 3.51, [2.5, 4.0], np.nan])
def test_at_and_slope_reject_points_off_the_grid(x):
    p = RoadProfile(2.0, 0.5, [0.0, 1.0, 4.0, 9.0])
    with pytest.raises(ValueError, match=r"\[2\.0, 3\.5\]"):
        p.at(x)
    with pytest.raises(ValueError, match=r"\[2\.0, 3\.5\]"):
        p.slope(x)


def test_slope_is_derivative_of_interpolant():
    p = iso8608_profile(3.0, 0.05, "D", seed=4)
    x = np.linspace(p.start_m + 1e-3, p.end_m - 1e-3, 997)
    h = 1e-7
    fd = (p.at(x + h) - p.at(x - h)) / (2 * h)
    off_nodes = np.abs((x / p.spacing_m) - np.round(x / p.spacing_m)) > 1e-3
    np.testing.assert_allclose(p.slope(x)[off_nodes], fd[off_nodes], rtol=1e-5, atol=1e-8)
    q = RoadProfile(0.0, 1.0, [0.0, 1.0, 3.0])
    np.testing.assert_allclose(q.slope([0.0, 0.5, 1.0, 2.0]), [1.0, 1.0, 2.0, 2.0])


def test_resampled():
    line = RoadProfile(1.0, 0.1, 0.5 * (1.0 + 0.1 * np.arange(31)) + 2.0)  # y = 0.5 x + 2 on [1, 4]
    r = line.resampled(0.25)
    assert r.spacing_m == 0.25 and r.start_m == 1.0 and r.end_m == pytest.approx(4.0)
    np.testing.assert_allclose(r.elevation_m, 0.5 * r.chainage_m + 2.0)
    assert line.resampled(0.7).end_m == pytest.approx(3.8)
    with pytest.raises(ValueError, match="spacing_m"):
        line.resampled(5.0)
    with pytest.raises(ValueError, match="spacing_m"):
        line.resampled(0.0)


# --- carpet --------------------------------------------------------------------------------------


def test_carpet_layout():
    c = carpet_profile(20.0)
    assert c.n_lanes == 11 and c.elevation_m.shape == (11, 2001)
    np.testing.assert_allclose(c.offsets_m, np.linspace(-0.5, 0.5, 11), atol=1e-15)
    assert len(c.lanes) == 11 and c.lane(5).end_m == pytest.approx(20.0)
    np.testing.assert_array_equal(c.lane(3).elevation_m, c.elevation_m[3])
    for bad in (11, -1):
        with pytest.raises(ValueError, match="lane index"):
            c.lane(bad)


def test_carpet_correlation_falls_with_lateral_separation():
    corr = np.mean([np.corrcoef(carpet_profile(100.0, seed=s).elevation_m) for s in range(3)], 0)
    by_lag = np.array([np.diagonal(corr, lag).mean() for lag in range(11)])
    assert np.all(np.diff(by_lag) < 0), by_lag
    assert by_lag[1] > 0.9  # neighbours nearly share the profile …
    assert by_lag[10] < by_lag[1] - 0.1  # … lanes 1 m apart clearly differ


def test_lateral_correlation_is_that_of_an_isotropic_surface():
    # Track cross-spectrum of an isotropic surface with 2-D spectrum |k|^-3, normalised by the
    # track spectrum: ∫ (a² + k²)^-3/2 cos(k d) dk / ∫ (a² + k²)^-3/2 dk, with a = 2π n.
    n, d = 1.7, np.array([[0.0, 0.05], [0.05, 0.0]])
    a = 2 * np.pi * n
    cross, _ = integrate.quad(lambda k: (a * a + k * k) ** -1.5, 0, np.inf, weight="cos", wvar=0.05)
    expected = cross / (1.0 / a**2)
    r = lateral_correlation(np.array([n]), d)[0]
    assert r[0, 1] == pytest.approx(expected, rel=1e-6)
    assert r[0, 0] == pytest.approx(1.0)
    x = 2 * np.pi * n * 0.05
    assert r[0, 1] == pytest.approx(x * special.k1(x), rel=1e-6)


def test_every_carpet_lane_is_class_a():
    carpets = [carpet_profile(1000.0, SPACING, "A", seed=s).elevation_m for s in range(2)]
    for lane in range(11):
        rows = np.stack([c[lane] for c in carpets])
        ratios = band_ratios(rows, SPACING, "A")
        np.testing.assert_array_less(np.abs(ratios - 1.0), 0.2, err_msg=f"lane {lane}: {ratios}")


def test_carpet_reproducibility_and_arguments():
    a, b, c = (carpet_profile(10.0, seed=s) for s in (1, 1, 2))
    np.testing.assert_array_equal(a.elevation_m, b.elevation_m)
    assert not np.allclose(a.elevation_m, c.elevation_m)
    five = carpet_profile(10.0, n_lanes=5, lane_spacing_m=0.2)
    np.testing.assert_allclose(five.offsets_m, [-0.4, -0.2, 0.0, 0.2, 0.4])
    for bad in ({"n_lanes": 0}, {"n_lanes": 2.5}, {"n_lanes": True}):
        with pytest.raises(ValueError, match="n_lanes"):
            carpet_profile(10.0, **bad)
    with pytest.raises(ValueError, match="lane_spacing_m"):
        carpet_profile(10.0, lane_spacing_m=0.0)
    with pytest.raises(ValueError, match="road_class"):
        carpet_profile(10.0, road_class="Z")


def test_carpet_validation():
    y = np.zeros((3, 4))
    with pytest.raises(ValueError, match="offsets_m"):
        Carpet(0.0, 0.1, [0.0, 0.0, 1.0], y)
    with pytest.raises(ValueError, match="elevation_m"):
        Carpet(0.0, 0.1, [0.0, 1.0], y)
    with pytest.raises(ValueError, match="elevation_m"):
        Carpet(0.0, 0.1, [0.0, 0.5, 1.0], np.zeros((3, 1)))
    with pytest.raises(ValueError, match="spacing_m"):
        Carpet(0.0, -0.1, [0.0, 0.5, 1.0], y)


def test_mean_profile():
    c = carpet_profile(20.0, seed=3)
    p = lane_probabilities()
    np.testing.assert_allclose(c.mean_profile(p).elevation_m, np.average(c.elevation_m, 0, p))
    np.testing.assert_allclose(c.mean_profile(np.ones(11) * 7).elevation_m, c.elevation_m.mean(0))
    one_hot = np.eye(11)[4]
    np.testing.assert_array_equal(c.mean_profile(one_hot).elevation_m, c.elevation_m[4])
    for bad in (np.ones(10), -one_hot, np.zeros(11), np.full(11, np.nan)):
        with pytest.raises(ValueError, match="weights"):
            c.mean_profile(bad)


def test_carpet_tyre_filter_matches_lane_by_lane():
    c = carpet_profile(10.0, seed=5)
    filtered = c.tyre_filtered()
    for i in (0, 5, 10):
        np.testing.assert_allclose(filtered.elevation_m[i], tyre_filter(c.lane(i)).elevation_m)


def test_lane_probabilities_match_truncated_normal():
    n, sd = 11, 3.0
    c = (n - 1) / 2
    dist = stats.truncnorm((-0.5 - c) / sd, (n - 0.5 - c) / sd, loc=c, scale=sd)
    i = np.arange(n)
    np.testing.assert_allclose(lane_probabilities(n, sd), dist.cdf(i + 0.5) - dist.cdf(i - 0.5))
    assert lane_probabilities(4, 0.01) == pytest.approx([0.0, 0.5, 0.5, 0.0])
    with pytest.raises(ValueError, match="sd_lanes"):
        lane_probabilities(11, 0.0)


def test_draw_lane():
    rng = np.random.default_rng(0)
    lanes = draw_lane(rng, size=20_000)
    assert lanes.min() >= 0 and lanes.max() <= 10
    counts = np.bincount(lanes, minlength=11)
    assert counts.size == 11 and np.argmax(counts) == 5
    np.testing.assert_allclose(counts / lanes.size, lane_probabilities(), atol=0.01)
    one = draw_lane(rng)
    assert isinstance(one, int) and 0 <= one <= 10
    assert set(draw_lane(rng, sd_lanes=1e-3, size=100)) == {5}
    assert set(draw_lane(rng, n_lanes=3, sd_lanes=50.0, size=1000)) == {0, 1, 2}
    with pytest.raises(TypeError, match="rng"):
        draw_lane(0)
