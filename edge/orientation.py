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

The GNSS track's accelerations are noisy (metres of position error, differentiated twice), so the
rotation leaves the vertical a few milliradians off, and |g| from the mean specific force takes the
drive's mean lateral acceleration in quadrature (a loop of left turns averages tenths of m/s²
sideways). Either leaves a constant of a fraction of a mm/s² in ``body_acc`` on a straight pass,
and the inverse integrates ``body_acc`` twice: such a constant bends each pass's profile by
millimetres over tens of metres, which the cloud reads as drift, widening the band and the IRI's
draws. `level_vertical` takes the vertical from the gyro (a car turns about it) and gravity from
the stretches between standstills, where the body's own acceleration integrates to zero.
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


def window_sd(z: np.ndarray, window: int) -> np.ndarray:
    """The sd of ``z`` over each run of ``window`` consecutive samples (``len(z) - window + 1`` of
    them), from cumulative sums of ``z`` less its mean (which keeps them small)."""
    d = np.asarray(z, float) - np.mean(z)
    c1 = np.concatenate([[0.0], np.cumsum(d)])
    c2 = np.concatenate([[0.0], np.cumsum(d**2)])
    m1 = (c1[window:] - c1[:-window]) / window
    return np.sqrt(np.maximum((c2[window:] - c2[:-window]) / window - m1**2, 0.0))


def standstills(acc: np.ndarray, up: np.ndarray, window: int, still_ratio: float = 0.1) -> np.ndarray:
    """Sample indices in the middle of each standstill of one run of uniform samples ``acc`` (n, 3).

    Standing, the body settles: the vertical channel's sd over ``window`` samples falls to the
    sensor's noise, far under its level while rolling (the road excites the body at any speed
    worth a pass). A standstill is a run of windows below ``still_ratio`` of the run's median sd, at
    least half a window long; its middle sample is taken, where the body has settled most.
    """
    z = np.asarray(acc, float) @ up
    if len(z) < 3 * window:
        return np.zeros(0, np.int64)
    sd = window_sd(z, window)
    still = sd < still_ratio * np.median(sd)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], still.astype(np.int8), [0]])))
    mids = [(a + b) // 2 + window // 2 for a, b in zip(edges[::2], edges[1::2]) if b - a >= window // 2]
    return np.asarray(mids, np.int64)


def level_vertical(frame: LoggerFrame, acc_runs: list[np.ndarray], gyro_runs: list[np.ndarray] | None,
                   window: int, min_axis_ratio: float = 10.0) -> LoggerFrame:
    """The frame with its vertical axis from the gyro and its gravity from the rests of the drive.

    ``acc_runs`` / ``gyro_runs``: the drive's raw specific force (m/s²) and turn rate (rad/s) in the
    logger frame, one (n, 3) array per run of uniform samples (``gyro_runs`` None: no gyro);
    ``window``: samples of about a second.

    Axis: a car turns about its vertical, so the turn rate's block means (``window`` samples: the
    body's pitch and roll vibration average out, turns last seconds) scatter along that axis; their
    principal axis is it, to a fraction of a milliradian, where the GNSS track's accelerations leave
    milliradians. A constant gyro bias does not move a covariance. The axis is taken only when its
    variance exceeds the next one's ``min_axis_ratio`` times (the drive turned); forward and lateral
    are then made orthogonal to it.

    Gravity: the mean of the vertical between the first and last standstill of each run
    (`standstills`): the body is at rest at both ends, so its own acceleration integrates to zero
    there, and the vehicle's longitudinal too. Without two standstills in a run, the frame's own
    gravity is kept.
    """
    up, fwd = frame.up, frame.forward
    if gyro_runs is not None:
        blocks = [np.asarray(w, float)[: (len(w) // window) * window].reshape(-1, window, 3).mean(axis=1)
                  for w in gyro_runs if len(w) >= window]
        w = np.concatenate(blocks) if blocks else np.zeros((0, 3))
        w = w[np.isfinite(w).all(axis=1)]
        if len(w) >= 10:
            vals, vecs = np.linalg.eigh(np.cov(w.T))
            if vals[2] > min_axis_ratio * max(vals[1], 1e-30):
                axis = vecs[:, 2] * np.sign(vecs[:, 2] @ up)
                up = axis / np.linalg.norm(axis)
                fwd = fwd - (fwd @ up) * up
                fwd = fwd / np.linalg.norm(fwd)
    total, count = 0.0, 0
    for acc in acc_runs:
        acc = np.asarray(acc, float)
        rest = standstills(acc, up, window)
        if len(rest) >= 2:
            z = acc[rest[0]:rest[-1]] @ up
            total += float(np.sum(z))
            count += len(z)
    g = total / count if count else frame.gravity_mps2
    return LoggerFrame(up, fwd, np.cross(up, fwd), g, frame.heading_fit_r2)


def vehicle_channels(frame: LoggerFrame, acc: np.ndarray, gyro: np.ndarray | None) -> VehicleChannels:
    """Project the raw IMU (``acc`` m/s², ``gyro`` rad/s, each (n, 3) in the logger frame) on the
    vehicle's axes; gravity is removed from the vertical."""
    acc = np.asarray(acc, float)
    body = acc @ frame.up - frame.gravity_mps2
    long_acc = acc @ frame.forward
    pitch = None if gyro is None else -(np.asarray(gyro, float) @ frame.lateral)
    return VehicleChannels(body, long_acc, pitch)
