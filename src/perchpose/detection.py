"""Detection of a target's markers: one detector pass over all its dictionaries.

Corners come back in the pixels of the original (distorted) image. For a lens whose distortion
bends a large marker's edges enough that OpenCV's quad finder misses it, a second pass runs on a
pinhole rectification of the image and maps the corners it finds back through the lens model.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.corners import EdgeFit, fit_marker_edges
from perchpose.pattern_fit import PatternFitSettings, printed_pattern, refine_corners_pattern
from perchpose.rectification import Rectification
from perchpose.target import TargetSpec, aruco_dictionary
from perchpose.values import MarkerDetection, quad_side_px

Array = NDArray[np.float64]

# A lens that moves the image border this far from its pinhole position gets the rectified pass.
RECTIFY_ABOVE_PX = 6.0
# Found in both passes, a marker this large in the original image is taken from the rectified
# pass (its edges are curved in the original); a smaller one from the original image.
CURVED_SIDE_PX = 40.0
CornerMethod = Literal["edges", "subpix"]
CORNER_METHODS: tuple[CornerMethod, ...] = ("edges", "subpix")
DEFAULT_MIN_PERIMETER_RATE = 0.03  # OpenCV's default minMarkerPerimeterRate
# The tracking pass thresholds the image once, with a 7 px window, where OpenCV's default
# thresholds it three times (3, 13 and 23 px). On rendered frames of both cameras and image
# qualities (markers of 14-400 px) the single window missed no more markers than the three, at a
# third of the time; on the real photos it missed 1 of 17. Markers under about 20 px (cells
# under 3 px) need the 3 px window too: it is added when one is expected. A hinted marker the
# tracking pass misses sends the frame to the full search, which keeps OpenCV's three windows.
TRACKING_THRESHOLD_WINDOWS_PX = (7, 7)
SMALL_MARKER_THRESHOLD_WINDOWS_PX = (3, 7)
SMALL_MARKER_SIDE_PX = 20.0


def one_target(
    target: TargetSpec, candidates: dict[int, list[MarkerDetection]]
) -> dict[int, MarkerDetection]:
    """One copy of the target from every quad found per marker, when several copies are in
    view: the largest quad of the largest marker found, and of each other marker the quad that
    sits where the plane through that one puts it (centre within half its side; a size that
    does not match is left to ``perchpose.consistency``, which says why). A marker with no
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


