"""GNSS error: align each pass in chainage against the consensus before it is fused.

A pass's chainage carries a constant bias (GNSS) and a stretch (the odometry scale error the edge's
fusion has not yet removed): x_reported = x_ref + b + (1 + ε)(x_true − x_ref). The pass's AP is
compared with the consensus of the *other* passes, band-passed:

1. coarse: every ``WINDOW_M`` window of the pass finds its shift against the consensus by FFT
   cross-correlation over the whole search range (normalised per lag, parabolic peak); a robust
   straight line through the windows' shifts (Theil–Sen, then least squares on the inliers) gives
   (b, ε) — a window on a featureless or disagreeing stretch is an outlier, not a bias;
2. fine: the pass re-gridded with (b, ε), each window's small residual shift in a short-wave band
   (``FINE_BAND_M``, where a wrong calibration hardly moves the AP's phase), the line refitted;
3. last: (b, ε) by least squares over all the fine stage's inlier windows at once (Gauss–Newton on
   the spline-interpolated pass) in a band above wheel hop (``REFINE_BAND_M``), where a wrong
   calibration changes the AP's gain but hardly its phase — free of the windows' sub-sample peak
   bias and of the vehicle's phase error.

The cost is a few dozen small FFTs per pass (~10 ms of one core)
instead of a correlation per trial stretch. The fleet's biases and stretches are independent across
passes with zero mean, so the daemon centres the estimated maps across a route's passes
(:func:`centred`): the consensus frame is the fleet's mean frame, which converges to the true one
as passes accumulate, not the first pass's.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
from scipy.interpolate import make_interp_spline
from scipy.signal import butter, fftconvolve, sosfiltfilt

from shared.schema import ApSegment

BAND_M = (1.0, 30.0)  # coarse: wide, so a window's correlation peak is unique over the search range
# Fine: short waves only. Between body bounce and wheel hop the AP barely depends on the vehicle's
# parameters, while near body bounce (~10–20 m at road speeds) a calibration error turns into a
# phase error, i.e. a false shift of several cm (5 cm sd with class-mean parameters in
# 1–30 m, 3 cm in 0.5–5 m, 1.5 cm with the true parameters in either).
FINE_BAND_M = (0.5, 5.0)
# Last, least squares in a band above every car's wheel hop (0.34–0.5 m is 40–60 Hz at 20 m/s, past
# ~10–15 Hz): there the inverse under wrong parameters errs in gain, hardly in phase (its transfer
# tends to the real k/m ratio), so a pass is placed where its road is, not where its vehicle's phase
# error puts it (with class-mean parameters, against the true profile: 0.3 cm sd per pass here,
# 2.2 cm in 0.5–5 m; a calibration learning from 3 cm misplaced passes is biased by tens of %). The
# edge's alias-free gridding keeps wavelengths down to 0.33 m. Local only: the fine stage must be
# within a quarter wave (~8 cm).
REFINE_BAND_M = (0.34, 0.5)
WINDOW_M = 30.0  # long enough to hold the band's longest wave, short enough that ε·W ≪ the shortest
FINE_LAG_M = 0.6  # residual shift searched after the coarse line (m)
MIN_POINTS = 400
DAMP_BELOW = 3.0  # a sweep's step is damped against fewer other passes than this (`damped`)
FULL_SHARE = 0.8  # a pass spanning this share of its route's covered stretch is a full pass (centring)


@dataclasses.dataclass(frozen=True)
class Alignment:
    shift_m: float  # b: reported − true chainage at x_ref
    stretch: float  # ε: relative scale error of the reported chainage
    x_ref_m: float
    score: float  # correlation at the optimum (0..1)

    def true_to_reported(self, x_true: np.ndarray) -> np.ndarray:
        return self.x_ref_m + self.shift_m + (1.0 + self.stretch) * (x_true - self.x_ref_m)

    def reported_to_true(self, x_rep: np.ndarray) -> np.ndarray:
        return self.x_ref_m + (x_rep - self.x_ref_m - self.shift_m) / (1.0 + self.stretch)


def damped(old: Alignment | None, new: Alignment, cons_x: np.ndarray, cons_n: np.ndarray, lo_m: float,
           hi_m: float) -> Alignment:
    """The step of a sweep towards ``new``, the pass's map (the pass at ``lo_m``–``hi_m``) against a
    consensus of ``cons_n`` other passes per point ``cons_x``, from its map of the last sweep ``old``.

    Every pass of a sweep is placed against the others where they were, and they move too. Against
    ``n`` others a full step overshoots by ``(n + 1)/n``: with one other pass, two passes swap their
    offset every sweep and never meet; with two, the error halves and flips sign per sweep; partial
    passes, each overlapping other subsets, pass such swings to and fro. The step ``n/(n + 1)``
    (``n`` the others' mean count over the pass) lands where passes that overlap in full agree in
    one sweep. It is taken from a pass's second sweep on (the first, from nothing, is the full
    estimate: a series then goes on while passes still move), for partial passes and against fewer
    than ``DAMP_BELOW`` others. Full passes against more take the full step: its error shrinks by
    ``1/n`` a sweep, and each sweep's map stays the pass's own estimate against the latest consensus,
    not partly an earlier one's against a consensus still smeared.
    """
    inside = (cons_x >= lo_m) & (cons_x < hi_m)
    n_in = cons_n[inside]
    if old is None or not (n_in > 0).any():
        return new
    n = float(np.mean(n_in[n_in > 0]))
    covered = cons_x[cons_n > 0]
    full = (np.mean(n_in > 0) >= FULL_SHARE and hi_m - lo_m >= FULL_SHARE * float(np.ptp(covered)))
    if full and n >= DAMP_BELOW:
        return new
    k = n / (n + 1.0)
    a_old, e_old = old.shift_m - old.stretch * old.x_ref_m, old.stretch
    a_new, e_new = new.shift_m - new.stretch * new.x_ref_m, new.stretch
    a, e = a_old + k * (a_new - a_old), e_old + k * (e_new - e_old)
    return Alignment(float(a + e * new.x_ref_m), float(e), new.x_ref_m, new.score)


def centred(alignments: list[Alignment], extents: list[tuple[float, float]] | None = None) -> list[Alignment]:
    """The maps re-expressed so that their mean is the identity: the consensus frame becomes the
    passes' mean frame.

    Each alignment maps consensus → reported chainage, ``T_p(y) = α_p + (1 + ε_p)·y`` with
    ``α_p = b_p − ε_p·x_ref,p``. The fleet's mean frame ``F`` (a feature's mean reported position)
    is the frame whose error is the average of the passes' independent errors; composing every map
    with ``F⁻¹`` removes it. Subtracting the mean shift at each pass's own ``x_ref`` instead would
    leave ``cov(ε_p, x_ref,p)`` in the frame when the passes start at different places.

    ``extents`` (each pass's consensus-frame start and end, m): ``F`` is the straight line closest
    to the maps *where each pass is* — every metre of road weighed once per pass covering it. A
    pass's map says nothing beyond its own stretch: extrapolated to a common origin, a short pass's
    ill-determined stretch far from chainage 0 (0.5 % of 400 m is 2 m) would move every pass's
    frame by metres. Without ``extents``, or when every pass spans most (``FULL_SHARE``) of the
    stretch the passes cover together, ``F = mean_p T_p``: there the line through the maps would
    gain a spurious tilt from the passes' extents moving with their own shifts. Passes in stretches
    of the route that no pass links (no overlap) are centred group by group.
    """
    if not alignments:
        return []
    groups = _overlapping(extents) if extents else [list(range(len(alignments)))]
    if len(groups) > 1:
        out: list[Alignment | None] = [None] * len(alignments)
        for g in groups:
            # Passes that share no road with another aligned pass share no frame with it either. A
            # lone one was placed against passes that did not align (they stay where they report):
            # its map is its place in their frame, and centring it alone would undo it.
            done = centred([alignments[i] for i in g], [extents[i] for i in g]) if len(g) > 1 else [alignments[g[0]]]
            for i, al in zip(g, done):
                out[i] = al
        return out
    alpha = np.array([a.shift_m - a.stretch * a.x_ref_m for a in alignments])
    beta = np.array([1.0 + a.stretch for a in alignments])
    a0, b0 = float(np.mean(alpha)), float(np.mean(beta))
    union = (min(lo for lo, _ in extents), max(hi for _, hi in extents)) if extents else (0.0, 0.0)
    partial = extents is not None and any(hi - lo < FULL_SHARE * (union[1] - union[0]) for lo, hi in extents)
    if partial:
        y = np.concatenate([np.linspace(lo, hi, 9) for lo, hi in extents])
        z = np.concatenate([al + be * np.linspace(lo, hi, 9) for (lo, hi), al, be in zip(extents, alpha, beta)])
        w = np.concatenate([np.full(9, max(hi - lo, 1e-3)) for lo, hi in extents])
        if np.ptp(y) > 1.0:  # passes spread along the route: the weighted line through their maps
            yc = float(np.average(y, weights=w))
            b0 = float(np.sum(w * (y - yc) * z) / np.sum(w * (y - yc) ** 2))
            a0 = float(np.average(z, weights=w)) - b0 * yc
    out = []
    for a, al, be in zip(alignments, alpha, beta):
        # T_p ∘ F⁻¹ with F(y) = a0 + b0·y: y ↦ α_p + β_p·(y − a0)/b0.
        al_c, be_c = al - be * a0 / b0, be / b0
        eps = be_c - 1.0
        out.append(Alignment(float(al_c + eps * a.x_ref_m), float(eps), a.x_ref_m, a.score))
    return out


def _overlapping(extents: list[tuple[float, float]]) -> list[list[int]]:
    """The indices of ``extents`` grouped into chains of stretches that overlap (in start order)."""
    order = sorted(range(len(extents)), key=lambda i: extents[i][0])
    groups: list[list[int]] = []
    end = -np.inf
    for i in order:
        lo, hi = extents[i]
        if groups and lo < end:
            groups[-1].append(i)
            end = max(end, hi)
        else:
            groups.append([i])
            end = hi
    return [sorted(g) for g in groups]


@functools.lru_cache(maxsize=16)
def _sos(spacing: float, band_m: tuple[float, float]) -> np.ndarray:
    return butter(2, [1.0 / band_m[1], 1.0 / band_m[0]], btype="band", fs=1.0 / spacing, output="sos")


def _band(x: np.ndarray, spacing: float, band_m: tuple[float, float]) -> np.ndarray:
    return sosfiltfilt(_sos(round(spacing, 12), tuple(band_m)), x)


def _filled(y: np.ndarray) -> np.ndarray:
    """``y`` with interior NaN gaps bridged linearly (the band-pass needs a gap-free record)."""
    ok = np.isfinite(y)
    if ok.all():
        return y
    i = np.arange(y.size)
    return np.interp(i, i[ok], y[ok])


def _window_shifts(a: np.ndarray, c: np.ndarray, starts: np.ndarray, n_win: int, lag: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """For each window ``a[s:s+n_win]``: the offset (samples, fractional) at which it best matches ``c``
    (``c[s+k : s+k+n_win]``, |k| ≤ lag; ``c`` is indexed like ``a``) and its normalised correlation."""
    k_out = np.full(starts.size, np.nan)
    r_out = np.full(starts.size, np.nan)
    for j, s in enumerate(starts):
        lo, hi = max(s - lag, 0), min(s + n_win + lag, c.size)
        if hi - lo < n_win + 2:
            continue
        w = a[s : s + n_win]
        cw = c[lo:hi]
        num = fftconvolve(cw, w[::-1], mode="valid")  # num[i] = Σ w · cw[i : i + n_win]
        e = np.concatenate([[0.0], np.cumsum(cw * cw)])
        ww = np.sum(w * w)
        ce = e[n_win:] - e[:-n_win]
        # Where the consensus is (almost) nil — past its ends, zero-padded — the running sums'
        # rounding leaves a ratio of two tiny numbers, not a correlation: no match there.
        r = np.where(ce > 1e-6 * ww, num / (np.sqrt(ww * np.maximum(ce, 0.0)) + 1e-300), 0.0)
        i = int(np.argmax(r))
        frac = 0.0
        if 0 < i < r.size - 1:
            y0, y1, y2 = r[i - 1], r[i], r[i + 1]
            d = y0 - 2 * y1 + y2
            frac = 0.5 * (y0 - y2) / d if d < 0 else 0.0
        k_out[j] = lo + i + frac - s
        r_out[j] = r[i]
    return k_out, r_out


def _line(x: np.ndarray, y: np.ndarray, w: np.ndarray, robust: bool, floor_m: float = 0.25
          ) -> tuple[float, float, np.ndarray]:
    """(intercept at x=0, slope, inlier mask) of y ≈ a + b·x; Theil–Sen then weighted LS if ``robust``."""
    keep = np.ones(x.size, bool)
    if robust and x.size >= 3:
        i, j = np.triu_indices(x.size, 1)
        dx = x[j] - x[i]
        ok = np.abs(dx) > 1e-9
        slope = float(np.median((y[j] - y[i])[ok] / dx[ok])) if ok.any() else 0.0
        icpt = float(np.median(y - slope * x))
        resid = np.abs(y - icpt - slope * x)
        keep = resid < max(floor_m, 3.0 * 1.4826 * float(np.median(resid)))
    if keep.sum() >= 2 and np.ptp(x[keep]) > 0:
        A = np.stack([np.ones(keep.sum()), x[keep]], axis=1) * w[keep, None]
        sol, *_ = np.linalg.lstsq(A, y[keep] * w[keep], rcond=None)
        return float(sol[0]), float(sol[1]), keep
    return float(np.median(y[keep])), 0.0, keep


def estimate_alignment(x_rep: np.ndarray, ap: np.ndarray, x_cons: np.ndarray, cons: np.ndarray,
                       max_shift_m: float = 10.0, max_stretch: float = 0.06, stretch_step: float | None = None,
                       band_m: tuple[float, float] = BAND_M, fine_band_m: tuple[float, float] = FINE_BAND_M,
                       window_m: float = WINDOW_M, refine_band_m: tuple[float, float] | None = None
                       ) -> Alignment | None:
    """(b, ε) of a pass's AP (on its reported grid ``x_rep``) against the consensus ``cons`` (on the
    regular grid ``x_cons``, same spacing). None if they overlap too little or nothing correlates.
    ``refine_band_m``: the band of the final least-squares fit (default ``REFINE_BAND_M``).
    ``stretch_step`` is accepted for compatibility and ignored (ε is not searched on a grid).
    With fewer than three usable windows the pass is placed by a shift alone (ε = 0)."""
    ok = np.isfinite(ap)
    okc = np.isfinite(cons)
    if ok.sum() < MIN_POINTS or okc.sum() < MIN_POINTS:
        return None
    h = float(x_cons[1] - x_cons[0])
    f, l = np.flatnonzero(ok)[[0, -1]]
    x_rep, ap = np.asarray(x_rep[f : l + 1], float), _filled(ap[f : l + 1])
    x_ref = float(x_rep[0])
    fc, lc = np.flatnonzero(okc)[[0, -1]]
    xc, c = np.asarray(x_cons[fc : lc + 1], float), _filled(cons[fc : lc + 1])
    c_band = _band(c, h, band_m)
    a_band = _band(ap, h, band_m)
    n_win = int(round(window_m / h))
    length = x_rep[-1] - x_rep[0]
    if length < window_m:
        n_win = x_rep.size
    # Coarse: pass windows against the consensus at the pass's *reported* positions.
    reach = max_shift_m + max_stretch * length
    i0 = int(round((x_rep[0] - xc[0]) / h))  # consensus index of the pass's first point
    pad = int(np.ceil(reach / h)) + 1
    cc = np.zeros(x_rep.size + 2 * pad)  # consensus on the pass's index frame, padded by the reach
    src = np.arange(i0 - pad, i0 + x_rep.size + pad)
    inside = (src >= 0) & (src < c_band.size)
    cc[inside] = c_band[src[inside]]
    starts = np.arange(0, x_rep.size - n_win + 1, max(n_win // 2, 1))
    k, r = _window_shifts(np.concatenate([np.zeros(pad), a_band, np.zeros(pad)]), cc, starts + pad, n_win, pad - 1)
    good = np.isfinite(k) & (r > 0.3)
    if good.sum() < 2 and not (good.sum() == 1 and starts.size == 1):
        return None
    # Window centre at reported x_r matches the consensus at x_t = x_r + k·h: shift d = x_r − x_t.
    x_r = x_rep[0] + (starts + n_win / 2) * h
    d = -k * h
    x_t = x_r - d
    # Two windows cannot out-vote a false peak, and they fix a line through it: when a short pass's
    # two windows (or a pass this little covered by the others) disagree beyond any plausible
    # stretch, it is placed by a shift alone — its best-correlated window's — its stretch (a few per
    # mille of tens of metres) left as reported.
    if good.sum() >= 3:
        # A few windows cannot out-vote a false peak in a robust line either (with three or four,
        # half the pairwise slopes involve it). Windows whose shifts differ by more than any
        # plausible stretch cannot both be right: the line goes through the largest set that agrees
        # with one window, the best-correlated such window's.
        idx = np.flatnonzero(good)
        dx, dd = np.abs(x_t[idx, None] - x_t[None, idx]), np.abs(d[idx, None] - d[None, idx])
        agree = dd <= FINE_LAG_M + max_stretch * dx
        support = agree.sum(axis=1) + r[idx] / 2.0  # ties go to the better correlated window
        good = np.zeros_like(good)
        good[idx[agree[int(np.argmax(support))]]] = True
    shift_only = good.sum() < 2
    if good.sum() == 2:  # a line through two windows only if they agree on a plausible stretch
        (i1, i2) = np.flatnonzero(good)
        shift_only = abs(d[i2] - d[i1]) > FINE_LAG_M + 0.01 * abs(x_t[i2] - x_t[i1])
    if shift_only:
        best = int(np.argmax(np.where(good, r, -np.inf)))
        b, eps = float(d[best]), 0.0
    else:
        b, eps, _ = _line(x_t[good] - x_ref, d[good], r[good], robust=True)
    if abs(eps) > 1.5 * max_stretch or abs(b) > max_shift_m + 2.0:
        return None
    # Fine: re-grid the pass with (b, ε) and refine on small residual shifts.
    c_coarse, a_coarse = c_band, a_band
    if fine_band_m != band_m:
        c_band, a_band = _band(c, h, fine_band_m), _band(ap, h, fine_band_m)
    lag = int(np.ceil(FINE_LAG_M / h))
    score = 0.0
    for _ in range(2):
        unconfirmed = 0.0  # a stretch dropped this step: the pass is re-gridded without it once more
        al = Alignment(b, eps, x_ref, 0.0)
        lo, hi = np.ceil(al.reported_to_true(x_rep[0]) / h), np.floor(al.reported_to_true(x_rep[-1]) / h)
        xg = np.arange(max(lo, np.ceil(xc[0] / h)), min(hi, np.floor(xc[-1] / h)) + 1) * h
        if xg.size < max(MIN_POINTS, n_win):
            return None
        aw = np.interp(al.true_to_reported(xg), x_rep, a_band)
        cw = np.interp(xg, xc, c_band)
        st = np.arange(0, xg.size - n_win + 1, max(n_win // 2, 1))
        kk, rr = _window_shifts(aw, cw, st, n_win, lag)
        g = np.isfinite(kk) & (rr > 0.3)
        if g.sum() < 1:
            return None
        xm = xg[0] + (st + n_win / 2) * h
        # A feature the warped pass shows at true x sits at x + kk·h in the consensus: the pass's
        # true chainage there is larger by kk·h, i.e. its shift smaller by (1+ε)·kk·h.
        yk = -(1.0 + eps) * kk[g] * h
        db, de, inl = _line(xm[g] - x_ref, yk, rr[g], robust=g.sum() >= 3, floor_m=0.02)
        if not shift_only and g.sum() < 2:
            # One window confirms the coarse line: a stretch needs two places where the pass matches
            # the consensus, and the coarse line's other windows may be false peaks (windows the
            # consensus only partly covers, against its zero padding). A stretch the overlap cannot
            # confirm is not applied: the pass is placed by a shift alone, its line's shift at the
            # confirming window, its stretch left as reported.
            shift_only, unconfirmed = True, eps
            b, eps = b + eps * (xm[g][0] - x_ref), 0.0
        if shift_only:  # the best window's residual shift, the others' left out
            best = int(np.argmax(rr[g]))
            db, de, inl = float(yk[best]), 0.0, np.arange(g.sum()) == best
        # The inlier windows' stretches of true chainage: where the pass and the consensus agree.
        inlier_m = [(xg[0] + s * h, xg[0] + (s + n_win - 1) * h) for s in st[g][inl]]
        if g.sum() < 3 or shift_only:
            de = 0.0
        b, eps = b + db, eps + de
        # The score is the coarse band's correlation: against a consensus still smeared by the
        # others' unknown shifts the short waves correlate poorly even when the pass is placed right.
        aw_c = np.interp(al.true_to_reported(xg), x_rep, a_coarse)
        cw_c = np.interp(xg, xc, c_coarse)
        score = float(np.sum(aw_c * cw_c) / (np.sqrt(np.sum(aw_c * aw_c) * np.sum(cw_c * cw_c)) + 1e-30))
        if abs(db) < 1e-3 and abs(de) < 1e-5 and unconfirmed == 0.0:
            break
    if abs(eps) > max_stretch * 1.5 or abs(b) > max_shift_m + 2.0:
        return None
    # Last: least squares over every inlier window at once, in REFINE_BAND_M. Each window's peak is
    # a parabola through three lags of a 5 cm grid, biased towards whole samples; the shift and
    # stretch that best map the whole pass onto the consensus are not.
    refine = refine_band_m or REFINE_BAND_M
    if refine != fine_band_m:
        c_band, a_band = _band(c, h, refine), _band(ap, h, refine)
    b, eps = _least_squares(x_rep, a_band, xc, c_band, Alignment(b, eps, x_ref, score), inlier_m,
                            max_move_m=refine[0] / 4.0, stretch=not shift_only)
    if abs(eps) > max_stretch * 1.5 or abs(b) > max_shift_m + 2.0:
        return None
    # A move must earn its place: a pass already in the consensus frame that differs from the others
    # (another lane of the surface, a patch) can still find a false optimum, decimetres away, whose
    # waves match worse than where the pass says it is, long and short. Keep the reported chainage
    # then. (Either band alone is not enough: the short waves carry the vehicle's phase error, which
    # can favour a reported chainage a decimetre off against a consensus still being placed.)
    found = Alignment(shift_m=float(b), stretch=float(eps), x_ref_m=x_ref, score=score)
    stay = Alignment(0.0, 0.0, x_ref, score)
    for band in (band_m, fine_band_m):
        c_b, a_b = _band(c, h, band), _band(ap, h, band)
        if _correlation(x_rep, a_b, xc, c_b, stay) < _correlation(x_rep, a_b, xc, c_b, found):
            return found
    return stay


def _correlation(x_rep: np.ndarray, a: np.ndarray, xc: np.ndarray, c: np.ndarray, al: Alignment) -> float:
    """Normalised correlation of the pass ``a`` (on its reported grid) placed by ``al`` with the
    consensus ``c`` (on the regular grid ``xc``), over the consensus points the placed pass covers."""
    h = float(xc[1] - xc[0])
    lo = max(np.ceil(al.reported_to_true(x_rep[0]) / h), np.ceil(xc[0] / h))
    hi = min(np.floor(al.reported_to_true(x_rep[-1]) / h), np.floor(xc[-1] / h))
    xg = np.arange(lo, hi + 1) * h
    if xg.size < MIN_POINTS:
        return -np.inf
    av = np.interp(al.true_to_reported(xg), x_rep, a)
    cv = c[np.clip(np.rint((xg - xc[0]) / h).astype(np.int64), 0, c.size - 1)]
    return float(np.dot(av, cv) / (np.sqrt(np.dot(av, av) * np.dot(cv, cv)) + 1e-300))


def _least_squares(x_rep: np.ndarray, a: np.ndarray, xc: np.ndarray, c: np.ndarray, al: Alignment,
                   inlier_m: list[tuple[float, float]], max_move_m: float, iterations: int = 4,
                   stretch: bool = True) -> tuple[float, float]:
    """(b, ε) minimising Σ (g·a(T(x)) − c(x))² over the true-chainage stretches ``inlier_m``, from
    ``al`` by Gauss–Newton (T: true → reported chainage; ``a`` on the reported grid ``x_rep`` is
    interpolated by a cubic spline, whose derivative is the Jacobian; g absorbs a gain mismatch).
    Returns ``al``'s (b, ε) if the fit is degenerate or would move the pass anywhere by more than
    ``max_move_m`` (a quarter of the band's shortest wave: beyond it the fit has left its basin, e.g.
    against a consensus still smeared by the others' unknown shifts)."""
    spline = make_interp_spline(x_rep, a, k=3)
    slope = spline.derivative()
    h = float(xc[1] - xc[0])
    b, eps = al.shift_m, al.stretch
    for _ in range(iterations):
        cur = Alignment(b, eps, al.x_ref_m, 0.0)
        lo = max(np.ceil(cur.reported_to_true(x_rep[0]) / h), np.ceil(xc[0] / h))
        hi = min(np.floor(cur.reported_to_true(x_rep[-1]) / h), np.floor(xc[-1] / h))
        xg = np.arange(lo, hi + 1) * h
        keep = np.zeros(xg.size, bool)
        for u, v in inlier_m:
            keep |= (xg >= u) & (xg <= v)
        xg = xg[keep]
        if xg.size < MIN_POINTS:
            return al.shift_m, al.stretch
        xr = cur.true_to_reported(xg)
        av, dv = spline(xr), slope(xr)
        cv = c[np.clip(np.rint((xg - xc[0]) / h).astype(np.int64), 0, c.size - 1)]
        gain = float(np.dot(av, cv) / (np.dot(av, av) + 1e-300))
        # r = g·a(T(x)) − c(x); ∂r/∂b = g·a', ∂r/∂ε = g·a'·(x − x_ref), ∂r/∂g = a.
        J = np.stack([gain * dv, gain * dv * (xg - al.x_ref_m), av], axis=1)
        if not stretch:  # ε stays as given
            J[:, 1] = 0.0
        r = gain * av - cv
        scale = np.sqrt(np.sum(J * J, axis=0)) + 1e-300
        step, *_ = np.linalg.lstsq(J / scale, -r, rcond=None)
        step /= scale
        if not np.all(np.isfinite(step)) or abs(step[0]) > FINE_LAG_M or abs(step[1]) > 0.01:
            return al.shift_m, al.stretch  # not a small correction: keep the windows' answer
        b, eps = b + float(step[0]), eps + float(step[1])
        if abs(step[0]) < 1e-5 and abs(step[1]) < 1e-7:
            break
    ends = np.array([x_rep[0], x_rep[-1]])
    moved = Alignment(b, eps, al.x_ref_m, 0.0).reported_to_true(ends) - al.reported_to_true(ends)
    if np.max(np.abs(moved)) > max_move_m:
        return al.shift_m, al.stretch
    return b, eps


def realign(segments: list[ApSegment], al: Alignment) -> list[ApSegment]:
    """The pass's segments re-gridded to true chainage (same identities, values interpolated).

    Segments that abut on the reported grid are re-gridded as one record, so they still abut on the
    true grid: each keeps the true-grid points from where it starts to where the next one starts,
    with values interpolated across the seam (cut separately, a stretch would leave one-point holes
    or overlaps at every seam, and a hole costs the calibration metres of data around it). A real
    hole in the pass stays a hole.
    """
    out = []
    by_axle: dict[int, list[ApSegment]] = {}
    for seg in segments:
        by_axle.setdefault(seg.axle, []).append(seg)
    for axle_segs in by_axle.values():
        axle_segs.sort(key=lambda s: s.start_index)
        runs = [[axle_segs[0]]]
        for seg in axle_segs[1:]:
            if seg.start_index == runs[-1][-1].end_index:
                runs[-1].append(seg)
            else:
                runs.append([seg])
        for run in runs:
            out.extend(_realign_run(run, al))
    return out


def _realign_run(run: list[ApSegment], al: Alignment) -> list[ApSegment]:
    h = run[0].spacing_m
    x_rep = np.concatenate([s.chainage_m for s in run])
    values = np.concatenate([s.values for s in run])
    sigma = np.concatenate([s.sigma for s in run])
    # Time runs linearly along each segment; over the run it is piecewise linear through them.
    t_rep = np.concatenate([np.linspace(s.t_first, s.t_last, s.n) for s in run])
    # Cubic, not linear: linear interpolation at a fractional offset is a low-pass filter (−1 % at
    # 1 m, −5 % at 0.5 m on a 5 cm grid), and since every pass is shifted, the whole fleet's short
    # waves would shrink together — which the calibration reads as a common stiffness error.
    if values.size >= 4 and np.all(np.isfinite(values)):
        resample = make_interp_spline(x_rep, values, k=3)
    else:
        def resample(x, xp=x_rep, fp=values):
            return np.interp(x, xp, fp)
    starts = [max(int(np.ceil(al.reported_to_true(s.chainage_m[0]) / h - 1e-9)), 0) for s in run]
    last = int(np.floor(al.reported_to_true(x_rep[-1]) / h + 1e-9))
    out = []
    for k, seg in enumerate(run):
        i0 = starts[k]
        i1 = starts[k + 1] - 1 if k + 1 < len(run) else last
        if i1 - i0 < 1:
            continue
        xg = np.arange(i0, i1 + 1) * h
        xr = al.true_to_reported(xg)
        vals = resample(xr)
        sig = np.interp(xr, x_rep, sigma)
        t0, t1 = np.interp(xr[[0, -1]], x_rep, t_rep)
        # The pass's speed over *true* chainage is the reported (odometer) speed without its scale
        # error: the calibration's time base needs it.
        out.append(ApSegment.make(vals, sig, vehicle_id=seg.vehicle_id, pass_id=seg.pass_id, route_id=seg.route_id,
                                  tile=seg.tile, axle=seg.axle, start_index=i0, spacing_m=h,
                                  calib_version=seg.calib_version, speed_mps=seg.speed_mps / (1.0 + al.stretch),
                                  t_first=float(t0), t_last=float(t1), seq=seg.seq, flags=seg.flags,
                                  n_segments_in_pass=seg.n_segments_in_pass, error_model=seg.error_model))
    return out
