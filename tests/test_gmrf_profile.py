"""Tests for cloud.road.gmrf_profile: exact against dense algebra, incremental, calibrated."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from cloud.road.gmrf_profile import GmrfProfile, difference_precision, segment_information
from cloud.export import profile_table
from shared.schema import ApSegment

DX = 0.05
Z95 = 1.959963984540054
WHITE = dict(drift_knot_m=None)  # the white/AR(1) model alone, as the dense references build it


def make_seg(values, sigma, start, pass_id="p0", *, axle=1, tile=0, route="R1", calib=0, vehicle="v1",
             spacing=DX) -> ApSegment:
    values = np.asarray(values, dtype=float)
    return ApSegment.make(values, np.broadcast_to(np.asarray(sigma, dtype=float), values.shape).copy(),
                          vehicle_id=vehicle, pass_id=pass_id, route_id=route, tile=tile, axle=axle,
                          start_index=start, spacing_m=spacing, calib_version=calib, speed_mps=20.0,
                          t_first=0.0, t_last=1.0, seq=tile)


def route_length(P: int) -> float:
    return (P - 1) * DX


def dense_posterior(P, segs, tau, order, rho, ridge, span=None):
    """Mean and marginal sd from dense matrices built independently of the banded code."""
    a, e = span if span is not None else (0, P)
    m = e - a
    D = np.diff(np.eye(m), n=order, axis=0)
    Q = tau * D.T @ D + ridge * np.eye(m)
    b = np.zeros(m)
    for s in segs:
        lo, hi = max(s.start_index, a), min(s.end_index, e)
        if hi <= lo:
            continue
        k = np.arange(s.n)
        C = rho ** np.abs(np.subtract.outer(k, k))
        R = np.diag(s.sigma) @ C @ np.diag(s.sigma)
        full = min(s.end_index, P) - s.start_index  # the estimator clips at the route's end
        Ri = np.linalg.inv(R[:full, :full])
        Q[lo - a : hi - a, lo - a : hi - a] += Ri
        b[lo - a : hi - a] += Ri @ s.values[:full]
    return np.linalg.solve(Q, b), np.sqrt(np.diag(np.linalg.inv(Q)))


def sd_of(snap):
    return (snap.hi95_m - snap.lo95_m) / (2 * Z95)


def random_segments(rng, P, n_segs, max_len=60):
    segs = []
    for j in range(n_segs):
        n = int(rng.integers(5, max_len))
        start = int(rng.integers(0, P - 3))
        segs.append(make_seg(rng.normal(0, 1e-3, n), rng.uniform(3e-4, 2e-3, n), start, f"p{j}",
                             axle=1 + j % 2, tile=j))
    return segs


# -- exactness ----------------------------------------------------------------------------------


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("rho", [0.0, 0.6])
def test_matches_dense_reference(order, rho):
    rng = np.random.default_rng(1)
    P = 121
    # Overlapping segments that together cover the route, one running past its end.
    segs = [make_seg(rng.normal(0, 1e-3, 50), rng.uniform(3e-4, 2e-3, 50), 0, "a"),
            make_seg(rng.normal(0, 1e-3, 60), rng.uniform(3e-4, 2e-3, 60), 35, "b"),
            make_seg(rng.normal(0, 1e-3, 40), rng.uniform(3e-4, 2e-3, 40), 90, "c")]
    tau = 3e5
    g = GmrfProfile({"R1": route_length(P)}, tau=tau, order=order, rho=rho, **WHITE)
    for s in segs:
        g.update(s)
    snap = g.snapshot()["R1"]
    mean, sd = dense_posterior(P, segs, tau, order, rho, g.ridge)
    np.testing.assert_allclose(snap.elevation_m, mean, rtol=0, atol=1e-10 * np.abs(mean).max())
    np.testing.assert_allclose(sd_of(snap), sd, rtol=1e-9)
    np.testing.assert_allclose(snap.lo95_m, mean - Z95 * sd, atol=1e-12)


def test_segment_information_inverts_ar1_covariance():
    rng = np.random.default_rng(2)
    n, rho = 12, -0.4
    y, s = rng.normal(size=n), rng.uniform(0.5, 2.0, n)
    diag, off, rhs = segment_information(y, s, rho)
    Ri = np.diag(diag) + np.diag(off, 1) + np.diag(off, -1)
    R = np.diag(s) @ (rho ** np.abs(np.subtract.outer(np.arange(n), np.arange(n)))) @ np.diag(s)
    np.testing.assert_allclose(Ri @ R, np.eye(n), atol=1e-12)
    np.testing.assert_allclose(rhs, Ri @ y, rtol=1e-12)


def test_difference_precision_is_DtD():
    for order in (1, 2):
        D = np.diff(np.eye(9), n=order, axis=0)
        band = difference_precision(9, order)
        dense = np.diag(band[0]) + sum(np.diag(band[k][: 9 - k], k) + np.diag(band[k][: 9 - k], -k)
                                       for k in range(1, order + 1))
        np.testing.assert_array_equal(dense, D.T @ D)


def test_update_order_does_not_matter():
    rng = np.random.default_rng(3)
    P = 301
    segs = random_segments(rng, P, 25)
    a = GmrfProfile({"R1": route_length(P)}, tau=1e5, rho=0.3)
    b = GmrfProfile({"R1": route_length(P)}, tau=1e5, rho=0.3)
    for s in segs:
        a.update(s)
    for i in rng.permutation(len(segs)):
        b.update(segs[i])
    qa, ba = a.information("R1")
    qb, bb = b.information("R1")
    np.testing.assert_allclose(qa, qb, rtol=1e-13, atol=1e-13 * np.abs(qa).max())
    np.testing.assert_allclose(ba, bb, rtol=0, atol=1e-13 * np.abs(ba).max())
    sa, sb = a.snapshot()["R1"], b.snapshot()["R1"]
    np.testing.assert_allclose(sa.elevation_m, sb.elevation_m, equal_nan=True, atol=1e-15)
    np.testing.assert_array_equal(sa.n_passes, sb.n_passes)


def test_update_then_retract_returns_to_the_prior():
    rng = np.random.default_rng(4)
    P = 301
    segs = random_segments(rng, P, 30)
    fresh = GmrfProfile({"R1": route_length(P)}, tau=1e5, rho=0.5)
    g = GmrfProfile({"R1": route_length(P)}, tau=1e5, rho=0.5)
    scale_q = max(float((1.0 / s.sigma**2).max()) for s in segs) * len(segs)
    scale_b = max(float(np.abs(s.values / s.sigma**2).max()) for s in segs) * len(segs)
    for s in segs:
        g.update(s)
    assert np.all(np.isfinite(g.snapshot()["R1"].elevation_m[g.routes["R1"].cover > 0]))
    for i in rng.permutation(len(segs)):
        g.retract(segs[i])
    q0, b0 = fresh.information("R1")
    q1, b1 = g.information("R1")
    assert np.abs(q1 - q0).max() <= 1e-12 * scale_q
    assert np.abs(b1 - b0).max() <= 1e-12 * scale_b
    assert not g.segments
    assert g.routes["R1"].cover.max() == 0 and g.routes["R1"].passes.max() == 0
    assert np.all(np.isnan(g.snapshot()["R1"].elevation_m))


def test_superseded_segment_replaced_exactly():
    """A recalibrated segment replaces the old one: retract(old) + update(new) == only new."""
    rng = np.random.default_rng(5)
    P = 201
    v = rng.normal(0, 1e-3, P)
    old = make_seg(v, 1e-3, 0, calib=0)
    new = make_seg(v * 1.1, 5e-4, 0, calib=1)
    g = GmrfProfile({"R1": route_length(P)}, tau=1e5)
    ref = GmrfProfile({"R1": route_length(P)}, tau=1e5)
    g.update(old)
    g.retract(old)
    g.update(new)
    ref.update(new)
    np.testing.assert_allclose(g.snapshot()["R1"].elevation_m, ref.snapshot()["R1"].elevation_m, atol=1e-15)
    # The same identity delivered twice replaces rather than adds (idempotent).
    g.update(new)
    np.testing.assert_allclose(g.information("R1")[0], ref.information("R1")[0], rtol=1e-13)


def test_retract_unknown_segment_changes_nothing(caplog):
    g = GmrfProfile({"R1": 5.0}, tau=1e5)
    s = make_seg(np.zeros(10), 1e-3, 0)
    g.update(s)
    q, b = g.information("R1")
    g.retract(make_seg(np.zeros(10), 1e-3, 0, pass_id="other"))
    assert "never added" in caplog.text
    np.testing.assert_array_equal(g.information("R1")[0], q)


def test_accepts():
    g = GmrfProfile({"R1": 5.0})
    assert g.accepts(make_seg(np.zeros(3), 1e-3, 0))
    assert not g.accepts(make_seg(np.zeros(3), 1e-3, 0, route="R2"))
    assert not g.accepts(make_seg(np.zeros(3), 1e-3, 0, spacing=0.1))


def test_set_rho_rebuilds_as_if_built_with_it():
    rng = np.random.default_rng(6)
    P = 201
    segs = random_segments(rng, P, 12)
    g = GmrfProfile({"R1": route_length(P)}, tau=1e5, rho=0.0)
    ref = GmrfProfile({"R1": route_length(P)}, tau=1e5, rho=0.7)
    for s in segs:
        g.update(s)
        ref.update(s)
    g.set_rho(0.7)
    np.testing.assert_allclose(g.information("R1")[0], ref.information("R1")[0], rtol=1e-13)
    np.testing.assert_allclose(g.snapshot()["R1"].elevation_m, ref.snapshot()["R1"].elevation_m,
                               equal_nan=True, atol=1e-15)
    with pytest.raises(ValueError):
        g.set_rho(1.0)


# -- coverage, gaps, NaN ------------------------------------------------------------------------


def test_uncovered_points_are_nan_and_short_gaps_are_bridged():
    rng = np.random.default_rng(7)
    P = 401
    tau = 2e5
    g = GmrfProfile({"R1": route_length(P), "R2": 10.0}, tau=tau, max_gap_m=1.0, **WHITE)
    # [0, 100) and [110, 200): a 0.5 m gap, bridged; [300, 350): separated by 5 m, its own block.
    segs = [make_seg(rng.normal(0, 1e-3, 100), 1e-3, 0, "a"),
            make_seg(rng.normal(0, 1e-3, 90), 1e-3, 110, "a", tile=1),
            make_seg(rng.normal(0, 1e-3, 50), 1e-3, 300, "b", axle=2)]
    for s in segs:
        g.update(s)
    snaps = g.snapshot()
    s = snaps["R1"]
    fin = np.isfinite(s.elevation_m)
    assert fin[:200].all() and not fin[200:300].any() and fin[300:350].all() and not fin[350:].any()
    np.testing.assert_array_equal(s.n_passes[:100], 1)
    np.testing.assert_array_equal(s.n_passes[100:110], 0)  # bridged, but nobody was there
    np.testing.assert_array_equal(s.n_passes[300:350], 0)  # axle 2 does not count as a pass
    for span in ((0, 200), (300, 350)):
        mean, sd = dense_posterior(P, segs, tau, 1, 0.0, g.ridge, span)
        np.testing.assert_allclose(s.elevation_m[span[0] : span[1]], mean, atol=1e-12)
        np.testing.assert_allclose(sd_of(s)[span[0] : span[1]], sd, rtol=1e-9)
    # The bridged gap is interpolated with a wider band than its covered neighbours.
    assert sd_of(s)[105] > 2 * sd_of(s)[50]
    # A route nobody drove: all NaN, and so are its draws.
    assert np.all(np.isnan(snaps["R2"].elevation_m))
    assert np.all(np.isnan(g.sample("R2", 3, rng)))
    # The export leaves uncovered points out.
    table = profile_table(snaps)
    assert table.num_rows == 250
    assert not np.isnan(table.column("elevation_m").to_numpy()).any()
    # A segment entirely beyond the route's end is ignored.
    g.update(make_seg(np.ones(5), 1e-3, P + 10, "z"))
    np.testing.assert_allclose(g.snapshot()["R1"].elevation_m, s.elevation_m, equal_nan=True)


# -- posterior draws -----------------------------------------------------------------------------


def test_sample_has_the_posterior_mean_and_covariance():
    rng = np.random.default_rng(8)
    P = 25
    segs = [make_seg(rng.normal(0, 1e-3, 15), 1e-3, 0, "a"), make_seg(rng.normal(0, 1e-3, 15), 2e-3, 10, "b")]
    tau = 1e6
    g = GmrfProfile({"R1": route_length(P)}, tau=tau, order=2, rho=0.3, **WHITE)
    for s in segs:
        g.update(s)
    q, b = g.information("R1")
    Q = np.diag(q[0]) + sum(np.diag(q[k][: P - k], k) + np.diag(q[k][: P - k], -k) for k in (1, 2))
    cov = np.linalg.inv(Q)
    mean = np.linalg.solve(Q, b)
    n = 100_000
    x = g.sample("R1", n, np.random.default_rng(9))
    assert x.shape == (n, P)
    se = np.sqrt(np.diag(cov) / n)
    assert np.all(np.abs(x.mean(axis=0) - mean) < 5 * se)
    emp = np.cov(x, rowvar=False)
    # Entry-wise standard error of a sample covariance: sqrt((S_ii S_jj + S_ij²) / n).
    se_cov = np.sqrt((np.outer(np.diag(cov), np.diag(cov)) + cov**2) / n)
    assert np.all(np.abs(emp - cov) < 5 * se_cov)


# -- a synthetic fleet -----------------------------------------------------------------------------


def fleet(truth, n_passes, sigma, rng, tile=200, rho=0.0, skip=None):
    """Independent noisy passes over ``truth`` cut into tiles; ``skip(p, t)`` leaves a tile out."""
    segs = []
    P = truth.size
    for p in range(n_passes):
        for t, lo in enumerate(range(0, P, tile)):
            if skip is not None and skip(p, t):
                continue
            hi = min(lo + tile, P)
            e = rng.normal(0, sigma, hi - lo)
            if rho:
                for i in range(1, e.size):  # stationary AR(1) with marginal sd sigma
                    e[i] = rho * e[i - 1] + np.sqrt(1 - rho**2) * e[i]
            segs.append(make_seg(truth[lo:hi] + e, sigma, lo, f"p{p}", tile=t, vehicle=f"v{p % 3}"))
    return segs


def test_learnt_tau_recovers_the_true_roughness():
    rng = np.random.default_rng(10)
    inc_sd = 1e-3
    truth = np.cumsum(rng.normal(0, inc_sd, 6001))
    g = GmrfProfile({"R1": route_length(truth.size)})
    for s in fleet(truth, 4, 3e-4, rng, tile=1000):
        g.update(s)
    g.snapshot()
    assert g.tau["R1"] == pytest.approx(1 / inc_sd**2, rel=0.1)
    # Recomputed (the cache dropped by an update and its retraction), it starts from the learnt τ
    # and stays at the same fixed point.
    tau = g.tau["R1"]
    extra = make_seg(np.zeros(10), 1e-3, 0, "extra")
    g.update(extra)
    g.retract(extra)
    g.snapshot()
    assert g.tau["R1"] == pytest.approx(tau, rel=1e-5)


def test_fleet_error_shrinks_like_one_over_sqrt_passes_and_bands_cover():
    """Data-dominated regime (increments ≫ noise): the posterior sd is ≈ sigma / √n, and the
    actual error follows it. (Where the prior dominates, the error falls more slowly, ~n^-1/4.)"""
    rng = np.random.default_rng(11)
    truth = np.cumsum(rng.normal(0, 1e-3, 4001))
    sigma = 3e-4
    rms = {}
    for n in (1, 4, 16):
        g = GmrfProfile({"R1": route_length(truth.size)})
        for s in fleet(truth, n, sigma, rng, tile=1000):
            g.update(s)
        snap = g.snapshot()["R1"]
        err = snap.elevation_m - truth
        err -= err.mean()  # the level is not identifiable
        rms[n] = np.sqrt(np.mean(err**2))
        sd = sd_of(snap)
        inside = np.mean((truth - truth.mean() + snap.elevation_m.mean() >= snap.lo95_m)
                         & (truth - truth.mean() + snap.elevation_m.mean() <= snap.hi95_m))
        assert inside >= 0.90, (n, inside)
        assert rms[n] == pytest.approx(np.sqrt(np.mean(sd**2)), rel=0.15)
        np.testing.assert_array_equal(snap.n_passes, n)
    assert rms[1] / rms[4] == pytest.approx(2.0, rel=0.2)
    assert rms[1] / rms[16] == pytest.approx(4.0, rel=0.2)


def test_correlated_errors_with_matching_rho_stay_calibrated():
    rng = np.random.default_rng(12)
    truth = np.cumsum(rng.normal(0, 1e-3, 4001))
    segs = fleet(truth, 20, 4e-4, rng, tile=1000, rho=0.7)
    g = GmrfProfile({"R1": route_length(truth.size)}, rho=0.0)
    for s in segs:
        g.update(s)
    assert g.estimate_rho() == pytest.approx(0.7, abs=0.1)
    g.set_rho(0.7)
    snap = g.snapshot()["R1"]
    shift = snap.elevation_m.mean() - truth.mean()
    inside = np.mean((truth + shift >= snap.lo95_m) & (truth + shift <= snap.hi95_m))
    assert inside >= 0.90


def test_tiling_is_invisible():
    """White errors: a pass cut into tiles gives exactly the posterior of the uncut pass."""
    rng = np.random.default_rng(13)
    truth = np.cumsum(rng.normal(0, 1e-3, 1001))
    whole = [make_seg(truth + rng.normal(0, 5e-4, truth.size), rng.uniform(3e-4, 8e-4, truth.size), 0, f"p{p}")
             for p in range(3)]
    # Cut the quantised codes, so that tiles carry exactly the values of the whole pass.
    tiled = [dataclasses.replace(w, values_q=w.values_q[lo : lo + 100], sigma_q=w.sigma_q[lo : lo + 100],
                                 start_index=lo, tile=lo // 100)
             for w in whole for lo in range(0, truth.size, 100)]
    a = GmrfProfile({"R1": route_length(truth.size)})
    b = GmrfProfile({"R1": route_length(truth.size)})
    for s in whole:
        a.update(s)
    for s in tiled:
        b.update(s)
    sa, sb = a.snapshot()["R1"], b.snapshot()["R1"]
    np.testing.assert_allclose(sb.elevation_m, sa.elevation_m, atol=1e-12 * np.abs(sa.elevation_m).max())
    np.testing.assert_allclose(sb.hi95_m - sb.lo95_m, sa.hi95_m - sa.lo95_m, rtol=1e-10)


def test_tile_seams_are_continuous():
    """Tiles seen by different sets of passes: the mean's error has no jump at tile boundaries.

    Noise well above the increments (the prior smooths), so the mean's error is smooth inside a
    tile; an estimator that solved tiles separately would have seam steps ~1.9× the interior ones.
    """
    rng = np.random.default_rng(13)
    tile = 100
    truth = np.cumsum(rng.normal(0, 1e-3, 300 * tile + 1))
    # Pass p covers only the tiles t with (t + p) % 3 != 0, so the pass set changes at every seam.
    segs = fleet(truth, 6, 4e-3, rng, tile=tile, skip=lambda p, t: (t + p) % 3 == 0)
    g = GmrfProfile({"R1": route_length(truth.size)})
    for s in segs:
        g.update(s)
    mu = g.snapshot()["R1"].elevation_m
    step_err = np.diff(mu - truth)  # error of each increment of the mean
    seams = np.arange(tile, truth.size - 1, tile) - 1  # increment from the last point of a tile to the next
    interior = np.setdiff1d(np.arange(step_err.size), seams)
    assert np.sqrt(np.mean(step_err[seams] ** 2)) < 1.2 * np.sqrt(np.mean(step_err[interior] ** 2))
    assert np.abs(step_err[seams]).max() < np.abs(step_err[interior]).max()


# -- speed ------------------------------------------------------------------------------------------


def test_update_and_snapshot_are_fast():
    rng = np.random.default_rng(14)
    P = 200_001  # 10 km at 0.05 m
    truth = np.cumsum(rng.normal(0, 5e-4, P))
    g = GmrfProfile({"R1": route_length(P)})
    segs = fleet(truth, 2, 1e-3, rng, tile=1000)
    g.update(segs[0])
    g.snapshot()  # compile / load the kernels
    t0 = time.perf_counter()
    for s in segs[1:]:
        g.update(s)
    per_update = (time.perf_counter() - t0) / (len(segs) - 1)
    t0 = time.perf_counter()
    snap = g.snapshot()["R1"]  # learns τ from its starting value: several factorisations
    cold = time.perf_counter() - t0
    g.update(segs[0])
    t0 = time.perf_counter()
    g.snapshot()
    warm = time.perf_counter() - t0
    assert np.isfinite(snap.elevation_m).all()
    assert per_update < 1e-3, per_update
    assert warm < 1.0 and cold < 2.0, (warm, cold)


# -- per-pass drift nuisance ----------------------------------------------------------------------


def dense_drift_posterior(P, segs, tau, rho, ridge, knot_m, drift_sd):
    """Mean and marginal sd of R from the joint (R, β) system built densely: every pass's drift
    on hat functions of its own knots, β ~ N(0, drift_sd² I), then R's block of the inverse."""
    D = np.diff(np.eye(P), axis=0)
    passes = sorted({(s.vehicle_id, s.pass_id, s.axle) for s in segs})
    knots = {}
    for key in passes:
        own = [s for s in segs if (s.vehicle_id, s.pass_id, s.axle) == key]
        lo = min(s.start_index for s in own)
        hi = min(max(s.end_index for s in own), P)
        knots[key] = np.arange(int(np.floor(lo * DX / knot_m + 1e-9)), int(np.floor((hi - 1) * DX / knot_m + 1e-9)) + 2)
    K = sum(k.size for k in knots.values())
    col = {}
    off = 0
    for key in passes:
        col[key] = off
        off += knots[key].size
    A = np.zeros((P + K, P + K))
    b = np.zeros(P + K)
    A[:P, :P] = tau * D.T @ D + ridge * np.eye(P)
    A[P:, P:] = np.eye(K) / drift_sd**2
    for s in segs:
        key = (s.vehicle_id, s.pass_id, s.axle)
        full = min(s.end_index, P) - s.start_index
        x = (s.start_index + np.arange(full)) * DX
        G = np.zeros((full, P + K))  # y = R[points] + Σ_j β_j φ_j(x)
        G[np.arange(full), s.start_index + np.arange(full)] = 1.0
        for j, kn in enumerate(knots[key]):
            G[:, P + col[key] + j] = np.clip(1.0 - np.abs(x / knot_m - kn), 0.0, None)
        k = np.arange(full)
        R = np.diag(s.sigma[:full]) @ (rho ** np.abs(np.subtract.outer(k, k))) @ np.diag(s.sigma[:full])
        Ri = np.linalg.inv(R)
        A += G.T @ Ri @ G
        b += G.T @ Ri @ s.values[:full]
    cov = np.linalg.inv(A)
    return np.linalg.solve(A, b)[:P], np.sqrt(np.diag(cov)[:P])


