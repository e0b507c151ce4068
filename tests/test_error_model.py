"""The AP error model from the inverse's own noise transfer (edge.error_model) and its use in the cloud.

Passes are made by the simulator (4× finer step, γ = ½: not the edge's inverse) or, noise-only, by
white noise on the channels; the error model is measured against the AP error these really give.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from scipy.signal import welch

from cloud.road.gmrf_profile import GmrfProfile, segment_band_information
from edge.drift import local_linear_trend
from edge.error_model import band_symbol, channel_noise_sd, fit_error_band
from edge.pipeline import EdgeConfig, PassProcessor
from shared.drivelog import list_drive_logs, read_drive_log
from shared.dynamics.inverse import build_inverse, edge_gamma
from shared.schema import ApSegment, InvalidMessage, SensorChunk, decode_ap
from shared.vehicles import vehicle_from_params
from shared.vehicles.half_car import TABLE_2_1
from simfleet.evaluate import band_pass, drift_controlled_truth
from simfleet.replay import chunks_of

SP = 0.05
BANDS = ((0.5, 2.0), (2.0, 5.0), (5.0, 20.0))


def _segments(model, model_name: str, chunks, **config) -> list[ApSegment]:
    first = chunks[0]
    pp = PassProcessor(model, first.vehicle_id, first.pass_id, first.route_id, 0, EdgeConfig(**config), model_name)
    out = []
    for c in chunks:
        out += pp.feed(c)
    return out + pp.finish()[0]


def _log_segments(logs_dir, **config) -> list[ApSegment]:
    out = []
    for path in list_drive_logs(logs_dir):
        log = read_drive_log(path)
        m = log.meta
        model = build_inverse(vehicle_from_params(m.vehicle_model, m.nominal_params).system(), 1.0 / m.sample_rate_hz,
                              gamma=edge_gamma(m.vehicle_model))
        out += _segments(model, m.vehicle_model, list(chunks_of(log)), **config)
    return out


def _axle_runs(segs):
    """Each (pass, axle)'s segments joined on the grid: (start index, values, reliable)."""
    runs = {}
    for s in segs:
        runs.setdefault((s.pass_id, s.axle), []).append(s)
    for ss in runs.values():
        lo, hi = min(s.start_index for s in ss), max(s.end_index for s in ss)
        v = np.full(hi - lo, np.nan)
        sig = np.full(hi - lo, np.inf)
        for s in ss:
            v[s.start_index - lo : s.end_index - lo] = s.values
            sig[s.start_index - lo : s.end_index - lo] = s.sigma
        ok = np.isfinite(v) & (sig < 10 * np.median(sig[np.isfinite(sig)]))  # not the flagged warm-up
        a, b = np.flatnonzero(ok)[[0, -1]]
        yield ss, lo + a, v[a : b + 1]


def _band_power(f, S, lo_m, hi_m):
    k = (f >= 1.0 / hi_m) & (f < 1.0 / lo_m)
    return float(S[k].sum())


def _compare_spectra(segs, truth_at):
    """Empirical spectrum of the AP error (drift-controlled as the edge does) against the mean of the
    segments' model spectra and of their white sigma, per band: returns {band: (model, white)} ratios
    model/empirical."""
    nper = 512
    emp = model = white = 0.0
    for ss, start, v in _axle_runs(segs):
        if v.size < 2 * nper:
            continue
        e = v - truth_at(start, v.size, ss[0].axle)
        e = e - local_linear_trend(e, np.ones(e.size, dtype=bool), EdgeConfig().drift_points)
        f, G = welch(e, fs=1.0 / SP, nperseg=nper, detrend="linear")
        f, G = f[1:], G[1:] * (0.5 / SP)  # per rad/step: a white process's S is its variance
        w = 2 * math.pi * f * SP
        mid = [s for s in ss if s.error_model.size]
        Sm = np.mean([(s.error_model[0] * s.sigma[0]) ** 2 / band_symbol(s.error_model[1:], w) for s in mid], axis=0)
        Sw = np.mean([s.sigma[0] ** 2 for s in mid]) * np.ones_like(w)
        emp, model, white = emp + G, model + Sm, white + Sw
    return {b: (_band_power(f, model, *b) / _band_power(f, emp, *b), _band_power(f, white, *b) / _band_power(f, emp, *b))
            for b in BANDS}


