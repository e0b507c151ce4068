"""Each pass registered to the others along the bridge's window, from the road off the span.

The estimators compare every pass's AP with the leave-one-out consensus of the others on the
approach and exit (the road there is common to all passes) and read its deflection on the span
against the registry's supports. A pass whose chainage is off by a few centimetres relative to the
others leaves the road's own slope times that error in AP − consensus: on a class-A road a
5 cm error leaves tens of micrometres, as much as the deflection under the wheel, and the crack's
signature, a few per cent of it, is lost. Where passes come from an odometer with a per-run scale
error, a GNSS fix, or a logger whose filter delays the acceleration against the time stamps (a
chainage shift of speed × delay), the route's alignment places them to a few centimetres at best.

Here each pass's shift is read from the road it shares with the others (least squares over a grid
of shifts with a local offset and slope free, refined by a parabola) and centred: the road does not
see a shift common to all passes, so the fleet's frame is kept — except for the part of the shifts
that grows with the pass's speed. A shift of speed × τ is what a constant delay τ between the
acceleration and the chainage's time base leaves (a logger's causal anti-alias filter, a channel
latency); odometer scale errors and GNSS biases do not scale with speed. Where the centred shifts'
regression on speed is significant (:data:`SIGNIFICANCE` standard errors), the delay it gives is
taken out whole, its common part (mean speed × τ) included, and every pass moves. Otherwise a pass
moves only where its shift is significant against its own error (:data:`SIGNIFICANCE`) and larger
than the registration resolves (:data:`MIN_SHIFT_M`), so passes that already agree are left exactly
as they are.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from cloud.bridge.passdata import PassData, Reference

#: shifts searched, m: beyond the alignment's residual after a per-run odometer error
MAX_SHIFT_M = 0.5
#: the road compared: this far from each support, m (the deflection under the wheel is zero off the
#: span, and the wheel reaches the deck a tyre patch before the support)
SUPPORT_CLEARANCE_M = 1.0
#: a pass moves only when its shift exceeds this, m: a tenth of the grid step, below which moving it
#: changes it more by the interpolation's smoothing than by the shift
MIN_SHIFT_M = 0.005
#: a shift counts when it exceeds this many of its standard errors (the least-squares error of a
#: shift: residual variance over the sum of the road's squared slope)
SIGNIFICANCE = 3.0
#: least points of road a pass must share with the consensus for its shift to be read
MIN_POINTS = 200


def _road_mask(p: PassData) -> np.ndarray:
    w = p.window
    x = w.x
    return (x < -SUPPORT_CLEARANCE_M) | (x > w.span_m + SUPPORT_CLEARANCE_M)


def _moved(values: np.ndarray, k: float) -> np.ndarray:
    """``values`` read ``k`` grid steps later (linear interpolation; the ends held)."""
    i = np.arange(values.size, dtype=float)
    return np.interp(i + k, i, values)


def _moved_valid(valid: np.ndarray, k: float) -> np.ndarray:
    """Where data read ``k`` grid steps later come from valid points of the window (both neighbours)."""
    i = np.arange(valid.size, dtype=float)
    return (_moved(valid.astype(float), k) > 0.999) & (i + k >= 0.0) & (i + k <= valid.size - 1)


def read_shift(p: PassData, consensus: np.ndarray) -> tuple[float, float] | None:
    """How far (m) the pass's road lies after the consensus's, ``p.ap(x + s) ≈ consensus(x)`` up to an
    offset and slope on the road off the span, and that shift's standard error (m); None if the pass
    shares too little road with the consensus."""
    w = p.window
    h = w.spacing_m
    ks = np.arange(-int(round(MAX_SHIFT_M / h)), int(round(MAX_SHIFT_M / h)) + 1)
    use = _road_mask(p) & np.isfinite(consensus)
    x = w.x
    costs = np.full(ks.size, np.inf)
    counts = np.zeros(ks.size)
    for j, k in enumerate(ks):
        ok = use & _moved_valid(p.valid, float(k))
        if ok.sum() < MIN_POINTS:
            continue
        r = _moved(p.ap, float(k))[ok] - consensus[ok]
        A = np.column_stack([np.ones(ok.sum()), x[ok]])
        coef, *_ = np.linalg.lstsq(A, r, rcond=None)
        costs[j], counts[j] = float(np.mean((r - A @ coef) ** 2)), ok.sum()
    if not np.isfinite(costs).any():
        return None
    j = int(np.argmin(costs))
    if j == 0 or j == ks.size - 1 or not np.isfinite(costs[j - 1]) or not np.isfinite(costs[j + 1]):
        return float(ks[j] * h), MAX_SHIFT_M  # at the search's edge: no error read, never significant
    c0, c1, c2 = costs[j - 1], costs[j], costs[j + 1]
    curv = c0 - 2 * c1 + c2  # = 2·mean(slope²) per grid step² near the minimum
    if not curv > 0:
        return float(ks[j] * h), MAX_SHIFT_M
    step = float(np.clip(0.5 * (c0 - c2) / curv, -0.5, 0.5))
    sd_steps = float(np.sqrt(2.0 * c1 / (counts[j] * curv)))
    return float((ks[j] + step) * h), sd_steps * h


def register(passes: Sequence[PassData], sweeps: int = 2) -> list[float]:
    """Each pass's shift (m, centred over the passes that have one, plus the shift a delay read from
    the shifts' dependence on speed leaves; 0 where none is significant), read against the
    leave-one-out consensus of the others, the consensus rebuilt from the moved passes between
    ``sweeps``."""
    shifts = np.zeros(len(passes))
    v = np.array([p.speed_mps for p in passes])
    for _ in range(sweeps):
        moved = [shift_pass(p, s) for p, s in zip(passes, shifts)]
        ref = Reference.of(moved)
        read = [read_shift(p, ref.mean(leave_out=m)) for p, m in zip(passes, moved)]
        have = np.array([r is not None for r in read])
        if not have.any():
            return [0.0] * len(passes)
        new = np.array([r[0] if r is not None else 0.0 for r in read])
        sd = np.array([r[1] if r is not None else np.inf for r in read])
        new[have] -= new[have].mean()
        shifts = np.where(have & (np.abs(new) > SIGNIFICANCE * sd), new, 0.0)
        tau = delay(v[have], new[have])
        if tau:
            shifts = np.where(have, new, 0.0) + v.mean() * tau - np.where(have, 0.0, (v.mean() - v) * tau)
    return [float(s) for s in shifts]


def delay(speed_mps: np.ndarray, centred_m: np.ndarray) -> float:
    """The delay τ (s) in ``centred ≈ (v − v̄)·τ``, or 0 when it is not significant or fewer than
    four passes have a shift."""
    if speed_mps.size < 4:
        return 0.0
    dv = speed_mps - speed_mps.mean()
    sxx = float(dv @ dv)
    if not sxx > 0:
        return 0.0
    tau = float(dv @ centred_m) / sxx
    rest = centred_m - centred_m.mean() - tau * dv
    se = math.sqrt(float(rest @ rest) / (speed_mps.size - 2) / sxx)
    return tau if abs(tau) > SIGNIFICANCE * se else 0.0


def shift_pass(p: PassData, shift_m: float) -> PassData:
    """The pass with its window data read ``shift_m`` later (the road it saw at x + s placed at x);
    unchanged below :data:`MIN_SHIFT_M`. Points whose source is outside the pass's valid data
    become invalid."""
    if abs(shift_m) < MIN_SHIFT_M:
        return p
    k = shift_m / p.window.spacing_m
    valid = _moved_valid(p.valid, k)
    return dataclasses.replace(p, ap=np.where(valid, _moved(p.ap, k), 0.0), valid=valid,
                               load_factor=_moved(p.load_factor, k))