@pytest.mark.parametrize("rho", [0.0, 0.5])
def test_drift_nuisance_matches_the_dense_joint_posterior(rho):
    """The marginalised drift (eliminated by Schur complement on a banded factor) is exactly the
    dense joint posterior's marginal, for passes of different extents cut into tiles."""
    rng = np.random.default_rng(21)
    P = 301  # 15 m
    segs = []
    for p, (lo, hi) in enumerate(((0, 301), (40, 301), (0, 250), (90, 210))):
        for t, a in enumerate(range(lo, hi, 70)):
            n = min(70, hi - a)
            segs.append(make_seg(rng.normal(0, 1e-3, n), rng.uniform(3e-4, 1e-3, n), a, f"p{p}", tile=t))
    g = GmrfProfile({"R1": route_length(P)}, tau=2e5, rho=rho, drift_knot_m=2.5, drift_sd_m=5e-4)
    for s in segs:
        g.update(s)
    snap = g.snapshot()["R1"]
    mean, sd = dense_drift_posterior(P, segs, 2e5, rho, g.ridge, 2.5, 5e-4)
    np.testing.assert_allclose(snap.elevation_m, mean, rtol=0, atol=1e-9 * np.abs(mean).max())
    np.testing.assert_allclose(sd_of(snap), sd, rtol=1e-7)
    # The drift widens the band beyond the drift-free posterior's.
    white = GmrfProfile({"R1": route_length(P)}, tau=2e5, rho=rho, **WHITE)
    for s in segs:
        white.update(s)
    assert np.all(sd_of(snap) > sd_of(white.snapshot()["R1"]))