@pytest.fixture(scope="module")
def half_car_long(tmp_path_factory):
    """road-hc's half-cars at its 1 % noise, true parameters in the logs, on 600 m (2 passes)."""
    from simfleet.scenarios import SCENARIOS
    from simfleet.sim import generate

    out = tmp_path_factory.mktemp("hc600")
    sc = dataclasses.replace(SCENARIOS["road-hc"], route_length_m=600.0)
    generate(sc, out, seed=2, passes=2, vehicles=2, nominal="true", workers=1, progress=False)
    return out


def test_channel_noise_level_is_measured_from_the_data(half_car_long):
    """Fourth differences see the sensor noise, not the vehicle: the level found on road-hc's logs is
    the 1 % of each channel's std the simulator added (within the estimator's own scatter)."""
    for path in list_drive_logs(half_car_long / "logs"):
        log = read_drive_log(path)
        z = np.column_stack([np.asarray(v, dtype=float) for v in log.channels.values()])
        added = 0.01 * z.std(axis=0)  # add_noise: 1 % of the (clean ≈ noisy) signal's std
        assert channel_noise_sd(z) == pytest.approx(added, rel=0.06)


def test_model_spectrum_matches_the_ap_error_of_noise_only_passes():
    """White noise on the half-car's channels (levels the edge must find itself, seed unlike the
    model's): the AP the edge makes of it is all error, and the model's spectrum holds it per band.

    The model describes the linearly gridded AP (the inverse's noise up to 250 Hz folded into the
    grid); the alias-free gridding (the edge's default) removes most of that fold, so there the
    model is an upper bound in every band (for a half-car's pitch rate by far: a precision band of
    low order cannot follow the filtered spectrum's 1 000× range)."""
    system = vehicle_from_params("half_car", TABLE_2_1).system()
    model = build_inverse(system, 0.002)
    rng = np.random.default_rng(7)
    n, v = 60_000, 18.0  # 120 s, 2.2 km
    levels = {"body_acc": 0.004, "body_pitch_rate": 1.5e-4}
    chunks = []
    for seq, i in enumerate(range(0, n, 500)):
        k = min(500, n - i)
        chunks.append(SensorChunk(
            vehicle_id="veh-1", pass_id="noise", route_id="R1", vehicle_model="half_car", seq=seq,
            t0=i * 0.002, sample_rate_hz=500.0, chainage=v * 0.002 * np.arange(i, i + k), speed=np.full(k, v),
            channels={c: (lvl * rng.standard_normal(k)).astype(np.float32) for c, lvl in levels.items()},
            final=i + k >= n))
    segs = _segments(model, "half_car", chunks, antialias=False)
    ratios = _compare_spectra(segs, lambda start, size, axle: np.zeros(size))
    for band, (r_model, r_white) in ratios.items():
        assert 0.75 <= r_model <= 1.33, (band, r_model)
    alias_free = _compare_spectra(_segments(model, "half_car", chunks), lambda start, size, axle: np.zeros(size))
    for band, (r_model, _) in alias_free.items():
        assert r_model >= 0.75, (band, r_model)
    # The white sigma (second differences) is set by the shortest wavelengths: 2–20 m far too high.
    assert ratios[(2.0, 5.0)][1] > 10 and ratios[(5.0, 20.0)][1] > 10


def test_model_spectrum_matches_the_ap_error_of_simulated_passes(half_car_long):
    """Road plus 1 % noise, simulated by another solver at a finer step: the AP error (road-hc's
    half-car, true parameters) against the model per band; measured 0.8–1.1."""
    truth = json.loads((half_car_long / "truth.json").read_text())
    p = truth["profile"]
    tx = p["start_m"] + p["spacing_m"] * np.arange(len(p["elevation_m"]))
    segs = _log_segments(half_car_long / "logs", antialias=False)  # what the model describes (above)
    ratios = _compare_spectra(segs, lambda start, size, axle: np.interp((start + np.arange(size)) * SP, tx,
                                                                         p["elevation_m"]))
    for band, (r_model, r_white) in ratios.items():
        assert 0.67 <= r_model <= 1.5, (band, r_model)
    assert ratios[(2.0, 5.0)][1] > 10


