"""Finding the target's markers as quads: OpenCV's ArUco detector over every dictionary of
the target at once, ``cornerSubPix`` corners, and one copy of the target when several are in
view. The quads are a start: ``perchpose.corners.refinement`` fits their corners to the image."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.target import TargetSpec, aruco_dictionary
from perchpose.values import MarkerDetection, quad_side_px

Array = NDArray[np.float64]
ImagePass = Literal["raw", "rectified"]

DEFAULT_MIN_PERIMETER_RATE = 0.03  # OpenCV's default minMarkerPerimeterRate
# The tracking pass thresholds the image once, with a 15 px window, where OpenCV's default
# thresholds it three times (3, 13 and 23 px). With a 7 px window, on rendered frames of both
# cameras (markers of 14-400 px) it missed no more markers than the three, at a third of the
# time; but under the harsh preset's noise it found the marker in 2 of tracking's 46 windows on
# the fpv approach, where 15 px finds it in 36 (seed 2: 4 and 39 of 48). On the default, analog
# and wide-lens approaches the two found the same (48 of 70, 16 of 29, 31 of 52 windows), and
# on the real photos both find 67 of their 68 markers. Markers under about 20 px (cells under
# 3 px) need the 3 px window: a pass of 3 and 7 px searches where one is expected (with 3 and
# 15 px, 2 fewer of 25 on the analog approach). A hinted marker the tracking pass misses sends
# the frame to the full search, which keeps OpenCV's three windows.
TRACKING_THRESHOLD_WINDOWS_PX = (15, 15)
SMALL_MARKER_THRESHOLD_WINDOWS_PX = (3, 7)
# A quick look at a whole frame thresholds it once, with OpenCV's largest window (23 px). Over
# the whole frames of the rendered fpv approaches where OpenCV's three windows found the
# target, it found it in all 219 of the default preset's and 214 of 216 of the harsh one's, at
# 0.4x and 0.6x of their time; it misses markers of under about 15 px (the inner marker at
# 10-14 px, on 16 of the default frames). The 7 px window of the tracking pass found nothing
# on 204 of the harsh frames: the noise breaks the border's outline at that scale.
QUICK_THRESHOLD_WINDOWS_PX = (23, 23)
# OpenCV's other two windows (3 and 13 px): after a quick look that found nothing, they make up
# the thorough search.
REST_THRESHOLD_WINDOWS_PX = (3, 13)
_OPENCV_WINDOW_STEP_PX = 10


def one_target(
    target: TargetSpec, candidates: dict[int, list[MarkerDetection]]
) -> dict[int, MarkerDetection]:
    """One copy of the target from every quad found per marker, when several copies are in
    view: the largest quad of the largest marker found, and of each other marker the quad that
    sits where the plane through that one puts it (centre within half its side; a size that
    does not match is left to ``perchpose.fusion.consistency``, which says why). A marker with no
    such quad belongs to another copy and is left out, so markers of two copies are never
    fused into one pose."""
    if not candidates:
        return {}
    reference_index = min(candidates)
    reference = max(candidates[reference_index], key=lambda d: d.side_px)
    chosen = {reference_index: reference}
    plane = target.markers[reference_index].corners_target_m[:, :2]
    H, _ = cv2.findHomography(plane, reference.corners_px)
    for index, dets in candidates.items():
        if index == reference_index:
            continue
        if H is None:
            chosen[index] = max(dets, key=lambda d: d.side_px)
            continue
        corners_m = target.markers[index].corners_target_m[:, :2].reshape(-1, 1, 2)
        predicted = np.asarray(cv2.perspectiveTransform(corners_m, H), np.float64).reshape(4, 2)
        centre, side = predicted.mean(axis=0), quad_side_px(predicted)
        best = min(dets, key=lambda d: float(np.linalg.norm(d.corners_px.mean(axis=0) - centre)))
        offset = float(np.linalg.norm(best.corners_px.mean(axis=0) - centre))
        if offset < 0.5 * side:
            chosen[index] = best
    return chosen


def detector_parameters(
    threshold_windows_px: tuple[int, int] | None = None, step_px: int = 4
) -> cv2.aruco.DetectorParameters:
    """OpenCV's defaults without corner refinement (``refine_corners`` fits its window to the
    marker's cells), and adaptive-threshold windows from the smallest to the largest of
    ``threshold_windows_px`` in steps of ``step_px`` if given."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
    if threshold_windows_px is not None:
        params.adaptiveThreshWinSizeMin, params.adaptiveThreshWinSizeMax = threshold_windows_px
        params.adaptiveThreshWinSizeStep = step_px
    return params


