"""The Kalman filters: the paper's (one per marker) and the fused pose's, both constant
velocity with yaw on the circle, on one set of equations and one rule for missed frames.

State x = [psi, psi_dot, tx, tx_dot, ty, ty_dot, tz, tz_dot] in rad, rad/s, m, m/s;
measurement z = [psi, tx, ty, tz]. F is the constant-velocity transition with dt from the frame
timestamps, H picks psi, tx, ty, tz, R = k1 * I4 and Q = k2 * I8 (the paper's form).
The paper does not give k1 and k2; the defaults below are ours (see ``KalmanSettings``).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.filters.steps import (
    corrected_state,
    gain,
    innovation_covariance,
    joseph_covariance,
    mahalanobis2,
    propagated_covariance,
    propagated_state,
)
from perchpose.geometry import angle_diff_rad, wrap_angle_rad

Array = NDArray[np.float64]

H = np.zeros((4, 8))
H[0, 0] = H[1, 2] = H[2, 4] = H[3, 6] = 1.0
_VELOCITIES = np.array([1, 3, 5, 7])


# The paper's coasting limit: 8 frames at its FPV camera's 30 frames per second.
PAPER_COAST_S = 8.0 / 30.0
# Timestamps built as k / fps carry rounding of about 1e-15 s; the time limit allows this much.
_TIME_SLACK_S = 1e-6


# An innovation this many squared standard deviations out (ten sigma in one dimension) is no
# measurement of the state the filter holds: the target was re-acquired, swapped or jumped.
REINIT_CHI2 = 100.0


def check_track_rule(alpha: float, n_max: int, max_coast_s: float, reinit_chi2: float) -> None:
    """The settings every ``Track`` shares: for frames without a measurement 0 <= alpha <= 1,
    n_max >= 0 and a positive time limit ``max_coast_s``; a positive ``reinit_chi2``."""
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha}")
    if n_max < 0:
        raise ValueError(f"n_max must be >= 0, got {n_max}")
    if not max_coast_s > 0:
        raise ValueError(f"max_coast_s must be positive, got {max_coast_s}")
    if not reinit_chi2 > 0:
        raise ValueError(f"reinit_chi2 must be positive, got {reinit_chi2}")


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
    max_coast_s : seconds a track may go without a detection before it is dropped, whatever
        the number of frames (default: the paper's 8 frames at 30 frames per second). A camera
        that stalls delivers no frames to count; this bound ends the extrapolation anyway.
    reinit_chi2 : a measurement whose innovation has a squared Mahalanobis distance above this
        restarts the filter at it (default 100: ten standard deviations).
    p0_position, p0_velocity : initial variances of the position/yaw and velocity states.
    """

    k1: float = 1e-5
    k2: float = 1e-4
    alpha: float = 0.85
    n_max: int = 8
    max_coast_s: float = PAPER_COAST_S
    reinit_chi2: float = REINIT_CHI2
    p0_position: float = 1e-4
    p0_velocity: float = 1.0

    def __post_init__(self) -> None:
        if not (self.k1 > 0 and self.k2 > 0):
            raise ValueError(f"k1 and k2 must be positive, got k1={self.k1}, k2={self.k2}")
        check_track_rule(self.alpha, self.n_max, self.max_coast_s, self.reinit_chi2)


def transition(dt_s: float) -> Array:
    """The constant-velocity transition F (8, 8) for a step of ``dt_s`` seconds."""
    F = np.eye(8)
    F[0, 1] = F[2, 3] = F[4, 5] = F[6, 7] = dt_s
    return F


