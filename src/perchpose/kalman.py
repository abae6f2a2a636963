"""The paper's Kalman filter: one per marker, constant velocity, yaw on the circle.

State x = [psi, psi_dot, tx, tx_dot, ty, ty_dot, tz, tz_dot] in rad, rad/s, m, m/s;
measurement z = [psi, tx, ty, tz]. F is the constant-velocity transition with dt from the frame
timestamps, H picks psi, tx, ty, tz, R = k1 * I4 and Q = k2 * I8 (the paper's form).
The paper does not give k1 and k2; the defaults below are ours (see ``KalmanSettings``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.geometry import angle_diff_rad, wrap_angle_rad

Array = NDArray[np.float64]

H = np.zeros((4, 8))
H[0, 0] = H[1, 2] = H[2, 4] = H[3, 6] = 1.0
_VELOCITIES = np.array([1, 3, 5, 7])


def _check_dropout_rule(alpha: float, n_max: int) -> None:
    """The paper's rule for frames without a measurement: 0 <= alpha <= 1, n_max >= 0."""
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha}")
    if n_max < 0:
        raise ValueError(f"n_max must be >= 0, got {n_max}")


@dataclass(frozen=True)
class KalmanSettings:
    """Settings of the paper's filter.

    k1 : measurement variance, R = k1 * I4 (m^2 and rad^2 alike). Default 1e-5: a 3.2 mm and
        0.18 deg standard deviation, what single-marker PnP gives at about 1 m.
    k2 : process noise per frame, Q = k2 * I8. Default 1e-4: with k2 / k1 = 10 the filter keeps
        up with a decelerating approach (1.5 m to contact in 6 s at 30 frames per second) to
        within 1 % of the distance; k2 = k1 lagged by up to 3.6 % on the same rendered frames.
    alpha : velocity decay per frame without a detection (paper: 0.85).
    n_max : frames a marker may go undetected before its track is dropped (paper: 8).
    p0_position, p0_velocity : initial variances of the position/yaw and velocity states.
    """

    k1: float = 1e-5
    k2: float = 1e-4
    alpha: float = 0.85
    n_max: int = 8
    p0_position: float = 1e-4
    p0_velocity: float = 1.0

    def __post_init__(self) -> None:
        if not (self.k1 > 0 and self.k2 > 0):
            raise ValueError(f"k1 and k2 must be positive, got k1={self.k1}, k2={self.k2}")
        _check_dropout_rule(self.alpha, self.n_max)


def transition(dt_s: float) -> Array:
    """The constant-velocity transition F (8, 8) for a step of ``dt_s`` seconds."""
    F = np.eye(8)
    F[0, 1] = F[2, 3] = F[4, 5] = F[6, 7] = dt_s
    return F


class PaperKalmanFilter:
    """The 8-state filter of one marker. Prior and posterior are both kept.

    x : (8,) state; P : (8, 8) covariance; x_prior, P_prior : after the last predict.
    """

    def __init__(self, z: Array, settings: KalmanSettings) -> None:
        self.settings = settings
        self.R = settings.k1 * np.eye(4)
        self.Q = settings.k2 * np.eye(8)
        self.x = np.zeros(8)
        self.x[[0, 2, 4, 6]] = z
        self.x[0] = wrap_angle_rad(float(z[0]))
        p0 = np.array([settings.p0_position, settings.p0_velocity] * 4)
        self.P = np.diag(p0)
        self.x_prior = self.x.copy()
        self.P_prior = self.P.copy()

    def predict(self, dt_s: float) -> None:
        """Propagate the state by ``dt_s`` seconds."""
        F = transition(dt_s)
        self.x = F @ self.x
        self.x[0] = wrap_angle_rad(float(self.x[0]))
        self.P = F @ self.P @ F.T + self.Q
        self.x_prior = self.x.copy()
        self.P_prior = self.P.copy()

    def decay_velocities(self) -> None:
        """Multiply the velocity states by alpha (a frame without a detection)."""
        self.x[_VELOCITIES] *= self.settings.alpha

    def update(self, z: Array) -> None:
        """Correct with a measurement z = [psi, tx, ty, tz]; the yaw innovation is wrapped.

        Joseph form keeps P symmetric and positive definite.
        """
        y = np.asarray(z, dtype=np.float64) - H @ self.x
        y[0] = angle_diff_rad(float(z[0]), float(self.x[0]))
        S = H @ self.P @ H.T + self.R
        K = np.linalg.solve(S, H @ self.P).T
        self.x = self.x + K @ y
        self.x[0] = wrap_angle_rad(float(self.x[0]))
        I_KH = np.eye(8) - K @ H
        self.P = I_KH @ self.P @ I_KH.T + K @ self.R @ K.T

    @property
    def pose(self) -> Array:
        """(4,) filtered [psi_rad, tx_m, ty_m, tz_m]."""
        return np.asarray(H @ self.x)