def _fuse(segs, length_m, with_model: bool):
    g = GmrfProfile({"R1": length_m}, SP)
    for s in segs:
        g.update(s if with_model else dataclasses.replace(s, error_model=np.zeros(0)))
    return g.snapshot()["R1"]


def _score(snap, truth, trim_m=10.0):
    p = truth["profile"]
    tx = p["start_m"] + p["spacing_m"] * np.arange(len(p["elevation_m"]))
    ok = np.flatnonzero(np.isfinite(snap.elevation_m))
    sl = slice(ok[0], ok[-1] + 1)
    est, x = snap.elevation_m[sl], snap.chainage_m[sl]
    true = np.interp(x, tx, p["elevation_m"])
    k = int(trim_m / SP)
    a, b = band_pass(est, SP)[k:-k], band_pass(true, SP)[k:-k]
    t = drift_controlled_truth(true, snap.n_passes[sl])
    t = t + np.mean(est - t)
    inside = (t >= snap.lo95_m[sl]) & (t <= snap.hi95_m[sl])
    return float(np.std(a - b) / np.std(b)), float(np.mean(inside[k:-k]))


def test_fused_half_car_profile_with_the_model(tmp_path):
    """road-hc as it is (6 half-cars, 100 m, 1 % noise), true parameters: with the white sigma the
    posterior shrinks every wavelength (67 % error on seed 0); with the model the error drops by
    more than half and the 95 % band still holds ≥ 90 % of the road."""
    from simfleet.scenarios import SCENARIOS
    from simfleet.sim import generate

    truth = generate(SCENARIOS["road-hc"], tmp_path, seed=3, nominal="true", workers=1, progress=False)
    segs = _log_segments(tmp_path / "logs")
    assert all(s.error_model.size for s in segs)
    err_white, _ = _score(_fuse(segs, 100.0, False), truth)
    err_model, coverage = _score(_fuse(segs, 100.0, True), truth)
    assert err_model < 0.5 * err_white, (err_model, err_white)
    assert coverage >= 0.9, coverage


# -- the cloud's side: exact, banded, retractable --------------------------------------------------


def _segment(rng, n, p, start=0, sigma=None):
    values = rng.normal(0, 1e-3, n)
    sigma = np.full(n, 2e-4) if sigma is None else sigma
    _, band = fit_error_band(np.linspace(0.01, math.pi, 400), 1.0 + 30 * np.linspace(0, 1, 400) ** 2, SP, order=p)
    return ApSegment.make(values, sigma, vehicle_id="v", pass_id=f"p{start}", route_id="R1", tile=0, axle=1,
                          start_index=start, spacing_m=SP, calib_version=0, speed_mps=20.0, t_first=0.0,
                          t_last=1.0, seq=0, error_model=np.concatenate([[1.3], band]))


def test_banded_information_is_the_dense_one_and_retracts():
    rng = np.random.default_rng(1)
    sigma = np.full(300, 2e-4)
    sigma[:20] *= 100  # a flagged stretch
    seg = _segment(rng, 300, 4, start=50, sigma=sigma)
    D = np.diag(seg.error_model[0] * seg.sigma)
    c = seg.error_model[1:]
    T = sum(np.diag(np.full(300 - k, c[k]), -k) + (np.diag(np.full(300 - k, c[k]), k) if k else 0) for k in range(c.size))
    Q = np.linalg.inv(D) @ T @ np.linalg.inv(D)
    band, rhs = segment_band_information(seg.values, seg.sigma, seg.error_model)
    for d in range(c.size):
        assert np.allclose(band[d, : 300 - d], np.diag(Q, -d), rtol=1e-12)
    assert np.allclose(rhs, Q @ seg.values, rtol=1e-10)
    profile = GmrfProfile({"R1": 399 * SP}, SP, tau=1.0)  # 400 points; the segment on 50..349
    route = profile.routes["R1"]
    profile.update(seg)  # the compiled sums, decoding the wire codes point by point
    assert np.allclose(route.q[:, 50:350], band, rtol=1e-12) and np.allclose(route.b[50:350], rhs, rtol=1e-12)
    profile.retract(seg)
    assert np.abs(route.q).max() <= 1e-9 * np.abs(band).max() and not route.cover.any() and not route.passes.any()


