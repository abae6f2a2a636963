"""Corners fitted to the frame for the detector: each found quad's fit (the largest first; a
small marker beside a much larger one may go without the pattern fit, and a pattern fit the
time budget has no room for is left out), a quad whose fit fails kept with its
``cornerSubPix`` corners and their covariance, and tracking's fits straight from a marker's
prediction, kept where its cells read back as printed."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.corners.edge_fit import EdgeFit
from perchpose.corners.refinement import CornerFitter
from perchpose.detection.budget import Budget
from perchpose.detection.finding import CURVED_SIDE_PX, QuadSearch
from perchpose.detection.verification import CellPattern, read_cells
from perchpose.target import TargetSpec
from perchpose.values import MarkerDetection

# With edge-fitted corners, a quad whose corners could not be fitted keeps its cornerSubPix
# corners, with independent errors of this many cells (px: times the side over the cells
# across) as their covariance, so that the fusion's filter leans on its prediction over them:
# on three harsh approaches (fpv, seeds 0-2) the four such quads of 30-32 px were 2.6-3.3 px
# off at their worst corner, half a cell, and one of them put the estimate 2.5 % of the
# distance off (1.2 % with this covariance). (Their error on clean frames is smaller, 0.1-0.3
# px: a small marker that keeps them there counts for less than it could.)
UNFITTED_SD_CELLS = 0.3
# A marker fitted so lies this far (px) inside the image: the edge fit's profiles reach past it.
DIRECT_MARGIN_PX = 2.0


class Fitting:
    """The corner fits of one detector: ``camera`` and ``target``'s, timed into ``budget``,
    with ``search`` for a curved quad's pinhole view; ``pattern_beside_ratio`` as
    ``DetectorSettings`` says."""

    def __init__(
        self,
        camera: CameraModel,
        target: TargetSpec,
        search: QuadSearch,
        budget: Budget,
        pattern_beside_ratio: float | None,
    ) -> None:
        self.camera = camera
        self.target = target
        self.search = search
        self.budget = budget
        self.pattern_beside_ratio = pattern_beside_ratio
        self.fitter = CornerFitter(camera, target)
        self.cell_patterns = [CellPattern.of(target, i) for i in range(len(target.markers))]

    def fit_found(
        self,
        grey: NDArray[np.uint8],
        seen: NDArray[np.uint8],
        found: tuple[MarkerDetection, ...],
    ) -> tuple[MarkerDetection, ...]:
        """The quads of a search (in ``seen``), with corners fitted to ``grey``; a quad whose
        fit fails keeps its ``cornerSubPix`` corners."""
        # a large marker whose curved quad is too far off for the edge fit: its quad from the
        # pinhole view (not a pattern fit from the curved quad's corners)
        curved_px = CURVED_SIDE_PX if self.search.rectify else math.inf
        fitted = self.fit_all(grey, found, edges_from_px=curved_px)
        curved = [d for d in found if fitted[d.marker_index] is None and d.side_px >= curved_px]
        wanted = {d.marker_index for d in curved}
        quads = [d.corners_px for d in curved]
        again = {
            d.marker_index: d
            for d in (self.search.rectified_tracking(seen, quads, search=True) if quads else [])
            if d.marker_index in wanted
        }
        refitted = self.fit_all(grey, again.values())
        return tuple(
            fitted[d.marker_index]
            or refitted.get(d.marker_index)
            or self.unfitted(again.get(d.marker_index, d))
            for d in found
        )

    def fit_corners(
        self,
        grey: NDArray[np.uint8],
        det: MarkerDetection,
        *,
        pattern: Callable[[MarkerDetection], bool] | None = None,
        predicted: bool = False,
        require_edges: bool = False,
    ) -> MarkerDetection | None:
        """``det`` with corners fitted to the image, or None (``CornerFitter.fit_corners``);
        the time it takes counts in ``corners_s``, and a pattern fit's in the cost model that
        predicts the next one's."""
        t0 = time.perf_counter()
        try:
            return self.fitter.fit_corners(
                grey, det, pattern=pattern, predicted=predicted, require_edges=require_edges
            )
        finally:
            self.budget.corners_s += time.perf_counter() - t0
            spent = self.fitter.pattern_s
            if spent > 0:
                self.budget.pattern_fitted(spent, det.side_px)

    def fit_all(
        self,
        grey: NDArray[np.uint8],
        found: Iterable[MarkerDetection],
        predicted: bool = False,
        fitted_px: float = 0.0,
        edges_from_px: float = math.inf,
    ) -> dict[int, MarkerDetection | None]:
        """Each of ``found`` with corners fitted (None where no fit succeeds; ``predicted``:
        see ``CornerFitter.fit_corners``), the largest first. With
        ``pattern_beside_ratio`` set, a marker that many times smaller than one whose corners
        were fitted (among these, or one of ``fitted_px`` fitted before) goes without the
        pattern fit. A marker of ``edges_from_px`` or more needs fitted edges (the
        ``require_edges`` of ``CornerFitter.fit_corners``)."""
        out: dict[int, MarkerDetection | None] = {}
        largest_px = fitted_px

        def pattern(det: MarkerDetection) -> bool:
            ratio = self.pattern_beside_ratio
            if ratio is not None and det.side_px * ratio <= largest_px:
                return False
            if self.budget.late(self.budget.pattern_s_per_px2 * det.side_px**2):
                self.budget.skip(f"pattern fit m{det.marker_index}")
                return False
            return True

        for det in sorted(found, key=lambda d: -d.side_px):
            fitted = self.fit_corners(
                grey,
                det,
                pattern=pattern,
                predicted=predicted,
                require_edges=det.side_px >= edges_from_px,
            )
            out[det.marker_index] = fitted
            if fitted is not None:
                largest_px = max(largest_px, det.side_px)
        return out

    def fit_edges(self, grey: NDArray[np.uint8], det: MarkerDetection) -> EdgeFit | None:
        """The edge fit alone of ``det``, or None (``CornerFitter.fit_edges``)."""
        return self.fitter.fit_edges(grey, det)

    def unfitted(self, det: MarkerDetection) -> MarkerDetection:
        """``det``, a quad whose corners could not be fitted, with the covariance of its
        ``cornerSubPix`` corners: independent, ``UNFITTED_SD_CELLS`` of a cell each way."""
        cell_px = det.side_px / self.target.markers[det.marker_index].cells.shape[0]
        variance_px2 = (UNFITTED_SD_CELLS * cell_px) ** 2
        return replace(det, corner_covariance_px2=variance_px2 * np.eye(8))

    def fit_direct(
        self, grey: NDArray[np.uint8], hint: list[MarkerDetection], least: float | None
    ) -> dict[int, MarkerDetection]:
        """Hinted markers of ``least`` px or more (``direct_side_px``) fitted (``fit_corners``)
        from their hinted corners, without a quad, kept where the marker's cells read through
        the fitted corners as printed (``detection.verification``): a fit that slid to another
        edge or onto something else reads wrong and is dropped."""
        if least is None:
            return {}
        starts = [
            MarkerDetection(d.marker_index, d.corners_px, "tracked")
            for d in hint
            if d.side_px >= least and self.camera.in_image(d.corners_px, DIRECT_MARGIN_PX)
        ]
        out: dict[int, MarkerDetection] = {}
        fits = self.fit_all(grey, starts, predicted=True)
        for index, fitted in fits.items():
            if fitted is None:
                continue
            reading = read_cells(grey, fitted.corners_px, self.camera, self.cell_patterns[index])
            if reading is not None and reading.matches():
                out[index] = fitted
        return out
