"""The start of a streaming calibration, a pure function of its first samples: each IMU's
units and white noise, each sensor's clock offset from the correlation of ``|w|`` with the
base's (where the drive shows it), and the residuals' noise levels (:func:`boot`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from imucal_cli.core.calibrate import CalibrationOptions
from imucal_cli.core.checks import Check, base_gravity
from imucal_cli.core.moments import noise_density
from imucal_cli.core.resample import Spline, filled, longest_covered
from imucal_cli.core.signals import Lowpass, derivative_noise_variance
from imucal_cli.core.timing import TimeOffset, refine_time_offset, time_offset_shown
from imucal_cli.errors import ImucalError
from imucal_cli.types import GRAVITY_MPS2

#: Degrees per radian: how much larger a gyro's numbers are in deg/s.
DPS = float(np.degrees(1.0))
#: The base's |w| must vary by this much (rad/s std) before a gyro's units can be told.
MIN_UNIT_MOTION_RADPS = 0.005


class UnitsError(ImucalError):
    """An IMU's units cannot be told from its data: names the topic and the config key."""

    def __init__(self, topic: str, key: str, detail: str) -> None:
        self.topic, self.key = topic, key
        super().__init__(f"{topic}: {detail}; set {key} in the config")


@dataclass(frozen=True)
class SensorUnits:
    """What the boot takes of a sensor's setup."""

    options: CalibrationOptions
    gyro_units: str = "auto"  # auto | radps | dps
    accel_units: str = "auto"  # auto | mps2 | g


@dataclass(frozen=True)
class Booted:
    """What the boot found."""

    #: Per IMU, the factors (gyro, accelerometer) that make its samples SI.
    scales: dict[str, tuple[float, float]]
    #: Per IMU, the units converted, in words.
    unit_notes: dict[str, list[str]]
    #: Per IMU, the white-noise densities (gyro, accelerometer) and the median rate (Hz).
    noise: dict[str, tuple[float, float]]
    rates_hz: dict[str, float]
    #: Per sensor, its residual noise per grid sample against the base (gyro, accelerometer).
    sigma: dict[str, tuple[float, float]]
    #: Per sensor, its clock offset as the correlation placed it (None: not estimated).
    time_offsets: dict[str, TimeOffset | None]
    #: Checks of the whole rig, counted in every sensor's status.
    given_checks: tuple[Check, ...]
    #: The noise variance of the base's angular acceleration after the low-pass.
    dw_noise_var: float

    def tau0(self, name: str) -> float:
        offset = self.time_offsets.get(name)
        return offset.tau_s if offset is not None and offset.shown else 0.0


