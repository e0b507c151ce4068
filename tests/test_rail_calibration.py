"""Rail scenarios (simfleet.rail) and batch self-calibration of run properties (cloud.rail.calibration,
thesis §3.4): a quick batch of the rail-track world, 2 % noise, GNSS speed ~2 % off."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from benchmarks.rail import started_mid_motion
from cloud.rail.calibration import calibrate_batch
from cloud.rail.records import RailRun
from cloud.reference.rail_cross_entropy import cross_entropy_batch
from shared.drivelog import MODEL_CHANNELS, list_drive_logs, read_drive_log
from shared.registry import load_site
from shared.track_quality import d1_longitudinal_level
from simfleet.cli import main as sim_main
from simfleet.reproduce_rail import load_runs
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

N_RUNS = 4


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    """A quick rail-track batch (4 runs over 100 m instead of 50 over 150 m)."""
    out = tmp_path_factory.mktemp("rail")
    scenario = dataclasses.replace(SCENARIOS["rail-track"], route_length_m=100.0)
    generate(scenario, out, seed=5, passes=N_RUNS, workers=2, progress=False)
    truth = json.loads((out / "truth.json").read_text())
    runs, _, _ = load_runs(out)
    return out, truth, load_site(out / "site.toml"), runs


def test_scenarios_listed(capsys):
    assert sim_main(["sim", "--list"]) == 0
    listed = capsys.readouterr().out
    names = ["rail-track"] + [f"rail-bridge-state{s}-profile{p}" for s in range(1, 8) for p in (1, 2)]
    for name in names:
        assert name in listed and SCENARIOS[name].vehicle_model == "carriage"
    losses = sorted({SCENARIOS[f"rail-bridge-state{s}-profile1"].bridge.global_loss for s in range(1, 8)})
    assert len(losses) == 7 and losses[0] == 0.0  # seven damage levels including a healthy one


def test_logs_site_and_truth(batch):
    out, truth, site, runs = batch
    assert len(runs) == N_RUNS
    log = read_drive_log(list_drive_logs(out / "logs")[0])
    assert log.meta.vehicle_model == "carriage" and log.meta.pass_id == "run001"
    assert set(MODEL_CHANNELS["carriage"]) <= set(log.channels)
    cls = site.vehicle_class("carriage")
    assert cls.mean["mv"] == pytest.approx(32.4e3) and cls.std["mv"] > 0
    passes = truth["passes"]
    # Run properties vary from run to run; the logged speed is the GNSS one, a few % off.
    assert np.std([p["mv"] for p in passes]) > 0.02 * 32.4e3 and np.std([p["v"] for p in passes]) > 0.2
    np.testing.assert_allclose(log.speed, passes[0]["v_gnss"], rtol=1e-12)
    assert 0.003 < np.median([abs(p["v_gnss"] / p["v"] - 1) for p in passes]) < 0.05
    # The carriage's global properties differ from the class means (a global calibration's error).
    car = truth["vehicles"]["car-0001"]
    assert max(abs(car[k] / cls.mean[k] - 1) for k in ("kp", "ks", "mb")) > 0.01


@pytest.fixture(scope="module")
def fit(batch):
    _, _, site, runs = batch
    cls = site.vehicle_class("carriage")
    return calibrate_batch(runs, cls.mean, cls.std)


def test_batch_calibration(batch, fit):
    """Seed 5, 4 runs, 100 m: the thresholds are the accuracy targets (the measured errors are in the
    report), and all but at most one run's 95 % interval holds its truth."""
    _, truth, _, _ = batch
    true = {p["pass_id"]: p for p in truth["passes"]}
    err = {k: [abs(r.mean[k] / true[r.pass_id][k] - 1) for r in fit.runs] for k in ("mv", "Iv", "v")}
    gnss = np.median([abs(p["v_gnss"] / p["v"] - 1) for p in truth["passes"]])
    assert np.median(err["mv"]) < 0.03 and np.median(err["Iv"]) < 0.03
    assert np.median(err["v"]) < 0.005 and np.median(err["v"]) < gnss / 3
    inside = {k: sum(r.lo95[k] <= true[r.pass_id][k] <= r.hi95[k] for r in fit.runs) for k in ("mv", "Iv", "v")}
    assert min(inside.values()) >= N_RUNS - 1, inside
    rows = fit.rows("car-0001")
    assert len(rows) == 3 * N_RUNS and {r["param"] for r in rows} == {"mv", "Iv", "v"}
    assert all(r["lo95"] < r["mean"] < r["hi95"] and r["pass_id"].startswith("run") for r in rows)


