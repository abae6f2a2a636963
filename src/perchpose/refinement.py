"""Corners fitted to the image, starting from a found quad: from the marker's four border edges
through the lens model (``perchpose.corners``), and for a marker whose cells span only a few
blur widths from its whole printed pattern (``perchpose.pattern_fit``)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.corners import EdgeFit, fit_marker_edges
from perchpose.pattern_fit import PatternFitSettings, printed_pattern, refine_corners_pattern
from perchpose.target import TargetSpec
from perchpose.values import MarkerDetection

# A predicted marker whose fitted corners end further than this (px) from where they were
# predicted is fitted again from them, and that second fit must move them less than this
# again (``CornerFitter.fit_corners``).
SETTLE_PX = 0.3
# A predicted marker's corners may move this far (in its cells) from the prediction: about
# half the profiles' reach across the edge. Further, the edge lies near the profiles' ends
# and a fit that ends there may not be the edge (a start 0.5-1 cell off, fitted 5-10 px from
# a 70 px marker's corners, read back its cells as printed).
PREDICTED_MAX_MOVE_CELLS = 0.25


class CornerFitter:
    """Fits the corners of the markers of ``target`` in grey images of ``camera``; what is
    printed around each marker (its cells, its white margin, its printed pattern) comes from
    the target and is prepared once."""

    def __init__(self, camera: CameraModel, target: TargetSpec) -> None:
        self.camera = camera
        self.target = target
        self.margins = [target.white_margin_cells(i) for i in range(len(target.markers))]
        self.patterns = [printed_pattern(target, i) for i in range(len(target.markers))]
        self.pattern_settings = PatternFitSettings()
        self.pattern_s = 0.0

    def fit_corners(
        self,
        grey: NDArray[np.uint8],
        det: MarkerDetection,
        *,
        pattern: Callable[[MarkerDetection], bool] | None = None,
        predicted: bool = False,
        require_edges: bool = False,
    ) -> MarkerDetection | None:
        """``det`` with corners fitted to the image, or None if no fit succeeds: from the
        marker's four border edges; for a marker whose cells span only a few blur widths,
        where the one-edge model pulls corners inwards, from its whole printed pattern,
        starting from the edges' corners (or from ``det``'s where the edges fail).
        ``pattern``, when given, is asked before a pattern fit and may refuse it (the edges'
        corners stay). ``pattern_s``: the seconds the pattern fit of this call took (0
        without one).

        predicted : ``det``'s corners are where the marker was predicted, not a quad found in
        this image: without fitted edges there is no answer, nor where they end further than
        ``PREDICTED_MAX_MOVE_CELLS`` from the start; where they end over ``SETTLE_PX`` from
        it the edge fit runs again from them (its profiles then straddle the edges evenly:
        from a start a pixel or two off, the corners are off by a few hundredths of a pixel,
        several times their noise on a large marker), and that fit must stay within
        ``SETTLE_PX`` of the first (a fit that has found the edge does).

        require_edges : without fitted edges there is no answer (no pattern fit from ``det``'s
        own corners either): for a start that may be too far off for both."""
        self.pattern_s = 0.0
        i = det.marker_index
        cells = self.target.markers[i].cells
        edges = self.fit_edges(grey, det)
        if edges is None and (predicted or require_edges):
            return None
        if predicted and edges is not None:
            moved = float(np.max(np.linalg.norm(edges.corners_px - det.corners_px, axis=1)))
            if moved > PREDICTED_MAX_MOVE_CELLS * det.side_px / cells.shape[0]:
                return None
            if moved > SETTLE_PX:
                again = self.fit_edges(grey, replace(det, corners_px=edges.corners_px))
                if again is None:
                    return None
                settled = np.linalg.norm(again.corners_px - edges.corners_px, axis=1)
                if float(np.max(settled)) > SETTLE_PX:
                    return None
                edges = again
        corners = None if edges is None else edges.corners_px
        covariance = None if edges is None else edges.covariance_px2
        printed = self.patterns[i]
        if (
            printed is not None
            and self.pattern_settings.applies(
                det.side_px, cells.shape[0], None if edges is None else edges.blur_px
            )
            and (pattern is None or pattern(det))
        ):
            t0 = time.perf_counter()
            start = det.corners_px if edges is None else edges.corners_px
            blur = 1.0 if edges is None else edges.blur_px
            fitted = refine_corners_pattern(
                grey, start, self.camera, printed, self.pattern_settings, blur
            )
            if fitted is not None:
                corners, covariance = fitted, None
            self.pattern_s = time.perf_counter() - t0
        if corners is None:
            return None
        return MarkerDetection(det.marker_index, corners, det.image_pass, covariance)

    def fit_edges(self, grey: NDArray[np.uint8], det: MarkerDetection) -> EdgeFit | None:
        """The edge fit alone of ``det`` (with the marker's cells and white margin), or None
        if it fails."""
        i = det.marker_index
        return fit_marker_edges(
            grey,
            det.corners_px,
            self.camera,
            self.target.markers[i].cells,
            margin_cells=self.margins[i],
        )
