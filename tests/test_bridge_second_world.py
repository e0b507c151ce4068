"""Bridge damage on the second (ivp) world: a crack found, located and alarmed; bearings whose D1/D2 mean
something.

The ivp world (``simfleet/worlds/``) simulates the bridge independently of the estimators' design
world: a Rayleigh–Ritz modal beam whose crack is a continuous triangle of lost E·I (not element
values), RK4 at 20 kHz, the logger's anti-alias FIR and resampling, vehicles drawn from the class
prior, logs that start mid-motion, a speed that wobbles within each pass (here an exact odometer).
Its passes go through the edge and cloud cores in process with fleet self-calibration; the bridge
estimator (``cloud/bridge/``, what these tests check) runs on every call. No truth reaches the
estimator; it is read here only to score. The simulated, calibrated passes are kept between
sessions (``tests/bridge_cache.py``).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import pickle
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from cloud.daemon.settings import CloudSettings
from shared.drivelog import DriveLog, list_drive_logs, read_drive_log
from shared.registry import load_site
from simfleet.harness import run_in_process
from simfleet.reproduce_bridge import Case, estimate_case
from simfleet.scenarios import SCENARIOS
from simfleet.worlds import ivp

from tests.bridge_cache import kept

EXACT_ODOMETER = ivp.WorldSettings(speed_error_sd=0.0)


def _delayed(log: DriveLog, samples: int) -> DriveLog:
    """The log as a logger whose filter delays every channel by ``samples`` against its time stamps
    (and so against the chainage) would write it: what the second world's logger compensates."""
    ch = {n: np.concatenate([np.full(samples, v[0]), v[:-samples]]).astype(np.float32)
          for n, v in log.channels.items()}
    return dataclasses.replace(log, channels=ch)


def _simulated(name: str, passes: int, seed: int) -> Path:
    """The case's simulated passes, made once for every variant of its logs."""
    return kept(f"ivp-{name}-{passes}-s{seed}-sim", lambda d: ivp.generate(
        SCENARIOS[name], d, seed=seed, passes=passes, noise_pct=2.0, progress=False, workers=1,
        settings=EXACT_ODOMETER))


def _make(name: str, passes: int, seed: int, delay_samples: int) -> Callable:
    def make(d: Path) -> None:
        t0 = time.perf_counter()
        sim = _simulated(name, passes, seed)
        logs = [read_drive_log(p) for p in list_drive_logs(sim / "logs")]
        if delay_samples:
            logs = [_delayed(lg, delay_samples) for lg in logs]
        site = load_site(sim / "site.toml")
        cloud, rounds = run_in_process(logs, site, None, CloudSettings(calibration="fleet"))
        params = {v: dict(st.params) for v, st in cloud.calibrator.vehicles.items()}
        case = Case(name, seed, passes, sim, site, json.loads((sim / "truth.json").read_text()),
                    list(cloud.aggregator.held.values()), params, rounds, time.perf_counter() - t0)
        (d / "case.pkl").write_bytes(pickle.dumps(case))
    return make


@functools.lru_cache(maxsize=None)
def estimate(name: str, passes: int, seed: int = 0, delay_samples: int = 0):
    tag = f"-delay{delay_samples}" if delay_samples else ""
    d = kept(f"ivp-{name}-{passes}-s{seed}{tag}", _make(name, passes, seed, delay_samples))
    case = pickle.loads((d / "case.pkl").read_bytes())
    e, _ = estimate_case(case)
    return e, np.asarray(case.truth["bridge"]["stiffness_ratio"])


def test_a_crack_is_located_measured_and_alarmed():
    """φ = 10 % at 10 m on a smooth deck (elements 10–11 at 0.819 of design, 9 and 12 at 0.977: the
    modal beam's element truth is the mean of its continuous E·I over each element), 50 passes:
    the weakest element within one element of the crack and its 95 % interval holding the truth
    (its loss within 5 points is the issue's goal at 300 passes; at 50 it reads 5 points off), the
    alarm raised, and the crack hypothesis placing it on the right element with a loss interval
    that holds the truth."""
    _crack_found(*estimate("bridge-crack10-10m", 50))


def test_a_crack_behind_a_logger_delay_is_located_measured_and_alarmed():
    """The same passes from a logger whose anti-alias filter delays the acceleration by 18 ms (9
    samples) against its time stamps, uncompensated: each pass's deflection lies speed × 18 ms
    (0.27–0.40 m) after its chainage. Left there, the crack read 44 % [35, 53] deep at 100 passes
    (truth 18 %) with elements ringing 0.68–1.30; the registration reads the delay from how the
    passes' shifts grow with speed and takes it out, so the same holds as without the delay."""
    _crack_found(*estimate("bridge-crack10-10m", 50, delay_samples=9))


def _crack_found(e, truth: np.ndarray) -> None:
    ratio = e.posterior.stiffness_ratio
    lo, hi = e.posterior.ei_lo95 / e.posterior.ei_design, e.posterior.ei_hi95 / e.posterior.ei_design
    weakest = int(np.argmin(ratio))
    a = e.assessment
    print(f"elements {np.round(ratio, 3).tolist()}; weakest {weakest + 1} [{lo[weakest]:.3f}, {hi[weakest]:.3f}]; "
          f"assessment {a.best} element {a.element} loss {a.severity:.3f} [{a.severity_lo95:.3f}, "
          f"{a.severity_hi95:.3f}] P {a.loss_probability:.3f}")
    assert weakest + 1 in (9, 10, 11, 12), weakest + 1
    assert lo[weakest] <= truth[weakest] <= hi[weakest], (lo[weakest], ratio[weakest], hi[weakest], truth[weakest])
    assert a.alarm and a.kind == "crack" and a.element in (10, 11), (a.kind, a.element)
    assert a.severity_lo95 <= 1.0 - truth.min() <= a.severity_hi95, (a.severity_lo95, a.severity_hi95)


def test_seized_bearings_read_their_beam_and_d1_d2_the_beams_loss():
    """Bearings Krot = 1e10 on a healthy beam, 30 passes: the bearings found (the hypothesis and the
    Krot interval), no alarm, the beam's mean stiffness within 3 points, and D1/D2 — a loss of
    flexural rigidity — reading the beam's loss as the elements do: against the pinned design span
    they read the restraint as a ~110 % stiffness gain."""
    e, truth = estimate("bearing-1e10", 30)
    (k, lo, hi), _ = e.posterior.krot
    mean = float(np.mean(e.posterior.stiffness_ratio))
    print(f"log10 Krot {k:.3f} [{lo:.3f}, {hi:.3f}], mean ratio {mean:.4f}, D1 {e.indicators.D1_pct:.2f} %, "
          f"D2 {e.indicators.D2_pct:.2f} %")
    assert e.assessment.best == "bearings" and not e.assessment.alarm
    assert lo <= 10.0 <= hi
    # The beam/bearing split is the weakly identified ridge (cloud/bridge/bearings.py): the mean
    # ratio's own 95 % interval spans several points at 30 passes; 3 points is the goal's 2 plus the
    # as-built tolerance prior's pull.
    assert abs(mean - 1.0) < 0.03, mean
    for d in (e.indicators.D1_pct, e.indicators.D2_pct):
        # D reads the beam's loss on the bearings found, as the elements do: the same number but for
        # how the mid-span ordinate and the area weigh the elements (a point here)
        assert abs(d - 100 * (1.0 - mean)) < 1.0, (e.indicators, mean)