def test_batch_calibration_of_records_that_start_mid_motion(batch, monkeypatch):
    """Records need not start at rest: each run's body initial state is a nuisance (and its chainage
    a shift), so dropping the first 0.3–1.0 s of every run keeps the target accuracy. Measured
    (seed 5, 4 runs, 100 m, truncation seed 0): median |error| mv 1.7 %, Iv 0.8 %, v 0.23 %; every run
    found far from rest (Wald 2 900–10 100 against the 18.5 threshold). The inverse held at rest (the
    calibration before the nuisance) on the same records: mv 3.3 %, Iv 13.5 %."""
    import cloud.rail.calibration as rc

    _, truth, site, runs = batch
    cls = site.vehicle_class("carriage")
    true = {p["pass_id"]: p for p in truth["passes"]}
    late = started_mid_motion(runs)

    def errors(f):
        return {k: float(np.median([abs(r.mean[k] / true[r.pass_id][k] - 1) for r in f.runs]))
                for k in ("mv", "Iv", "v")}

    fit = calibrate_batch(late, cls.mean, cls.std)
    err = errors(fit)
    gnss = np.median([abs(p["v_gnss"] / p["v"] - 1) for p in truth["passes"]])
    assert not any(r.started_at_rest for r in fit.runs), [r.rest_wald for r in fit.runs]
    assert err["mv"] < 0.03 and err["Iv"] < 0.03 and err["v"] < 0.005 and err["v"] < gnss / 3, err
    inside = {k: sum(r.lo95[k] <= true[r.pass_id][k] <= r.hi95[k] for r in fit.runs) for k in ("mv", "Iv", "v")}
    assert min(inside.values()) >= N_RUNS - 1, inside
    # Each record's chainage shift is fitted (not held at the log's): the truth's is (v − v_gnss)·t_cut
    # for the dropped time, up to the batch's common shift (the gauge holds the mean at the logs').
    # Measured: within 3.1 cm of it, the shifts spanning 1.3 m.
    cut = np.array([(len(r.channels) - len(c.channels)) * r.dt for r, c in zip(runs, late)])
    shift_true = np.array([true[r.pass_id]["v"] - r.speed_mps for r in runs]) * cut
    shift = np.array([r.shift_m for r in fit.runs])
    np.testing.assert_allclose(shift - shift.mean(), shift_true - shift_true.mean(), atol=0.05)
    # the same records with every run's state held at rest: what the nuisance fixes
    monkeypatch.setattr(rc, "REST_CHI2", math.inf)
    held = errors(calibrate_batch(late, cls.mean, cls.std))
    assert held["Iv"] > 0.05 and held["Iv"] > 4 * err["Iv"], (held, err)


def test_records_at_the_logs_chainage_keep_it(batch, fit, monkeypatch):
    """A record whose fitted chainage shift is consistent with zero keeps the log's chainage (held
    there for the last stage): held where the middle stage left it, the last stage's speeds took up
    its error and scattered (the blind test's healthy batches: per-run speed sd 0.007 → 0.033 %).
    Measured here (seed 5, 4 runs, 100 m, exact logged chainages): every shift held; the runs' speed
    errors' sd 0.0033 % held, 0.011 % with the shift never held."""
    import cloud.rail.calibration as rc

    _, truth, site, runs = batch
    true = {p["pass_id"]: p for p in truth["passes"]}

    def speed_scatter(f):
        return float(np.std([r.mean["v"] / true[r.pass_id]["v"] - 1 for r in f.runs]))

    assert all(abs(r.shift_m) < 1e-6 for r in fit.runs), [r.shift_m for r in fit.runs]
    monkeypatch.setattr(rc, "SHIFT_CHI2", 0.0)  # never held: the middle stage's shift kept
    free = calibrate_batch(runs, site.vehicle_class("carriage").mean, site.vehicle_class("carriage").std)
    assert any(abs(r.shift_m) > 1e-3 for r in free.runs)
    assert speed_scatter(fit) < 0.5 * speed_scatter(free), (speed_scatter(fit), speed_scatter(free))


