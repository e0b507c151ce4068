"""The half-car's per-vehicle step (acceleration space) recovers Table 2.6's ratios from a wrong start.

Data from finer physics than the step's own discretisation (Newmark γ = ½ at 0.5 ms, the logger
at 2 ms), 1 % sensor noise, through the edge's real pass processor (inverse under the current
calibration, anti-aliased gridding); the consensus is the mean AP of two other vehicles of
Table 2.4 under their true parameters, at other speeds (what a calibrated fleet makes of the road,
the edge's discretisation undone per pass, as the fleet's vehicle step does). The remap settings
(cloud.road.calibration.RemapSettings: the start state a nuisance, a low-pass) are what make the
channels reconstructed from the noisy AP close enough for a pass to move the ratios off the class
prior.
"""

import numpy as np

from scipy.signal import butter, sosfiltfilt

from cloud.road.calibration import PassAp, calibration_names, class_prior, fit_vehicle, to_calibration
from cloud.road.continuous import continuous_ap
from cloud.road.fleet_calibration import FleetCalibrator
from edge.pipeline import PassProcessor
from shared.dynamics.forward import simulate_on_profile
from shared.dynamics.inverse import build_inverse, edge_gamma
from shared.profiles.iso8608 import iso8608_profile, tyre_filter
from shared.schema import SensorChunk
from shared.sensors import add_noise
from shared.vehicles import vehicle_from_params
from simfleet.scenarios import TABLE_2_4

DT = 0.002  # s, the logger
FINE = 4  # simulation steps per logger sample
NOISE_PCT = 1.0  # sensor noise, % of each channel's std
ROUNDS = 3  # vehicle steps, each on APs recomputed under the last


def _pass(true: dict, start: dict, prof, speed: float, length_m: float, rng, pass_id: str,
          noise_pct: float) -> PassAp:
    """One logged pass of the ``true`` vehicle, its AP computed by the edge under ``start``."""
    r = simulate_on_profile(vehicle_from_params("half_car", true).system(), prof.at, prof.slope, 5.0, speed,
                            length_m / speed, DT / FINE, gamma=0.5)
    channels = add_noise(r.channels[::FINE], noise_pct, rng)
    x = r.x_cg[::FINE]
    system = vehicle_from_params("half_car", start).system()
    chunk = SensorChunk(vehicle_id="v", pass_id=pass_id, route_id="r", vehicle_model="half_car", seq=0, t0=0.0,
                        sample_rate_hz=1.0 / DT, chainage=x, speed=np.full(x.size, speed),
                        channels={ch.name: channels[:, i].astype(np.float32) for i, ch in enumerate(system.channels)},
                        final=True)
    proc = PassProcessor(build_inverse(system, DT, gamma=edge_gamma("half_car")), "v", pass_id, "r", 0,
                         model_name="half_car")
    (ap,) = FleetCalibrator._passes(proc.feed(chunk) + proc.finish()[0])
    return ap


