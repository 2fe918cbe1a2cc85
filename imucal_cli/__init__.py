"""imucal: calibrate the extrinsics of every lidar on a vehicle from raw IMU signals alone.

The method is Das & Boberg, "IMU-based online multi-lidar calibration without lidar
odometry" (Scania/KTH). See README.md for the conventions and the commands.
"""

__all__ = [
    "__version__",
    "calibrate_log",
    "evaluate",
    "export_extrinsics",
    "load_config",
    "stream_biases",
    "write_document",
    "write_report",
]


def __getattr__(name: str):
    if name == "__version__":
        from imucal_cli.version import version

        globals()["__version__"] = version()
        return globals()["__version__"]
    if name in (
        "calibrate_log",
        "evaluate",
        "export_extrinsics",
        "stream_biases",
        "write_document",
        "write_report",
    ):
        from imucal_cli import api

        return getattr(api, name)
    if name == "load_config":
        from imucal_cli.config import load_config

        return load_config
    raise AttributeError(f"module 'imucal_cli' has no attribute {name!r}")
