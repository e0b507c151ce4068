"""One vehicle pass on the edge: raw sensor chunks in, AP segments on the route's tile grid out.

Pure logic (no transport): the node feeds :class:`PassProcessor` with decoded chunks and publishes
what it returns. Output depends only on the stream, never on how it was chunked.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from shared.dynamics.inverse import InverseModel, InverseStream
from shared.jit import kernel
from shared.schema import FLAG_UNRELIABLE, ApSegment, PassDone, SensorChunk
from shared.vehicles import RAIL_MODELS

from .chainage import ChainageTracker, track_into
from .drift import drift_trend
from .error_model import (BAND_ORDER, LONGEST_M, encode_error_model, fit_error_band, median_abs_deviations,
                          noise_sd_from_d4, unit_error_band, unit_spectra, white_equivalent)


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
    # Anti-alias the AP before gridding (see :func:`_antialias`); off: plain linear interpolation,
    # which folds the inverse's noise up to 250 Hz into the 5 cm grid's band: on a bridge span that is
    # ~10× the sensor noise at the quarter-car's γ = 0.6, and it is coloured like the vehicle's
    # transfer, so the bridge's calibration nuisance fits it and reads the span stiff
    # (tests/test_bridge_common_calibration.py).
    antialias: bool = True
    # The AP error model sent with each segment (edge.error_model): each channel's noise level from
    # its data pushed through the inverse's transfer, fitted with a precision band of this order
    # over wavelengths up to error_longest_m. Off: segments carry only the white sigma.
    error_model: bool = True
    error_band_order: int = BAND_ORDER
    error_longest_m: float = LONGEST_M

    def __post_init__(self) -> None:
        if not (self.spacing_m > 0 and self.tile_m > 0):
            raise ValueError("EdgeConfig: tile_m and spacing_m must be positive")
        if not (0 <= self.error_band_order <= 8):
            raise ValueError("EdgeConfig.error_band_order: must lie in 0..8")
        if not (self.error_longest_m > 4 * self.spacing_m):
            raise ValueError("EdgeConfig.error_longest_m: must exceed 4 grid steps")
        ratio = self.tile_m / self.spacing_m
        if abs(ratio - round(ratio)) > 1e-9:
            raise ValueError("EdgeConfig.tile_m: must be a whole number of spacing_m steps")

    @property
    def tile_points(self) -> int:
        return int(round(self.tile_m / self.spacing_m))

    @property
    def drift_points(self) -> int:
        return int(round(self.drift_half_width_m / self.spacing_m))


@kernel
def _interp_between(x, y, j, xg):
    """``np.interp``'s value at ``xg`` strictly between samples ``j`` and ``j + 1``."""
    slope = (y[j + 1] - y[j]) / (x[j + 1] - x[j])
    v = slope * (xg - x[j]) + y[j]
    if np.isnan(v):  # as np.interp: try from the other end, then the flat case
        v = slope * (xg - x[j + 1]) + y[j + 1]
        if np.isnan(v) and y[j] == y[j + 1]:
            v = y[j]
    return v


@kernel
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


#: The gridding's anti-alias low-pass, in chainage: flat (ripple ≤ 1e-4) up to ANTIALIAS_PASS_CPM
#: (0.33 m wavelength, past the 0.5 m the cloud uses), ≥ 80 dB down from ANTIALIAS_STOP_CPM, the 5 cm
#: grid's Nyquist, so nothing above it folds into the grid. A Kaiser-windowed sinc; its half-width
#: (0.36 m) is the lookahead the grid needs.
ANTIALIAS_PASS_CPM = 3.0
ANTIALIAS_STOP_CPM = 10.0
_AA_DB = 80.0
_AA_BETA = 0.1102 * (_AA_DB - 8.7)  # Kaiser's formula for the window's shape at this attenuation
_AA_CUTOFF_CPM = 0.5 * (ANTIALIAS_PASS_CPM + ANTIALIAS_STOP_CPM)
_AA_HALF_WIDTH_M = 0.5 * (_AA_DB - 8.0) / (2.285 * 2.0 * math.pi * (ANTIALIAS_STOP_CPM - ANTIALIAS_PASS_CPM))
#: The cut-off in time is at most this fraction of the sample rate (a fast vehicle's samples are
#: sparser than the grid: nothing to alias, the kernel then only interpolates).
_AA_MAX_CUTOFF_FRACTION = 0.4


def _kaiser_table(n: int = 4096) -> np.ndarray:
    """The Kaiser window w(u) = I₀(β√(1−u²)) / I₀(β) at u = 0, 1/n, …, 1 (and a 0 past the end):
    looked up with linear interpolation (error ~1e-7), far cheaper than I₀ per tap."""
    u = np.linspace(0.0, 1.0, n + 1)
    return np.concatenate([np.i0(_AA_BETA * np.sqrt(1.0 - u * u)) / np.i0(_AA_BETA), [0.0]])


_KAISER = _kaiser_table()


