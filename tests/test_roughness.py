"""Tests for shared.roughness (IRI, ASTM E1926) and the roughness export."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import expm

from cloud.export import roughness_table
from shared.profiles.iso8608 import ISO8608_GD0, N0, iso8608_profile
from shared.roughness import GOLDEN_CAR, IRI_SPEED_MPS, iri, iri_segments

DX = 0.05
V = IRI_SPEED_MPS


def naive_iri_rates(y, dx):
    """Sayers' reference loop written out plainly: per step, the suspension rate / speed.

    The Golden Car equations of motion per unit sprung mass (k1 tyre, k2 spring, c damper, mu
    axle) are assembled here independently of the module, in slope form, and stepped with the
    exact zero-order-hold transition.
    """
    k1, k2, c, mu = 653.0, 63.3, 6.0, 0.15
    A = np.zeros((4, 4))
    A[0, 1] = 1.0
    A[1] = [-k2, -c, k2, c]
    A[2, 3] = 1.0
    A[3] = [k2 / mu, c / mu, -(k1 + k2) / mu, -c / mu]
    B = np.array([0.0, 0.0, 0.0, k1 / mu])
    ST = expm(A * dx / V)
    PR = np.linalg.inv(A) @ (ST - np.eye(4)) @ B
    base = max(1, round(0.25 / dx))
    i11 = round(11.0 / dx)
    s0 = (y[i11] - y[0]) / (i11 * dx)
    z = np.array([s0, 0.0, s0, 0.0])
    rates = []
    for i in range(len(y) - base):
        slope = (y[i + base] - y[i]) / (base * dx)
        z = ST @ z + PR * slope
        rates.append(abs(z[0] - z[2]))
    return np.array(rates)


def golden_car_relative_velocity(lam_m):
    """|ż_s − ż_u| / V per unit road amplitude for a sinusoid of wavelength ``lam_m`` (steady state).

    From m_s z_s'' = −k2 (z_s − z_u) − c (ż_s − ż_u) and
    m_u z_u'' = k2 (z_s − z_u) + c (ż_s − ż_u) − k1 (z_u − y), with z = Z e^{iωt}:
        (−ω² + iωc + k2) Z_s − (iωc + k2) Z_u = 0
        −(iωc + k2) Z_s + (−μω² + iωc + k2 + k1) Z_u = k1 Y
    """
    k1, k2, c, mu = GOLDEN_CAR
    w = 2 * math.pi * V / lam_m
    s = 1j * w
    M = np.array([[s * s + s * c + k2, -(s * c + k2)], [-(s * c + k2), mu * s * s + s * c + k2 + k1]])
    zs, zu = np.linalg.solve(M, np.array([0.0, k1]))
    return abs(s * (zs - zu)) / V


def test_kernel_matches_the_plain_reference_loop():
    rng = np.random.default_rng(0)
    y = np.cumsum(rng.normal(0, 5e-4, 3001))
    rates = naive_iri_rates(y, DX)
    assert iri(y, DX) == pytest.approx(1000 * rates.mean(), rel=1e-10)
    start, end, v = iri_segments(np.arange(y.size) * DX, y, 10.0)
    mids = np.arange(rates.size) * DX + 0.125  # the centre of each step's 250 mm base
    for k in range(start.size):
        sel = (mids >= k * 10.0) & (mids < (k + 1) * 10.0)
        assert v[k] == pytest.approx(1000 * rates[sel].mean(), rel=1e-10)


@pytest.mark.parametrize("lam", [1.5, 2.5, 4.5, 9.0, 15.0, 30.0])
def test_sinusoid_matches_the_golden_car_frequency_response(lam):
    """IRI of A sin(2πx/λ) = 1000 · (2/π) · A · |H(λ)| · sinc(0.25/λ) (m/km), in steady state.

    (2/π is the mean of |sin|, H the suspension-rate response above, sinc the 250 mm moving
    average.) Measured over 900 m after a 100 m run-up, an integer number of wavelengths.
    """
    amp = 2e-3
    x = np.arange(0, 1000.0 + DX / 2, DX)
    y = amp * np.sin(2 * np.pi * x / lam)
    _, _, v = iri_segments(x, y, 100.0)
    steady = v[1:].mean()
    expected = 1000 * (2 / np.pi) * amp * golden_car_relative_velocity(lam) * np.sinc(0.25 / lam)
    # The slope held over each 5 cm step (the discrete recursion) costs 0.05 % at λ = 1.5 m.
    assert steady == pytest.approx(expected, rel=1e-3 if lam < 4 else 2e-4)


def test_response_peaks_where_the_golden_car_resonates():
    """The IRI slope gain peaks near 2.3 m (wheel hop) and 15 m (body bounce) at 80 km/h."""
    lams = np.linspace(1.0, 40.0, 400)
    gain = np.array([golden_car_relative_velocity(lam) * lam / (2 * np.pi) for lam in lams])
    x = np.arange(0, 1000.0 + DX / 2, DX)
    measured = [iri(np.sin(2 * np.pi * x / lam) * lam / (2 * np.pi), DX) for lam in (2.3, 15.0, 6.0)]
    assert 1.5 < gain.max() < 1.8
    assert measured[0] > measured[2] and measured[1] > measured[2]


@pytest.mark.parametrize("profile", ["flat", "linear", "offset"])
def test_straight_profiles_have_zero_iri(profile):
    x = np.arange(0, 300.0 + DX / 2, DX)
    y = {"flat": np.zeros_like(x), "linear": 0.03 * x - 1.0, "offset": np.full_like(x, 7.0)}[profile]
    assert abs(iri(y, DX)) < 1e-9
    _, _, v = iri_segments(x, y, 10.0)
    assert np.all(np.abs(v) < 1e-9)


def test_iso8608_profile_matches_the_spectral_prediction():
    """For a Gaussian profile, IRI = 1000 √(2/π) σ_r with σ_r² = ∫ G_slope |H|² sinc² dn.

    ISO 8608 (w = 2) has a white slope PSD (2π n0)² Gd0; class A's geometric mean gives ≈ 2.2 m/km
    and class B twice that (amplitudes double, the IRI is homogeneous of degree one).
    """
    n = np.linspace(1e-3, 10.0, 20000)
    gain2 = np.array([golden_car_relative_velocity(1 / f) ** 2 for f in n]) / (2 * np.pi * n) ** 2
    slope_psd = (2 * np.pi * N0) ** 2 * ISO8608_GD0["A"]
    predicted = 1000 * math.sqrt(2 / math.pi) * math.sqrt(np.trapezoid(slope_psd * gain2 * np.sinc(0.25 * n) ** 2, n))
    a = iso8608_profile(5000.0, DX, "A", seed=4).elevation_m
    b = iso8608_profile(5000.0, DX, "B", seed=4).elevation_m
    assert 1.0 < iri(a, DX) < 3.5
    assert iri(a, DX) == pytest.approx(predicted, rel=0.03)  # 5 km of one random profile
    assert iri(b, DX) == pytest.approx(2 * iri(a, DX), rel=1e-9)


@pytest.mark.parametrize("x0, length", [(0.0, 10.0), (0.0, 100.0), (3.2, 10.0), (12.35, 100.0)])
def test_segments_tile_the_profile(x0, length):
    rng = np.random.default_rng(1)
    x = x0 + np.arange(7001) * DX
    y = np.cumsum(rng.normal(0, 5e-4, x.size))
    start, end, v = iri_segments(x, y, length)
    assert start[0] == x[0] and end[-1] == x[-1]
    np.testing.assert_array_equal(start[1:], end[:-1])
    assert np.all(end - start <= length + 1e-9) and np.all(end > start)
    inner = start[1:-1]
    np.testing.assert_allclose(inner / length, np.round(inner / length), atol=1e-9)  # on the L grid
    assert np.all(np.isfinite(v[1:-1]))


def test_segments_after_the_first_are_run_up_from_the_preceding_profile():
    """Changing the first 20 m changes the segments up to ~100 m on only: the car carries its state
    across segment boundaries, and the memory of the start decays (body mode, ~0.4 s at 80 km/h)."""
    rng = np.random.default_rng(2)
    x = np.arange(4001) * DX
    y = np.cumsum(rng.normal(0, 5e-4, x.size))
    y2 = y.copy()
    y2[:400] += np.linspace(0.01, 0.0, 400) + rng.normal(0, 1e-3, 400)
    _, _, v = iri_segments(x, y, 10.0)
    _, _, v2 = iri_segments(x, y2, 10.0)
    assert abs(v[0] - v2[0]) > 0.1
    np.testing.assert_allclose(v[12:], v2[12:], rtol=1e-6)


def test_gaps_and_rows():
    rng = np.random.default_rng(3)
    x = np.arange(6001) * DX
    rows = np.cumsum(rng.normal(0, 5e-4, (3, x.size)), axis=1)
    rows[:, 2000:2400] = np.nan  # 100–120 m unknown
    start, end, v = iri_segments(x, rows, 10.0)
    assert v.shape == (3, start.size)
    gap = (start >= 100.0) & (end <= 120.0)
    assert np.all(np.isnan(v[:, gap])) and np.all(np.isfinite(v[:, ~gap]))
    for r in range(3):
        np.testing.assert_array_equal(iri_segments(x, rows[r], 10.0)[2], v[r])
    # After the gap the car restarts from the 11 m initialisation, as at a profile's start.
    after = iri_segments(x[2400:], rows[0, 2400:], 10.0)[2]
    np.testing.assert_allclose(v[0, 12:], after, rtol=1e-12)
    with pytest.raises(ValueError):
        iri(rows[0], DX)
    with pytest.raises(ValueError):
        iri_segments(x, rows[0, :-1], 10.0)


def test_roughness_table():
    rng = np.random.default_rng(4)
    x = np.arange(4001) * DX  # 200 m
    base = np.cumsum(rng.normal(0, 5e-4, x.size))
    draws = base + rng.normal(0, 2e-4, (50, x.size)).cumsum(axis=1) * 0.05
    draws[:, 3000:] = np.nan  # the last 50 m unknown
    t = roughness_table("R1", x, draws, DX)
    assert t.column_names == ["route_id", "start_m", "end_m", "length_m", "iri_m_per_km", "iri_lo95", "iri_hi95",
                              "chainage_frame"]
    d = {k: np.asarray(v) for k, v in t.to_pydict().items()}
    assert set(d["route_id"]) == {"R1"}
    ten = d["length_m"] == 10.0
    assert ten.sum() == 15 and (~ten).sum() == 1  # 0–150 m known; 100–200 m is less than half known
    assert d["end_m"][ten].max() == x[2999]  # the last known point: bounds are the profile's, not the route's
    assert np.all(d["iri_lo95"] <= d["iri_m_per_km"]) and np.all(d["iri_m_per_km"] <= d["iri_hi95"])
    assert np.all(d["iri_hi95"] > d["iri_lo95"])
    # One profile: the band collapses onto the value, which is the profile's IRI.
    one = {k: np.asarray(v) for k, v in roughness_table("R1", x, base, DX).to_pydict().items()}
    _, _, v100 = iri_segments(x, base, 100.0)
    np.testing.assert_allclose(one["iri_m_per_km"][one["length_m"] == 100.0], v100)
    np.testing.assert_array_equal(one["iri_lo95"], one["iri_hi95"])


def test_roughness_segments_start_where_the_profile_does():
    """Passes begin a few metres into the route: the first segment's IRI is of the stretch from there
    (the car's run starts at the first known point), and its bounds say so rather than [0, L)."""
    rng = np.random.default_rng(5)
    x = np.arange(4001) * DX
    draws = np.cumsum(rng.normal(0, 5e-4, (20, x.size)), axis=1)
    draws[:, :97] = np.nan  # known from 4.85 m
    d = {k: np.asarray(v) for k, v in roughness_table("R1", x, draws, DX).to_pydict().items()}
    for length in (10.0, 100.0):
        rows = d["length_m"] == length
        assert d["start_m"][rows].min() == x[97]
        assert d["end_m"][rows].max() == x[-1]
    _, _, v = iri_segments(x[97:], draws[:, 97:], 10.0)  # the same IRI as of the known stretch alone
    np.testing.assert_allclose(d["iri_m_per_km"][d["length_m"] == 10.0], v.mean(axis=0))
