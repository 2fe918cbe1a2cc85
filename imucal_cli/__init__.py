"""imucal: calibrate the extrinsics of every lidar on a vehicle from raw IMU signals alone.

The method is Das & Boberg, "IMU-based online multi-lidar calibration without lidar
odometry" (Scania/KTH). See README.md for the conventions and the commands.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("imucal")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.1.0"

__all__ = ["__version__"]
