"""Along-track fusion: matched GNSS chainages and the IMU's longitudinal acceleration → a smooth
distance, speed and acceleration, by a Kalman filter and Rauch–Tung–Striebel smoother over time.

State ``[s, v, b, e]``: distance along the direction of travel (m), speed (m/s), the
accelerometer's bias (m/s²; it also takes a road grade's share of gravity) and the GNSS fixes'
slowly varying along-track error (m). The measured longitudinal acceleration drives the state
(s̈ = a_imu − b + w, white w of density ``q_acc``; b a random walk of density ``q_bias``); each fix
measures s + e with the rest of its 1σ as white noise. A receiver's error is mostly not white: the
satellites' geometry, the atmosphere and multipath change over tens of seconds, so consecutive fixes
share most of their error (e a first-order Gauss–Markov process of time constant
``gnss_tau_s`` carrying ``gnss_correlated_share`` of each fix's variance). Treating fixes as
independent would let the track follow that wander within a pass — a smooth but non-linear chainage
error no pass alignment (a shift and a stretch) removes, blurring the short waves when passes are
fused. With e in the state, the IMU says how the vehicle moves within seconds and the fixes where it
is, on average (metres, absolute, no cumulative stretch), so a short dropout is bridged without a
jump. Without an IMU the input is zero and ``q_acc`` must be larger: a constant-acceleration-noise
model of the GNSS track alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from shared.jit import kernel


@dataclass(frozen=True)
class FusionSettings:
    """``q_acc``: white acceleration noise density, (m/s²)²/Hz, with an IMU; ``q_acc_no_imu``: the
    same without one; ``q_bias``: bias random-walk density, (m/s²)²/s; ``bias_sd``: prior 1σ of the
    bias, m/s²; ``rate_hz``: the rate the filter runs at (the IMU is averaged down to it);
    ``gnss_tau_s``: time constant of the fixes' correlated error, s; ``gnss_correlated_share``: the
    share of a fix's variance that is correlated (0: white fixes).

    ``q_acc`` is a phone accelerometer's own noise density (~1e-5) with a margin of two for what a
    tilt error of a milliradian leaks in of the body's vibration (far less); ``q_bias`` is a phone
    accelerometer's bias instability (about a milli-g over an hour, with temperature). Any freedom
    beyond the sensor's own is freedom for the fixes' wander to shape the track: a model that lets
    the acceleration or the bias move by millimetres per second squared over a pass lets a wander
    of metres over tens of seconds bend the pass's chainage by centimetres, which no pass alignment
    (a shift and a stretch) removes. So the IMU, not the fixes, shapes the track within a pass,
    provided the bias is known (from the whole drive, `edge.trip.imu_bias`): a bias wrong by
    0.01 m/s² bends a 20 s pass by decimetres. A road's changing grade enters as a changing bias
    (g times the grade's change), so on hilly roads ``q_bias`` must grow with it."""

    q_acc: float = 2e-5
    q_acc_no_imu: float = 2.0
    q_bias: float = 3e-8
    bias_sd: float = 0.3
    rate_hz: float = 50.0
    gnss_tau_s: float = 30.0
    gnss_correlated_share: float = 0.7

    def __post_init__(self):
        for k, v in self.__dict__.items():
            if k == "gnss_correlated_share":
                if not (isinstance(v, (int, float)) and 0.0 <= v < 1.0):
                    raise ValueError(f"FusionSettings.{k}: must be in [0, 1), got {v!r}")
            elif not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"FusionSettings.{k}: must be a positive finite number, got {v!r}")


class Track(NamedTuple):
    """The smoothed track at the requested times: distance (m), speed (m/s), acceleration (m/s²),
    and the distance's posterior 1σ (m)."""

    s: np.ndarray
    v: np.ndarray
    a: np.ndarray
    s_sd: np.ndarray


@kernel
def _rts(h, acc, meas, meas_var, q_acc, q_bias, phi, q_gnss, x0, P0):
    n = acc.size
    xf = np.empty((n, 4))
    Pf = np.empty((n, 4, 4))
    xp = np.empty((n, 4))
    Pp = np.empty((n, 4, 4))
    F = np.array([[1.0, h, -0.5 * h * h, 0.0], [0.0, 1.0, -h, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, phi]])
    B = np.array([0.5 * h * h, h, 0.0, 0.0])
    Q = np.array([[q_acc * h**3 / 3.0, q_acc * h * h / 2.0, 0.0, 0.0],
                  [q_acc * h * h / 2.0, q_acc * h, 0.0, 0.0],
                  [0.0, 0.0, q_bias * h, 0.0],
                  [0.0, 0.0, 0.0, q_gnss]])
    Hm = np.array([1.0, 0.0, 0.0, 1.0])  # a fix sees the position and its own correlated error
    x = x0.copy()
    P = P0.copy()
    for k in range(n):
        if k > 0:
            x = F @ x + B * acc[k - 1]
            P = F @ P @ F.T + Q
        xp[k] = x
        Pp[k] = P
        if meas_var[k] > 0.0:  # a fix at this step: update on s + e
            PH = P @ Hm
            S = Hm @ PH + meas_var[k]
            K = PH / S
            x = x + K * (meas[k] - Hm @ x)
            P = P - np.outer(K, PH)
        xf[k] = x
        Pf[k] = P
    xs = xf.copy()
    Ps = Pf.copy()
    for k in range(n - 2, -1, -1):
        G = Pf[k] @ F.T @ np.linalg.inv(Pp[k + 1])
        xs[k] = xf[k] + G @ (xs[k + 1] - xp[k + 1])
        Ps[k] = Pf[k] + G @ (Ps[k + 1] - Pp[k + 1]) @ G.T
    return xs, Ps


