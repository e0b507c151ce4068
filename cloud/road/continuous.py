"""The continuous-time correction of the edge's AP: a pass's AP as an exact inverse of the
continuous-time vehicle would have made it from the same channels (:func:`continuous_ap`, the edge
inverse's Newmark transfer undone per pass), and a pass's held segments so corrected for the fusion
(:func:`continuous_segments`)."""

from __future__ import annotations

import math

import numpy as np

from shared.dynamics.inverse import edge_gamma
from shared.dynamics.transfer import continuous_transfer, newmark_transfer
from shared.schema import ApSegment
from shared.vehicles import vehicle_from_params

from cloud.road.calibration import REMAP_DT, PassAp

#: Hz: :func:`continuous_ap` corrects up to here, faded to identity by 1.5× it: 0.5 m (the shortest
#: wavelength the profile is scored on) is 60 Hz at 30 m/s, and the edge's AP still carries its
#: scheme's gain and phase error there. ``|T⁻¹H|`` stays near 1 on the diagonal in that band, so the
#: correction amplifies no noise.
CONTINUOUS_CUTOFF_HZ = 60.0
MEMORY_S = 2.0  # s: how far past a pass's ends :func:`continuous_ap` continues it (mirrored, tapered)


def _correction_inputs(model: str, params: dict, ap: PassAp):
    """The vehicle's system, the pass's AP values (n_points, n_contacts) and where they are finite,
    for the continuous-time corrections; one channel per contact or a ValueError."""
    system = vehicle_from_params(model, params).system()
    values = np.asarray(ap.values, float)
    if len(system.channels) != values.shape[1]:
        raise ValueError(f"continuous_ap: {model} measures {len(system.channels)} channels for {values.shape[1]} contacts")
    return system, values, np.isfinite(values)


def continuous_ap(model: str, params: dict, ap: PassAp, cutoff_hz: float = CONTINUOUS_CUTOFF_HZ) -> np.ndarray:
    """The pass's AP (n_points, n_contacts) as an exact inverse of the continuous-time vehicle
    ``params`` would have made it from the same channels: ``T⁻¹H`` applied to the edge's AP, ``H``
    the edge inverse's discrete Newmark transfer (its γ), ``T`` the continuous one.

    The edge's γ > ½ damps the wheel hop numerically, and how much depends on each vehicle's
    parameters and speed: a consensus of such APs is a blend of different distortions of the road,
    against which no vehicle's own distortion matches. Undone per pass before fusing, the consensus
    is the road again (up to noise), and a vehicle step can predict with continuous physics.

    Applied on the route grid itself, in wavenumber ``κ`` (the transfers at ``f = vκ``, constant
    speed ``v``): contact i meets chainage x at the time contact j meets ``x + off_j − off_i``, so
    ``Â'_i(κ) = Σ_j C_ij(vκ) e^{2πiκ(off_j − off_i)} Â_j(κ)``. (Resampling to the time grid and back
    would lose more of the AP's short waves to the linear interpolation than the correction gains:
    :func:`continuous_ap_resampled`.) Each contact on its own extent (holes bridged linearly, a straight line
    removed, continued past its ends mirrored and tapered), faded to identity between ``cutoff_hz``
    and 1.5× it; NaN stays NaN.
    A pass's ends (within the correction's memory, ~0.5 s, and a wheelbase) are approximate: what
    the other contacts would add there was not driven."""
    system, values, ok = _correction_inputs(model, params, ap)
    n_points, n_contacts = values.shape
    h, v = ap.spacing_m, ap.speed_mps
    off = np.asarray(system.offsets_m, float)
    if (ok.sum(axis=0) < 64).any() or not v > 0:
        return values.copy()
    first = [int(np.flatnonzero(ok[:, i])[0]) for i in range(n_contacts)]
    last = [int(np.flatnonzero(ok[:, i])[-1]) + 1 for i in range(n_contacts)]
    # The correction's memory (the body mode's ~1 s) reaches past a contact's ends: there each contact
    # continues as its mirror image, tapered to zero (an abrupt end would ring through ``T⁻¹H − 1`` at
    # the body mode, more than the edge's own error over a pass's first metres).
    ext = int(math.ceil(MEMORY_S * v / h))
    a, b = min(first) - ext, max(last) + ext
    series = np.zeros((b - a, n_contacts))
    trend = np.zeros((b - a, n_contacts))
    kk = np.arange(a, b, dtype=float)
    for i in range(n_contacts):
        idx = np.flatnonzero(ok[:, i])
        k = np.arange(first[i], last[i])
        y = np.interp(k, idx, values[idx, i])
        line = np.polyfit(k.astype(float), y, 1)
        trend[:, i] = np.polyval(line, kk)
        y = y - trend[first[i] - a : last[i] - a, i]
        m = min(ext, y.size - 1)
        taper = 0.5 * (1.0 + np.cos(math.pi * np.arange(1, m + 1) / (m + 1)))
        lo, hi = first[i] - a, last[i] - a
        series[lo:hi, i] = y
        series[lo - m : lo, i] = (y[1 : m + 1] * taper)[::-1]
        series[hi : hi + m, i] = y[-2 : -m - 2 : -1] * taper
    # The mirrored ends, tapered to zero, keep the circular wrap harmless: no zero-padding beyond the
    # contacts' shifts.
    pad = int(math.ceil(np.ptp(off) / h)) if n_contacts > 1 else 0
    n_fft = 1 << int(math.ceil(math.log2((b - a) + 2 * pad)))
    spec = np.fft.rfft(series, n_fft, axis=0)
    kappa = np.fft.rfftfreq(n_fft, h)  # cycles per metre
    f = v * kappa
    fade = np.clip((1.5 * cutoff_hz - f) / (0.5 * cutoff_hz), 0.0, 1.0)
    use = np.flatnonzero((f > 0) & (fade > 0))
    H = newmark_transfer(system, f[use], ap.dt_s, edge_gamma(model))  # the edge's step, not the grid's
    T = continuous_transfer(system, f[use])
    if n_contacts == 1:  # (a sprung mass, a quarter-car: scalars, no shifts)
        spec[use, 0] *= 1.0 + fade[use] * (H[:, 0, 0] / T[:, 0, 0] - 1.0)
    else:
        eye = np.eye(n_contacts)
        corr = eye + fade[use, None, None] * (np.linalg.solve(T, H) - eye)
        shift = np.exp(2j * math.pi * kappa[use, None, None] * (off[None, None, :] - off[None, :, None]))
        rest = np.setdiff1d(np.arange(f.size), use)
        out_spec = np.zeros_like(spec)
        out_spec[use] = np.einsum("fij,fj->fi", corr * shift, spec[use])
        out_spec[rest] = spec[rest]  # identity (the shifts cancel on the diagonal)
        spec = out_spec
    fixed = np.fft.irfft(spec, n_fft, axis=0)[: b - a] + trend
    out = values.copy()
    for i in range(n_contacts):
        j = np.flatnonzero(ok[:, i])
        out[j, i] = fixed[j - a, i]
    return out


