"""Vehicle models: validated parameter sets and their linear systems."""

from .base import GRAVITY, Channel, Vehicle, VehicleSystem
from .bogie import BogieHalfCar
from .carriage import Carriage
from .half_car import HalfCar
from .quarter_car import QuarterCar
from .sprung_mass import SprungMass

#: interfaces.md §1 ``vehicle_model`` → parameter class.
MODELS: dict[str, type[Vehicle]] = {
    cls.model: cls for cls in (SprungMass, QuarterCar, HalfCar, BogieHalfCar, Carriage)
}

#: Vehicle models whose passes are train runs: the cloud re-runs their dynamics over the whole record
#: (a batch calibration of each run's properties) instead of fusing the edge's AP pass by pass.
RAIL_MODELS = frozenset({"carriage", "bogie_half_car"})


def vehicle_from_params(model: str, params: dict[str, float]) -> Vehicle:
    """The vehicle of ``model`` with ``params``; unknown model or bad parameters raise ValueError."""
    try:
        cls = MODELS[model]
    except KeyError:
        raise ValueError(f"vehicle_model: unknown model {model!r} (known: {', '.join(sorted(MODELS))})") from None
    return cls.from_params(params)


__all__ = ["GRAVITY", "Channel", "Vehicle", "VehicleSystem", "SprungMass", "QuarterCar", "HalfCar",
           "BogieHalfCar", "Carriage", "MODELS", "vehicle_from_params"]