def test_drift_nuisance_retracts_exactly_and_draws_its_posterior():
    rng = np.random.default_rng(22)
    P = 401
    truth = np.cumsum(rng.normal(0, 1e-3, P))
    segs = fleet(truth, 5, 4e-4, rng, tile=100)
    extra = [make_seg(truth[a : a + 100] + 2e-3, 4e-4, a, "late", tile=t) for t, a in enumerate(range(0, 400, 100))]
    kw = dict(tau=1e6, drift_knot_m=5.0)
    g = GmrfProfile({"R1": route_length(P)}, **kw)
    ref = GmrfProfile({"R1": route_length(P)}, **kw)
    for s in segs:
        g.update(s)
        ref.update(s)
    for s in extra:
        g.update(s)
    g.snapshot()
    for s in extra:
        g.retract(s)
    a, b = g.snapshot()["R1"], ref.snapshot()["R1"]
    assert g.drift_sd["R1"] == pytest.approx(ref.drift_sd["R1"], rel=1e-9)
    np.testing.assert_allclose(a.elevation_m, b.elevation_m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sd_of(a), sd_of(b), rtol=1e-9)
    # Draws carry the marginalised drift: their spread is the snapshot's band.
    x = g.sample("R1", 4000, np.random.default_rng(3))
    np.testing.assert_allclose(x.std(axis=0), sd_of(a), rtol=0.1)
    assert np.abs(x.mean(axis=0) - a.elevation_m).max() < 5 * sd_of(a).max() / np.sqrt(4000)


