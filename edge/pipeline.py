"""One vehicle pass on the edge: raw sensor chunks in, AP segments on the route's tile grid out.

Pure logic (no transport): the node feeds :class:`PassProcessor` with decoded chunks and publishes
what it returns. Output depends only on the stream, never on how it was chunked.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

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


class _AxleGrid:
    """The AP of one axle on the global grid, growing as the pass advances."""

    def __init__(self) -> None:
        self.base: int | None = None  # grid index of values[0]
        self.values = np.zeros(0)
        self.valid = np.zeros(0, dtype=bool)
        self.t = np.zeros(0)
        self._last: tuple[float, float, float, bool] | None = None  # (chainage, ap, t, reliable)

    @property
    def end(self) -> int:
        return (self.base or 0) + self.values.size

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
        idx = np.arange(first, last + 1)
        xg = idx * spacing
        vals = np.interp(xg, x, ap)
        tg = np.interp(xg, x, t)
        # A grid point is reliable only if both neighbouring samples are.
        pos = np.clip(np.searchsorted(x, xg, side="left"), 1, x.size - 1)
        ok = reliable[pos] & reliable[pos - 1]
        if self.base is None:
            self.base = first
        gap = first - self.end
        if gap > 0:  # skipped grid points (e.g. a stop) stay invalid
            self.values = np.concatenate([self.values, np.zeros(gap)])
            self.valid = np.concatenate([self.valid, np.zeros(gap, bool)])
            self.t = np.concatenate([self.t, np.zeros(gap)])
        self.values = np.concatenate([self.values, vals])
        self.valid = np.concatenate([self.valid, ok])
        self.t = np.concatenate([self.t, tg])


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
        self.next_tile: int | None = None
        self.seq = 0
        self.n_samples = 0
        self.speeds: list[float] = []
        self.finished = False

    def feed(self, chunk: SensorChunk) -> list[ApSegment]:
        names = [ch.name for ch in self.system.channels]
        missing = [n for n in names if n not in chunk.channels]
        if missing:
            raise ValueError(f"chunk lacks channel(s) {', '.join(missing)} for model {chunk.vehicle_model}")
        if chunk.n:
            z = np.stack([chunk.channels[n].astype(np.float64) for n in names], axis=1)
            ap = self.inverse.update(z)
            x_cg = self.tracker.update(chunk.chainage, chunk.speed)
            t = chunk.t
            k = self.n_samples + np.arange(chunk.n)
            moving = chunk.speed >= self.config.min_speed_mps
            reliable = (k >= self.inverse.reliable_from) & moving
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
            if not seg_valid.all():
                sigma[~seg_valid] *= 100.0  # unreliable points carry (almost) no weight
                seg_vals = np.where(seg_valid, seg_vals, 0.0)
                flags |= FLAG_UNRELIABLE
            t_seg = g.t[a - g.base + first : a - g.base + last + 1]
            out.append(ApSegment.make(
                seg_vals, sigma, vehicle_id=self.vehicle_id, pass_id=self.pass_id, route_id=self.route_id,
                tile=tile, axle=axle, start_index=a + int(first), spacing_m=self.config.spacing_m,
                calib_version=self.calib_version, speed_mps=float(np.mean(self.speeds)) if self.speeds else 0.0,
                t_first=float(t_seg[0]), t_last=float(t_seg[-1]), seq=self.seq, flags=flags,
            ))
            self.seq += 1
        return out