def test_held_globals_carry_their_uncertainty(batch, fit):
    """A batch that holds another fit's global properties (the blind test's damaged batches hold the
    healthy batch's) keeps the held point but carries the held values' covariance into its run
    intervals: given the globals, plus their error propagated — on the batch the covariance came
    from, the marginal interval of the fit with the globals free. Measured (seed 5, 4 runs): log
    width of mv's 95 % interval 0.078 free, 0.022 held as exact, 0.078 held with the covariance
    (Iv 0.079 / 0.020 / 0.079); the speed's carries the held bogie spacing's error the same way."""
    _, _, site, runs = batch
    cls = site.vehicle_class("carriage")
    mean, sd = dict(cls.mean), dict(cls.std)
    mean.update(fit.globals_)
    sd.update({k: 0.0 for k in fit.globals_})
    exact = calibrate_batch(runs, mean, sd)
    carried = calibrate_batch(runs, mean, sd, held_globals_cov=fit.globals_log_cov)

    def width(f, k):
        return np.array([np.log(r.hi95[k] / r.lo95[k]) for r in f.runs])

    for k in ("mv", "Iv", "v"):
        assert all(a.mean[k] == b.mean[k] for a, b in zip(exact.runs, carried.runs))  # the same point
        assert np.all(width(carried, k) > 2.5 * width(exact, k)), k
        np.testing.assert_allclose(width(carried, k), width(fit, k), rtol=0.02)


def _prior_explained_log_scale_error(truth: dict, cls) -> float:
    """The batch-common log error of the masses that the priors alone explain. The data fix every
    ratio of the inverse's masses, stiffnesses and dampings (it is invariant to scaling them all),
    so the common scale s is where the priors balance: Σ (log true + s − log class mean)/sd² = 0 over
    every run's mv and Iv and the carriage's six globals."""
    from cloud.rail.calibration import GLOBAL_FIT

    car = next(iter(truth["vehicles"].values()))
    terms = [(p[k], cls.mean[k], cls.std[k]) for p in truth["passes"] for k in ("mv", "Iv")]
    terms += [(car[k], cls.mean[k], cls.std[k]) for k in GLOBAL_FIT]
    w = np.array([(m / sd) ** 2 for _, m, sd in terms])
    return -float(np.sum(w * np.log([t / m for t, m, _ in terms])) / np.sum(w))


def _batch_of(tmp_path, seed, length_m):
    out = tmp_path / f"seed{seed}"
    generate(dataclasses.replace(SCENARIOS["rail-track"], route_length_m=length_m), out, seed=seed, passes=N_RUNS,
             workers=2, progress=False)
    runs, _, _ = load_runs(out)
    return json.loads((out / "truth.json").read_text()), load_site(out / "site.toml"), runs


