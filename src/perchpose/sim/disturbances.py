"""What differs from one flight to the next besides the wind, drawn per run: motors that do not
match, a flight controller whose attitude estimate is slightly off and whose odometry drifts,
a camera whose latency jitters and whose frames are lost in bursts, a battery that sags.

``Disturbances`` holds the distributions; ``VehicleDraw.draw`` makes one run's draws from its
seeded generator; ``OdometryModel`` is the flight controller's own position and velocity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import DisturbanceConfigError
from perchpose.geometry import rot_x, rot_y
from perchpose.sim.flow_deck import FlowDeckError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Disturbances:
    """Per-run spreads (SI units).

    thrust_mismatch : each motor gives uniform(1 - m, 1 + m) of its nominal thrust.
    attitude_bias_deg : standard deviation of the attitude estimate's roll and pitch error.
    latency_jitter : probability that a frame reaches the estimator a frame later than usual.
    bursts_per_s : rate of camera dropouts in bursts (Poisson), each lasting uniform
    ``burst_s`` (the paper's test lost the camera for 1 s). battery_start : uniform range of
    the thrust the battery gives at the start (1: fully charged). battery_sag_per_s : uniform
    range of its loss per second of flight. odometry_noise_mps : white noise of the odometry's
    velocity. odometry_drift_mps_per_sqrt_s : random walk of its velocity bias (the default
    gives a bias of about 4 mm/s and a horizontal position drift of about 7 cm (median) after
    20 s of hover; a perching run lasts 4-8 s).
    """

    thrust_mismatch: float = 0.03
    attitude_bias_deg: float = 0.5
    latency_jitter: float = 0.2
    bursts_per_s: float = 0.05
    burst_s: tuple[float, float] = (0.2, 1.0)
    battery_start: tuple[float, float] = (0.92, 1.0)
    battery_sag_per_s: tuple[float, float] = (0.0, 0.002)
    odometry_noise_mps: float = 0.01
    odometry_drift_mps_per_sqrt_s: float = 0.001

    def __post_init__(self) -> None:
        for name in (
            "thrust_mismatch",
            "attitude_bias_deg",
            "bursts_per_s",
            "odometry_noise_mps",
            "odometry_drift_mps_per_sqrt_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise DisturbanceConfigError(f"{name} must be a non-negative number, got {value}")
        if not 0 <= self.latency_jitter <= 1:
            raise DisturbanceConfigError("latency_jitter is a probability (0 to 1)")
        if self.thrust_mismatch >= 0.5:
            raise DisturbanceConfigError("thrust_mismatch must stay under 0.5")
        for name in ("burst_s", "battery_start", "battery_sag_per_s"):
            low, high = getattr(self, name)
            if not 0 <= low <= high:
                raise DisturbanceConfigError(f"{name} must be 0 <= low <= high")
        if self.battery_start[1] > 1.0 or self.battery_start[0] <= 0.5:
            raise DisturbanceConfigError("battery_start must lie in (0.5, 1]")

    @staticmethod
    def none() -> Disturbances:
        """A clean lab: matched motors, exact attitude, steady latency, no bursts, a full
        battery, odometry with white noise only."""
        return Disturbances(
            thrust_mismatch=0.0,
            attitude_bias_deg=0.0,
            latency_jitter=0.0,
            bursts_per_s=0.0,
            battery_start=(1.0, 1.0),
            battery_sag_per_s=(0.0, 0.0),
            odometry_drift_mps_per_sqrt_s=0.0,
        )


@dataclass(frozen=True)
class VehicleDraw:
    """One run's draws: per-motor thrust factors, the attitude estimate's error, the battery,
    and the camera's lost intervals ``(start_s, end_s)``."""

    motor_scale: tuple[float, float, float, float]
    attitude_bias: Array = field(repr=False)
    battery_start: float
    battery_sag_per_s: float
    bursts: tuple[tuple[float, float], ...]

    @staticmethod
    def draw(d: Disturbances, duration_s: float, rng: np.random.Generator) -> VehicleDraw:
        m = rng.uniform(1.0 - d.thrust_mismatch, 1.0 + d.thrust_mismatch, 4)
        roll, pitch = np.radians(rng.normal(0.0, d.attitude_bias_deg, 2))
        n_bursts = int(rng.poisson(d.bursts_per_s * duration_s))
        starts = np.sort(rng.uniform(0.0, duration_s, n_bursts))
        lengths = rng.uniform(*d.burst_s, n_bursts)
        return VehicleDraw(
            motor_scale=(float(m[0]), float(m[1]), float(m[2]), float(m[3])),
            attitude_bias=rot_x(float(roll)) @ rot_y(float(pitch)),
            battery_start=float(rng.uniform(*d.battery_start)),
            battery_sag_per_s=float(rng.uniform(*d.battery_sag_per_s)),
            bursts=tuple((float(s), float(s + n)) for s, n in zip(starts, lengths, strict=True)),
        )

    def thrust_scale(self, t_s: float) -> tuple[float, float, float, float]:
        """Each motor's share of its nominal thrust at ``t_s``."""
        battery = max(0.5, self.battery_start - self.battery_sag_per_s * t_s)
        a, b, c, d = self.motor_scale
        return (a * battery, b * battery, c * battery, d * battery)

    def in_burst(self, t_s: float) -> bool:
        return any(start <= t_s < end for start, end in self.bursts)


class OdometryModel:
    """The flight controller's position and velocity: the truth plus white velocity noise and
    a velocity bias that random-walks; the position integrates the biased velocity, so it
    drifts from the truth as a real state estimate does. ``flow_noise_mps``: white velocity
    noise that the position integrates too (an optical-flow estimator's). ``flow``: a flow
    deck's horizontal error (``sim.flow_deck``), correlated in time, in place of the white
    flow noise along x and y; ``update`` then needs the vehicle's attitude and body rates."""

    def __init__(
        self,
        d: Disturbances,
        p_m: Array,
        rng: np.random.Generator,
        flow_noise_mps: float = 0.0,
        flow: FlowDeckError | None = None,
    ) -> None:
        self._d = d
        self._rng = rng
        self.flow_noise_mps = flow_noise_mps
        self.flow = flow
        self.bias_mps = np.zeros(3)
        self.drift_m = np.zeros(3)
        self.p_m = np.asarray(p_m, np.float64).copy()
        self.v_mps = np.zeros(3)

    def update(
        self,
        p_true_m: Array,
        v_true_mps: Array,
        dt_s: float,
        R_world_body: Array | None = None,
        omega_rad_s: Array | None = None,
    ) -> None:
        """Advance by ``dt_s`` to the vehicle's true position and velocity (with a flow deck,
        also its attitude and body rates)."""
        d = self._d
        self.bias_mps = self.bias_mps + d.odometry_drift_mps_per_sqrt_s * math.sqrt(
            dt_s
        ) * self._rng.normal(size=3)
        noise = self._rng.normal(0.0, d.odometry_noise_mps, 3)
        # an optical-flow velocity's own noise, which the position integrates
        flow = self._rng.normal(0.0, self.flow_noise_mps, 3) if self.flow_noise_mps else 0.0
        if self.flow is not None:
            if R_world_body is None or omega_rad_s is None:
                raise ValueError("a flow deck's odometry needs the attitude and body rates")
            flow = flow * np.array([0.0, 0.0, 1.0]) + self.flow.advance(
                dt_s, float(p_true_m[2]), v_true_mps, R_world_body, omega_rad_s
            )
        self.drift_m = self.drift_m + dt_s * (self.bias_mps + flow)
        self.v_mps = np.asarray(v_true_mps, np.float64) + self.bias_mps + noise + flow
        self.p_m = np.asarray(p_true_m, np.float64) + self.drift_m
