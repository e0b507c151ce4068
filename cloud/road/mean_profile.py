"""The plain profile estimator: precision-weighted mean of all passes per grid point.

Exact to add and retract (sums only), order-independent. Its band combines each pass's stated
error with the scatter between passes, so it stays honest when calibration errors dominate.
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
def _accumulate(sw, swy, swyy, count, lo, values_q, scale, offset, sigma_q, sigma_ref, sigma_scale, sign, is_pass):
    """Add ``sign`` times a segment's ``w = 1/sigma²``, ``w·y`` and ``w·y²`` from index ``lo`` (and move
    ``count`` by ``sign`` if ``is_pass``) in one pass, the segment given by its wire codes and decoded
    point by point as :attr:`ApSegment.values` and :attr:`ApSegment.sigma` decode them."""
    step = int(sign)
    for i in range(values_q.size):
        y = offset + scale * np.float64(values_q[i])
        s = sigma_ref * sigma_scale[-np.int64(sigma_q[i])]
        w = sign * (1.0 / (s * s))
        wy = w * y
        sw[lo + i] += w
        swy[lo + i] += wy
        swyy[lo + i] += wy * y
        if is_pass:
            count[lo + i] += step


class _RouteSums:
    def __init__(self, n: int):
        self.sw = np.zeros(n)
        self.swy = np.zeros(n)
        self.swyy = np.zeros(n)
        self.count = np.zeros(n, dtype=np.int64)  # segments of axle 1 = passes


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
        _accumulate(sums.sw, sums.swy, sums.swyy, sums.count, lo, seg.values_q[:n], seg.scale_m, seg.offset_m,
                    seg.sigma_q[:n], seg.sigma_ref_m, SIGMA_SCALE, sign, seg.axle == 1)

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
                has = s.sw > 0
                mean = np.where(has, s.swy / np.where(has, s.sw, 1.0), np.nan)
                var_w = np.where(has, s.swyy / np.where(has, s.sw, 1.0) - mean**2, np.nan)
                n = np.maximum(s.count, 1)
                # Standard error: the larger of the stated precision and the observed scatter.
                se = np.sqrt(np.maximum(1.0 / np.where(has, s.sw, np.inf), np.maximum(var_w, 0.0) / n))
            x = np.arange(s.sw.size) * self.spacing_m
            out[rid] = ProfileSnapshot(rid, x, mean, mean - 1.96 * se, mean + 1.96 * se, s.count.copy())
        return out