def smooth_track(t: np.ndarray, long_acc: np.ndarray | None, t_fix: np.ndarray, s_fix: np.ndarray,
                 sd_fix: np.ndarray, settings: FusionSettings = FusionSettings(), bias_mps2: float = 0.0,
                 bias_sd_mps2: float | None = None) -> Track:
    """Fuse fixes ``s_fix`` (m along the direction of travel, 1σ ``sd_fix``, at times ``t_fix``)
    with ``long_acc`` (m/s² at the uniform times ``t``, or None) and return the track at ``t``.

    ``bias_mps2``, ``bias_sd_mps2``: the accelerometer bias's prior mean and 1σ (default 0 and the
    settings' ``bias_sd``), e.g. from the whole drive (`edge.trip.imu_bias`): a stretch's own fixes
    hardly tell a bias from the GNSS error's wander, and a wrong bias bends the track."""
    t = np.asarray(t, float)
    if len(t) < 2 or len(t_fix) < 2:
        raise ValueError("smooth_track: needs at least two samples and two fixes")
    h_in = float(t[1] - t[0])
    m = max(1, int(round(1.0 / (settings.rate_hz * h_in))))
    h = m * h_in
    nb = (len(t) + m - 1) // m
    tb = t[0] + np.arange(nb) * h
    if long_acc is None:
        acc = np.zeros(nb)
        q = settings.q_acc_no_imu
    else:
        pad = np.full(nb * m, np.nan)
        pad[: len(t)] = long_acc
        acc = np.nanmean(pad.reshape(nb, m), axis=1)  # block means: the filter's own anti-alias
        q = settings.q_acc
    meas = np.zeros(nb)
    var = np.zeros(nb)
    idx = np.clip(np.rint((np.asarray(t_fix, float) - tb[0]) / h).astype(int), 0, nb - 1)
    rho = settings.gnss_correlated_share
    for i, k in enumerate(idx):  # one fix per filter step: the later one wins (5–10 Hz ≪ rate_hz)
        meas[k] = s_fix[i]
        var[k] = (1.0 - rho) * max(float(sd_fix[i]), 1e-3) ** 2
    # The correlated error's stationary variance: the fixes' typical correlated share (floored at a
    # millimetre's, nil against metre fixes, so the smoother's covariances stay invertible).
    e_var = max(rho * float(np.median(np.maximum(np.asarray(sd_fix, float), 1e-3))) ** 2, 1e-6)
    phi = math.exp(-h / settings.gnss_tau_s)
    first = int(idx[0])
    v0 = (s_fix[-1] - s_fix[0]) / max(float(t_fix[-1] - t_fix[0]), h)
    b_sd = settings.bias_sd if bias_sd_mps2 is None else max(float(bias_sd_mps2), 1e-6)
    x0 = np.array([s_fix[0] - v0 * (tb[first] - tb[0]), v0, float(bias_mps2) if long_acc is not None else 0.0, 0.0])
    P0 = np.diag([100.0**2, 10.0**2, b_sd**2, e_var])
    xs, Ps = _rts(h, acc, meas, var, q, settings.q_bias, phi, e_var * (1.0 - phi * phi), x0, P0)
    # Back to the input times: the distance by cubic Hermite (s, v known), speed linearly.
    s = np.interp(t, tb, xs[:, 0])
    v = np.interp(t, tb, xs[:, 1])
    u = (t - tb[0]) / h
    k = np.clip(np.floor(u).astype(int), 0, nb - 2) if nb > 1 else np.zeros(len(t), int)
    if nb > 1:
        f = u - k
        h00, h10 = 2 * f**3 - 3 * f**2 + 1, f**3 - 2 * f**2 + f
        h01, h11 = -2 * f**3 + 3 * f**2, f**3 - f**2
        s = h00 * xs[k, 0] + h10 * h * xs[k, 1] + h01 * xs[k + 1, 0] + h11 * h * xs[k + 1, 1]
    bias = np.interp(t, tb, xs[:, 2])
    a = (np.interp(t, tb, acc) - bias) if long_acc is None else np.asarray(long_acc, float) - bias
    if long_acc is None:
        a = np.gradient(v, t)
    return Track(s, v, a, np.sqrt(np.interp(t, tb, Ps[:, 0, 0])))
