"""A disturbance observer on the vehicle's velocity loop.

The flight controller's velocity loop is taken as first order: ``dv/dt = k_v (v_sp - v) + a``,
where ``a`` is what no one asked for (wind, a sagging battery, motors that do not match, an
attitude estimate that is off), an acceleration in the world frame. A Luenberger observer on
the odometry's velocity estimates ``v`` and ``a``:

    dv^/dt = k_v (v_sp - v^) + a^ + L1 (v_odometry - v^)
    da^/dt = L2 (v_odometry - v^)

with both error poles at ``rate`` (``k_v + L1 = 2 rate``, ``L2 = rate^2``). The velocity
setpoint that cancels it is ``v_cmd - a^ / k_v``. Because the observer predicts the loop's own
lag, a commanded change of speed is not mistaken for a disturbance, which a plain integral of
the velocity error would wind up on. A velocity that arrives late (it describes the vehicle
``age_s`` ago) is compared with the observer's own estimate of that moment, not of now.

A real flight controller answers later than a first-order loop: its attitude loop must tilt
the vehicle first (the Crazyflie firmware's PID lags a first-order 4.3 /s loop by about 55
deg at 1 Hz and 95 deg at 2 Hz, about 0.13 s). ``delay_s`` makes the model answer the
setpoint that was sent that long ago: without it, an observer as fast as 6-18 rad/s reads the
vehicle's own late answer as a disturbance and rings with it at about 2 Hz.

The vertical loop answers sooner: thrust moves the vehicle up with no tilt to wait for. The
firmware's PID lags by 56 deg at 1 Hz and 88 deg at 2 Hz vertically (on its Kalman filter
58 and 77), the model's loops by 65 and 91 (``benchmarks/bench_agreement.py``'s vehicles,
a sine asked of each): a first-order loop of 5.5 /s answering 0.02 s late lags by 56 and 80.
Modelled as the horizontal loop (4.3 /s, 0.1 s: 92 and 143 deg), the observer reads the
vertical answer as arriving early and rings with it: under the plate, on a Kalman filter's
height from a range sensor 2 m from the floor, it swung the vertical setpoint by +-0.3 m/s
(its clamp) at about 3 Hz, and the climb stalled there for seconds. ``vertical_gain`` and
``vertical_delay_s`` are that loop's model (None: the horizontal one).

A disturbance measured apart (the accelerometer's aerodynamic push, cancelled through the
setpoint by the controller) is a known input ``a_k`` of the model, ``dv/dt = k_v (v_sp - v) +
a_k + a``: the observer then estimates only what it leaves unexplained, and does not cancel the
push a second time.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from numpy.typing import NDArray

from perchpose.control.history import newest_at

Array = NDArray[np.float64]
HISTORY = 32  # the observer's past estimates kept for late measurements


class DisturbanceObserver:
    """Estimates the disturbance acceleration from setpoints sent and velocities flown."""

    def __init__(
        self,
        velocity_gain: float,
        rate: float,
        max_offset_mps: tuple[float, float, float],
        delay_s: float = 0.0,
        *,
        vertical_gain: float | None = None,
        vertical_delay_s: float | None = None,
    ) -> None:
        self._k_v = velocity_gain
        self.delay_s = delay_s
        self.vertical_gain = vertical_gain
        self.vertical_delay_s = delay_s if vertical_delay_s is None else vertical_delay_s
        self.rate = rate  # sets the gains l1, l2
        self.max_offset_mps = np.asarray(max_offset_mps, np.float64)
        self.v_mps: Array | None = None
        self.a_mps2 = np.zeros(3)
        self._clock_s = 0.0
        self._past: deque[tuple[float, Array]] = deque(maxlen=HISTORY)
        self._sent: deque[tuple[float, Array]] = deque(maxlen=HISTORY)  # setpoints, by time

    @property
    def k_v(self) -> float:
        """The horizontal velocity loop's gain in the model, 1/s."""
        return self._k_v

    @k_v.setter
    def k_v(self, velocity_gain: float) -> None:
        """A new horizontal loop gain (the pilot set the vehicle's): l1 follows."""
        self._k_v = velocity_gain
        self.rate = self._rate

    @property
    def gains(self) -> Array:
        """The model's loop gain per axis (x, y, z), 1/s."""
        k_z = self._k_v if self.vertical_gain is None else self.vertical_gain
        return np.array([self._k_v, self._k_v, k_z])

    @property
    def rate(self) -> float:
        """The observer's error poles, rad/s."""
        return self._rate

    @rate.setter
    def rate(self, rate: float) -> None:
        """Move the poles (the estimates carry on from where they are)."""
        self._rate = rate
        self.l1 = np.maximum(0.0, 2.0 * rate - self.gains)  # per axis
        self.l2 = rate * rate

    @property
    def offset_mps(self) -> Array:
        """The setpoint offset that cancels the disturbance (clamped)."""
        return np.clip(-self.a_mps2 / self.gains, -self.max_offset_mps, self.max_offset_mps)

    def update(
        self,
        v_sp_mps: Array,
        v_odometry_mps: Array,
        dt_s: float,
        age_s: float = 0.0,
        known_mps2: Array | None = None,
    ) -> None:
        """Advance ``dt_s`` with the setpoint the vehicle flew over it and the velocity it
        reports, which describes it ``age_s`` ago. ``known_mps2``: a disturbance measured
        (and cancelled by the setpoint) apart from this observer, which it then leaves out of
        its estimate."""
        v_odo = np.asarray(v_odometry_mps, np.float64)
        if self.v_mps is None:
            self.v_mps = v_odo.copy()
            self._past.append((self._clock_s, self.v_mps))
            self._sent.append((self._clock_s, v_odo.copy()))  # what it was flying before
            return
        if dt_s <= 0:
            return
        then = newest_at(self._past, self._clock_s - age_s) if age_s > 0 else self.v_mps
        error = v_odo - then
        self._sent.append((self._clock_s, np.asarray(v_sp_mps, np.float64)))
        answered = newest_at(self._sent, self._clock_s - self.delay_s).copy()
        answered[2] = newest_at(self._sent, self._clock_s - self.vertical_delay_s)[2]
        gains = self.gains
        dv = gains * (answered - self.v_mps) + self.a_mps2
        if known_mps2 is not None:
            dv = dv + known_mps2
        self.v_mps = self.v_mps + dt_s * (dv + self.l1 * error)
        limit = self.max_offset_mps * gains
        # anti-windup: the estimate never leaves what the clamp lets the setpoint cancel
        self.a_mps2 = np.clip(self.a_mps2 + dt_s * self.l2 * error, -limit, limit)
        self._clock_s += dt_s
        self._past.append((self._clock_s, self.v_mps))

    def reset(self) -> None:
        self.v_mps = None
        self.a_mps2 = np.zeros(3)
        self._past.clear()
        self._sent.clear()
