"""Detection of a target's markers: the quads OpenCV finds (``detection.quads``), in windows
around where they are expected while tracking (``detection.windows``), with corners fitted to
the image (``corners.refinement``).

Corners come back in the pixels of the original (distorted) image. For a lens whose distortion
bends a large marker's edges enough that OpenCV's quad finder misses it, a second pass runs on a
pinhole rectification of the image (``detection.rectification``) and maps the corners it finds
back through the lens model.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import replace
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.corners.edge_fit import EdgeFit
from perchpose.corners.refinement import CornerFitter
from perchpose.detection.quads import (
    ImagePass,
    QuadFinder,
    QuadPass,
    refine_corners,
    target_dictionaries,
)
from perchpose.detection.rectification import COARSE_STEP, Rectification
from perchpose.detection.verification import CellPattern, read_cells
from perchpose.detection.windows import (
    Box,
    predicted_quads,
    rectified_box,
    rectified_windows,
    tracking_window,
)
from perchpose.target import TargetSpec
from perchpose.values import MarkerDetection, quad_side_px

__all__ = [
    "CORNER_METHODS",
    "PATTERN_BESIDE_RATIO",
    "CornerMethod",
    "MarkerDetector",
    "refine_corners",
    "target_dictionaries",
]

Array = NDArray[np.float64]

# A lens that moves the image border this far from its pinhole position gets the rectified pass.
RECTIFY_ABOVE_PX = 6.0
# Found in both passes, a marker this large in the original image is taken from the rectified
# pass (its edges are curved in the original); a smaller one from the original image.
CURVED_SIDE_PX = 40.0
CornerMethod = Literal["edges", "subpix"]
CORNER_METHODS: tuple[CornerMethod, ...] = ("edges", "subpix")
# With edge-fitted corners, a quad whose corners could not be fitted keeps its cornerSubPix
# corners, with independent errors of this many cells (px: times the side over the cells
# across) as their covariance, so that the fusion's filter leans on its prediction over them:
# on three harsh approaches (fpv, seeds 0-2) the four such quads of 30-32 px were 2.6-3.3 px
# off at their worst corner, half a cell, and one of them put the estimate 2.5 % of the
# distance off (1.2 % with this covariance). (Their error on clean frames is smaller, 0.1-0.3
# px: a small marker that keeps them there counts for less than it could.)
UNFITTED_SD_CELLS = 0.3
# A hinted marker under this side may drop out of tracking without sending the frame to the
# full search; the tracking pass adds OpenCV's 3 px threshold window for such markers.
SMALL_MARKER_SIDE_PX = 20.0
# A pattern fit's first predicted cost, seconds per square pixel of the marker's side (10 ms
# at 45 px: what a fit on 2x2 blocks under the harsh preset's blur cost on a 2-core x86
# machine before the model merged its bands; about 1.5 ms now); each fit run updates the
# prediction.
PATTERN_S_PER_PX2 = 5e-6
# Each learnt cost (a pattern fit's per square pixel, a whole-frame search's, a quick look's)
# moves this fraction of the way to each new run's.
COST_UPDATE = 0.3
# Glare: a frame with at least GLARE_FRACTION of its pixels at GLARE_LEVEL or above has its
# quads searched in copies clipped at these levels (None: the frame as it is), tried in this
# order, the next one whenever the current one finds nothing: a level between the black
# border's grey and the white margin's works, and these cover white margins from about 50 to
# 230 grey levels.
GLARE_LEVEL = 250
GLARE_FRACTION = 0.05
GLARE_CLIP_LEVELS: tuple[int | None, ...] = (None, 108, 72, 162, 48, 224)
# While the target is not tracked, a whole frame is looked at quickly first (one threshold
# window, ``QuadFinder.quick``), and the markers that finds are completed where the target's
# plane through them puts the others; where the quick looks find nothing, the estimator's
# detector searches the whole frame thoroughly (OpenCV's other two windows) on every
# THOROUGH_EVERY-th such frame (``MarkerDetector(thorough_every=...)``; None: on every one).
THOROUGH_EVERY = 3
# While tracking, every this many frames the whole frame is searched for the markers tracking
# has not got (none when it has them all), shrunk by CHECK_SCALE.
FULL_SEARCH_EVERY = 30
CHECK_SCALE = 0.5
# While tracking, the window is searched shrunk so that the smallest predicted marker spans
# this much (never enlarged): the quads are a start for the fit at full resolution, and a
# large marker costs the detector a fraction of its pixels.
TRACKING_SIDE_PX = 48.0
# While tracking, a hinted marker this large is fitted straight from where it is predicted,
# and kept if its cells read back as printed; only the others, and those whose fit fails or
# reads wrong, go through a quad search. Whatever its white margin: where the profiles reach
# near the margin's end the fit depends a little on its start (the paper target's outer
# marker at 25-50 px on the fpv approach: 0.0134 px RMS from its prediction, 0.0124 from a
# quad's cornerSubPix corners, which lie a little inside the edge; no change from 100 px up),
# which no pose figure shows, and the window search it spares cost about 0.3 ms a frame.
DIRECT_SIDE_PX = 20.0
# While tracking, a marker the target's plane puts in view without a hint is searched for
# once it is predicted this large (a little under the smallest marker OpenCV's quad pass
# finds, about 9 px on rendered frames).
MIN_SEARCH_SIDE_PX = 7.0
# A marker fitted so lies this far (px) inside the image: the edge fit's profiles reach past it.
DIRECT_MARGIN_PX = 2.0
# While tracking, a marker the target's plane puts in view without a hint is not searched for
# while its cells are narrower than this many blur sigmas (the blur of the markers fitted in
# the same frame): OpenCV cannot read it yet (the paper target's inner marker on the fpv
# approach is first read at 2.05 sigmas; under the harsh preset, at 2.5 and from 4.6 on).
MIN_READ_CELL_BLURS = 1.8
# A marker this many times smaller than another whose corners were fitted in the same frame
# may go without the pattern fit (``MarkerDetector(pattern_beside_ratio=...)``).
PATTERN_BESIDE_RATIO = 4.0


def _learnt(cost: float, measured: float) -> float:
    """A learnt cost moved ``COST_UPDATE`` of the way to the one just ``measured``."""
    return cost + COST_UPDATE * (measured - cost)


def has_glare(grey: NDArray[np.uint8]) -> bool:
    """Whether ``grey`` has a large saturated area (``GLARE_FRACTION`` of its pixels)."""
    # OpenCV's threshold and count: the same count as numpy's comparison, a third the time
    _, saturated = cv2.threshold(grey, GLARE_LEVEL - 1, 255, cv2.THRESH_BINARY)
    return int(cv2.countNonZero(saturated)) >= GLARE_FRACTION * grey.size


class MarkerDetector:
    """Finds the markers of ``target`` in grey images of ``camera``.

    All dictionaries of the target are searched in one ``detectMarkersMultiDict`` pass; ids that
    are not the target's (dictionary, id) pairs are ignored. ``pattern_beside_ratio``: a marker
    that many times smaller than another whose corners were fitted in the same frame keeps its
    edge-fitted corners without the pattern fit (None: every small marker gets it).
    ``thorough_every``: while the target is not tracked and the quick looks at a frame find
    nothing, the whole frame is searched thoroughly only on every that many-th such frame
    (``THOROUGH_EVERY``; None, the default: on every one, as unrelated images need; ``_look``).
    """

    def __init__(
        self,
        camera: CameraModel,
        target: TargetSpec,
        corners: CornerMethod = "edges",
        pattern_beside_ratio: float | None = None,
        thorough_every: int | None = None,
    ) -> None:
        if corners not in CORNER_METHODS:
            raise ValueError(f"corners must be one of {', '.join(CORNER_METHODS)}, got {corners!r}")
        if thorough_every is not None and thorough_every < 1:
            raise ValueError(f"thorough_every must be at least 1, got {thorough_every}")
        self.camera = camera
        self.target = target
        self.corners = corners
        self.pattern_beside_ratio = pattern_beside_ratio
        self.thorough_every = thorough_every
        # frames in a row without the target that had only quick looks (None: none has been
        # searched thoroughly since ``restart``)
        self._quick_only: int | None = None
        self.tracking_side_px = TRACKING_SIDE_PX
        self.full_search_every: int | None = FULL_SEARCH_EVERY
        self._tracked_frames = 0
        # whether this frame's tracking also searches the whole frame (``_interval_due``)
        self._check = False
        self.quads = QuadFinder(target, max(camera.size))
        self.fitter = CornerFitter(camera, target)
        self.cell_patterns = [CellPattern.of(target, i) for i in range(len(target.markers))]
        # hinted markers this large that tracking's quad pass misses are fitted without a quad
        # (None: never)
        self.direct_side_px: float | None = DIRECT_SIDE_PX
        self.rectify = camera.max_distortion_px() > RECTIFY_ABOVE_PX
        # seconds spent fitting corners during the last ``detect``
        self.corners_s = 0.0
        # the way of searching a whole frame tried first (``search_ladder``): the one that
        # found the target last, or the next one to try
        self._rung: tuple[int | None, ImagePass] = (None, "raw")
        # where in the ladder the search for a lost target has got to
        self._explored = 0
        # thorough whole-frame searches, and frames looked at a second way, since the target
        # was last found (``_look``)
        self._thorough_turn = 0
        self._second_turn = 0
        # the time budget of the current ``detect``, what it left out, and the pattern fit's
        # cost per square pixel of marker side (learnt from the fits run; first guess
        # ``PATTERN_S_PER_PX2``)
        self._deadline_s: float | None = None
        self.skipped: list[str] = []
        self._pattern_s_per_px2 = PATTERN_S_PER_PX2
        self._search_s = 0.0  # a whole-frame search's cost, learnt likewise
        self._quick_s = 0.0  # a quick look's, likewise

    def restart(self) -> None:
        """A new run of frames: the next frame without the target is searched thoroughly, and
        the other ways of the ladder are gone through from its start."""
        self._quick_only = None
        self._thorough_turn = self._second_turn = 0

    def detect(
        self,
        grey: NDArray[np.uint8],
        hint: tuple[MarkerDetection, ...] = (),
        deadline_s: float | None = None,
    ) -> tuple[MarkerDetection, ...]:
        """Detect the target's markers in a grey (H, W) uint8 image of the camera's size.

        hint : the previous frame's detections (see ``_track_edges``). With ``corners="edges"``
        (the default) each marker's corners are then refitted from its four border edges
        through the lens model (``corners.edge_fit``); ``"subpix"`` keeps the ``cornerSubPix``
        corners.

        Where nothing is tracked, the whole frame is searched, in one of the ways of
        ``search_ladder``: the frame as it is, and through a strongly distorted lens its
        pinhole view; under glare also the frame clipped at each level of
        ``GLARE_CLIP_LEVELS`` (every level of the frame first: the pinhole view is for large
        markers near contact). A frame starts with the way that found the target last
        (``_found_by``) and, when that finds nothing, tries the next way not yet tried
        since the target was lost: a lost target is looked for every way in turn, one more a
        frame. With edge-fitted corners each of the two ways is a quick look first
        (``_look``); the ``cornerSubPix`` pipeline searches both thoroughly.

        Glare: where a large part of the frame is saturated (a bright sky or lamps around a
        target in shadow), the adaptive threshold sees the sheet's white margin as dark next to
        the surround and no quad closes. The quads are then searched in the frame clipped at a
        level between the sheet's black and white (corners are still fitted to the frame
        itself).

        deadline_s : a ``time.perf_counter()`` reading by which the detection should be done.
        What would not end by then is left out where it can be (each step's cost predicted
        from its runs so far): a pattern fit, the whole-frame search after tracking lost a
        marker, the second way of searching, and the whole-frame search for markers it
        lacks that tracking runs every ``full_search_every`` frames (``FULL_SEARCH_EVERY``,
        ``_with_unseen``). ``skipped`` names what this call left out.
        """
        self.corners_s = 0.0
        self.skipped = []
        self._deadline_s = deadline_s
        self._check = self._interval_due(hint)
        ladder = self.search_ladder(has_glare(grey))
        if self._rung not in ladder:
            self._rung = ladder[0]
        first = self._rung
        if self.corners == "subpix":
            return self._search_afresh(grey, hint, ladder, first)
        if hint:
            seen = self._seen(grey, first[0])
            tracked, window_quads = self._track_edges(grey, seen, hint)
            if tracked is not None:
                if self._check:
                    tracked = self._with_unseen(grey, seen, tracked)
                return self._found_by(tracked, first)
            return self._after_loss(grey, seen, hint, ladder, first, window_quads)
        return self._look(grey, ladder, first)

    def _after_loss(
        self,
        grey: NDArray[np.uint8],
        seen: NDArray[np.uint8],
        hint: tuple[MarkerDetection, ...],
        ladder: list[tuple[int | None, ImagePass]],
        first: tuple[int | None, ImagePass],
        window_quads: bool,
    ) -> tuple[MarkerDetection, ...]:
        """The search after tracking lost a marker it needs. Where its window pass saw quads
        (``window_quads``) it could not use (a fit refused, a curved quad), the window where
        the target's plane puts the markers is searched thoroughly first; where it saw none
        (the target hidden or gone), or that finds none, the whole frame is looked at
        (``_look``). None of it where the budget has no room for it: the filter coasts."""
        if self._late(self._search_s):
            self.skipped.append("search")
            return ()
        if not window_quads:
            return self._look(grey, ladder, first)
        whole = self._hint_window(seen, hint) is None or first[1] == "rectified"
        found = self._thorough(seen, hint, first[1], whole=False)
        if found:
            return self._found_by(self._fit_found(grey, seen, found), first)
        return self._look(grey, ladder, first, looked=whole)

    def _search_afresh(
        self,
        grey: NDArray[np.uint8],
        hint: tuple[MarkerDetection, ...],
        ladder: list[tuple[int | None, ImagePass]],
        first: tuple[int | None, ImagePass],
    ) -> tuple[MarkerDetection, ...]:
        """The ``cornerSubPix`` pipeline's search: thorough, ``first`` way and, where that
        finds nothing, one way more (``_find``: around ``hint`` first)."""
        clip_level, view = first
        # at the interval, the whole frame searched afresh
        afresh = self._check and self._interval_search(self._search_s)
        found = self._find(self._seen(grey, clip_level), () if afresh else hint, view)
        if found or len(ladder) == 1:
            return self._found_by(found, first)
        rung = self._next_way(ladder, first)
        if self._late(self._search_s):
            # no room for it: it is the next frame's first
            self.skipped.append(self._second_label(rung))
            self._rung = rung
            return found
        return self._found_by(self._find(self._seen(grey, rung[0]), (), rung[1]), rung)

    def _next_way(
        self, ladder: list[tuple[int | None, ImagePass]], first: tuple[int | None, ImagePass]
    ) -> tuple[int | None, ImagePass]:
        """The next way of the ladder not yet tried in this run of frames without the target
        (never ``first``)."""
        self._explored = (self._explored + 1) % len(ladder)
        if ladder[self._explored] == first:
            self._explored = (self._explored + 1) % len(ladder)
        return ladder[self._explored]

    def _second_way(
        self, ladder: list[tuple[int | None, ImagePass]], first: tuple[int | None, ImagePass]
    ) -> tuple[int | None, ImagePass]:
        """The way a frame without the target is looked at after ``first``: on every other
        such frame the ladder's first way but ``first`` (under glare, the first clip level of
        the frame), else the next other way not yet tried (``_next_way``). A target that one way
        finds on some frames only (small and noisy) is then found within a few frames, not
        once the whole ladder has been gone through (twelve frames through a fisheye under
        glare)."""
        priority = next(way for way in ladder if way != first)
        self._second_turn += 1
        if self._second_turn % 2 == 1 or len(ladder) <= 2:
            return priority
        way = self._next_way(ladder, first)
        return self._next_way(ladder, first) if way == priority else way

    @staticmethod
    def _second_label(rung: tuple[int | None, ImagePass]) -> str:
        """What ``skipped`` calls the second way of searching a frame, left out."""
        return "glare search" if rung[0] is not None else "second search"

    @staticmethod
    def _seen(grey: NDArray[np.uint8], clip_level: int | None) -> NDArray[np.uint8]:
        """The image the quads are searched in: ``grey`` clipped at ``clip_level`` (None: as
        it is)."""
        return grey if clip_level is None else np.minimum(grey, np.uint8(clip_level))

    def _look(
        self,
        grey: NDArray[np.uint8],
        ladder: list[tuple[int | None, ImagePass]],
        first: tuple[int | None, ImagePass],
        looked: bool = False,
    ) -> tuple[MarkerDetection, ...]:
        """The target, not tracked, searched for in the whole frame: a quick look
        (``QuadFinder.quick``, one threshold window) the ``first`` way (not where ``looked``:
        this frame was just searched whole that way, thoroughly) and, through a
        distorted lens or under glare, one way more (``_next_way``); where one finds
        markers, they and those it lacks where the target's plane through them puts them
        (``_quick_look``). Where neither finds any: the thorough search of the whole frame the
        ``first`` way, with OpenCV's other two threshold windows (the quick look misses markers
        under about 15 px); with ``thorough_every``, only on every that many-th frame since the
        target was last found or the frame last searched so, and on the first after
        ``restart``."""
        ways = [first] if len(ladder) == 1 else [first, self._second_way(ladder, first)]
        for k, way in enumerate(ways):
            if k == 0 and looked:
                continue
            if k > 0 and self._late(self._quick_s):
                # no room for it: it is the next frame's first
                self.skipped.append(self._second_label(way))
                self._rung = way
                return ()
            found = self._quick_look(grey, way)
            if found:
                return self._found_by(found, way)
        every = self.thorough_every
        if every is not None and self._quick_only is not None and self._quick_only < every - 1:
            self._quick_only += 1
            return ()
        if self._late(self._search_s):
            self.skipped.append("search")
            return ()
        # the quick look had OpenCV's widest threshold window: the other two make up the rest
        way = self._thorough_way(ladder, first)
        seen = self._seen(grey, way[0])
        found = self._thorough(seen, (), way[1], detector=self.quads.rest)
        return self._found_by(self._fit_found(grey, seen, found), way)

    def _thorough_way(
        self, ladder: list[tuple[int | None, ImagePass]], first: tuple[int | None, ImagePass]
    ) -> tuple[int | None, ImagePass]:
        """The way a lost target's next thorough search goes: the ways of ``first``'s view in
        the ladder's order, one a search, from ``first`` on. Under glare that takes in every
        clip level: the quick look's one threshold window misses small markers at any level,
        and the frame itself, unclipped, seldom shows them at all (the harsh approach through
        ``fpv_wide``, 20-23 px at 150 cm: found at clip level 108 by the thorough search
        alone)."""
        same_view = [way for way in ladder if way[1] == first[1]]
        start = same_view.index(first) if first in same_view else 0
        way = same_view[(start + self._thorough_turn) % len(same_view)]
        self._thorough_turn += 1
        return way

    def _quick_look(
        self, grey: NDArray[np.uint8], way: tuple[int | None, ImagePass]
    ) -> tuple[MarkerDetection, ...]:
        """The markers a quick look at the whole frame finds ``way``, with those it lacks that
        the target's plane through them puts in view (``_with_predicted``), fitted; () where
        it finds none. Through the pinhole view, what the quick look finds (corners mapped
        back to the frame)."""
        clip_level, view = way
        seen = self._seen(grey, clip_level)
        t0 = time.perf_counter()
        if view == "rectified":
            found = self._find(seen, (), "rectified", detector=self.quads.quick)
        else:
            quick = self.quads.find(seen, "raw", detector=self.quads.quick)
            found = tuple(quick[i] for i in sorted(quick))
        self._quick_s = _learnt(self._quick_s, time.perf_counter() - t0)
        if not found:
            return ()
        if view == "raw":
            found = self._with_predicted(seen, found)
        return self._fit_found(grey, seen, found)

    def _with_predicted(
        self, seen: NDArray[np.uint8], found: tuple[MarkerDetection, ...]
    ) -> tuple[MarkerDetection, ...]:
        """``found``, and the target's markers it lacks where the plane through it puts them
        in view and large enough to read (``_may_be_found``), searched in a window around
        them as tracking's pass does (``_window_pass``: the quick look's one wide threshold
        window misses small markers, which that pass searches with a 3 px one) and, through a
        strongly distorted lens, those still missing in the pinhole view's windows around where
        the plane puts them there (``_rectified_refind``, as ``_find`` does)."""
        have = {d.marker_index: d for d in found}
        missing = {
            i: q
            for i, q in predicted_quads(self.target, found).items()
            if i not in have and self._may_be_found(q, i, hinted=False)
        }
        if missing:
            for index, det in self._window_pass(seen, missing).items():
                if index in missing:
                    have.setdefault(index, det)
        if self.rectify and len(have) < len(self.target.markers):
            have = self._rectified_refind(seen, have, None)
        return tuple(have[i] for i in sorted(have))

    def _thorough(
        self,
        seen: NDArray[np.uint8],
        hint: tuple[MarkerDetection, ...],
        view: ImagePass,
        whole: bool = True,
        detector: QuadPass | None = None,
    ) -> tuple[MarkerDetection, ...]:
        """``_find`` (OpenCV's three threshold windows, or ``detector``'s), its cost learnt;
        the frame counts as searched thoroughly."""
        t0 = time.perf_counter()
        found = self._find(seen, hint, view, refind_curved=False, whole=whole, detector=detector)
        self._search_s = _learnt(self._search_s, time.perf_counter() - t0)
        self._quick_only = 0
        return found

    def _found_by(
        self, found: tuple[MarkerDetection, ...], rung: tuple[int | None, ImagePass]
    ) -> tuple[MarkerDetection, ...]:
        """``found``; where it holds a marker, the next frame starts the way ``rung`` says,
        but with ``cornerSubPix`` corners in the frame itself: their pinhole view is searched
        at full size, two to three times the cost of the frame, and is needed only while no
        quad closes there."""
        if found:
            self._rung = rung if self.corners == "edges" else (rung[0], "raw")
            self._quick_only = 0
            self._thorough_turn = self._second_turn = 0
        return found

    def search_ladder(self, glare: bool) -> list[tuple[int | None, ImagePass]]:
        """The ways of searching a whole frame, in the order they are tried: (clip level or
        None, ``raw`` or ``rectified``)."""
        levels = GLARE_CLIP_LEVELS if glare else (None,)
        views: tuple[ImagePass, ...] = ("raw", "rectified") if self.rectify else ("raw",)
        return [(level, view) for view in views for level in levels]

    def _interval_due(self, hint: tuple[MarkerDetection, ...]) -> bool:
        """Whether ``full_search_every`` tracked frames have passed since the last
        whole-frame look (``_with_unseen``); it stays due until one is made."""
        every = self.full_search_every
        if not hint or every is None:
            self._tracked_frames = 0
            return False
        self._tracked_frames += 1
        return self._tracked_frames >= every

    def _interval_search(self, cost_s: float) -> bool:
        """Whether the interval's whole-frame look, of ``cost_s`` predicted, runs now: not
        where the budget has no room for it (it is then put off to the next frame)."""
        if self._late(cost_s):
            self.skipped.append("interval search")
            return False
        self._tracked_frames = 0
        return True

    def _with_unseen(
        self,
        grey: NDArray[np.uint8],
        seen: NDArray[np.uint8],
        tracked: tuple[MarkerDetection, ...],
    ) -> tuple[MarkerDetection, ...]:
        """``tracked``, and the target's markers it lacks where a search of the whole of
        ``seen`` shrunk by ``CHECK_SCALE`` finds them and their corners can be fitted to
        ``grey``: so a marker the windows cannot see (the plane put it elsewhere) is found
        within ``full_search_every`` frames. Tracked markers are kept as tracked (fitted
        from their prediction, their cells read back); with all of them tracked there is
        nothing to look for."""
        have = {d.marker_index: d for d in tracked}
        if len(have) == len(self.target.markers):
            self._tracked_frames = 0
            return tracked
        if not self._interval_search(self._search_s * CHECK_SCALE**2):
            return tracked
        found = self.quads.find(seen, "raw", scale=CHECK_SCALE)
        new = [d for i, d in found.items() if i not in have]
        fitted_px = max((d.side_px for d in tracked), default=0.0)
        for index, fitted in self._fit_all(grey, new, fitted_px=fitted_px).items():
            if fitted is not None:  # a shrunk image's quad is no corners to keep unfitted
                have[index] = fitted
        return tuple(have[i] for i in sorted(have))

    def _fit_found(
        self,
        grey: NDArray[np.uint8],
        seen: NDArray[np.uint8],
        found: tuple[MarkerDetection, ...],
    ) -> tuple[MarkerDetection, ...]:
        """The quads of a search (in ``seen``), with corners fitted to ``grey``; a quad whose
        fit fails keeps its ``cornerSubPix`` corners."""
        # a large marker whose curved quad is too far off for the edge fit: its quad from the
        # pinhole view (not a pattern fit from the curved quad's corners)
        curved_px = CURVED_SIDE_PX if self.rectify else math.inf
        fitted = self._fit_all(grey, found, edges_from_px=curved_px)
        curved = [d for d in found if fitted[d.marker_index] is None and d.side_px >= curved_px]
        wanted = {d.marker_index for d in curved}
        quads = [d.corners_px for d in curved]
        again = {
            d.marker_index: d
            for d in (self._rectified_tracking(seen, quads, search=True) if quads else [])
            if d.marker_index in wanted
        }
        refitted = self._fit_all(grey, again.values())
        return tuple(
            fitted[d.marker_index]
            or refitted.get(d.marker_index)
            or self._unfitted(again.get(d.marker_index, d))
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
            self.corners_s += time.perf_counter() - t0
            spent = self.fitter.pattern_s
            if spent > 0:
                rate = spent / max(1.0, det.side_px**2)
                self._pattern_s_per_px2 = _learnt(self._pattern_s_per_px2, rate)

    def _fit_all(
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
            if self._late(self._pattern_s_per_px2 * det.side_px**2):
                self.skipped.append(f"pattern fit m{det.marker_index}")
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

    def _late(self, more_s: float) -> bool:
        """Whether ``more_s`` seconds of work from now would end past the deadline."""
        deadline = self._deadline_s
        return deadline is not None and time.perf_counter() + more_s > deadline

    def fit_edges(self, grey: NDArray[np.uint8], det: MarkerDetection) -> EdgeFit | None:
        """The edge fit alone of ``det``, or None (``CornerFitter.fit_edges``)."""
        return self.fitter.fit_edges(grey, det)

    def _track_edges(
        self, grey: NDArray[np.uint8], seen: NDArray[np.uint8], hint: tuple[MarkerDetection, ...]
    ) -> tuple[tuple[MarkerDetection, ...] | None, bool]:
        """Tracking with edge-fitted corners, and whether its window pass found any quad.
        Each hinted marker of ``direct_side_px`` or more
        is fitted straight from where it is predicted and kept where its cells read back as
        printed (``_fit_direct``): no quad search for it. The markers left (smaller ones,
        those whose fit failed or read wrong, and those the target's plane puts in view that
        were not hinted and may be read, ``_may_be_found``) are searched in one
        single-threshold pass over a window around them (the whole image when the window would
        cover most of it), then fitted through the lens model, which also straightens what a
        fisheye bends; a hinted quad whose fit fails keeps its ``cornerSubPix`` corners.

        Through a strongly distorted lens, hinted markers still missing, and a large marker
        whose curved quad is too far off for the edge fit, are searched again in windows of
        the rectified view around where they are predicted. None when a marker of 20 px or
        more predicted in view is still not found: the caller then runs the full search (one
        predicted across the image's border is leaving the view, and let go). A hinted marker under
        20 px (at the edge of detection, where markers come and go) may drop out without one.
        A small marker whose edges cannot be fitted keeps its ``cornerSubPix`` corners. Quads
        are searched in ``seen`` (``grey`` or its clipped copy), corners fitted to ``grey``."""
        quads = predicted_quads(self.target, hint)
        self.fitter.forget_blur()
        result = self._fit_direct(grey, list(hint))
        blur_px = self.fitter.blur_px if result else None
        hinted = {d.marker_index for d in hint}
        left = {
            i: q
            for i, q in quads.items()
            if i not in result and self._may_be_found(q, i, i in hinted, blur_px)
        }
        found = self._window_pass(seen, left) if left else {}
        required: list[int] = []
        fitted_px = max((d.side_px for d in result.values()), default=0.0)
        searched = {i: d for i, d in found.items() if i not in result}
        for index, fitted in self._fit_all(grey, searched.values(), fitted_px=fitted_px).items():
            det = searched[index]
            if fitted is None and self.rectify and det.side_px >= CURVED_SIDE_PX:
                required.append(index)  # a curved quad too far off for the fit
            else:
                # where the fit fails, the quad's cornerSubPix corners (on blurred frames they
                # can be pixels off; the prediction's own fit failed or read wrong before)
                result[index] = fitted or self._unfitted(det)
        # a marker predicted across the image's border is leaving the view: no quad closes there
        missing = [d for d in hint if d.marker_index not in result and self._in_view(d.corners_px)]
        required += [d.marker_index for d in missing if d.side_px >= SMALL_MARKER_SIDE_PX]
        again = [d.marker_index for d in missing]
        again += [i for i in required if i not in result and i not in again]
        if again and self.rectify:
            retry = [quads[i] for i in again if i in quads]
            for det in self._rectified_tracking(seen, retry):
                if det.marker_index in again and det.marker_index not in result:
                    result[det.marker_index] = self.fit_corners(grey, det) or self._unfitted(det)
        if any(index not in result for index in required):
            return None, bool(found)
        return tuple(result[i] for i in sorted(result)), bool(found)

    def _unfitted(self, det: MarkerDetection) -> MarkerDetection:
        """``det``, a quad whose corners could not be fitted, with the covariance of its
        ``cornerSubPix`` corners: independent, ``UNFITTED_SD_CELLS`` of a cell each way."""
        cell_px = det.side_px / self.target.markers[det.marker_index].cells.shape[0]
        variance_px2 = (UNFITTED_SD_CELLS * cell_px) ** 2
        return replace(det, corner_covariance_px2=variance_px2 * np.eye(8))

    def _may_be_found(
        self, quad: Array, index: int, hinted: bool, blur_px: float | None = None
    ) -> bool:
        """Whether the window pass should look for marker ``index`` predicted at ``quad``:
        where it lies wholly in the image (``_in_view``: OpenCV keeps no quad that crosses
        the border), a hinted one always; one the plane predicts (not hinted) where it is
        large enough for OpenCV's smallest quad (``MIN_SEARCH_SIDE_PX``) and, given the
        frame's blur sigma ``blur_px``, has cells of ``MIN_READ_CELL_BLURS`` of it or more."""
        if not self._in_view(quad):
            return False
        if hinted:
            return True
        side_px = quad_side_px(quad)
        cells = int(self.target.markers[index].cells.shape[0])
        if blur_px is not None and side_px / cells < MIN_READ_CELL_BLURS * blur_px:
            return False
        return side_px >= MIN_SEARCH_SIDE_PX

    def _in_view(self, quad: Array) -> bool:
        """Whether ``quad`` lies in the image as far from its border as OpenCV keeps its
        quads (``QuadFinder.border_margin_px``)."""
        return self.camera.in_image(quad, self.quads.border_margin_px)

    def _window_pass(
        self, seen: NDArray[np.uint8], quads: dict[int, Array]
    ) -> dict[int, MarkerDetection]:
        """The tracking detector's quads in a window around the predicted ``quads``, searched
        shrunk so that the smallest of them spans ``tracking_side_px``."""
        smallest = min((quad_side_px(q) for q in quads.values()), default=math.inf)
        small = smallest < SMALL_MARKER_SIDE_PX
        detector = self.quads.tracking_small if small else self.quads.tracking
        box = tracking_window(seen.shape, quads)
        # every predicted marker at least tracking_side_px across in the searched image
        scale = min(1.0, self.tracking_side_px / smallest) if 0 < smallest < math.inf else 1.0
        if box is None:
            return self.quads.find(seen, "raw", detector=detector, scale=scale)
        x0, y0, x1, y1 = box
        return self.quads.find(seen[y0:y1, x0:x1], "raw", (x0, y0), detector, scale)

    def _fit_direct(
        self, grey: NDArray[np.uint8], hint: list[MarkerDetection]
    ) -> dict[int, MarkerDetection]:
        """Hinted markers of ``direct_side_px`` or more fitted (``fit_corners``) from their
        hinted corners, without a quad, kept where the marker's cells read through the fitted
        corners as printed (``detection.verification``): a fit that slid to another edge or
        onto something else reads wrong and is dropped."""
        least = self.direct_side_px
        if least is None:
            return {}
        starts = [
            MarkerDetection(d.marker_index, d.corners_px, "tracked")
            for d in hint
            if d.side_px >= least and self.camera.in_image(d.corners_px, DIRECT_MARGIN_PX)
        ]
        out: dict[int, MarkerDetection] = {}
        fits = self._fit_all(grey, starts, predicted=True)
        for index, fitted in fits.items():
            if fitted is None:
                continue
            reading = read_cells(grey, fitted.corners_px, self.camera, self.cell_patterns[index])
            if reading is not None and reading.matches():
                out[index] = fitted
        return out

    def _rectified_tracking(
        self, grey: NDArray[np.uint8], quads: list[Array], search: bool = False
    ) -> list[MarkerDetection]:
        """Markers found in windows of the rectified view around ``quads`` (original pixels),
        with corners mapped back to the original: by the tracking detector (one threshold
        window), or with ``search`` by the full search's (OpenCV's three)."""
        maps = self._rectification.maps
        out = []
        for quad in quads:
            rectified = self._rectification.to_rectified(quad)
            box = rectified_box(rectified, maps[0].shape)
            if box is None:
                continue
            small = quad_side_px(rectified) < SMALL_MARKER_SIDE_PX
            detector = self.quads.tracking_small if small else self.quads.tracking
            for index, det in self._rectified_pass(
                grey, maps, box, None if search else detector
            ).items():
                mapped = self._unrectify(det.corners_px)
                if mapped is not None:
                    out.append(MarkerDetection(index, mapped, "rectified"))
        return out

    def _find(
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
        maps = self._rectification.maps if self.rectify else None
        if view == "rectified" and maps is not None:
            # edge-fitted corners need only a start: the view at half its size, a quarter of
            # the pixels to remap and search (it is larger than the image)
            coarse = self.corners == "edges"
            step = COARSE_STEP if coarse else 1
            seen_maps = self._rectification.coarse_maps if coarse else maps
            rect = np.asarray(cv2.remap(grey, *seen_maps, interpolation=cv2.INTER_LINEAR), np.uint8)
            view_found: dict[int, MarkerDetection] = {}
            for index, det in self.quads.find(rect, "rectified", detector=detector).items():
                mapped = self._unrectify(det.corners_px * step)
                if mapped is not None:
                    view_found[index] = MarkerDetection(index, mapped, "rectified")
            return tuple(view_found[i] for i in sorted(view_found))
        found: dict[int, MarkerDetection] = {}
        box = self._hint_window(grey, hint)
        if box is not None:
            x0, y0, x1, y1 = box
            found = self.quads.find(grey[y0:y1, x0:x1], "raw", (x0, y0), detector)
        if not found and (whole or box is None):
            found = self.quads.find(grey, "raw", detector=detector)
        if maps is not None and found:
            found = self._rectified_refind(grey, found, CURVED_SIDE_PX if refind_curved else None)
        return tuple(found[i] for i in sorted(found))

    def _rectified_refind(
        self, grey: NDArray[np.uint8], found: dict[int, MarkerDetection], curved_px: float | None
    ) -> dict[int, MarkerDetection]:
        """``found`` (in ``grey``, a strongly distorted lens's image), with the markers the
        target's plane through them puts in view but that are missing searched in windows of
        the pinhole view (OpenCV's three threshold windows), and with ``curved_px`` those found
        that large searched there again (corners mapped back)."""
        maps = self._rectification.maps
        limit_px = math.inf if curved_px is None else curved_px
        rectified: dict[int, MarkerDetection] = {}
        margin_px = self.quads.border_margin_px
        for box in rectified_windows(self._rectification, self.target, found, limit_px, margin_px):
            for index, det in self._rectified_pass(grey, maps, box).items():
                rectified.setdefault(index, det)
        out = dict(found)
        for det in rectified.values():
            raw = found.get(det.marker_index)
            if raw is not None and raw.side_px < limit_px:
                continue
            mapped = self._unrectify(det.corners_px)
            if mapped is not None:
                out[det.marker_index] = MarkerDetection(det.marker_index, mapped, "rectified")
        return out

    def _hint_window(
        self, grey: NDArray[np.uint8], hint: tuple[MarkerDetection, ...]
    ) -> Box | None:
        """The window around ``hint`` and where the target's plane through it puts the other
        markers (``tracking_window``); None without a hint or where the window would cover
        most of the image."""
        return tracking_window(grey.shape, predicted_quads(self.target, hint)) if hint else None

    def _rectified_pass(
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
    def _rectification(self) -> Rectification:
        """The camera's pinhole view (``detection.rectification``: built once per camera)."""
        return Rectification.of(self.camera)

    def _unrectify(self, corners_rect_px: Array) -> Array | None:
        uv, ok = self._rectification.to_original(corners_rect_px)
        if not ok:
            return None
        # the rectified view reaches past the image, where it is black: a marker running out
        # of the image closes there into a quad that is not the marker (OpenCV's own
        # minDistanceToBorder keeps such quads out of the plain pass)
        return uv if self.camera.in_image(uv, self.quads.border_margin_px) else None
