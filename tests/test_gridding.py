"""The edge's gridding: AP samples (uniform in time) onto the route's 5 cm grid, anti-aliased.

The grid samples at v / 5 cm (300–430 Hz at road speeds), below the AP's 500 Hz; content between
the grid's Nyquist (10 cycles/m) and the samples' (250 Hz / v) would fold into the grid, and linear
interpolation also bends the passband (−1.6 % at 0.5 m wavelength, 15 m/s). The anti-aliased grid
must be exact in the passband, empty above the grid's Nyquist, streamable, and agree with a
profile made on a 1 mm grid and band-limited by FFT (a different method from the edge's).
"""

from __future__ import annotations

import numpy as np
import pytest

from edge.pipeline import ANTIALIAS_PASS_CPM, ANTIALIAS_STOP_CPM, AxleGrid

DT = 0.002  # s: 500 Hz
SPACING = 0.05  # m
MIN_SPEED = 0.5


def _trajectory(v_mean: float, seconds: float, x0: float = 3.1) -> np.ndarray:
    """Chainage of each sample for a vehicle whose speed swings ±10 % at 0.5 Hz."""
    t = np.arange(int(seconds / DT)) * DT
    w = 2.0 * np.pi * 0.5
    return x0 + v_mean * t + 0.1 * v_mean / w * np.sin(w * t)


def _grid(x, ap, antialias: bool, cuts=(), reliable=None):
    n = x.size
    t = np.arange(n) * DT
    rel = np.ones(n, dtype=bool) if reliable is None else reliable
    g = AxleGrid(antialias, DT, MIN_SPEED)
    for a, b in zip((0, *cuts), (*cuts, n)):
        g.add(x[a:b], ap[a:b], t[a:b], rel[a:b], SPACING)
    g.flush()
    xg = (g.base + np.arange(g.done)) * SPACING
    return g, xg


def _interior(xg, x, margin=1.0):
    return (xg > x[0] + margin) & (xg < x[-1] - margin)


@pytest.mark.parametrize("v", [6.0, 12.0, 18.0, 25.0])
def test_passband_is_exact_and_nothing_above_the_grid_nyquist_folds_in(v):
    x = _trajectory(v, 6.0)
    passband = (0.02, 0.5, 1.0, 2.0, ANTIALIAS_PASS_CPM)  # cycles/m: 50 m … 0.33 m
    phases = np.linspace(0.3, 2.0, len(passband))

    def road(xs):
        return sum(np.sin(2 * np.pi * f * xs + p) for f, p in zip(passband, phases))

    sample_nyquist = 0.5 / (v * DT)
    high = 0.5 * (ANTIALIAS_STOP_CPM + sample_nyquist)  # between the grid's Nyquist and the samples'
    ap = road(x) + (np.sin(2 * np.pi * high * x) if sample_nyquist > ANTIALIAS_STOP_CPM + 0.5 else 0.0)
    errors = {}
    for aa in (False, True):
        g, xg = _grid(x, ap, aa)
        inner = _interior(xg, x)
        errors[aa] = float(np.max(np.abs(g.values - road(xg))[inner]))
    # five unit sinusoids: ≤ 1e-3 is ≤ 2e-4 of each; linear interpolation misses by far more
    assert errors[True] <= 1e-3, errors
    assert errors[False] > 10 * errors[True], errors


