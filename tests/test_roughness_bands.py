"""IRI bands hold the truth: the draws the IRI is computed from carry every error term the profile band has.

The passes here are made by a different process than the estimator assumes: each pass has white
noise at its stated level, its own integration drift (twice-integrated white noise, drift-controlled)
and its own calibration error — a gain on the road's 1–30 m band, which moves the IRI to first order.
The estimator sees only the segments.
"""

from __future__ import annotations

import numpy as np

from cloud.road.gmrf_profile import GmrfProfile
from cloud.road.long_wave import drift_of, pass_error_draws, pass_error_variance
from cloud.export import profile_draws
from shared.profiles.iso8608 import iso8608_profile
from shared.roughness import iri_segments
from tests.test_profile_coverage import DX, detrend, tile_segments


def _moving_average(x, w):
    return np.convolve(x, np.ones(w) / w, mode="same")


def _iri_coverage(seed: int, length_m=300.0, n_passes=8, gain_sd=0.03, sigma=3e-4, drift_level=3e-8, n_draws=200):
    """Whether the truth's IRI per 100 m lies in the 95 % band, from posterior draws without and with
    the pass-error term (drift nuisance on: the band's long-wave part is the posterior's own, the
    passes' scatter adds what exceeds it)."""
    rng = np.random.default_rng(seed)
    road = iso8608_profile(length_m, DX, "B", seed=rng).elevation_m
    n = road.size
    band = _moving_average(road, 21) - _moving_average(road, 601)  # 1–30 m
    segs = []
    for p in range(n_passes):
        drift = detrend(np.cumsum(np.cumsum(rng.normal(0.0, drift_level, n))))
        y = road + gain_sd * rng.standard_normal() * band + drift + rng.normal(0.0, sigma, n)
        segs += tile_segments(y, sigma, f"p{p}")
    g = GmrfProfile({"R1": (n - 1) * DX}, drift_knot_m=25.0)
    for s in segs:
        g.update(s)
    snap = g.snapshot()["R1"]
    x = snap.chainage_m
    post = g.sample("R1", n_draws, rng)
    drift = drift_of(g, "R1")
    err = pass_error_draws(snap, segs, n_draws, rng, drift=drift)
    full = profile_draws(g, "R1", snap, segs, n_draws, rng)  # what the export computes the IRI from
    # The draws' error has the band's variance (drawn, so to within sampling).
    v = pass_error_variance(snap, segs, drift=drift)
    inner = slice(600, n - 600)  # away from the ends, where the band filters are whole
    assert np.allclose(err[:, inner].var(axis=0).mean(), v[inner].mean(), rtol=0.15)
    _, _, truth = iri_segments(x, road, 100.0)
    out = []
    for draws in (post, full):
        _, _, iri = iri_segments(x, draws, 100.0)
        lo, hi = np.quantile(iri, 0.025, axis=0), np.quantile(iri, 0.975, axis=0)
        out.append((truth >= lo) & (truth <= hi))
    return out


def test_iri_band_holds_the_truth_with_the_pass_error_term():
    """Over 8 fleets × 3 segments of 100 m: with the pass-error term in the draws the IRI's 95 %
    band holds the truth's IRI in 21 of 24 segments (measured 0.875; the segments of one fleet share
    its calibration gains, so this is closer to 8 trials than 24); from the posterior alone (what
    the exported IRI band was) in 4 of 24 (0.17)."""
    without, with_err = [], []
    for seed in range(8):
        a, b = _iri_coverage(seed)
        without.append(a)
        with_err.append(b)
    cover_without, cover_with = np.mean(np.concatenate(without)), np.mean(np.concatenate(with_err))
    assert cover_with >= 0.8, (cover_with, with_err)
    assert cover_without <= 0.4, (cover_without, without)
