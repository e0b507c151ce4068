"""The simulated worlds of ``driveby sim``: routes, bridges, fleets and sensor errors."""

from __future__ import annotations

import dataclasses

import numpy as np

from shared.vehicles.half_car import TABLE_2_1

#: Table 4.1 (quarter-car fleet): mean and standard deviation of each parameter.
TABLE_4_1 = {
    "mean": {"M": 4450.0, "m": 420.0, "K": 5.0e5, "k": 1.95e6, "c": 2.0e4},
    "std": {"M": 445.0, "m": 42.0, "K": 5.0e4, "k": 1.95e5, "c": 2.0e3},
}

#: Table 2.4 (half-car fleet of six vehicles).
TABLE_2_4 = [
    dict(Is=89415, ms=15499, mu1=783, mu2=1035, Ks1=384005, Ks2=1119084, Kt1=1733740, Kt2=3257879, Cs1=8944, Cs2=15659),
    dict(Is=77891, ms=13502, mu1=697, mu2=1340, Ks1=427600, Ks2=879754, Kt1=1608501, Kt2=3800299, Cs1=11415, Cs2=19882),
    dict(Is=94629, ms=16403, mu1=723, mu2=1085, Ks1=432625, Ks2=998021, Kt1=1800050, Kt2=3938900, Cs1=9195, Cs2=17979),
    dict(Is=96146, ms=16666, mu1=712, mu2=1113, Ks1=428476, Ks2=984328, Kt1=1522849, Kt2=2942195, Cs1=10529, Cs2=21229),
    dict(Is=82743, ms=14343, mu1=687, mu2=1217, Ks1=451610, Ks2=839591, Kt1=1871435, Kt2=2995662, Cs1=10219, Cs2=21015),
    dict(Is=104587, ms=18129, mu1=751, mu2=1107, Ks1=426744, Ks2=1025730, Kt1=2026006, Kt2=3699902, Cs1=9078, Cs2=23385),
]
for _v in TABLE_2_4:
    _v.update(D1=2.375, D2=2.375)


@dataclasses.dataclass(frozen=True)
class BridgeSpec:
    """A bridge on the route and its true condition (the registry only learns the design values)."""

    start_m: float = 100.0
    span_m: float = 20.0
    n_elements: int = 20
    E_pa: float = 35e9
    I_m4: float = 1.25
    mass_per_m: float = 37500.0
    depth_m: float = 1.0
    damping_ratio: float = 0.03
    krot_nm_per_rad: float | None = None  # None: simply supported
    crack_x_m: float | None = None
    crack_phi: float = 0.0
    global_loss: float = 0.0

    @property
    def supports(self) -> str:
        return "simply_supported" if self.krot_nm_per_rad is None else "rotational_springs"


@dataclasses.dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    vehicle_model: str = "quarter_car"
    fleet: str = "table_4_1"  # how vehicles are drawn: table_4_1 | table_2_4
    n_vehicles: int = 30
    n_passes: int | None = None  # default: one pass per vehicle
    route_length_m: float = 200.0
    road_class: str = "A"
    noise_pct: float = 2.0
    bridge: BridgeSpec | None = None
    rough_deck: bool = False
    carpet: bool = False
    gnss_bias_sd_m: float = 0.0
    gnss_jitter_sd_m: float = 0.0
    speed_error_sd: float = 0.0
    speed_range_mps: tuple[float, float] = (15.0, 22.0)
    sample_rate_hz: float = 500.0

    @property
    def passes(self) -> int:
        return self.n_passes if self.n_passes is not None else self.n_vehicles


def _bridge_scenarios() -> list[Scenario]:
    base = dict(route_length_m=140.0)
    specs = {
        "bridge-healthy": ("healthy 20 m span", BridgeSpec()),
        "bridge-crack10-10m": ("crack phi=10 % at 10 m", BridgeSpec(crack_x_m=10.0, crack_phi=0.10)),
        "bridge-crack10-14m": ("crack phi=10 % at 14 m", BridgeSpec(crack_x_m=14.0, crack_phi=0.10)),
        "bridge-crack5-10m": ("crack phi=5 % at 10 m", BridgeSpec(crack_x_m=10.0, crack_phi=0.05)),
        "bridge-crack5-14m": ("crack phi=5 % at 14 m", BridgeSpec(crack_x_m=14.0, crack_phi=0.05)),
        "bridge-global5": ("uniform 5 % stiffness loss", BridgeSpec(global_loss=0.05)),
        "bridge-global10": ("uniform 10 % stiffness loss", BridgeSpec(global_loss=0.10)),
        "bearing-1e9": ("rotational-spring bearings Krot=1e9 N·m/rad", BridgeSpec(krot_nm_per_rad=1e9)),
        "bearing-1e10": ("rotational-spring bearings Krot=1e10 N·m/rad", BridgeSpec(krot_nm_per_rad=1e10)),
        "bearing-1e12": ("rotational-spring bearings Krot=1e12 N·m/rad", BridgeSpec(krot_nm_per_rad=1e12)),
    }
    out = []
    for name, (what, spec) in specs.items():
        common = "30 quarter-cars, 100 m approach, 20 m bridge (§4.2), 20 m exit, 2 % noise"
        out.append(Scenario(name, f"{what}; {common}, smooth deck", bridge=spec, **base))
        out.append(Scenario(f"{name}-rough", f"{what}; {common}, road profile continues over the deck",
                            bridge=spec, rough_deck=True, **base))
    return out


