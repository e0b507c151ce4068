"""The edge inverse's discretisation is undone before the cloud fuses a pass.

The edge runs its inverse at Newmark γ > ½ for stability (quarter-car 0.6, half-car 0.8). Against the
road that scheme has a gain and phase error every vehicle of a class shares, so fused as sent it
biases the profile, its IRI and the fleet calibration alike. The cloud maps each complete pass to
the AP of an exact continuous-time inverse (cloud.road.continuous.continuous_segments), fuses that,
and calibrates on it with a vehicle step that reconstructs and predicts at γ ½.

Data from finer physics than the edge's (the simulator: γ ½ at a quarter of the logger's step).
"""

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from cloud.daemon.settings import CloudSettings
from cloud.road.calibration import PassAp, class_prior, fit_vehicle, to_calibration
from cloud.road.continuous import continuous_ap
from shared.dynamics.forward import simulate_on_profile
from shared.dynamics.inverse import InverseStream, build_inverse, edge_gamma
from shared.profiles import iso8608_profile, tyre_filter
from shared.vehicles import QuarterCar
from simfleet.scenarios import SCENARIOS, TABLE_4_1


def test_the_vehicle_step_on_continuous_aps_has_no_shared_bias():
    """Noise-free, true profile as the consensus, true parameters as the start: what the step finds
    is its model's bias, which every vehicle would share. On the edge's AP that is k/M +1.9 %, c/M
    −1.3 %, m/M +1.1 % (measured); on the continuous-time AP at γ ½ ≤ 0.25 %."""
    true = dict(TABLE_4_1["mean"])
    prof = tyre_filter(iso8608_profile(260.0, 0.01, "A", seed=3))
    speed, h = 22.0, 0.05
    r = simulate_on_profile(QuarterCar(**true).system(), prof.at, prof.slope, 0.0, speed, 200.0 / speed,
                            0.0005, gamma=0.5)
    inverse = build_inverse(QuarterCar(**true).system(), 0.002, gamma=edge_gamma("quarter_car"))  # the edge's
    ap = InverseStream(inverse).update(r.channels[::4])[:, 0]
    grid = np.arange(int(round(20.0 / h)), int(round(190.0 / h)))
    edge = PassAp(int(grid[0]), h, np.interp(grid * h, r.x_cg[::4], ap)[:, None], speed)
    road = prof.at(grid * h)[:, None]
    prior = class_prior("quarter_car", TABLE_4_1["mean"], TABLE_4_1["std"])
    want = to_calibration("quarter_car", true)

    def bias(item, ap_gamma):
        fit = fit_vehicle("quarter_car", true, [(item, road)], prior, true["M"], ap_gamma=ap_gamma)
        return {n: m / want[n] - 1.0 for n, m in zip(fit.names, fit.mean)}

    before = bias(edge, None)
    fixed = PassAp(edge.start_index, h, continuous_ap("quarter_car", true, edge), speed)
    after = bias(fixed, 0.5)
    assert before["k/M"] > 0.01, before  # the edge's discretisation, seen by the step
    assert max(abs(e) for e in after.values()) < 0.005, after


def fused_profile_gains(sim, out, continuous_aps: bool = True) -> dict[tuple[float, float], float]:
    """A simulation's logs through the edge and cloud code in process (nominal calibration, into
    ``out``): the fused profile's gain against the road's in the 0.5–1 and 1–2 m bands (10 m trimmed
    at each end)."""
    from shared.drivelog import list_drive_logs, read_drive_log
    from shared.registry import load_site
    from simfleet.evaluate import band_pass
    from simfleet.reproduce import run_in_process

    logs = [read_drive_log(p) for p in list_drive_logs(sim / "logs")]
    run_in_process(logs, load_site(sim / "site.toml"), out,
                   settings=CloudSettings(calibration="nominal", continuous_aps=continuous_aps))
    truth = json.loads((sim / "truth.json").read_text())
    t = pq.read_table(out / "profile.parquet").to_pydict()
    x, est = np.asarray(t["chainage_m"]), np.asarray(t["elevation_m"])
    p = truth["profile"]
    h = p["spacing_m"]
    true = np.interp(x, p["start_m"] + h * np.arange(len(p["elevation_m"])), p["elevation_m"])
    k = int(10.0 / h)
    gains = {}
    for lo, hi in ((0.5, 1.0), (1.0, 2.0)):
        e, r = band_pass(est, h, lo, hi)[k:-k], band_pass(true, h, lo, hi)[k:-k]
        gains[lo, hi] = float(e @ r / (r @ r))
    return gains


@pytest.mark.parametrize("corrected", [True, False])
def test_the_fused_profile_has_the_roads_gain_at_short_wavelengths(tmp_path, corrected):
    """Six quarter-cars of road-qc, 0.2 % noise (so that the posterior hardly shrinks), each log with
    the vehicle's true parameters, through the edge and cloud code (nominal calibration): the fused
    profile's gain against the road at 0.5–2 m. Fused as the edge sends them, the APs make it
    +2.1–2.5 % (measured); as continuous-time APs within 0.1 %."""
    from simfleet.sim import generate

    sim = tmp_path / "sim"
    generate(SCENARIOS["road-qc"], sim, seed=5, passes=6, vehicles=6, noise_pct=0.2, nominal="true", workers=1,
             progress=False)
    for (lo, hi), gain in fused_profile_gains(sim, tmp_path / "out", continuous_aps=corrected).items():
        if corrected:
            assert abs(gain - 1.0) < 0.006, (lo, hi, gain)
        else:  # the test sees the edge's discretisation when it is there
            assert gain > 1.015, (lo, hi, gain)
