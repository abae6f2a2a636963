"""Per-marker pose: IPPE square PnP with both solutions considered, each refined to the least
squares of its reprojection errors (``pnp.refine_pose``)."""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.camera.lens import Lens, lens_project
from perchpose.numeric.jit import compiled
from perchpose.pose.refine import refine_pose, rotation_of
from perchpose.target import MarkerSpec
from perchpose.values import MarkerPose, PoseFailure

Array = NDArray[np.float64]

# Two IPPE solutions whose reprojection errors are within this factor are called ambiguous,
# and the one closer to the previous rotation is kept.
AMBIGUITY_RATIO = 2.0
# Beyond that, the solution closer to the expected rotation by more than FLIP_DEG still wins
# while its reprojection error is under FLIP_RATIO times the other's, or under FLIP_FLOOR_PX:
# four corners leave two degrees of freedom to the residual, so with corner noise of a tenth of
# a pixel (a small marker on blurred images) either solution may reproject to 0.01 px or
# 0.1 px by chance, and a ratio of two such numbers says nothing. When both reproject under
# FLIP_FLOOR_PX, the one closer to the expected rotation wins by any margin (nearly head-on the
# two lie only a few degrees apart).
FLIP_DEG = 5.0
FLIP_RATIO = 4.0
FLIP_FLOOR_PX = 0.25
# IPPE runs on normalised coordinates: the identity for a camera matrix
_NORMALISED = np.eye(3)


def rotation_angle_rad(R_a: Array, R_b: Array) -> float:
    """Angle of the rotation taking ``R_b`` to ``R_a``, radians in [0, pi]."""
    c = (float(np.vdot(R_a, R_b)) - 1.0) / 2.0  # trace(R_a^T R_b)
    return math.acos(max(-1.0, min(1.0, c)))


def reprojection_rms_px(
    camera: CameraModel, T_camera_target: Array, points_target_m: Array, uv_px: Array
) -> float:
    """RMS pixel distance between ``uv_px`` (N, 2) and the projection of points (N, 3)."""
    return _reprojection_rms_compiled(
        camera.compiled_lens,
        np.ascontiguousarray(T_camera_target, np.float64),
        np.ascontiguousarray(points_target_m, np.float64),
        np.ascontiguousarray(uv_px, np.float64),
    )


@compiled
def _reprojection_rms_compiled(lens: Lens, T: Array, points_m: Array, uv_px: Array) -> float:
    """``reprojection_rms_px`` through the lens of ``CameraModel.compiled_lens``."""
    n = points_m.shape[0]
    p = np.empty((n, 3))
    for i in range(n):
        for j in range(3):
            s = T[j, 0] * points_m[i, 0] + T[j, 1] * points_m[i, 1] + T[j, 2] * points_m[i, 2]
            p[i, j] = s + T[j, 3]
    uv, in_front = lens_project(lens[0], p, lens[1], lens[2])
    total = 0.0
    for i in range(n):
        if not in_front[i]:
            return math.inf
        dx, dy = uv[i, 0] - uv_px[i, 0], uv[i, 1] - uv_px[i, 1]
        total += dx * dx + dy * dy
    return math.sqrt(total / n)


@compiled
def _refined_solution(
    points_marker_m: Array, xy: Array, rvec: Array, tvec: Array, T_marker_target: Array
) -> tuple[Array, bool]:
    """One IPPE solution (``rvec``, ``tvec``: the marker's pose) refined (``refine_pose``)
    and carried to the target's centre: ``T_camera_target`` (4, 4), and whether the marker
    lies in front of the camera."""
    R, t, _ = refine_pose(points_marker_m, xy, rotation_of(rvec[0], rvec[1], rvec[2]), tvec)
    T = np.zeros((4, 4))
    for i in range(3):
        for j in range(4):
            s = R[i, 0] * T_marker_target[0, j] + R[i, 1] * T_marker_target[1, j]
            s += R[i, 2] * T_marker_target[2, j]
            T[i, j] = s + t[i] * T_marker_target[3, j]
    T[3, 3] = 1.0
    return T, t[2] > 0.0


def solve_marker_pose(
    camera: CameraModel,
    marker: MarkerSpec,
    marker_index: int,
    corners_px: Array,
    R_previous: Array | None = None,
) -> MarkerPose | PoseFailure:
    """Pose of the target from one marker's four corners.

    corners_px : (4, 2) float, pixels of the original image, ArUco order.
    R_previous : (3, 3) rotation ``R_camera_target`` of the last accepted pose, used to choose
        between the two IPPE solutions when reprojection cannot tell them apart.
    """
    xy = camera.normalize(corners_px)
    if not np.isfinite(xy).all():
        return PoseFailure(marker_index, "corner outside the lens model")
    obj = marker.corners_marker_m.reshape(4, 1, 3)
    img = xy.reshape(4, 1, 2)
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            obj, img, _NORMALISED, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
    except cv2.error:
        return PoseFailure(marker_index, "degenerate corners")
    if n == 0:
        return PoseFailure(marker_index, "no PnP solution")
    T_marker_target = marker.T_marker_target
    candidates: list[tuple[float, Array]] = []
    points_marker_m = np.ascontiguousarray(marker.corners_marker_m)
    for rvec, tvec in zip(rvecs, tvecs, strict=True):
        T_camera_target, in_front = _refined_solution(
            points_marker_m,
            xy,
            np.asarray(rvec, np.float64).reshape(3),
            np.asarray(tvec, np.float64).reshape(3),
            T_marker_target,
        )
        if not in_front:
            continue
        err = reprojection_rms_px(camera, T_camera_target, marker.corners_target_m, corners_px)
        candidates.append((err, T_camera_target))
    if not candidates:
        return PoseFailure(marker_index, "marker behind the camera")
    candidates.sort(key=lambda c: c[0])
    best_err, best_T = candidates[0]
    alt_err, alt_T = candidates[1] if len(candidates) > 1 else (math.inf, None)
    ambiguous = alt_err < AMBIGUITY_RATIO * max(best_err, 1e-3)
    if R_previous is not None and alt_T is not None:
        # the rotation expected from before scores the two solutions too: when reprojection
        # cannot tell them apart, the closer one wins; a solution far (over FLIP_DEG) from the
        # expected rotation loses to one that agrees with it unless it reprojects several
        # times better (a small marker seen head-on flips between them on noise alone)
        d_best = rotation_angle_rad(best_T[:3, :3], R_previous)
        d_alt = rotation_angle_rad(alt_T[:3, :3], R_previous)
        agrees = d_alt < d_best - math.radians(FLIP_DEG)
        # both under the floor, reprojection cannot tell them apart either
        indistinct = ambiguous or alt_err < FLIP_FLOOR_PX
        if (indistinct and d_alt < d_best) or (agrees and alt_err < FLIP_RATIO * best_err):
            best_err, best_T, alt_err, alt_T = alt_err, alt_T, best_err, best_T
    if not math.isfinite(best_err):
        return PoseFailure(marker_index, "reprojection failed")
    return MarkerPose(marker_index, best_T, best_err, alt_err, ambiguous, alt_T)
