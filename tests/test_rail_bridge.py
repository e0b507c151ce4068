"""Bridge damage from bogie data (cloud.rail.bridge, thesis §3.5–3.6): a healthy and a 13 %-damaged
culvert span under quick batches (10 runs, 40 m approach instead of 50 runs over 120 m)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from cloud.bridge.mril import damage_indicators
from cloud.rail.batches import span_stiffness
from cloud.rail.bridge import (MODELS, difference_shift, bogie_influence, damage_from_batch_means, influence_of_aps,
                                pooled_healthy, registered_runs, run_aps)
from cloud.rail.calibration import calibrate_batch
from simfleet.rail import RailBridgeSpec
from simfleet.reproduce_rail import load_runs, true_effective_levels
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

N_RUNS = 10


def calibrated_batch(tmp_path, name, loss, scenario="rail-bridge-state7-profile1"):
    """A quick batch (runs, its calibration off the bridge, class, bridge) and its truth (read only to score)."""
    scenario = dataclasses.replace(SCENARIOS[scenario], route_length_m=70.0, batch=0,
                                   bridge=RailBridgeSpec(start_m=40.2, global_loss=loss))  # same runs for both
    generate(scenario, tmp_path / name, seed=3, passes=N_RUNS, workers=2, progress=False)
    runs, cls, bridge = load_runs(tmp_path / name)
    fit = calibrate_batch(runs, cls.mean, cls.std, window_m=(0.0, bridge.start_chainage_m - 2.0))  # off the bridge
    return (runs, fit, cls, bridge), json.loads((tmp_path / name / "truth.json").read_text())


def influences_of(runs, fit, cls, bridge):
    return {m: bogie_influence(runs, fit, cls.mean, bridge.start_chainage_m, bridge.span_m, model=m) for m in MODELS}


def influences(tmp_path, name, loss):
    """All models' influence of a quick batch, and the batch's truth."""
    batch, truth = calibrated_batch(tmp_path, name, loss)
    return influences_of(*batch), truth


@pytest.fixture(scope="module")
def healthy_batch(tmp_path_factory):
    return calibrated_batch(tmp_path_factory.mktemp("rail_bridge"), "healthy", 0.0)


def test_damage_level_from_a_healthy_and_a_damaged_batch(tmp_path, healthy_batch):
    """Same track and runs, the span's E·I 13 % lower (its 5 % per-element scatter is the bridge's
    own, in both states, so D1/D2 of its static line against the healthy span's are 13 % exactly).
    Measured (seed 3, 10 runs): regression over the calibrated wheel loads with the carriage inverse
    D1 14.0 %, D2 14.1 %; from the batch means 12.3 % / 12.2 % — the spread of a small batch. The
    indicators' bounds are ±5 points here (the blind test's 50 runs: ``driveby reproduce rail``)."""
    healthy = influences_of(*healthy_batch[0])
    damaged, truth = influences(tmp_path, "damaged", 0.13)
    h, d = healthy["carriage"], damaged["carriage"]
    # Deflection per unit wheel load (m/N) of the order of a 10 m span plus its track: ~1e-8.
    assert 3e-9 < h.mril.midspan() < 3e-8
    assert h.mril.J[0] == pytest.approx(0.0, abs=0.1 * h.mril.midspan())  # zero at the supports
    effective = true_effective_levels(truth, h.mril.x_m, against_healthy=True)
    assert effective == pytest.approx((13.0, 13.0), abs=1e-6)
    ind = damage_indicators(h.mril, d.mril)
    assert abs(ind.D1_pct - effective[0]) < 5.0 and abs(ind.D2_pct - effective[1]) < 5.0, (ind, effective)
    assert np.ptp(h.wheel_load_n) > 0.05 * h.wheel_load_n.mean()  # what separates the profile
    means = damage_from_batch_means(h, d)  # the estimator that also holds across independent batches
    assert abs(means.D1_pct - effective[0]) < 5.0 and abs(means.D2_pct - effective[1]) < 5.0, (means, effective)
    # Every batch over the track reads the healthy line: its own regression less the change of its
    # batch mean. From the damaged batch alone that is the healthy batch's line (measured: 0.2 % rms
    # of its peak, J⁰ 0.6 %), not the damaged one's (8.6 %, J⁰ 14 %: the 13 % loss).
    own, from_damaged = pooled_healthy(h, [h]), pooled_healthy(h, [d])
    for line in ("mril", "difference"):
        ref = getattr(own, line).J
        off = {name: np.sqrt(np.mean((getattr(b, line).J - ref) ** 2)) / np.abs(ref).max()
               for name, b in (("pooled", from_damaged), ("damaged", pooled_healthy(d, [d])))}
        assert off["pooled"] < 0.02 and off["damaged"] > 0.05, (line, off)
    # The body's force on a bogie acts at its centre: the two wheels' time-synchronous AP difference
    # is the same whether the body is modelled (carriage) or not (bogie half-car).
    for batch in (healthy, damaged):
        for line in ("difference", "difference_unseparated"):
            a, b = getattr(batch["carriage"], line).J, getattr(batch["bogie_half_car"], line).J
            assert np.abs(a - b).max() <= 1e-6 * np.abs(a).max()
        a = batch["carriage"].difference.J
        assert a.max() > 0.3 * batch["carriage"].mril.J.max()  # a line, not noise: same order as J⁰ + J¹
    # The leading bogie's two channels with the body modelled (the trailing bogie over the AP its
    # wheels found): the batch-mean AP line on the span close to the four-channel inverse's, unlike
    # the half-car's (the body's force left out). Measured (seed 3, 10 runs, 40 m approach): rms
    # off the carriage's line 3.1 %/3.0 % of its peak (healthy/damaged), the half-car's 18 %/18 %;
    # D1/D2 from the batch means 15.4/16.3 % (the carriage's 13.4/13.5 %).
    for batch in (healthy, damaged):
        ref = batch["carriage"].mean_line.J
        off = {m: np.sqrt(np.mean((batch[m].mean_line.J - ref) ** 2)) / np.abs(ref).max()
               for m in ("leading_bogie", "bogie_half_car")}
        assert off["leading_bogie"] < 0.25 * off["bogie_half_car"], off
    means = damage_from_batch_means(healthy["leading_bogie"], damaged["leading_bogie"])
    assert abs(means.D1_pct - effective[0]) < 5.0 and abs(means.D2_pct - effective[1]) < 5.0, (means, effective)


def test_batches_are_registered_on_the_wheels_difference(healthy_batch):
    """Two batches' chainage differs by their calibrated speeds' common error (~1 cm at the span);
    the registration reads it off the leading bogie's time-synchronous wheel difference beside the
    span. The same runs reported 12 mm further along and 0.01 % faster (expected shift at mid-span
    −15.5 mm) give −15.3 mm back (seed 3, 10 runs, 29 m before the span; −13.9 mm by a single
    linearised step on the healthy line's slope: a noisy regressor pulls it towards zero), the same from the bogie half-car's channels as from the carriage's (the body's
    force, which the half-car leaves out, cancels in the difference). And 12 mm alone moves D1/D2 of
    the same runs by −2.4/−3.3 points unregistered, −0.05/−0.04 registered (carriage); the
    half-car's J⁰ reading −3.9/−4.8 and 1.0/2.1."""
    (runs, fit, cls, bridge), _ = healthy_batch
    mid = bridge.start_chainage_m + 0.5 * bridge.span_m - (cls.mean["Lv"] + cls.mean["Lb"])  # wheel 1 at mid-span
    a = influences_of(runs, fit, cls, bridge)
    span = float(a["carriage"].mril.x_m[-1])
    for shift, stretch in ((0.012, 1e-4), (0.012, 0.0)):
        moved = [dataclasses.replace(r, x0_m=r.x0_m + shift) for r in runs]
        fit_moved = dataclasses.replace(fit, runs=[dataclasses.replace(e, mean={**e.mean, "v": e.mean["v"] * (1 + stretch)})
                                                   for e in fit.runs])
        b = influences_of(moved, fit_moved, cls, bridge)
        found = {m: difference_shift(a[m].difference_line, b[m].difference_line, span, a[m].wheelbase_m)
                 for m in ("carriage", "bogie_half_car")}
        # b(x) = a(x − shift − stretch·(x − x0 − offset)): with current(x − δ) ≈ healthy(x), δ ≈ −(that).
        expected = -(shift + stretch * mid)
        assert found["carriage"] == pytest.approx(expected, rel=0.05), (found, expected)
        assert found["bogie_half_car"] == pytest.approx(found["carriage"], abs=1e-9)
    worst = {}
    for m, fundamental in (("carriage", False), ("bogie_half_car", True)):
        for register in (True, False):
            d = damage_from_batch_means(a[m], b[m], fundamental=fundamental, register=register)
            worst[m, register] = max(abs(d.D1_pct), abs(d.D2_pct))
    assert worst["carriage", True] < 0.5 and worst["carriage", False] > 3 * worst["carriage", True], worst
    assert worst["bogie_half_car", True] < 0.7 * worst["bogie_half_car", False], worst