def test_content_above_the_grid_nyquist_is_suppressed():
    for v in (6.0, 9.0, 12.0):
        x = _trajectory(v, 4.0)
        for f in np.linspace(ANTIALIAS_STOP_CPM, 0.95 * 0.5 / (v * DT), 5):
            g, xg = _grid(x, np.sin(2 * np.pi * f * x + 0.7), True)
            lin, _ = _grid(x, np.sin(2 * np.pi * f * x + 0.7), False)
            inner = _interior(xg, x)
            assert np.max(np.abs(g.values[inner])) < 1e-3, (v, f)  # ≥ 60 dB down
            assert np.max(np.abs(lin.values[inner])) > 0.5, (v, f)  # what linear interpolation lets fold in


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_chunking_does_not_change_the_grid(seed):
    """Any cut of the stream gives the same grid to the bit, including stops (repeated chainage,
    slow samples flagged unreliable) and an unreliable stretch (warm-up-like); the samples kept
    stay bounded by the filter's reach, not the pass's length."""
    rng = np.random.default_rng(seed)
    x = _trajectory(14.0, 8.0)
    n = x.size
    stop = slice(n // 3, n // 3 + 300)
    x[stop.start :] -= np.linspace(0.0, x[stop.stop] - x[stop.start], n - stop.start).clip(max=0.0)
    x[stop] = x[stop.start]  # standing still for 0.6 s
    x[stop.stop :] += x[stop.start] - x[stop.stop]
    reliable = np.ones(n, dtype=bool)
    reliable[:500] = False  # warm-up
    reliable[stop] = False
    ap = rng.normal(size=n).cumsum() * 1e-3
    whole, xg = _grid(x, ap, True, reliable=reliable)
    cuts = np.sort(rng.choice(np.arange(1, n), size=60, replace=False))
    pieces, _ = _grid(x, ap, True, cuts=tuple(int(c) for c in cuts), reliable=reliable)
    tiny, _ = _grid(x, ap, True, cuts=tuple(range(1, n, 7)), reliable=reliable)
    for other in (pieces, tiny):
        assert other.base == whole.base and other.done == whole.done == whole.size
        assert np.array_equal(other.values, whole.values)
        assert np.array_equal(other.valid, whole.valid) and np.array_equal(other.t, whole.t)
    assert tiny._sap.size < 0.8 / (MIN_SPEED * DT) + 20  # the samples kept: ≤ the window at min speed
    # next to unreliable samples the value is the plain interpolation (nothing leaks across)
    lin, _ = _grid(x, ap, False, reliable=reliable)
    first_valid = np.flatnonzero(whole.valid)[0]
    assert whole.values[first_valid] == lin.values[first_valid]
    assert not np.array_equal(whole.values, lin.values)


def test_points_become_final_only_once_the_window_is_in():
    """Streaming: after each chunk the final points never change later, and they lag the samples
    by at most the filter's half-width (plus a grid step)."""
    x = _trajectory(16.0, 3.0)
    ap = np.sin(2 * np.pi * 1.3 * x)
    t = np.arange(x.size) * DT
    g = AxleGrid(True, DT, MIN_SPEED)
    snapshots = []
    for a in range(0, x.size, 50):
        g.add(x[a : a + 50], ap[a : a + 50], t[a : a + 50], np.ones(min(50, x.size - a), bool), SPACING)
        snapshots.append(g.values.copy())
        lag = x[min(a + 50, x.size) - 1] - g.end * SPACING
        assert 0.0 < lag < 0.4 + SPACING
    g.flush()
    assert g.done == g.size
    for s in snapshots:
        assert np.array_equal(g.values[: s.size], s)


def test_agrees_with_a_finer_profile_band_limited_by_fft():
    """Not the edge's own arithmetic on both sides: a road made on a 1 mm grid (a random walk,
    rough at every wavelength, band-limited by FFT below the samples' Nyquist so the 500 Hz
    samples themselves do not alias), sampled along a varying-speed drive, gridded by the edge;
    the error in the 0.5–50 m band (FFT, on the 5 cm grid) is compared with the road's there."""
    rng = np.random.default_rng(7)
    fine_dx = 0.001
    n_fine = 140_001  # 140 m
    road = np.cumsum(rng.normal(0.0, 1e-4, n_fine))
    k = np.fft.rfftfreq(n_fine, fine_dx)
    spec = np.fft.rfft(road - np.linspace(road[0], road[-1], n_fine))
    spec[k > 12.0] = 0.0  # below 250 Hz / 20 m/s
    road = np.fft.irfft(spec, n_fine)
    fine_x = np.arange(n_fine) * fine_dx
    x = _trajectory(16.0, 7.0, x0=5.0)  # 16 ± 1.6 m/s: sample Nyquist ≥ 14 c/m
    assert x[-1] < fine_x[-1] - 5.0
    ap = np.interp(x, fine_x, road)  # 1 mm steps: linear here is exact to ~1e-6 at 12 c/m

    def in_band(e):  # the 0.5–50 m band of a 5 cm series (brick wall)
        s = np.fft.rfft(e)
        f = np.fft.rfftfreq(e.size, SPACING)
        s[(f < 0.02) | (f > 2.0)] = 0.0
        return np.fft.irfft(s, e.size)

    rel = {}
    for aa in (False, True):
        g, xg = _grid(x, ap, aa)
        truth = road[np.rint(xg / fine_dx).astype(int)]  # the grid points are on the 1 mm grid
        inner = _interior(xg, x, margin=2.0)
        rel[aa] = float(np.std(in_band(g.values - truth)[inner]) / np.std(in_band(truth)[inner]))
    assert rel[True] < 1e-3, rel
    assert rel[False] > 3 * rel[True], rel


def test_points_whose_window_the_pass_ends_cut_are_invalid():
    """Every valid point is the filter's: gridding a longer drive over the same samples gives the
    same value there. Near the pass's end the kernel is cut, and the linear value it would keep
    carries the full-band noise (above the grid's Nyquist) that the filter removes elsewhere."""
    rng = np.random.default_rng(3)
    x = _trajectory(15.0, 4.0)
    ap = rng.normal(0.0, 1e-3, x.size)  # white: the filter changes every point
    m = x.size - 400
    short, xs = _grid(x[:m], ap[:m], True)
    long, _ = _grid(x, ap, True)
    assert short.base == long.base
    k = np.flatnonzero(short.valid)
    assert np.allclose(short.values[k], long.values[k], rtol=0.0, atol=1e-15)
    # only the kernel's reach (≤ 0.36 m, plus a grid step) is given up at the end
    assert x[m - 1] - xs[k[-1]] < 0.4 + SPACING
