"""Shared fixtures: small simulated drives and paths to the shipped data."""

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
