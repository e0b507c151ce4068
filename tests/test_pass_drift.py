"""The per-pass drift nuisance (cloud.road.pass_drift), eliminated locally, against dense algebra.

The estimator eliminates the profile chunk by chunk between separators at the knots; the references
here build the whole joint (profile + every pass's knot coefficients) densely and invert it, so any
coupling the local elimination dropped would show.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from cloud.road.gmrf_profile import GmrfProfile
from cloud.road.pass_drift import DRIFT_PRIOR_SCALE, log_prior, stated_error_sd
from tests.test_gmrf_profile import DX, make_seg, route_length, sd_of


def _knots(segs, key, a, e, knot_m):
    own = [s for s in segs if (s.vehicle_id, s.pass_id, s.axle) == key]
    lo = max(min(s.start_index for s in own), a)
    hi = min(max(s.end_index for s in own), e)
    return np.arange(math.floor(lo * DX / knot_m + 1e-9), math.floor((hi - 1) * DX / knot_m + 1e-9) + 2)


def dense_joint(segs, a, e, tau, order, rho, ridge, knot_m):
    """Joint precision (without the drift prior), information vector and K of block ``[a, e)``."""
    m = e - a
    inside = [s for s in segs if s.start_index >= a and s.start_index < e]
    passes = sorted({(s.vehicle_id, s.pass_id, s.axle) for s in inside})
    knots = {key: _knots(inside, key, a, e, knot_m) for key in passes}
    col, K = {}, 0
    for key in passes:
        col[key] = K
        K += knots[key].size
    D = np.diff(np.eye(m), n=order, axis=0)
    A = np.zeros((m + K, m + K))
    b = np.zeros(m + K)
    A[:m, :m] = tau * D.T @ D + ridge * np.eye(m)
    for s in inside:
        key = (s.vehicle_id, s.pass_id, s.axle)
        full = min(s.end_index, e) - s.start_index
        x = (s.start_index + np.arange(full)) * DX
        G = np.zeros((full, m + K))  # y = R[points] + Σ_j β_j φ_j(x)
        G[np.arange(full), s.start_index - a + np.arange(full)] = 1.0
        for j, kn in enumerate(knots[key]):
            G[:, m + col[key] + j] = np.clip(1.0 - np.abs(x / knot_m - kn), 0.0, None)
        k = np.arange(full)
        if s.error_model.size:  # the edge's banded error model: R⁻¹ = D⁻¹ T D⁻¹, T Toeplitz
            lag = np.abs(np.subtract.outer(k, k))
            T = np.where(lag < s.error_model.size - 1, s.error_model[1:][np.minimum(lag, s.error_model.size - 2)], 0.0)
            Dinv = np.diag(1.0 / (s.error_model[0] * s.sigma[:full]))
            Ri = Dinv @ T @ Dinv
        else:
            R = np.diag(s.sigma[:full]) @ (rho ** np.abs(np.subtract.outer(k, k))) @ np.diag(s.sigma[:full])
            Ri = np.linalg.inv(R)
        A += G.T @ Ri @ G
        b += G.T @ Ri @ s.values[:full]
    return A, b, m, K


def dense_marginal(A, b, m, K, s2):
    A = A.copy()
    A[m:, m:] += np.eye(K) / s2
    return np.linalg.solve(A, b)[:m], np.sqrt(np.diag(np.linalg.inv(A))[:m])


def dense_log_evidence(A, b, m, K, s2):
    """The drift-dependent part of log p(y | s²): ½bᵀA⁻¹b − ½log|A| − ½K log s² less its s² → 0 limit."""
    J = A.copy()
    J[m:, m:] += np.eye(K) / s2
    ref = 0.5 * b[:m] @ np.linalg.solve(A[:m, :m], b[:m]) - 0.5 * np.linalg.slogdet(A[:m, :m])[1]
    return 0.5 * b @ np.linalg.solve(J, b) - 0.5 * np.linalg.slogdet(J)[1] - 0.5 * K * math.log(s2) - ref


def _passes(rng, extents, tile=70, drift=0.0, first_tile=0, error_model=None):
    segs = []
    for p, (lo, hi) in enumerate(extents):
        x = np.arange(lo, hi) * DX
        d = drift * np.sin(x / 1.7 + p)  # a smooth per-pass error, not the model's hats
        for t, a in enumerate(range(lo, hi, tile)):
            n = min(tile, hi - a)
            seg = make_seg(rng.normal(0, 1e-3, n) + d[a - lo : a - lo + n], rng.uniform(3e-4, 1e-3, n), a,
                           f"p{p}", tile=first_tile + t, vehicle=f"v{p % 2}")
            if error_model is not None and p % 2 == 0:  # every other pass with the edge's own model
                seg = dataclasses.replace(seg, error_model=np.asarray(error_model, dtype=float))
            segs.append(seg)
    return segs


EDGE_MODEL = [1.3, 2.0, -0.7, 0.15, -0.02]  # [r, c₀..c₃]: a 4-band Toeplitz precision (positive definite)


@pytest.mark.parametrize("order,rho,knot_m,model", [(1, 0.0, 2.5, None), (2, 0.5, 2.5, None), (1, 0.5, 2.37, None),
                                                    (2, 0.0, 1.13, None), (1, 0.3, 2.5, EDGE_MODEL),
                                                    (2, 0.0, 0.17, EDGE_MODEL)])
def test_local_elimination_is_the_dense_joint_posterior(order, rho, knot_m, model):
    """Random walk of order 1 and 2 (separators of 1 and 2 points), AR(1) errors and the edge's
    banded error model (which couple a point to its neighbours' knots; with knots 3.4 grid steps
    apart, to knots two away), knots on and off the grid, passes of different extents: the mean
    and band are the dense joint posterior's marginal."""
    rng = np.random.default_rng(31)
    P = 321
    segs = _passes(rng, ((0, 321), (40, 321), (0, 250), (90, 210), (300, 321)), error_model=model)
    tau, s2 = 2e5 if order == 1 else 2e7, 4e-7
    g = GmrfProfile({"R1": route_length(P)}, tau=tau, order=order, rho=rho, drift_knot_m=knot_m,
                    drift_sd_m=math.sqrt(s2))
    for s in segs:
        g.update(s)
    snap = g.snapshot()["R1"]
    mean, sd = dense_marginal(*dense_joint(segs, 0, P, tau, order, rho, g.ridge, knot_m), s2)
    np.testing.assert_allclose(snap.elevation_m, mean, rtol=0, atol=1e-9 * np.abs(mean).max())
    np.testing.assert_allclose(sd_of(snap), sd, rtol=1e-7)


