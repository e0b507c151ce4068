"""The contraction of the fleet's common modes that the vehicle intervals divide the consensus' common
move by: read off the fleet's linearised coupling (``(I − M)⁻¹`` on the common modes), whatever the
rounds' trend says."""

from __future__ import annotations

import numpy as np

from cloud.road.fleet_calibration import FleetCalibrator


def _solve_for(M: np.ndarray):
    """The operator ``r ↦ (I − M)⁻¹ r`` on rows, as :meth:`FleetCalibrator._fixed_point` returns it."""
    inv = np.linalg.inv(np.eye(M.shape[0]) - M)
    return lambda R: np.atleast_2d(R) @ inv.T


def test_common_contraction_is_one_minus_the_coupling_of_the_common_mode():
    V, P = 7, 4
    lam = np.array([0.93, 0.78, 0.3, 0.0])  # the common modes' share kept per round, per quantity
    # Every vehicle's quantity j moves by lam_j times the fleet's mean change of j, plus a little of
    # its own and of the other quantities (modes that are not common): the common mode of j is an
    # eigenvector of the averaging part, and the rest only perturbs it.
    rng = np.random.default_rng(0)
    own = 0.05 * rng.standard_normal((V * P, V * P))
    own -= np.kron(np.ones((V, V)) / V, np.eye(P)) @ own  # nothing of it moves the fleet's mean
    M = np.kron(np.ones((V, V)) / V, np.diag(lam)) + own
    g = FleetCalibrator._common_contraction(_solve_for(M), V, P, np.full(P, 0.5))
    np.testing.assert_allclose(g, 1.0 - lam, atol=1e-9)


def test_common_contraction_falls_back_where_the_coupling_amplifies_nothing():
    V, P = 5, 2
    M = np.kron(np.ones((V, V)) / V, np.diag([1.5, 0.6]))  # the first common mode runs away
    g = FleetCalibrator._common_contraction(_solve_for(M), V, P, np.array([0.25, 0.25]))
    np.testing.assert_allclose(g, [0.25, 0.4], atol=1e-9)