def _detector_parameters(
    threshold_windows_px: tuple[int, int] | None = None,
) -> cv2.aruco.DetectorParameters:
    """OpenCV's defaults without corner refinement (``refine_corners`` fits its window to the
    marker's cells), and adaptive-threshold windows from the smallest to the largest of
    ``threshold_windows_px`` in steps of 4 px if given."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
    if threshold_windows_px is not None:
        params.adaptiveThreshWinSizeMin, params.adaptiveThreshWinSizeMax = threshold_windows_px
        params.adaptiveThreshWinSizeStep = 4
    return params


class _Pass:
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


class MarkerDetector:
    """Finds the markers of ``target`` in grey images of ``camera``.

    All dictionaries of the target are searched in one ``detectMarkersMultiDict`` pass; ids that
    are not the target's (dictionary, id) pairs are ignored.
    """

    def __init__(
        self, camera: CameraModel, target: TargetSpec, corners: CornerMethod = "edges"
    ) -> None:
        if corners not in CORNER_METHODS:
            raise ValueError(f"corners must be one of {', '.join(CORNER_METHODS)}, got {corners!r}")
        self.camera = camera
        self.target = target
        self.corners = corners
        self._dict_names = target.dictionaries
        dicts, self._dict_marker_index = target_dictionaries(target)
        self._search = _Pass(dicts, _detector_parameters())
        self._tracking = _Pass(dicts, _detector_parameters(TRACKING_THRESHOLD_WINDOWS_PX))
        self._tracking_small = _Pass(dicts, _detector_parameters(SMALL_MARKER_THRESHOLD_WINDOWS_PX))
        self.rectify = camera.max_distortion_px() > RECTIFY_ABOVE_PX
        self._margins = [target.white_margin_cells(i) for i in range(len(target.markers))]
        self._patterns = [printed_pattern(target, i) for i in range(len(target.markers))]
        self.pattern_settings = PatternFitSettings()

    def detect(
        self, grey: NDArray[np.uint8], hint: tuple[MarkerDetection, ...] = ()
    ) -> tuple[MarkerDetection, ...]:
        """Detect the target's markers in a grey (H, W) uint8 image of the camera's size.

        hint : the previous frame's detections (see ``_find``). With ``corners="edges"`` (the
        default) each marker's corners are then refitted from its four border edges through
        the lens model (``perchpose.corners``); ``"subpix"`` keeps the ``cornerSubPix`` corners.
        """
        if self.corners == "subpix":
            return self._find(grey, hint)
        if hint:
            tracked = self._track_edges(grey, hint)
            if tracked is not None:
                return tracked
        return tuple(self.fit_corners(grey, det) or det for det in self._find(grey, hint))

    def fit_corners(self, grey: NDArray[np.uint8], det: MarkerDetection) -> MarkerDetection | None:
        """``det`` with corners fitted to the image, or None if no fit succeeds: from the
        marker's four border edges (``perchpose.corners``, with its cells and white margin from
        the target); for a marker whose cells span only a few blur widths, where the one-edge
        model pulls corners inwards, from its whole printed pattern (``perchpose.pattern_fit``)
        starting from the edges' corners."""
        i = det.marker_index
        cells = self.target.markers[i].cells
        edges = self.fit_edges(grey, det)
        corners = None if edges is None else edges.corners_px
        pattern = self._patterns[i]
        if pattern is not None and self.pattern_settings.applies(
            det.side_px, cells.shape[0], None if edges is None else edges.blur_px
        ):
            start = det.corners_px if edges is None else edges.corners_px
            blur = 1.0 if edges is None else edges.blur_px
            fitted = refine_corners_pattern(
                grey, start, self.camera, pattern, self.pattern_settings, blur
            )
            corners = fitted if fitted is not None else corners
        return (
            None if corners is None else MarkerDetection(det.marker_index, corners, det.image_pass)
        )

    def fit_edges(self, grey: NDArray[np.uint8], det: MarkerDetection) -> EdgeFit | None:
        """The edge fit alone of ``det`` (``perchpose.corners``, with the marker's cells and
        white margin from the target), or None if it fails."""
        i = det.marker_index
        return fit_marker_edges(
            grey,
            det.corners_px,
            self.camera,
            self.target.markers[i].cells,
            margin_cells=self._margins[i],
        )

    def _track_edges(
        self, grey: NDArray[np.uint8], hint: tuple[MarkerDetection, ...]
    ) -> tuple[MarkerDetection, ...] | None:
        """Tracking with edge-fitted corners: one single-threshold pass over a window of the
        image (the whole image when the window would cover most of it), then the edge fit
        through the lens model, which also straightens what a fisheye bends.

        Through a strongly distorted lens, hinted markers the pass missed, and a large marker
        whose curved quad is too far off for the edge fit, are searched again in windows of the
        rectified view around where they are predicted. None when a marker of 20 px or more is
        still not found: the caller then runs the full search. A hinted marker under 20 px (at
        the edge of detection, where markers come and go) may drop out without one. A small
        marker whose edges cannot be fitted keeps its ``cornerSubPix`` corners."""
        quads = self._predicted_quads(hint)
        small = any(quad_side_px(q) < SMALL_MARKER_SIDE_PX for q in quads.values())
        detector = self._tracking_small if small else self._tracking
        box = self._tracking_window(grey.shape, quads)
        if box is None:
            found = self._detect_pass(grey, "raw", detector=detector)
        else:
            x0, y0, x1, y1 = box
            found = self._detect_pass(grey[y0:y1, x0:x1], "raw", (x0, y0), detector)
        result: dict[int, MarkerDetection] = {}
        missing = [d for d in hint if d.marker_index not in found]
        required = [d.marker_index for d in missing if d.side_px >= SMALL_MARKER_SIDE_PX]
        for index, det in found.items():
            fitted = self.fit_corners(grey, det)
            if fitted is None and self.rectify and det.side_px >= CURVED_SIDE_PX:
                required.append(index)  # a curved quad too far off for the fit
            else:
                result[index] = fitted or det
        again = required + [d.marker_index for d in missing if d.side_px < SMALL_MARKER_SIDE_PX]
        if again and self.rectify:
            retry = [quads[i] for i in again if i in quads]
            for det in self._rectified_tracking(grey, retry):
                if det.marker_index in again and det.marker_index not in result:
                    result[det.marker_index] = self.fit_corners(grey, det) or det
        if any(index not in result for index in required):
            return None
        return tuple(result[i] for i in sorted(result))

    def _rectified_tracking(
        self, grey: NDArray[np.uint8], quads: list[Array]
    ) -> list[MarkerDetection]:
        """Markers found by the tracking detector in windows of the rectified view around the
        predicted ``quads`` (original pixels), with corners mapped back to the original."""
        maps = self._rectification.maps
        out = []
        for quad in quads:
            rectified = self._rectification.to_rectified(quad)
            box = self._rectified_box(rectified, maps[0].shape)
            if box is None:
                continue
            small = quad_side_px(rectified) < SMALL_MARKER_SIDE_PX
            detector = self._tracking_small if small else self._tracking
            for index, det in self._rectified_pass(grey, maps, box, detector).items():
                mapped = self._unrectify(det.corners_px)
                if mapped is not None:
                    out.append(MarkerDetection(index, mapped, "rectified"))
        return out

    def _find(
        self, grey: NDArray[np.uint8], hint: tuple[MarkerDetection, ...] = ()
    ) -> tuple[MarkerDetection, ...]:
        """The target's markers with ``cornerSubPix`` corners.

        hint : the previous frame's detections. The search then starts in a window around them
            and around where the target's plane puts its other markers, and falls back to the
            whole image only when the window holds no marker.

        With a strongly distorted lens, markers found large (curved edges) and markers missing
        but predicted by the plane through a found one are searched again in windows of the
        rectified view; with nothing found, the whole rectified view is searched.
        """
        found: dict[int, MarkerDetection] = {}
        box = self._tracking_window(grey.shape, self._predicted_quads(hint)) if hint else None
        if box is not None:
            x0, y0, x1, y1 = box
            found = self._detect_pass(grey[y0:y1, x0:x1], "raw", (x0, y0))
        if not found:
            found = self._detect_pass(grey, "raw")
        if not self.rectify:
            return tuple(found[i] for i in sorted(found))
        maps = self._rectification.maps
        if not found:
            rect = np.asarray(cv2.remap(grey, *maps, interpolation=cv2.INTER_LINEAR), np.uint8)
            rectified = self._detect_pass(rect, "rectified")
        else:
            rectified = {}
            for box in self._rectified_windows(found):
                for index, det in self._rectified_pass(grey, maps, box).items():
                    rectified.setdefault(index, det)
        for det in rectified.values():
            raw = found.get(det.marker_index)
            if raw is not None and raw.side_px < CURVED_SIDE_PX:
                continue
            mapped = self._unrectify(det.corners_px)
            if mapped is not None:
                found[det.marker_index] = MarkerDetection(det.marker_index, mapped, "rectified")
        return tuple(found[i] for i in sorted(found))

    def _rectified_windows(
        self, found: dict[int, MarkerDetection]
    ) -> list[tuple[int, int, int, int]]:
        """Windows (x0, y0, x1, y1) of the rectified view to search: around each large found
        marker, and around where the plane through a found marker puts each missing one."""
        h, w = self._rectification.size
        reference = max(found.values(), key=lambda d: d.side_px)
        ref_rect = self._rectification.to_rectified(reference.corners_px)
        ref_plane = self.target.markers[reference.marker_index].corners_target_m[:, :2]
        H, _ = cv2.findHomography(ref_plane, ref_rect)
        windows = []
        for index, marker in enumerate(self.target.markers):
            det = found.get(index)
            if det is not None and det.side_px < CURVED_SIDE_PX:
                continue
            if det is not None:
                quad = self._rectification.to_rectified(det.corners_px)
            elif H is not None:
                quad = np.asarray(
                    cv2.perspectiveTransform(marker.corners_target_m[:, :2].reshape(-1, 1, 2), H),
                    np.float64,
                ).reshape(4, 2)
            else:
                continue
            window = self._rectified_box(quad, (h, w))
            if window is not None:
                windows.append(window)
        return windows

    @staticmethod
    def _rectified_box(quad: Array, shape: tuple[int, ...]) -> tuple[int, int, int, int] | None:
        """A window (x0, y0, x1, y1) of the rectified view around ``quad`` (rectified pixels),
        padded by 0.3 of its extent plus 8 px, or None if not finite or under 16 px."""
        if not np.all(np.isfinite(quad)):
            return None
        h, w = shape[:2]
        lo, hi = quad.min(axis=0), quad.max(axis=0)
        pad = 0.3 * float(np.max(hi - lo)) + 8.0
        x0, y0 = (int(max(0, np.floor(v - pad))) for v in lo)
        x1 = int(min(w, np.ceil(hi[0] + pad)))
        y1 = int(min(h, np.ceil(hi[1] + pad)))
        return (x0, y0, x1, y1) if x1 - x0 >= 16 and y1 - y0 >= 16 else None

    def _predicted_quads(self, hint: tuple[MarkerDetection, ...]) -> dict[int, Array]:
        """Where each marker should be: the hinted markers where they were, the others where
        the plane through the largest hinted marker puts them."""
        quads = {d.marker_index: d.corners_px for d in hint}
        reference = max(hint, key=lambda d: d.side_px)
        plane = self.target.markers[reference.marker_index].corners_target_m[:, :2]
        H, _ = cv2.findHomography(plane, reference.corners_px)
        if H is not None:
            for index, marker in enumerate(self.target.markers):
                if index not in quads:
                    quads[index] = np.asarray(
                        cv2.perspectiveTransform(
                            marker.corners_target_m[:, :2].reshape(-1, 1, 2), H
                        ),
                        np.float64,
                    ).reshape(4, 2)
        return {i: q for i, q in quads.items() if np.all(np.isfinite(q))}

    @staticmethod
    def _window(
        quads: list[Array], shape: tuple[int, ...], pad_fraction: float, pad_px: float
    ) -> tuple[int, int, int, int] | None:
        """The box (x0, y0, x1, y1) around ``quads`` padded by a fraction of their extent plus
        ``pad_px``, clipped to ``shape``; None if under 16 px either way."""
        h, w = shape[:2]
        points = np.concatenate(quads)
        lo, hi = points.min(axis=0), points.max(axis=0)
        pad = pad_fraction * float(np.max(hi - lo)) + pad_px
        x0, y0 = int(max(0, np.floor(lo[0] - pad))), int(max(0, np.floor(lo[1] - pad)))
        x1, y1 = int(min(w, np.ceil(hi[0] + pad))), int(min(h, np.ceil(hi[1] + pad)))
        if x1 - x0 < 16 or y1 - y0 < 16:
            return None
        return (x0, y0, x1, y1)

    def _tracking_window(
        self, shape: tuple[int, ...], quads: dict[int, Array]
    ) -> tuple[int, int, int, int] | None:
        """A window of the image around the predicted ``quads`` (``_predicted_quads``), or None
        when it would cover most of the image anyway."""
        if not quads:
            return None
        box = self._window(list(quads.values()), shape, 0.5, 16.0)
        h, w = shape[:2]
        if box is None or (box[2] - box[0]) * (box[3] - box[1]) > 0.6 * w * h:
            return None
        return box

    def _rectified_pass(
        self,
        grey: NDArray[np.uint8],
        maps: tuple[NDArray[np.float32], NDArray[np.float32]],
        box: tuple[int, int, int, int],
        detector: _Pass | None = None,
    ) -> dict[int, MarkerDetection]:
        """Markers found in the window ``box`` of the rectified view (rectified pixels)."""
        x0, y0, x1, y1 = box
        window = np.asarray(
            cv2.remap(
                grey,
                maps[0][y0:y1, x0:x1],
                maps[1][y0:y1, x0:x1],
                interpolation=cv2.INTER_LINEAR,
            ),
            np.uint8,
        )
        return self._detect_pass(window, "rectified", (x0, y0), detector)

    def _detect_pass(
        self,
        grey: NDArray[np.uint8],
        image_pass: Literal["raw", "rectified"],
        offset: tuple[int, int] = (0, 0),
        detector: _Pass | None = None,
    ) -> dict[int, MarkerDetection]:
        """Markers of the target in ``grey``, with ``cornerSubPix`` corners shifted by
        ``offset`` (a window's origin), by ``detector`` (the full search's by default)."""
        run = (detector or self._search).run
        corners, ids, dict_indices = run(grey, max(self.camera.size))
        candidates: dict[int, list[MarkerDetection]] = {}
        if ids is None or len(ids) == 0:
            return {}
        for quad, marker_id, dict_index in zip(
            corners,
            np.asarray(ids).reshape(-1),
            np.asarray(dict_indices).reshape(-1),
            strict=True,
        ):
            index = self._dict_marker_index[int(dict_index)][int(marker_id)]
            cells = int(self.target.markers[index].cells.shape[0])
            refined = refine_corners(grey, np.asarray(quad, np.float64).reshape(4, 2), cells)
            det = MarkerDetection(index, refined + np.array(offset, np.float64), image_pass)
            candidates.setdefault(index, []).append(det)
        return one_target(self.target, candidates)

    @property
    def _rectification(self) -> Rectification:
        """The camera's pinhole view (``perchpose.rectification``: built once per camera)."""
        return Rectification.of(self.camera)

    def _unrectify(self, corners_rect_px: Array) -> Array | None:
        uv, ok = self._rectification.to_original(corners_rect_px)
        if not ok:
            return None
        # the rectified view reaches past the image, where it is black: a marker running out
        # of the image closes there into a quad that is not the marker (OpenCV's own
        # minDistanceToBorder keeps such quads out of the plain pass)
        w, h = self.camera.size
        margin = float(self._search.params.minDistanceToBorder)
        inside = (uv[:, 0] >= margin) & (uv[:, 0] <= w - 1 - margin)
        inside &= (uv[:, 1] >= margin) & (uv[:, 1] <= h - 1 - margin)
        return uv if bool(np.all(inside)) else None