@kernel
def _grid_positions(x, number0, first, spacing, index, speed, dt):
    """At grid points ``first, first + 1, …``: the fractional sample number (samples' chainage
    ``x``, numbered ``number0, number0 + 1, …``) and the chainage speed (m/s) between the two
    samples around it. Counting in samples, not seconds, keeps the result exact whatever the
    chunking (whole sample number + fraction, so no rounding depends on where a chunk starts)."""
    n = x.size
    j = 0
    for k in range(index.size):
        xg = (first + k) * spacing
        while j < n - 2 and x[j + 1] <= xg:
            j += 1
        step = x[j + 1] - x[j]
        speed[k] = step / dt
        index[k] = float(number0 + j) + ((xg - x[j]) / step if step > 0 else 0.0)


@kernel
def _antialias(sap, srel, s0, index, speed, linear, out, valid, k0, dt, min_speed, final):
    """Low-pass and resample the AP at grid points ``k0, k0 + 1, …`` (their fractional sample
    numbers ``index``, chainage speeds ``speed``) from its samples ``sap`` (numbered ``s0, s0 + 1,
    …``, interval ``dt``); returns the first point not done (its window reaches past the samples so
    far; ``final``: none is left).

    The filter is a Kaiser-windowed sinc in chainage mapped to time by the point's speed (over the
    kernel's ±0.36 m the speed is constant to far better than the window's tolerance): cut-off
    ``_AA_CUTOFF_CPM × v`` Hz. A sum over the uniform samples is an exact band-limited
    resampling at the fractional sample (the kernel's band and the AP's, ≤ Nyquist, add to less
    than the sample rate), normalised so a constant passes exactly. Points whose window is not all
    reliable samples of this pass (warm-up, a stop, the pass's start) keep the linear value: a
    garbage AP must not leak into its neighbours. Points whose window the pass's end cuts become
    invalid (``valid``): a truncated kernel is not the filter, and their linear value carries the
    full-band noise (5× the anti-aliased points' second differences at 2 % noise), which the
    cloud's bridge likelihood would see as χ² ≈ 100 in the last row of every pass ending near a bridge.
    """
    n = sap.size
    fc_max = _AA_MAX_CUTOFF_FRACTION / dt
    m = _KAISER.size - 2
    for k in range(k0, index.size):
        v = speed[k]
        if not (v >= min_speed):  # a stop or a gap (speed 0): no filter defined
            out[k] = linear[k]
            continue
        fc = min(_AA_CUTOFF_CPM * v, fc_max) * dt  # cycles per sample
        half = _AA_HALF_WIDTH_M * _AA_CUTOFF_CPM / fc  # samples: the chainage kernel's half-width
        lo = int(math.ceil(index[k] - half)) - s0
        hi = int(math.floor(index[k] + half)) - s0 + 1
        if hi > n:
            if not final:
                return k
            out[k] = linear[k]
            valid[k] = False
            continue
        if lo < 0:  # the pass's first samples: kept (the rail's trailing bogie needs them from the start)
            out[k] = linear[k]
            continue
        ok = True
        for i in range(lo, hi):
            if not srel[i]:
                ok = False
                break
        if not ok:
            out[k] = linear[k]
            continue
        num, den = 0.0, 0.0
        for i in range(lo, hi):
            tau = index[k] - (s0 + i)
            u = abs(tau) / half * m
            iu = min(int(u), m)
            w = _KAISER[iu] + (u - iu) * (_KAISER[iu + 1] - _KAISER[iu])
            a = 2.0 * fc * tau
            if a != 0.0:
                w *= math.sin(math.pi * a) / (math.pi * a)
            num += w * sap[i]
            den += w
        out[k] = num / den
    return index.size


@kernel
def _fourth_differences_into(tail, z, out, at):
    """``np.diff(concatenate([tail, z]), 4, axis=0)`` (its operations, so its bits) written to
    ``out[at:]``; returns the rows written."""
    m = tail.shape[0] + z.shape[0]
    if m < 5:
        return 0
    c = z.shape[1]
    a = np.empty((m, c))
    a[: tail.shape[0]] = tail
    a[tail.shape[0] :] = z
    for order in range(4):
        for i in range(m - order - 1):
            for j in range(c):
                a[i, j] = a[i + 1, j] - a[i, j]
    out[at : at + m - 4] = a[: m - 4]
    return m - 4


#: The first capacity of a pass's grid points and fourth differences: a road pass of a few hundred
#: metres fits without growing (each growth is a chunk's kernel call run again).
_FIRST_ROWS = 4096


class _Rows:
    """Rows appended at the end and dropped from the start, in amortised O(rows): a buffer of
    doubling capacity, compacted when the dropped part would otherwise be copied past."""

    def __init__(self, width: int) -> None:
        self.data = np.zeros((_FIRST_ROWS, width))
        self.t = np.zeros(_FIRST_ROWS)
        self.lo = self.hi = 0

    def reserve(self, rows: int) -> None:
        """Room for ``rows`` more at the end."""
        n = self.hi - self.lo
        if self.hi + rows <= self.t.size:
            return
        if 2 * (n + rows) <= self.t.size:  # room once compacted: moved in place, nothing allocated
            data, t = self.data, self.t
        else:
            cap = 2 * (n + rows)
            data, t = np.zeros((cap, self.data.shape[1])), np.zeros(cap)
        data[:n], t[:n] = self.data[self.lo : self.hi], self.t[self.lo : self.hi]  # (numpy copies overlaps safely)
        self.data, self.t, self.lo, self.hi = data, t, 0, n


