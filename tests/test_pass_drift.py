"""The per-pass drift nuisance (cloud.estimators.pass_drift), eliminated locally, against dense algebra.

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

from cloud.estimators.gmrf_profile import GmrfProfile
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
    the blocks, and it is the maximiser of the dense evidence."""
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
    res = minimize_scalar(lambda u: -sum(dense_log_evidence(*j, math.exp(u)) for j in joints),
                          bounds=(math.log(1e-12), math.log(1e-4)), method="bounded", options={"xatol": 1e-6})
    s2 = math.exp(res.x)
    assert -res.fun > 1.0  # the data do show drift
    assert g.drift_sd["R1"] == pytest.approx(math.sqrt(s2), rel=1e-3)
    s2 = g.drift_sd["R1"] ** 2
    for (a, e), j in zip(blocks, joints):
        mean, sd = dense_marginal(*j, s2)
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
