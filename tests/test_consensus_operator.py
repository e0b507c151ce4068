"""The fleet error's fast path against the direct computation it replaces.

:func:`shared.dynamics.forward.channels_transpose` is the transpose of the forward model, and
:class:`cloud.road.calibration.ConsensusSensitivity` moves a vehicle's fit under a consensus change
through it (:meth:`~cloud.road.calibration.PassRemap.consensus_weights`) instead of a forward run
per change (:meth:`~cloud.road.calibration.PassRemap.consensus_response`, the direct path, kept).
Both are the same linear map evaluated in another order, so they agree to rounding; the tolerances
below are rounding's (an FFT correlation and a recurrence over a few thousand steps: a few hundred
ulps of the sum's scale), far below anything an interval could show.
"""

from __future__ import annotations

import numpy as np
import pytest

from cloud.road.calibration import REFERENCE, ConsensusSensitivity, PassAp, class_prior
from shared.dynamics.forward import channels_from_ap, channels_transpose, simulate_on_profile
from shared.dynamics.inverse import InverseStream, build_inverse, edge_gamma
from shared.dynamics.newmark import newmark_constants
from shared.profiles import iso8608_profile, tyre_filter
from shared.vehicles import HalfCar, QuarterCar, vehicle_from_params
from shared.vehicles.bogie import table_3_2
from shared.vehicles.half_car import TABLE_2_1
from simfleet.scenarios import TABLE_4_1

#: relative to the sum's scale (|weights|·|channels|): rounding of a 2n-point FFT and of the
#: recurrence, each ~1e-15–1e-13 here; 1e-10 leaves room and still fails any wrong term (a missed
#: start, a shifted lag or a wrong contact changes the sum by O(1) of its scale)
ROUNDING = 1e-10

VEHICLES = {
    "quarter_car": QuarterCar(**TABLE_4_1["mean"]),
    "half_car": HalfCar(**TABLE_2_1),
    "bogie_half_car": table_3_2(),  # damped contacts: the contact rate's own recurrence is in the map
}


@pytest.mark.parametrize("name", sorted(VEHICLES))
@pytest.mark.parametrize("gamma", [0.5, 0.6, 0.8])
def test_the_transpose_gives_the_forward_models_sums(name, gamma):
    system = VEHICLES[name].system()
    rng = np.random.default_rng(7)
    n = 1500
    c = newmark_constants(0.002, gamma)
    ap = np.cumsum(rng.standard_normal((n, system.n_contacts)), axis=0) * 1e-4
    ap[0] += 3e-3  # a start away from zero: the static equilibrium's own column is in the sum
    weights = rng.standard_normal((4, n, len(system.channels)))
    z = channels_from_ap(system, ap, c)
    direct = np.einsum("bnh,nh->b", weights, z)
    v = channels_transpose(system, weights, c)
    assert v.shape == (4, n, system.n_contacts)
    scale = np.linalg.norm(weights.reshape(4, -1), axis=1) * np.linalg.norm(z)
    np.testing.assert_array_less(np.abs(np.einsum("bnc,nc->b", v, ap) - direct), ROUNDING * scale)
    # one row alone is the batch's row
    np.testing.assert_allclose(channels_transpose(system, weights[1], c), v[1], rtol=0, atol=1e-12 * np.abs(v).max())


def _pass(model: str, params: dict, speed: float, seed: int):
    """One pass of ``model`` over a class A road, its AP by the edge's inverse, and a consensus that is
    the road plus an error: (PassAp, consensus) on a 0.05 m grid."""
    system = vehicle_from_params(model, params).system()
    prof = tyre_filter(iso8608_profile(200.0, 0.01, "A", seed=seed))
    r = simulate_on_profile(system, prof.at, prof.slope, 5.0, speed, 150.0 / speed, 0.0005, gamma=0.5)
    z, x = r.channels[::4], r.x_cg[::4]
    ap = InverseStream(build_inverse(system, 0.002, gamma=edge_gamma(model))).update(z)
    h = 0.05
    grid = np.arange(int(round(30.0 / h)), int(round(140.0 / h)))
    values = np.stack([np.interp(grid * h, x + system.offsets_m[i], ap[:, i]) for i in range(system.n_contacts)],
                      axis=1)
    rng = np.random.default_rng(seed)
    cons = np.stack([prof.at(grid * h) for _ in range(system.n_contacts)], axis=1)
    cons = cons + 1e-4 * rng.standard_normal(cons.shape[0])[:, None]
    return PassAp(int(grid[0]), h, values, speed), cons


@pytest.mark.parametrize("model", ["quarter_car", "half_car"])
def test_the_sensitivitys_moves_are_the_direct_runs(model):
    """Random consensus changes (holes included) through each pass's map give the moves a forward run
    per change gives. The half-car exercises the low-pass and the start-state projection."""
    params = dict(TABLE_4_1["mean"]) if model == "quarter_car" else dict(TABLE_2_1)
    std = {k: 0.1 * v for k, v in params.items()}
    passes = [_pass(model, params, 17.0, 1), _pass(model, params, 21.0, 2)]
    ref, _ = REFERENCE[model]
    sens = ConsensusSensitivity(model, params, passes, class_prior(model, params, std), params[ref])
    rng = np.random.default_rng(3)
    deltas = []
    for ap, _ in passes:
        d = 1e-4 * rng.standard_normal((5,) + ap.values.shape)
        d[:, 100:140] = np.nan  # a hole in the consensus: no change there
        deltas.append(d)
    got = sens.moves(deltas)
    want = np.stack([-np.linalg.solve(sens.A, sens.J.T @ (sens.w * np.concatenate(
        [r.consensus_response(params, d[k]) for r, d in zip(sens.remaps, deltas)]))) for k in range(5)])
    assert np.abs(want).max() > 0  # the changes move the fit
    np.testing.assert_allclose(got, want, rtol=0, atol=ROUNDING * np.abs(want).max())