def test_half_car_step_recovers_ratios_from_a_wrong_start():
    mean = {k: float(np.mean([v[k] for v in TABLE_2_4])) for k in TABLE_2_4[0]}
    std = {k: (0.02 if k in ("D1", "D2") else 0.1) * v for k, v in mean.items()}
    true = {k: float(v) for k, v in TABLE_2_4[1].items()}  # vehicle 2 of Table 2.4
    start = dict(mean)  # the class mean, as the fleet starts
    for k, f in (("Ks1", 0.85), ("Cs2", 1.15), ("Kt1", 0.88), ("mu2", 0.9)):  # and further off
        start[k] *= f
    want, got0 = to_calibration("half_car", true), to_calibration("half_car", start)
    prof = tyre_filter(iso8608_profile(150.0, 0.01, "A", seed=5))
    # The consensus: what a well-calibrated fleet makes of the road, the mean AP of two other vehicles
    # of Table 2.4 under their true parameters (noise-free: a large fleet's average), through the
    # same edge inverse, each with the edge's discretisation undone under its own parameters (as
    # cloud.road.fleet_calibration.CONTINUOUS_CONSENSUS does). Without that, the edge's Newmark γ = 0.8
    # distorts every AP's wheel-hop band, each vehicle's differently, and no vehicle matches the blend.
    others = []
    for j, speed in ((0, 18.0), (2, 19.0)):
        other = {k: float(v) for k, v in TABLE_2_4[j].items()}
        o = _pass(other, other, prof, speed, 130.0, np.random.default_rng(j), f"o{j}", 0.0)
        others.append(PassAp(o.start_index, o.spacing_m, continuous_ap("half_car", other, o), o.speed_mps))
    lo = max(o.start_index for o in others)
    hi = min(o.start_index + o.values.shape[0] for o in others)
    consensus = np.mean([o.values[lo - o.start_index : hi - o.start_index].mean(axis=1) for o in others], axis=0)
    params = dict(start)
    history = []
    for _ in range(ROUNDS):  # as the fleet does: the edge recomputes its APs under each new calibration
        rng = np.random.default_rng(2)  # the same logs every round
        items = []
        for k, speed in enumerate((16.0, 21.0)):
            ap = _pass(true, params, prof, speed, 130.0, rng, f"p{k}", NOISE_PCT)
            grid = ap.start_index + np.arange(ap.values.shape[0])
            cons = np.interp(grid, lo + np.arange(consensus.size), consensus, left=np.nan, right=np.nan)
            items.append((ap, np.repeat(cons[:, None], 2, axis=1)))
        fit = fit_vehicle("half_car", params, items, class_prior("half_car", mean, std), start["ms"])
        params = fit.params
        history.append({n: round(100 * (m / want[n] - 1), 1) for n, m in zip(fit.names, fit.mean)})
    names = calibration_names("half_car")
    start_err = {n: got0[n] / want[n] - 1 for n in names}
    err = {n: m / want[n] - 1 for n, m in zip(fit.names, fit.mean)}
    assert sorted(abs(e) for e in start_err.values())[-4] > 0.1, start_err  # four ratios start > 10 % off
    # measured (3 rounds): median 0.1 %, worst 0.6 % (round 1: Cs1/ms −8.0 %); with the others' APs
    # as the edge made them (γ = 0.8, predicted at 0.8): median 1.4 %, worst Cs1/ms −5.7 %. The
    # thesis's noise-free Table 2.6: medians up to 22 % (Cs1/ms).
    assert np.median([abs(e) for e in err.values()]) < 0.01, history
    assert max(abs(e) for e in err.values()) < 0.03, history


def test_continuous_ap_undoes_the_edge_discretisation():
    """The edge's γ = 0.8 inverse damps the half-car's wheel hop numerically; ``continuous_ap`` maps
    its AP to what an exact inverse of the continuous vehicle gives. Data from finer physics (γ = ½
    at 0.5 ms), noise-free, through the edge's pass processor; compared with the true profile on
    1.5 c/m – 30 m (the band the vehicle step compares, the drift below it left out)."""
    true = {k: float(v) for k, v in TABLE_2_4[1].items()}
    prof = tyre_filter(iso8608_profile(150.0, 0.01, "A", seed=5))
    sos = butter(2, [1 / 30.0, 1.5], btype="band", fs=20.0, output="sos")
    for speed in (12.0, 25.0):
        ap = _pass(true, true, prof, speed, 130.0, np.random.default_rng(0), "p", 0.0)
        h = ap.spacing_m
        assert h == 0.05
        road = np.repeat(prof.at((ap.start_index + np.arange(ap.values.shape[0])) * h)[:, None], 2, axis=1)
        ok = np.all(np.isfinite(ap.values), axis=1)
        k = int(10.0 / h)  # filter and extent edges
        band = sosfiltfilt(sos, road[ok], axis=0)[k:-k]

        def error(values):
            return np.std(sosfiltfilt(sos, values[ok] - road[ok], axis=0)[k:-k], axis=0) / np.std(band, axis=0)

        edge, fixed = error(ap.values), error(continuous_ap("half_car", true, ap))
        # measured: edge 2.0–4.2 %, corrected 0.4–0.9 %
        assert np.all(edge > 0.01), (speed, edge)
        assert np.all(fixed < 0.3 * edge), (speed, edge, fixed)
