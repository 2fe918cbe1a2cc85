"""Drives that a real truck or bus makes, as smooth :class:`Trajectory` objects.

A scenario is a driver program: speed ``v(t)`` and path curvature ``kappa(t)`` as breakpoints
joined by quintic smoothsteps (continuous up to the second derivative). From them:

- yaw rate ``= v * kappa``; planar position by integrating ``v [cos yaw, sin yaw]``;
- road grade (slow, a few per cent) gives elevation and pitch;
- the suspension responds to lateral and longitudinal acceleration with a damped second-order
  system (body rolls out of a turn, dives under braking);
- road bumps at 1-2 Hz excite roll, pitch and heave, scaled with speed (zero at standstill, so
  stops are true rests).

The sampled signals are interpolated with quintic splines (:meth:`Trajectory.from_samples`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import signal
from scipy.integrate import cumulative_trapezoid

from imucal_cli.sim.trajectory import Trajectory

#: Scenario name -> default duration (s). Aggressive and urban match the paper's Seq-1/Seq-2.
SCENARIOS: dict[str, float] = {
    "aggressive": 81.0,
    "urban": 283.0,
    "highway": 120.0,
    "parking": 120.0,
    "stationary": 60.0,
    "wheel": 60.0,
}
#: Road roughness per scenario (scales the bump amplitudes): a test track, city streets, a
#: smooth motorway, a depot yard.
ROAD_ROUGHNESS: dict[str, float] = {
    "aggressive": 1.0,
    "urban": 1.0,
    "highway": 0.3,
    "parking": 0.6,
    "stationary": 0.0,
    "wheel": 0.0,
}
#: The ``wheel`` scenario: B is a car wheel's hub (x along its axle), rolling at up to 8 m/s on
#: a tyre of this radius (m): up to 1,390 deg/s about one axis, as two IMUs on a real car's
#: wheel recorded (1,184 deg/s, 82 m/s^2 at 14 cm).
WHEEL_RADIUS_M = 0.33

GRID_HZ = 50.0  # driver-program sampling before spline interpolation


@dataclass(frozen=True)
class VehicleDynamics:
    """Body motion on the suspension (bus/truck-like)."""

    roll_per_lateral_accel: float = np.radians(0.9)  # rad per m/s^2
    pitch_per_longitudinal_accel: float = np.radians(0.6)  # rad per m/s^2
    natural_frequency_hz: float = 1.3
    damping_ratio: float = 0.45
    bump_roll_rad: float = np.radians(0.25)
    bump_pitch_rad: float = np.radians(0.3)
    bump_heave_m: float = 0.012
    bump_band_hz: tuple[float, float] = (1.0, 2.0)
    max_grade: float = 0.04


def smoothstep_profile(t: np.ndarray, knots_t: np.ndarray, knots_v: np.ndarray) -> np.ndarray:
    """Piecewise profile through ``(knots_t, knots_v)`` joined by quintic smoothsteps.

    Between consecutive knots the value moves with ``s(u) = 10u^3 - 15u^4 + 6u^5``, whose first
    and second derivatives vanish at both ends: the profile is C2 everywhere.
    """
    knots_t = np.asarray(knots_t, dtype=np.float64)
    knots_v = np.asarray(knots_v, dtype=np.float64)
    index = np.clip(np.searchsorted(knots_t, t, side="right") - 1, 0, len(knots_t) - 2)
    t0, t1 = knots_t[index], knots_t[index + 1]
    u = np.clip((t - t0) / np.maximum(t1 - t0, 1e-12), 0.0, 1.0)
    s = u**3 * (10.0 - 15.0 * u + 6.0 * u**2)
    return knots_v[index] + (knots_v[index + 1] - knots_v[index]) * s


class _Program:
    """Breakpoints for speed and curvature, appended maneuver by maneuver."""

    def __init__(self, speed: float = 0.0) -> None:
        self.t = 0.0
        self.speed_knots: list[tuple[float, float]] = [(0.0, speed)]
        self.curv_knots: list[tuple[float, float]] = [(0.0, 0.0)]

    @property
    def speed(self) -> float:
        return self.speed_knots[-1][1]

    def hold(self, duration: float) -> None:
        self.t += duration
        self.speed_knots.append((self.t, self.speed))
        self.curv_knots.append((self.t, self.curv_knots[-1][1]))

    def change_speed(self, target: float, accel: float) -> None:
        """Reach ``target`` m/s with a peak acceleration about ``accel`` (smoothstep: 1.875x
        mean)."""
        duration = max(1.0, 1.875 * abs(target - self.speed) / max(abs(accel), 1e-3))
        self.t += duration
        self.speed_knots.append((self.t, target))
        self.curv_knots.append((self.t, self.curv_knots[-1][1]))

    def curve(self, kappa: float, ramp: float, hold: float) -> None:
        """Ramp curvature to ``kappa``, hold, ramp back to straight (speed held)."""
        for duration, value in ((ramp, kappa), (hold, kappa), (ramp, 0.0)):
            self.t += duration
            self.curv_knots.append((self.t, value))
            self.speed_knots.append((self.t, self.speed))

    def turn(self, angle_rad: float, radius: float, ramp: float = 1.5) -> None:
        """A turn of about ``angle_rad`` (sign: left positive) at constant speed."""
        speed = max(abs(self.speed), 0.5)
        kappa = np.sign(angle_rad) / radius
        # yaw = v * kappa * (hold + ramp): the two smoothstep ramps add half a ramp each.
        hold = max(0.0, abs(angle_rad) / (speed * abs(kappa)) - ramp)
        self.curve(kappa, ramp, hold)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        st, sv = map(np.asarray, zip(*self.speed_knots, strict=True))
        ct, cv = map(np.asarray, zip(*self.curv_knots, strict=True))
        return st, sv, ct, cv


def _aggressive(rng: np.random.Generator, duration: float) -> _Program:
    """Slalom with hard acceleration and braking, never stopping (paper Seq-1)."""
    p = _Program(speed=rng.uniform(6.0, 9.0))
    while p.t < duration:
        choice = rng.uniform()
        if choice < 0.45:  # slalom: alternate curvature, lateral accel up to ~4 m/s^2
            for k in range(rng.integers(2, 5)):
                v = max(p.speed, 3.0)
                kappa = (-1) ** k * min(rng.uniform(0.25, 0.45) / v, 4.0 / v**2)
                p.curve(kappa, ramp=rng.uniform(0.6, 1.0), hold=rng.uniform(0.2, 0.8))
        elif choice < 0.75:  # hard acceleration or braking
            target = rng.uniform(4.0, 13.0)
            p.change_speed(target, accel=rng.uniform(2.0, 3.5))
        else:  # a sharp turn
            radius = max(rng.uniform(12.0, 25.0), p.speed**2 / 4.0)  # lateral accel <= 4 m/s^2
            p.turn(rng.choice([-1, 1]) * rng.uniform(0.6, 1.6), radius=radius)
    return p


def _urban(rng: np.random.Generator, duration: float) -> _Program:
    """Normal traffic: stops of 5-10 s at lights, 90-degree turns, lane changes (paper Seq-2)."""
    p = _Program(speed=0.0)
    p.hold(rng.uniform(6.0, 9.0))  # parked at the start: the first rest
    block, stop_first = 0, True
    while p.t < duration:
        p.change_speed(rng.uniform(9.0, 13.0), accel=rng.uniform(1.0, 1.8))
        p.hold(rng.uniform(6.0, 18.0))
        if rng.uniform() < 0.5:  # lane change
            v = p.speed
            kappa = rng.choice([-1, 1]) * rng.uniform(0.6, 1.2) / v**2
            p.curve(kappa, ramp=1.0, hold=0.5)
            p.curve(-kappa, ramp=1.0, hold=0.5)
            p.hold(rng.uniform(3.0, 8.0))
        # Alternate red lights and intersections (in random order within each pair), so
        # every drive has both stops and 90-degree turns.
        if block % 2 == 0:
            stop_first = rng.uniform() < 0.5
        block += 1
        if (block % 2 == 1) == stop_first:  # red light
            p.change_speed(0.0, accel=rng.uniform(1.2, 2.2))
            p.hold(rng.uniform(5.0, 10.0))
        else:  # 90-degree turn at an intersection
            p.change_speed(rng.uniform(3.5, 5.0), accel=rng.uniform(1.2, 2.0))
            p.turn(rng.choice([-1, 1]) * np.pi / 2, radius=rng.uniform(10.0, 16.0))
    return p


def _highway(rng: np.random.Generator, duration: float) -> _Program:
    """Straight at constant speed: almost no rotational excitation."""
    p = _Program(speed=rng.uniform(22.0, 26.0))
    while p.t < duration:
        p.hold(rng.uniform(10.0, 30.0))
        kappa = rng.choice([-1, 1]) * rng.uniform(1.0, 3.0) * 1e-4  # radius > 3 km
        p.curve(kappa, ramp=rng.uniform(5.0, 10.0), hold=rng.uniform(5.0, 15.0))
    return p


def _parking(rng: np.random.Generator, duration: float) -> _Program:
    """Low speed forward and reverse at full steering lock, with stops."""
    p = _Program(speed=0.0)
    p.hold(rng.uniform(4.0, 6.0))
    while p.t < duration:
        direction = rng.choice([-1.0, 1.0])
        p.change_speed(direction * rng.uniform(1.2, 2.5), accel=rng.uniform(0.8, 1.5))
        kappa = rng.choice([-1, 1]) / rng.uniform(7.0, 9.0)  # full lock, bus/truck
        p.curve(kappa, ramp=rng.uniform(1.5, 2.5), hold=rng.uniform(2.0, 5.0))
        p.change_speed(0.0, accel=rng.uniform(0.8, 1.5))
        p.hold(rng.uniform(2.5, 5.0))
    return p


def _stationary(rng: np.random.Generator, duration: float) -> _Program:
    """Parked the whole time (an end-of-line check that forgot to drive): nothing observable."""
    p = _Program(speed=0.0)
    p.hold(duration)
    return p


_PROGRAMS: dict[str, Callable[[np.random.Generator, float], _Program]] = {
    "aggressive": _aggressive,
    "urban": _urban,
    "highway": _highway,
    "parking": _parking,
    "stationary": _stationary,
}


def _bumps(
    rng: np.random.Generator, t: np.ndarray, band_hz: tuple[float, float], count: int = 6
) -> np.ndarray:
    """A band-limited random signal (sum of sinusoids) of ``t`` (time, or distance with the band
    in cycles per metre), unit RMS."""
    freqs = rng.uniform(band_hz[0], band_hz[1], count)
    phases = rng.uniform(0.0, 2.0 * np.pi, count)
    amps = rng.uniform(0.5, 1.0, count)
    out = np.sum(
        amps[:, None] * np.sin(2.0 * np.pi * freqs[:, None] * t[None, :] + phases[:, None]), axis=0
    )
    return out / np.sqrt(0.5 * np.sum(amps**2))


def _suspension(t: np.ndarray, u: np.ndarray, dyn: VehicleDynamics) -> np.ndarray:
    """Second-order (damped, unit DC gain) body response to the quasi-static input ``u``.

    Starts settled at ``u[0]``: the filter runs on ``u - u[0]`` from rest.
    """
    wn = 2.0 * np.pi * dyn.natural_frequency_hz
    system = signal.lti([wn**2], [1.0, 2.0 * dyn.damping_ratio * wn, wn**2])
    _, y, _ = signal.lsim(system, u - u[0], t - t[0])
    return np.asarray(y) + u[0]


def _wheel(rng: np.random.Generator, duration: float) -> Trajectory:
    """A wheel of a car driving straight on a level road at the speeds of an aggressive program
    (:func:`_aggressive`, scaled to 2.4-7.8 m/s): B spins about its x axis (the axle, across
    the car: roll) at ``v / r`` and about no other, as the real recording's wheel did."""
    program = _aggressive(rng, duration)
    st, sv, _, _ = program.arrays()
    t = np.arange(-1.0, duration + 1.0 + 0.5 / GRID_HZ, 1.0 / GRID_HZ)
    speed = 0.6 * smoothstep_profile(np.clip(t, 0.0, None), st, sv)  # (a smooth top)
    speed *= 1.0 + 0.002 * _bumps(rng, t, (0.2, 1.0))  # the road and the engine: never held
    heading = rng.uniform(-np.pi, np.pi)
    spin = cumulative_trapezoid(speed / WHEEL_RADIUS_M, t, initial=0.0)
    along = cumulative_trapezoid(speed, t, initial=0.0)
    position = np.column_stack(
        [-np.sin(heading) * along, np.cos(heading) * along, np.full(len(t), WHEEL_RADIUS_M)]
    )
    rpy = np.column_stack([spin, np.zeros(len(t)), np.full(len(t), heading)])
    trajectory = Trajectory.from_samples(t, position, rpy)
    return Trajectory(trajectory.position_world, trajectory.rpy, 0.0, duration)


