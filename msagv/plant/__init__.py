"""Vehicle plant: tire and wear models, n-axle swerve dynamics, and the stepping plant.

Imports nothing of the project's other packages (no transport, no controller).
"""

from .vehicle import (Vehicle, VehicleError, default_vehicle, load_vehicle, n_axle_vehicle,
                      vehicle_from_dict)
from .interface import PlantError, PlantInterface
from .signals import input_names, signal_names, state_names
from .stepping import Plant, PlantSnapshot

__all__ = [
    "Vehicle", "VehicleError", "default_vehicle", "load_vehicle", "n_axle_vehicle",
    "vehicle_from_dict", "Plant", "PlantError", "PlantSnapshot", "input_names",
    "signal_names", "state_names", "PlantInterface",
]
