"""The trip splitter's parts against exact answers: resampling of jittered timestamps (with its
anti-alias filter and its refusals), the Kalman/RTS track, and the logger's orientation."""

import numpy as np
import pytest

from edge.fusion import smooth_track
from edge.orientation import OrientationError, estimate_frame, vehicle_channels
from edge.resample import ResampleError, ResampleSettings, resample
from simfleet.network import logger_rotation


def jittered(fs, duration, jitter, rng):
    t = np.arange(0.0, duration, 1.0 / fs)
    return t + rng.uniform(-jitter, jitter, len(t)) / fs


def test_jittered_tone_is_resampled_exactly():
    rng = np.random.default_rng(0)
    t = jittered(200.0, 10.0, 0.3, rng)
    y = np.sin(2 * np.pi * 7.0 * t)
    runs, lost = resample(t, {"y": y}, 200.0)
    assert len(runs) == 1 and lost == 0.0
    r = runs[0]
    assert np.allclose(np.diff(r.t), 1 / 200.0)
    # A cubic spline through 200 Hz samples of a 7 Hz tone: error ~ (2π·7/200)⁴/384 ≈ 6e-6.
    assert np.max(np.abs(r.signals["y"] - np.sin(2 * np.pi * 7.0 * r.t))) < 1e-4


@pytest.mark.parametrize("jitter,tol", [
    (0.0, 1e-4),  # the filter alone: the 150 Hz tone is ~80 dB down
    # With jittered stamps the spline's own error on a tone at 0.375 of the logger's rate spreads
    # over all frequencies; ±5 % jitter leaves ~0.01 of it below the cut-off. A fold would leave 0.71.
    (0.05, 0.02),
])
def test_faster_logger_is_anti_aliased(jitter, tol):
    rng = np.random.default_rng(1)
    t = jittered(400.0, 10.0, jitter, rng)
    low, high = np.sin(2 * np.pi * 5.0 * t), np.sin(2 * np.pi * 150.0 * t)  # 150 Hz would fold to 50 Hz
    runs, _ = resample(t, {"y": low + high}, 200.0)
    r = runs[0]
    mid = slice(200, -200)  # a second in from the run's ends
    err = r.signals["y"][mid] - np.sin(2 * np.pi * 5.0 * r.t[mid])
    assert np.std(err) < tol


def test_gaps_cut_runs_and_are_counted():
    rng = np.random.default_rng(2)
    t = jittered(100.0, 20.0, 0.2, rng)
    t = np.delete(t, slice(800, 850))  # a 0.5 s gap at 8 s
    runs, lost = resample(t, {"y": np.cos(t)}, 100.0)
    assert len(runs) == 2
    assert lost == pytest.approx(0.51, abs=0.01)
    assert runs[0].t[-1] < 8.0 < runs[1].t[0]


@pytest.mark.parametrize("case,match", [("scatter", "scatter"), ("slow", "below the nominal")])
def test_broken_timestamps_are_refused_in_one_line(case, match):
    rng = np.random.default_rng(3)
    if case == "scatter":
        t = np.cumsum(rng.choice([0.002, 0.008, 0.01], 2000, p=[0.45, 0.1, 0.45]))
        t = t * (0.01 / np.mean(np.diff(t)))  # right mean rate, wild steps (two streams merged)
    else:
        t = np.arange(0.0, 10.0, 1 / 80.0)  # an 80 Hz logger declared at 100 Hz
    with pytest.raises(ResampleError, match=match) as info:
        resample(t, {"y": np.zeros(len(t))}, 100.0, ResampleSettings(max_gap_steps=5.0))
    assert "\n" not in str(info.value)


def test_track_follows_a_braking_vehicle_through_a_dropout():
    rng = np.random.default_rng(4)
    fs = 100.0
    t = np.arange(0.0, 60.0, 1 / fs)
    a = np.where((t > 20) & (t < 24), -2.0, 0.0) + np.where((t > 40) & (t < 44), 1.5, 0.0)
    v = 15.0 + np.cumsum(a) / fs
    s = np.cumsum(v) / fs
    fix = (np.arange(len(t)) % 20 == 0) & ~((t > 30) & (t < 38))  # 5 Hz, an 8 s dropout
    sd = 1.0
    tr = smooth_track(t, a + 0.05 + rng.normal(0, 0.05, len(t)), t[fix], s[fix] + rng.normal(0, sd, fix.sum()),
                      np.full(fix.sum(), sd))
    assert np.median(np.abs(tr.s - s)) < 0.5 and np.max(np.abs(tr.s - s)) < 2.0
    assert np.max(np.abs(tr.v - v)[100:-100]) < 0.3
    # The 0.05 m/s² accelerometer bias is learnt: what is left is the sensor's white noise (0.05 rms),
    # which a 1 s mean brings to 0.005.
    err_1s = np.convolve(tr.a - a, np.ones(100) / 100, mode="valid")
    assert abs(np.mean(tr.a - a)) < 0.01 and np.max(np.abs(err_1s)) < 0.04
    inside = (tr.s_sd[(t > 33) & (t < 35)]).min()
    assert inside > tr.s_sd[(t > 10) & (t < 12)].max()  # the dropout shows in the posterior spread


def test_orientation_is_recovered_and_gravity_removed():
    rng = np.random.default_rng(5)
    R = logger_rotation(12.0, -20.0, 115.0)
    n = 400
    along = rng.normal(0.0, 1.0, n)
    lateral = rng.normal(0.0, 0.5, n)
    b = np.column_stack([along, lateral, np.full(n, 9.81)])
    a = b @ R.T + rng.normal(0.0, 0.05, (n, 3))
    f = estimate_frame(a, b)
    assert np.degrees(np.arccos(f.up @ R[:, 2])) < 0.3
    assert np.degrees(np.arccos(f.forward @ R[:, 0])) < 0.5
    bump = np.column_stack([np.zeros(5), np.zeros(5), 9.81 + np.arange(5.0)]) @ R.T
    ch = vehicle_channels(f, bump, np.tile(R[:, 1], (5, 1)))  # rotating about +lateral (left): nose down
    assert np.allclose(ch.body_acc, np.arange(5.0), atol=0.01)
    assert np.allclose(ch.pitch_rate, -1.0, atol=0.01)


def test_loose_logger_is_refused():
    rng = np.random.default_rng(6)
    b = np.column_stack([rng.normal(0, 1, 300), rng.normal(0, 0.5, 300), np.full(300, 9.81)])
    a = np.column_stack([rng.normal(0, 1, 300), rng.normal(0, 1, 300), np.full(300, 9.81)])  # unrelated
    with pytest.raises(OrientationError, match="explains only"):
        estimate_frame(a, b)
