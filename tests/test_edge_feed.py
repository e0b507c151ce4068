"""A pass's per-chunk work in one compiled call (``edge.pipeline._feed_chunk`` through
:meth:`PassProcessor.feed`) against its steps run on the whole stream at once: the tracker's
chainage, the inverse, :class:`AxleGrid` and numpy's fourth differences. Bit for bit, with chunks
of a length that does not divide the stream (the grid's and the differences' buffers grow and are
compacted along the way)."""

from __future__ import annotations

import numpy as np
import pytest

from edge.chainage import ChainageTracker
from edge.pipeline import AxleGrid, EdgeConfig, PassProcessor
from shared.drivelog import list_drive_logs, read_drive_log
from shared.dynamics.inverse import InverseStream, build_inverse, edge_gamma
from shared.vehicles import vehicle_from_params
from simfleet.replay import chunks_of
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """A quarter-car pass (one axle: gridded in the call) and a half-car pass (two: gridded after it)."""
    out = []
    for name, seed in (("road-qc", 5), ("road-hc", 6)):
        d = tmp_path_factory.mktemp(name)
        generate(SCENARIOS[name], d, seed=seed, passes=1, workers=1, progress=False)
        out.append(read_drive_log(list_drive_logs(d / "logs")[0]))
    return out


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("which", [0, 1])
def test_a_pass_fed_in_chunks_is_its_steps_on_the_whole_stream(logs, which):
    log = logs[which]
    m = log.meta
    dt = 1.0 / m.sample_rate_hz
    model = build_inverse(vehicle_from_params(m.vehicle_model, m.nominal_params).system(), dt,
                          gamma=edge_gamma(m.vehicle_model))
    config = EdgeConfig()
    pp = PassProcessor(model, m.vehicle_id, m.pass_id, m.route_id, 0, config, m.vehicle_model)
    chunks = [c for c in chunks_of(log, 0.037) if c.n]  # 18–19 samples: no chunk boundary falls alike
    assert len(chunks) > 100
    for c in chunks:
        pp.feed(c)

    # the steps, each on the whole stream (times as each chunk computes its own: t0 + i / rate)
    gnss = np.concatenate([c.chainage for c in chunks])
    speed = np.concatenate([c.speed for c in chunks])
    t = np.concatenate([c.t for c in chunks])
    z = np.concatenate([pp.channels_of(c) for c in chunks])
    x = ChainageTracker(dt).update(gnss, speed)
    ap = InverseStream(model).update(z)
    reliable = speed >= config.min_speed_mps
    reliable[: min(pp.inverse.reliable_from, int(np.ceil(config.hard_warmup_s / dt)))] = False
    assert pp.n_samples == gnss.size
    assert pp.tracker.state[0] == x[-1]
    for i, grid in enumerate(pp.grids):
        ref = AxleGrid(config.antialias, dt, max(config.min_speed_mps, 0.1))
        ref.add(x + pp.system.offsets_m[i], ap[:, i], t, reliable, config.spacing_m, pp.min_index)
        assert grid.base == ref.base and grid.size == ref.size > 1000 and grid.done == ref.done
        for name in ("values", "linear", "valid", "t"):
            assert _same(getattr(grid, name), getattr(ref, name)), (i, name)
    # the fourth differences kept (the older ones are trimmed as tiles are released) are the
    # stream's last ones, with their samples' times
    d4 = pp._d4
    kept = d4.hi - d4.lo
    assert kept > 100
    assert _same(d4.data[d4.lo : d4.hi], np.diff(z, 4, axis=0)[-kept:])
    assert _same(d4.t[d4.lo : d4.hi], t[-kept:])
    # the mean speed each chunk adds is numpy's
    assert pp.speeds == [float(np.mean(c.speed)) for c in chunks]
