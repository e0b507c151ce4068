"""A long pass against a short consensus: a stretch the overlap cannot confirm is not applied."""

from __future__ import annotations

import numpy as np
import pytest

from cloud.road.alignment import Alignment, estimate_alignment
from shared.profiles import iso8608_profile, tyre_filter


def test_a_long_pass_against_a_short_consensus_is_not_stretched_by_windows_past_its_end():
    """The consensus (another pass, 52 m) covers only the last part of a 122 m pass. The pass's road
    just before the consensus starts repeats the consensus's first metres 9 m further on, so windows
    the consensus only partly covers find false peaks metres away; a line through them and the true
    windows is a stretch of several per cent that only one window of the fine stage confirms. The
    pass's chainage has a shift and no stretch: it must be placed by its shift, stretch left alone."""
    h = 0.05
    profile = tyre_filter(iso8608_profile(260.0, 0.01, "A", seed=1))
    rng = np.random.default_rng(1)
    x_true = np.arange(48.0, 170.0, h)
    road = np.where(x_true < 110.0, profile.at(x_true + 9.0), profile.at(x_true))
    al_true = Alignment(-0.8, 0.0, float(x_true[0]), 1.0)
    x_rep = al_true.true_to_reported(x_true)
    grid = np.arange(np.ceil(x_rep[0] / h), np.floor(x_rep[-1] / h)) * h
    ap = np.interp(grid, x_rep, road) + rng.normal(0, 5e-5, grid.size)
    xc = np.arange(0.0, 250.0, h)
    cons = np.where((xc >= 110.0) & (xc <= 162.0), profile.at(xc) + rng.normal(0, 5e-5, xc.size), np.nan)
    al = estimate_alignment(grid, ap, xc, cons)
    assert al is not None and al.score > 0.5
    # The 52 m overlap identifies a stretch to a few per mille at best; a per-cent stretch is false.
    assert al.stretch == pytest.approx(0.0, abs=0.005)
    overlap = (x_true > 110.0) & (x_true < 162.0)
    # As in test_alignment: the implied positions where the pass meets the consensus, within 15 cm.
    assert np.max(np.abs(al.true_to_reported(x_true[overlap]) - x_rep[overlap])) < 0.15


@pytest.mark.parametrize("seed, repeat_m", [(5, 3.0), (3, 9.0)])
def test_a_window_partly_past_the_consensus_does_not_drag_the_line(seed, repeat_m):
    """A 78 m pass whose first 22 m lie before the consensus starts, on road that repeats the
    consensus's first metres ``repeat_m`` further on: its first window finds a false peak metres
    away. Of four windows, three agree on a plausible stretch; the false one must neither tilt the
    line (a stretch of per cents, metres off) nor make the pass unplaceable."""
    h = 0.05
    profile = tyre_filter(iso8608_profile(260.0, 0.01, "A", seed=seed))
    rng = np.random.default_rng(seed)
    x_true = np.arange(40.0, 118.0, h)
    road = np.where(x_true < 62.0, profile.at(x_true + repeat_m), profile.at(x_true))
    al_true = Alignment(-0.8, 0.0, float(x_true[0]), 1.0)
    x_rep = al_true.true_to_reported(x_true)
    grid = np.arange(np.ceil(x_rep[0] / h), np.floor(x_rep[-1] / h)) * h
    ap = np.interp(grid, x_rep, road) + rng.normal(0, 5e-5, grid.size)
    xc = np.arange(0.0, 250.0, h)
    cons = np.where(xc >= 62.0, profile.at(xc) + rng.normal(0, 5e-5, xc.size), np.nan)
    al = estimate_alignment(grid, ap, xc, cons)
    assert al is not None and al.score > 0.5
    assert al.stretch == pytest.approx(0.0, abs=0.005)  # 56 m of overlap: a few per mille at most
    overlap = x_true > 62.0
    assert np.max(np.abs(al.true_to_reported(x_true[overlap]) - x_rep[overlap])) < 0.15  # as test_alignment
