"""The pilot's own horizontal velocity loop, for a vehicle sent attitude setpoints.

With ``PilotSettings.command`` ``attitude`` the pilot sends a roll, a pitch, a yaw rate and a
height (cflib's ``send_zdistance_setpoint``): the vehicle's attitude loop flies the lean and its
position loop holds the height on its own estimate, and the horizontal velocity loop is the
pilot's. A Crazyflie's velocity loop flies its Kalman filter's velocity, which models no drag:
a vehicle leaning into a gust reads to it as accelerating, and in strong wind that velocity
runs 0.5-1 m/s off for a second at a time. The pilot's loop flies instead the velocity the
camera's fixes and the accelerometer give (``control.inertial``), and cancels the push the
accelerometer measures as it comes, as a lean rather than as a velocity offset for a loop to
turn into one.

The acceleration asked is ``gain * (v_asked - v) - push`` (world x and y), within the lean
``max_lean_rad`` allows; the lean that gives it under the vehicle's heading is

    pitch = atan(a_forward / g),  roll = atan(-a_left * cos(pitch) / g)

(ZYX Euler angles: pitch positive tilts the nose down, towards +x; roll positive lowers the
right side, towards -y), thrust along the body's z axis holding the weight.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from perchpose.control.lean import GRAVITY_MPS2
from perchpose.control.push import PushFilter
from perchpose.geometry import clip_norm


@dataclass(frozen=True)
class Lean:
    """A lean to send: roll and pitch (rad, as above), and whether the acceleration asked was
    cut to the largest lean."""

    roll_rad: float
    pitch_rad: float
    clamped: bool = False


def lean_for(a_world_mps2: ArrayLike, yaw_rad: float, max_lean_rad: float) -> Lean:
    """The roll and pitch that accelerate the vehicle by ``a_world_mps2`` (world x and y)
    under heading ``yaw_rad``, the acceleration cut to ``g tan(max_lean_rad)``."""
    asked = np.asarray(a_world_mps2, np.float64).reshape(-1)[:2]
    top = GRAVITY_MPS2 * math.tan(max_lean_rad)
    a = clip_norm(asked, top)
    clamped = float(np.linalg.norm(asked)) > top
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    forward = c * float(a[0]) + s * float(a[1])
    left = -s * float(a[0]) + c * float(a[1])
    pitch = math.atan2(forward, GRAVITY_MPS2)
    roll = math.atan2(-left * math.cos(pitch), GRAVITY_MPS2)
    return Lean(roll, pitch, clamped)


class LeanLoop:
    """Velocity asked -> lean: ``gain_per_s`` (1/s) on the velocity error, less the push
    (low-passed over ``push_filter_s``, at most ``max_push_mps2``; none where
    ``push_feedforward`` is off or no sample came), within ``max_lean_rad``.

    The velocity it is given describes the vehicle some time ago (``v_age_s``: the odometry's
    age), and the estimate behind it lags the vehicle by a few hundredths of a second more;
    the attitude loop that flies the lean answers over about 0.15 s (the firmware's attitude
    P gain is 6 /s). Flown as it comes, that lag leaves a stiff loop ringing. The loop carries
    the velocity forward over ``v_age_s + lead_s`` by the acceleration the vehicle has now
    (``a_now_mps2``: its lean's, from the attitude, which is fresher than the odometry, and
    the push), so that it answers the vehicle's velocity now, not the velocity it had."""

    def __init__(
        self,
        gain_per_s: float,
        max_lean_rad: float,
        *,
        push_feedforward: bool = True,
        push_filter_s: float = 0.03,
        max_push_mps2: float = 4.0,
        lead_s: float = 0.0,
    ) -> None:
        self.gain_per_s = gain_per_s
        self.lead_s = lead_s
        self.max_lean_rad = max_lean_rad
        self._push = PushFilter(push_feedforward, push_filter_s, max_push_mps2)
        self._t_s: float | None = None

    def lean(
        self,
        t_s: float,
        v_asked_mps: ArrayLike,
        v_now_mps: ArrayLike,
        push_mps2: ArrayLike | None,
        yaw_rad: float,
        v_age_s: float = 0.0,
        a_now_mps2: ArrayLike | None = None,
    ) -> Lean:
        """The lean for the horizontal velocity asked (world, m/s), the vehicle's velocity
        ``v_age_s`` ago, the push the accelerometer measures (world x and y, m/s^2; None: no
        sample) and the horizontal acceleration the vehicle has now (world, m/s^2, before the
        push; None: none carried)."""
        # the first sample is taken as it is; later ones through the low-pass
        dt_s = math.inf if self._t_s is None else max(0.0, t_s - self._t_s)
        self._t_s = t_s
        push = self._push.update(push_mps2, dt_s)
        v = np.asarray(v_now_mps, np.float64)[:2]
        if a_now_mps2 is not None:
            a_now = np.asarray(a_now_mps2, np.float64).reshape(-1)[:2] + push
            if np.all(np.isfinite(a_now)):
                v = v + a_now * (max(0.0, v_age_s) + self.lead_s)
        error = np.asarray(v_asked_mps, np.float64)[:2] - v
        return lean_for(self.gain_per_s * error - push, yaw_rad, self.max_lean_rad)
