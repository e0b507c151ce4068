"""The plain profile estimator: precision-weighted mean of all passes per grid point.

Sums only, so adding and retracting are cheap and order-independent up to rounding; whether a
point has data is an integer count, exact whatever rounding the sums went through. Its band combines
each pass's stated error with the scatter between passes, so it stays honest when calibration errors
dominate.
Roads are estimated by the Bayesian GMRF (:mod:`.gmrf_profile`); this is the data-only
consensus the vehicle step compares against (no prior smoothing to bias the shortest waves), and
its snapshot type is the one every profile estimator returns.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from shared.jit import kernel
from shared.schema import SIGMA_SCALE, ApSegment


@dataclasses.dataclass(frozen=True)
class ProfileSnapshot:
    route_id: str
    chainage_m: np.ndarray
    elevation_m: np.ndarray  # NaN where no pass has been
    lo95_m: np.ndarray
    hi95_m: np.ndarray
    n_passes: np.ndarray  # int


@kernel
def _accumulate(sw, swy, swyy, count, held, lo, values_q, scale, offset, sigma_q, sigma_ref, sigma_scale, sign,
                is_pass):
    """Add ``sign`` times a segment's ``w = 1/sigma²``, ``w·y`` and ``w·y²`` from index ``lo`` (and move
    ``count`` by ``sign`` if ``is_pass``, ``held`` always) in one pass, the segment given by its wire
    codes and decoded point by point as :attr:`ApSegment.values` and :attr:`ApSegment.sigma` decode
    them. A point no segment holds any more gets its sums back at exactly zero: retraction leaves
    rounding there, and a ratio of two rounding residues is not a profile (see ``snapshot``)."""
    step = int(sign)
    for i in range(values_q.size):
        y = offset + scale * np.float64(values_q[i])
        s = sigma_ref * sigma_scale[-np.int64(sigma_q[i])]
        w = sign * (1.0 / (s * s))
        wy = w * y
        sw[lo + i] += w
        swy[lo + i] += wy
        swyy[lo + i] += wy * y
        held[lo + i] += step
        if held[lo + i] == 0:
            sw[lo + i] = 0.0
            swy[lo + i] = 0.0
            swyy[lo + i] = 0.0
        if is_pass:
            count[lo + i] += step


class _RouteSums:
    def __init__(self, n: int):
        self.sw = np.zeros(n)
        self.swy = np.zeros(n)
        self.swyy = np.zeros(n)
        self.count = np.zeros(n, dtype=np.int64)  # segments of axle 1 = passes
        self.held = np.zeros(n, dtype=np.int64)  # segments of any axle


class MeanProfile:
    """Per-route sums on a fixed grid of ``spacing_m`` from chainage 0 to the route length."""

    def __init__(self, routes: dict[str, float], spacing_m: float = 0.05):
        self.spacing_m = spacing_m
        self.routes = {rid: _RouteSums(int(round(length / spacing_m)) + 1) for rid, length in routes.items()}

    def _slice(self, seg: ApSegment):
        sums = self.routes[seg.route_id]
        lo, hi = seg.start_index, min(seg.end_index, sums.sw.size)
        return sums, lo, hi

    def _apply(self, seg: ApSegment, sign: float) -> None:
        sums, lo, hi = self._slice(seg)
        if hi <= lo:
            return
        n = hi - lo
        _accumulate(sums.sw, sums.swy, sums.swyy, sums.count, sums.held, lo, seg.values_q[:n], seg.scale_m,
                    seg.offset_m, seg.sigma_q[:n], seg.sigma_ref_m, SIGMA_SCALE, sign, seg.axle == 1)

    def accepts(self, seg: ApSegment) -> bool:
        return seg.route_id in self.routes and abs(seg.spacing_m - self.spacing_m) < 1e-12

    def update(self, seg: ApSegment) -> None:
        self._apply(seg, +1.0)

    def retract(self, seg: ApSegment) -> None:
        self._apply(seg, -1.0)

    def snapshot(self, route_id: str | None = None) -> dict[str, ProfileSnapshot]:
        out = {}
        for rid, s in self.routes.items():
            if route_id is not None and rid != route_id:
                continue
            with np.errstate(invalid="ignore", divide="ignore"):
                # Whether a point has data is a count, not the sign of a sum: a leave-one-out view
                # (the pass retracted) would otherwise show a rounding residue where only that pass
                # was, as a value, present or not by the residue's sign.
                has = (s.held > 0) & (s.sw > 0)
                mean = np.where(has, s.swy / np.where(has, s.sw, 1.0), np.nan)
                var_w = np.where(has, s.swyy / np.where(has, s.sw, 1.0) - mean**2, np.nan)
                n = np.maximum(s.count, 1)
                # Standard error: the larger of the stated precision and the observed scatter.
                se = np.sqrt(np.maximum(1.0 / np.where(has, s.sw, np.inf), np.maximum(var_w, 0.0) / n))
            x = np.arange(s.sw.size) * self.spacing_m
            out[rid] = ProfileSnapshot(rid, x, mean, mean - 1.96 * se, mean + 1.96 * se, s.count.copy())
        return out
