"""What a calibration run found: the one typed outcome every document, table and figure is
made from (:func:`imucal_cli.api.calibrate`, ``follow``, ``batch`` and the CLI alike)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from imucal_cli.config import Config
    from imucal_cli.core.calibrate import SensorEstimate
    from imucal_cli.core.segments import WindowInfo
    from imucal_cli.io.base import Loss
    from imucal_cli.types import Transform


@dataclass(frozen=True)
class Reading:
    """What reading a log found."""

    log: Path
    format_name: str
    #: Per topic, what reading counted (:class:`~imucal_cli.reading.ReadStats`, the
    #: calibrator's duplicate stamps in).
    counts: Mapping[str, Mapping[str, int]]
    #: Parts of a damaged log that could not be read, and notes on how it was read.
    losses: list[Loss]


@dataclass(frozen=True)
class Calibration:
    """Every sensor's estimate with what the run measured.

    >>> cal = imucal_cli.calibrate("drive.mcap", "vehicle.yaml")     # doctest: +SKIP
    >>> cal.T_base_lidar("front_left_top").as_matrix()               # doctest: +SKIP
    >>> cal.document()["sensors"]["front_left_top"]["status"]        # doctest: +SKIP
    """

    config: Config
    estimates: dict[str, SensorEstimate]
    #: Per sensor, every window's observability (what ``segments`` reports).
    windows: Mapping[str, Sequence[WindowInfo]] = field(default_factory=dict)
    #: The first IMU stamp (ns): the origin of the documents' and the report's times.
    t0_ns: int = 0
    #: The origin of the window grid (ns).
    t_ref_ns: int = 0
    #: Per sensor, its clock offset as the start placed it (s).
    time_offsets_s: Mapping[str, float] = field(default_factory=dict)
    #: Median sample rate of each IMU ("base" and the sensor names), where measured (Hz).
    rates_hz: Mapping[str, float] = field(default_factory=dict)
    #: White-noise density of each IMU's gyro and accelerometer (rad/s/sqrt(Hz), m/s^2/sqrt(Hz)).
    noise_density: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    #: What reading the log found (None: calibrated from streams in memory).
    reading: Reading | None = None
    #: Followed (``calibrate --follow``): the documents say what each sensor still lacks.
    followed: bool = False

    def T_base_lidar(self, name: str) -> Transform:
        return self.estimates[name].T_base_imu * self.config.sensor(name).T_imu_lidar

    @property
    def all_ok(self) -> bool:
        return all(e.status == "ok" for e in self.estimates.values())

    @property
    def log(self) -> Path:
        return self.reading.log if self.reading is not None else Path("<memory>")

    def missing(self, name: str) -> list[str]:
        """The axes of sensor ``name`` not yet within the config's ``stop:`` targets, each with
        the driving that supplies it."""
        from imucal_cli.core.status import missing_axes

        return missing_axes(self.estimates[name], self.config.stop)

    @property
    def converged(self) -> bool:
        """Every sensor ``ok`` and within the config's ``stop:`` targets."""
        return all(e.status == "ok" and not self.missing(n) for n, e in self.estimates.items())

    def document(self) -> dict[str, Any]:
        """The SPEC's calibrate document (what ``imucal calibrate -o`` writes)."""
        from imucal_cli.outputs import calibration_document

        reading = self.reading
        document = calibration_document(
            self,
            str(self.log),
            reading.losses if reading is not None else (),
            reading.counts if reading is not None else None,
        )
        if self.followed:
            for name, sensor in document["sensors"].items():
                sensor["missing"] = self.missing(name)
            document["converged"] = self.converged
        return document

    def follow_line(self, windows: int) -> dict[str, Any]:
        """What ``calibrate --follow --json`` prints after ``windows`` windows."""
        from imucal_cli.outputs import follow_line

        return follow_line(self, windows)

    def segments_document(self, streamed: bool = False) -> dict[str, Any]:
        """The SPEC's segments document (what ``imucal segments -o`` writes); ``streamed``: each
        sensor's windows made as :func:`~imucal_cli.documents.write_document` writes them, a
        chunk at a time (a day-long log's are never held whole)."""
        from imucal_cli.outputs import segments_document

        return segments_document(self, streamed)