def test_common_mass_error_is_what_the_priors_explain_over_seeds(batch, fit, tmp_path):
    """Over several seeds (the module's batch and two more, 60 m), the batch-common error of the run
    masses is the one the priors explain (:func:`_prior_explained_log_scale_error`) — no model bias
    on top — and the 95 % intervals cover. Measured, log mv common error minus the prior-explained
    part, seeds 5/1/2: −0.3/+1.1/+0.5 % (mean +0.4 %) with the calibration's inverse at γ = 0.5 and
    the stages' low-pass in space (+0.2/+1.8/+0.5 % with it on the channels); at the edge's γ = 0.8
    (numerical damping read as a softer cp) +1.4/+3.9/+2.7 % (mean +2.7 %).
    Coverage over the 12 runs: mv 1.00, Iv 0.83, v 1.00 (nominal 0.95; 4-run batches are short of
    statistics: this bound guards a regression, the blind test's 50-run batches are in the report)."""
    offsets, inside = [], {k: [] for k in ("mv", "Iv", "v")}
    batches = [(batch[1], batch[2], fit)]
    for seed in (1, 2):
        truth, site, runs = _batch_of(tmp_path, seed, 60.0)
        cls = site.vehicle_class("carriage")
        batches.append((truth, site, calibrate_batch(runs, cls.mean, cls.std)))
    for truth, site, fitted in batches:
        true = {p["pass_id"]: p for p in truth["passes"]}
        offsets.append(np.mean([np.log(r.mean["mv"] / true[r.pass_id]["mv"]) for r in fitted.runs])
                       - _prior_explained_log_scale_error(truth, site.vehicle_class("carriage")))
        for k in inside:
            inside[k] += [r.lo95[k] <= true[r.pass_id][k] <= r.hi95[k] for r in fitted.runs]
    assert abs(np.mean(offsets)) < 0.0125, offsets
    assert all(np.mean(v) >= 0.75 for v in inside.values()), {k: np.mean(v) for k, v in inside.items()}


def test_masses_share_one_scale_without_noise(tmp_path):
    """Noise-free runs (seed 5, 6 runs over 100 m, the train–track simulator at half the logger's
    step): what is left of a calibrated mass's error is the method's, and it must be one scale
    common to the batch (where the priors balance: the inverse is invariant to scaling all masses,
    stiffnesses and dampings together), not an error that grows with the run's mass — that
    over-disperses the masses and biases the bridge's load regression. Measured: log-log slope of
    calibrated on true mv 0.997, scatter of log(mv / true) about its mean 0.03 %; with the stages'
    low-pass on the channels before the inverse (the filter's edge error at the record's start,
    carried for seconds by the inverse's body modes, depends on mv: :class:`cloud.rail.mapping.
    Mapper`) 1.024 and 0.28 % (the blind test's healthy batch, 50 noisy runs: slope 1.045 → 1.010)."""
    out = tmp_path / "quiet"
    generate(dataclasses.replace(SCENARIOS["rail-track"], route_length_m=100.0, noise_pct=0.0), out, seed=5,
             passes=6, workers=2, progress=False)
    truth = json.loads((out / "truth.json").read_text())
    runs, cls, _ = load_runs(out)
    fitted = calibrate_batch(runs, cls.mean, cls.std)
    true = {p["pass_id"]: p["mv"] for p in truth["passes"]}
    t = np.log([true[r.pass_id] for r in fitted.runs])
    e = np.log([r.mean["mv"] for r in fitted.runs])
    assert abs(np.polyfit(t, e, 1)[0] - 1.0) < 0.01
    assert np.std(e - t) < 0.001, np.std(e - t)


def test_consensus_profile_gives_the_track_quality(batch, fit):
    """The batch's consensus AP (cubic removed) against the true unloaded rail in the D1 band:
    the track's deflection under the wheels hardly varies, so D1 is the rail's."""
    _, truth, _, _ = batch
    prof = truth["profile"]
    x_true = prof["start_m"] + prof["spacing_m"] * np.arange(len(prof["elevation_m"]))
    z_true = np.interp(fit.grid_m, x_true, prof["elevation_m"])
    spacing = float(fit.grid_m[1] - fit.grid_m[0])
    d_fit = d1_longitudinal_level(fit.consensus_m, spacing, edge_m=10.0)
    d_true = d1_longitudinal_level(z_true, spacing, edge_m=10.0)
    ok = np.isfinite(d_fit) & np.isfinite(d_true)
    assert ok.sum() > 300
    assert d_fit[ok].std() == pytest.approx(d_true[ok].std(), rel=0.05)
    assert np.abs(d_fit[ok]).max() == pytest.approx(np.abs(d_true[ok]).max(), rel=0.10)


def test_cross_entropy_reference_improves_its_objective(batch):
    _, _, site, runs = batch
    cls = site.vehicle_class("carriage")
    ce = cross_entropy_batch(runs[:3], cls.mean, cls.std, np.random.default_rng(0), population=30,
                             max_generations=6, restarts=0)
    assert ce.best_objective < ce.initial_objective
    assert ce.evaluations == 1 + 30 * ce.generations


