"""The pipeline's result values: detections, per-marker poses, and the estimate of one frame.

This is the bottom layer: the links, the controller and the sinks import these types without
the vision pipeline. Every value carries SI units once (metres, radians, seconds); the paper's
centimetres and degrees are derived properties for the output edge (CSV columns, reports).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from perchpose.geometry import rotation_from_angles, rotation_vector_jacobian, yaw_rad

Array = NDArray[np.float64]


def quad_side_px(quad: Array) -> float:
    """Mean side length of a (4, 2) quadrilateral, pixels."""
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = np.asarray(quad, np.float64).tolist()
    sides = math.hypot(x1 - x0, y1 - y0) + math.hypot(x2 - x1, y2 - y1)
    return 0.25 * (sides + math.hypot(x3 - x2, y3 - y2) + math.hypot(x0 - x3, y0 - y3))


def corners_sd_px(covariance_px2: Array) -> float:
    """The corners' standard deviation, px: the root mean of the variances on the diagonal of
    their (8, 8) covariance (x0, y0, x1, ...)."""
    return math.sqrt(float(np.trace(covariance_px2)) / covariance_px2.shape[0])


def corner_noise_px(covariance_px2: Array | None, floor_px: float, without_px: float) -> float:
    """The corner noise (px) to assume for corners with ``covariance_px2``: their standard
    deviation (``corners_sd_px``) but at least ``floor_px``; ``without_px`` where they carry no
    covariance."""
    return without_px if covariance_px2 is None else max(floor_px, corners_sd_px(covariance_px2))


@dataclass(frozen=True)
class MarkerDetection:
    """One target marker found in an image.

    marker_index : index into ``TargetSpec.markers``.
    corners_px : (4, 2) float64, pixels of the original image, ArUco order.
    image_pass : ``raw`` (found on the image itself), ``rectified`` (found on the lens's
    pinhole view, corners mapped back), or ``tracked`` (fitted straight from where tracking
    predicted it and checked by reading its cells, without a quad search).
    corner_covariance_px2 : (8, 8) covariance of the corners (px^2; x0, y0, x1, ...) where
    the corner fit gives one (the edge fit), else None.
    """

    marker_index: int
    corners_px: Array
    image_pass: Literal["raw", "rectified", "tracked"]
    corner_covariance_px2: Array | None = field(default=None, repr=False, compare=False)

    @cached_property
    def side_px(self) -> float:
        """Mean side length in pixels."""
        return quad_side_px(self.corners_px)


@dataclass(frozen=True)
class MarkerPose:
    """The pose of the target measured from one marker.

    T_camera_target : (4, 4) float64, metres.
    reproj_rms_px : RMS distance between detected and reprojected corners, pixels.
    alt_reproj_rms_px : the same for the other IPPE solution (inf if there was none).
    ambiguous : the two solutions were too close to tell apart by reprojection alone.
    alt_T_camera_target : (4, 4) the other IPPE solution, or None.
    """

    marker_index: int
    T_camera_target: Array
    reproj_rms_px: float
    alt_reproj_rms_px: float
    ambiguous: bool
    alt_T_camera_target: Array | None = None

    @property
    def yaw_rad(self) -> float:
        """Yaw of the target in the camera frame, radians."""
        return yaw_rad(self.T_camera_target[:3, :3])

    @property
    def t_m(self) -> Array:
        """Target centre in the camera frame, (3,) metres."""
        return self.T_camera_target[:3, 3]

    @property
    def filter_z(self) -> Array:
        """The pose as the filters measure it: (4,) [psi_rad, x_m, y_m, z_m]."""
        return np.array([self.yaw_rad, *self.t_m])


@dataclass(frozen=True)
class PoseFailure:
    """A marker whose pose could not be computed, and why. Falsy."""

    marker_index: int
    reason: str

    def __bool__(self) -> bool:
        return False


@dataclass(frozen=True)
class MarkerState:
    """What one marker contributed to a frame.

    label : ``DICTIONARY:id``.
    detection : the detected corners, or None.
    measurement : the raw per-frame pose, or None (not detected, or rejected).
    rejected : why a detected marker gave no measurement ('' if it did).
    filtered_pose : (4,) [yaw_rad, x_m, y_m, z_m] of the marker's filter after this frame, or None.
    missed_frames : consecutive frames without a measurement.
    contributing : the marker's filtered pose went into the fused estimate.
    border : how the corners were corrected where one side's border read wider than the
        others ('' where none was; ``perchpose.detection.borders``).
    """

    label: str
    detection: MarkerDetection | None
    measurement: MarkerPose | None
    rejected: str
    filtered_pose: Array | None
    missed_frames: int
    contributing: bool
    border: str = ""


@dataclass(frozen=True)
class Timings:
    """Wall-clock milliseconds spent in each step of one update: finding the markers' quads
    (``detect_ms``), fitting their corners to the image (``corners_ms``), each marker's pose
    (``pose_ms``), the per-marker filters (``filter_ms``) and the fusion (``fuse_ms``: with the
    covariance fusion, its joint pose and its filter)."""

    detect_ms: float = 0.0
    pose_ms: float = 0.0
    filter_ms: float = 0.0
    total_ms: float = 0.0
    corners_ms: float = 0.0
    fuse_ms: float = 0.0

    STAGES = ("detect", "corners", "pose", "filter", "fuse")

    def stage_ms(self, stage: str) -> float:
        """The milliseconds of one of ``STAGES``."""
        if stage not in self.STAGES:
            raise ValueError(f"unknown stage {stage!r} (one of {', '.join(self.STAGES)})")
        return float(getattr(self, f"{stage}_ms"))


NO_POSITION = (math.nan, math.nan, math.nan)

# The first columns of every per-frame pose file (track files, truth.csv): the public contract.
POSE_COLUMNS = ("frame", "t_s", "valid", "stage", "x_cm", "y_cm", "z_cm", "yaw_deg")


@dataclass(frozen=True)
class Estimate:
    """The target's pose in the camera frame for one frame (DESIGN section 2), in SI units.

    t_s : the frame's capture time, seconds.
    valid : there is a pose to act on.
    stage : 0 no estimate, 1 outer marker only, 2 both, 3 inner only.
    t_camera_target_m : (x, y, z) target centre in the camera frame, metres (NaN if not valid).
    yaw_rad : atan2(R[1,0], R[0,0]) of R_camera_target, radians in (-pi, pi] (NaN if not valid).
    markers : per-marker contributions (empty when the pose did not come from images).
    timings : time spent on the frame.
    age_s : seconds since the newest measurement the pose rests on (0 when this frame measured
        the target; a coasting filter's extrapolation is older). Links refuse poses older than
        their limit.
    skipped : what the detection left out of this frame to stay within its time budget
        (``PerchingEstimator(budget_ms=...)``): ``pattern fit m{i}``, ``search`` (the
        search after tracking lost a marker, or the thorough whole-frame search of a frame
        without the target), ``glare search`` or ``second search`` (a frame's look the second
        way, at a clip level or through the lens's pinhole view), ``interval search``
        (tracking's periodic whole-frame search for the markers it lacks, put off to a later
        frame).
    latency_s : seconds from the frame's capture (or, for files, its reading) to this estimate,
        where the caller knows it (``perchpose track`` does); NaN otherwise.
    roll_rad, pitch_rad : the tilt of the target's plane (``geometry.tilt_rad``: 0 when it
        faces the camera); with ``yaw_rad`` the whole rotation (``T_camera_target``). NaN
        when unknown.
    covariance_flat : the 36 entries (row by row) of ``covariance``; empty when unknown.
    grabbed_s : ``time.monotonic()`` when its frame was grabbed, where the caller knows it
        (``perchpose track`` does); NaN otherwise.
    camera_latency_s : the camera chain's glass-to-grab latency the caller subtracted
        (``perchpose track --camera-latency-ms``): the frame was captured at ``captured_s``,
        ``grabbed_s`` minus it. The pilots count an estimate's age from there, and the MAVLink
        link maps it to the autopilot's clock (TIMESYNC) for ``time_usec``.

    ``x_cm``, ``y_cm``, ``z_cm`` and ``yaw_deg`` are the same pose in the paper's units.
    """

    t_s: float
    valid: bool
    stage: int
    t_camera_target_m: tuple[float, float, float] = NO_POSITION
    yaw_rad: float = math.nan
    markers: tuple[MarkerState, ...] = ()
    timings: Timings = field(default_factory=Timings)
    age_s: float = 0.0
    skipped: tuple[str, ...] = ()
    latency_s: float = math.nan
    roll_rad: float = math.nan
    pitch_rad: float = math.nan
    covariance_flat: tuple[float, ...] = ()
    grabbed_s: float = math.nan
    camera_latency_s: float = 0.0

    @property
    def captured_s(self) -> float:
        """``time.monotonic()`` at the frame's capture (NaN where the grab time is unknown)."""
        return self.grabbed_s - self.camera_latency_s

    @classmethod
    def none(cls, t_s: float, markers: tuple[MarkerState, ...] = ()) -> Estimate:
        """No pose for the frame at ``t_s``."""
        return cls(t_s, False, 0, markers=markers)

    @classmethod
    def of_pose(
        cls,
        t_s: float,
        t_camera_target_m: tuple[float, float, float] | Array,
        yaw_rad: float,
        stage: int = 2,
        age_s: float = 0.0,
    ) -> Estimate:
        """A valid estimate of a known pose (a simulation's truth, a replay, a test)."""
        x, y, z = (float(v) for v in t_camera_target_m)
        return cls(t_s, True, stage, (x, y, z), float(yaw_rad), age_s=age_s)

    @property
    def t_m(self) -> Array:
        """(3,) target centre in the camera frame, metres."""
        return np.array(self.t_camera_target_m, dtype=np.float64)

    @property
    def T_camera_target(self) -> Array:
        """(4, 4) the fused pose, metres: the rotation from yaw, roll and pitch (a tilt not
        known is taken as none: the target facing the camera); NaN when not valid."""
        if not self.valid:
            return np.full((4, 4), np.nan)
        roll = self.roll_rad if math.isfinite(self.roll_rad) else 0.0
        pitch = self.pitch_rad if math.isfinite(self.pitch_rad) else 0.0
        T = np.eye(4)
        T[:3, :3] = rotation_from_angles(self.yaw_rad, roll, pitch)
        T[:3, 3] = self.t_m
        return T

    @property
    def covariance(self) -> Array:
        """(6, 6) covariance of the pose in the camera frame: [x, y, z] in m^2, then a small
        rotation vector about the camera's axes (``R_true = exp([w]) R``) in rad^2; NaN when
        unknown (``PerchingEstimator`` gives it with both fusions; see ``Fused``)."""
        if len(self.covariance_flat) != 36:
            return np.full((6, 6), np.nan)
        return np.array(self.covariance_flat, np.float64).reshape(6, 6)

    @property
    def std(self) -> tuple[float, float, float, float]:
        """Standard deviations of x, y, z (m) and of yaw (rad) from ``covariance`` (NaN when
        unknown)."""
        C = self.covariance
        if not np.all(np.isfinite(C)) or not math.isfinite(self.pitch_rad):
            return (math.nan,) * 4
        J = rotation_vector_jacobian(self.yaw_rad, self.pitch_rad)
        angles = np.linalg.solve(J, np.linalg.solve(J, C[3:, 3:]).T)
        x, y, z, yaw = (math.sqrt(max(0.0, float(v))) for v in (*np.diag(C)[:3], angles[2, 2]))
        return x, y, z, yaw

    @property
    def finite(self) -> bool:
        """Every pose field is a finite number."""
        return all(math.isfinite(v) for v in (*self.t_camera_target_m, self.yaw_rad))

    @property
    def x_cm(self) -> float:
        return self.t_camera_target_m[0] * 100.0

    @property
    def y_cm(self) -> float:
        return self.t_camera_target_m[1] * 100.0

    @property
    def z_cm(self) -> float:
        return self.t_camera_target_m[2] * 100.0

    @property
    def yaw_deg(self) -> float:
        return math.degrees(self.yaw_rad)

    @property
    def detected(self) -> tuple[int, ...]:
        """Indices of the markers measured in this frame."""
        return tuple(i for i, m in enumerate(self.markers) if m.measurement is not None)

    @property
    def measured_label(self) -> str:
        """The markers measured in this frame as the track file names them: ``m0+m1``, ``m1``,
        or empty."""
        return "+".join(f"m{i}" for i in self.detected)

    @property
    def predicted(self) -> bool:
        """A valid pose that no measurement of this frame backs: the filter's prediction from
        the newest one, ``age_s`` ago (a coasted frame of a dropout)."""
        return self.valid and self.age_s > 0.0
