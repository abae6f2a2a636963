"""Fusion of the markers into one target pose: the paper's stages and sigma weights, and the
joint pose with its covariance; two strategies behind one interface (``Fusion``).

The paper's fusion (``fuse_paper``, ``PaperFusion``): stage 1, only the outer (largest) marker
-> its pose; stage 3, only inner markers -> their pose; stage 2, both -> per component
``sigma * outer + (1 - sigma) * inner``, yaw on the circle. With more than one inner marker,
the inner markers are averaged first. Its inputs are the per-marker filters' poses.

The covariance fusion (``CovarianceFusion``): one PnP over every corner of every marker
measured in the frame, its covariance from the Jacobian and the corner noise, and one filter of
the fused pose that owns its own state. Its stage is the paper's, from the markers that
contribute, so that both report the same stages.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.errors import FusionFileError
from perchpose.filters.kalman import CovarianceFilterSettings, CovarianceTrack, MarkerFilters
from perchpose.geometry import (
    rotation_vector_jacobian,
    rotation_vector_jacobian_inverse,
    tilt_rad,
    weighted_circular_mean_rad,
    yaw_rad,
)
from perchpose.numeric.linalg import sandwiched
from perchpose.pose.joint import (
    measurement_jacobian,
    pose_covariance,
    solve_joint_pose,
)
from perchpose.target import TargetSpec
from perchpose.values import MarkerDetection, MarkerPose, corner_noise_px

Array = NDArray[np.float64]

STAGE_NONE, STAGE_OUTER, STAGE_BOTH, STAGE_INNER = 0, 1, 2, 3
SIGMA_FIELDS = ("x", "y", "z", "yaw")


@dataclass(frozen=True)
class FusionSigmas:
    """Weights of the outer marker per component (the paper's LMS fit by default)."""

    x: float = 0.275
    y: float = 0.306
    z: float = 0.728
    yaw: float = 0.469

    def __post_init__(self) -> None:
        for name in SIGMA_FIELDS:
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise ValueError(f"sigma_{name} must be in [0, 1], got {value}")

    def as_array(self) -> Array:
        """(4,) [sigma_yaw, sigma_x, sigma_y, sigma_z] in the filter's state order."""
        return np.array([self.yaw, self.x, self.y, self.z])

    def to_dict(self) -> dict[str, float]:
        """The weights by field name, as ``fit-fusion --json`` writes them."""
        return {name: float(getattr(self, name)) for name in SIGMA_FIELDS}

    @staticmethod
    def load(path: str | Path) -> FusionSigmas:
        """The weights of a JSON file with the fields ``x``, ``y``, ``z`` and ``yaw`` at its top
        level (what ``perchpose fit-fusion --json`` writes; other keys are ignored). Raises
        ``FusionFileError`` naming the file and the field at fault."""
        try:
            content = json.loads(Path(path).read_text(encoding="utf-8"))
        except FileNotFoundError as exc:
            raise FusionFileError(f"{path}: file not found") from exc
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise FusionFileError(f"{path}: not a JSON file of fusion weights ({exc})") from exc
        if not isinstance(content, dict):
            raise FusionFileError(f"{path}: expected an object with x, y, z and yaw")
        missing = [name for name in SIGMA_FIELDS if name not in content]
        if missing:
            raise FusionFileError(
                f"{path}: missing {', '.join(missing)} (write the file with "
                "'perchpose fit-fusion DATA --json FILE')"
            )
        values = {}
        for name in SIGMA_FIELDS:
            value = content[name]
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise FusionFileError(f"{path}: {name} must be a number, got {value!r}")
            values[name] = float(value)
        try:
            return FusionSigmas(**values)
        except ValueError as exc:
            raise FusionFileError(f"{path}: {exc}") from exc


def stage_of(indices: set[int] | frozenset[int]) -> int:
    """The paper's stage for the set of contributing marker indices (0 is the outer one)."""
    if not indices:
        return STAGE_NONE
    has_outer = 0 in indices
    has_inner = any(i > 0 for i in indices)
    if has_outer and has_inner:
        return STAGE_BOTH
    return STAGE_OUTER if has_outer else STAGE_INNER


def _mean_pose(poses: list[Array]) -> Array:
    stacked = np.stack(poses)
    out = stacked.mean(axis=0)
    out[0] = weighted_circular_mean_rad(stacked[:, 0], np.ones(len(poses)))
    return np.asarray(out)


def fuse_paper(poses: dict[int, Array], sigmas: FusionSigmas) -> tuple[Array, int]:
    """Fuse per-marker poses [psi_rad, tx_m, ty_m, tz_m] keyed by marker index.

    Returns the fused (4,) pose and the stage; an empty input gives NaNs and stage 0.
    """
    stage = stage_of(set(poses))
    if stage == STAGE_NONE:
        return np.full(4, np.nan), stage
    inner = [p for i, p in poses.items() if i > 0]
    if stage == STAGE_OUTER:
        return poses[0].copy(), stage
    inner_pose = _mean_pose(inner)
    if stage == STAGE_INNER:
        return inner_pose, stage
    s = sigmas.as_array()
    outer_pose = poses[0]
    fused = s * outer_pose + (1.0 - s) * inner_pose
    fused[0] = weighted_circular_mean_rad(
        np.array([outer_pose[0], inner_pose[0]]), np.array([s[0], 1.0 - s[0]])
    )
    return fused, stage


def _residual_pair(outer: Array, inner: Array, truth: Array, circular: bool) -> tuple[Array, Array]:
    """d = outer - inner and r = truth - inner (wrapped to (-pi, pi] when ``circular``)."""
    d = np.asarray(outer, np.float64) - np.asarray(inner, np.float64)
    r = np.asarray(truth, np.float64) - np.asarray(inner, np.float64)
    if circular:
        d = np.remainder(d + np.pi, 2 * np.pi) - np.pi
        r = np.remainder(r + np.pi, 2 * np.pi) - np.pi
    return d, r


def fit_sigma_least_squares(
    outer: Array, inner: Array, truth: Array, circular: bool = False
) -> float:
    """Closed-form sigma in [0, 1] minimising the mean of
    (sigma*outer + (1-sigma)*inner - truth)^2.

    outer, inner, truth : (N,) one component, same unit (radians if ``circular``).
    Writing the fused value as inner + sigma * (outer - inner), the unconstrained minimiser is
    sum(d * r) / sum(d * d) with d = outer - inner and r = truth - inner. The paper's fusion
    is a weighted mean of the two markers, so sigma is held to [0, 1] (``FusionSigmas``); the
    error is a convex quadratic in sigma, so the constrained minimiser is the unconstrained
    one clipped to that range (noise can put it just past 1 when the outer marker is far the
    better one).
    """
    d, r = _residual_pair(outer, inner, truth, circular)
    denominator = float(np.sum(d * d))
    if denominator <= 0.0:
        raise ValueError("the two markers agree exactly: sigma is not determined")
    return min(1.0, max(0.0, float(np.sum(d * r) / denominator)))


def fit_sigma_lms(
    outer: Array,
    inner: Array,
    truth: Array,
    circular: bool = False,
    step: float = 0.5,
    epochs: int = 200,
    tol: float = 1e-9,
    sigma0: float = 0.5,
) -> tuple[float, int]:
    """The paper's iterative Least Mean Squares fit of sigma, minimising E{|e(n)|^2}.

    One normalised LMS update per sample, e(n) = truth - fused, sigma += step * e * d / mean(d^2),
    over the data in order for up to ``epochs`` passes, stopping when a pass moves sigma by less
    than ``tol``. Returns (sigma, passes used). The step is normalised by the data's power so the
    same ``step`` works in centimetres and radians. Each pass ends projected onto [0, 1] (as
    ``fit_sigma_least_squares``), so both fits give weights ``FusionSigmas`` takes.
    """
    d, r = _residual_pair(outer, inner, truth, circular)
    power = float(np.mean(d * d))
    if power <= 0.0:
        raise ValueError("the two markers agree exactly: sigma is not determined")
    mu = step / (power * d.size)
    sigma = sigma0
    for epoch in range(1, epochs + 1):
        before = sigma
        for dn, rn in zip(d, r, strict=True):
            e = rn - sigma * dn
            sigma += mu * e * dn
        sigma = min(1.0, max(0.0, sigma))
        if abs(sigma - before) < tol:
            return sigma, epoch
    return sigma, epochs


@dataclass(frozen=True)
class Fused:
    """A frame's fused pose: ``pose`` (4,) [psi_rad, x_m, y_m, z_m] (NaN when there is none),
    the paper's ``stage``, the markers whose poses took part, and ``age_s``, the time since the
    newest measurement behind it (0 for a measured frame). ``tilt_rad``: (roll, pitch) of the
    target's plane (``geometry.tilt_rad``; NaN when unknown). ``covariance``: (6, 6) over
    [x, y, z] (m) and a small rotation vector about the camera's axes (rad), or None."""

    pose: Array
    stage: int
    contributing: frozenset[int]
    age_s: float
    tilt_rad: tuple[float, float] = (math.nan, math.nan)
    covariance: Array | None = None


def angles_covariance(T: Array, covariance_w_dt: Array) -> Array:
    """A pose covariance over (w, dt) (``pose.joint``) carried to (6, 6) over
    [roll, pitch, yaw, x, y, z] (``geometry.tilt_rad``, ``geometry.yaw_rad``)."""
    _, pitch = tilt_rad(T[:3, :3])
    A = np.eye(6)
    A[:3, :3] = rotation_vector_jacobian_inverse(yaw_rad(T[:3, :3]), pitch)
    return sandwiched(A, np.asarray(covariance_w_dt, np.float64))


def camera_covariance(yaw_rad_: float, pitch_rad: float, covariance_angles: Array) -> Array:
    """A covariance over [roll, pitch, yaw, x, y, z] carried to the estimate's (6, 6) over
    [x, y, z] and a small rotation vector about the camera's axes."""
    B = np.zeros((6, 6))
    B[0, 3] = B[1, 4] = B[2, 5] = 1.0
    B[3:, :3] = rotation_vector_jacobian(yaw_rad_, pitch_rad)
    out = sandwiched(B, np.asarray(covariance_angles, np.float64))
    return np.asarray(0.5 * (out + out.T), np.float64)


class Fusion(Protocol):
    """How a frame's markers become one pose. Each strategy owns the filter state it needs
    beyond the per-marker filters, which the estimator advances before calling ``fuse``."""

    @property
    def reinitialised(self) -> int:
        """Restarts of the strategy's own filter."""
        ...

    def fuse(
        self,
        t_s: float,
        detections: tuple[MarkerDetection, ...],
        measurements: dict[int, MarkerPose],
        markers: MarkerFilters,
    ) -> Fused:
        """The fused pose of the frame at ``t_s``."""
        ...

    def predicted_pose(self, t_s: float) -> Array | None:
        """[psi, x, y, z] the strategy's own filter expects at ``t_s``; None without one."""
        ...


def _marker_poses(
    measurements: dict[int, MarkerPose], markers: MarkerFilters, use_filter: bool
) -> dict[int, Array]:
    """The poses that fuse: the filtered poses (``MarkerFilters.contributing``), or this
    frame's raw measurements without the filter."""
    if not use_filter:
        return {i: m.filter_z for i, m in measurements.items()}
    return markers.contributing(set(measurements))


class PaperFusion:
    """The paper's fusion of the per-marker filters with fixed sigmas, by stage.

    With ``camera``, ``target`` and ``corner_sigma_px`` it also gives the target's tilt and a
    covariance: those of the frame's fused measurement (each measured marker's pose
    covariance from its own corners, weighed as the poses are). The paper's filters have no
    calibrated noise model, so their smoothing is not in it; a frame the filters bridge
    without a measurement has none."""

    reinitialised = 0

    def __init__(
        self,
        sigmas: FusionSigmas,
        *,
        use_filter: bool = True,
        camera: CameraModel | None = None,
        target: TargetSpec | None = None,
        corner_sigma_px: float = 0.0,
    ) -> None:
        self.sigmas = sigmas
        self.use_filter = use_filter
        self.camera = camera
        self.target = target
        self.corner_sigma_px = corner_sigma_px
        self._tilt: tuple[float, float] = (math.nan, math.nan)

    def _measured_uncertainty(
        self, measurements: dict[int, MarkerPose], contributing: set[int]
    ) -> tuple[tuple[float, float], Array | None] | None:
        """The weighed tilt and covariance over [roll, pitch, yaw, x, y, z] of the markers
        measured in this frame that take part, or None."""
        camera, target = self.camera, self.target
        used = {i: m for i, m in measurements.items() if i in contributing}
        if camera is None or target is None or not used or not self.corner_sigma_px > 0:
            return None
        tilts: dict[int, Array] = {}
        covariances: dict[int, Array | None] = {}
        for i, m in used.items():
            T = m.T_camera_target
            tilts[i] = np.array(tilt_rad(T[:3, :3]))
            points = target.markers[i].corners_target_m
            c = pose_covariance(camera, T, points, self.corner_sigma_px)
            covariances[i] = None if c is None else angles_covariance(T, c)
        # the inner markers are averaged first, as their poses are (``fuse_paper``)
        groups = [g for g in ([i for i in used if i == 0], [i for i in used if i > 0]) if g]
        tilt_g = [np.mean([tilts[i] for i in g], axis=0) for g in groups]
        cov_g: list[Array | None] = []
        for g in groups:
            covs = [covariances[i] for i in g]
            known = [c for c in covs if c is not None]
            cov_g.append(
                sum(known, np.zeros((6, 6))) / len(g) ** 2 if len(known) == len(g) else None
            )
        if len(groups) == 1:
            return (float(tilt_g[0][0]), float(tilt_g[0][1])), cov_g[0]
        s = self.sigmas.as_array()  # [yaw, x, y, z]: the outer marker's weights
        w = np.array([s[0], s[0], s[0], s[1], s[2], s[3]])
        tilt = w[0] * tilt_g[0] + (1.0 - w[0]) * tilt_g[1]
        cov_o, cov_i = cov_g
        if cov_o is None or cov_i is None:
            return (float(tilt[0]), float(tilt[1])), None
        W, V = np.diag(w), np.diag(1.0 - w)
        return (float(tilt[0]), float(tilt[1])), W @ cov_o @ W + V @ cov_i @ V

    def fuse(
        self,
        t_s: float,
        detections: tuple[MarkerDetection, ...],
        measurements: dict[int, MarkerPose],
        markers: MarkerFilters,
    ) -> Fused:
        poses = _marker_poses(measurements, markers, self.use_filter)
        pose, stage = fuse_paper(poses, self.sigmas)
        age = 0.0 if measurements or not self.use_filter else markers.age_s(poses, t_s)
        measured = self._measured_uncertainty(measurements, set(poses))
        covariance = None
        if measured is not None:
            self._tilt, angles = measured
            if angles is not None and stage != STAGE_NONE:
                covariance = camera_covariance(float(pose[0]), self._tilt[1], angles)
        tilt = self._tilt if stage != STAGE_NONE else (math.nan, math.nan)
        return Fused(pose, stage, frozenset(poses), age, tilt, covariance)

    def predicted_pose(self, t_s: float) -> Array | None:
        return None


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
    corrected with each measurement's own covariance (``CovarianceTrack``)."""

    def __init__(
        self,
        camera: CameraModel,
        target: TargetSpec,
        settings: CovarianceFilterSettings,
        *,
        use_filter: bool = True,
    ) -> None:
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
        markers: MarkerFilters,
    ) -> Fused:
        poses = _marker_poses(measurements, markers, self.use_filter)
        stage = stage_of(set(poses))
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