# AxleGrid's scalar state, one int64 array the kernels update in place.
_HAS_BASE, _BASE, _SIZE, _DONE, _N_SEEN, _S_LO, _S_HI, _S0, _HAS_LAST = range(9)


@kernel
def _grid_filter(st, values, smooth, valid, speed, index, sap, srel, dt, min_speed, final):
    """Anti-alias the points whose window the samples cover (all, if ``final``); drop the samples
    no pending point can reach: its window is at most ± the kernel's half-width at min_speed
    (slower points are not filtered)."""
    n = st[_SIZE]
    lo, hi = st[_S_LO], st[_S_HI]
    done = _antialias(sap[lo:hi], srel[lo:hi], st[_S0], index[:n], speed[:n], values[:n], smooth[:n], valid[:n],
                      st[_DONE], dt, min_speed, final)
    st[_DONE] = done
    horizon = index[done] if done < n else float(st[_N_SEEN])
    keep = int(math.floor(horizon - _AA_HALF_WIDTH_M / (min_speed * dt))) - 1 - st[_S0]
    if keep > 0:
        st[_S_LO] += keep
        st[_S0] += keep


@kernel
def _grid_add(x, ap, t, rel, spacing, min_index, st, last, values, times, valid, smooth, speed, index, sap, srel,
              antialias, dt, min_speed):
    """:meth:`AxleGrid.add` in one call. Returns ``(points, samples)``: (0, 0) once done, else the
    capacities the grid's point and sample arrays need first (nothing has changed then)."""
    n_new = x.size
    carried = st[_HAS_LAST] == 1
    m = n_new + (1 if carried else 0)
    xx, aa, tt, rr = np.empty(m), np.empty(m), np.empty(m), np.empty(m, dtype=np.bool_)
    k0 = 0
    if carried:  # the previous chunk's last sample: the interval up to this chunk's first
        xx[0], aa[0], tt[0], rr[0] = last[0], last[1], last[2], last[3] != 0.0
        k0 = 1
    for i in range(n_new):
        xx[k0 + i], aa[k0 + i], tt[k0 + i], rr[k0 + i] = x[i], ap[i], t[i], rel[i]
    # the grid points these samples pass, and the room they need
    first, stop, a = 0, 0, 0
    if m >= 2:
        filled_end = (st[_BASE] if st[_HAS_BASE] else 0) + st[_SIZE]
        if st[_HAS_BASE]:
            first = max(max(int(math.floor(xx[0] / spacing)) + 1, min_index), filled_end)
        else:
            first = max(int(math.ceil(xx[0] / spacing)), min_index)
            filled_end = first
        stop = int(math.floor(xx[m - 1] / spacing)) + 1
        if stop > first:
            a = st[_SIZE] + first - filled_end  # skipped grid points (e.g. a stop) stay invalid
    need_points = a + stop - first if stop > first else 0
    need_samples = st[_S_HI] + n_new if antialias else 0
    if need_samples > sap.size:
        lo, hi = st[_S_LO], st[_S_HI]
        if max(2 * (hi - lo + n_new), 1024) <= sap.size:  # room once compacted (AxleGrid._reserve_samples's rule)
            for i in range(hi - lo):
                sap[i], srel[i] = sap[lo + i], srel[lo + i]
            st[_S_LO], st[_S_HI] = 0, hi - lo
            need_samples = hi - lo + n_new
    if need_points > values.size or need_samples > sap.size:
        return need_points, need_samples
    if antialias:
        for i in range(n_new):
            sap[st[_S_HI] + i] = ap[i]
            srel[st[_S_HI] + i] = rel[i]
        st[_S_HI] += n_new
    if m > 0:
        last[0], last[1], last[2], last[3] = xx[m - 1], aa[m - 1], tt[m - 1], 1.0 if rr[m - 1] else 0.0
        st[_HAS_LAST] = 1
    if m >= 2 and stop > first:
        if not st[_HAS_BASE]:
            st[_HAS_BASE], st[_BASE] = 1, first
        b = a + stop - first
        st[_SIZE] = b
        _to_grid(xx, aa, tt, rr, first, spacing, values[a:b], times[a:b], valid[a:b])
        if antialias:  # xx[0] is sample n_seen (this chunk's first) or, carried over, the one before it
            _grid_positions(xx, st[_N_SEEN] - k0, first, spacing, index[a:b], speed[a:b], dt)
    st[_N_SEEN] += n_new
    if antialias:
        _grid_filter(st, values, smooth, valid, speed, index, sap, srel, dt, min_speed, False)
    else:
        st[_DONE] = st[_SIZE]
    return 0, 0


