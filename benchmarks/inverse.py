"""Inverse Newmark-β throughput: samples per second per core, against real time and a plain loop.

* ``inverse.<model>.one_stream``: one vehicle, the whole record in one update (kernel throughput);
  models: sprung mass, quarter-car, half-car, bogie half-car and the 4-axle carriage (whose samples
  are four channels in, the AP under four wheels out);
* ``inverse.quarter_car.one_stream_1s_chunks``: the same fed one second (500 samples) at a time,
  as an edge node receives it (adds the per-update overhead);
* ``inverse.quarter_car.bank_<S>_streams``: S quarter-cars with different parameters interleaved
  in one kernel call, fed one second at a time; samples counted over all streams.

Streams are built and started before timing (steady state); each figure is the best of a few
repeats after a warm-up. Ratios: to the 500 Hz real-time rate (how many vehicles one core keeps
up with) and to the literal per-sample Python loops of ``tests/naive.py``, timed on fewer samples
in the same run.
"""

from __future__ import annotations

import logging
import time
from typing import Callable, Iterator

import numpy as np

from shared.dynamics.forward import simulate_on_profile
from shared.dynamics.inverse import InverseBank, InverseStream, build_inverse
from shared.vehicles import HalfCar, QuarterCar, SprungMass
from shared.vehicles.bogie import table_3_2
from shared.vehicles.carriage import table_3_1
from shared.vehicles.half_car import TABLE_2_1

log = logging.getLogger(__name__)

RATE_HZ = 500.0
DT = 1.0 / RATE_HZ
CHUNK = 500  # samples per update: one second of data

VEHICLES = {
    "sprung_mass": SprungMass(m=15000.0, k=3.5e6),
    "quarter_car": QuarterCar(M=4450.0, m=420.0, K=5e5, k=1.95e6, c=2e4),
    "half_car": HalfCar(**TABLE_2_1),
    "bogie_half_car": table_3_2(),
    "carriage": table_3_1(),  # 6 DOF, four channels in, AP under four wheels out (App. B.2)
}


def best_time(fn: Callable[[], object], repeats: int = 15) -> float:
    """Best wall time of ``repeats`` calls, s, after one warm-up call (numba compile, caches)."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def measured_channels(vehicle, n_samples: int) -> np.ndarray:
    """Channels of a simulated 20 s drive at 20 m/s over a two-tone road, repeated to ``n_samples``."""

    def elevation(x):
        return 0.005 * np.sin(2 * np.pi * x / 9.0) + 0.002 * np.sin(2 * np.pi * x / 1.7)

    def slope(x):
        return 0.005 * 2 * np.pi / 9.0 * np.cos(2 * np.pi * x / 9.0) + 0.002 * 2 * np.pi / 1.7 * np.cos(
            2 * np.pi * x / 1.7
        )

    channels = simulate_on_profile(vehicle.system(), elevation, slope, 0.0, 20.0, 20.0, DT).channels
    return np.resize(channels, (n_samples, channels.shape[1]))


def feeder(target, z: np.ndarray, chunk: int) -> Callable[[], None]:
    """A callable feeding ``z`` to a started stream or bank, ``chunk`` samples per update."""
    target.update(z[:1])  # the first sample sets the initial state: kept out of the timing

    def feed():
        for k in range(0, len(z), chunk):
            target.update(z[k : k + chunk])

    return feed


def plain_loop_rate(name: str, vehicle, z: np.ndarray) -> float | None:
    """Samples/s of the literal Python loop of tests/naive.py (None when tests is not importable)."""
    try:
        from tests import naive  # optional: importable only from the repository root
    except ImportError:
        log.warning("tests.naive is not importable (run from the repository root): no plain_loop ratio")
        return None
    system = vehicle.system()
    n, nc = system.n_dof, system.n_contacts
    initial = (np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(nc), np.zeros(nc))
    p = vehicle.params()
    loops = {
        "sprung_mass": lambda: naive.sprung_mass_inverse(p["m"], p["k"], z[:, 0], DT, initial[:3]),
        "quarter_car": lambda: naive.quarter_car_inverse(*p.values(), z[:, 0], DT, initial[:3]),
        "half_car": lambda: naive.half_car_inverse(*p.values(), z[:, 0], z[:, 1], DT, initial[:3]),
        "bogie_half_car": lambda: naive.bogie_half_car_inverse(vehicle, z, DT, initial),
        "carriage": lambda: naive.generic_inverse(system, z, DT, initial),
    }
    return len(z) / best_time(loops[name], repeats=3)


def result(name: str, rate: float, plain: float | None) -> dict:
    ratios = {"realtime_500hz": rate / RATE_HZ}
    if plain is not None:
        ratios["plain_loop"] = rate / plain
    return {"name": name, "value": rate, "unit": "samples/s", "ratio_to": ratios}


def run(n_samples: int = 2_000_000, n_streams: int = 256, n_plain: int = 5_000) -> Iterator[dict]:
    """One stream of each model, then a bank of ``n_streams`` quarter-cars (samples/s per core)."""
    plain = {}
    for name, vehicle in VEHICLES.items():
        z = measured_channels(vehicle, n_samples)
        plain[name] = plain_loop_rate(name, vehicle, z[:n_plain])
        model = build_inverse(vehicle.system(), DT)
        rate = n_samples / best_time(feeder(InverseStream(model), z, n_samples))
        yield result(f"inverse.{name}.one_stream", rate, plain[name])
        if name == "quarter_car":
            rate = n_samples / best_time(feeder(InverseStream(model), z, CHUNK))
            yield result(f"inverse.{name}.one_stream_1s_chunks", rate, plain[name])
    base = VEHICLES["quarter_car"]
    rng = np.random.default_rng(0)
    models = [
        build_inverse(base.replace(**{k: v * rng.uniform(0.9, 1.1) for k, v in base.params().items()}).system(), DT)
        for _ in range(n_streams)
    ]
    per_stream = max(n_samples // n_streams, CHUNK)
    z1 = measured_channels(base, per_stream + n_streams)
    z = np.stack([z1[q : q + per_stream] for q in range(n_streams)], axis=-1)  # staggered starts
    rate = per_stream * n_streams / best_time(feeder(InverseBank(models), z, CHUNK))
    yield result(f"inverse.quarter_car.bank_{n_streams}_streams", rate, plain["quarter_car"])
