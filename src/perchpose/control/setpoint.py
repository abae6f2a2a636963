"""The last step before a vehicle link: nothing non-finite leaves, and every setpoint is clamped
to configured limits, whatever computed it."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from perchpose.errors import ControllerConfigError, require_positive


@dataclass(frozen=True)
class SetpointLimits:
    """The largest setpoint a link may send (SI units): horizontal speed (the norm of x and y),
    vertical speed, yaw rate."""

    max_xy_mps: float = 1.0
    max_z_mps: float = 0.5
    max_yaw_rate_rad_s: float = 2.0

    def __post_init__(self) -> None:
        names = ("max_xy_mps", "max_z_mps", "max_yaw_rate_rad_s")
        require_positive(self, names, ControllerConfigError, "setpoint limit ")
        for name in names:
            if not math.isfinite(getattr(self, name)):
                raise ControllerConfigError(f"setpoint limit {name} must be finite")


@dataclass(frozen=True)
class Setpoint:
    """A velocity setpoint fit to send: world frame, m/s, yaw rate in rad/s.

    clamped : a component was cut to its limit. replaced : the input had a non-finite
    component, and a hover (all zero) is sent instead.
    """

    v_mps: tuple[float, float, float]
    yaw_rate_rad_s: float
    clamped: bool = False
    replaced: bool = False


def safe_setpoint(v_mps: ArrayLike, yaw_rate_rad_s: float, limits: SetpointLimits) -> Setpoint:
    """``v_mps`` (3,) and the yaw rate clamped to ``limits``; any NaN or infinity anywhere makes
    the whole setpoint a hover (a direction with a non-finite part is no direction)."""
    v = np.asarray(v_mps, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not (np.all(np.isfinite(v)) and math.isfinite(yaw_rate_rad_s)):
        return Setpoint((0.0, 0.0, 0.0), 0.0, replaced=True)
    vx, vy, vz = (float(c) for c in v)
    clamped = False
    horizontal = math.hypot(vx, vy)
    if horizontal > limits.max_xy_mps:
        scale = limits.max_xy_mps / horizontal
        vx, vy = vx * scale, vy * scale
        clamped = True
    if abs(vz) > limits.max_z_mps:
        vz = math.copysign(limits.max_z_mps, vz)
        clamped = True
    yaw_rate = float(yaw_rate_rad_s)
    if abs(yaw_rate) > limits.max_yaw_rate_rad_s:
        yaw_rate = math.copysign(limits.max_yaw_rate_rad_s, yaw_rate)
        clamped = True
    return Setpoint((vx, vy, vz), yaw_rate, clamped=clamped)
