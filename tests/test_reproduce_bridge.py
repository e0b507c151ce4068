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
