"""PerchingEstimator: image + time in, filtered and fused target pose out."""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.detection.borders import BorderProfiles, border_problem, moved_in
from perchpose.detection.detector import (
    PATTERN_BESIDE_RATIO,
    THOROUGH_EVERY,
    CornerMethod,
    MarkerDetector,
)
from perchpose.detection.windows import extrapolated
from perchpose.errors import PerchposeError, TimestampError
from perchpose.filters.kalman import CovarianceFilterSettings, KalmanSettings, MarkerFilters
from perchpose.fusion.base import STAGE_NONE, Fusion
from perchpose.fusion.consistency import DISAGREE_CHI2, disagreements
from perchpose.fusion.covariance import CovarianceFusion
from perchpose.fusion.paper import FusionSigmas, PaperFusion
from perchpose.geometry import angle_diff_rad, rot_z, yaw_rad
from perchpose.pose.marker import solve_marker_pose
from perchpose.target import TargetSpec
from perchpose.values import (
    Estimate,
    MarkerDetection,
    MarkerPose,
    MarkerState,
    PoseFailure,
    Timings,
    corner_noise_px,
)

FusionMethod = Literal["paper", "covariance"]
FUSION_METHODS: tuple[FusionMethod, ...] = ("paper", "covariance")

Array = NDArray[np.float64]


def _flat(covariance: Array | None) -> tuple[float, ...]:
    """The 36 entries of a (6, 6) covariance, or none when it is unknown or not finite."""
    if covariance is None:
        return ()
    entries: list[float] = covariance.reshape(-1).tolist()
    return tuple(entries) if all(map(math.isfinite, entries)) else ()


