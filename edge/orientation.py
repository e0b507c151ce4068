"""Logger orientation: a raw 3-axis IMU in the logger's own frame turned into the vehicle's channels.

A phone or telematics box is mounted at an unknown, fixed angle. Its accelerometer measures the
specific force f = a − g (at rest +9.81 m/s² *up*). The GNSS track tells what the vehicle's
low-passed specific force must have been in the vehicle's own axes (x forward, y left, z up):
(a_long, a_lat, |g|), with a_long the track's speed change and a_lat = v × heading rate. The
rotation that best maps those onto the IMU's low-passed readings at the same instants (Wahba's
problem, solved by SVD) gives up, forward and lateral together — the gravity direction from the
data, the heading from the motion — without the bias a plain mean of f takes from turns that all
go one way. Projected on those axes: ``body_acc`` = f·up − |g| (gravity removed), ``long_acc`` =
f·forward and, from the gyro, ``pitch_rate`` = ω·(−lateral), positive when the nose rises (the
half-car's convention).
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


def estimate_frame(f_logger: np.ndarray, f_vehicle: np.ndarray, weights: np.ndarray | None = None,
                   min_r2: float = 0.5) -> LoggerFrame:
    """The logger's orientation in the vehicle.

    Parameters
    ----------
    f_logger : (k, 3) array
        Low-passed specific force in the logger frame, m/s² (gravity included).
    f_vehicle : (k, 3) array
        What it must have been in the vehicle frame at the same instants (from the GNSS track):
        ``(a_long, a_lat, g)``, m/s².
    weights : (k,) array, optional
        Non-negative weights of the pairs.
    min_r2 : float
        The rotation must explain at least this share of the track's horizontal acceleration
        variance, or the orientation is refused (a logger loose in the car, or a track without
        speed changes or turns).
    """
    f_logger = np.asarray(f_logger, float)
    f_vehicle = np.asarray(f_vehicle, float)
    w = np.ones(len(f_logger)) if weights is None else np.asarray(weights, float)
    ok = np.isfinite(f_vehicle).all(axis=1) & np.isfinite(f_logger).all(axis=1) & (w > 0)
    if ok.sum() < 10:
        raise OrientationError("too few samples with a GNSS track to orient the logger")
    _, g = vertical_axis(f_logger[ok])
    A, B, w = f_logger[ok], f_vehicle[ok], w[ok]
    R = _wahba(A, B, w)
    # One trimmed refit: pairs the track cannot describe (a turn begun while braking into a stop,
    # a window across a jolt) are outliers, not noise; 3 robust sigmas of the residual keep the rest.
    res = np.linalg.norm(A @ R - B, axis=1)
    inlier = res <= 3.0 * 1.4826 * np.median(res) + 1e-9
    if inlier.sum() >= 10:
        A, B, w = A[inlier], B[inlier], w[inlier]
        R = _wahba(A, B, w)
    horiz = B[:, :2]
    fitted = (A @ R)[:, :2]
    var = float(np.average(np.sum((horiz - np.average(horiz, axis=0, weights=w)) ** 2, axis=1), weights=w))
    r2 = 1.0 - float(np.average(np.sum((horiz - fitted) ** 2, axis=1), weights=w)) / var if var > 0 else 0.0
    if r2 < min_r2:
        raise OrientationError(f"the logger's horizontal acceleration explains only {r2:.2f} of the track's "
                               f"(needs {min_r2:g}): logger not fixed in the vehicle?")
    return LoggerFrame(R[:, 2].copy(), R[:, 0].copy(), R[:, 1].copy(), g, r2)


def _wahba(A: np.ndarray, B: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The rotation R (logger ← vehicle) minimising Σ w |A − B Rᵀ|² (Kabsch, by SVD)."""
    U, _, Vt = np.linalg.svd((B * w[:, None]).T @ A)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    return Vt.T @ D @ U.T


def vehicle_channels(frame: LoggerFrame, acc: np.ndarray, gyro: np.ndarray | None) -> VehicleChannels:
    """Project the raw IMU (``acc`` m/s², ``gyro`` rad/s, each (n, 3) in the logger frame) on the
    vehicle's axes; gravity is removed from the vertical."""
    acc = np.asarray(acc, float)
    body = acc @ frame.up - frame.gravity_mps2
    long_acc = acc @ frame.forward
    pitch = None if gyro is None else -(np.asarray(gyro, float) @ frame.lateral)
    return VehicleChannels(body, long_acc, pitch)