def continuous_ap_resampled(model: str, params: dict, ap: PassAp, cutoff_hz: float = 30.0) -> np.ndarray:
    """:func:`continuous_ap` through the pass's time grid (resampled linearly from the route grid and
    back, which loses part of the AP's short waves), up to 30 Hz. The half-car's corrected consensus
    (cloud.road.fleet_calibration.CONTINUOUS_CONSENSUS) uses it: its common gain and step halving are
    tuned on this one, and with :func:`continuous_ap` its damping ratios calibrate worse until they
    are tuned again.

    The pass's AP (n_points, n_contacts) as an exact inverse of the continuous-time vehicle
    ``params`` would have made it from the same channels: ``T⁻¹H`` applied to the edge's AP, ``H``
    the edge inverse's discrete Newmark transfer (its γ), ``T`` the continuous one.

    The edge's γ = 0.8 damps a half-car's wheel hop numerically, and how much depends on each
    vehicle's parameters and speed: a consensus of such APs is a blend of different distortions of
    the road, against which no vehicle's own distortion matches. Undone per pass before fusing, the
    consensus is the road again (up to noise), and a vehicle step can predict with continuous physics.
    The contacts are corrected together on the pass's time grid (constant speed), on their common
    extent (straight line removed, zero-padded FFT), faded to identity between ``cutoff_hz`` and 1.5×
    it; points outside that extent keep the edge's value, NaN stays NaN."""
    system, values, ok = _correction_inputs(model, params, ap)
    n_points, n_contacts = values.shape
    h, v = ap.spacing_m, ap.speed_mps
    x = (ap.start_index + np.arange(n_points)) * h
    off = system.offsets_m
    if (ok.sum(axis=0) < 16).any() or not v > 0:
        return values.copy()
    lo = max(x[ok[:, i]][0] - off[i] for i in range(n_contacts))
    hi = min(x[ok[:, i]][-1] - off[i] for i in range(n_contacts))
    t = np.arange(0.0, (hi - lo) / v, REMAP_DT) if hi > lo else np.zeros(0)
    if t.size < 64:
        return values.copy()
    series = np.stack([np.interp(lo + off[i] + v * t, x[ok[:, i]], values[ok[:, i], i]) for i in range(n_contacts)],
                      axis=1)
    k = np.arange(t.size, dtype=float)
    trend = np.stack([np.polyval(np.polyfit(k, series[:, i], 1), k) for i in range(n_contacts)], axis=1)
    n_fft = 1 << int(math.ceil(math.log2(2 * t.size)))
    spec = np.fft.rfft(series - trend, n_fft, axis=0)
    f = np.fft.rfftfreq(n_fft, REMAP_DT)
    fade = np.clip((1.5 * cutoff_hz - f) / (0.5 * cutoff_hz), 0.0, 1.0)
    use = (f > 0) & (fade > 0)
    eye = np.eye(n_contacts)
    corr = np.broadcast_to(eye, (f.size, n_contacts, n_contacts)).astype(complex)
    H = newmark_transfer(system, f[use], ap.dt_s, edge_gamma(model))  # the edge's step, not the grid's
    T = continuous_transfer(system, f[use])
    corr[use] = eye + fade[use, None, None] * (np.linalg.solve(T, H) - eye)
    fixed = np.fft.irfft(np.einsum("fij,fj->fi", corr, spec), n_fft, axis=0)[: t.size] + trend
    out = values.copy()
    for i in range(n_contacts):
        x_cg = x - off[i]
        inside = ok[:, i] & (x_cg >= lo) & (x_cg <= lo + v * t[-1])
        out[inside, i] = np.interp(x_cg[inside], lo + v * t, fixed[:, i])
    return out


