"""imucal: calibrate the extrinsics of every lidar on a vehicle from raw IMU signals alone.

The method is Das & Boberg, "IMU-based online multi-lidar calibration without lidar
odometry" (Scania/KTH). See README.md for the conventions and the commands, and
:mod:`imucal_cli.api` for the functions below.
"""

__all__ = [
    "Calibration",
    "__version__",
    "biases",
    "calibrate",
    "calibrate_streams",
    "evaluate",
    "export",
    "follow",
    "load_config",
    "segments",
    "write_document",
    "write_report",
]


def __getattr__(name: str):
    if name == "__version__":
        from imucal_cli.version import version

        globals()["__version__"] = version()
        return globals()["__version__"]
    if name in __all__:
        from imucal_cli import api

        return getattr(api, name)
    raise AttributeError(f"module 'imucal_cli' has no attribute {name!r}")
