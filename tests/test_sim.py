"""``driveby sim``: the scenario list, what a small generation writes (logs, site.toml, truth.json),
noise-free and reproducible output, and one-line errors for bad arguments."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from shared.drivelog import MODEL_CHANNELS, list_drive_logs, read_drive_log
from shared.dynamics.inverse import apparent_profile, build_inverse
from shared.fe import crack_ei_factor
from shared.registry import load_site
from shared.vehicles import vehicle_from_params
from simfleet.scenarios import SCENARIOS, TABLE_4_1, fleet_class
from simfleet.sim import generate

BRIDGE_STATES = [
    "bridge-healthy", "bridge-crack10-10m", "bridge-crack10-14m", "bridge-crack5-10m", "bridge-crack5-14m",
    "bridge-global5", "bridge-global10", "bearing-1e9", "bearing-1e10", "bearing-1e12",
]
EXPECTED = ["road-qc", "road-hc", "road-qc-gnss", "carpet", *BRIDGE_STATES,
            *(f"{b}-rough" for b in BRIDGE_STATES), "fleet-large",
            "rail-track", *(f"rail-bridge-state{s}-profile{p}" for s in range(1, 8) for p in (1, 2)), "demo-crack20-14m", "demo-healthy", "rail-track-prior", "rail-bridge-prior-loss0", "rail-bridge-prior-loss10",
            "network", "network-clean"]
GENERATED = ["road-qc", "road-hc", "carpet", "bridge-crack10-10m", "bearing-1e10"]
PASSES = 3
SEED = 11


def driveby(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "simfleet.cli", "sim", *args], capture_output=True, text=True,
                          timeout=600, stdin=subprocess.DEVNULL)  # a cold numba cache on a loaded machine


def load_logs(out: Path) -> list:
    return [read_drive_log(p) for p in list_drive_logs(out / "logs")]


def assert_same_logs(a: list, b: list) -> None:
    assert len(a) == len(b)
    for la, lb in zip(a, b):
        assert la.meta == lb.meta
        for name in ("t", "chainage", "speed"):
            np.testing.assert_array_equal(getattr(la, name), getattr(lb, name))
        assert la.channels.keys() == lb.channels.keys()
        for ch in la.channels:
            np.testing.assert_array_equal(la.channels[ch], lb.channels[ch])


@pytest.fixture(scope="module")
def generated(tmp_path_factory) -> dict[str, tuple[Path, dict]]:
    """Small versions (3 passes) of five scenarios, generated once for the module."""
    out = {}
    for name in GENERATED:
        d = tmp_path_factory.mktemp(name)
        out[name] = (d, generate(SCENARIOS[name], d, seed=SEED, passes=PASSES, workers=1, progress=False))
    return out


# --- the scenario list --------------------------------------------------------------------------


def test_list_shows_every_scenario_of_the_issue_once_per_line():
    res = driveby("--list")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.strip().splitlines()
    names = [line.split()[0] for line in lines]
    assert names == list(SCENARIOS)
    assert sorted(names) == sorted(EXPECTED)
    for line in lines:
        assert len(line.split(maxsplit=1)) == 2  # a name and a description


def test_rough_variants_and_the_large_fleet_are_what_they_claim():
    for name in BRIDGE_STATES:
        smooth, rough = SCENARIOS[name], SCENARIOS[f"{name}-rough"]
        assert smooth.bridge == rough.bridge and smooth.bridge is not None
        assert not smooth.rough_deck and rough.rough_deck
    large = SCENARIOS["fleet-large"]
    assert large.passes == large.n_vehicles == 300
    assert (large.bridge.crack_x_m, large.bridge.crack_phi) == (10.0, 0.05)
    assert SCENARIOS["bearing-1e10"].bridge.krot_nm_per_rad == 1e10


# --- what a generation writes -------------------------------------------------------------------


@pytest.mark.parametrize("name", GENERATED)
def test_logs_are_valid_drive_logs_of_the_scenario(generated, name):
    out, truth = generated[name]
    scenario = SCENARIOS[name]
    logs = load_logs(out)
    assert len(logs) == PASSES
    mean, _ = fleet_class(scenario)
    offsets = vehicle_from_params(scenario.vehicle_model, mean).system().offsets_m
    for log, record in zip(logs, truth["passes"]):
        meta = log.meta
        assert meta.vehicle_model == scenario.vehicle_model
        assert meta.sample_rate_hz == 500.0
        assert meta.route_id == truth["route"]["id"] == "R1"
        assert (meta.pass_id, meta.vehicle_id) == (record["pass_id"], record["vehicle_id"])
        assert meta.nominal_params == pytest.approx(mean)  # --nominal class (default)
        assert set(log.channels) == set(MODEL_CHANNELS[scenario.vehicle_model])
        assert all(c.dtype == np.float32 and np.all(np.isfinite(c)) for c in log.channels.values())
        assert len(log) == record["n_samples"]
        np.testing.assert_allclose(np.diff(log.t), 1 / 500.0, rtol=1e-9)
        # Chainage (of the centre of gravity) runs over the route while every axle is on it.
        step = record["speed_mps"] / 500.0
        assert np.all(np.diff(log.chainage) > 0)
        assert 0.0 <= log.chainage[0] < step
        assert scenario.route_length_m - offsets.max() - step < log.chainage[-1] <= scenario.route_length_m
        lo, hi = scenario.speed_range_mps
        assert lo <= record["speed_mps"] <= hi
        np.testing.assert_allclose(log.speed, record["speed_mps"])
        np.testing.assert_allclose(np.diff(log.chainage) * 500.0, record["speed_mps"], rtol=1e-9)
    assert len({log.meta.pass_id for log in logs}) == PASSES


@pytest.mark.parametrize("name", GENERATED)
def test_site_toml_loads_with_the_route_fleet_class_and_bridge(generated, name):
    out, truth = generated[name]
    scenario = SCENARIOS[name]
    site = load_site(out / "site.toml")
    assert [(r.id, r.length_m) for r in site.routes] == [("R1", scenario.route_length_m)]
    (vc,) = site.vehicle_classes
    assert vc.model == scenario.vehicle_model
    assert (vc.mean, vc.std) == fleet_class(scenario)
    spec = scenario.bridge
    if spec is None:
        assert site.bridges == ()
        return
    (bridge,) = site.bridges
    assert (bridge.route, bridge.start_chainage_m, bridge.span_m, bridge.n_elements) == ("R1", 100.0, 20.0, 20)
    assert (bridge.E_pa, bridge.I_m4, bridge.mass_per_m, bridge.damping_ratio) == (35e9, 1.25, 37500.0, 0.03)
    expected = "rotational_springs" if name.startswith("bearing") else "simply_supported"
    assert bridge.supports == expected == truth["bridge"]["supports"]
    assert bridge.end_chainage_m <= scenario.route_length_m


@pytest.mark.parametrize("name", GENERATED)
def test_truth_holds_profile_vehicles_and_passes(generated, name):
    out, truth = generated[name]
    assert json.loads((out / "truth.json").read_text()) == truth
    scenario = SCENARIOS[name]
    assert truth["scenario"] == name and truth["seed"] == SEED
    assert truth["noise_pct"] == scenario.noise_pct
    profile = truth["profile"]
    n = len(profile["elevation_m"])
    assert profile["start_m"] == 0.0
    assert (n - 1) * profile["spacing_m"] == pytest.approx(scenario.route_length_m)
    elevation = np.array(profile["elevation_m"])
    assert 1e-4 < np.std(elevation) < 1e-2  # a class A road, in metres
    assert truth["vehicle_model"] == scenario.vehicle_model
    assert len(truth["vehicles"]) == scenario.n_vehicles
    for params in truth["vehicles"].values():
        vehicle_from_params(scenario.vehicle_model, params)  # every truth parameter set is valid
    assert [p["vehicle_id"] for p in truth["passes"]] == list(truth["vehicles"])[:PASSES]
    if scenario.carpet:
        for log, record in zip(load_logs(out), truth["passes"]):
            assert 0 <= record["lane"] <= 10
            assert log.meta.lane_offset_m == pytest.approx((record["lane"] - 5) * 0.1)
    else:
        assert all(p["lane"] is None for p in truth["passes"])
    if scenario.bridge is None:
        assert "bridge" not in truth
    else:
        x = np.arange(n) * profile["spacing_m"]
        deck = (x >= 100.0) & (x <= 120.0)
        assert np.all(elevation[deck] == 0.0)  # smooth deck
        assert np.all(elevation[(x > 10) & (x < 90)] != 0.0)


def test_truth_of_a_cracked_bridge_carries_the_element_losses(generated):
    _, truth = generated["bridge-crack10-10m"]
    b = truth["bridge"]
    assert (b["crack_x_m"], b["crack_phi"], b["global_loss"]) == (10.0, 0.10, 0.0)
    ratio = np.array(b["stiffness_ratio"])
    np.testing.assert_allclose(ratio, crack_ei_factor(20, 20.0, 1.0, 10.0, 0.10))
    np.testing.assert_allclose(np.array(b["EI"]), 35e9 * 1.25 * ratio)
    loss = 1.0 - ratio
    # §4.5: φ = 10 % takes ~18 % off the two elements at the crack and ~5 % off their neighbours
    np.testing.assert_allclose(loss[8:12], [0.045, 0.181, 0.181, 0.045], atol=0.005)
    assert np.all(loss[:8] == 0) and np.all(loss[12:] == 0)
    assert 4.0 < b["f1_hz"] < 4.24  # softer than the healthy 4.24 Hz


def test_truth_of_a_bearing_scenario_has_springs_and_a_stiffer_bridge(generated):
    _, truth = generated["bearing-1e10"]
    b = truth["bridge"]
    assert b["supports"] == "rotational_springs" and b["krot_nm_per_rad"] == 1e10
    assert b["stiffness_ratio"] == [1.0] * 20
    assert b["f1_hz"] > 4.25  # end restraint raises f1 above the simply supported 4.24 Hz


def test_rough_deck_variant_keeps_the_profile_over_the_span(tmp_path):
    truth = generate(SCENARIOS["bridge-healthy-rough"], tmp_path, seed=SEED, passes=1, workers=1, progress=False)
    elevation = np.array(truth["profile"]["elevation_m"])
    x = np.arange(len(elevation)) * truth["profile"]["spacing_m"]
    assert np.all(elevation[(x >= 100.0) & (x <= 120.0)] != 0.0)


def test_gnss_errors_are_in_the_logged_chainage_and_speed(tmp_path):
    truth = generate(SCENARIOS["road-qc-gnss"], tmp_path, seed=SEED, passes=3, workers=1, progress=False)
    biases = []
    for log, record in zip(load_logs(tmp_path), truth["passes"]):
        v, bias, scale = record["speed_mps"], record["gnss_bias_m"], record["speed_scale_error"]
        biases.append(bias)
        # first logged true chainage is in [0, v/fs); the jitter has sd 0.05 m
        assert -0.25 < log.chainage[0] - bias < v / 500.0 + 0.25
        np.testing.assert_allclose(log.speed, v * (1 + scale))
        # GNSS measures position (bias + jitter, no scale error); the odometer's speed carries the scale
        slope = np.polyfit(log.t, log.chainage, 1)[0]
        assert slope == pytest.approx(v, rel=1e-3)
    assert all(abs(b) > 0 for b in biases) and len(set(biases)) == 3


# --- fleet size, noise, reproducibility ------------------------------------------------------------


def test_vehicles_cycle_when_passes_exceed_vehicles(tmp_path):
    res = driveby("road-hc", "--passes", "7", "--vehicles", "3", "--nominal", "true", "--out", str(tmp_path))
    assert res.returncode == 0, res.stderr
    truth = json.loads((tmp_path / "truth.json").read_text())
    ids = list(truth["vehicles"])
    assert len(ids) == 3
    logs = load_logs(tmp_path)
    assert [log.meta.vehicle_id for log in logs] == [ids[i % 3] for i in range(7)]
    for log in logs:  # --nominal true: each log carries its own vehicle's parameters
        assert log.meta.nominal_params == pytest.approx(truth["vehicles"][log.meta.vehicle_id])
    assert len({round(p["speed_mps"], 9) for p in truth["passes"]}) == 7  # a new speed each pass


def test_noise_free_channels_invert_to_the_true_profile(tmp_path):
    """--noise 0 and true parameters: the inverse at the 500 Hz log rate (the simulator ran 4× finer,
    so no inverse crime) recovers the truth profile to ~1 % of its std (measured 1.1–1.2 %)."""
    truth = generate(SCENARIOS["road-qc"], tmp_path, seed=SEED, passes=2, noise_pct=0.0, nominal="true",
                     workers=1, progress=False)
    assert truth["noise_pct"] == 0.0
    profile = np.array(truth["profile"]["elevation_m"])
    grid = np.arange(len(profile)) * truth["profile"]["spacing_m"]
    for log in load_logs(tmp_path):
        system = vehicle_from_params("quarter_car", log.meta.nominal_params).system()
        z = np.column_stack([log.channels[ch.name] for ch in system.channels]).astype(float)
        ap = apparent_profile(system, z, log.meta.dt)[:, 0]
        after = slice(build_inverse(system, log.meta.dt).n_warmup, None)
        true = np.interp(log.chainage[after], grid, profile)
        d = ap[after] - true
        d = d - np.polyval(np.polyfit(log.t[after], d, 1), log.t[after])  # unknown start: offset + drift
        assert np.sqrt(np.mean(d**2)) < 0.03 * np.std(true)


def test_noise_is_the_requested_percentage_of_each_channel(tmp_path):
    """Same seed, --noise 0 against --noise 5: the difference is the noise alone."""
    clean = generate(SCENARIOS["road-hc"], tmp_path / "clean", seed=SEED, passes=2, noise_pct=0.0, workers=1,
                     progress=False)
    noisy = generate(SCENARIOS["road-hc"], tmp_path / "noisy", seed=SEED, passes=2, noise_pct=5.0, workers=1,
                     progress=False)
    assert clean["passes"] == noisy["passes"]
    for a, b in zip(load_logs(tmp_path / "clean"), load_logs(tmp_path / "noisy")):
        np.testing.assert_array_equal(a.chainage, b.chainage)
        for ch in a.channels:
            signal = a.channels[ch].astype(float)
            noise = b.channels[ch].astype(float) - signal
            # ~2600 samples: the sample std is within ~4 % (3 sd) of the true one
            assert np.std(noise) / np.std(signal) == pytest.approx(0.05, rel=0.06)


def test_same_seed_reproduces_identical_logs_and_a_different_seed_differs(tmp_path):
    kw = dict(passes=2, workers=1, progress=False)
    t1 = generate(SCENARIOS["road-hc"], tmp_path / "a", seed=5, **kw)
    t2 = generate(SCENARIOS["road-hc"], tmp_path / "b", seed=5, **kw)
    t3 = generate(SCENARIOS["road-hc"], tmp_path / "c", seed=6, **kw)
    assert t1 == t2
    assert_same_logs(load_logs(tmp_path / "a"), load_logs(tmp_path / "b"))
    assert t3["profile"]["elevation_m"] != t1["profile"]["elevation_m"]
    for la, lc in zip(load_logs(tmp_path / "a"), load_logs(tmp_path / "c")):
        n = min(len(la), len(lc))
        assert not np.array_equal(la.channels["body_acc"][:n], lc.channels["body_acc"][:n])


def test_parallel_workers_write_the_same_logs_as_one(tmp_path):
    kw = dict(seed=SEED, passes=3, progress=False)
    t1 = generate(SCENARIOS["road-hc"], tmp_path / "one", workers=1, **kw)
    t2 = generate(SCENARIOS["road-hc"], tmp_path / "two", workers=2, **kw)
    assert t1 == t2
    assert_same_logs(load_logs(tmp_path / "one"), load_logs(tmp_path / "two"))


def test_regenerating_into_a_directory_replaces_its_logs(tmp_path):
    generate(SCENARIOS["road-hc"], tmp_path, seed=SEED, passes=3, workers=1, progress=False)
    generate(SCENARIOS["road-hc"], tmp_path, seed=SEED, passes=2, workers=1, progress=False)
    assert len(list_drive_logs(tmp_path / "logs")) == 2


def test_cli_writes_what_generate_writes(tmp_path):
    res = driveby("road-hc", "--passes", "2", "--seed", "4", "--noise", "0.5", "--out", str(tmp_path / "cli"))
    assert res.returncode == 0, res.stderr
    assert "wrote 2 drive logs" in res.stdout
    truth = generate(SCENARIOS["road-hc"], tmp_path / "api", seed=4, passes=2, noise_pct=0.5, workers=1,
                     progress=False)
    assert json.loads((tmp_path / "cli" / "truth.json").read_text()) == truth
    assert_same_logs(load_logs(tmp_path / "cli"), load_logs(tmp_path / "api"))
    assert (tmp_path / "cli" / "site.toml").read_text() == (tmp_path / "api" / "site.toml").read_text()


# --- bad arguments ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "args, mentions",
    [
        (["no-such-scenario", "--out", "{out}"], "no-such-scenario"),
        (["road-qc", "--passes", "0", "--out", "{out}"], "--passes"),
        (["road-qc", "--vehicles", "0", "--out", "{out}"], "--vehicles"),
        (["road-qc"], "--out"),
        (["--out", "{out}"], "SCENARIO"),
        (["road-qc", "--noise", "-1", "--out", "{out}"], "--noise"),
        (["road-qc", "--noise", "100", "--out", "{out}"], "--noise"),
        (["road-qc", "--noise", "nan", "--out", "{out}"], "--noise"),
        (["road-qc", "--seed", "-1", "--out", "{out}"], "--seed"),
    ],
    ids=["unknown-scenario", "passes-0", "vehicles-0", "no-out", "no-scenario", "noise-negative", "noise-100",
         "noise-nan", "seed-negative"],
)
def test_bad_arguments_exit_nonzero_with_one_line_and_write_nothing(tmp_path, args, mentions):
    out = tmp_path / "out"
    res = driveby(*(a.format(out=out) for a in args))
    assert res.returncode != 0
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("driveby sim: ") and mentions in lines[0]
    assert res.stdout == ""
    assert not out.exists()


def test_an_unwritable_out_exits_nonzero_with_one_line(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    res = driveby("road-hc", "--passes", "1", "--out", str(blocker))
    assert res.returncode != 0
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("driveby sim: ") and str(blocker) in lines[0], res.stderr
    assert blocker.read_text() == "not a directory"


def test_the_demo_with_an_unwritable_out_exits_nonzero_with_one_line(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    res = subprocess.run([sys.executable, "-m", "simfleet.cli", "demo", "--out", str(blocker)], capture_output=True,
                         text=True, timeout=600, stdin=subprocess.DEVNULL)  # a cold numba cache on a loaded machine
    assert res.returncode == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0] == f"driveby demo: cannot write to {blocker}: Not a directory", res.stderr
    assert blocker.read_text() == "not a directory"


@pytest.mark.parametrize(
    "kw",
    [dict(passes=0), dict(passes=-2), dict(passes=1.5), dict(vehicles=0), dict(noise_pct=-1.0),
     dict(noise_pct=float("nan")), dict(noise_pct=100.0), dict(nominal="truth")],
    ids=lambda kw: "-".join(f"{k}={v}" for k, v in kw.items()),
)
def test_generate_rejects_bad_values_before_writing(tmp_path, kw):
    with pytest.raises(ValueError):
        generate(SCENARIOS["road-hc"], tmp_path / "out", workers=1, progress=False, **kw)
    assert not (tmp_path / "out").exists()


def test_the_fleet_tables_are_the_thesis_values():
    assert TABLE_4_1["mean"] == {"M": 4450.0, "m": 420.0, "K": 5.0e5, "k": 1.95e6, "c": 2.0e4}
    assert all(TABLE_4_1["std"][k] == pytest.approx(0.1 * v) for k, v in TABLE_4_1["mean"].items())
