"""The vehicle and IMU simulator behind ``imucal simulate``: ground truth for every test."""

from imucal_cli.sim.drive import BASE_TOPIC, DriveOptions, SimulatedDrive, simulate_drive
from imucal_cli.sim.scenarios import SCENARIOS, make_scenario

__all__ = ["BASE_TOPIC", "SCENARIOS", "DriveOptions", "SimulatedDrive", "make_scenario", "simulate_drive"]