class ConstantVelocityFilter:
    """The Kalman equations, written once, for the 8-state constant-velocity model with yaw on
    the circle.

    x : (8,) state [psi, psi_dot, tx, tx_dot, ty, ty_dot, tz, tz_dot]; P : (8, 8) covariance.
    x_prior, P_prior : after the last predict. y : (4,) the last innovation (yaw wrapped),
    S : (4, 4) its covariance.
    P_actual : with ``P0_actual``, the state's covariance when the measurements' noise is
    what ``update_with`` is told it actually is (``R_actual``) while the gains stay those of
    ``R``: the same recursion with the filter's own gains (a fixed-gain filter's error
    covariance, as in a Kalman filter's sensitivity analysis); None otherwise.
    """

    def __init__(self, z: Array, P0: Array, P0_actual: Array | None = None) -> None:
        self.x = np.zeros(8)
        self.x[[0, 2, 4, 6]] = z
        self.x[0] = wrap_angle_rad(float(z[0]))
        self.P = np.asarray(P0, dtype=np.float64).copy()
        self.P_actual = None if P0_actual is None else np.asarray(P0_actual, np.float64).copy()
        self.x_prior = self.x.copy()
        self.P_prior = self.P.copy()
        self.y = np.zeros(4)
        self.S = np.full((4, 4), np.nan)

    def predict_with(self, dt_s: float, Q: Array) -> None:
        """x = F x, P = F P F^T + Q for a step of ``dt_s`` seconds (``filters.steps``)."""
        self.x = propagated_state(self.x, dt_s)
        self.x[0] = wrap_angle_rad(float(self.x[0]))
        self.P = propagated_covariance(self.P, dt_s, Q)
        if self.P_actual is not None:
            self.P_actual = propagated_covariance(self.P_actual, dt_s, Q)
        self.x_prior = self.x.copy()
        self.P_prior = self.P.copy()

    def innovation(self, z: Array, R: Array) -> tuple[Array, Array]:
        """(y, S): the innovation of z = [psi, tx, ty, tz] (yaw wrapped) and its covariance
        for a measurement of covariance R (4, 4)."""
        y = np.asarray(z, dtype=np.float64) - self.x[0::2]
        y[0] = angle_diff_rad(float(z[0]), float(self.x[0]))
        return y, innovation_covariance(self.P, np.asarray(R, np.float64))

    def update_with(self, z: Array, R: Array, R_actual: Array | None = None) -> None:
        """Correct with z = [psi, tx, ty, tz] of covariance R (4, 4); the yaw innovation is
        wrapped. The Joseph form keeps P symmetric and positive definite. ``R_actual``: the
        measurement's actual covariance, carried into ``P_actual`` with the same gain (R
        where it is not given). Raises ``numpy.linalg.LinAlgError`` where the innovation's
        covariance is singular."""
        R = np.asarray(R, np.float64)
        self.correct(*self.innovation(z, R), R, R_actual)

    def correct(self, y: Array, S: Array, R: Array, R_actual: Array | None = None) -> None:
        """``update_with`` given the innovation ``y`` and its covariance ``S`` (as
        ``innovation`` gives them) for a measurement of covariance R (4, 4)."""
        solved, K = gain(self.P, S)
        if not solved:
            raise np.linalg.LinAlgError("singular innovation covariance")
        self.x = corrected_state(self.x, K, y)
        self.x[0] = wrap_angle_rad(float(self.x[0]))
        self.P = joseph_covariance(self.P, K, R)
        if self.P_actual is not None:
            R_a = R if R_actual is None else np.asarray(R_actual, np.float64)
            self.P_actual = joseph_covariance(self.P_actual, K, R_a)
        self.y = y
        self.S = S

    def decay_velocities(self, alpha: float) -> None:
        """Multiply the velocity states by ``alpha`` (a frame without a measurement)."""
        self.x[_VELOCITIES] *= alpha

    @property
    def pose(self) -> Array:
        """(4,) filtered [psi_rad, tx_m, ty_m, tz_m]."""
        return self.x[0::2].copy()

    def predicted_pose(self, dt_s: float) -> Array:
        """(4,) [psi, tx, ty, tz] ``dt_s`` seconds ahead, without changing the filter."""
        return np.asarray(self.x[0::2] + dt_s * self.x[1::2])


class PaperKalmanFilter(ConstantVelocityFilter):
    """The 8-state filter of one marker: R = k1 I4, Q = k2 I8 per step."""

    def __init__(self, z: Array, settings: KalmanSettings) -> None:
        p0 = np.array([settings.p0_position, settings.p0_velocity] * 4)
        super().__init__(z, np.diag(p0))
        self.settings = settings
        self.R = settings.k1 * np.eye(4)
        self.Q = settings.k2 * np.eye(8)

    def predict(self, dt_s: float) -> None:
        """Propagate the state by ``dt_s`` seconds."""
        self.predict_with(dt_s, self.Q)

    def decay_velocities(self, alpha: float | None = None) -> None:
        """Multiply the velocity states by alpha (default: the settings')."""
        super().decay_velocities(self.settings.alpha if alpha is None else alpha)

    def update(self, z: Array) -> None:
        """Correct with a measurement z = [psi, tx, ty, tz]."""
        self.update_with(z, self.R)