def test_profile_with_banded_segments_is_order_independent_and_retracts():
    rng = np.random.default_rng(2)
    old = ApSegment.make(rng.normal(0, 1e-3, 200), np.full(200, 3e-4), vehicle_id="v", pass_id="old",
                         route_id="R1", tile=0, axle=1, start_index=100, spacing_m=SP, calib_version=0,
                         speed_mps=20.0, t_first=0.0, t_last=1.0, seq=0)  # no model: the white/AR(1) path
    segs = [_segment(rng, 300, 4, start=0), _segment(rng, 250, 2, start=150), old]
    a, b = GmrfProfile({"R1": 30.0}, SP, tau=1e7), GmrfProfile({"R1": 30.0}, SP, tau=1e7)
    for s in segs:
        a.update(s)
    for s in reversed(segs):
        b.update(s)
    qa, ba = a.information("R1")
    qb, bb = b.information("R1")
    assert qa.shape[0] == 5 and np.allclose(qa, qb, rtol=1e-12) and np.allclose(ba, bb, rtol=1e-12)
    ma = a.snapshot()["R1"].elevation_m
    # the banded posterior is the dense solve of the same system
    n = qa.shape[1]
    Q = np.zeros((n, n))
    for d in range(qa.shape[0]):
        Q += np.diag(qa[d, : n - d], -d) + (np.diag(qa[d, : n - d], d) if d else 0)
    ok = np.isfinite(ma)
    assert np.allclose(ma[ok], np.linalg.solve(Q, ba)[ok], rtol=1e-6, atol=1e-9)
    ref = GmrfProfile({"R1": 30.0}, SP, tau=1e7)
    ref.update(old)
    a.retract(segs[0])
    a.retract(segs[1])
    qr, br = ref.information("R1")
    qa, ba = a.information("R1")
    assert np.allclose(qa[:2], qr, atol=1e-6 * np.abs(qr).max()) and np.abs(qa[2:]).max() <= 1e-6 * np.abs(qr).max()


# -- the wire ------------------------------------------------------------------------------------


def test_error_model_round_trips_and_old_payloads_decode():
    rng = np.random.default_rng(3)
    seg = _segment(rng, 50, 3)
    back = decode_ap(seg.encode())[0]
    assert back == seg and np.array_equal(back.error_model, seg.error_model)
    from shared import schema

    cols = schema._ap_columns([seg])
    del cols["error_model"]  # what an older edge wrote
    payload = schema._encode(ApSegment.KIND, cols)
    old = decode_ap(payload)[0]
    assert old.error_model.size == 0 and np.array_equal(old.values, seg.values)


@pytest.mark.parametrize("bad, reason", [
    ([1.0, 1.0, 0.6], "bad_value"),  # 1 + 1.2 cos ω < 0 at π: not positive definite
    ([0.0, 1.0], "bad_value"),
    ([1.0], "bad_shape"),
    ([1.0, 1.0, np.nan], "non_finite"),
])
def test_bad_error_models_are_rejected(bad, reason):
    with pytest.raises(InvalidMessage) as e:
        ApSegment.make(np.zeros(4), np.full(4, 1e-4), vehicle_id="v", pass_id="p", route_id="R1", tile=0, axle=1,
                       start_index=0, spacing_m=SP, calib_version=0, speed_mps=1.0, t_first=0.0, t_last=1.0, seq=0,
                       error_model=np.array(bad))
    assert e.value.reason == reason


