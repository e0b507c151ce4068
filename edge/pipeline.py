"""One vehicle pass on the edge: raw sensor chunks in, AP segments on the route's tile grid out.

Pure logic (no transport): the node feeds :class:`PassProcessor` with decoded chunks and publishes
what it returns. Output depends only on the stream, never on how it was chunked.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from numba import njit

from shared.dynamics.inverse import InverseModel, InverseStream
from shared.schema import FLAG_UNRELIABLE, ApSegment, PassDone, SensorChunk

from .chainage import ChainageTracker
from .drift import drift_trend


@dataclasses.dataclass(frozen=True)
class EdgeConfig:
    """Tiling and drift control. ``tile_m`` must be a whole number of ``spacing_m`` steps."""

    tile_m: float = 50.0
    spacing_m: float = 0.05
    drift_half_width_m: float = 150.0  # 0 disables drift control
    min_speed_mps: float = 0.5  # slower samples are not gridded (a stopped vehicle maps nowhere)
    # A vehicle whose inverse forgets a wrong initial state slowly (a rail carriage's lightly damped
    # body: ~18 s) would have nothing reliable in a short log. Its warm-up past this time is sent
    # flagged unreliable and down-weighted (σ × 100) instead of dropped; road vehicles settle sooner.
    hard_warmup_s: float = 1.0

    def __post_init__(self) -> None:
        if not (self.spacing_m > 0 and self.tile_m > 0):
            raise ValueError("EdgeConfig: tile_m and spacing_m must be positive")
        ratio = self.tile_m / self.spacing_m
        if abs(ratio - round(ratio)) > 1e-9:
            raise ValueError("EdgeConfig.tile_m: must be a whole number of spacing_m steps")

    @property
    def tile_points(self) -> int:
        return int(round(self.tile_m / self.spacing_m))

    @property
    def drift_points(self) -> int:
        return int(round(self.drift_half_width_m / self.spacing_m))


@njit(cache=True)
def _interp_between(x, y, j, xg):
    """``np.interp``'s value at ``xg`` strictly between samples ``j`` and ``j + 1``."""
    slope = (y[j + 1] - y[j]) / (x[j + 1] - x[j])
    v = slope * (xg - x[j]) + y[j]
    if np.isnan(v):  # as np.interp: try from the other end, then the flat case
        v = slope * (xg - x[j + 1]) + y[j + 1]
        if np.isnan(v) and y[j] == y[j + 1]:
            v = y[j]
    return v


@njit(cache=True)
def _to_grid(x, ap, t, reliable, first, spacing, values, times, valid):
    """Samples (chainage ``x`` non-decreasing) onto grid points ``first, first + 1, …`` (``values.size`` of
    them), in place: ``np.interp`` of ``ap`` and ``t`` (its arithmetic and its choice of neighbours,
    so the result is bit-identical), and a point is valid only if both neighbouring samples are reliable.
    One pass with two pointers, since grid points and samples both increase."""
    n = x.size
    le = 0  # samples <= the grid point
    lt = 0  # samples < the grid point
    for k in range(values.size):
        xg = (first + k) * spacing
        while le < n and x[le] <= xg:
            le += 1
        while lt < n and x[lt] < xg:
            lt += 1
        j = le - 1
        if j < 0:
            values[k], times[k] = ap[0], t[0]
        elif j == n - 1:  # at or beyond the last sample
            values[k], times[k] = ap[n - 1], t[n - 1]
        elif x[j] == xg:
            values[k], times[k] = ap[j], t[j]
        else:
            values[k] = _interp_between(x, ap, j, xg)
            times[k] = _interp_between(x, t, j, xg)
        pos = min(max(lt, 1), n - 1)
        valid[k] = reliable[pos] and reliable[pos - 1]