@kernel
def _feed_chunk(gnss, speed, z, ap, t0, rate, warmup, tail_n, d4_lo, d4_hi,
                chain, dt, k_pos, k_scale, min_speed, tail, d4, d4_t, with_d4, x_cg, t, rel, with_grid, offset, spacing,
                min_index, st, last, values, times, valid, smooth, gspeed, index, sap, srel, antialias, gdt, gmin_speed):
    """A chunk's per-pass work in one call (:meth:`PassProcessor.feed_ap`): chainage (the tracker's
    ``chain`` state, :func:`~edge.chainage.track_into`), sample times ``t``, reliability ``rel``
    (moving, past the hard warm-up), the channels' fourth differences appended to ``d4``/``d4_t``
    (``with_d4``), and, ``with_grid``, the pass's one axle gridded (:func:`_grid_add`, chainage
    ``x_cg + offset``, AP ``ap[:, 0]``). Each is the operations of the step it replaces, so the
    same bits. The chunk's own arguments come first, the pass's (:meth:`PassProcessor._feed_args`)
    after.

    Returns ``(points, samples, rows, written, tail_n, d4_lo, d4_hi, end)``: the first three
    nonzero when the grid's points or samples, or the differences' rows, need that capacity first
    (then nothing has changed but where the kept rows and samples lie: the state is committed only
    once everything fits); else the differences written, the rows of ``tail`` (the last ≤ 4
    samples of the channels) now held, where the differences now lie in ``d4``, and the grid's
    end (base + final points)."""
    n = gnss.size
    scale = track_into(chain, gnss, speed, dt, k_pos, k_scale, x_cg)
    for i in range(n):
        t[i] = t0 + i / rate  # (chunk.t's operations)
        rel[i] = speed[i] >= min_speed
    for i in range(min(warmup, n)):
        rel[i] = False
    m = tail_n + n
    if with_d4 and d4_hi + n > d4.shape[0]:
        if 2 * (d4_hi - d4_lo + n) > d4.shape[0]:
            return 0, 0, n, 0, tail_n, d4_lo, d4_hi, 0
        for r in range(d4_hi - d4_lo):  # room once compacted (_Rows.reserve's rule)
            d4[r] = d4[d4_lo + r]
            d4_t[r] = d4_t[d4_lo + r]
        d4_lo, d4_hi = 0, d4_hi - d4_lo
    if with_grid:
        x = np.empty(n)
        for i in range(n):
            x[i] = x_cg[i] + offset
        points, samples = _grid_add(x, ap[:, 0], t, rel, spacing, min_index, st, last, values, times, valid, smooth, gspeed,
                                    index, sap, srel, antialias, gdt, gmin_speed)
        if points != 0 or samples != 0:
            return points, samples, 0, 0, tail_n, d4_lo, d4_hi, 0
    written = 0
    if with_d4:
        written = _fourth_differences_into(tail[:tail_n], z, d4, d4_hi)
        for i in range(written):
            d4_t[d4_hi + i] = t[n - written + i]
        keep = min(4, m)
        new = np.empty((keep, tail.shape[1]))
        for r in range(keep):
            src = m - keep + r
            if src < tail_n:
                new[r] = tail[src]
            else:
                new[r] = z[src - tail_n]
        tail[:keep] = new
        tail_n = keep
    chain[0], chain[1], chain[2] = x_cg[n - 1], scale, 1.0
    return 0, 0, 0, written, tail_n, d4_lo, d4_hi + written, st[_BASE] + st[_DONE]


