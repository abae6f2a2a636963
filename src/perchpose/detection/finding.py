"""Where the target's quads are searched: the whole frame or a window around where they are
expected (``QuadFinder`` over every dictionary of the target), and, through a strongly
distorted lens, its pinhole view (``detection.rectification``) with the corners mapped back
to the frame's pixels. ``QuadSearch`` holds no state between frames."""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.detection.quads import ImagePass, QuadFinder, QuadPass
from perchpose.detection.rectification import COARSE_STEP, Rectification
from perchpose.detection.windows import (
    Box,
    predicted_quads,
    rectified_box,
    rectified_windows,
    tracking_window,
)
from perchpose.target import TargetSpec
from perchpose.values import MarkerDetection, quad_side_px

Array = NDArray[np.float64]

# A lens that moves the image border this far from its pinhole position gets the rectified pass.
RECTIFY_ABOVE_PX = 6.0
# Found in both passes, a marker this large in the original image is taken from the rectified
# pass (its edges are curved in the original); a smaller one from the original image.
CURVED_SIDE_PX = 40.0
# While tracking, a marker the target's plane puts in view without a hint is searched for
# once it is predicted this large (a little under the smallest marker OpenCV's quad pass
# finds, about 9 px on rendered frames).
MIN_SEARCH_SIDE_PX = 7.0
# While tracking, a marker the target's plane puts in view without a hint is not searched for
# while its cells are narrower than this many blur sigmas (the blur of the markers fitted in
# the same frame): OpenCV cannot read it yet (the paper target's inner marker on the fpv
# approach is first read at 2.05 sigmas; under the harsh preset, at 2.5 and from 4.6 on).
MIN_READ_CELL_BLURS = 1.8
# A hinted marker under this side may drop out of tracking without sending the frame to the
# full search; the tracking pass adds OpenCV's 3 px threshold window for such markers.
SMALL_MARKER_SIDE_PX = 20.0