def test_blocks_across_a_gap_and_the_learnt_level_are_the_dense_ones():
    """A gap longer than max_gap_m splits the route into blocks solved apart (a pass's drift has
    independent coefficients on either side); the level is learnt from the evidence summed over
    the blocks, and it is the maximiser of the dense evidence times the level's prior."""
    rng = np.random.default_rng(32)
    P = 361
    segs = _passes(rng, ((0, 150), (0, 150), (30, 150)), drift=1e-3)
    segs += _passes(rng, ((200, 361), (210, 361), (200, 300)), drift=1e-3, first_tile=10)  # the same passes
    tau, knot_m = 2e5, 2.5
    g = GmrfProfile({"R1": route_length(P)}, tau=tau, drift_knot_m=knot_m, max_gap_m=1.0)
    for s in segs:
        g.update(s)
    snap = g.snapshot()["R1"]
    blocks = [(0, 150), (200, 361)]
    joints = [dense_joint(segs, a, e, tau, 1, 0.0, g.ridge, knot_m) for a, e in blocks]
    s0 = DRIFT_PRIOR_SCALE * stated_error_sd(segs)
    levels = {}
    for name, prior in (("map", s0), ("ml", None)):
        res = minimize_scalar(lambda u: -sum(dense_log_evidence(*j, math.exp(u)) for j in joints)
                              - log_prior(math.exp(u), prior),
                              bounds=(math.log(1e-12), math.log(1e-4)), method="bounded", options={"xatol": 1e-6})
        assert -res.fun > 1.0  # the data do show drift
        levels[name] = math.exp(res.x)
    assert levels["map"] < levels["ml"]  # the prior only pulls the level down
    # The mean at the MAP level, the band at the larger (here the ML one) about it.
    assert g.drift_mean_sd["R1"] == pytest.approx(math.sqrt(levels["map"]), rel=1e-3)
    assert g.drift_sd["R1"] == pytest.approx(math.sqrt(levels["ml"]), rel=1e-3)
    # ... to far below the optimiser's value tolerance: the dense score equation (EM fixed point)
    # s² = E[βᵀβ | y] / (K + s²/s₀²) holds at each learnt level (s₀ → ∞ for the ML one; a stop ~1e-6
    # short of the maximum would depend on the rounding of the sums, i.e. on the order the segments
    # arrived in).
    s2_mean, s2_band = g.drift_mean_sd["R1"] ** 2, g.drift_sd["R1"] ** 2
    for s2, prior_term in ((s2_mean, 1.0 / s0**2), (s2_band, 0.0)):
        stat = K = 0.0
        for A, b, m, k in joints:
            J = A.copy()
            J[m:, m:] += np.eye(k) / s2
            cov = np.linalg.inv(J)
            mu = cov @ b
            stat += mu[m:] @ mu[m:] + np.trace(cov[m:, m:])
            K += k
        assert stat / (K + s2 * prior_term) == pytest.approx(s2, rel=1e-8)
    for (a, e), j in zip(blocks, joints):
        mean = dense_marginal(*j, s2_mean)[0]
        mean_band, sd_band = dense_marginal(*j, s2_band)
        sd = np.sqrt(sd_band**2 + (mean_band - mean) ** 2)  # the band also holds the mean at its level
        np.testing.assert_allclose(snap.elevation_m[a:e], mean, rtol=0, atol=1e-9 * np.abs(mean).max())
        np.testing.assert_allclose(sd_of(snap)[a:e], sd, rtol=1e-7)
    assert np.isnan(snap.elevation_m[150:200]).all()


