"""The tilt that a drag-free attitude estimate misses: the lean a push needs, predicted.

A flying Crazyflie's Kalman filter (``kalman_core.c``) takes the accelerometer to measure the
thrust alone: its model has no drag. Held against a wind, the vehicle leans into it; the
filter reads the lean as an acceleration that the flow deck does not see, and over about a
second corrects its attitude toward level. So its attitude is off by the lean that the push
needs, ``push / g`` about the horizontal axis across the push, taken in as the push
low-passed over that second (fitted offline on recorded moderate-wind runs: within 0.2-0.9
degrees RMS of the filter's tilt error, against errors of 1.6-5.3 degrees RMS; the record in
benchmarks/notes/simulation.md). The push is what the accelerometer measures along the body's
x and y (drag over mass), so the error can be predicted as it builds and taken out of the
attitude before the pilot uses it: the camera's view turned into the world, the tilt gate,
the push's own direction.

The accelerometer's own offset reads as a push that is not there (the BMI088's after its
level calibration is up to about 0.1 m/s^2 a side, a lean of 0.6 degrees, as large as the
filter's whole error in still air). It cannot be told from a steady wind, so the lean is
taken from the push beyond it: ``offset_mps2`` less along the push's direction, none below.

The pilot takes over a vehicle already flying: where a wind blows, the filter's attitude is
already off by the whole lean, so the model starts from the first push as if it had held
(starting from none, it would take a lag's time to catch up with an error that is all there).

An estimator that knows its tilt (the truth in simulation, an autopilot's EKF with a drag
model or an external attitude) needs none of it: ``LeanCorrection`` is only built for a
drag-free one, with ``lag_s`` its time constant.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import ControllerConfigError
from perchpose.geometry import rotation_from_vector

Array = NDArray[np.float64]
GRAVITY_MPS2 = 9.81
CRAZYFLIE_KALMAN_LAG_S = 1.2  # the fit above, under the plate
ACCEL_OFFSET_MPS2 = 0.1  # the accelerometer's offset, a side (above)
MAX_STEP_S = 0.1  # a longer gap between samples is taken as this (the model does not coast)


class LeanCorrection:
    """Predicts a drag-free estimator's tilt error from the accelerometer's push and takes it
    out of its attitude. ``correct`` is called with each attitude the pilot uses, in time
    order; ``lean_rad`` is the tilt correction last applied (world x and y axes)."""

    def __init__(self, lag_s: float, offset_mps2: float = ACCEL_OFFSET_MPS2) -> None:
        if not (math.isfinite(lag_s) and lag_s > 0.0):
            raise ControllerConfigError(f"lean correction lag_s must be positive, got {lag_s}")
        if not (math.isfinite(offset_mps2) and offset_mps2 >= 0.0):
            raise ControllerConfigError(
                f"lean correction offset_mps2 must be non-negative, got {offset_mps2}"
            )
        self.lag_s = lag_s
        self.offset_mps2 = offset_mps2
        self._push_mps2 = np.zeros(2)  # the world-frame push, low-passed over lag_s
        self._t_s: float | None = None
        self._pushed = False  # the first push is taken as steady (the pilot takes over a flight)
        self.lean_rad = np.zeros(2)

    def correct(self, R_world_body: Array, f_body_mps2: Array | None, t_s: float) -> Array:
        """``R_world_body`` tilted by the lean the push has built up by ``t_s``; the push
        (``f_body_mps2``, the accelerometer's body x and y) moves the model on (None or
        non-finite: the model holds)."""
        R = np.asarray(R_world_body, np.float64)
        dt = 0.0 if self._t_s is None else min(MAX_STEP_S, max(0.0, t_s - self._t_s))
        self._t_s = t_s if self._t_s is None else max(self._t_s, t_s)
        if f_body_mps2 is not None and np.all(np.isfinite(f_body_mps2[:2])):
            push = (R @ np.array([f_body_mps2[0], f_body_mps2[1], 0.0]))[:2]
            alpha = 1.0 - math.exp(-dt / self.lag_s) if self._pushed else 1.0
            self._push_mps2 = self._push_mps2 + alpha * (push - self._push_mps2)
            self._pushed = True
        size = float(np.linalg.norm(self._push_mps2))
        beyond = self._push_mps2 * (max(0.0, size - self.offset_mps2) / size if size > 0 else 0.0)
        # the body's z leans against the push: about x by push_y / g, about y by -push_x / g
        self.lean_rad = np.array([beyond[1], -beyond[0]]) / GRAVITY_MPS2
        return _tilt_about(self.lean_rad) @ R


def _tilt_about(angles_rad: Array) -> Array:
    """The rotation by the rotation vector (x, y, 0)."""
    return rotation_from_vector(np.array([angles_rad[0], angles_rad[1], 0.0]))
