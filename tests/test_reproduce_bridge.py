"""``driveby reproduce bridge --large`` estimates from the first 30/100 passes of one 300-pass
simulation: that is only the same as simulating 30 or 100 passes if a scenario's first passes do
not depend on how many follow."""

from __future__ import annotations

import numpy as np

from shared.drivelog import list_drive_logs, read_drive_log
from simfleet import sim
from simfleet.scenarios import SCENARIOS


def test_the_first_passes_of_a_longer_simulation_are_the_shorter_simulation(tmp_path):
    scenario = SCENARIOS["bridge-crack10-10m"]
    short = sim.generate(scenario, tmp_path / "short", seed=3, passes=2, workers=1, progress=False)
    long = sim.generate(scenario, tmp_path / "long", seed=3, passes=3, workers=1, progress=False)
    assert [r["pass_id"] for r in long["passes"][:2]] == [r["pass_id"] for r in short["passes"]]
    assert long["passes"][:2] == short["passes"]
    a = [read_drive_log(p) for p in list_drive_logs(tmp_path / "short" / "logs")]
    b = [read_drive_log(p) for p in list_drive_logs(tmp_path / "long" / "logs")][:2]
    for x, y in zip(a, b, strict=True):
        assert x.meta == y.meta
        assert np.array_equal(x.chainage, y.chainage) and np.array_equal(x.speed, y.speed)
        assert x.channels.keys() == y.channels.keys()
        assert all(np.array_equal(x.channels[k], y.channels[k]) for k in x.channels)


def test_the_report_shows_the_efficient_estimators_largest_error_beside_ours():
    """The CRB section's bridge-healthy table and the --large bound column are computed from the
    information (scaled from 30 passes), not typed: P(all within) grows with the bound, and each
    row shows its own entry."""
    from cloud.bridge.information import Information
    from cloud.bridge.stiffness import StiffnessPrior
    from simfleet.reproduce_bridge import bound_cell, healthy_bound_pts, largest_error_entry, largest_error_report

    rng = np.random.default_rng(2)
    X = rng.standard_normal((80, 20)) * np.sin(np.linspace(0.1, np.pi - 0.1, 20)) * 60.0  # ends barely seen
    info = Information(X.T @ X, 30, 10)
    Q = StiffnessPrior().precision(20)
    le = {str(k): largest_error_entry(info.scaled(k), Q, healthy_bound_pts(k), 0) for k in (30, 300)}
    assert le["30"]["bound_pts"] == 5.0 and le["300"]["bound_pts"] == 3.0
    loose = largest_error_entry(info.scaled(300), Q, 5.0, 0)
    assert loose["p_within"] > le["300"]["p_within"] and loose["median_pts"] == le["300"]["median_pts"]
    r = {"crb": {"bridge-healthy": {"largest_error": le}}, "scenarios": {"bridge-healthy": {"element_err_max_pts": 2.5}},
         "large": {"bridge-healthy": {"300": {"element_err_max_pts": 3.25}}}}
    rows = [line for line in largest_error_report(r) if line.startswith("| 30 ") or line.startswith("| 300 ")]
    assert len(rows) == 2
    for row, k, ours in zip(rows, ("30", "300"), ("2.50", "3.25")):
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[4].startswith(f"{le[k]['median_pts']:.2f}") and cells[5] == f"{le[k]['p_within']:.2f}"
        assert cells[6] == ours
    assert f"= {le['300']['p_within']:.2f}" in bound_cell(le["300"]) and bound_cell(None) == "–"
