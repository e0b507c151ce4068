"""The edge's gridding and tiling shortcuts against their plain definitions: the anti-alias against
its definition point by point; a drift window computed once per pass against once per
tile, and noise levels measured ahead against measured at each segment's release."""

from __future__ import annotations

import math

import numpy as np
import pytest

from edge import pipeline
from edge.pipeline import EdgeConfig, PassProcessor
from shared.dynamics.inverse import build_inverse, edge_gamma
from shared.schema import SensorChunk
from shared.vehicles import QuarterCar

DT = 1 / 500


def _antialias_reference(sap, index, speed, k, dt):
    """One point of :func:`edge.pipeline._antialias` as its docstring defines it, a sine per tap
    (a point whose window lies inside the samples, all reliable)."""
    fc = min(pipeline._AA_CUTOFF_CPM * speed[k], pipeline._AA_MAX_CUTOFF_FRACTION / dt) * dt
    half = pipeline._AA_HALF_WIDTH_M * pipeline._AA_CUTOFF_CPM / fc
    lo, hi = math.ceil(index[k] - half), math.floor(index[k] + half) + 1
    table, m = pipeline._KAISER, pipeline._KAISER.size - 2
    num = den = 0.0
    for i in range(lo, hi):
        tau = index[k] - i
        u = abs(tau) / half * m
        iu = min(int(u), m)
        w = table[iu] + (u - iu) * (table[iu + 1] - table[iu])
        a = 2.0 * fc * tau
        if a != 0.0:
            w *= math.sin(math.pi * a) / (math.pi * a)
        num += w * sap[i]
        den += w
    return num / den


@pytest.mark.parametrize("v", [0.6, 3.0, 12.0, 33.0])
def test_the_antialias_is_its_sine_per_tap_definition(v):
    rng = np.random.default_rng(7)
    n = 4000 if v < 1 else 600
    sap = rng.standard_normal(n) * 1e-3
    # fractional sample numbers, some exactly on a sample and some a hair off one (a ≈ 0)
    index = np.concatenate([np.arange(n * 0.4, n * 0.6, 0.37), [n / 2, n / 2 + 1e-12, n / 2 + 1 - 1e-13]])
    speed = np.full(index.size, v)
    out, valid = np.zeros(index.size), np.ones(index.size, dtype=bool)
    assert pipeline._antialias(sap, np.ones(n, dtype=bool), 0, index, speed, np.zeros(index.size), out, valid,
                               0, DT, 0.5, True) == index.size
    want = np.array([_antialias_reference(sap, index, speed, k, DT) for k in range(index.size)])
    assert valid.all()
    # The same arithmetic in the same order: only a compiler's contraction of a multiply-add may round
    # differently (~1e-16 of the samples a tap, over up to ~700 taps at 0.6 m/s).
    assert np.max(np.abs(out - want)) <= 1e-12 * np.max(np.abs(sap))


class _EveryTile(PassProcessor):
    """Drift trend and white level computed for every tile afresh (no window kept), and each
    segment's noise levels measured when it is released (none ahead)."""

    def _window(self, axle, g, wa, wb):
        self._windows.clear()
        return super()._window(axle, g, wa, wb)

    def _measure_ahead(self):
        pass


@pytest.mark.parametrize("seconds", [9.0, 40.0])  # shorter than the drift window, and several of them
def test_windows_and_noise_levels_computed_once_are_those_computed_per_segment(seconds):
    model = build_inverse(QuarterCar(M=4450.0, m=420.0, K=5e5, k=1.95e6, c=2e4).system(), DT,
                          gamma=edge_gamma("quarter_car"))
    rng = np.random.default_rng(3)
    n = int(seconds / DT)
    speed = 18.0 + rng.standard_normal(n).cumsum() * 0.01
    chainage = 3.0 + np.cumsum(speed) * DT
    body = rng.standard_normal(n) * 0.05 + np.sin(chainage / 3.0)
    procs = [cls(model, "v", "v-p", "r", 0, EdgeConfig(), "quarter_car") for cls in (PassProcessor, _EveryTile)]
    out: list[list] = [[], []]
    for j, proc in enumerate(procs):
        for a in range(0, n, 50):
            b = min(n, a + 50)
            chunk = SensorChunk("v", "v-p", "r", "quarter_car", a // 50, a * DT, 1 / DT, chainage[a:b], speed[a:b],
                                {model.system.channels[0].name: body[a:b].astype(np.float32)}, b == n)
            out[j] += proc.feed(chunk)
        out[j] += proc.finish()[0]
    assert len(out[0]) == len(out[1]) >= 4
    assert all(s.error_model.size for s in out[0][1:-1])  # (the error models are there to compare)
    assert procs[0]._ahead > 0 and not procs[0]._noise  # measured ahead, and every measurement used
    assert [s.encode() for s in out[0]] == [s.encode() for s in out[1]]  # bit for bit
