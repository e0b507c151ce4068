"""Chart geometry for Rerun's 2D view: data ranges mapped onto a fixed screen box, with ticks a reader can label.

Rerun's 2D view has no axes, draws +y downwards and keeps one scale for x and y. A chart here is a
`Frame`: a data rectangle (e.g. chainage m × elevation mm) mapped onto a fixed box of screen units
(the view's visual bounds never change), so two quantities of different units each fill their
side of the box, and the frame's gridlines and tick labels say what the positions mean. Pure numpy:
:mod:`cloud.view` turns the geometry into Rerun archetypes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

NICE_STEPS = (1.0, 2.0, 2.5, 5.0, 10.0)


def nice_step(span: float, target: int = 6) -> float:
    """A tick step of 1, 2, 2.5 or 5 × 10^k giving about ``target`` intervals over ``span``."""
    if not (span > 0 and math.isfinite(span)):
        return 1.0
    raw = span / max(target, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    return next(s * mag for s in NICE_STEPS if s * mag >= raw * (1 - 1e-9))


def nice_range(lo: float, hi: float, target: int = 6, pad: float = 0.05) -> tuple[float, float, float]:
    """``(lo, hi, step)``: the data range widened by ``pad`` of itself, then out to multiples of a nice step.

    A degenerate or non-finite range becomes ±1 around its centre (or around 0)."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        lo, hi = -1.0, 1.0
    if hi - lo <= 1e-12 * max(1.0, abs(lo), abs(hi)):
        c = 0.5 * (lo + hi)
        lo, hi = c - 1.0, c + 1.0
    margin = pad * (hi - lo)
    lo, hi = lo - margin, hi + margin
    step = nice_step(hi - lo, target)
    return math.floor(lo / step) * step, math.ceil(hi / step) * step, step


def ticks(lo: float, hi: float, step: float) -> np.ndarray:
    """Multiples of ``step`` in ``[lo, hi]`` (rounded so that labels print cleanly)."""
    first = math.ceil(lo / step - 1e-9)
    last = math.floor(hi / step + 1e-9)
    return np.round(np.arange(first, last + 1) * step, 10)


def tick_label(value: float, step: float) -> str:
    """A tick's label with as many decimals as the step needs (2.5 → one, 0.05 → two)."""
    decimals = next((d for d in range(7) if abs(step * 10**d - round(step * 10**d)) < 1e-6), 6)
    text = f"{value:.{decimals}f}"
    return "0" if float(text) == 0 else text


@dataclass(frozen=True)
class Frame:
    """Data ``[x_lo, x_hi] × [y_lo, y_hi]`` drawn in the screen box ``[0, width] × [0, height]``.

    Screen y grows downwards, so ``y_hi`` is at the top (screen y = 0). ``x_step``/``y_step`` are
    the tick steps (data units).
    """

    x_lo: float
    x_hi: float
    x_step: float
    y_lo: float
    y_hi: float
    y_step: float
    width: float
    height: float

    def __post_init__(self):
        if not (self.x_hi > self.x_lo and self.y_hi > self.y_lo and self.width > 0 and self.height > 0):
            raise ValueError(f"Frame: empty data range or screen box: {self}")

    @classmethod
    def fit(cls, x: tuple[float, float], y: tuple[float, float], width: float, height: float,
            x_pad: float = 0.0, y_pad: float = 0.05, x_ticks: int = 10, y_ticks: int = 5) -> Frame:
        """A frame whose nice ranges hold ``x = (lo, hi)`` and ``y = (lo, hi)`` (data units)."""
        xl, xh, xs = nice_range(*x, target=x_ticks, pad=x_pad)
        yl, yh, ys = nice_range(*y, target=y_ticks, pad=y_pad)
        return cls(xl, xh, xs, yl, yh, ys, float(width), float(height))

    def sx(self, x) -> np.ndarray:
        """Screen x of data x."""
        return (np.asarray(x, dtype=float) - self.x_lo) / (self.x_hi - self.x_lo) * self.width

    def sy(self, y) -> np.ndarray:
        """Screen y of data y (down the screen is down the data)."""
        return (self.y_hi - np.asarray(y, dtype=float)) / (self.y_hi - self.y_lo) * self.height

    def data_y(self, screen_y) -> np.ndarray:
        """Data y of screen y: the inverse of `sy`, for readers of a recording."""
        return self.y_hi - np.asarray(screen_y, dtype=float) / self.height * (self.y_hi - self.y_lo)

    def points(self, x, y) -> np.ndarray:
        """(n, 2) screen points of data ``(x, y)``."""
        return np.column_stack([self.sx(x), self.sy(y)])

    def x_ticks(self) -> np.ndarray:
        return ticks(self.x_lo, self.x_hi, self.x_step)

    def y_ticks(self) -> np.ndarray:
        return ticks(self.y_lo, self.y_hi, self.y_step)

    def gridlines(self) -> list[np.ndarray]:
        """A vertical line per x tick and a horizontal one per y tick, across the box."""
        v = [np.array([[s, 0.0], [s, self.height]]) for s in self.sx(self.x_ticks())]
        h = [np.array([[0.0, s], [self.width, s]]) for s in self.sy(self.y_ticks())]
        return v + h

    def box(self) -> np.ndarray:
        """The frame's outline as one closed strip."""
        w, h = self.width, self.height
        return np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h], [0.0, 0.0]])

    def x_labels(self, offset: float) -> tuple[np.ndarray, list[str]]:
        """Positions ``offset`` screen units below the box and texts of the x tick labels."""
        t = self.x_ticks()
        return (np.column_stack([self.sx(t), np.full(t.size, self.height + offset)]),
                [tick_label(v, self.x_step) for v in t])

    def y_labels(self, offset: float) -> tuple[np.ndarray, list[str]]:
        """Positions ``offset`` screen units left of the box and texts of the y tick labels."""
        t = self.y_ticks()
        return np.column_stack([np.full(t.size, -offset), self.sy(t)]), [tick_label(v, self.y_step) for v in t]