#: ``driveby demo``'s world: a crack its 30-pass fleet finds and locates (simfleet/demo.py says why
#: this one), and the same span healthy for its false-alarm check (same seed: same fleet and road).
DEMO_SCENARIO = "demo-crack20-14m"
DEMO_HEALTHY = "demo-healthy"


def _demo_scenarios() -> list[Scenario]:
    return [Scenario(DEMO_SCENARIO, "crack phi = 20 % at 14 m (elements 14–15 lose 33 %), smooth deck",
                     bridge=BridgeSpec(crack_x_m=14.0, crack_phi=0.20), route_length_m=140.0),
            Scenario(DEMO_HEALTHY, "healthy span, smooth deck", bridge=BridgeSpec(), route_length_m=140.0)]


SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in [
        Scenario("road-qc", "30 quarter-cars (Table 4.1), 200 m class A road, 2 % noise"),
        Scenario("road-hc", "6 half-cars (Table 2.4), 100 m class A road, 1 % noise", vehicle_model="half_car",
                 fleet="table_2_4", n_vehicles=6, route_length_m=100.0, noise_pct=1.0),
        Scenario("road-qc-gnss", "road-qc with GNSS chainage bias (sd 2 m) and 2 % speed error",
                 gnss_bias_sd_m=2.0, gnss_jitter_sd_m=0.05, speed_error_sd=0.02),
        Scenario("carpet", "road-qc on a 3-D carpet of 11 correlated lanes, lane drawn per pass", carpet=True),
        *_bridge_scenarios(),
        *_demo_scenarios(),
        Scenario("fleet-large", "300 quarter-cars on bridge-crack5-10m (smooth deck)", n_vehicles=300,
                 route_length_m=140.0, bridge=BridgeSpec(crack_x_m=10.0, crack_phi=0.05)),
    ]
}


def draw_fleet(scenario: Scenario, n_vehicles: int, rng: np.random.Generator) -> list[dict[str, float]]:
    """True parameters of each vehicle of the fleet."""
    if scenario.fleet == "table_4_1":
        mean, std = TABLE_4_1["mean"], TABLE_4_1["std"]
        fleet = []
        for _ in range(n_vehicles):
            # Normal draws as the thesis; clipped at 3 sd so that no vehicle has a non-physical value.
            fleet.append({k: float(mean[k] + std[k] * np.clip(rng.standard_normal(), -3, 3)) for k in mean})
        return fleet
    if scenario.fleet == "table_2_4":
        table = [dict((k, float(v)) for k, v in row.items()) for row in TABLE_2_4]
        mean, std = fleet_class(scenario)
        extra = [{k: float(mean[k] + std[k] * np.clip(rng.standard_normal(), -3, 3)) for k in mean}
                 for _ in range(max(n_vehicles - len(table), 0))]
        return (table + extra)[:n_vehicles]
    raise ValueError(f"unknown fleet {scenario.fleet!r}")


def fleet_class(scenario: Scenario) -> tuple[dict[str, float], dict[str, float]]:
    """The vehicle-class prior (mean, std) that the site registry declares for the fleet."""
    if scenario.fleet == "table_4_1":
        return dict(TABLE_4_1["mean"]), dict(TABLE_4_1["std"])
    rows = [dict((k, float(v)) for k, v in row.items()) for row in TABLE_2_4]
    mean = {k: float(np.mean([r[k] for r in rows])) for k in TABLE_2_1}
    # Axle positions are nearly fixed by design; everything else varies ~10 % across a class.
    std = {k: (0.02 if k in ("D1", "D2") else 0.10) * mean[k] for k in mean}
    return mean, std


# Rail worlds (one instrumented carriage, batches of runs): simfleet.rail.
from .rail import rail_scenarios  # noqa: E402

SCENARIOS.update(rail_scenarios())

# Network worlds (whole drives over routes with coordinates): simfleet.network.
from .network import network_scenarios  # noqa: E402

SCENARIOS.update(network_scenarios(TABLE_4_1))
