"""The logger's vertical from the gyro and gravity from the standstills (edge.orientation.level_vertical):
a constant left in ``body_acc`` is bent twice into every pass's profile, so it must be far under
what the GNSS-track orientation leaves (a few milliradians, tenths of mm/s²)."""

import numpy as np

from edge.orientation import LoggerFrame, level_vertical, standstills
from simfleet.network import logger_rotation

FS = 200.0
G = 9.81


def _drive(rng):
    """A drive from rest to rest with a stop between, turns one way, a body vibrating while rolling."""
    t = np.arange(0.0, 120.0, 1.0 / FS)
    moving = ((t > 3.0) & (t < 55.0)) | ((t > 60.0) & (t < 115.0))
    # The body's vertical velocity: a vibration that is zero at rest (its acceleration its derivative).
    envelope = np.convolve(moving.astype(float), np.ones(int(2 * FS)) / (2 * FS), mode="same") * moving
    v_body = 0.03 * np.sin(2 * np.pi * 1.3 * t) * envelope
    body = np.gradient(v_body, t)
    a_long = 1.2 * np.sin(2 * np.pi * t / 25.0) * moving
    yaw = np.where(moving, 0.25 * (np.sin(2 * np.pi * t / 17.0) > 0.3), 0.0)  # turns, all to the left
    a_lat = 12.0 * yaw
    f = np.column_stack([a_long, a_lat, G + body]) + rng.normal(0.0, 0.01, (t.size, 3))
    w = np.column_stack([np.zeros(t.size), np.zeros(t.size), yaw]) + rng.normal(0.0, 1e-3, (t.size, 3))
    return f, w


def test_the_gyro_gives_the_vertical_and_the_rests_give_gravity():
    rng = np.random.default_rng(3)
    f, w = _drive(rng)
    R = logger_rotation(12.0, -20.0, 115.0)
    bias = np.array([0.01, -0.02, 0.005])  # a phone gyro's constant bias (rad/s)
    acc, gyro = f @ R.T, w @ R.T + bias
    true_up, true_fwd = R[:, 2], R[:, 0]
    # The GNSS-track frame: a few milliradians off, its gravity the norm of the mean.
    tilt = np.cross(true_up, true_fwd) * 4e-3 + true_fwd * 2e-3
    up0 = (true_up + tilt) / np.linalg.norm(true_up + tilt)
    frame = LoggerFrame(up0, true_fwd, np.cross(up0, true_fwd), float(np.linalg.norm(acc.mean(axis=0))), 1.0)
    half = len(acc) // 2
    out = level_vertical(frame, [acc[:half], acc[half:]], [gyro[:half], gyro[half:]], int(FS))
    # The track's frame is 4.5 mrad off; the gyro's blocks leave ~0.2 mrad (its noise over the turns).
    assert np.arccos(min(1.0, out.up @ true_up)) < 5e-4
    assert abs(out.forward @ out.up) < 1e-12 and abs(np.linalg.norm(out.lateral) - 1.0) < 1e-12
    body = acc @ out.up - out.gravity_mps2
    moving_straight = (np.abs(f[:, 0]) < 0.05) & (np.abs(f[:, 1]) < 0.05)
    # The constant a straight pass would carry: the accelerometer's noise over the rest-to-rest
    # stretch (0.01/sqrt(11 000): 0.1 mm/s²) plus the axis's leak of that stretch's mean lateral
    # acceleration (~0.9 m/s² x 0.2 mrad): 0.4 mm/s² is three of each.
    assert abs(np.mean((body - (f[:, 2] - G))[moving_straight])) < 4e-4
    before = acc @ frame.up - frame.gravity_mps2
    assert abs(np.mean((before - (f[:, 2] - G))[moving_straight])) > 2e-3  # the track's frame: mm/s²


def test_standstills_are_the_middles_of_the_rests():
    rng = np.random.default_rng(4)
    f, _ = _drive(rng)
    rest = standstills(f, np.array([0.0, 0.0, 1.0]), int(FS))
    t = rest / FS
    assert len(t) == 3 and abs(t[0] - 1.5) < 1.0 and abs(t[1] - 57.5) < 1.0 and abs(t[2] - 117.5) < 1.0