def too_old(age_s: float, max_coast_s: float) -> bool:
    """A newest measurement ``age_s`` old is past the coasting limit ``max_coast_s``."""
    return age_s > max_coast_s + _TIME_SLACK_S


class Track(ABC):
    """A filter plus the rule for frames without a measurement, written once for both filters.

    A frame without a measurement decays the velocities by alpha and predicts; the track is
    dropped (``alive`` False) after ``n_max`` such frames in a row or when its newest
    measurement is more than ``max_coast_s`` old, whichever comes first. A measurement after
    such a gap starts a new filter, and so does one whose innovation the filter's own
    covariance calls impossible (squared Mahalanobis distance over ``reinit_chi2``: a
    re-acquired or swapped target is followed at once instead of over many frames; counted in
    ``reinitialised``).
    """

    def __init__(self, alpha: float, n_max: int, max_coast_s: float, reinit_chi2: float) -> None:
        self.alpha = alpha
        self.n_max = n_max
        self.max_coast_s = max_coast_s
        self.reinit_chi2 = reinit_chi2
        self.reinitialised = 0
        self.filter: ConstantVelocityFilter | None = None
        self.t_s = 0.0
        self.t_measured_s = math.nan
        self.missed = 0

    @property
    def alive(self) -> bool:
        """True while the track has a state to offer."""
        return self.filter is not None

    @property
    def pose_covariance(self) -> Array | None:
        """(4, 4) covariance of ``pose`` [psi, tx, ty, tz] (the filter's), or None."""
        return None if self.filter is None else self.filter.P[0::2, 0::2].copy()

    @property
    def pose(self) -> Array | None:
        """(4,) [psi_rad, tx_m, ty_m, tz_m], or None."""
        return None if self.filter is None else self.filter.pose

    def age_s(self, t_s: float) -> float:
        """Seconds from the newest measurement to ``t_s`` (inf without one)."""
        return math.inf if self.filter is None else t_s - self.t_measured_s

    def _too_old(self, t_s: float) -> bool:
        return too_old(t_s - self.t_measured_s, self.max_coast_s)

    @abstractmethod
    def _start(
        self, z: Array, R: Array | None, R_actual: Array | None = None
    ) -> ConstantVelocityFilter:
        """The first filter of a track."""

    @abstractmethod
    def _noise(self, R: Array | None) -> Array:
        """The measurement covariance (4, 4) to correct with."""

    @abstractmethod
    def _coast(self, dt_s: float) -> None:
        """Predict by ``dt_s`` without a measurement."""

    def _measure(
        self, z: Array, R: Array | None, t_s: float, R_actual: Array | None = None
    ) -> None:
        if self.filter is None or self._too_old(t_s):
            self.filter = self._start(z, R, R_actual)
        else:
            self._coast(t_s - self.t_s)
            R_used = np.asarray(self._noise(R), np.float64)
            y, S = self.filter.innovation(z, R_used)
            if mahalanobis2(y, S) > self.reinit_chi2:
                self.filter = self._start(z, R, R_actual)
                self.reinitialised += 1
            else:
                self.filter.correct(y, S, R_used, R_actual)
        self.t_s = self.t_measured_s = t_s
        self.missed = 0

    def missed_frame(self, t_s: float) -> None:
        """A frame at ``t_s`` without a measurement: coast, or drop the track."""
        if self.filter is None:
            return
        self.missed += 1
        if self.missed > self.n_max or self._too_old(t_s):
            self.filter = None
            return
        self.filter.decay_velocities(self.alpha)
        self._coast(t_s - self.t_s)
        self.t_s = t_s

    def predicted_pose(self, t_s: float) -> Array | None:
        """(4,) [psi, tx, ty, tz] the track expects at ``t_s``, without changing it."""
        return None if self.filter is None else self.filter.predicted_pose(t_s - self.t_s)