def test_a_scale_line_that_is_not_a_deflection_is_not_read(healthy_batch):
    """An AP whose errors follow the wheel load more than the deflection does (blind seed 4 profile 1,
    ``leading_bogie``: every batch's regression area −32…+12 µm·m/kN, the carriage's +24…+32) gives a
    healthy line near zero or of the wrong sign, and D = 100·(1 − IL_H/IL_D) then reads anything
    (D1 −4310 there). Made here from the healthy batch's own APs with each run's calibrated wheel load
    mirrored about the batch mean (same mean and spread, the slope's sign reversed): a clear error, not
    a number; the same APs with their own loads read D ≈ 0 against themselves."""
    (runs, fit, cls, bridge), _ = healthy_batch
    span = (bridge.start_chainage_m, bridge.span_m)
    aps = run_aps(runs, fit, cls.mean, "carriage")
    w_mean = np.mean([r.wheel_load_n for r in aps])
    mirrored = [dataclasses.replace(r, wheel_load_n=2 * w_mean - r.wheel_load_n) for r in aps]
    own, wrong = influence_of_aps(aps, *span), influence_of_aps(mirrored, *span)
    assert wrong.mril.area < 0 < own.mril.area
    same = damage_from_batch_means(own, own)
    assert abs(same.D1_pct) < 1e-6 and abs(same.D2_pct) < 1e-6
    with pytest.raises(ValueError, match="healthy line .* is not a deflection"):
        damage_from_batch_means(wrong, own)
    with pytest.raises(ValueError, match="healthy line .* is not a deflection"):
        damage_from_batch_means(wrong, own, fundamental=True)


