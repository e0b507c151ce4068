"""GNSS alignment of a pass against the consensus: shift and stretch recovered, re-gridding exact."""

from __future__ import annotations

import numpy as np
import pytest

from cloud.alignment import Alignment, estimate_alignment, realign
from shared.profiles import iso8608_profile, tyre_filter
from shared.schema import ApSegment


@pytest.mark.parametrize("bias, stretch", [(0.0, 0.0), (2.3, 0.0), (-4.1, 0.021), (1.2, -0.035)])
def test_shift_and_stretch_are_recovered(bias, stretch):
    h = 0.05
    profile = tyre_filter(iso8608_profile(260.0, 0.01, "A", seed=5))
    x_true = np.arange(10.0, 230.0, h)
    rng = np.random.default_rng(1)
    truth = profile.at(x_true)
    al_true = Alignment(bias, stretch, float(x_true[0]), 1.0)
    x_rep = al_true.true_to_reported(x_true)  # where the pass *thinks* each of its points is
    grid = np.arange(np.ceil(x_rep[0] / h), np.floor(x_rep[-1] / h)) * h
    ap = np.interp(grid, x_rep, truth) + rng.normal(0, 5e-5, grid.size)
    xc = np.arange(0.0, 250.0, h)
    al = estimate_alignment(grid, ap, xc, profile.at(xc))
    assert al is not None and al.score > 0.9
    assert al.stretch == pytest.approx(stretch, abs=0.002)
    # Compare the implied positions rather than (b, x_ref) separately: both define the same map.
    assert np.max(np.abs(al.true_to_reported(x_true) - x_rep)) < 0.15


def test_realign_puts_values_back_on_true_chainage():
    h = 0.05
    al = Alignment(shift_m=1.5, stretch=0.01, x_ref_m=20.0, score=1.0)
    x_true = np.arange(0, 4000) * h

    def f(x):
        return 1e-3 * np.sin(2 * np.pi * x / 7.3)

    x_rep_grid = np.arange(400, 1400) * h  # a segment on the reported grid
    true_pos = al.x_ref_m + (x_rep_grid - al.x_ref_m - al.shift_m) / (1 + al.stretch)
    seg = ApSegment.make(f(true_pos), np.full(x_rep_grid.size, 1e-4), vehicle_id="v", pass_id="p",
                         route_id="R1", tile=0, axle=1, start_index=400, spacing_m=h, calib_version=3,
                         speed_mps=20.0, t_first=0.0, t_last=1.0, seq=0)
    (out,) = realign([seg], al)
    assert out.identity == seg.identity
    assert np.max(np.abs(out.values - f(out.chainage_m))) < 2e-5  # linear interpolation of a 7 m sine
    assert x_true[0] <= out.chainage_m[0]