class QuadPass:
    """One configured ``ArucoDetector`` over the target's dictionaries."""

    def __init__(
        self, dictionaries: list[cv2.aruco.Dictionary], params: cv2.aruco.DetectorParameters
    ) -> None:
        self.params = params
        self.detector = cv2.aruco.ArucoDetector(dictionaries[0], params)
        self.detector.setDictionaries(dictionaries)

    def run(self, grey: NDArray[np.uint8], image_size_px: int) -> tuple[Sequence[Any], Any, Any]:
        """Quads, ids and dictionary indices found in ``grey``, part of an image whose larger
        side is ``image_size_px``.

        OpenCV sets the smallest candidate perimeter relative to the image searched; a window
        keeps the whole image's absolute limit, or every speck of noise in it becomes a
        candidate to decode (a noisy 123 px window took 2 s instead of 2 ms).
        """
        rate = min(3.5, DEFAULT_MIN_PERIMETER_RATE * image_size_px / float(max(grey.shape[:2])))
        if rate != self.params.minMarkerPerimeterRate:
            self.params.minMarkerPerimeterRate = rate
            self.detector.setDetectorParameters(self.params)
        corners, ids, _rejected, dict_indices = self.detector.detectMarkersMultiDict(grey)
        return corners, ids, dict_indices


_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3)


def refine_corners(grey: NDArray[np.uint8], corners_px: Array, cells: int) -> Array:
    """Subpixel corners by ``cv2.cornerSubPix`` with a half-window of 0.4 of a cell, between
    2 and 6 pixels.

    ArUco's own SUBPIX refinement shrinks its window with the cell size down to one pixel, which
    leaves corners of markers under about 30 px up to a pixel off; a 2-pixel half-window still
    fits inside the black border there and brings them to about 0.3 px. Keeping the window under
    half a cell keeps it inside a quiet zone one cell wide, so the edge of a plate around the
    printed sheet does not pull the corner (measured on rendered frames, 15-400 px markers).
    """
    side = float(np.mean(np.linalg.norm(np.roll(corners_px, -1, axis=0) - corners_px, axis=1)))
    half = int(np.clip(round(0.4 * side / cells), 2, 6))
    pts = np.ascontiguousarray(corners_px, dtype=np.float32).reshape(-1, 1, 2)
    refined = cv2.cornerSubPix(grey, pts, (half, half), (-1, -1), _SUBPIX_CRITERIA)
    out = np.asarray(refined, dtype=np.float64).reshape(4, 2)
    # a corner that wandered further than the window is a failed refinement: keep the original
    moved = np.linalg.norm(out - corners_px, axis=1) > half
    out[moved] = corners_px[moved]
    return out


def target_dictionaries(
    target: TargetSpec,
) -> tuple[list[cv2.aruco.Dictionary], list[list[int]]]:
    """One dictionary per dictionary name of the target, holding only the target's markers, and
    for each the target's marker index of each of its entries.

    OpenCV compares every candidate quad with every entry of a dictionary, and that dominates the
    detection time: a 120 px marker in a 640x480 image took 23 ms with all of DICT_4X4_1000 and
    5 ms with DICT_4X4_50. A subset keeps the full dictionary's ``maxCorrectionBits``, which is
    under half the distance between any two of its markers, so it accepts exactly the bit
    patterns the full dictionary would have assigned to the target's ids (for the paper's
    dictionaries, exact matches only: DICT_4X4_1000 corrects 0 bits, DICT_ARUCO_ORIGINAL 1,
    which the default ``errorCorrectionRate`` of 0.6 rounds down to 0).
    """
    dictionaries: list[cv2.aruco.Dictionary] = []
    indices: list[list[int]] = []
    for name in target.dictionaries:
        full = aruco_dictionary(name)
        members = [i for i, m in enumerate(target.markers) if m.dictionary == name]
        ids = [target.markers[i].marker_id for i in members]
        dictionaries.append(
            cv2.aruco.Dictionary(full.bytesList[ids], full.markerSize, full.maxCorrectionBits)
        )
        indices.append(members)
    return dictionaries, indices