class _AxleGrid:
    """The AP of one axle on the global grid, growing as the pass advances.

    The grid lives in arrays of doubling capacity, so appending a chunk's points costs amortised
    O(points) (appending by concatenation copied the whole pass every chunk: O(n²) over a long
    pass). ``values``, ``valid`` and ``t`` are views of the filled part.
    """

    def __init__(self) -> None:
        self.base: int | None = None  # grid index of values[0]
        self.size = 0
        self._values = np.zeros(0)
        self._valid = np.zeros(0, dtype=bool)
        self._t = np.zeros(0)
        self._last: tuple[float, float, float, bool] | None = None  # (chainage, ap, t, reliable)

    @property
    def values(self) -> np.ndarray:
        return self._values[: self.size]

    @property
    def valid(self) -> np.ndarray:
        return self._valid[: self.size]

    @property
    def t(self) -> np.ndarray:
        return self._t[: self.size]

    @property
    def end(self) -> int:
        return (self.base or 0) + self.size

    def add(self, x: np.ndarray, ap: np.ndarray, t: np.ndarray, reliable: np.ndarray, spacing: float) -> None:
        """Interpolate samples (chainage ``x`` increasing) onto the grid points they pass."""
        if self._last is not None:
            x = np.concatenate([[self._last[0]], x])
            ap = np.concatenate([[self._last[1]], ap])
            t = np.concatenate([[self._last[2]], t])
            reliable = np.concatenate([[self._last[3]], reliable])
        if x.size == 0:
            return
        self._last = (float(x[-1]), float(ap[-1]), float(t[-1]), bool(reliable[-1]))
        if x.size < 2:
            return
        first = max(int(math.floor(x[0] / spacing)) + 1, 0) if self.base is not None else max(
            int(math.ceil(x[0] / spacing)), 0)
        if self.base is not None:
            first = max(first, self.end)
        last = int(math.floor(x[-1] / spacing))
        if last < first:
            return
        if self.base is None:
            self.base = first
        gap = first - self.end  # skipped grid points (e.g. a stop) stay invalid
        a = self.size + gap
        b = self._reserve(a + last + 1 - first)
        _to_grid(x, ap, t, reliable, first, spacing, self._values[a:b], self._t[a:b], self._valid[a:b])

    def _reserve(self, size: int) -> int:
        """Grow the capacity to at least ``size`` points (new points are 0, invalid); set the size."""
        if size > self._values.size:
            cap = max(size, 2 * self._values.size, 1024)
            for name in ("_values", "_valid", "_t"):
                old = getattr(self, name)
                new = np.zeros(cap, dtype=old.dtype)
                new[: self.size] = old[: self.size]
                setattr(self, name, new)
        self.size = size
        return size


def ap_sigma(values: np.ndarray, valid: np.ndarray) -> float:
    """Robust noise scale of an AP stretch (m): MAD of its second differences, scaled for white noise."""
    v = values[valid]
    if v.size < 5:
        return 1e-3
    d2 = np.diff(v, 2)
    return float(max(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0), 1e-7))