def test_calibration_rejects_bad_input(batch):
    _, _, site, runs = batch
    cls = site.vehicle_class("carriage")
    with pytest.raises(ValueError, match="at least two runs"):
        calibrate_batch(runs[:1], cls.mean, cls.std)
    with pytest.raises(ValueError, match="too short a window"):
        calibrate_batch(runs[:2], cls.mean, cls.std, window_m=(20.0, 30.0))
    with pytest.raises(ValueError, match="channels"):
        RailRun("x", np.zeros((100, 3)), 0.002, 30.0)


def test_blind_test_states_differ_only_by_the_global_loss_and_the_journeys():
    """The span's per-element scatter is the bridge's (drawn once per profile and seed): every state's
    E·I is (1 − loss) times the healthy span's, element by element, so the nominal loss is the true
    level against the healthy state; each state is a different set of journeys of the same carriage."""
    from simfleet.rail import STATE_LOSS, bridge_span, draw_carriage, draw_runs

    for profile in (1, 2):
        healthy = SCENARIOS[f"rail-bridge-state7-profile{profile}"]
        ei_h = bridge_span(healthy, 0).ei_factor
        assert np.std(ei_h) > 0.01  # the healthy span has its scatter too
        runs_h = draw_runs(healthy, 5, 0)
        for state, loss in enumerate(STATE_LOSS, start=1):
            s = SCENARIOS[f"rail-bridge-state{state}-profile{profile}"]
            np.testing.assert_allclose(bridge_span(s, 0).ei_factor, (1 - loss) * ei_h, rtol=1e-12)
            assert draw_carriage(s, 0) == draw_carriage(healthy, 0)
            if state != 7:
                assert all(a["mv"] != b["mv"] for a, b in zip(draw_runs(s, 5, 0), runs_h))
    p1, p2 = (bridge_span(SCENARIOS[f"rail-bridge-state7-profile{p}"], 0).ei_factor for p in (1, 2))
    assert not np.allclose(p1, p2)  # another profile, another bridge realisation


def test_batched_inverse_is_the_reference_inverse():
    """carriage_aps_runs (all trials of all runs in one compiled call) gives the AP of the per-trial
    reference inverse (shared.dynamics.population.population_aps) exactly, runs of different
    lengths and steps included."""
    from cloud.rail.carriage_inverse import INVERSE_GAMMA, INVERSE_NAMES, carriage_aps_runs
    from shared.dynamics.population import population_aps
    from shared.vehicles.carriage import TABLE_3_1

    rng = np.random.default_rng(1)
    z = [rng.standard_normal((n, 4)) * [1.0, 0.01, 1.0, 0.01] for n in (700, 450)]
    dts = np.array([0.002, 0.004])
    trials = [dict(TABLE_3_1, mv=30e3 * (1 + 0.1 * i), Iv=1.8e6, ks=0.8e6 + 1e5 * i, cp=6e3 + 500 * i) for i in range(3)]
    Z = np.zeros((2, 700, 4))
    Z[0], Z[1, :450] = z
    theta = np.array([[t[k] for k in INVERSE_NAMES] for t in trials * 2])
    run_of = np.repeat([0, 1], 3)
    got = carriage_aps_runs(theta, run_of, TABLE_3_1["Lb"], TABLE_3_1["Lv"], Z, np.array([700, 450]), dts)
    for r in (0, 1):
        ref = population_aps("carriage", trials, z[r], float(dts[r]), gamma=INVERSE_GAMMA)[0]
        n = len(z[r])
        assert np.abs(got[3 * r:3 * r + 3, :n] - ref).max() <= 1e-12 * np.abs(ref).max()