@dataclass(frozen=True)
class Rig:
    """The IMUs the boot reads: the base's name and declared units, each sensor's setup, the
    grid's rate and the calibration's low-pass, and each IMU's (topic, config key) for
    messages."""

    base_name: str
    base_units: tuple[str, str]
    sensors: Mapping[str, SensorUnits]
    rate: float
    lowpass: Lowpass
    labels: Mapping[str, tuple[str, str]]

    def noise_levels(
        self,
        samples: dict[str, tuple[np.ndarray, np.ndarray]],
        scales: dict[str, tuple[float, float]],
    ) -> tuple[dict[str, tuple[float, float]], dict[str, float], dict[str, tuple[float, float]]]:
        """Each IMU's white noise and rate, and each sensor's residual noise per grid sample
        against the base (gyro, accelerometer)."""
        noise, rates = {}, {}
        for name, (t, both) in samples.items():
            rate = 1.0 / (float(np.median(np.diff(t))) * 1e-9)  # the IMU's own, as Spline takes it
            _, uniform = filled((t - t[0]) * 1e-9, both, 1.0 / rate)  # (as a uniform series)
            noise[name] = noise_density(uniform * np.repeat(scales[name], 3), rate)
            rates[name] = rate
        gb, ab = noise[self.base_name]
        sigma = {}
        for name in self.sensors:
            gs, as_ = noise[name]
            sigma[name] = (
                float(np.sqrt((gs**2 + gb**2) * self.rate)),
                float(np.sqrt((as_**2 + ab**2) * self.rate)),
            )
        return noise, rates, sigma

    def _refine_offsets(
        self,
        offsets: dict[str, TimeOffset],
        grid: np.ndarray,
        splines: dict[str, Spline],
        speeds: dict[str, np.ndarray],
        scales: dict[str, tuple[float, float]],
    ) -> None:
        """Each placed offset refined below the grid's step, by the sensor's own spline: the
        one minimising the squared difference of the two ``|w|`` (:func:`refine_time_offset`)."""
        base_speed = speeds[self.base_name] - speeds[self.base_name].mean()
        for name, found in offsets.items():
            if not found.shown:
                continue

            def misfit(
                tau: float, spline: Spline = splines[name], k: float = scales[name][0]
            ) -> float:
                speed = k * np.linalg.norm(self.lowpass(spline.gyro(grid + tau)), axis=1)
                return -float(np.sum((speed - speed.mean() - base_speed) ** 2))

            tau = refine_time_offset(found.tau_s, 1.0 / self.rate, misfit)
            offsets[name] = replace(found, tau_s=tau)

    def clock_offsets(
        self,
        grid: np.ndarray,
        speeds: dict[str, np.ndarray],
        sigma: dict[str, tuple[float, float]],
        splines: dict[str, Spline],
        scales: dict[str, tuple[float, float]],
    ) -> dict[str, TimeOffset]:
        """Each sensor's clock offset from the correlation of ``|w|`` with the base's, refined
        by its own spline (:meth:`_refine_offsets`)."""
        offsets = {}
        gain = self.lowpass.white_noise_gain()
        for name, setup in self.sensors.items():
            if setup.options.max_time_offset_s > 0:
                offsets[name] = time_offset_shown(
                    grid,
                    speeds[self.base_name],
                    speeds[name],
                    setup.options.max_time_offset_s,
                    sigma[name][0],
                    gain,
                )
        self._refine_offsets(offsets, grid, splines, speeds, scales)
        return offsets

    def _label(self, name: str, key: str) -> tuple[str, str]:
        topic, path = self.labels.get(name, ("", ""))
        return topic or name, f"{path or name}.{key}"

    def _accel_scale(
        self, name: str, both: np.ndarray, accel_units: str, notes: dict[str, list[str]]
    ) -> float:
        """The factor that makes an accelerometer's samples m/s^2: as declared, or (``auto``)
        by its mean ``|f|``, about 1 for g and 9.8 for m/s^2."""
        if accel_units != "auto":
            return GRAVITY_MPS2 if accel_units == "g" else 1.0
        mean = float(np.mean(np.linalg.norm(both[:, 3:], axis=1)))
        if 0.5 <= mean <= 2.0:
            notes.setdefault(name, []).append(
                f"accelerometer publishes g (mean |f| {mean:.3f}): converted to m/s^2"
            )
            return GRAVITY_MPS2
        if not 5.0 <= mean <= 20.0:
            raise UnitsError(
                *self._label(name, "accel_units"),
                f"the accelerometer's mean |f| is {mean:.3g}: neither m/s^2 (about 9.8) "
                "nor g (about 1)",
            )
        return 1.0

    def units(
        self,
        samples: dict[str, tuple[np.ndarray, np.ndarray]],
        speeds: dict[str, np.ndarray],
        notes: dict[str, list[str]],
        final: bool,
    ) -> dict[str, tuple[float, float]] | None:
        """Per IMU, the factors (gyro, accelerometer) that make its samples SI: as its setup
        says, or, for ``auto``, an accelerometer whose ``|f|`` averages about 1 publishes g and
        a gyro whose ``|w|`` varies 57.3 times as much as the base's (or the base's as much as
        a sensor's / 57.3) publishes deg/s. None while the base has not moved enough to tell."""
        units = {
            self.base_name: self.base_units,
            **{name: (s.gyro_units, s.accel_units) for name, s in self.sensors.items()},
        }
        scales: dict[str, list[float]] = {}
        for name, (gyro_units, accel_units) in units.items():
            accel = self._accel_scale(name, samples[name][1], accel_units, notes)
            scales[name] = [{"dps": np.radians(1.0)}.get(gyro_units, 1.0), accel]
        auto = [name for name, (gyro_units, _) in units.items() if gyro_units == "auto"]
        spread = {name: float(np.std(speed)) * scales[name][0] for name, speed in speeds.items()}
        moving = spread[self.base_name] >= MIN_UNIT_MOTION_RADPS
        if auto and not moving and not final:
            return None
        if auto and moving:  # (never moving: taken as declared)
            ratios = {name: spread[name] / spread[self.base_name] for name in self.sensors}
            if self.base_name in auto and any(
                abs(np.log(r * DPS)) < np.log(2.0) for r in ratios.values()
            ):
                scales[self.base_name][0] = np.radians(1.0)
                notes.setdefault(self.base_name, []).append(
                    "gyro publishes deg/s (the sensors' |w| varies 57.3 times less): converted to "
                    "rad/s"
                )
                ratios = {name: r * DPS for name, r in ratios.items()}
            for name, ratio in ratios.items():
                if name not in auto:
                    continue
                if abs(np.log(ratio / DPS)) < np.log(2.0):
                    scales[name][0] = np.radians(1.0)
                    notes.setdefault(name, []).append(
                        f"gyro publishes deg/s (|w| varies {ratio:.1f} times the base's): "
                        "converted to rad/s"
                    )
                elif abs(np.log(ratio)) >= np.log(2.0):
                    raise UnitsError(
                        *self._label(name, "gyro_units"),
                        f"the gyro's |w| varies {ratio:.3g} times the base's: neither rad/s (1) "
                        "nor deg/s (57.3)",
                    )
        return {name: (g, a) for name, (g, a) in scales.items()}


