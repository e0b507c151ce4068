"""GNSS alignment of a pass against the consensus: shift and stretch recovered, re-gridding exact."""

from __future__ import annotations

import numpy as np
import pytest

from cloud.daemon.core import Cloud
from cloud.daemon.settings import CloudSettings
from cloud.road.alignment import Alignment, centred, estimate_alignment, realign
from shared import keys
from shared.profiles import iso8608_profile, tyre_filter
from shared.registry import Route, Site, VehicleClass
from shared.schema import ApSegment, PassDone


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
    assert np.max(np.abs(out.values - f(out.chainage_m))) < 1e-7  # cubic interpolation of a 7 m sine
    assert x_true[0] <= out.chainage_m[0]


def test_a_stretch_that_disagrees_with_the_consensus_does_not_bias_the_alignment():
    """Windows are fitted by a robust line: 30 m of the pass on a different surface (a patch, another
    lane) is an outlier, not a shift."""
    h = 0.05
    profile = tyre_filter(iso8608_profile(260.0, 0.01, "A", seed=8))
    other = tyre_filter(iso8608_profile(260.0, 0.01, "A", seed=9))
    x_true = np.arange(10.0, 230.0, h)
    truth = profile.at(x_true)
    patch = (x_true > 100.0) & (x_true < 130.0)
    truth[patch] = other.at(x_true[patch])
    al_true = Alignment(3.1, -0.018, float(x_true[0]), 1.0)
    x_rep = al_true.true_to_reported(x_true)
    grid = np.arange(np.ceil(x_rep[0] / h), np.floor(x_rep[-1] / h)) * h
    ap = np.interp(grid, x_rep, truth)
    xc = np.arange(0.0, 250.0, h)
    al = estimate_alignment(grid, ap, xc, profile.at(xc))
    assert al is not None
    assert np.max(np.abs(al.true_to_reported(x_true) - x_rep)) < 0.05


def test_realigned_segments_carry_the_true_speed_and_their_own_time_span():
    """The calibration's time base is chainage over time: after re-gridding both must be true."""
    h, v_true, eps = 0.05, 20.0, 0.02
    al = Alignment(shift_m=0.7, stretch=eps, x_ref_m=0.0, score=1.0)
    x_rep = np.arange(1000, 2000) * h
    t = (al.reported_to_true(x_rep)) / v_true  # the vehicle passed true chainage x at x / v
    seg = ApSegment.make(np.zeros(x_rep.size), np.full(x_rep.size, 1e-4), vehicle_id="v", pass_id="p",
                         route_id="R1", tile=1, axle=1, start_index=1000, spacing_m=h, calib_version=0,
                         speed_mps=v_true * (1 + eps), t_first=float(t[0]), t_last=float(t[-1]), seq=0)
    (out,) = realign([seg], al)
    assert out.speed_mps == pytest.approx(v_true, rel=1e-12)
    x = out.chainage_m
    assert (x[-1] - x[0]) / (out.t_last - out.t_first) == pytest.approx(v_true, rel=1e-9)
    assert out.t_first == pytest.approx(x[0] / v_true, abs=1e-9)


@pytest.mark.parametrize("stretch", [0.021, -0.017])
def test_abutting_segments_still_abut_after_realignment(stretch):
    """No one-point holes or overlaps at the seams (a hole costs the calibration metres around it)."""
    h = 0.05
    al = Alignment(shift_m=-1.3, stretch=stretch, x_ref_m=5.0, score=1.0)

    def f(x):
        return 1e-3 * np.sin(2 * np.pi * x / 3.7)

    segs = []
    for k, (a, b) in enumerate([(200, 1000), (1000, 2000), (2000, 2600), (2700, 3000)]):  # a real hole
        x_rep = np.arange(a, b) * h
        segs.append(ApSegment.make(f(al.reported_to_true(x_rep)), np.full(b - a, 1e-4), vehicle_id="v", pass_id="p",
                                   route_id="R1", tile=k, axle=1, start_index=a, spacing_m=h, calib_version=0,
                                   speed_mps=20.0, t_first=a * h / 20, t_last=(b - 1) * h / 20, seq=k))
    out = sorted(realign(segs, al), key=lambda s: s.start_index)
    assert [s.tile for s in out] == [0, 1, 2, 3]
    assert out[0].end_index == out[1].start_index and out[1].end_index == out[2].start_index
    assert out[3].start_index - out[2].end_index > 50  # the hole stays a hole
    for s in out:
        assert np.max(np.abs(s.values - f(s.chainage_m))) < 1e-7


def test_realigned_segments_keep_the_edges_error_model():
    """The edge's AP error model (and the pass's segment count) travel with the re-gridded segment:
    without it the cloud would weigh an aligned pass by its white σ alone, unlike the same pass
    unaligned."""
    h = 0.05
    al = Alignment(shift_m=0.9, stretch=-0.012, x_ref_m=10.0, score=1.0)
    x_rep = np.arange(300, 1300) * h
    model = np.array([1.7, 2.5, -1.1, 0.2])  # [r, c0, c1, c2]: a banded, positive definite precision
    seg = ApSegment.make(1e-3 * np.sin(x_rep), np.full(x_rep.size, 2e-4), vehicle_id="v", pass_id="p",
                         route_id="R1", tile=0, axle=1, start_index=300, spacing_m=h, calib_version=2,
                         speed_mps=18.0, t_first=0.0, t_last=2.7, seq=0, n_segments_in_pass=1, error_model=model)
    (out,) = realign([seg], al)
    assert out.start_index != seg.start_index  # really re-gridded
    np.testing.assert_array_equal(out.error_model, seg.error_model)
    assert out.n_segments_in_pass == 1