def test_reduced_system_stays_local_as_the_route_grows():
    """The cost's reason: the reduced (separators, knots) system's bandwidth is set by the passes at
    a point, not by the route length or the passes held over the whole route. 3 passes at every
    point of a 2 km route, 12 passes held in all (each covers a 500 m stretch)."""
    rng = np.random.default_rng(33)
    P = 40001
    extents = [(a, min(a + 10000, P)) for a in range(0, P - 1, 10000) for _ in range(3)]
    segs = _passes(rng, extents, tile=1000, drift=1e-3)
    g = GmrfProfile({"R1": route_length(P)}, tau=1e6, drift_knot_m=25.0, drift_sd_m=1e-3)
    for s in segs:
        g.update(s)
    g.snapshot()
    (blk,) = g._posterior("R1").blocks
    bandwidth = blk.drift.red.shape[0] - 1
    assert blk.drift.n_beta == sum(len(range(a // 500, (b - 1) // 500 + 2)) for a, b in extents)
    # Within a stretch: a separator, then 3 passes × 2 knots; at a stretch seam 6 passes meet.
    assert bandwidth <= 2 * (6 + 1), bandwidth


def _history_run(segs, order, snapshots_after, retracted):
    """Feed ``segs`` in ``order`` (indices), snapshotting after the given steps and retracting and
    re-adding ``retracted`` at the first of them; the final snapshot with its long-wave band."""
    from cloud.road.long_wave import with_long_wave_band

    g = GmrfProfile({"R1": route_length(401)}, drift_knot_m=2.5)  # τ and the drift level both learnt
    fed = []
    for step, i in enumerate(order):
        g.update(segs[i])
        fed.append(segs[i])
        if step in snapshots_after:
            g.snapshot()
            back = [s for s in retracted if s in fed]
            for s in back:
                g.retract(s)
            if back:
                g.snapshot()
            for s in back:
                g.update(s)
    snap = with_long_wave_band(g.snapshot()["R1"], fed, longest=False)
    return snap, g.tau["R1"], g.drift_sd["R1"]


def test_the_export_is_a_function_of_the_held_segments_not_of_their_history():
    """Exact replays: the same held segments give the same profile, band, τ and drift level
    whatever the order they arrived in, the snapshots taken on the way (τ is warm-started from the
    last one) and the segments retracted and added again. Every segment has its own error model (the
    edge's varies along a pass), so the long-wave band's choice of one per pass is exercised too.
    The tolerance (1e-9, of τ and of the profile's sd) lies between rounding (≲ 1e-11 sd on real
    road-qc passes) and what a history-dependent result shows there (τ 1e-6 off when warm-started
    where a previous solve stopped, the mean 6e-8 sd, the band 5e-4 sd)."""
    rng = np.random.default_rng(41)
    segs = _passes(rng, ((0, 401), (20, 401), (0, 330), (60, 401), (0, 401)), drift=1e-3, error_model=EDGE_MODEL)
    for i, s in enumerate(segs):
        if s.error_model.size:  # the level r of the edge's model varies from segment to segment
            em = s.error_model.copy()
            em[0] *= 1.0 + 0.05 * (s.tile % 3)
            segs[i] = dataclasses.replace(s, error_model=em)
    ref, tau, drift = _history_run(segs, range(len(segs)), (), [])
    assert drift > 0  # the drift is on and learnt
    scale = np.nanstd(ref.elevation_m)
    for trial in range(3):
        order = rng.permutation(len(segs))
        snaps = set(rng.choice(len(segs), 3, replace=False).tolist())
        retracted = [segs[i] for i in rng.choice(len(segs), 4, replace=False)] if trial else []
        snap, t, d = _history_run(segs, order, snaps, retracted)
        assert t == pytest.approx(tau, rel=1e-9)
        assert d == pytest.approx(drift, rel=1e-9)
        np.testing.assert_array_equal(snap.n_passes, ref.n_passes)
        for f in ("elevation_m", "lo95_m", "hi95_m"):
            assert np.nanmax(np.abs(getattr(snap, f) - getattr(ref, f))) <= 1e-9 * scale, (trial, f)


def _hat_drift(n, knot_pts, beta):
    """``Σ_k β_k φ_k`` on grid points ``0 .. n − 1`` (knot k at ``k · knot_pts``): the nuisance's own model."""
    u = np.arange(n) / knot_pts
    k = np.floor(u).astype(np.int64)
    w = u - k
    return beta[..., k] * (1.0 - w) + beta[..., k + 1] * w


def _centred_mean(x, width):
    """Mean of ``x`` over ``width`` (odd) points centred on each point; exact where the window fits."""
    return np.convolve(x, np.ones(width) / width, mode="same")


def test_drift_band_shares_are_the_hat_drifts_variance_per_band():
    """The long-wave term's model share of each band for the drift nuisance, against Monte Carlo
    drifts built from the hats directly and cut into bands as the passes' residuals are."""
    from cloud.road.long_wave import drift_band_shares

    rng = np.random.default_rng(43)
    widths, knot_m = [11, 41, 201, 1001], 25.0
    n = 10001
    beta = rng.standard_normal((300, int(n * DX / knot_m) + 3))
    d = _hat_drift(n, knot_m / DX, beta)
    mas = [np.array([_centred_mean(row, w) for row in d]) for w in widths]
    inner = slice(1500, n - 1500)  # farther from the ends than the widest mean reaches
    mc = [np.mean((mas[j] - mas[j + 1] if j + 1 < len(widths) else mas[j])[:, inner] ** 2) for j in range(len(widths))]
    np.testing.assert_allclose(drift_band_shares(knot_m, DX, widths), mc, rtol=0.05)  # (measured within 1.2 %)


def test_the_passes_scatter_adds_only_the_drift_beyond_the_learnt_level():
    """With the nuisance on, the band's long-wave term counts the learnt drift's share of every band
    as modelled: passes drifting as the model says add next to nothing beyond 50 m (the drift is not
    counted twice), while a stretch where they drift 3× more than the route-wide level gets the
    excess (a level learnt for the whole route cannot see it)."""
    from cloud.road.long_wave import band_error_variances, drift_of
    from shared.profiles.iso8608 import iso8608_profile
    from tests.test_profile_coverage import tile_segments

    rng = np.random.default_rng(44)
    n, knot_m, s, sigma = 6001, 25.0, 3e-4, 3e-4
    road = iso8608_profile((n - 1) * DX, DX, "A", seed=rng).elevation_m
    half = np.arange(n) >= n // 2
    inner0, inner1 = slice(600, n // 2), slice(n // 2, n - 600)
    added = {}
    for name, scale in (("model", 1.0), ("uneven", np.where(half, 3.0, 1.0))):
        segs = []
        for p in range(12):
            d = _hat_drift(n, knot_m / DX, rng.normal(0.0, s, int(n * DX / knot_m) + 3)) * scale
            segs += tile_segments(road + d + rng.normal(0.0, sigma, n), sigma, f"p{p}")
        g = GmrfProfile({"R1": (n - 1) * DX}, drift_knot_m=knot_m)
        for seg in segs:
            g.update(seg)
        snap = g.snapshot()["R1"]
        added[name] = (band_error_variances(snap, segs, drift=drift_of(g, "R1")),
                       band_error_variances(snap, segs, longest=True))  # as if no drift were modelled
    new, none = added["model"]
    assert new[-1][inner0].mean() + new[-1][inner1].mean() < 0.2 * (none[-1][inner0].mean() + none[-1][inner1].mean())
    new, _ = added["uneven"]
    total = new.sum(axis=0)
    assert total[inner1].mean() > 5.0 * total[inner0].mean()