class QuadFinder:
    """The target's configured passes (``search``: OpenCV's three threshold windows;
    ``tracking`` and ``tracking_small``: one window, for the windows around predicted
    markers; ``quick``: one wide window, a first look at a whole frame; ``rest``: the other
    two of OpenCV's windows) and the map from a dictionary's entries to the target's
    markers."""

    def __init__(self, target: TargetSpec, image_size_px: int) -> None:
        self.target = target
        self.image_size_px = image_size_px
        dicts, self.dict_marker_index = target_dictionaries(target)
        self.search = QuadPass(dicts, detector_parameters())
        self.tracking = QuadPass(dicts, detector_parameters(TRACKING_THRESHOLD_WINDOWS_PX))
        self.tracking_small = QuadPass(
            dicts, detector_parameters(SMALL_MARKER_THRESHOLD_WINDOWS_PX)
        )
        self.quick = QuadPass(dicts, detector_parameters(QUICK_THRESHOLD_WINDOWS_PX))
        self.rest = QuadPass(
            dicts, detector_parameters(REST_THRESHOLD_WINDOWS_PX, _OPENCV_WINDOW_STEP_PX)
        )

    @property
    def border_margin_px(self) -> float:
        """How far from the image border OpenCV keeps its quads (``minDistanceToBorder``)."""
        return float(self.search.params.minDistanceToBorder)

    def find(
        self,
        grey: NDArray[np.uint8],
        image_pass: ImagePass,
        offset: tuple[int, int] = (0, 0),
        detector: QuadPass | None = None,
        scale: float = 1.0,
    ) -> dict[int, MarkerDetection]:
        """Markers of the target in ``grey``, with ``cornerSubPix`` corners shifted by
        ``offset`` (a window's origin), by ``detector`` (the full search's by default).
        ``scale`` under 1 searches ``grey`` shrunk by that factor (area-averaged) and maps the
        corners back: a start for a fit at full resolution, about a pixel of the shrunk image
        off."""
        run = (detector or self.search).run
        image = grey
        if scale < 1.0:
            size = (max(1, round(grey.shape[1] * scale)), max(1, round(grey.shape[0] * scale)))
            image = np.asarray(cv2.resize(grey, size, interpolation=cv2.INTER_AREA), np.uint8)
        corners, ids, dict_indices = run(image, round(self.image_size_px * min(1.0, scale)))
        candidates: dict[int, list[MarkerDetection]] = {}
        if ids is None or len(ids) == 0:
            return {}
        # a pixel centre at u in the shrunk image is at (u + 0.5) / s - 0.5 in the original
        factor = (grey.shape[1] / image.shape[1], grey.shape[0] / image.shape[0])
        for quad, marker_id, dict_index in zip(
            corners,
            np.asarray(ids).reshape(-1),
            np.asarray(dict_indices).reshape(-1),
            strict=True,
        ):
            index = self.dict_marker_index[int(dict_index)][int(marker_id)]
            cells = int(self.target.markers[index].cells.shape[0])
            refined = refine_corners(image, np.asarray(quad, np.float64).reshape(4, 2), cells)
            if image is not grey:
                refined = (refined + 0.5) * np.array(factor) - 0.5
            det = MarkerDetection(index, refined + np.array(offset, np.float64), image_pass)
            candidates.setdefault(index, []).append(det)
        return one_target(self.target, candidates)