def test_centred_maps_average_to_the_identity_at_every_chainage():
    """The consensus frame is the passes' mean frame: after centring, a feature's reported position
    averages to where the consensus puts it, everywhere along the route — also when the passes start
    at different places with stretches that correlate with where they start (centring each pass's
    shift at its own start would leave cov(ε, x_ref) in the frame)."""
    rng = np.random.default_rng(2)
    x_ref = np.linspace(0.0, 80.0, 9)
    als = [Alignment(float(b), float(e), float(x0), 1.0)
           for b, e, x0 in zip(rng.normal(0, 2.0, 9), 0.02 + 0.001 * x_ref, x_ref)]  # ε grows with x_ref
    out = centred(als)
    x = np.linspace(0.0, 300.0, 7)
    mean_map = np.mean([a.true_to_reported(x) for a in out], axis=0)
    np.testing.assert_allclose(mean_map, x, atol=1e-9)
    # Each pass keeps its place relative to the others: only the common frame moved.
    before = np.array([a.true_to_reported(x) for a in als])
    frame = np.mean(before, axis=0)  # F(x): the old frame's mean map
    for b, a in zip(before, out):
        np.testing.assert_allclose(a.true_to_reported(frame), b, atol=1e-9)  # T_p = (T_p ∘ F⁻¹) ∘ F
    assert [a.x_ref_m for a in out] == [a.x_ref_m for a in als]
    # Maps already centred stay as they are.
    again = centred(out)
    for a, b in zip(again, out):
        assert a.shift_m == pytest.approx(b.shift_m, abs=1e-12) and a.stretch == pytest.approx(b.stretch, abs=1e-15)


def _send_pass(cloud: Cloud, i: int, al: Alignment, version: int, profile, rng) -> None:
    """Pass ``i`` of a GNSS-biased fleet into the core: its AP on the grid of its reported chainage
    (``al``: true → reported), cut into tiles, then its pass-done."""
    h = 0.05
    x_true = np.arange(10.0, 190.0, h)
    x_rep = al.true_to_reported(x_true)
    i0, i1 = int(np.ceil(x_rep[0] / h)), int(np.floor(x_rep[-1] / h))
    ap = np.interp(np.arange(i0, i1) * h, x_rep, profile.at(x_true)) + rng.normal(0, 2e-5, i1 - i0)
    starts = list(range(i0, i1, 1000))
    for k, a in enumerate(starts):
        z = min(a + 1000, i1)
        seg = ApSegment.make(ap[a - i0 : z - i0], np.full(z - a, 1e-4), vehicle_id=f"v{i}", pass_id=f"p{i}",
                             route_id="R1", tile=k, axle=1, start_index=a, spacing_m=h, calib_version=version,
                             speed_mps=20.0, t_first=a * h / 20, t_last=(z - 1) * h / 20, seq=k)
        cloud.on_segment(keys.ap_key("t", "R1", k, f"v{i}"), seg.encode())
    done = PassDone(f"v{i}", f"p{i}", "R1", version, len(starts), "quarter_car")
    cloud.on_done(keys.done_key("t", f"v{i}"), done.encode())


def test_alignment_is_idle_work_and_places_passes_in_the_fleets_mean_frame():
    """Default settings align, but never on the ingest path: segments and pass-dones only note what
    is due; the sweep (idle) places every pass in the fleet's mean frame — each estimated map is the
    true one composed with the inverse of the mean of the true maps — and a pass recomputed later
    is re-gridded with its alignment when idle again, not when it arrives."""
    site = Site(routes=(Route(id="R1", length_m=200.0),),
                vehicle_classes=(VehicleClass(model="quarter_car", mean={"M": 1.0}, std={"M": 0.1}),))
    profile = tyre_filter(iso8608_profile(220.0, 0.01, "A", seed=5))
    rng = np.random.default_rng(3)
    cloud = Cloud("t", site, lambda k, p: None, CloudSettings(calibration="nominal", continuous_aps=False))
    assert cloud.settings.align  # on by default
    truth = [Alignment(float(rng.normal(0, 2.0)), float(rng.normal(0, 0.01)), 10.0, 1.0) for _ in range(6)]
    for i, al in enumerate(truth):
        _send_pass(cloud, i, al, 0, profile, rng)
    agg = cloud.aggregator
    assert len(agg.passes) == 6 and all(ps.acked for ps in agg.passes.values())
    assert not cloud.alignments and all(agg.held[sl] is agg.segments[sl] for sl in agg.held)  # ingest only
    assert cloud.maybe_align()
    while cloud.maybe_align():  # one sweep per idle call, until the series ends
        pass
    x = np.linspace(10.0, 190.0, 5)
    for i, want in enumerate(centred(truth)):  # the true maps about their own mean frame
        got = cloud.alignments[(f"v{i}", f"p{i}")]
        # 2 cm: the windows' fit on a noise-free AP places passes to mm; the consensus each is fitted
        # against is still a mean of passes a few mm apart.
        assert np.max(np.abs(got.true_to_reported(x) - want.true_to_reported(x))) < 0.02, i
    assert all(agg.held[sl] is not agg.segments[sl] for sl in agg.held)  # every pass moved metres: re-gridded
    # The pass comes back recomputed (a new calibration version): held as it arrived until idle.
    _send_pass(cloud, 0, truth[0], 1, profile, rng)
    slots = sorted(agg.passes[("v0", "p0")].slots)
    assert all(agg.held[sl] is agg.segments[sl] for sl in slots)
    while cloud.maybe_align():
        pass
    assert all(agg.held[sl] is not agg.segments[sl] for sl in slots)
