"""The covariance fusion: one PnP over every corner of every marker measured in the frame, its
covariance from the Jacobian and the corners' noise, and one filter of the fused pose that owns
its own state. Its stage is the paper's, from the markers that contribute (those measured in the
frame; in a frame without measurements, those still tracked under the per-marker filters' rule,
``MarkerPresence``, which it keeps itself), so that both fusions report the same stages."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.filters.kalman import (
    CovarianceFilterSettings,
    CovarianceTrack,
    KalmanSettings,
    MarkerPresence,
)
from perchpose.fusion.base import STAGE_NONE, Fused, stage_of
from perchpose.fusion.transport import angles_covariance, camera_covariance
from perchpose.geometry import tilt_rad, yaw_rad
from perchpose.numeric.linalg import sandwiched
from perchpose.pose.joint import measurement_jacobian, solve_joint_pose
from perchpose.target import TargetSpec
from perchpose.values import MarkerDetection, MarkerPose, corner_noise_px

Array = NDArray[np.float64]


class _FadingSums:
    """A ratio pooled over frames: each frame adds to a numerator and a denominator, and both
    fade with a time constant of ``frames`` frames."""

    def __init__(self, frames: float, numerator: float = 0.0, denominator: float = 0.0) -> None:
        self.keep = math.exp(-1.0 / frames)
        self.numerator = numerator
        self.denominator = denominator

    def _pool(self, numerator: float, denominator: float) -> None:
        self.numerator = self.keep * self.numerator + numerator
        self.denominator = self.keep * self.denominator + denominator


class CornerNoise(_FadingSums):
    """The corners' noise per axis, pooled from the joint poses' residuals: each frame adds
    its squared residuals and their degrees of freedom (2 per corner, less the pose's 6), and
    both pools fade with a time constant of ``frames`` frames. Before the pools hold anything
    it is ``prior_px``, which also weighs as ``prior_dof`` degrees of freedom; it never goes
    under ``floor_px`` (a noise-free render would otherwise claim certainty)."""

    def __init__(
        self,
        prior_px: float,
        frames: float = 30.0,
        prior_dof: float = 1.0,
        floor_px: float = 0.005,
    ) -> None:
        super().__init__(frames, prior_px**2 * prior_dof, prior_dof)
        self.floor_px2 = floor_px**2

    def add(self, sum_squares_px2: float, dof: float) -> None:
        """One frame's residuals: their sum of squares (px^2) and degrees of freedom."""
        if dof <= 0 or not math.isfinite(sum_squares_px2):
            return
        self._pool(sum_squares_px2, dof)

    @property
    def variance_px2(self) -> float:
        """The pooled variance per axis, px^2."""
        return max(self.floor_px2, self.numerator / self.denominator)


class VarianceFactor(_FadingSums):
    """The corners' covariance's a-posteriori variance factor (``pose.joint.corner_misfit``)
    pooled over frames (``add(observed, expected)``, each frame's ``r^T S^-1 r`` and its
    expected value, both sums fading with a time constant of ``frames`` frames): the observed
    over the expected, never under 1 (1 before any frame); a frame with a non-finite value is
    left out."""

    def __init__(self, frames: float = 30.0) -> None:
        super().__init__(frames)

    def add(self, observed: float, expected: float) -> None:
        if math.isfinite(observed) and math.isfinite(expected):
            self._pool(observed, expected)

    @property
    def factor(self) -> float:
        if not self.denominator > 0:
            return 1.0
        return max(1.0, self.numerator / self.denominator)


class CovarianceFusion:
    """One PnP over every measured marker's corners, through one filter of the fused pose
    corrected with each measurement's own covariance (``CovarianceTrack``). ``marker_rule``:
    the per-marker filters' settings whose rule for frames without a measurement (``n_max``,
    ``max_coast_s``) says which markers a coasting frame still counts (default: the paper's)."""

    def __init__(
        self,
        camera: CameraModel,
        target: TargetSpec,
        settings: CovarianceFilterSettings,
        *,
        use_filter: bool = True,
        marker_rule: KalmanSettings | None = None,
    ) -> None:
        rule = marker_rule or KalmanSettings()
        self.presence = MarkerPresence(len(target.markers), rule.n_max, rule.max_coast_s)
        self.camera = camera
        self.target = target
        self.settings = settings
        self.use_filter = use_filter
        self.track = CovarianceTrack(settings)
        self.noise = CornerNoise(settings.corner_sigma_px)
        self.misfit = VarianceFactor()
        # the target's tilt from the last joint pose, and that pose's covariance over
        # [roll, pitch, yaw, x, y, z]
        self._tilt: tuple[float, float] = (math.nan, math.nan)
        self._angles_covariance: Array | None = None

    @property
    def reinitialised(self) -> int:
        return self.track.reinitialised

    def predicted_pose(self, t_s: float) -> Array | None:
        return self.track.predicted_pose(t_s) if self.track.alive else None

    def _joint(
        self, detections: tuple[MarkerDetection, ...], measurements: dict[int, MarkerPose]
    ) -> tuple[Array, Array, Array | None] | None:
        """This frame's joint pose T_camera_target (4, 4), its covariance over (w, dt) for
        the filter's assumed corner noise (``_assumed_sigma_px``), and from the corners' own
        covariances (None when degenerate); or None."""
        if not measurements:
            return None
        used = tuple(d for d in detections if d.marker_index in measurements)
        start = max(used, key=lambda d: d.side_px).marker_index
        joint = solve_joint_pose(
            self.camera,
            self.target,
            used,
            measurements[start].T_camera_target,
            self._assumed_sigma_px(used),
            corner_covariance_px2=self._corners_covariance_px2(used),
        )
        if joint is None:
            return None
        # the corner noise the frames show, for markers whose corner fit gives no covariance
        n_points = 4 * len(used)
        self.noise.add(joint.reproj_rms_px**2 * n_points, 2 * n_points - 6)
        self.misfit.add(*joint.misfit)
        own = joint.corners_covariance
        return (
            joint.T_camera_target,
            joint.covariance,
            None if own is None else own * self.misfit.factor,
        )

    def _assumed_sigma_px(self, used: tuple[MarkerDetection, ...]) -> Array:
        """The corner noise the filter assumes for each of ``used``: ``corner_sigma_px``, or
        the marker's own where that is larger: its corners' standard deviation from their
        covariance (the edge fit's, or an unfitted quad's), else the noise pooled from the
        joint poses' residuals (``CornerNoise``). So the filter leans on its prediction over
        noisy corners (a quad that could not be fitted, blurred frames)."""
        sigma = self.settings.corner_sigma_px
        pooled = max(sigma, math.sqrt(self.noise.variance_px2))
        return np.array([corner_noise_px(d.corner_covariance_px2, sigma, pooled) for d in used])

    def _corners_covariance_px2(self, used: tuple[MarkerDetection, ...]) -> Array:
        """The corners' own covariance (8N, 8N; px^2): the detection's (the edge fit's, or
        an unfitted quad's), and for a marker without one independent corners at the noise
        pooled from the joint poses' residuals."""
        S = np.zeros((8 * len(used), 8 * len(used)))
        for k, d in enumerate(used):
            own = d.corner_covariance_px2
            block = self.noise.variance_px2 * np.eye(8) if own is None else own
            S[8 * k : 8 * k + 8, 8 * k : 8 * k + 8] = block
        return S

    def fuse(
        self,
        t_s: float,
        detections: tuple[MarkerDetection, ...],
        measurements: dict[int, MarkerPose],
    ) -> Fused:
        self.presence.advance(set(measurements), t_s)
        poses = self.presence.tracked(set(measurements)) if self.use_filter else set(measurements)
        stage = stage_of(poses)
        joint = self._joint(detections, measurements)
        measured: Array | None = None
        if joint is None:
            self.track.missed_frame(t_s)
        else:
            T, covariance, from_corners = joint
            J = measurement_jacobian(T)
            measured = np.array([yaw_rad(T[:3, :3]), *T[:3, 3]])
            if from_corners is None:  # degenerate: independent corners at the pooled noise
                scale = self.noise.variance_px2 / self.settings.corner_sigma_px**2
                from_corners = covariance * scale
            assumed = sandwiched(J, covariance)
            self.track.measured(measured, assumed, t_s, sandwiched(J, from_corners))
            self._tilt = tilt_rad(T[:3, :3])
            self._angles_covariance = angles_covariance(T, from_corners)
        filtered = self.track.pose if stage != STAGE_NONE else None
        pose = filtered if self.use_filter else measured
        if pose is None:
            return Fused(np.full(4, np.nan), STAGE_NONE, frozenset(poses), math.nan)
        age = self.track.age_s(t_s) if self.use_filter else 0.0
        return Fused(pose, stage, frozenset(poses), age, self._tilt, self._covariance(pose))

    def _covariance(self, pose: Array) -> Array | None:
        """The output's covariance, from the corners' own covariances (the edge fit's;
        ``_corners_covariance_px2``, scaled by ``VarianceFactor``): the tilt's from the last
        joint pose; yaw and position from the filter (without it, the joint pose's, whole).
        The filter runs with the independent corner noise it is set to assume
        (``corner_sigma_px``, 0.1 px: a tuning that keeps it steady on analog video; a
        marker's own corner noise where larger, ``_assumed_sigma_px``); its gains come from
        that, and the covariance reported is the one its errors have when the
        measurements' noise is what the corners say while the gains stay those
        (``CovarianceTrack.actual_pose_covariance``), with the filter's own motion model."""
        angles = self._angles_covariance
        if angles is None:
            return None
        if self.use_filter:
            filtered = self.track.actual_pose_covariance
            if filtered is None:
                return None
            angles = angles.copy()
            angles[2:, :] = angles[:, 2:] = 0.0  # the tilt keeps its own block
            angles[2:, 2:] = filtered
        return camera_covariance(float(pose[0]), self._tilt[1], angles)