def test_sensitivities_are_the_derivatives_of_the_inverse():
    """carriage_aps_sensitivities (forward mode through the inverse's recursion, the calibration's
    Jacobian) gives carriage_aps_runs' AP exactly and its derivatives in every log parameter as a
    central difference of carriage_aps_runs does (to the difference's own error, ~1e-7 here), runs
    of different lengths and steps included, damped and undamped contacts."""
    from cloud.rail.carriage_inverse import INVERSE_NAMES, carriage_aps_runs, carriage_aps_sensitivities
    from shared.vehicles.carriage import TABLE_3_1

    rng = np.random.default_rng(2)
    Z = np.zeros((3, 700, 4))
    lengths = np.array([700, 450, 300])
    for r, n in enumerate(lengths):  # a random walk: low-frequency content like a bogie's
        Z[r, :n] = np.cumsum(rng.standard_normal((n, 4)), axis=0) * [0.1, 0.001, 0.1, 0.001]
    dts = np.array([0.002, 0.004, 0.003])
    trials = [dict(TABLE_3_1, mv=30e3, Iv=1.8e6), dict(TABLE_3_1, mv=34e3, Iv=2.1e6, ks=0.9e6, cs=3e4),
              dict(TABLE_3_1, mv=31e3, cp=0.0)]
    theta = np.array([[t[k] for k in INVERSE_NAMES] for t in trials])
    Lb, Lv = TABLE_3_1["Lb"], TABLE_3_1["Lv"]
    sens = carriage_aps_sensitivities(theta, Lb, Lv, Z, lengths, dts)
    base = carriage_aps_runs(theta, np.arange(3), Lb, Lv, Z, lengths, dts)
    h = 1e-5
    for r, n in enumerate(lengths):
        assert np.abs(sens[r, 0, :n] - base[r, :n]).max() <= 1e-12 * np.abs(base[r, :n]).max()
        for j, name in enumerate(INVERSE_NAMES):
            if name == "cp" and theta[r, j] == 0.0:
                continue
            pm = np.repeat(theta[r][None], 2, axis=0)
            pm[0, j] *= math.exp(h)
            pm[1, j] *= math.exp(-h)
            ap = carriage_aps_runs(pm, np.array([r, r]), Lb, Lv, Z, lengths, dts)
            fd = (ap[0, :n] - ap[1, :n]) / (2 * h)
            assert np.abs(fd).max() > 0, name
            assert np.abs(sens[r, 1 + j, :n] - fd).max() <= 1e-5 * np.abs(fd).max(), (r, name)


def test_sensitivities_in_the_body_initial_state():
    """From a body initial state (a record that starts mid-motion), carriage_aps_runs and the
    sensitivities' AP agree exactly, at rest they are the batched inverse's, and the derivatives in
    the state (the free responses: the AP is affine in it) are its central differences to rounding;
    the parameters' derivatives still match theirs."""
    from cloud.rail.carriage_inverse import BODY0_NAMES, INVERSE_NAMES, carriage_aps_runs, carriage_aps_sensitivities
    from shared.vehicles.carriage import TABLE_3_1

    rng = np.random.default_rng(4)
    lengths = np.array([600, 400])
    Z = np.zeros((2, 600, 4))
    for r, n in enumerate(lengths):
        Z[r, :n] = np.cumsum(rng.standard_normal((n, 4)), axis=0) * [0.1, 0.001, 0.1, 0.001]
    dts = np.array([0.002, 0.003])
    theta = np.array([[dict(TABLE_3_1, mv=31e3 + 2e3 * r)[k] for k in INVERSE_NAMES] for r in range(2)])
    Lb, Lv = TABLE_3_1["Lb"], TABLE_3_1["Lv"]
    body0 = rng.standard_normal((2, 4)) * [2e-3, 2e-4, 2e-2, 2e-3]
    rest = carriage_aps_runs(theta, np.arange(2), Lb, Lv, Z, lengths, dts)
    np.testing.assert_array_equal(carriage_aps_runs(theta, np.arange(2), Lb, Lv, Z, lengths, dts,
                                                    body0=np.zeros((2, 4))), rest)
    sens = carriage_aps_sensitivities(theta, Lb, Lv, Z, lengths, dts, body0=body0)
    moving = carriage_aps_runs(theta, np.arange(2), Lb, Lv, Z, lengths, dts, body0=body0)
    for r, n in enumerate(lengths):
        np.testing.assert_array_equal(sens[r, 0, :n], moving[r, :n])
        assert np.abs(moving[r, :n] - rest[r, :n]).max() > 1e-4  # it matters: ~1 mm of AP here
        for j, name in enumerate(BODY0_NAMES):
            b = np.repeat(body0[r][None], 2, axis=0)
            b[0, j] += 1e-3
            b[1, j] -= 1e-3
            ap = carriage_aps_runs(theta[[r, r]], np.array([r, r]), Lb, Lv, Z, lengths, dts, body0=b)
            fd = (ap[0, :n] - ap[1, :n]) / 2e-3
            assert np.abs(sens[r, 9 + j, :n] - fd).max() <= 1e-8 * np.abs(fd).max(), name
        pm = np.repeat(theta[r][None], 2, axis=0)
        pm[0, 0] *= math.exp(1e-5)
        pm[1, 0] *= math.exp(-1e-5)
        ap = carriage_aps_runs(pm, np.array([r, r]), Lb, Lv, Z, lengths, dts, body0=np.repeat(body0[r][None], 2, 0))
        fd = (ap[0, :n] - ap[1, :n]) / 2e-5
        assert np.abs(sens[r, 1, :n] - fd).max() <= 1e-5 * np.abs(fd).max()