class PassProcessor:
    """Streams one pass: ``feed(chunk)`` → segments ready so far; ``finish()`` → the rest + done marker."""

    def __init__(self, model: InverseModel, vehicle_id: str, pass_id: str, route_id: str,
                 calib_version: int, config: EdgeConfig = EdgeConfig(), model_name: str = ""):
        self.model = model
        self.model_name = model_name
        self.system = model.system
        self.vehicle_id, self.pass_id, self.route_id = vehicle_id, pass_id, route_id
        self.calib_version = calib_version
        self.config = config
        self.inverse = InverseStream(model)
        self.tracker = ChainageTracker(model.constants.dt)
        self.grids = [_AxleGrid() for _ in range(self.system.n_contacts)]
        self.channel_names = [ch.name for ch in self.system.channels]
        self.next_tile: int | None = None
        self.seq = 0
        self.n_samples = 0
        self.speeds: list[float] = []
        self.finished = False
        # Time from which the inverse has forgotten its initial state; earlier points are sent
        # down-weighted (see EdgeConfig.hard_warmup_s). -inf: no such points.
        self.settled_t = math.inf if model.n_warmup * model.constants.dt > self.config.hard_warmup_s else -math.inf

    def feed(self, chunk: SensorChunk) -> list[ApSegment]:
        names = self.channel_names
        missing = [n for n in names if n not in chunk.channels]
        if missing:
            raise ValueError(f"chunk lacks channel(s) {', '.join(missing)} for model {chunk.vehicle_model}")
        if chunk.n:
            z = np.empty((chunk.n, len(names)))
            for j, name in enumerate(names):
                z[:, j] = chunk.channels[name]
            ap = self.inverse.update(z)
            x_cg = self.tracker.update(chunk.chainage, chunk.speed)
            t = chunk.t
            reliable = chunk.speed >= self.config.min_speed_mps  # moving
            hard = min(self.inverse.reliable_from, int(math.ceil(self.config.hard_warmup_s / self.model.constants.dt)))
            warmup = hard - self.n_samples  # samples of this chunk still warming up
            if warmup > 0:
                reliable[:warmup] = False
            soft_end = self.inverse.reliable_from - self.n_samples
            if self.inverse.reliable_from > hard and 0 <= soft_end < chunk.n:
                self.settled_t = float(t[soft_end])  # the first sample past the whole warm-up
            for i, grid in enumerate(self.grids):
                grid.add(x_cg + self.system.offsets_m[i], ap[:, i], t, reliable, self.config.spacing_m)
            self.n_samples += chunk.n
            self.speeds.append(float(np.mean(chunk.speed)))
        return self._emit(final=False)

    def finish(self) -> tuple[list[ApSegment], PassDone]:
        segments = self._emit(final=True)
        self.finished = True
        done = PassDone(vehicle_id=self.vehicle_id, pass_id=self.pass_id, route_id=self.route_id,
                        calib_version=self.calib_version, n_segments=self.seq,
                        vehicle_model=self.model_name)
        return segments, done

    def _emit(self, final: bool) -> list[ApSegment]:
        grids = [g for g in self.grids if g.base is not None]
        if not grids:
            return []
        P = self.config.tile_points
        if self.next_tile is None:
            self.next_tile = min(g.base for g in grids) // P
        # A tile is ready once every axle's grid extends past its end by the drift half-width.
        frontier = min(g.end for g in grids) if len(grids) == len(self.grids) else 0
        last_tile = max(g.end for g in grids) // P + 1 if final else (frontier - self.config.drift_points) // P
        out = []
        while self.next_tile < last_tile or (final and self.next_tile * P < max(g.end for g in grids)):
            out.extend(self._tile_segments(self.next_tile))
            self.next_tile += 1
        return out

    def _tile_segments(self, tile: int) -> list[ApSegment]:
        P, H = self.config.tile_points, self.config.drift_points
        out = []
        for axle, g in enumerate(self.grids, start=1):
            if g.base is None:
                continue
            lo, hi = tile * P, (tile + 1) * P
            a, b = max(lo, g.base), min(hi, g.end)
            if b <= a:
                continue
            # Drift control on a window around the tile (everything within ±H is available).
            wa, wb = max(g.base, a - H), min(g.end, b + H)
            vals = g.values[wa - g.base : wb - g.base]
            valid = g.valid[wa - g.base : wb - g.base]
            if H > 0:
                trend = drift_trend(vals, valid, H)
                vals = vals - trend
            seg_vals = vals[a - wa : b - wa]
            seg_valid = valid[a - wa : b - wa]
            if not seg_valid.any():
                continue
            first, last = np.flatnonzero(seg_valid)[[0, -1]]
            seg_vals, seg_valid = seg_vals[first : last + 1], seg_valid[first : last + 1]
            sigma = np.full(seg_vals.size, ap_sigma(vals, valid))
            flags = 0
            t_seg = g.t[a - g.base + first : a - g.base + last + 1]
            unsettled = t_seg < self.settled_t
            if unsettled.any():
                sigma[unsettled] *= 100.0
                flags |= FLAG_UNRELIABLE
            if not seg_valid.all():
                sigma[~seg_valid] *= 100.0  # unreliable points carry (almost) no weight
                seg_vals = np.where(seg_valid, seg_vals, 0.0)
                flags |= FLAG_UNRELIABLE
            out.append(ApSegment.make(
                seg_vals, sigma, vehicle_id=self.vehicle_id, pass_id=self.pass_id, route_id=self.route_id,
                tile=tile, axle=axle, start_index=a + int(first), spacing_m=self.config.spacing_m,
                calib_version=self.calib_version, speed_mps=float(np.mean(self.speeds)) if self.speeds else 0.0,
                t_first=float(t_seg[0]), t_last=float(t_seg[-1]), seq=self.seq, flags=flags,
            ))
            self.seq += 1
        return out