class AxleGrid:
    """The AP of one axle on the global grid, growing as the pass advances.

    The grid lives in arrays of doubling capacity, so appending a chunk's points costs amortised
    O(points) (appending by concatenation would copy the whole pass every chunk: O(n²) over a long
    pass). ``values``, ``valid`` and ``t`` are views of the part that is final. A chunk is added in
    one compiled call (:func:`_grid_add`): the per-chunk work is a few dozen samples, so the calls
    around it would otherwise cost more than the work.

    Without anti-alias a point is final once interpolated. With it (``min_speed`` given), a point
    is final once the samples reach past its filter window (~0.36 m ahead), or at ``flush()``; the
    grid keeps the samples the pending points still need (≤ the window at ``min_speed``).
    """

    def __init__(self, antialias: bool = False, dt: float = 0.0, min_speed: float = 0.5) -> None:
        self.antialias = antialias
        if antialias and not (dt > 0 and min_speed > 0):
            raise ValueError("AxleGrid: anti-alias needs the sample interval dt and min_speed > 0")
        self._dt, self._min_speed = dt, min_speed
        self._st = np.zeros(9, dtype=np.int64)
        self._last = np.zeros(4)  # the last sample (chainage, ap, t, reliable) for the next chunk's interval
        self._values = np.zeros(0)  # linear interpolation
        self._valid = np.zeros(0, dtype=bool)
        self._t = np.zeros(0)
        self._smooth = np.zeros(0)  # anti-aliased values
        self._speed = np.zeros(0)  # chainage speed at each point (m/s; 0 in gaps)
        self._index = np.zeros(0)  # fractional sample number of each point
        self._samples = np.zeros(0)  # the samples kept (from sample number _S0 on, at _S_LO … _S_HI)
        self._sreliable = np.zeros(0, dtype=bool)

    @property
    def base(self) -> int | None:
        """Grid index of the first point (None before any)."""
        return int(self._st[_BASE]) if self._st[_HAS_BASE] else None

    @property
    def size(self) -> int:
        """Points interpolated."""
        return int(self._st[_SIZE])

    @property
    def done(self) -> int:
        """Points final (== size without anti-alias)."""
        return int(self._st[_DONE])

    @property
    def _sap(self) -> np.ndarray:
        """The samples kept."""
        return self._samples[self._st[_S_LO] : self._st[_S_HI]]

    @property
    def values(self) -> np.ndarray:
        return self._smooth[: self.done] if self.antialias else self._values[: self.size]

    @property
    def linear(self) -> np.ndarray:
        """The final points' linearly interpolated values (no anti-alias)."""
        return self._values[: self.done]

    @property
    def valid(self) -> np.ndarray:
        return self._valid[: self.done]

    @property
    def t(self) -> np.ndarray:
        return self._t[: self.done]

    @property
    def end(self) -> int:
        """One past the last final grid index."""
        st = self._st
        return int((st[_BASE] if st[_HAS_BASE] else 0) + st[_DONE])

    def add(self, x: np.ndarray, ap: np.ndarray, t: np.ndarray, reliable: np.ndarray, spacing: float,
            min_index: int = 0) -> None:
        """Interpolate samples (chainage ``x`` increasing) onto the grid points they pass, from grid
        index ``min_index`` on (0: nothing before the route's start)."""
        while True:
            points, samples = _grid_add(x, ap, t, reliable, spacing, min_index, self._st, self._last, self._values,
                                        self._t, self._valid, self._smooth, self._speed, self._index, self._samples,
                                        self._sreliable, self.antialias, self._dt, self._min_speed)
            if points == 0 and samples == 0:
                return
            self._reserve(points)
            self._reserve_samples(samples)

    def flush(self) -> None:
        """The pass has ended: make every point final (those whose window the end cuts are invalid)."""
        if self.antialias:
            _grid_filter(self._st, self._values, self._smooth, self._valid, self._speed, self._index, self._samples,
                         self._sreliable, self._dt, self._min_speed, True)

    def _reserve(self, size: int) -> None:
        """Capacity for at least ``size`` points (new points are 0, invalid)."""
        if size > self._values.size:
            cap = max(size, 2 * self._values.size, _FIRST_ROWS)
            n = self.size
            for name in ("_values", "_valid", "_t", "_smooth", "_speed", "_index"):
                old = getattr(self, name)
                new = np.zeros(cap, dtype=old.dtype)
                new[:n] = old[:n]
                setattr(self, name, new)

    def _reserve_samples(self, size: int) -> None:
        """Room for the kept samples to reach ``size`` (counted from the buffer's start): the kept ones
        are moved to the start, into a larger buffer if need be."""
        if size > self._samples.size:
            st = self._st
            lo, hi = int(st[_S_LO]), int(st[_S_HI])
            cap = max(2 * (hi - lo + size - hi), 1024)
            if cap <= self._samples.size:  # room once compacted: moved in place, nothing allocated
                samples, reliable = self._samples, self._sreliable
            else:
                samples, reliable = np.zeros(cap), np.zeros(cap, dtype=bool)
            samples[: hi - lo], reliable[: hi - lo] = self._samples[lo:hi], self._sreliable[lo:hi]
            self._samples, self._sreliable = samples, reliable
            st[_S_LO], st[_S_HI] = 0, hi - lo


def ap_sigma(values: np.ndarray, valid: np.ndarray) -> float:
    """Robust noise scale of an AP stretch (m): MAD of its second differences, scaled for white noise."""
    v = values[valid]
    if v.size < 5:
        return 1e-3
    d2 = np.diff(v, 2)
    mad = median_abs_deviations(d2[:, None])[0] if np.isfinite(d2).all() else np.median(np.abs(d2 - np.median(d2)))
    return float(max(1.4826 * mad / math.sqrt(6.0), 1e-7))