def make_scenario(
    name: str,
    duration_s: float | None = None,
    seed: int = 0,
    dynamics: VehicleDynamics | None = None,
) -> Trajectory:
    """Build the trajectory of scenario ``name`` (see :data:`SCENARIOS`)."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r} (expected one of: {', '.join(SCENARIOS)})")
    duration = SCENARIOS[name] if duration_s is None else float(duration_s)
    if duration <= 0:
        raise ValueError("duration must be positive")
    dyn = dynamics or VehicleDynamics()
    rng = np.random.default_rng(seed)
    if name == "wheel":
        return _wheel(rng, duration)
    program = _PROGRAMS[name](rng, duration)

    # Start and end with a second of margin so the IMUs' sample times stay inside the splines.
    margin = 1.0
    t = np.arange(-margin, duration + margin + 0.5 / GRID_HZ, 1.0 / GRID_HZ)
    st, sv, ct, cv = program.arrays()
    tp = np.clip(t, 0.0, None)
    speed = smoothstep_profile(tp, st, sv)
    kappa = smoothstep_profile(tp, ct, cv)
    yaw_rate = speed * kappa
    heading0 = rng.uniform(-np.pi, np.pi)
    yaw = heading0 + cumulative_trapezoid(yaw_rate, t, initial=0.0)

    # Road grade: a function of the distance travelled (hills every 100-500 m), so a vehicle
    # standing still does not pitch.
    distance = cumulative_trapezoid(np.abs(speed), t, initial=0.0)
    grade = dyn.max_grade * np.tanh(
        _bumps(rng, distance, (1.0 / 500.0, 1.0 / 100.0), count=3) * 0.7
    )
    distance_rate = speed
    x = cumulative_trapezoid(distance_rate * np.cos(yaw), t, initial=0.0)
    y = cumulative_trapezoid(distance_rate * np.sin(yaw), t, initial=0.0)
    z = cumulative_trapezoid(np.abs(distance_rate) * grade, t, initial=0.0)

    accel_lon = np.gradient(speed, t)
    accel_lat = speed * yaw_rate
    bump_scale = ROAD_ROUGHNESS[name] * np.abs(speed) / (np.abs(speed) + 3.0)
    roll = _suspension(t, dyn.roll_per_lateral_accel * accel_lat, dyn)
    roll = roll + dyn.bump_roll_rad * bump_scale * _bumps(rng, t, dyn.bump_band_hz)
    pitch = _suspension(t, -dyn.pitch_per_longitudinal_accel * accel_lon, dyn)
    pitch = pitch - np.arctan(grade)
    pitch = pitch + dyn.bump_pitch_rad * bump_scale * _bumps(rng, t, dyn.bump_band_hz)
    heave = dyn.bump_heave_m * bump_scale * _bumps(rng, t, dyn.bump_band_hz)

    position = np.column_stack([x, y, z + heave])
    rpy = np.column_stack([roll, pitch, yaw])
    trajectory = Trajectory.from_samples(t, position, rpy)
    return Trajectory(trajectory.position_world, trajectory.rpy, 0.0, duration)
