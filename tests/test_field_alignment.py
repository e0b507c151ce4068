"""Centring the passes' alignment maps when passes are partial (field drives cut at stops and turns):
a short pass far from chainage 0 must not move the fleet's frame by its ill-determined stretch."""

import numpy as np

from cloud.road.alignment import Alignment, centred, damped, estimate_alignment
from shared.profiles import iso8608_profile, tyre_filter


def test_a_short_pass_far_down_the_route_leaves_the_frame_where_the_passes_are():
    # Two passes over the whole 600 m route, already in the true frame, and a 110 m pass at 430–540 m
    # whose stretch came out at +0.5 % (a short pass's stretch is poorly known): exact at its middle,
    # 0.28 m off at its ends — but 2.4 m off if its line is carried to chainage 0.
    als = [Alignment(0.0, 0.0, 0.0, 1.0), Alignment(0.0, 0.0, 5.0, 1.0), Alignment(-0.005 * 55.0, 0.005, 430.0, 1.0)]
    extents = [(0.0, 600.0), (5.0, 600.0), (430.0, 540.0)]
    x = np.linspace(0.0, 600.0, 61)
    moved = [np.max(np.abs(c.true_to_reported(x) - a.true_to_reported(x))) for a, c in zip(als, centred(als, extents))]
    # The full passes' frames move by what the short pass's stretch tilts the route's mean line (a
    # few cm where the passes are), not by its extrapolated offset.
    assert max(moved[:2]) < 0.1, moved
    # Without the extents the maps are averaged at chainage 0, and every pass moves by ~0.8 m.
    moved_at_origin = [np.max(np.abs(c.true_to_reported(x) - a.true_to_reported(x))) for a, c in zip(als, centred(als))]
    assert min(moved_at_origin[:2]) > 0.5, moved_at_origin


def test_passes_spanning_the_same_stretch_centre_as_before():
    rng = np.random.default_rng(1)
    als = [Alignment(float(b), float(e), 0.0, 1.0) for b, e in zip(rng.normal(0, 2, 5), rng.normal(0, 0.01, 5))]
    extents = [(0.0, 500.0)] * 5
    for a, b in zip(centred(als), centred(als, extents)):
        assert abs(a.shift_m - b.shift_m) < 1e-9 and abs(a.stretch - b.stretch) < 1e-12


def test_a_sweep_over_few_passes_lands_where_they_agree_instead_of_swapping_them():
    # Passes at offsets x_p (reported − true) over the whole road, each placed against the mean of
    # the others where they are held: a full step overshoots by (n + 1)/n — two passes swap for
    # ever, three halve and flip sign. The damped step n/(n + 1) from the second sweep on meets.
    xc = np.arange(0.0, 200.0, 1.0)
    for x in ([1.0, -0.8], [0.9, -0.4, 0.2]):
        x = np.asarray(x)
        n = np.full(xc.size, len(x) - 1)
        held = {"full": [None] * len(x), "damped": [None] * len(x)}  # each pass's map
        for _ in range(6):
            for how, maps in held.items():
                t = [0.0 if m is None else m.shift_m for m in maps]
                est = [Alignment(x[p] - np.mean([x[q] - t[q] for q in range(len(x)) if q != p]), 0.0, 0.0, 1.0)
                       for p in range(len(x))]
                if how == "damped":
                    est = [damped(maps[p], a, xc, n, 0.0, 200.0) for p, a in enumerate(est)]
                maps[:] = centred(est)
        placed = x - np.array([m.shift_m for m in held["damped"]])
        assert np.ptp(placed) < 1e-9, placed
        if len(x) == 2:  # undamped, two passes swap their offset every sweep: after an even number, as reported
            assert abs(np.ptp(x - np.array([m.shift_m for m in held["full"]])) - np.ptp(x)) < 1e-9


