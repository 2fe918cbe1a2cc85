"""The vehicle and IMU simulator behind ``imucal simulate``: ground truth for every test."""

from imucal_cli.sim.drive import (
    BASE_TOPIC,
    ERROR_CLASSES,
    DriveOptions,
    SimulatedDrive,
    simulate_drive,
    with_errors,
)
from imucal_cli.sim.scenarios import SCENARIOS, make_scenario

__all__ = [
    "BASE_TOPIC",
    "ERROR_CLASSES",
    "SCENARIOS",
    "DriveOptions",
    "SimulatedDrive",
    "make_scenario",
    "simulate_drive",
    "with_errors",
]