class QuadSearch:
    """The quads of ``target`` in ``camera``'s frames: ``find`` (whole frame, around a hint,
    or the pinhole view), the tracking pass's ``window_pass`` and ``rectified_tracking``, and
    ``rectified_refind``. ``coarse``: the pinhole view is searched at half size (edge-fitted
    corners need only a start)."""

    def __init__(self, camera: CameraModel, target: TargetSpec, coarse: bool) -> None:
        self.camera = camera
        self.target = target
        self.coarse = coarse
        self.quads = QuadFinder(target, max(camera.size))
        self.rectify = camera.max_distortion_px() > RECTIFY_ABOVE_PX

    @staticmethod
    def seen(grey: NDArray[np.uint8], clip_level: int | None) -> NDArray[np.uint8]:
        """The image the quads are searched in: ``grey`` clipped at ``clip_level`` (None: as
        it is)."""
        return grey if clip_level is None else np.minimum(grey, np.uint8(clip_level))

    def may_be_found(
        self, quad: Array, index: int, hinted: bool, blur_px: float | None = None
    ) -> bool:
        """Whether the window pass should look for marker ``index`` predicted at ``quad``:
        where it lies wholly in the image (``_in_view``: OpenCV keeps no quad that crosses
        the border), a hinted one always; one the plane predicts (not hinted) where it is
        large enough for OpenCV's smallest quad (``MIN_SEARCH_SIDE_PX``) and, given the
        frame's blur sigma ``blur_px``, has cells of ``MIN_READ_CELL_BLURS`` of it or more."""
        if not self.in_view(quad):
            return False
        if hinted:
            return True
        side_px = quad_side_px(quad)
        cells = int(self.target.markers[index].cells.shape[0])
        if blur_px is not None and side_px / cells < MIN_READ_CELL_BLURS * blur_px:
            return False
        return side_px >= MIN_SEARCH_SIDE_PX

    def in_view(self, quad: Array) -> bool:
        """Whether ``quad`` lies in the image as far from its border as OpenCV keeps its
        quads (``QuadFinder.border_margin_px``)."""
        return self.camera.in_image(quad, self.quads.border_margin_px)

    def window_pass(
        self, seen: NDArray[np.uint8], quads: dict[int, Array], tracking_side_px: float
    ) -> dict[int, MarkerDetection]:
        """The tracking detector's quads in a window around the predicted ``quads``, searched
        shrunk so that the smallest of them spans ``tracking_side_px``."""
        smallest = min((quad_side_px(q) for q in quads.values()), default=math.inf)
        small = smallest < SMALL_MARKER_SIDE_PX
        detector = self.quads.tracking_small if small else self.quads.tracking
        box = tracking_window(seen.shape, quads)
        # every predicted marker at least tracking_side_px across in the searched image
        scale = min(1.0, tracking_side_px / smallest) if 0 < smallest < math.inf else 1.0
        if box is None:
            return self.quads.find(seen, "raw", detector=detector, scale=scale)
        x0, y0, x1, y1 = box
        return self.quads.find(seen[y0:y1, x0:x1], "raw", (x0, y0), detector, scale)

    def rectified_tracking(
        self, grey: NDArray[np.uint8], quads: list[Array], search: bool = False
    ) -> list[MarkerDetection]:
        """Markers found in windows of the rectified view around ``quads`` (original pixels),
        with corners mapped back to the original: by the tracking detector (one threshold
        window), or with ``search`` by the full search's (OpenCV's three)."""
        maps = self.rectification.maps
        out = []
        for quad in quads:
            rectified = self.rectification.to_rectified(quad)
            box = rectified_box(rectified, maps[0].shape)
            if box is None:
                continue
            small = quad_side_px(rectified) < SMALL_MARKER_SIDE_PX
            detector = self.quads.tracking_small if small else self.quads.tracking
            for index, det in self.rectified_pass(
                grey, maps, box, None if search else detector
            ).items():
                mapped = self.unrectify(det.corners_px)
                if mapped is not None:
                    out.append(MarkerDetection(index, mapped, "rectified"))
        return out

    def find(
        self,
        grey: NDArray[np.uint8],
        hint: tuple[MarkerDetection, ...] = (),
        view: ImagePass = "raw",
        refind_curved: bool = True,
        whole: bool = True,
        detector: QuadPass | None = None,
    ) -> tuple[MarkerDetection, ...]:
        """The target's markers with ``cornerSubPix`` corners, searched in ``grey`` (``raw``)
        or in the whole of the lens's pinhole view of it (``rectified``; corners mapped back),
        by ``detector`` (the full search's, OpenCV's three threshold windows, by default).

        hint : the previous frame's detections. The raw search then starts in a window around
            them and around where the target's plane puts its other markers, and falls back to
            the whole image only when the window holds no marker (with ``whole``; else only
            when the window would cover most of the image).

        With a strongly distorted lens, markers missing but predicted by the plane through a
        found one are searched again in windows of the rectified view, and with
        ``refind_curved`` so are markers the raw search finds large (their edges curved: their
        ``cornerSubPix`` corners are off; the edge fit through the lens model straightens
        them, so the edge-fitted path leaves it out and falls back on such a window only where
        the fit fails).
        """
        maps = self.rectification.maps if self.rectify else None
        if view == "rectified" and maps is not None:
            # edge-fitted corners need only a start: the view at half its size, a quarter of
            # the pixels to remap and search (it is larger than the image)
            coarse = self.coarse
            step = COARSE_STEP if coarse else 1
            seen_maps = self.rectification.coarse_maps if coarse else maps
            rect = np.asarray(cv2.remap(grey, *seen_maps, interpolation=cv2.INTER_LINEAR), np.uint8)
            view_found: dict[int, MarkerDetection] = {}
            for index, det in self.quads.find(rect, "rectified", detector=detector).items():
                mapped = self.unrectify(det.corners_px * step)
                if mapped is not None:
                    view_found[index] = MarkerDetection(index, mapped, "rectified")
            return tuple(view_found[i] for i in sorted(view_found))
        found: dict[int, MarkerDetection] = {}
        box = self.hint_window(grey, hint)
        if box is not None:
            x0, y0, x1, y1 = box
            found = self.quads.find(grey[y0:y1, x0:x1], "raw", (x0, y0), detector)
        if not found and (whole or box is None):
            found = self.quads.find(grey, "raw", detector=detector)
        if maps is not None and found:
            found = self.rectified_refind(grey, found, CURVED_SIDE_PX if refind_curved else None)
        return tuple(found[i] for i in sorted(found))

    def rectified_refind(
        self, grey: NDArray[np.uint8], found: dict[int, MarkerDetection], curved_px: float | None
    ) -> dict[int, MarkerDetection]:
        """``found`` (in ``grey``, a strongly distorted lens's image), with the markers the
        target's plane through them puts in view but that are missing searched in windows of
        the pinhole view (OpenCV's three threshold windows), and with ``curved_px`` those found
        that large searched there again (corners mapped back)."""
        maps = self.rectification.maps
        limit_px = math.inf if curved_px is None else curved_px
        rectified: dict[int, MarkerDetection] = {}
        margin_px = self.quads.border_margin_px
        for box in rectified_windows(self.rectification, self.target, found, limit_px, margin_px):
            for index, det in self.rectified_pass(grey, maps, box).items():
                rectified.setdefault(index, det)
        out = dict(found)
        for det in rectified.values():
            raw = found.get(det.marker_index)
            if raw is not None and raw.side_px < limit_px:
                continue
            mapped = self.unrectify(det.corners_px)
            if mapped is not None:
                out[det.marker_index] = MarkerDetection(det.marker_index, mapped, "rectified")
        return out

    def hint_window(self, grey: NDArray[np.uint8], hint: tuple[MarkerDetection, ...]) -> Box | None:
        """The window around ``hint`` and where the target's plane through it puts the other
        markers (``tracking_window``); None without a hint or where the window would cover
        most of the image."""
        return tracking_window(grey.shape, predicted_quads(self.target, hint)) if hint else None

    def rectified_pass(
        self,
        grey: NDArray[np.uint8],
        maps: tuple[NDArray[np.float32], NDArray[np.float32]],
        box: Box,
        detector: QuadPass | None = None,
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
        return self.quads.find(window, "rectified", (x0, y0), detector)

    @property
    def rectification(self) -> Rectification:
        """The camera's pinhole view (``detection.rectification``: built once per camera)."""
        return Rectification.of(self.camera)

    def unrectify(self, corners_rect_px: Array) -> Array | None:
        uv, ok = self.rectification.to_original(corners_rect_px)
        if not ok:
            return None
        # the rectified view reaches past the image, where it is black: a marker running out
        # of the image closes there into a quad that is not the marker (OpenCV's own
        # minDistanceToBorder keeps such quads out of the plain pass)
        return uv if self.camera.in_image(uv, self.quads.border_margin_px) else None
