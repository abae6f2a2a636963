"""The pilot's own attitude on a drag-free estimator: the gyro over seconds, the estimate beyond.

A flying Crazyflie's Kalman filter misses the lean a wind's push needs; ``control/lean.py``
predicts that lean from the push, low-passed over the filter's lag, and leaves 0.4-0.8 degrees
RMS of tilt error, most of it changing faster than 3 s (the filter's own corrections as the
gusts change, which no model of the push alone follows). Each such degree is 0.17 m/s^2 of
acceleration that is not there when the pilot turns the accelerometer into the world.

The gyro, integrated, has none of those corrections. Over a few seconds its only error is its
bias (up to 0.1 deg/s after the firmware's start-up calibration: 0.3 degrees over 3 s, a
constant the inertial filter's bias state takes in) and its noise (0.3 deg/s a sample, under
0.1 degree over 3 s at 50 Hz). So the pilot's attitude follows the integrated gyro over short
times and the estimate, its lean taken out, over long ones: a complementary filter whose time
constant is ``blend_s``. ``GyroAttitude`` integrates the rates the vehicle logs, where they
arrive (the Crazyflie link's log callback, the simulation's sensed samples);
``BlendedAttitude`` holds the gyro's frame to the estimate's.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import ControllerConfigError
from perchpose.geometry import rotation_from_vector, vector_from_rotation

Array = NDArray[np.float64]
MAX_GAP_S = 0.1  # a longer gap between rate samples is not integrated across (a stalled log)


class GyroReading(NamedTuple):
    """The integrated gyro as the pilot reads it: the body in the integral's own frame, and
    how many times the integral restarted after a gap."""

    R_ref_body: Array
    restarts: int


class GyroAttitude:
    """The body's attitude in a frame of its own (``R_ref_body``, identity at the first
    sample), integrated from body rates (rad/s) sample by sample: each interval at the mean of
    the rates at its ends. A gap over ``MAX_GAP_S`` is not integrated across: the integral
    restarts there from where it was, and ``restarts`` counts it (the blend then takes the
    estimate's word afresh)."""

    def __init__(self) -> None:
        self.R_ref_body: Array = np.eye(3)
        self.restarts = 0
        self._last: tuple[float, Array] | None = None

    def add(self, t_s: float, omega_body_rad_s: Array) -> None:
        omega = np.asarray(omega_body_rad_s, np.float64)
        if not (math.isfinite(t_s) and np.all(np.isfinite(omega))):
            return
        if self._last is not None:
            t0_s, omega0 = self._last
            dt_s = t_s - t0_s
            if dt_s < 0.0:
                return
            if dt_s > MAX_GAP_S:
                self.restarts += 1
            elif dt_s > 0.0:
                self.R_ref_body = self.R_ref_body @ rotation_from_vector(
                    0.5 * (omega0 + omega) * dt_s
                )
        self._last = (t_s, omega)

    def reading(self) -> GyroReading | None:
        """The integral so far (None before the first sample)."""
        if self._last is None:
            return None
        return GyroReading(self.R_ref_body.copy(), self.restarts)


class BlendedAttitude:
    """``R_world_body`` from the gyro's attitude and the estimate's: the frame that takes the
    gyro's reference into the world (``R_world_ref``, constant were both exact) is the
    estimate's, low-passed over ``blend_s``; the attitude is that frame times the gyro's."""

    def __init__(self, blend_s: float) -> None:
        if not (math.isfinite(blend_s) and blend_s > 0.0):
            raise ControllerConfigError(f"gyro blend_s must be positive, got {blend_s}")
        self.blend_s = blend_s
        self._R_world_ref: Array | None = None
        self._t_s: float | None = None
        self._restarts = 0

    def blend(self, R_world_body: Array, gyro: GyroReading, t_s: float) -> Array:
        """The blended attitude at ``t_s`` from the estimate's ``R_world_body`` and the gyro's
        reading (an integral that restarted is taken afresh from the estimate)."""
        R_ref_body = np.asarray(gyro.R_ref_body, np.float64)
        measured = np.asarray(R_world_body, np.float64) @ R_ref_body.T
        restarts = gyro.restarts
        if self._R_world_ref is None or self._t_s is None or restarts != self._restarts:
            self._R_world_ref = measured
        else:
            dt_s = max(0.0, t_s - self._t_s)
            share = 1.0 - math.exp(-dt_s / self.blend_s)
            step = vector_from_rotation(self._R_world_ref.T @ measured)
            self._R_world_ref = self._R_world_ref @ rotation_from_vector(share * step)
        self._t_s, self._restarts = t_s, restarts
        return self._R_world_ref @ R_ref_body