class MarkerTrack:
    """A marker's filter plus the paper's lost-marker rule.

    A frame without the marker decays its velocities by alpha and predicts; after ``n_max``
    such frames in a row the track is dropped (``alive`` False) and the next detection starts a
    new filter.
    """

    def __init__(self, settings: KalmanSettings) -> None:
        self.settings = settings
        self.filter: PaperKalmanFilter | None = None
        self.t_s = 0.0
        self.missed = 0

    @property
    def alive(self) -> bool:
        """True while the track has a state to offer."""
        return self.filter is not None

    def measured(self, z: Array, t_s: float) -> None:
        """A detection at ``t_s``: start the filter, or predict and correct."""
        if self.filter is None:
            self.filter = PaperKalmanFilter(z, self.settings)
        else:
            self.filter.predict(t_s - self.t_s)
            self.filter.update(z)
        self.t_s = t_s
        self.missed = 0

    def missed_frame(self, t_s: float) -> None:
        """A frame at ``t_s`` without a detection: coast, or drop after n_max frames."""
        if self.filter is None:
            return
        self.missed += 1
        if self.missed > self.settings.n_max:
            self.filter = None
            return
        self.filter.decay_velocities()
        self.filter.predict(t_s - self.t_s)
        self.t_s = t_s

    def predicted_pose(self, t_s: float) -> Array | None:
        """(4,) [psi, tx, ty, tz] the track expects at ``t_s``, without changing it."""
        if self.filter is None:
            return None
        pose = transition(t_s - self.t_s) @ self.filter.x
        return np.asarray(H @ pose)


@dataclass(frozen=True)
class CovarianceFilterSettings:
    """The filter of the fused pose when each measurement comes with its covariance.

    q_position : spectral density of the white-noise acceleration of x, y, z (m^2/s^3); the
        process noise over a step dt is q [[dt^3/3, dt^2/2], [dt^2/2, dt]] per axis. Default
        0.05: accelerations of a few tenths of m/s^2 (a drone slowing down on its approach) are
        followed without lag.
    q_yaw : the same for yaw (rad^2/s^3).
    alpha, n_max : the paper's rule for frames without a measurement (velocities times alpha
        per frame; after n_max frames the estimate is dropped).
    corner_sigma_px : corner noise per axis the measurement covariance is computed with.
    """

    q_position: float = 0.05
    q_yaw: float = 0.5
    alpha: float = 0.85
    n_max: int = 8
    corner_sigma_px: float = 0.1

    def __post_init__(self) -> None:
        if not (self.q_position > 0 and self.q_yaw > 0 and self.corner_sigma_px > 0):
            raise ValueError("q_position, q_yaw and corner_sigma_px must be positive")
        _check_dropout_rule(self.alpha, self.n_max)


def white_acceleration_noise(dt_s: float, q: Array) -> Array:
    """Process noise (8, 8) of the constant-velocity model for densities q = (yaw, x, y, z)."""
    dt = max(dt_s, 0.0)
    block = np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])
    Q = np.zeros((8, 8))
    for k in range(4):
        Q[2 * k : 2 * k + 2, 2 * k : 2 * k + 2] = q[k] * block
    return Q


class CovarianceTrack:
    """One filter of the fused pose, corrected with each measurement's own covariance, with the
    paper's dropout rule (velocities decay by alpha; dropped after n_max missed frames)."""

    def __init__(self, settings: CovarianceFilterSettings) -> None:
        self.settings = settings
        self.x: Array | None = None
        self.P = np.zeros((8, 8))
        self.t_s = 0.0
        self.missed = 0
        self._q = np.array([settings.q_yaw, settings.q_position, settings.q_position,
                            settings.q_position])  # fmt: skip

    @property
    def alive(self) -> bool:
        return self.x is not None

    @property
    def pose(self) -> Array | None:
        """(4,) [psi_rad, tx_m, ty_m, tz_m], or None."""
        return None if self.x is None else np.asarray(H @ self.x)

    def predicted_pose(self, t_s: float) -> Array | None:
        """(4,) [psi, tx, ty, tz] the filter expects at ``t_s``, without changing it."""
        if self.x is None:
            return None
        return np.asarray(H @ (transition(t_s - self.t_s) @ self.x))

    def _predict(self, t_s: float) -> None:
        assert self.x is not None
        dt = t_s - self.t_s
        F = transition(dt)
        self.x = F @ self.x
        self.x[0] = wrap_angle_rad(float(self.x[0]))
        self.P = F @ self.P @ F.T + white_acceleration_noise(dt, self._q)
        self.t_s = t_s

    def measured(self, z: Array, R: Array, t_s: float) -> None:
        """A measurement z = [psi, tx, ty, tz] with covariance R (4, 4) at ``t_s``."""
        if self.x is None:
            self.x = np.zeros(8)
            self.x[[0, 2, 4, 6]] = z
            self.x[0] = wrap_angle_rad(float(z[0]))
            self.P = np.zeros((8, 8))
            self.P[np.ix_([0, 2, 4, 6], [0, 2, 4, 6])] = R
            self.P[_VELOCITIES, _VELOCITIES] = 1.0
            self.t_s = t_s
            self.missed = 0
            return
        self._predict(t_s)
        y = np.asarray(z, np.float64) - H @ self.x
        y[0] = angle_diff_rad(float(z[0]), float(self.x[0]))
        S = H @ self.P @ H.T + R
        K = np.linalg.solve(S, H @ self.P).T
        self.x = self.x + K @ y
        self.x[0] = wrap_angle_rad(float(self.x[0]))
        I_KH = np.eye(8) - K @ H
        self.P = I_KH @ self.P @ I_KH.T + K @ R @ K.T
        self.missed = 0

    def missed_frame(self, t_s: float) -> None:
        """A frame at ``t_s`` without a measurement: coast, or drop after n_max frames."""
        if self.x is None:
            return
        self.missed += 1
        if self.missed > self.settings.n_max:
            self.x = None
            return
        self.x[_VELOCITIES] *= self.settings.alpha
        self._predict(t_s)