class MarkerTrack(Track):
    """The paper's filter of one marker with its lost-marker rule."""

    filter: PaperKalmanFilter | None

    def __init__(self, settings: KalmanSettings) -> None:
        super().__init__(settings.alpha, settings.n_max, settings.max_coast_s, settings.reinit_chi2)
        self.settings = settings

    def _start(self, z: Array, R: Array | None, R_actual: Array | None = None) -> PaperKalmanFilter:
        return PaperKalmanFilter(z, self.settings)

    def _noise(self, R: Array | None) -> Array:
        assert self.filter is not None
        return self.filter.R

    def _coast(self, dt_s: float) -> None:
        assert self.filter is not None
        self.filter.predict(dt_s)

    def measured(self, z: Array, t_s: float) -> None:
        """A detection z = [psi, tx, ty, tz] at ``t_s``: start the filter, or predict and
        correct."""
        self._measure(z, None, t_s)


@dataclass(frozen=True)
class CovarianceFilterSettings:
    """The filter of the fused pose when each measurement comes with its covariance.

    q_position : spectral density of the white-noise acceleration of x, y, z (m^2/s^3); the
        process noise over a step dt is q [[dt^3/3, dt^2/2], [dt^2/2, dt]] per axis. Default
        0.05: accelerations of a few tenths of m/s^2 (a drone slowing down on its approach) are
        followed without lag.
    q_yaw : the same for yaw (rad^2/s^3).
    alpha, n_max, max_coast_s : the rule for frames without a measurement (velocities times
        alpha per frame; dropped after n_max frames or max_coast_s seconds).
    reinit_chi2 : the innovation (squared Mahalanobis distance) that restarts the filter.
    corner_sigma_px : corner noise per axis the measurement covariance is computed with.
    """

    q_position: float = 0.05
    q_yaw: float = 0.5
    alpha: float = 0.85
    n_max: int = 8
    corner_sigma_px: float = 0.1
    max_coast_s: float = PAPER_COAST_S
    reinit_chi2: float = REINIT_CHI2

    def __post_init__(self) -> None:
        if not (self.q_position > 0 and self.q_yaw > 0 and self.corner_sigma_px > 0):
            raise ValueError("q_position, q_yaw and corner_sigma_px must be positive")
        check_track_rule(self.alpha, self.n_max, self.max_coast_s, self.reinit_chi2)


def white_acceleration_noise(dt_s: float, q: Array) -> Array:
    """Process noise (8, 8) of the constant-velocity model for densities q = (yaw, x, y, z)."""
    dt = max(dt_s, 0.0)
    block = np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])
    Q = np.zeros((8, 8))
    for k in range(4):
        Q[2 * k : 2 * k + 2, 2 * k : 2 * k + 2] = q[k] * block
    return Q


class CovarianceTrack(Track):
    """One filter of the fused pose, corrected with each measurement's own covariance and
    driven by white-noise acceleration, with the same rule for missed frames."""

    def __init__(self, settings: CovarianceFilterSettings) -> None:
        super().__init__(settings.alpha, settings.n_max, settings.max_coast_s, settings.reinit_chi2)
        self.settings = settings
        self._q = np.array([settings.q_yaw, settings.q_position, settings.q_position,
                            settings.q_position])  # fmt: skip
        self._Q_dt_s = math.nan
        self._Q = np.zeros((8, 8))

    def _start(
        self, z: Array, R: Array | None, R_actual: Array | None = None
    ) -> ConstantVelocityFilter:
        assert R is not None
        return ConstantVelocityFilter(
            z, _first_covariance(R), None if R_actual is None else _first_covariance(R_actual)
        )

    def _coast(self, dt_s: float) -> None:
        assert self.filter is not None
        if dt_s != self._Q_dt_s:  # frames usually come at one rate: Q is kept for it
            self._Q, self._Q_dt_s = white_acceleration_noise(dt_s, self._q), dt_s
        self.filter.predict_with(dt_s, self._Q)

    def _noise(self, R: Array | None) -> Array:
        assert R is not None
        return R

    def measured(self, z: Array, R: Array, t_s: float, R_actual: Array | None = None) -> None:
        """A measurement z = [psi, tx, ty, tz] with covariance R (4, 4) at ``t_s``; with
        ``R_actual``, what its covariance actually is (``actual_pose_covariance``)."""
        self._measure(z, R, t_s, R_actual)

    @property
    def actual_pose_covariance(self) -> Array | None:
        """(4, 4) covariance of ``pose`` for the measurements' actual covariances (each
        ``R_actual``) through the gains their assumed ones gave, or None where the track has
        none (no track, or one started without ``R_actual``)."""
        if self.filter is None or self.filter.P_actual is None:
            return None
        return self.filter.P_actual[0::2, 0::2].copy()