def test_long_wave_band_shares_follow_the_segment_model():
    """:mod:`.long_wave` subtracts each pass's own modelled share of a band from the passes' scatter:
    for a white segment that is ``1/a − 1/b``; for the edge's model it is the band's variance of
    noise drawn from that model (here 20 000 points drawn through its banded Cholesky factor)."""
    from scipy.linalg import cholesky_banded, solve_banded

    from cloud.road.gmrf_profile import error_band_shares

    widths = [11, 41, 201]
    assert np.allclose(error_band_shares(np.zeros(0), widths), [1 / 11 - 1 / 41, 1 / 41 - 1 / 201, 1 / 201])
    rng = np.random.default_rng(4)
    em = _segment(rng, 10, 4).error_model
    n, c = 20_000, em[1:]
    ab = np.zeros((c.size, n))
    for d in range(c.size):
        ab[d, : n - d] = c[d]
    L = cholesky_banded(ab, lower=True)  # T = L Lᵀ; x = L⁻ᵀ z has covariance T⁻¹
    upper = np.zeros_like(L)  # Lᵀ in upper banded storage
    for d in range(c.size):
        upper[c.size - 1 - d, d:] = L[d, : n - d]
    x = em[0] * solve_banded((0, c.size - 1), upper, rng.standard_normal(n))
    ma = [np.convolve(x, np.ones(a) / a, mode="same") for a in widths]
    bands = [ma[0] - ma[1], ma[1] - ma[2], ma[2]]
    emp = np.array([np.var(b[500:-500]) for b in bands])
    assert np.allclose(error_band_shares(em, widths), emp, rtol=0.15)


# -- the edge's cost: cached unit spectra and the tabulated symbol change nothing ----------------------


def test_cached_error_model_is_the_uncached_one(monkeypatch):
    """The unit spectra are cached per (inverse, speed bucket, spacing, drift width) and the fit's
    symbol is tabulated on its check grid (edge CPU per segment, within the edge's real-time latency): a
    half-car pass (two channels, so the per-segment noise mix matters) gives the same error model
    with a warm cache as with none, and the tabulated variance and white equivalent are the direct
    quadrature of ``band_symbol`` for every order the edge allows."""
    import edge.error_model as em

    system = vehicle_from_params("half_car", TABLE_2_1).system()
    model = build_inverse(system, 0.002)
    rng = np.random.default_rng(11)
    n, v = 15_000, 15.0  # 30 s, 450 m: several tiles at two speeds (two cache buckets)
    levels = {"body_acc": 0.004, "body_pitch_rate": 1.5e-4}
    speed = np.where(np.arange(n) < n // 2, v, 1.3 * v)
    chainage = np.concatenate([[0.0], np.cumsum(speed[:-1] * 0.002)])
    chunks = [SensorChunk(vehicle_id="veh-1", pass_id="p", route_id="R1", vehicle_model="half_car", seq=seq,
                          t0=i * 0.002, sample_rate_hz=500.0, chainage=chainage[i : i + 500], speed=speed[i : i + 500],
                          channels={c: (lvl * rng.standard_normal(min(500, n - i))).astype(np.float32)
                                    for c, lvl in levels.items()}, final=i + 500 >= n)
              for seq, i in enumerate(range(0, n, 500))]
    em._CACHE.clear()
    warm = _segments(model, "half_car", chunks)
    warm_again = _segments(model, "half_car", chunks)  # every spectrum now a cache hit
    monkeypatch.setattr(em, "_CACHE_SIZE", 0)  # nothing is kept: each segment computes its own
    em._CACHE.clear()
    cold = _segments(model, "half_car", chunks)
    with_model = [s for s in cold if s.error_model.size]
    assert len(with_model) >= 8
    for a, b, c in zip(warm, warm_again, cold, strict=True):
        np.testing.assert_array_equal(a.error_model, c.error_model)
        np.testing.assert_array_equal(b.error_model, c.error_model)
    w = em._OMEGA_CHECK
    for p in range(0, 9):
        c = fit_error_band(np.linspace(0.01, math.pi, 400), 1.0 + rng.uniform(1, 50) * np.linspace(0, 1, 400) ** 2,
                           SP, order=p)[1]
        P = band_symbol(c, w)
        assert em.band_variance(c) == pytest.approx(np.trapezoid(1.0 / P, w) / math.pi, rel=1e-12)
        direct = math.sqrt(np.trapezoid((2 - 2 * np.cos(w)) ** 2 * 4.0 / P, w) / math.pi / 6.0)
        assert em.white_equivalent(2.0, c) == pytest.approx(direct, rel=1e-12)
