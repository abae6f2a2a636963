"""Corners fitted to the image, starting from a found quad: from the marker's four border edges
through the lens model (``edge_fit``), and for a marker whose cells span only a few
blur widths from its whole printed pattern (``pattern_fit``)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.corners.edge_fit import EdgeFit, fit_marker_edges
from perchpose.corners.pattern_fit import (
    PatternFitSettings,
    PrintedPattern,
    printed_pattern,
    refine_corners_pattern,
)
from perchpose.corners.pattern_model import banded
from perchpose.target import TargetSpec
from perchpose.values import MarkerDetection, corners_sd_px

Array = NDArray[np.float64]

# A predicted marker whose fitted corners end further than this (px) from where they were
# predicted is fitted again from them, and that second fit must move them less than this
# again (``CornerFitter.fit_corners``) ...
SETTLE_PX = 0.3
# ... or than this many of the first fit's standard deviations, where that is more: on harsh
# frames (corners 0.08-0.1 px sd by the fit, 0.3 px RMS from the truth) a fit from another
# start lands that much apart; on the harsh fpv approach, 4 of 19 frames whose tracking fell
# back on a whole-frame search did so only for this, with the same errors against the truth.
SETTLE_SDS = 5.0
# How far a start m px off pulls the edge fit's corners, per px^2 of m: the profiles then
# straddle the edges unevenly (on clean fpv renders 1.5 px off: 0.08 px at 37 px, 0.06 at 46,
# 0.04 at 65, 0.01 at 72, under 0.01 at 81; 2 px off: 0.13, 0.11, 0.08, 0.04, 0.01). A second
# fit from the first's corners is worth its time only where that pull, with m the corners'
# mean move from the start, is a fair part of their own noise: SETTLE_NOISE_FRACTION of their
# standard deviation (it then adds at most 12 % to it). On harsh frames it is not.
STRADDLE_PULL_PX = 0.03
SETTLE_NOISE_FRACTION = 0.5
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
        # how many more pattern fits take bands over the rows in from their first round: the
        # latest fits found the video banded (``PatternFitSettings``)
        self.banded_fits_left = 0
        # the blur sigma (px) the latest successful edge fit found; None until one does or
        # after ``forget_blur``
        self.blur_px: float | None = None

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
        it and so far that the uneven straddle pulls them by a fair part of their own noise
        (``STRADDLE_PULL_PX``), the edge fit runs again from them (its profiles then straddle
        the edges evenly), and that fit must stay within ``SETTLE_PX`` of the first, or
        within ``SETTLE_SDS`` of its standard deviations (a fit that has found the edge
        does). A pattern fit, where the marker gets one, starts from the first edge fit's
        corners: it ends in the same place from either.

        require_edges : without fitted edges there is no answer (no pattern fit from ``det``'s
        own corners either): for a start that may be too far off for both."""
        self.pattern_s = 0.0
        i = det.marker_index
        cells = self.target.markers[i].cells
        edges = self.fit_edges(grey, det)
        if edges is None and (predicted or require_edges):
            return None
        unsettled = False
        if predicted and edges is not None:
            moves = np.linalg.norm(edges.corners_px - det.corners_px, axis=1)
            moved = float(np.max(moves))
            if moved > PREDICTED_MAX_MOVE_CELLS * det.side_px / cells.shape[0]:
                return None
            noise_px = corners_sd_px(edges.covariance_px2)
            pull_px = STRADDLE_PULL_PX * float(np.mean(moves)) ** 2
            unsettled = moved > SETTLE_PX and pull_px > SETTLE_NOISE_FRACTION * noise_px
        printed = self.patterns[i]
        if (
            printed is not None
            and self.pattern_settings.applies(
                det.side_px, cells.shape[0], None if edges is None else edges.blur_px
            )
            and (pattern is None or pattern(det))
        ):
            # the whole pattern fitted from the edges' corners (where they are a little off,
            # it takes them to the same end as from settled ones: no second edge fit first)
            t0 = time.perf_counter()
            start = det.corners_px if edges is None else edges.corners_px
            # without its own edges' blur, that of the latest edge fit that succeeded
            # (``blur_px``): it also decides whether the fit runs on 2x2 blocks (a harsh
            # frame's 37 px marker: 6 ms on pixels from 1 px, 2 ms on blocks)
            blur = edges.blur_px if edges is not None else (self.blur_px or 1.0)
            fitted = self._fit_pattern(grey, start, printed, blur, edges is None)
            self.pattern_s = time.perf_counter() - t0
            if fitted is not None:
                return MarkerDetection(det.marker_index, fitted, det.image_pass, None)
        if edges is not None and unsettled:
            edges = self._settled(grey, det, edges)
        if edges is None:
            return None
        return MarkerDetection(
            det.marker_index, edges.corners_px, det.image_pass, edges.covariance_px2
        )

    def _fit_pattern(
        self,
        grey: NDArray[np.uint8],
        start: Array,
        printed: PrintedPattern,
        blur_px: float,
        from_quad: bool,
    ) -> Array | None:
        """The pattern fit's corners from ``start`` (``from_quad``: a found quad's corners),
        with bands over the rows from the first round where recent fits found them."""
        cfg = self.pattern_settings
        known = self.banded_fits_left > 0
        fit = refine_corners_pattern(
            grey, start, self.camera, printed, cfg, blur_px, from_quad=from_quad, banded=known
        )
        self.banded_fits_left = max(0, self.banded_fits_left - 1)
        if fit is None:
            return None
        if banded(fit.banding, cfg.banded_fits_above):
            self.banded_fits_left = cfg.banded_fits
        return fit.corners_px

    def _settled(
        self, grey: NDArray[np.uint8], det: MarkerDetection, edges: EdgeFit
    ) -> EdgeFit | None:
        """The edge fit of ``det`` again from the corners of its first fit ``edges``; None
        where it fails or moves them over ``SETTLE_PX`` or ``SETTLE_SDS`` of the first's
        standard deviations, whichever is more (the first did not find the edge)."""
        again = self.fit_edges(grey, replace(det, corners_px=edges.corners_px))
        if again is None:
            return None
        settled = np.linalg.norm(again.corners_px - edges.corners_px, axis=1)
        limit = max(SETTLE_PX, SETTLE_SDS * corners_sd_px(edges.covariance_px2))
        return None if float(np.max(settled)) > limit else again

    def fit_edges(self, grey: NDArray[np.uint8], det: MarkerDetection) -> EdgeFit | None:
        """The edge fit alone of ``det`` (with the marker's cells and white margin), or None
        if it fails. A fit that succeeds sets ``blur_px``."""
        i = det.marker_index
        fit = fit_marker_edges(
            grey,
            det.corners_px,
            self.camera,
            self.target.markers[i].cells,
            margin_cells=self.margins[i],
        )
        if fit is not None:
            self.blur_px = fit.blur_px
        return fit

    def forget_blur(self) -> None:
        """Forgets the blur of earlier fits (``blur_px``: None): e.g. at a new frame."""
        self.blur_px = None