#: Vehicle models whose passes the cloud fuses as continuous-time APs (:func:`continuous_segments`).
#: Rail models are left out (their cloud re-runs the dynamics from the edge's AP, cloud.rail.batches), and so
#: is the sprung mass (its joint step, :func:`cloud.road.calibration.fit_fleet`, reconstructs at the edge's
#: γ). Half-cars too: each corrected pass is closer to the road, but the fusion over-shrinks half-car passes at 1–5 m
#: (their edge error model is far too large there: edge.error_model grids its unit spectra by plain
#: interpolation, whose aliasing of the pitch-rate noise leaves a floor the alias-free AP does not
#: have), and the uncorrected AP's gain error offsets part of that shrinkage, so fused corrected the
#: profile comes out worse. They keep the corrected consensus in their vehicle step only
#: (cloud.road.fleet_calibration.CONTINUOUS_CONSENSUS) until the error model is fixed.
CONTINUOUS_MODELS = frozenset({"quarter_car"})
#: Points weighted down this much or more (the edge's σ × 100: invalid points, zeroed, and the
#: inverse's warm-up) are holes for the correction (bridged, and kept as sent): a filter would spread them.
_HOLE_WEIGHT = 50.0


def pass_values(segs: list[ApSegment], n_axles: int) -> tuple[int, np.ndarray]:
    """One pass's segments on its grid slice: the first grid index and the values (points, axles),
    NaN where no segment holds a point."""
    lo, hi = min(s.start_index for s in segs), max(s.end_index for s in segs)
    vals = np.full((hi - lo, n_axles), np.nan)
    for s in segs:
        vals[s.start_index - lo : s.end_index - lo, s.axle - 1] = s.values
    return lo, vals


def pass_speed(segs: list[ApSegment]) -> float:
    """The pass's time base (m/s): chainage its lead axle covered over the time taken (the aligned
    frame's when the cloud re-gridded it), else the speed the edge reported."""
    lead = [s for s in segs if s.axle == 1 and s.t_last > s.t_first]
    dx = sum((s.end_index - 1 - s.start_index) * s.spacing_m for s in lead)
    dt = sum(s.t_last - s.t_first for s in lead)
    return dx / dt if dt > 0 and dx > 0 else segs[0].speed_mps


def continuous_segments(model: str, params: dict, segs: list[ApSegment],
                        dt_s: float = REMAP_DT) -> list[ApSegment]:
    """One pass's segments (all axles) as continuous-time APs (:func:`continuous_ap` under the
    vehicle's ``params``, the edge having inverted at ``dt_s``), same identities, sigma and error
    model, in the order given.

    Why: the edge's inverse runs Newmark at γ > ½ for stability, and its AP carries that scheme's
    gain and phase error against the road at short wavelengths. Every vehicle of a class shares it,
    so fused as sent it biases the profile, its IRI and the fleet calibration alike. The error model
    is kept: ``|T⁻¹H|`` is near 1 on the diagonal in the corrected band, so the edge's noise spectrum
    stays about right, if anything conservative."""
    n_axles = max(s.axle for s in segs)
    lo, vals = pass_values(segs, n_axles)
    floor = min(float(np.min(s.sigma)) for s in segs)
    for s in segs:
        sigma = np.asarray(s.sigma)
        hole = sigma >= _HOLE_WEIGHT * floor
        vals[s.start_index - lo : s.end_index - lo, s.axle - 1][hole] = np.nan
    fixed = continuous_ap(model, params, PassAp(lo, segs[0].spacing_m, vals, pass_speed(segs), dt_s))
    out = []
    for s in segs:
        v = fixed[s.start_index - lo : s.end_index - lo, s.axle - 1]
        v = np.where(np.isfinite(v), v, s.values)
        out.append(ApSegment.make(v, s.sigma, vehicle_id=s.vehicle_id, pass_id=s.pass_id, route_id=s.route_id,
                                  tile=s.tile, axle=s.axle, start_index=s.start_index, spacing_m=s.spacing_m,
                                  calib_version=s.calib_version, speed_mps=s.speed_mps, t_first=s.t_first,
                                  t_last=s.t_last, seq=s.seq, n_segments_in_pass=s.n_segments_in_pass,
                                  flags=s.flags, error_model=s.error_model))
    return out