def test_true_effective_level_of_a_uniform_loss_is_the_loss():
    """The scoring's 'effective' level: a uniform loss L reads as D1 = D2 = 100·L; scatter moves it."""
    spec = RailBridgeSpec()
    x = np.linspace(0.0, spec.span_m, 205)
    ei = spec.E_pa * spec.I_m4
    for loss in (0.0, 0.05, 0.13):
        truth = {"bridge": {"span_m": spec.span_m, "EI": [ei * (1 - loss)] * spec.n_elements}}
        d1, d2 = true_effective_levels(truth, x)
        assert d1 == pytest.approx(100 * loss, abs=1e-6) and d2 == pytest.approx(100 * loss, abs=1e-6)
    weak_middle = [ei * (0.7 if 6 <= i <= 10 else 1.0) for i in range(spec.n_elements)]
    d1, d2 = true_effective_levels({"bridge": {"span_m": spec.span_m, "EI": weak_middle}}, x)
    assert 0 < d2 < 30 and d1 > d2  # a weak middle shows more at mid-span than in the area


@pytest.fixture(scope="module")
def prior_batches(tmp_path_factory):
    """The rail-bridge-prior carriage (globals and lengths from a ±5 % class prior: seed 3's bogie
    spacing Lv 6.5 % short, its wheelbase Lb 6.5 % long) in quick batches (10 runs, 40 m approach),
    healthy and 13 %-damaged (the same runs)."""
    tmp = tmp_path_factory.mktemp("rail_bridge_prior")
    return (calibrated_batch(tmp, "healthy", 0.0, "rail-bridge-prior-loss0"),
            calibrated_batch(tmp, "damaged", 0.13, "rail-bridge-prior-loss0"))


