"""Chart geometry for the view's 2D charts (cloud.chart): nice ranges, ticks, labels, the screen map."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cloud.chart import Frame, nice_range, nice_step, tick_label, ticks


@pytest.mark.parametrize("span, target, step", [(140.0, 10, 20.0), (1.0, 5, 0.2), (23.0, 5, 5.0), (0.37, 6, 0.1),
                                                 (1000.0, 10, 100.0), (9.0, 6, 2.0)])
def test_nice_step_is_one_two_two_and_a_half_or_five_times_a_power_of_ten(span, target, step):
    assert nice_step(span, target) == pytest.approx(step)
    mantissa = step / 10 ** math.floor(math.log10(step))
    assert min(abs(mantissa - m) for m in (1.0, 2.0, 2.5, 5.0)) < 1e-9


def test_nice_range_holds_the_data_on_step_multiples():
    rng = np.random.default_rng(0)
    for _ in range(200):
        lo = rng.normal(0, 10 ** rng.uniform(-3, 3))
        hi = lo + 10 ** rng.uniform(-3, 3)
        a, b, step = nice_range(lo, hi)
        assert a <= lo and b >= hi
        assert a / step == pytest.approx(round(a / step), abs=1e-6)
        assert b / step == pytest.approx(round(b / step), abs=1e-6)
        assert (b - a) / step <= 12  # about the target number of intervals, never a wall of ticks
    a, b, _ = nice_range(float("nan"), 1.0)  # no data: about ±1
    assert -2.0 < a <= -1.0 and 1.0 <= b < 2.0
    a, b, _ = nice_range(5.0, 5.0)  # one value: a range around it
    assert a < 5.0 < b


def test_ticks_and_labels():
    np.testing.assert_allclose(ticks(-0.3, 0.75, 0.25), [-0.25, 0.0, 0.25, 0.5, 0.75])
    assert [tick_label(v, 0.25) for v in ticks(-0.3, 0.75, 0.25)] == ["-0.25", "0", "0.25", "0.50", "0.75"]
    assert [tick_label(v, 2.5) for v in (0.0, 2.5, 5.0)] == ["0", "2.5", "5.0"]
    assert tick_label(120.0, 20.0) == "120" and tick_label(-1e-17, 0.1) == "0"


def test_frame_maps_data_to_the_screen_box_and_back():
    f = Frame.fit((0.0, 140.0), (-12.3, 8.1), 1000.0, 150.0)
    assert (f.x_lo, f.x_hi) == (0.0, 140.0) and f.y_lo <= -12.3 and f.y_hi >= 8.1
    np.testing.assert_allclose(f.points([0.0, 140.0], [f.y_hi, f.y_lo]), [[0.0, 0.0], [1000.0, 150.0]])
    y = np.array([-12.3, 0.0, 8.1])
    np.testing.assert_allclose(f.data_y(f.sy(y)), y)
    assert len(f.gridlines()) == f.x_ticks().size + f.y_ticks().size
    pos, text = f.x_labels(5.0)
    assert (pos[:, 1] == 155.0).all() and text[0] == "0" and text[-1] == "140"
    with pytest.raises(ValueError):
        Frame(0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 10.0, 10.0)