def test_lowpass_is_scipys_zero_phase_filter():
    """The compiled zero-phase low-pass is scipy.signal.sosfiltfilt (odd padding, steady-state
    starts) on the closed-form Butterworth sections, to rounding, short records included."""
    from scipy.signal import butter, sosfiltfilt

    from cloud.rail.filters import butter4_sos, sosfiltfilt_columns, sosfiltfilt_rows

    rng = np.random.default_rng(3)
    for wn in (0.01, 0.06, 0.3):
        sos = butter4_sos(wn)
        np.testing.assert_allclose(sos, butter(4, wn, output="sos"), rtol=1e-10, atol=1e-15)
        for n in (16, 100, 2600):
            x = np.cumsum(rng.standard_normal((n, 4)), axis=0) + 5.0
            want = sosfiltfilt(sos, x, axis=0)
            assert np.abs(sosfiltfilt_columns(sos, x) - want).max() <= 1e-12 * np.abs(want).max(), (wn, n)
    # along rows (the mapper's), in blocks: more rows than a block, and fewer
    for rows in (3, 70):
        x = np.cumsum(rng.standard_normal((rows, 500)), axis=1)
        want = sosfiltfilt(sos, x, axis=1)
        assert np.abs(sosfiltfilt_rows(sos, x) - want).max() <= 1e-12 * np.abs(want).max(), rows


def test_noise_information_is_the_profiled_jacobians_quadratic_form():
    """The sandwich's meat (cloud.rail.calibration.noise_information, from per-run spectra) is
    Jᵀ Σ J of the dense profiled-consensus Jacobian (each run's rows, less the mean of all rows) with
    Σ block-diagonal over runs, each block the four wheels' block-Toeplitz cross-covariances that the
    residual shows (biased estimates, pooled over runs): a residual correlated along the track and
    between wheels, inactive local coordinates left out."""
    from cloud.rail.calibration import noise_information

    rng = np.random.default_rng(0)
    n, L, n_g, K = 3, 5, 2, 17
    active = np.array([0, 1, 3, 4])
    D = rng.standard_normal((n, L + n_g, 4, K))
    e = np.cumsum(rng.standard_normal((n, 4, K)), axis=-1) + 0.5 * rng.standard_normal((n, 1, K))
    n_par = n * L + n_g
    J = np.zeros((n, 4, K, n_par))
    for r in range(n):
        for j in active:
            J[r, :, :, r * L + j] = D[r, j]
        J[r, :, :, n * L:] = np.moveaxis(D[r, L:], 0, -1)
    J = (J - J.mean(axis=(0, 1), keepdims=True)).reshape(n, 4 * K, n_par)
    lag = np.arange(K)[:, None] - np.arange(K)[None, :]
    C = np.zeros((4 * K, 4 * K))  # c_wv(a − b) = Σ_r Σ_k e_rw(k + a − b) e_rv(k) / (n·K)
    for w in range(4):
        for v in range(4):
            c = sum(np.correlate(e[r, w], e[r, v], mode="full") for r in range(n)) / (n * K)  # lags −(K−1)…K−1
            C[w * K:(w + 1) * K, v * K:(v + 1) * K] = c[lag + K - 1]
    want = sum(J[r].T @ C @ J[r] for r in range(n))
    got = noise_information(e, D, L, active)
    assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()
    inactive = [r * L + j for r in range(n) for j in range(L) if j not in active]
    assert not got[inactive].any() and not got[:, inactive].any()