class PerchingEstimator:
    """The paper's pipeline: detect, per-marker PnP, per-marker Kalman filter, staged fusion.

    Keyword options:
    kalman : KalmanSettings (k1, k2, alpha, n_max).
    sigmas : FusionSigmas (paper's LMS values by default).
    max_reproj_px : a marker pose whose corner reprojection RMS exceeds this is rejected.
    markers : indices of the target's markers to use (default all); the others are ignored, for
        ablations such as "outer marker only".
    use_filter : False fuses each frame's raw measurements without the Kalman filter (no
        coasting: a frame without a detection has no estimate).
    corners : ``"edges"`` (default: corners from the four fitted border edges, unbiased) or
        ``"subpix"`` (OpenCV's ``cornerSubPix``, about 0.2 px inside the true corners).
    disagree_chi2 : markers whose positions are further apart than this squared Mahalanobis
        distance (with ``covariance_filter.corner_sigma_px`` corner noise) are not fused: the
        one nearer the filter's prediction is kept, neither without one
        (``perchpose.fusion.consistency``).
    fusion : ``"covariance"`` (default: one PnP over every corner of every marker, its
        covariance from the Jacobian, and one filter of the fused pose with a
        white-noise-acceleration model; settings in ``covariance_filter``) or ``"paper"``
        (per-marker filters fused with the fixed sigmas by stage, as in the paper).
    budget_ms : a time budget per frame: past it the detection leaves out what it can (a
        pattern fit, the whole-frame search after tracking lost a marker, another glare level;
        ``MarkerDetector.detect``) and the estimate's ``skipped`` says what. None: no budget.
    check_borders : where a marker's black border reads clearly wider on one side than on the
        others (something dark flush with its edge, which the fitted corners follow: the marker
        then looks larger and nearer than it is) in two frames running, that side is moved in
        by the difference and its corners' covariance grows by the move; the marker's
        ``border`` says so (``perchpose.detection.borders``). Only ``update`` checks:
        ``update_detections`` has no image.
    """

    def __init__(
        self,
        camera: CameraModel,
        target: TargetSpec,
        *,
        kalman: KalmanSettings | None = None,
        sigmas: FusionSigmas | None = None,
        max_reproj_px: float = 3.0,
        markers: tuple[int, ...] | None = None,
        use_filter: bool = True,
        corners: CornerMethod = "edges",
        fusion: FusionMethod = "covariance",
        covariance_filter: CovarianceFilterSettings | None = None,
        disagree_chi2: float = DISAGREE_CHI2,
        budget_ms: float | None = None,
        check_borders: bool = True,
    ) -> None:
        if fusion not in FUSION_METHODS:
            raise ValueError(f"fusion must be one of {', '.join(FUSION_METHODS)}, got {fusion!r}")
        self.fusion = fusion
        self.covariance_filter = covariance_filter or CovarianceFilterSettings()
        if not disagree_chi2 > 0:
            raise ValueError(f"disagree_chi2 must be positive, got {disagree_chi2}")
        self.disagree_chi2 = disagree_chi2
        if budget_ms is not None and not (math.isfinite(budget_ms) and budget_ms > 0):
            raise ValueError(f"budget_ms must be a positive number, got {budget_ms}")
        self.budget_ms = budget_ms
        # the time the last frame spent after detection (poses, filters, fusion): kept out of
        # the detection's share of the budget
        self._after_detect_s = 0.0
        n = len(target.markers)
        self.markers = tuple(range(n)) if markers is None else tuple(sorted(set(markers)))
        self.borders = (
            tuple(BorderProfiles.of(target, i) for i in range(n)) if check_borders else None
        )
        if not self.markers or not all(0 <= i < n for i in self.markers):
            raise ValueError(f"markers must be indices 0-{n - 1} of the target, got {markers}")
        self.use_filter = use_filter
        self.camera = camera
        self.target = target
        self.kalman = kalman or KalmanSettings()
        self.sigmas = sigmas or FusionSigmas()
        self.max_reproj_px = max_reproj_px
        # the joint pose weighs each corner alike, so a marker a quarter the size of another
        # barely moves it: its pattern fit (3 ms at 12-22 px) is skipped (on a rendered fpv
        # approach the fused position moved by at most 0.11 mm, under 0.02 % of the distance)
        beside = PATTERN_BESIDE_RATIO if fusion == "covariance" else None
        self.detector = MarkerDetector(
            camera, target, corners, pattern_beside_ratio=beside, thorough_every=THOROUGH_EVERY
        )
        self.reset()

    @staticmethod
    def configured(
        camera: CameraModel,
        target: TargetSpec,
        *,
        sigmas_file: str | None = None,
        budget_ms: float | None = None,
    ) -> PerchingEstimator:
        """The estimator a user configures by files and a budget (``perchpose track``, the
        ROS 2 node): with ``sigmas_file`` (``fit-fusion --json``) the paper's fusion and those
        weights, else the joint pose; ``budget_ms`` per frame (None: none)."""
        if budget_ms is not None and not (math.isfinite(budget_ms) and budget_ms > 0):
            raise PerchposeError(f"--budget-ms must be a positive number, got {budget_ms:g}")
        if sigmas_file is None:
            return PerchingEstimator(camera, target, budget_ms=budget_ms)
        sigmas = FusionSigmas.load(sigmas_file)
        return PerchingEstimator(camera, target, fusion="paper", sigmas=sigmas, budget_ms=budget_ms)

    def _new_fusion(self) -> Fusion:
        if self.fusion == "covariance":
            return CovarianceFusion(
                self.camera,
                self.target,
                self.covariance_filter,
                use_filter=self.use_filter,
                marker_rule=self.kalman,
            )
        return PaperFusion(
            self.sigmas,
            self._markers,
            use_filter=self.use_filter,
            camera=self.camera,
            target=self.target,
            corner_sigma_px=self.covariance_filter.corner_sigma_px,
        )

    @property
    def reinitialised(self) -> int:
        """Times a filter restarted at a measurement its covariance called impossible."""
        return self._fusion.reinitialised + self._markers.reinitialised

    def reset(self) -> None:
        """Forget all tracks (a new sequence)."""
        self.detector.restart()
        self._markers = MarkerFilters(len(self.target.markers), self.kalman)
        self._fusion = self._new_fusion()
        self._last_R: list[Array | None] = [None] * len(self.target.markers)
        # whether each last rotation was settled: by reprojection, or by a settled reference
        self._settled: list[bool] = [True] * len(self.target.markers)
        self._settled_now: dict[int, bool] = {}
        self._last_t_s: float | None = None
        # the side of each marker whose border read wider than the others in the last frame
        self._odd_sides: dict[int, int] = {}
        # the last two frames' detections and their times (tracking's hint: where the markers
        # should be now, at the pace they moved between those frames)
        self._hint: tuple[MarkerDetection, ...] = ()
        self._hint_t_s = math.nan
        self._earlier: tuple[MarkerDetection, ...] = ()
        self._earlier_t_s = math.nan

    def _check_time(self, t_s: float) -> float:
        try:
            t = float(t_s)
        except (TypeError, ValueError) as exc:
            raise TimestampError(f"timestamp {t_s!r} is not a number") from exc
        if not math.isfinite(t):
            raise TimestampError(f"timestamp {t_s!r} is not finite")
        if self._last_t_s is not None and t < self._last_t_s:
            raise TimestampError(
                f"timestamp {t:.6f} s goes backwards (previous {self._last_t_s:.6f} s)"
            )
        return t

    def update(self, image: NDArray[np.uint8], t_s: float) -> Estimate:
        """Process one frame taken at ``t_s`` seconds; ``image`` is grey or BGR uint8."""
        t = self._check_time(t_s)
        grey = self.camera.check_image(image)
        t0 = time.perf_counter()
        deadline = (
            None if self.budget_ms is None else t0 + self.budget_ms / 1e3 - self._after_detect_s
        )
        hint = extrapolated(self._hint, self._hint_t_s, self._earlier, self._earlier_t_s, t)
        detected = self.detector.detect(grey, hint, deadline)
        self._earlier, self._earlier_t_s = self._hint, self._hint_t_s
        self._hint, self._hint_t_s = detected.markers, t
        measured, notes = self._checked_borders(grey, detected.markers)
        estimate = self._estimate(t, measured, t0, detected.corners_s, notes)
        timings = estimate.timings
        self._after_detect_s = (timings.pose_ms + timings.filter_ms + timings.fuse_ms) / 1e3
        skipped = detected.skipped
        return replace(estimate, skipped=skipped) if skipped else estimate

    def update_detections(self, detections: tuple[MarkerDetection, ...], t_s: float) -> Estimate:
        """Process markers already detected (by ``self.detector`` or elsewhere) in a frame taken
        at ``t_s``; corners are pixels of this camera's images. Several estimators can share one
        detection pass this way."""
        t = self._check_time(t_s)
        t0 = time.perf_counter()
        return self._estimate(t, detections, t0, 0.0)

    def _checked_borders(
        self, grey: NDArray[np.uint8], detections: tuple[MarkerDetection, ...]
    ) -> tuple[tuple[MarkerDetection, ...], dict[int, str]]:
        """The detections to measure, a side moved in where its border reads wider than the
        others in this frame and the one before (``check_borders``: something lying along the
        edge stays there; a misreading of one frame does not), and what was moved, by
        marker."""
        if self.borders is None:
            return detections, {}
        checked: list[MarkerDetection] = []
        notes: dict[int, str] = {}
        odd_now: dict[int, int] = {}
        for det in detections:
            i = det.marker_index
            profiles = self.borders[i]
            odd = border_problem(grey, det, self.camera, profiles) if i in self.markers else None
            if odd is not None:
                odd_now[i] = odd.side
                again = self._odd_sides.get(i) == odd.side  # read so in the frame before too
                moved = moved_in(det, self.camera, profiles.n_cells, odd) if again else None
                if moved is not None:
                    notes[i] = odd.describe()
                    det = moved  # noqa: PLW2901  (the detection measured in its place)
            checked.append(det)
        self._odd_sides = odd_now
        return tuple(checked), notes

    def _estimate(
        self,
        t: float,
        detections: tuple[MarkerDetection, ...],
        t0: float,
        corners_s: float,
        notes: dict[int, str] | None = None,
    ) -> Estimate:
        t1 = time.perf_counter()
        measurements, rejected = self._measure(detections, t)
        self._drop_disagreeing(detections, measurements, rejected, t)
        t2 = time.perf_counter()
        fused = self._filter_and_fuse(
            t, detections, measurements, rejected, (t0, t1, t2), corners_s
        )
        if not notes:
            return fused
        states = tuple(replace(m, border=notes.get(i, "")) for i, m in enumerate(fused.markers))
        return replace(fused, markers=states)

    def _measure(
        self, detections: tuple[MarkerDetection, ...], t: float
    ) -> tuple[dict[int, MarkerPose], dict[int, str]]:
        measurements: dict[int, MarkerPose] = {}
        rejected: dict[int, str] = {}
        # Each marker's two IPPE solutions are scored by reprojection and by agreement with the
        # rotation expected: the largest marker measured in this frame (all markers measure
        # the same target frame) when there is one; else the marker's last rotation (or any
        # marker's) turned to the yaw the filter predicts for this frame. A rotation that was
        # itself a toss-up (both solutions reprojecting alike, with nothing settled to go by)
        # is no reference: the next frame chooses by reprojection again.
        self._settled_now = {}
        for det in sorted(detections, key=lambda d: -d.side_px):
            if det.marker_index not in self.markers:
                continue
            reference: Array | None
            if measurements:
                first = next(iter(measurements))
                reference = measurements[first].T_camera_target[:3, :3]
                referred = self._settled_now[first]
            else:
                settled = [
                    R if ok else None for R, ok in zip(self._last_R, self._settled, strict=True)
                ]
                reference = settled[det.marker_index]
                if reference is None:
                    reference = next((R for R in settled if R is not None), None)
                referred = reference is not None
                yaw_predicted = self._predicted_yaw_rad(det.marker_index, t)
                if reference is not None and yaw_predicted is not None:
                    turn = angle_diff_rad(yaw_predicted, yaw_rad(reference))
                    reference = rot_z(turn) @ reference
            result = solve_marker_pose(
                self.camera,
                self.target.markers[det.marker_index],
                det.marker_index,
                det.corners_px,
                reference,
            )
            if isinstance(result, PoseFailure):
                rejected[det.marker_index] = result.reason
            elif result.reproj_rms_px > self.max_reproj_px:
                rejected[det.marker_index] = f"reprojection {result.reproj_rms_px:.1f} px"
            else:
                measurements[det.marker_index] = result
                self._settled_now[det.marker_index] = not result.ambiguous or referred
        return measurements, rejected

    def _drop_disagreeing(
        self,
        detections: tuple[MarkerDetection, ...],
        measurements: dict[int, MarkerPose],
        rejected: dict[int, str],
        t: float,
    ) -> None:
        """Markers whose positions disagree beyond ``disagree_chi2`` are not fused: the one
        nearer the filter's prediction stays; without a prediction neither does (the frame
        then has no measurement, and the reason is in each marker's ``rejected``). Each
        marker's corner noise is ``corner_sigma_px`` or, where larger, what its corner fit
        reports (an unfitted quad's corners on a blurred frame: a pixel or more)."""
        floor = self.covariance_filter.corner_sigma_px
        sigma = dict.fromkeys(measurements, floor)
        for det in detections:
            if det.marker_index in sigma:
                sigma[det.marker_index] = corner_noise_px(det.corner_covariance_px2, floor, floor)
        found = disagreements(self.camera, self.target, measurements, sigma, self.disagree_chi2)
        if not found:
            return
        predicted = self._predicted_pose(min(measurements), t)
        for d in found:
            labels = {i: self.target.markers[i].label for i in (d.reference, d.other)}
            pair = (d.reference, d.other)
            losers: tuple[int, ...]
            if predicted is None:
                losers = pair
            else:
                miss = {i: float(np.linalg.norm(measurements[i].t_m - predicted[1:])) for i in pair}
                losers = (max(pair, key=lambda i: miss[i]),)
            for i in losers:
                other = labels[d.other if i == d.reference else d.reference]
                rejected[i] = f"disagrees with {other} (chi2 {d.chi2:.0f})"
                measurements.pop(i, None)

    def _predicted_pose(self, marker_index: int, t: float) -> Array | None:
        """(4,) [yaw, x, y, z] the filter expects at ``t``: the fused filter's (covariance
        fusion), else the marker's own track's, else any live track's; None without one."""
        predicted = self._fusion.predicted_pose(t)
        if predicted is not None:
            return predicted
        return self._markers.predicted_pose(marker_index, t)

    def _predicted_yaw_rad(self, marker_index: int, t: float) -> float | None:
        """The yaw the filter expects at ``t`` (``_predicted_pose``)."""
        predicted = self._predicted_pose(marker_index, t)
        return None if predicted is None else float(predicted[0])

    def _filter_and_fuse(
        self,
        t: float,
        detections: tuple[MarkerDetection, ...],
        measurements: dict[int, MarkerPose],
        rejected: dict[int, str],
        clocks: tuple[float, float, float],
        corners_s: float,
    ) -> Estimate:
        """``clocks``: when detection, the poses and the filters started; ``corners_s``: the
        part of detection spent fitting corners."""
        t0, t1, t2 = clocks
        self._markers.advance({i: m.filter_z for i, m in measurements.items()}, t)
        t_filtered = time.perf_counter()
        for i, track in enumerate(self._markers.tracks):
            if i in measurements:
                self._last_R[i] = measurements[i].T_camera_target[:3, :3].copy()
                self._settled[i] = self._settled_now.get(i, True)
            elif not track.alive:
                self._last_R[i] = None
        self._last_t_s = t
        fused = self._fusion.fuse(t, detections, measurements)
        t3 = time.perf_counter()
        by_index = {d.marker_index: d for d in detections}
        states = tuple(
            MarkerState(
                label=spec.label,
                detection=by_index.get(i),
                measurement=measurements.get(i),
                rejected=rejected.get(i, ""),
                filtered_pose=tr.pose,
                missed_frames=tr.missed,
                contributing=i in fused.contributing,
            )
            for i, (spec, tr) in enumerate(
                zip(self.target.markers, self._markers.tracks, strict=True)
            )
        )
        pose = fused.pose
        position = (float(pose[1]), float(pose[2]), float(pose[3]))
        valid = fused.stage != STAGE_NONE and bool(np.isfinite(pose).all())
        return Estimate(
            t_s=t,
            valid=valid,
            stage=fused.stage if valid else STAGE_NONE,
            t_camera_target_m=position if valid else (math.nan, math.nan, math.nan),
            yaw_rad=float(pose[0]) if valid else math.nan,
            markers=states,
            timings=Timings(
                detect_ms=(t1 - t0 - corners_s) * 1e3,
                corners_ms=corners_s * 1e3,
                pose_ms=(t2 - t1) * 1e3,
                filter_ms=(t_filtered - t2) * 1e3,
                fuse_ms=(t3 - t_filtered) * 1e3,
                total_ms=(t3 - t0) * 1e3,
            ),
            age_s=fused.age_s if valid else math.nan,
            roll_rad=fused.tilt_rad[0] if valid else math.nan,
            pitch_rad=fused.tilt_rad[1] if valid else math.nan,
            covariance_flat=_flat(fused.covariance) if valid else (),
        )