def _first_covariance(R: Array) -> Array:
    """A track's first state covariance (8, 8): the measurement's R for the pose, 1 for each
    velocity (m^2/s^2, rad^2/s^2: unknown)."""
    P0 = np.zeros((8, 8))
    P0[np.ix_([0, 2, 4, 6], [0, 2, 4, 6])] = R
    P0[_VELOCITIES, _VELOCITIES] = 1.0
    return P0


class MarkerFilters:
    """The paper's filter of each of a target's markers, advanced together frame by frame."""

    def __init__(self, n_markers: int, settings: KalmanSettings) -> None:
        self.tracks = [MarkerTrack(settings) for _ in range(n_markers)]

    @property
    def reinitialised(self) -> int:
        """Restarts of any marker's filter at an impossible innovation."""
        return sum(tr.reinitialised for tr in self.tracks)

    def advance(self, measured: dict[int, Array], t_s: float) -> None:
        """A frame at ``t_s``: the markers in ``measured`` (index -> [psi, tx, ty, tz]) correct
        their filters, the others coast or are dropped."""
        for i, track in enumerate(self.tracks):
            z = measured.get(i)
            if z is not None:
                track.measured(z, t_s)
            else:
                track.missed_frame(t_s)

    def contributing(self, measured: set[int]) -> dict[int, Array]:
        """The filtered poses that fuse in this frame: the markers measured in it, or, in a
        frame without measurements, every live filter (coasting)."""
        indices = measured or {i for i, tr in enumerate(self.tracks) if tr.alive}
        return {
            i: pose
            for i, tr in enumerate(self.tracks)
            if i in indices and (pose := tr.pose) is not None
        }

    def age_s(self, indices: set[int] | dict[int, Array], t_s: float) -> float:
        """The youngest measurement among ``indices`` (inf without one)."""
        return min((self.tracks[i].age_s(t_s) for i in indices), default=math.inf)

    def predicted_pose(self, marker_index: int, t_s: float) -> Array | None:
        """[psi, x, y, z] the marker's own filter expects at ``t_s``, else any live filter's;
        None without one."""
        tracks = [self.tracks[marker_index], *self.tracks]
        track = next((tr for tr in tracks if tr.alive), None)
        return None if track is None else track.predicted_pose(t_s)


class MarkerPresence:
    """Which of a target's markers are still tracked, under the per-marker filters' rule for
    frames without a measurement (``Track``) but without their filters: a marker measured in
    a frame is tracked; it stays so for ``n_max`` frames in a row without a measurement, and
    while its newest measurement is at most ``max_coast_s`` old."""

    def __init__(self, n_markers: int, n_max: int, max_coast_s: float) -> None:
        self.n_max = n_max
        self.max_coast_s = max_coast_s
        self._measured_s = [math.nan] * n_markers
        self._missed = [0] * n_markers
        self._tracked = [False] * n_markers

    def advance(self, measured: set[int] | frozenset[int], t_s: float) -> None:
        """A frame at ``t_s`` in which the markers ``measured`` were measured."""
        for i in range(len(self._tracked)):
            if i in measured:
                self._measured_s[i], self._missed[i], self._tracked[i] = t_s, 0, True
            elif self._tracked[i]:
                self._missed[i] += 1
                age = t_s - self._measured_s[i]
                if self._missed[i] > self.n_max or too_old(age, self.max_coast_s):
                    self._tracked[i] = False

    def tracked(self, measured: set[int] | frozenset[int]) -> set[int]:
        """The markers that fuse in this frame: those ``measured`` in it, or, in a frame
        without measurements, every marker still tracked (coasting)."""
        return set(measured) or {i for i, on in enumerate(self._tracked) if on}