@pytest.fixture(scope="module")
def prior_batches(tmp_path_factory):
    """The rail-track-prior carriage (globals and lengths drawn from a ±5 % class prior, its bogie
    spacing 6.5 % short): three seeds of 8 runs over 100 m (the full world is 50 over 150 m)."""
    out = []
    for seed in (0, 1, 2):
        d = tmp_path_factory.mktemp(f"prior{seed}")
        generate(dataclasses.replace(SCENARIOS["rail-track-prior"], route_length_m=100.0), d, seed=seed, passes=8,
                 workers=2, progress=False)
        runs, cls, _ = load_runs(d)
        out.append((json.loads((d / "truth.json").read_text()), runs, calibrate_batch(runs, cls.mean, cls.std)))
    return out


def test_a_carriage_off_its_class_lengths_calibrates(prior_batches):
    """With the bogie spacing 6.5 % off its class mean (held at the class, the speeds were 6.8 % off
    and the masses 14 %), the lengths are calibrated with the batch: the wheels' delays fix every
    speed against them, and the common scale is where the GNSS speeds' mean and the lengths' prior
    put it — so each batch's speed error is its GNSS errors' mean (sd 2 %/√8 here), not the bogie
    spacing's. Measured (seeds 0/1/2): speed error −0.09/+0.50/−0.83 % (the GNSS means −0.11/+0.45/−1.00 %),
    median |error| over the 24 runs mv 2.7 %, Iv 2.0 %, v 0.50 %; 95 % coverage v 1.00, mv 0.75, Iv 0.67."""
    err, inside = {k: [] for k in ("mv", "Iv", "v")}, {k: [] for k in ("mv", "Iv", "v")}
    for truth, runs, fit in prior_batches:
        true = {p["pass_id"]: p for p in truth["passes"]}
        car = truth["vehicles"]["car-0001"]
        assert car["Lv"] / 9.5 - 1 == pytest.approx(-0.065)  # the world's premise
        gnss = np.mean([math.log(p["v_gnss"] / p["v"]) for p in truth["passes"]])
        v_err = np.array([math.log(r.mean["v"] / true[r.pass_id]["v"]) for r in fit.runs])
        # The scale is the GNSS mean's (pulled a little towards the class lengths: their prior's
        # weight is (2 %/√8)² / 5 %² of the mean's), and the runs' ratios the data's.
        assert abs(v_err.mean() - gnss) < 0.03 * abs(0.065) + 0.001, (v_err.mean(), gnss)
        assert np.ptp(v_err) < 0.001
        assert abs(math.log(fit.globals_["Lv"] / car["Lv"]) - v_err.mean()) < 0.001
        for k in err:
            err[k] += [abs(r.mean[k] / true[r.pass_id][k] - 1) for r in fit.runs]
            inside[k] += [r.lo95[k] <= true[r.pass_id][k] <= r.hi95[k] for r in fit.runs]
    print({k: float(np.median(v)) for k, v in err.items()}, {k: float(np.mean(v)) for k, v in inside.items()})
    assert np.median(err["mv"]) < 0.03 and np.median(err["Iv"]) < 0.05  # the goals
    # Coverage over 24 runs of 3 batches (their errors share each batch's common scale: few
    # independent draws), so a bound that guards a regression, not the nominal 0.95.
    assert all(np.mean(v) >= 0.6 for v in inside.values()), {k: np.mean(v) for k, v in inside.items()}
