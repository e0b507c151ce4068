"""The element stiffnesses' prior: a smooth field about a level common to the span."""

from __future__ import annotations

import numpy as np

from cloud.bridge.static import StiffnessPrior


def test_the_precision_is_that_of_the_field_plus_a_common_level():
    n = 20
    p = StiffnessPrior(level_sd=0.1, step_sd=0.05, common_sd=0.3)
    D = np.diff(np.eye(n), axis=0)
    field = np.linalg.inv(np.eye(n) / 0.1**2 + D.T @ D / 0.05**2)
    np.testing.assert_allclose(np.linalg.inv(p.precision(n)), field + 0.3**2, rtol=1e-9, atol=1e-12)
    plain = StiffnessPrior(level_sd=0.1, step_sd=0.05, common_sd=None)
    np.testing.assert_allclose(np.linalg.inv(plain.precision(n)), field, rtol=1e-9, atol=1e-12)


def test_an_element_no_pass_sees_is_drawn_to_the_span_level_not_left_at_its_neighbour():
    """The end elements barely change any deflection. Given the elements the passes do see (here
    6–15, known to 0.2 % at a level 10 % below the design, rising 4 points towards the right), the
    prior's mean of the right-hand end lies between its nearest seen neighbour and the span's
    level; anchored on the design value alone it drifted towards the design instead (bridge-global10
    seed 5, 30 passes: both ends 8 points stiff while the span's level was right to 0.1)."""
    n, seen = 20, np.arange(5, 15)
    values = np.linspace(-0.12, -0.08, seen.size)
    H = np.zeros((seen.size, n))
    H[np.arange(seen.size), seen] = 1.0

    def end_mean(prior: StiffnessPrior) -> float:
        Q = prior.precision(n) + H.T @ H / 0.002**2
        return float(np.linalg.solve(Q, H.T @ values / 0.002**2)[-1])

    neighbour, level = values[-1], float(values.mean())
    common = end_mean(StiffnessPrior())
    assert level < common < neighbour - 0.005, (common, neighbour, level)
    design_anchored = end_mean(StiffnessPrior(level_sd=0.3, common_sd=None))
    assert design_anchored > neighbour + 0.005, design_anchored