class PassProcessor:
    """Streams one pass: ``feed(chunk)`` → segments ready so far; ``finish()`` → the rest + done marker."""

    def __init__(self, model: InverseModel, vehicle_id: str, pass_id: str, route_id: str,
                 calib_version: int, config: EdgeConfig = EdgeConfig(), model_name: str = ""):
        self.model = model
        self.model_name = model_name
        self.system = model.system
        self.vehicle_id, self.pass_id, self.route_id = vehicle_id, pass_id, route_id
        self.calib_version = calib_version
        self.min_index = 0  # the first grid index kept (tile 0 takes every index below P)
        if model_name in RAIL_MODELS:
            # The cloud re-runs a train run's dynamics over the whole record, which needs every wheel's AP
            # from the first sample: the warm-up is sent flagged (none dropped), and so is the AP of wheels
            # still behind chainage 0 when the log starts (a carriage's trailing bogie starts Lv + Lb behind
            # the body's centre), at negative grid indices of tile 0; the cloud fuses only chainage >= 0.
            config = dataclasses.replace(config, hard_warmup_s=0.0)
            behind = max(0.0, -float(np.min(self.system.offsets_m)))
            self.min_index = -int(math.ceil(behind / config.spacing_m)) - 1
        self.config = config
        self.inverse = InverseStream(model)
        self._hard_warmup = min(self.inverse.reliable_from, int(math.ceil(self.config.hard_warmup_s / model.constants.dt)))
        self.tracker = ChainageTracker(model.constants.dt)
        # (points slower than min_speed are not filtered; the floor bounds the samples a grid keeps)
        self.grids = [AxleGrid(config.antialias, model.constants.dt, max(config.min_speed_mps, 0.1))
                      for _ in range(self.system.n_contacts)]
        self.channel_names = [ch.name for ch in self.system.channels]
        # what passes fed as one bank share (edge.bank.feed_bank): the model, its channels and contacts
        self.bank_key = (model_name, len(self.system.channels), self.system.n_contacts)
        self.next_tile: int | None = None
        self.seq = 0
        self.n_samples = 0
        self.speeds: list[float] = []
        self._speed_mean = (0, 0.0)  # (chunks, their mean speed) last computed
        self.finished = False
        # Time from which the inverse has forgotten its initial state; earlier points are sent
        # down-weighted (see EdgeConfig.hard_warmup_s). -inf: no such points.
        self.settled_t = math.inf if model.n_warmup * model.constants.dt > self.config.hard_warmup_s else -math.inf
        # Fourth differences of the channels and their times, for each segment's noise levels (the
        # samples in the segment's own time span, so the result does not depend on chunking).
        # Rail vehicles keep the white sigma: their cloud re-runs the dynamics itself.
        self.error_model = self.config.error_model and model_name not in RAIL_MODELS
        self._z_tail = np.zeros((4, len(self.channel_names)))  # the channels' last samples (_tail_n of them)
        self._tail_n = 0
        self._d4 = _Rows(len(self.channel_names))
        self._trimmed_for: int | None = None  # the next tile the differences were last trimmed for
        self._windows: dict[int, tuple] = {}  # axle → (its last drift window, (trend, white sigma))
        self._buffers = (np.empty(0), np.empty(0), np.empty(0, dtype=np.bool_))  # a chunk's chainage, times, reliability
        # the first sample past the whole warm-up, if that is past the hard warm-up (settled_t)
        self._soft_from = self.inverse.reliable_from if self.inverse.reliable_from > self._hard_warmup else None
        self._offset0 = float(self.system.offsets_m[0])
        self._one = len(self.grids) == 1  # one axle: gridded in _feed_chunk
        self._args: tuple | None = None  # _feed_args()
        self._based = False  # every axle's grid has its first point
        self._base0 = 0  # (the first axle's base, once based)
        self._tile_points, self._drift_points = self.config.tile_points, self.config.drift_points
        self._noise: dict[tuple[float, float], np.ndarray | None] = {}  # a coming segment's (t0, t1) → _noise_sd
        self._ahead = 0  # the first tile whose noise levels are not measured ahead
        self._st0 = self.grids[0]._st  # (the first axle's state: a cheap test whether a tile may be complete)

    def feed(self, chunk: SensorChunk) -> list[ApSegment]:
        z = self.channels_of(chunk)
        return self.feed_ap(chunk, z, self.inverse.update(z) if chunk.n else None)

    def channels_of(self, chunk: SensorChunk) -> np.ndarray:
        """The chunk's channels as the inverse takes them: (samples, channels) in the model's order."""
        names, channels = self.channel_names, chunk.channels
        if len(names) == 1 and names[0] in channels:  # (a one-channel vehicle: a column, converted)
            return channels[names[0]].astype(np.float64)[:, None]
        missing = [n for n in names if n not in channels]
        if missing:
            raise ValueError(f"chunk lacks channel(s) {', '.join(missing)} for model {chunk.vehicle_model}")
        z = np.empty((chunk.n, len(names)))
        for j, name in enumerate(names):
            z[:, j] = channels[name]
        return z

    def feed_ap(self, chunk: SensorChunk, z: np.ndarray, ap: np.ndarray | None,
                mean_speed: float | None = None) -> list[ApSegment]:
        """:meth:`feed` once the inverse has run (``ap`` from ``self.inverse`` on ``z``; None if the
        chunk is empty): what :func:`edge.bank.feed_bank` calls after one inverse call for many passes
        (``mean_speed``, if given, is ``float(np.add.reduce(chunk.speed)) / chunk.n``, computed for
        many chunks at once)."""
        n = z.shape[0]  # (chunk.n)
        if not n:
            return self._emit(final=False)
        if self._buffers[0].size != n:
            self._buffers = (np.empty(n), np.empty(n), np.empty(n, dtype=np.bool_))
            self._args = None
        args = self._args or self._feed_args()
        d4, g = self._d4, self.grids[0]
        while True:
            points, samples, rows, written, tail_n, d4.lo, d4.hi, end = _feed_chunk(
                chunk.chainage, chunk.speed, z, ap, chunk.t0, chunk.sample_rate_hz, self._hard_warmup - self.n_samples,
                self._tail_n, d4.lo, d4.hi, *args)
            if not (points or samples or rows):
                break
            g._reserve(points)
            g._reserve_samples(samples)
            if rows:
                d4.reserve(n)
            args = self._feed_args()
        self._tail_n = tail_n
        if self._soft_from is not None and 0 <= self._soft_from - self.n_samples < n:
            # the first sample past the whole warm-up (t's operations)
            self.settled_t = chunk.t0 + (self._soft_from - self.n_samples) / chunk.sample_rate_hz
        if not self._one:
            x_cg, t, rel = self._buffers
            for i, grid in enumerate(self.grids):
                grid.add(x_cg + self.system.offsets_m[i], ap[:, i], t, rel, self.config.spacing_m, self.min_index)
        self.n_samples += n
        self.speeds.append(float(np.add.reduce(chunk.speed)) / n if mean_speed is None else mean_speed)
        if self._one and self._based:  # what _emit's first test concludes, without its calls when it has nothing to do
            P = self._tile_points
            if end < (self.next_tile + 1) * P + self._drift_points:
                if not self.error_model:
                    return []
                k = self.next_tile * P - self._base0
                trim = self._trimmed_for != self.next_tile and 0 <= k < end - self._base0
                if not trim and end < (self._ahead + 1) * P:
                    return []
        return self._emit(final=False)

    def _feed_args(self) -> tuple:
        """The pass's arguments of :func:`_feed_chunk` (its arrays are replaced when they grow)."""
        tracker, cfg, d4, g = self.tracker, self.config, self._d4, self.grids[0]
        self._args = (tracker.state, tracker.dt, tracker.k_pos, tracker.k_scale, cfg.min_speed_mps, self._z_tail,
                      d4.data, d4.t, self.error_model, *self._buffers, self._one, self._offset0, cfg.spacing_m,
                      self.min_index, g._st, g._last, g._values, g._t, g._valid, g._smooth, g._speed, g._index,
                      g._samples, g._sreliable, g.antialias, g._dt, g._min_speed)
        return self._args

    def finish(self) -> tuple[list[ApSegment], PassDone]:
        for grid in self.grids:
            grid.flush()
        segments = self._emit(final=True)
        self.finished = True
        done = PassDone(vehicle_id=self.vehicle_id, pass_id=self.pass_id, route_id=self.route_id,
                        calib_version=self.calib_version, n_segments=self.seq,
                        vehicle_model=self.model_name, sample_interval_s=self.model.constants.dt)
        return segments, done

    def _mean_speed(self) -> float:
        """The mean of the chunks' mean speeds so far (m/s; computed once per chunk count)."""
        if self._speed_mean[0] != len(self.speeds):
            self._speed_mean = (len(self.speeds), float(np.mean(self.speeds)) if self.speeds else 0.0)
        return self._speed_mean[1]

    def _trim_differences(self) -> None:
        """Drop the differences older than any segment still to come needs (once per next tile:
        the start times it depends on are final)."""
        if self._trimmed_for == self.next_tile:
            return
        P = self.config.tile_points
        starts = []
        for g in self.grids:
            if g.base is None:
                return
            k = self.next_tile * P - g.base
            if not 0 <= k < g.done:
                return
            starts.append(g.t[k])
        d4 = self._d4
        d4.lo += int(np.searchsorted(d4.t[d4.lo : d4.hi], min(starts)))
        self._trimmed_for = self.next_tile

    def _noise_sd(self, t0: float, t1: float) -> np.ndarray | None:
        """Each channel's noise sd from the fourth differences within times t0..t1, or None when
        there are too few or they say nothing."""
        d4 = self._d4
        lo, hi = np.searchsorted(d4.t[d4.lo : d4.hi], [t0, t1], side="left") + d4.lo
        if hi - lo < 64 or not t1 > t0:
            return None
        sd = noise_sd_from_d4(d4.data[lo:hi])
        if not (np.all(np.isfinite(sd)) and np.any(sd > 0)):
            return None
        return sd

    def _measure_ahead(self) -> None:
        """The noise levels of the tiles whose points are all final but which wait for the drift
        window, measured now (:meth:`_noise_sd` of the span each segment will have): what the
        segment needs of the channels is there already, and a short pass's end, which releases
        all its tiles at once, then has only its last tile's to measure."""
        P = self._tile_points
        tile = max(self._ahead, self.next_tile)
        while all(g._st[_BASE] + g._st[_DONE] >= (tile + 1) * P for g in self.grids):
            lo = tile * P if tile > 0 else min(self.min_index, 0)
            for g in self.grids:
                base = int(g._st[_BASE])
                a = max(lo, base)
                valid = g.valid[a - base : (tile + 1) * P - base]
                if valid.size > 1 and valid.any():
                    first, last = np.flatnonzero(valid)[[0, -1]]
                    if last > first:  # (a segment of one point has no error model)
                        key = (float(g.t[a - base + first]), float(g.t[a - base + last]))
                        if key not in self._noise:
                            self._noise[key] = self._noise_sd(*key)
            tile += 1
        self._ahead = tile

    def _error_model(self, axle: int, t0: float, t1: float, n_points: int, sigma_white: float) -> np.ndarray | None:
        """The wire error model of an axle's segment spanning times t0..t1 over n_points grid points
        (edge.error_model), or None when there is too little to measure the noise from."""
        key = (t0, t1)
        sd = self._noise.pop(key) if key in self._noise else self._noise_sd(t0, t1)
        if sd is None:
            return None
        speed = (n_points - 1) * self.config.spacing_m / (t1 - t0)  # the segment's own chainage speed
        cfg = self.config
        if sd.size == 1 and sd[0] > 0:  # one channel: the unit fit, scaled (see unit_error_band)
            sd1, band, white1, level = unit_error_band(self.model, speed, cfg.spacing_m, cfg.drift_points, axle,
                                                       cfg.error_band_order, cfg.error_longest_m)
            if sd[0] ** 2 * level <= sigma_white**2:
                sd_m = float(sd[0]) * sd1
                sd_m *= max(1.0, sigma_white / (sd_m * white1))  # as below
                return encode_error_model(sd_m, band, sigma_white)
        omega, S = unit_spectra(self.model, speed, self.config.spacing_m, self.config.drift_points)
        spectrum = np.tensordot(sd * sd, S[:, axle - 1], axes=1)
        if not np.any(spectrum > 0):
            return None
        sd_m, band = fit_error_band(omega, spectrum, self.config.spacing_m, self.config.error_band_order,
                                    self.config.error_longest_m, fill_ceiling=sigma_white**2)
        # Never below what the AP's own second differences show (see edge.error_model).
        sd_m *= max(1.0, sigma_white / white_equivalent(sd_m, band))
        return encode_error_model(sd_m, band, sigma_white)

    def _emit(self, final: bool) -> list[ApSegment]:
        if not final and self._based:  # most chunks release nothing: say so without the general case
            need = (self.next_tile + 1) * self._tile_points + self._drift_points
            for g in self.grids:
                st = g._st
                if st[_BASE] + st[_DONE] < need:  # (the general case's frontier condition)
                    if self.error_model:
                        if self._trimmed_for != self.next_tile:
                            self._trim_differences()
                        if self._st0[_BASE] + self._st0[_DONE] >= (self._ahead + 1) * self._tile_points:
                            self._measure_ahead()
                    return []
        grids = [g for g in self.grids if g.base is not None]
        if not grids:
            return []
        P = self.config.tile_points
        if self.next_tile is None:
            self.next_tile = max(min(g.base for g in grids) // P, 0)
        self._based = len(grids) == len(self.grids)
        self._base0 = grids[0].base
        # A tile is ready once every axle's grid extends past its end by the drift half-width.
        frontier = min(g.end for g in grids) if len(grids) == len(self.grids) else 0
        last_tile = max(g.end for g in grids) // P + 1 if final else (frontier - self.config.drift_points) // P
        out = []
        while self.next_tile < last_tile or (final and self.next_tile * P < max(g.end for g in grids)):
            out.extend(self._tile_segments(self.next_tile))
            self.next_tile += 1
        if self.error_model:
            self._trim_differences()
        return out

    def _window(self, axle: int, g: AxleGrid, wa: int, wb: int) -> tuple[np.ndarray | None, float]:
        """The drift trend over grid indices ``wa … wb - 1`` of an axle (None without drift control)
        and the white noise level there. Computed once per window: the points of a window are
        final, and the tiles of a pass shorter than the drift window share theirs (each tile's
        reaches from the pass's start to its end), which makes a short pass's end several tiles of
        work in one tick."""
        hit = self._windows.get(axle)
        if hit is not None and hit[0] == (wa, wb):
            return hit[1]
        H = self.config.drift_points
        vals, valid = g.values[wa - g.base : wb - g.base], g.valid[wa - g.base : wb - g.base]
        trend = drift_trend(vals, valid, H) if H > 0 else None
        # The noise level from the unfiltered AP: the anti-alias takes the noise above the
        # passband that second differences see, but the white-equivalent level in the band the
        # cloud uses is unchanged.
        raw = g.linear[wa - g.base : wb - g.base]
        out = trend, ap_sigma(raw - trend if H > 0 else raw, valid)
        self._windows[axle] = ((wa, wb), out)
        return out

    def _tile_segments(self, tile: int) -> list[ApSegment]:
        P, H = self.config.tile_points, self.config.drift_points
        out = []
        for axle, g in enumerate(self.grids, start=1):
            if g.base is None:
                continue
            lo, hi = (tile * P if tile > 0 else min(self.min_index, 0)), (tile + 1) * P
            a, b = max(lo, g.base), min(hi, g.end)
            if b <= a:
                continue
            # Drift control on a window around the tile (everything within ±H is available).
            wa, wb = max(g.base, a - H), min(g.end, b + H)
            valid = g.valid[wa - g.base : wb - g.base]
            seg_valid = valid[a - wa : b - wa]
            if not seg_valid.any():
                continue
            trend, sigma_white = self._window(axle, g, wa, wb)
            vals = g.values[wa - g.base : wb - g.base]
            seg_vals = vals[a - wa : b - wa] - trend[a - wa : b - wa] if H > 0 else vals[a - wa : b - wa]
            first, last = np.flatnonzero(seg_valid)[[0, -1]]
            seg_vals, seg_valid = seg_vals[first : last + 1], seg_valid[first : last + 1]
            sigma = np.full(seg_vals.size, sigma_white)
            flags = 0
            t_seg = g.t[a - g.base + first : a - g.base + last + 1]
            error_model = None
            if self.error_model and seg_vals.size > 1:
                error_model = self._error_model(axle, float(t_seg[0]), float(t_seg[-1]), seg_vals.size, sigma_white)
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
                calib_version=self.calib_version, speed_mps=self._mean_speed(),
                t_first=float(t_seg[0]), t_last=float(t_seg[-1]), seq=self.seq, flags=flags,
                error_model=error_model,
            ))
            self.seq += 1
        return out
