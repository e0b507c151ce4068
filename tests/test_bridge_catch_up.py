"""Passes arriving at once are fed to the bridges in steps, estimated after each: the steps cover
every pass, there are few of them, and the estimate at the end is the one-shot estimate's."""

from __future__ import annotations

import numpy as np

from cloud.bridge.monitor import CATCH_UP_ESTIMATES, CATCH_UP_LEAST, catch_up_steps

from tests.test_bridge_system import new_fed_monitor


def test_the_steps_cover_every_pass_in_few_estimates():
    for pending in range(0, 400):
        steps = catch_up_steps(pending)
        assert steps[-1] is None and all(s is not None for s in steps[:-1])
        fed = sum(steps[:-1])
        assert fed < max(pending, 1)  # the last step, unlimited, has passes left to take
        assert len(steps) <= CATCH_UP_ESTIMATES
        assert all(s >= CATCH_UP_LEAST for s in steps[:-1])
        if pending <= CATCH_UP_LEAST:
            assert steps == [None]


def test_an_estimate_caught_up_in_steps_ends_where_one_estimate_does():
    monitor, added, agg, used = new_fed_monitor(0.30)
    one = monitor.estimate()
    assert added == 12 and one  # a 30 % loss: alarmed at once
    ratios = monitor.bridges["B1"].latest.element_rows()

    stepped, _, agg2, used2 = new_fed_monitor(0.30)
    st = stepped.bridges["B1"]
    for key in list(st.fed):  # the same passes, unfed again
        st.estimator.remove(*key)
    st.fed.clear()
    counts = []
    for limit in catch_up_steps(stepped.unfed(agg2.passes, agg2.held)):
        stepped.sync(agg2.passes, agg2.held, lambda vid, model, version: used2[vid], limit=limit)
        stepped.estimate()
        counts.append(st.estimator.n_passes)
    assert counts == [8, 12]
    # The fit of each step starts from the last one's, so it stops at the same optimum only to the
    # solver's tolerance (a few 1e-4 of the ratio here); 2e-3 is still a fifth of the one point (1e-2)
    # any reading of the span resolves.
    np.testing.assert_allclose([r["stiffness_ratio"] for r in st.latest.element_rows()],
                               [r["stiffness_ratio"] for r in ratios], rtol=2e-3)
    assert st.alarmed