def test_the_damped_step_is_the_share_of_the_move_for_few_or_partial_passes_and_all_of_it_else():
    xc = np.arange(0.0, 300.0, 1.0)
    old, est = Alignment(0.2, 0.001, 0.0, 0.9), Alignment(1.0, 0.004, 100.0, 0.9)
    x = np.array([0.0, 100.0, 300.0])
    one = np.ones(xc.size)
    # From nothing (a pass's first sweep): the estimate itself.
    assert damped(None, est, xc, one, 0.0, 300.0) == est
    # One other pass: half-way, maps combined as maps (given at different reference chainages).
    step = damped(old, est, xc, one, 0.0, 300.0)
    assert np.allclose(step.true_to_reported(x), 0.5 * (old.true_to_reported(x) + est.true_to_reported(x)))
    assert step.score == 0.9
    # Ten others over the whole pass: the full step. Ten others over a third of it: damped.
    assert damped(old, est, xc, 10 * one, 0.0, 300.0) == est
    part = np.where(xc < 100.0, 10.0, 0.0)
    step = damped(old, est, xc, part, 0.0, 300.0)
    assert np.allclose(step.true_to_reported(x), old.true_to_reported(x) + 10 / 11 * (est.true_to_reported(x)
                                                                                      - old.true_to_reported(x)))


def test_stretches_no_pass_links_are_centred_each_on_its_own_and_a_lone_pass_keeps_its_place():
    # Two passes at 0–250 m (offsets +1 and −1), two at 400–600 m (+3 and +1) and a lone pass at
    # 700–760 m placed +2 m against a pass that did not align.
    als = [Alignment(1.0, 0.0, 0.0, 1.0), Alignment(-1.0, 0.0, 0.0, 1.0), Alignment(3.0, 0.0, 400.0, 1.0),
           Alignment(1.0, 0.0, 400.0, 1.0), Alignment(2.0, 0.0, 700.0, 1.0)]
    extents = [(0.0, 250.0), (10.0, 240.0), (400.0, 600.0), (420.0, 590.0), (700.0, 760.0)]
    out = centred(als, extents)
    assert np.allclose([a.shift_m for a in out[:2]], [1.0, -1.0], atol=1e-9)
    assert np.allclose([a.shift_m for a in out[2:4]], [1.0, -1.0], atol=1e-9)
    assert out[4] == als[4]
    for a in out:
        assert abs(a.stretch) < 1e-12


def _pass_on(profile, lo: float, hi: float, shift: float, stretch: float, seed: int):
    """A pass's AP over true chainage lo–hi, gridded where it reports itself (5 cm)."""
    h = 0.05
    x_true = np.arange(lo, hi, h)
    al = Alignment(shift, stretch, lo, 1.0)
    x_rep = al.true_to_reported(x_true)
    grid = np.arange(np.ceil(x_rep[0] / h), np.floor(x_rep[-1] / h)) * h
    ap = np.interp(grid, x_rep, profile.at(x_true)) + np.random.default_rng(seed).normal(0, 5e-5, grid.size)
    return grid, ap, al, x_true


def test_a_short_pass_is_placed_by_a_shift_and_a_partial_consensus_does_not_invent_matches():
    profile = tyre_filter(iso8608_profile(800.0, 0.01, "A", seed=3))
    h = 0.05
    xc = np.arange(0.0, 800.0, h)
    # A 55 m pass 3.3 m off: two windows. Against the road they agree (shift and stretch); against
    # a consensus whose second half is another surface (a patch, another lane) the second window
    # matches somewhere else, and the pass is placed by the first one's shift.
    grid, ap, al_true, x_true = _pass_on(profile, 400.0, 455.0, 3.3, 0.002, 1)
    other = tyre_filter(iso8608_profile(800.0, 0.01, "A", seed=11))
    for cons, tol in ((profile.at(xc), 0.03), (np.where(xc < 428.0, profile.at(xc), other.at(xc)), 0.1)):
        al = estimate_alignment(grid, ap, xc, cons)
        assert al is not None
        # Shift alone: off by up to ε·L = 11 cm at the far end.
        assert np.max(np.abs(al.true_to_reported(x_true) - al_true.true_to_reported(x_true))) < tol + 0.02
    # A 115 m pass whose first 30 m the consensus does not cover (the others start later): windows
    # there must not match the zeros beyond the consensus's end.
    grid, ap, al_true, x_true = _pass_on(profile, 50.0, 165.0, 0.3, 0.003, 2)
    cons = np.where((xc >= 82.0) & (xc <= 167.0), profile.at(xc), np.nan)
    al = estimate_alignment(grid, ap, xc, cons)
    assert al is not None
    covered = x_true[x_true >= 82.0]
    assert np.max(np.abs(al.true_to_reported(covered) - al_true.true_to_reported(covered))) < 0.05