def boot(
    rig: Rig,
    samples: dict[str, tuple[np.ndarray, np.ndarray]],
    seconds: dict[str, np.ndarray],
    grid: np.ndarray,
    patient: bool,
) -> Booted | None:
    """The boot on ``samples`` (per IMU, stamps in ns and ``[gyro, accel]`` as published;
    ``seconds``: the stamps on the grid's clock) over ``grid``; None where it waits for more
    data (``patient``: for the motion that tells the gyros' units and places every clock
    offset)."""
    notes: dict[str, list[str]] = {}
    splines = {  # the gyros': the boot reads only |w| (half the work of both triads)
        n: Spline(seconds[n], b[:, :3], rig.rate) for n, (_, b) in samples.items()
    }
    grid = longest_covered(grid, [s.covered(grid) for s in splines.values()], rig.lowpass.pad)
    if len(grid) < rig.lowpass.pad:
        return None  # no stretch that every IMU covers yet
    raw_speeds = {
        name: np.linalg.norm(rig.lowpass(spline.gyro(grid)), axis=1)
        for name, spline in splines.items()
    }
    scales = rig.units(samples, raw_speeds, notes, final=not patient)
    if scales is None:
        return None  # not enough motion yet to tell the gyros' units
    speeds = {name: raw_speeds[name] * scales[name][0] for name in samples}  # |w| scales
    noise, rates, sigma = rig.noise_levels(samples, scales)
    offsets = rig.clock_offsets(grid, speeds, sigma, splines, scales)
    if patient and not all(o.shown for o in offsets.values()):
        return None  # not enough motion yet to place every clock offset
    # the base's mean specific force over the boot, in B's axes (turned as it came)
    base_f = (samples[rig.base_name][1][:, 3:] * scales[rig.base_name][1]).mean(axis=0)
    return Booted(
        scales,
        notes,
        noise,
        rates,
        sigma,
        {name: offsets.get(name) for name in rig.sensors},
        (base_gravity(base_f),),
        derivative_noise_variance(rig.lowpass, noise[rig.base_name][0]),
    )