def _drifting_fleet(rng, truth, n_passes, drift_level, sigma):
    """Passes with white errors and their own drift: twice-integrated white noise less its line
    (what drift control leaves), a different process from the estimator's hat-function model."""
    P = truth.size
    segs = []
    for p in range(n_passes):
        d = np.cumsum(np.cumsum(rng.normal(0, drift_level, P)))
        d -= np.polyval(np.polyfit(np.arange(P), d, 1), np.arange(P))
        y = truth + d + rng.normal(0, sigma, P)
        segs += [make_seg(y[a : a + 1000], sigma, a, f"p{p}", tile=t) for t, a in enumerate(range(0, P, 1000))]
    return segs


def _covered(snap, truth):
    shift = np.mean(snap.elevation_m - truth)
    return np.mean((truth + shift >= snap.lo95_m) & (truth + shift <= snap.hi95_m))


def test_drift_level_is_learnt_from_the_data():
    """White errors only: the evidence puts the drift at exactly zero and the posterior is the
    drift-free one. Passes that drift: over independent fleets the learnt level is the drift's
    size, and the band holds ~95 % of the truth where the drift-free band holds far less. (One
    200 m route is a poor judge on its own: its long-wave error is a couple of numbers.)"""
    rng = np.random.default_rng(23)
    P = 4001  # 200 m
    truth = np.cumsum(rng.normal(0, 1e-3, P))
    g = GmrfProfile({"R1": route_length(P)}, tau=1e6, drift_knot_m=25.0)
    w = GmrfProfile({"R1": route_length(P)}, tau=1e6, **WHITE)
    for s in fleet(truth, 8, 3e-4, rng, tile=1000):
        g.update(s)
        w.update(s)
    np.testing.assert_array_equal(g.snapshot()["R1"].hi95_m, w.snapshot()["R1"].hi95_m)
    assert g.drift_sd["R1"] == 0.0
    cover = {"drift": [], "white": []}
    for _ in range(8):
        truth = np.cumsum(rng.normal(0, 1e-3, P))
        segs = _drifting_fleet(rng, truth, 8, 6e-8, 3e-4)
        g = GmrfProfile({"R1": route_length(P)}, tau=1e6, drift_knot_m=25.0)
        w = GmrfProfile({"R1": route_length(P)}, tau=1e6, **WHITE)
        for s in segs:
            g.update(s)
            w.update(s)
        cover["drift"].append(_covered(g.snapshot()["R1"], truth))
        cover["white"].append(_covered(w.snapshot()["R1"], truth))
        assert 3e-4 < g.drift_sd["R1"] < 1.5e-3, g.drift_sd  # the drifts' rms is ~0.75 mm
    assert np.mean(cover["white"]) < 0.6, cover
    assert 0.88 <= np.mean(cover["drift"]) <= 0.99, cover
