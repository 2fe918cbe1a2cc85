"""Shared fixtures and helpers: small simulated drives, the shipped data, a lidar's error."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DATA = Path(__file__).resolve().parent / "data"
SAMPLE_DATA = ROOT / "sample_data"
REALDATA = ROOT.parent / "shared" / "realdata"


@pytest.fixture(scope="session")
def short_drive():
    """A 20 s aggressive drive with default noise, two lidars."""
    from imucal_cli.sim import DriveOptions, simulate_drive

    return simulate_drive(DriveOptions(scenario="aggressive", duration_s=20.0, seed=11))


@pytest.fixture(scope="session")
def ideal_drive():
    """A 20 s urban drive with ideal sensors (no noise, biases, jitter, drops or offsets)."""
    from imucal_cli.sim import DriveOptions, simulate_drive

    return simulate_drive(
        DriveOptions(
            scenario="urban",
            duration_s=20.0,
            seed=5,
            noise_scale=0.0,
            time_offsets_s=(0.0,),
            sensors=4,
        )
    )


def log_name(fmt: str, stem: str = "drive") -> str:
    """A log's file (or rosbag2 folder) name in format ``fmt``, by the formats' table."""
    from imucal_cli.io.formats import FORMATS

    return stem + (FORMATS[fmt].suffix or "")


def lidar_error(drive, result, name):
    """A lidar's ``T_base_lidar`` error against the simulated truth (rotation about the base
    axes, rad, then xyz, m) and the reported std of each axis (None without a covariance)."""
    import numpy as np

    mount = next(m for m in drive.mounts if m.name == name)
    T = result.T_base_lidar(name)
    rotation = (mount.T_base_lidar.rotation * T.rotation.inv()).as_rotvec()
    error = np.concatenate([rotation, T.translation - mount.T_base_lidar.translation])
    covariance = result.estimates[name].lidar_covariance(mount.T_imu_lidar)
    return error, None if covariance is None else np.sqrt(np.diag(covariance))


def without_summary(path: Path, out: Path) -> Path:
    """The MCAP file ``path`` with its summary section dropped (as a recorder stopped hard
    leaves it: the footer says there is none), written to ``out``."""
    import struct

    data = path.read_bytes()
    footer = len(data) - 8 - (1 + 8 + 8 + 8 + 4)  # opcode, length, three offsets and a CRC
    (summary_start,) = struct.unpack_from("<Q", data, footer + 9)
    record = struct.pack("<BQQQI", 0x02, 20, 0, 0, 0)
    out.write_bytes(data[:summary_start] + record + data[-8:])
    return out