def test_a_carriage_off_its_class_lengths_calibrates_before_the_bridge(prior_batches):
    """Off the bridge (a 24 m window), the lengths are found: Lb/Lv from the wheels' agreement (a grid
    search, then Gauss–Newton; from the class's ratio, 14 % off, Gauss–Newton alone settled 3 % off with
    every global 5–11 % off), the common scale from the GNSS mean (10 runs: sd 0.6 %). Measured (seed
    3): Lb +0.3 %, Lv +0.7 %, speeds +0.65 %, globals within 2.6 %."""
    (runs, fit, cls, bridge), truth = prior_batches[0]
    car = truth["vehicles"]["car-0001"]
    gnss = float(np.mean([np.log(p["v_gnss"] / p["v"]) for p in truth["passes"]]))
    # the wheelbase to the wheels' delays, the spacing (the common scale) to the GNSS mean's sd
    assert abs(np.log(fit.globals_["Lb"] / fit.globals_["Lv"] * car["Lv"] / car["Lb"])) < 0.01
    assert abs(np.log(fit.globals_["Lv"] / car["Lv"]) - gnss) < 0.005
    assert max(abs(fit.globals_[k] / car[k] - 1) for k in ("mb", "Ib", "kp", "cp", "ks", "cs")) < 0.05


@pytest.mark.xfail(strict=True, reason="open: the load regression's lever is the runs' mass spread, and the per-run "
                   "masses' errors from the quick batches' 24 m calibration window (lengths and globals free) are not "
                   "small against it: with the true masses put in it reads within the bound. The span's placement is "
                   "not the cause: with the true speed scale put in it reads the same. The 28-run batches of the full "
                   "world read within a point")
def test_a_carriage_off_its_class_lengths_reads_the_bridge(prior_batches):
    """The 13 % loss read as the daemon reads it (every run registered, the healthy line pooled over
    both batches), and one batch's stiffness interval holding the truth. Measured (seed 3): D1/D2
    20.6/21.5 %; stiffness 1.61 [0.25, 10.3] (true 1.01)."""
    ((runs, fit, cls, bridge), truth), ((d_runs, d_fit, _, _), _) = prior_batches
    span = (bridge.start_chainage_m, bridge.span_m)
    h_aps = registered_runs(run_aps(runs, fit, cls.mean, "carriage"), *span)
    healthy = influence_of_aps(h_aps, *span)
    d_aps = registered_runs(run_aps(d_runs, d_fit, cls.mean, "carriage"), *span, reference=healthy.difference_line)
    damaged = influence_of_aps(d_aps, *span)
    ind = damage_from_batch_means(pooled_healthy(healthy, [healthy, damaged]), damaged)
    mean, lo, hi = span_stiffness(bridge, healthy, h_aps, span)
    true_ratio = float(np.mean(truth["bridge"]["stiffness_ratio"]))
    print(f"D1 {ind.D1_pct:.1f} %, D2 {ind.D2_pct:.1f} %; stiffness {mean:.3f} [{lo:.3f}, {hi:.3f}], true {true_ratio:.3f}")
    # ±5 points: the old world's bound on these quick batches (the blind test's 50 runs: driveby reproduce rail)
    assert abs(ind.D1_pct - 13.0) < 5.0 and abs(ind.D2_pct - 13.0) < 5.0, ind
    assert lo <= true_ratio <= hi
