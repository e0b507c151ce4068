"""Logger orientation: a raw 3-axis IMU in the logger's own frame turned into the vehicle's channels.

A phone or telematics box is mounted at an unknown, fixed angle. Its accelerometer measures the
specific force f = a − g (so at rest it reads +9.81 m/s² *up*). Over a drive the vehicle's own
accelerations average out (it starts and ends slow, turns both ways, roads are nearly level), so
the long mean of f points up: that gives the vertical axis. The forward axis lies in the plane
normal to it, at the angle where the horizontal specific force best follows the longitudinal
acceleration of the GNSS track (least squares on low-passed signals); lateral completes a
right-handed frame. Projected on those axes: ``body_acc`` = f·up − |ḡ| (gravity removed),
``long_acc`` = f·forward (what brakes and accelerates the car) and, from the gyro,
``pitch_rate`` = ω·(−lateral), positive when the nose rises (the half-car's convention).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class OrientationError(ValueError):
    """The data cannot fix the logger's orientation (the message says why, in one line)."""


class LoggerFrame(NamedTuple):
    """The vehicle's axes expressed in the logger's frame (unit vectors) and the gravity magnitude."""

    up: np.ndarray  # (3,)
    forward: np.ndarray  # (3,)
    lateral: np.ndarray  # (3,) up × forward: to the left
    gravity_mps2: float
    heading_fit_r2: float  # share of the track's longitudinal-acceleration variance the fit explains


class VehicleChannels(NamedTuple):
    body_acc: np.ndarray  # (n,) m/s², vertical, gravity removed
    long_acc: np.ndarray  # (n,) m/s², along the vehicle's forward axis
    pitch_rate: np.ndarray | None  # (n,) rad/s, nose up positive; None without a gyro


def vertical_axis(acc: np.ndarray) -> tuple[np.ndarray, float]:
    """The logger-frame unit vector pointing up and |g| (m/s²), from the mean specific force."""
    mean = np.asarray(acc, float).mean(axis=0)
    g = float(np.linalg.norm(mean))
    if not (5.0 < g < 15.0):  # far from 9.81: not an accelerometer in m/s² including gravity
        raise OrientationError(f"mean specific force {g:.3g} m/s² is not gravity (expected ~9.81 m/s² "
                               "with gravity included)")
    return mean / g, g


def estimate_frame(acc: np.ndarray, long_acc_ref: np.ndarray, weights: np.ndarray | None = None,
                   min_r2: float = 0.5) -> LoggerFrame:
    """The logger's orientation in the vehicle.

    Parameters
    ----------
    acc : (n, 3) array
        Specific force in the logger frame, m/s² (gravity included), low-passed or raw.
    long_acc_ref : (n,) array
        The vehicle's longitudinal acceleration from the GNSS track at the same instants (m/s²),
        low-passed like ``acc``; NaN where unknown.
    weights : (n,) array, optional
        Non-negative weights of the samples in the heading fit.
    min_r2 : float
        The heading fit must explain at least this share of the reference's variance, or the
        orientation is refused (a logger loose in the car, or a track without speed changes).
    """
    acc = np.asarray(acc, float)
    up, g = vertical_axis(acc)
    # Any two unit vectors normal to up span the horizontal plane.
    seed = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = np.cross(up, seed)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    h = np.column_stack([acc @ e1, acc @ e2])
    ok = np.isfinite(long_acc_ref)
    w = np.ones(len(acc)) if weights is None else np.asarray(weights, float)
    ok &= w > 0
    if ok.sum() < 10:
        raise OrientationError("too few samples with a GNSS track to find the forward axis")
    sw = np.sqrt(w[ok])
    y = long_acc_ref[ok]
    # long_acc ≈ cos ψ h1 + sin ψ h2 + bias (the bias takes a road grade's share of gravity).
    X = np.column_stack([h[ok], np.ones(ok.sum())])
    coef, *_ = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)
    c, s = coef[0], coef[1]
    norm = float(np.hypot(c, s))
    if norm == 0.0:
        raise OrientationError("the horizontal acceleration does not follow the track's speed changes")
    resid = y - X @ coef
    var = float(np.average((y - np.average(y, weights=w[ok])) ** 2, weights=w[ok]))
    r2 = 1.0 - float(np.average(resid**2, weights=w[ok])) / var if var > 0 else 0.0
    if r2 < min_r2:
        raise OrientationError(f"the forward axis explains only {r2:.2f} of the track's longitudinal "
                               f"acceleration (needs {min_r2:g}): logger not fixed in the vehicle?")
    forward = (c * e1 + s * e2) / norm
    lateral = np.cross(up, forward)
    return LoggerFrame(up, forward, lateral, g, r2)


def vehicle_channels(frame: LoggerFrame, acc: np.ndarray, gyro: np.ndarray | None) -> VehicleChannels:
    """Project the raw IMU (``acc`` m/s², ``gyro`` rad/s, each (n, 3) in the logger frame) on the
    vehicle's axes; gravity is removed from the vertical."""
    acc = np.asarray(acc, float)
    body = acc @ frame.up - frame.gravity_mps2
    long_acc = acc @ frame.forward
    pitch = None if gyro is None else -(np.asarray(gyro, float) @ frame.lateral)
    return VehicleChannels(body, long_acc, pitch)
