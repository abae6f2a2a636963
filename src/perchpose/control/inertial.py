"""The vehicle's horizontal position and velocity from the camera's fixes and the
accelerometer, and what the vehicle's own velocity estimate is off by.

A flight controller flies its velocity loop on its own estimate. A Crazyflie's comes from a
Flow deck: at 2 m a pixel of flow noise is centimetres per second, and the Kalman filter leaves
that error correlated over a tenth of a second or more (in wind it also lags: its model has no
drag). The loop holds the *estimate* on the setpoint, so the vehicle itself moves by the error
and its odometry does not see it: held on the target by the position loop, the magnet wanders
3 cm around the target's axis under the plate (``--odometry flow-deck``), far beyond the 4 mm
capture cone the final climb waits for.

The camera sees where the vehicle really is, a latency late; the accelerometer and the
attitude say how it accelerates. Together they tell the vehicle's true position now and its
true velocity, and so what its own estimate is off by: the controller steers on that
position and adds that error to each setpoint, and the vehicle's loop then flies the
velocity asked for (``PerchingController``). It is a visual-inertial estimate reduced to
what perching needs: per horizontal axis a linear Kalman filter with four states,

- ``r``, the body's centre relative to the target, ``r' = v``;
- ``v``, its velocity, ``v' = a - b``, driven by the horizontal kinematic acceleration ``a``
  (the specific force the accelerometer logs, turned into the world by the attitude);
- ``b``, the acceleration's bias (the accelerometer's own, and an attitude estimate that is
  off, which tilts gravity into it), a slow random walk;
- ``e``, the odometry's correlated velocity error, first order with ``odometry_error_s``;

measured by each fix (``r``, at its capture time) and by each of the flight controller's
velocities (``v + e`` plus white noise). How large ``e`` is, and how much of the odometry's
error is white, is learnt from the odometry's residuals as they come (covariance matching:
only a correlated error survives from one sample to the next): a white error (the odometry
model's default) is left to the vehicle's loop, which averages it: the filter is then not
used at all (``in_use``), and the controller flies the odometry as it did without it; a
Flow deck's error is corrected. Where the vehicle's estimator is known to leave a correlated
error (``assume_correlated``: the pilot on a Crazyflie's Kalman filter), the filter is used
whatever size the residuals give it: in still and light air that filter's velocity is off by
only 1.5-4 cm/s, too little to pass ``use_above_mps``, but the error lasts a few tenths of a
second, and flown as it comes it swings the magnet 2-3 cm about the target. A fix arrives a
latency after its capture: the filter keeps its states and samples of the last
``history_s`` and replays them from the fix's time.

It says nothing until its velocity is known to ``ready_velocity_std_mps`` (a few fixes); a
fix that disagrees by more than ``reset_m`` and ``gate_sigma`` spreads starts it afresh (the
camera found the target again after a gap). It needs all three axes of the accelerometer
with the odometry: the Crazyflie link logs them; the MAVLink link does not read an
accelerometer, and the controller then flies the odometry as before.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from perchpose.control.history import index_at
from perchpose.errors import ControllerConfigError, require_positive

Array = NDArray[np.float64]


@dataclass(frozen=True)
class InertialSettings:
    """enabled : use the filter (off: the controller flies the vehicle's own odometry, as
    before). accel_noise_mps2 : the horizontal acceleration's white noise as a spectral
    density's square root, m/s^2/sqrt(Hz) (the accelerometer's vibration, 0.2 m/s^2 per
    sample at 50-100 Hz, and the attitude's noise, 0.2 deg, with a margin for the
    accelerometer's 30 Hz filter and the attitude sampled a few ms apart). bias_walk_mps3 :
    how fast the acceleration's bias may wander, m/s^2/sqrt(s) (the yaw turns the
    accelerometer's own bias in the world). odometry_error_mps, odometry_error_s : the
    vehicle's velocity estimate's correlated error, its spread at a restart and its time
    constant (a Flow deck's at 1-2 m, as ``sim.flow_deck`` models it); odometry_noise_mps :
    its white noise per sample at the start. learn_s : the time constant over which both are
    learnt from the odometry's residuals, the correlated one within min_odometry_error_mps
    and max_odometry_error_mps. initial_velocity_std_mps, initial_bias_std_mps2 : the
    spreads the filter starts with (the odometry's velocity, a bias of up to 0.1 m/s^2 and an
    attitude 0.5 deg off). fix_std_m, fix_std_per_m : a fix's spread, a floor plus a share
    of the distance to the target. history_s : how far back a late fix is replayed from.
    ready_velocity_std_mps : the velocity's spread under which the filter is ready.
    keep_velocity_std_mps : once ready, the spread it stays ready under (blind under the
    plate, with no fixes, the spread grows; dropping the filter there would switch the
    controller to the odometry's drifted view, centimetres off, mid-alignment).
    gate_sigma, reset_m : a fix further than both from the prediction starts the filter
    afresh. max_correction_mps : the largest correction of the vehicle's velocity estimate
    the controller adds to a setpoint. use_above_mps, use_below_mps : the filter is used
    once the odometry's correlated error is learnt above the first, and left (the odometry
    flown as it comes) once it falls below the second: a white error is better averaged by
    the vehicle's own loop than corrected."""

    enabled: bool = True
    accel_noise_mps2: float = 0.02
    bias_walk_mps3: float = 0.02
    odometry_error_mps: float = 0.04
    odometry_error_s: float = 0.15
    odometry_noise_mps: float = 0.03
    learn_s: float = 2.0
    min_odometry_error_mps: float = 0.005
    max_odometry_error_mps: float = 0.15
    initial_velocity_std_mps: float = 0.1
    initial_bias_std_mps2: float = 0.2
    fix_std_m: float = 0.001
    fix_std_per_m: float = 0.005
    history_s: float = 0.4
    ready_velocity_std_mps: float = 0.02
    keep_velocity_std_mps: float = 0.06
    gate_sigma: float = 6.0
    reset_m: float = 0.05
    max_correction_mps: float = 0.3
    use_above_mps: float = 0.025
    use_below_mps: float = 0.02

    def __post_init__(self) -> None:
        names = (
            "accel_noise_mps2",
            "bias_walk_mps3",
            "odometry_error_mps",
            "odometry_error_s",
            "odometry_noise_mps",
            "learn_s",
            "min_odometry_error_mps",
            "max_odometry_error_mps",
            "initial_velocity_std_mps",
            "initial_bias_std_mps2",
            "fix_std_m",
            "history_s",
            "ready_velocity_std_mps",
            "keep_velocity_std_mps",
            "gate_sigma",
            "reset_m",
            "max_correction_mps",
            "use_above_mps",
            "use_below_mps",
        )
        require_positive(self, names, ControllerConfigError, "inertial ")
        if self.keep_velocity_std_mps < self.ready_velocity_std_mps:
            raise ControllerConfigError(
                f"inertial keep_velocity_std_mps ({self.keep_velocity_std_mps}) must be at "
                f"least ready_velocity_std_mps ({self.ready_velocity_std_mps})"
            )
        if not (math.isfinite(self.fix_std_per_m) and self.fix_std_per_m >= 0):
            raise ControllerConfigError(
                f"inertial fix_std_per_m must be >= 0, got {self.fix_std_per_m}"
            )


# the state's rows: the body's centre relative to the target, its velocity, the
# acceleration's bias, the vehicle's velocity estimate's correlated error (columns: x, y)
R, V, B, E = range(4)


class _Step(NamedTuple):
    """The filter after the flight controller's sample at ``t_s``: its acceleration (held
    until the next sample) and velocity estimate, the state and its covariance (the same for
    both axes: they see the same noise)."""

    t_s: float
    a_mps2: Array
    v_mps: Array
    x: Array
    P: Array


class InertialTracker:
    """The filter; ``sample`` with each of the flight controller's samples, ``fix`` with
    each measured frame; ``state_at`` for the vehicle's position and velocity,
    ``odometry_error`` for what its own velocity estimate is off by."""

    def __init__(self, settings: InertialSettings | None = None) -> None:
        self.settings = settings or InertialSettings()
        self._steps: deque[_Step] = deque()
        self._started = False
        self._fix_t_s = -math.inf
        self.resets = 0
        s = self.settings
        # the odometry's error as learnt from its residuals: correlated, white (variances);
        # taken as white until its residuals say otherwise (the filter is then not used)
        self.error_var = s.min_odometry_error_mps**2
        self.noise_var = s.odometry_noise_mps**2
        self._moments = np.array([self.error_var + self.noise_var, self.error_var])
        self._last_residual: Array | None = None
        self.correlated = False  # the odometry's error is worth correcting (``in_use``)
        self._known_correlated = False  # said so (``assume_correlated``), not learnt
        self._kept = False  # ready, and its velocity's spread still under keep_velocity_std_mps

    @property
    def in_use(self) -> bool:
        """``ready``, and the odometry's error learnt as correlated enough to correct (or said
        to be, ``assume_correlated``)."""
        return self.settings.enabled and self.correlated and self.ready

    def assume_correlated(self) -> None:
        """Take the odometry's error as correlated from now on, however small its residuals
        say it is: the vehicle's estimator is known to leave such an error (a Kalman filter
        fusing a Flow deck's flow). Its size is still learnt."""
        self._known_correlated = self.correlated = True

    @property
    def ready(self) -> bool:
        """Started, and the velocity known to ``ready_velocity_std_mps``; once ready, it
        stays so while the spread is under ``keep_velocity_std_mps`` (``_settle``, after
        each sample and fix: reading it changes nothing)."""
        return self._kept

    def _settle(self) -> None:
        """Whether the filter is ready, from its newest velocity spread, with hysteresis."""
        if not self._started or not self._steps:
            self._kept = False
            return
        s = self.settings
        limit = s.keep_velocity_std_mps if self._kept else s.ready_velocity_std_mps
        self._kept = math.sqrt(float(self._steps[-1].P[V, V])) < limit

    def _predict(self, x: Array, P: Array, a_mps2: Array, dt_s: float) -> tuple[Array, Array]:
        if dt_s <= 0.0:
            return x, P
        s = self.settings
        decay = math.exp(-dt_s / s.odometry_error_s)
        F = np.eye(4)
        F[R, V], F[R, B] = dt_s, -0.5 * dt_s * dt_s
        F[V, B] = -dt_s
        F[E, E] = decay
        G = np.zeros(4)
        G[R], G[V] = 0.5 * dt_s * dt_s, dt_s
        q = s.accel_noise_mps2**2
        Q = np.zeros((4, 4))
        Q[R, R], Q[V, V] = q * dt_s**3 / 3.0, q * dt_s
        Q[R, V] = Q[V, R] = q * dt_s**2 / 2.0
        Q[B, B] = s.bias_walk_mps3**2 * dt_s
        Q[E, E] = self.error_var * (1.0 - decay * decay)
        return F @ x + np.outer(G, a_mps2), F @ P @ F.T + Q

    @staticmethod
    def _update(x: Array, P: Array, H: Array, z: Array, var: float) -> tuple[Array, Array]:
        """A scalar-per-axis measurement ``z = H x`` with variance ``var``."""
        PH = P @ H
        S = float(H @ PH) + var
        K = PH / S
        x = x + np.outer(K, z - H @ x)
        P = P - np.outer(K, PH)
        return x, 0.5 * (P + P.T)

    def _measure_velocity(self, x: Array, P: Array, v_mps: Array) -> tuple[Array, Array]:
        """The flight controller's velocity estimate: the true velocity plus its error."""
        H = np.zeros(4)
        H[V], H[E] = 1.0, 1.0
        return self._update(x, P, H, v_mps, self.noise_var)

    def sample(self, t_s: float, a_mps2: Array, v_mps: Array) -> None:
        """The flight controller's sample at ``t_s``: the horizontal kinematic acceleration
        and its horizontal velocity estimate (world frame, m/s^2, m/s). Samples out of order
        or not finite are ignored."""
        a = np.asarray(a_mps2, np.float64)[:2]
        v = np.asarray(v_mps, np.float64)[:2]
        if not (self.settings.enabled and np.all(np.isfinite(a)) and np.all(np.isfinite(v))):
            return
        if self._steps and t_s <= self._steps[-1].t_s:
            return
        if not self._started:
            x = np.zeros((4, 2))
            x[V] = v
            P = np.zeros((4, 4))
        else:
            last = self._steps[-1]
            x, P = self._predict(last.x, last.P, last.a_mps2, t_s - last.t_s)
            self._learn(v - x[V], t_s - last.t_s)
            x, P = self._measure_velocity(x, P, v)
        self._steps.append(_Step(t_s, a, v, x, P))
        while self._steps and self._steps[0].t_s < t_s - self.settings.history_s:
            self._steps.popleft()
        self._settle()

    def _learn(self, residual: Array, dt_s: float) -> None:
        """Learn how the odometry's velocity error behaves from its residual against the
        filter's own velocity (covariance matching): its variance, and its covariance with
        the previous sample's, which only a correlated error has. A white error (the
        odometry then serves the loop better than a correction would) leaves the correlated
        part near its floor; a Flow deck's raises it."""
        s = self.settings
        previous, self._last_residual = self._last_residual, residual
        if previous is None or dt_s <= 0.0:
            return
        w = min(1.0, dt_s / s.learn_s)
        sample = np.array([float(residual @ residual), float(residual @ previous)]) / 2.0
        self._moments = self._moments + w * (sample - self._moments)
        decay = math.exp(-dt_s / s.odometry_error_s)
        error_var = self._moments[1] / decay
        self.error_var = float(
            np.clip(error_var, s.min_odometry_error_mps**2, s.max_odometry_error_mps**2)
        )
        self.noise_var = max(s.min_odometry_error_mps**2, float(self._moments[0]) - self.error_var)
        if self._known_correlated:
            return  # said so: its size is learnt, the filter's use is not
        size = math.sqrt(self.error_var)
        if size > s.use_above_mps:
            self.correlated = True
        elif size < s.use_below_mps:
            self.correlated = False

    def fix(self, t_capture_s: float, r_m: Array, distance_m: float) -> None:
        """A fix: the body's centre relative to the target (world frame, horizontal) when the
        frame was captured, ``distance_m`` from the target. Replays the samples since."""
        s = self.settings
        r = np.asarray(r_m, np.float64)[:2]
        if not self._steps or not np.all(np.isfinite(r)) or t_capture_s <= self._fix_t_s:
            return  # nothing to place it with, or older than a fix already taken
        i = index_at(self._steps, t_capture_s)
        if i < 0:
            return  # older than the history
        self._fix_t_s = t_capture_s
        std = s.fix_std_m + s.fix_std_per_m * max(0.0, distance_m)
        if self._started:
            self._correct(i, t_capture_s, r, std)
        else:
            self._start(i, t_capture_s, r, std)
        self._settle()

    def _correct(self, i: int, t_s: float, r: Array, std: float) -> None:
        """Take a fix into the filter at ``t_s`` (after sample ``i``) and replay from it; one
        that disagrees beyond the gate starts the filter afresh there."""
        s = self.settings
        step = self._steps[i]
        x, P = self._predict(step.x, step.P, step.a_mps2, t_s - step.t_s)
        innovation = r - x[R]
        spread = math.sqrt(float(P[R, R]) + std * std)
        if float(np.max(np.abs(innovation))) > max(s.reset_m, s.gate_sigma * spread):
            self.resets += 1
            self._start(i, t_s, r, std)
            return
        H = np.zeros(4)
        H[R] = 1.0
        x, P = self._update(x, P, H, r, std * std)
        self._replay(i, t_s, x, P)

    def _start(self, i: int, t_s: float, r: Array, std: float) -> None:
        """Start afresh at a fix: its position, the flight controller's velocity then."""
        s = self.settings
        x = np.zeros((4, 2))
        x[R], x[V] = r, self._steps[i].v_mps
        P = np.diag(
            [
                std * std,
                s.initial_velocity_std_mps**2,
                s.initial_bias_std_mps2**2,
                s.odometry_error_mps**2,
            ]
        )
        self._started = True
        self._replay(i, t_s, x, P)

    def _replay(self, i: int, t_s: float, x: Array, P: Array) -> None:
        """From the state at ``t_s`` (after sample ``i``), predict and update again through
        the samples after it. A fix newer than the last sample leaves the state at the fix's
        time, where the next sample predicts on from."""
        a = self._steps[i].a_mps2
        for j in range(i + 1, len(self._steps)):
            step = self._steps[j]
            x, P = self._predict(x, P, a, step.t_s - t_s)
            x, P = self._measure_velocity(x, P, step.v_mps)
            self._steps[j] = step._replace(x=x, P=P)
            t_s, a = step.t_s, step.a_mps2
        if i == len(self._steps) - 1:
            self._steps[i] = self._steps[i]._replace(t_s=t_s, x=x, P=P)

    def state_at(self, t_s: float) -> tuple[Array, Array] | None:
        """The body's centre relative to the target and its velocity (world frame,
        horizontal) at ``t_s``, predicted from the last sample; None unless ``in_use``."""
        if not self.in_use:
            return None
        last = self._steps[-1]
        x, _ = self._predict(last.x, last.P, last.a_mps2, max(0.0, t_s - last.t_s))
        return x[R].copy(), x[V].copy()

    def velocity_at(self, t_s: float) -> Array | None:
        """The velocity at the last sample, if that was at ``t_s``; None otherwise or unless
        ``in_use``."""
        if not self.in_use or abs(self._steps[-1].t_s - t_s) > 1e-6:
            return None
        velocity: Array = self._steps[-1].x[V].copy()
        return velocity

    def odometry_error(self, t_s: float) -> Array | None:
        """What the flight controller's velocity estimate is off by at ``t_s`` (its
        correlated error at the last sample, decayed to ``t_s``); None unless ``in_use``."""
        if not self.in_use:
            return None
        last = self._steps[-1]
        decay = math.exp(-max(0.0, t_s - last.t_s) / self.settings.odometry_error_s)
        error: Array = decay * last.x[E]
        return error
