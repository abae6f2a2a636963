"""Detection of a target's markers: the quads OpenCV finds (``detection.quads``), in windows
around where they are expected while tracking (``detection.windows``), with corners fitted to
the image (``corners.refinement``).

Corners come back in the pixels of the original (distorted) image. For a lens whose distortion
bends a large marker's edges enough that OpenCV's quad finder misses it, a second pass runs on a
pinhole rectification of the image (``detection.rectification``) and maps the corners it finds
back through the lens model.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.corners.edge_fit import EdgeFit
from perchpose.detection.budget import Budget, learnt
from perchpose.detection.finding import CURVED_SIDE_PX, SMALL_MARKER_SIDE_PX, QuadSearch
from perchpose.detection.fitting import Fitting
from perchpose.detection.quads import (
    ImagePass,
    QuadFinder,
    QuadPass,
    refine_corners,
    target_dictionaries,
)
from perchpose.detection.schedule import GLARE_CLIP_LEVELS, SearchSchedule, Way
from perchpose.detection.windows import predicted_quads
from perchpose.target import TargetSpec
from perchpose.values import MarkerDetection

__all__ = [
    "CORNER_METHODS",
    "GLARE_CLIP_LEVELS",
    "PATTERN_BESIDE_RATIO",
    "CornerMethod",
    "Detected",
    "DetectorSettings",
    "MarkerDetector",
    "refine_corners",
    "target_dictionaries",
]

Array = NDArray[np.float64]

CornerMethod = Literal["edges", "subpix"]
CORNER_METHODS: tuple[CornerMethod, ...] = ("edges", "subpix")
# Glare: a frame with at least GLARE_FRACTION of its pixels at GLARE_LEVEL or above has its
# quads searched in copies clipped at each of ``schedule.GLARE_CLIP_LEVELS``.
GLARE_LEVEL = 250
GLARE_FRACTION = 0.05
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
# A marker this many times smaller than another whose corners were fitted in the same frame
# may go without the pattern fit (``MarkerDetector(pattern_beside_ratio=...)``).
PATTERN_BESIDE_RATIO = 4.0


def has_glare(grey: NDArray[np.uint8]) -> bool:
    """Whether ``grey`` has a large saturated area (``GLARE_FRACTION`` of its pixels)."""
    # OpenCV's threshold and count: the same count as numpy's comparison, a third the time
    _, saturated = cv2.threshold(grey, GLARE_LEVEL - 1, 255, cv2.THRESH_BINARY)
    return int(cv2.countNonZero(saturated)) >= GLARE_FRACTION * grey.size


@dataclass(frozen=True)
class DetectorSettings:
    """A detector's knobs. ``corners``: ``edges`` (fitted through the lens model, the default)
    or ``subpix`` (OpenCV's ``cornerSubPix``). ``pattern_beside_ratio``: a marker that many
    times smaller than another whose corners were fitted in the same frame keeps its
    edge-fitted corners without the pattern fit (None: every small marker gets it).
    ``thorough_every``: while the target is not tracked and the quick looks at a frame find
    nothing, the whole frame is searched thoroughly only on every that many-th such frame
    (``THOROUGH_EVERY``; None: on every one, as unrelated images need). While tracking: the
    window is searched shrunk so that the smallest predicted marker spans
    ``tracking_side_px``; a hinted marker of ``direct_side_px`` or more is fitted straight
    from its prediction (None: never); every ``full_search_every`` frames the whole frame is
    searched for the markers tracking lacks (None: never)."""

    corners: CornerMethod = "edges"
    pattern_beside_ratio: float | None = None
    thorough_every: int | None = None
    tracking_side_px: float = TRACKING_SIDE_PX
    direct_side_px: float | None = DIRECT_SIDE_PX
    full_search_every: int | None = FULL_SEARCH_EVERY

    def __post_init__(self) -> None:
        if self.corners not in CORNER_METHODS:
            raise ValueError(
                f"corners must be one of {', '.join(CORNER_METHODS)}, got {self.corners!r}"
            )
        if self.thorough_every is not None and self.thorough_every < 1:
            raise ValueError(f"thorough_every must be at least 1, got {self.thorough_every}")
        if self.full_search_every is not None and self.full_search_every < 1:
            raise ValueError(f"full_search_every must be at least 1, got {self.full_search_every}")


@dataclass(frozen=True)
class Detected:
    """What one ``MarkerDetector.detect`` found: the ``markers`` (by marker index), what it
    left out to keep its time budget (``skipped``: ``pattern fit m1``, ``search``,
    ``interval search``, ``glare search``, ``second search``), and ``corners_s``, the seconds
    its corner fits took."""

    markers: tuple[MarkerDetection, ...]
    skipped: tuple[str, ...] = ()
    corners_s: float = 0.0


class MarkerDetector:
    """Finds the markers of ``target`` in grey images of ``camera``: the frame's search
    (``finding.QuadSearch``), the corner fits (``fitting.Fitting``), the search schedule
    (``schedule.SearchSchedule``) and the time budget (``budget.Budget``) put together.

    All dictionaries of the target are searched in one ``detectMarkersMultiDict`` pass; ids that
    are not the target's (dictionary, id) pairs are ignored. The knobs are
    ``DetectorSettings``' (given whole as ``settings``, or as keywords)."""

    def __init__(
        self,
        camera: CameraModel,
        target: TargetSpec,
        corners: CornerMethod = "edges",
        pattern_beside_ratio: float | None = None,
        thorough_every: int | None = None,
        *,
        full_search_every: int | None = FULL_SEARCH_EVERY,
        settings: DetectorSettings | None = None,
    ) -> None:
        self.settings = settings or DetectorSettings(
            corners,
            pattern_beside_ratio,
            thorough_every,
            full_search_every=full_search_every,
        )
        self.camera = camera
        self.target = target
        self.budget = Budget()
        self.search = QuadSearch(camera, target, coarse=self.settings.corners == "edges")
        self.schedule = SearchSchedule(self.search.rectify, self.settings.full_search_every)
        self.fitting = Fitting(
            camera, target, self.search, self.budget, self.settings.pattern_beside_ratio
        )

    @property
    def quads(self) -> QuadFinder:
        """OpenCV's quads over the target's dictionaries (``detection.quads``)."""
        return self.search.quads

    @property
    def rectify(self) -> bool:
        """Whether the lens gets the pinhole view."""
        return self.search.rectify

    def search_ladder(self, glare: bool) -> list[Way]:
        """The ways of searching a whole frame, in the order they are tried
        (``SearchSchedule.ladder``)."""
        return self.schedule.ladder(glare)

    def fit_corners(self, grey: NDArray[np.uint8], det: MarkerDetection) -> MarkerDetection | None:
        """``det`` with corners fitted to the image, or None (``Fitting.fit_corners``)."""
        return self.fitting.fit_corners(grey, det)

    def fit_edges(self, grey: NDArray[np.uint8], det: MarkerDetection) -> EdgeFit | None:
        """The edge fit alone of ``det``, or None (``CornerFitter.fit_edges``)."""
        return self.fitting.fit_edges(grey, det)

    def restart(self) -> None:
        """A new run of frames: the next frame without the target is searched thoroughly, and
        the other ways of the ladder are gone through from its start."""
        self.schedule.restart()

    def detect(
        self,
        grey: NDArray[np.uint8],
        hint: tuple[MarkerDetection, ...] = (),
        deadline_s: float | None = None,
    ) -> Detected:
        """Detect the target's markers in a grey (H, W) uint8 image of the camera's size:
        what was found, what was left out for the budget, and the corner fits' time.

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
        ``_with_unseen``). ``Detected.skipped`` names what this call left out.
        """
        self.budget.start(deadline_s)
        self.schedule.check = self.schedule.interval_due(hint)
        ladder, first = self.schedule.first_way(has_glare(grey))
        markers = self._markers(grey, hint, ladder, first)
        return Detected(markers, tuple(self.budget.skipped), self.budget.corners_s)

    def _markers(
        self,
        grey: NDArray[np.uint8],
        hint: tuple[MarkerDetection, ...],
        ladder: list[Way],
        first: Way,
    ) -> tuple[MarkerDetection, ...]:
        """This frame's markers: the ``cornerSubPix`` pipeline's search, tracking from
        ``hint``, or a look at the whole frame."""
        if self.settings.corners == "subpix":
            return self._search_afresh(grey, hint, ladder, first)
        if hint:
            seen = self.search.seen(grey, first[0])
            tracked, window_quads = self._track_edges(grey, seen, hint)
            if tracked is not None:
                if self.schedule.check:
                    tracked = self._with_unseen(grey, seen, tracked)
                return self._found_by(tracked, first)
            return self._after_loss(grey, seen, hint, ladder, first, window_quads)
        return self._look(grey, ladder, first)

    def _after_loss(
        self,
        grey: NDArray[np.uint8],
        seen: NDArray[np.uint8],
        hint: tuple[MarkerDetection, ...],
        ladder: list[Way],
        first: Way,
        window_quads: bool,
    ) -> tuple[MarkerDetection, ...]:
        """The search after tracking lost a marker it needs. Where its window pass saw quads
        (``window_quads``) it could not use (a fit refused, a curved quad), the window where
        the target's plane puts the markers is searched thoroughly first; where it saw none
        (the target hidden or gone), or that finds none, the whole frame is looked at
        (``_look``). None of it where the budget has no room for it: the filter coasts."""
        if self.budget.late(self.budget.search_s):
            self.budget.skip("search")
            return ()
        if not window_quads:
            return self._look(grey, ladder, first)
        whole = self.search.hint_window(seen, hint) is None or first[1] == "rectified"
        found = self._thorough(seen, hint, first[1], whole=False)
        if found:
            return self._found_by(self.fitting.fit_found(grey, seen, found), first)
        return self._look(grey, ladder, first, looked=whole)

    def _search_afresh(
        self,
        grey: NDArray[np.uint8],
        hint: tuple[MarkerDetection, ...],
        ladder: list[Way],
        first: Way,
    ) -> tuple[MarkerDetection, ...]:
        """The ``cornerSubPix`` pipeline's search: thorough, ``first`` way and, where that
        finds nothing, one way more (``_find``: around ``hint`` first)."""
        clip_level, view = first
        # at the interval, the whole frame searched afresh
        afresh = self.schedule.check and self._interval_search(self.budget.search_s)
        found = self.search.find(self.search.seen(grey, clip_level), () if afresh else hint, view)
        if found or len(ladder) == 1:
            return self._found_by(found, first)
        rung = self.schedule.next_way(ladder, first)
        if self.budget.late(self.budget.search_s):
            # no room for it: it is the next frame's first
            self.budget.skip(self.schedule.second_label(rung))
            self.schedule.rung = rung
            return found
        return self._found_by(self.search.find(self.search.seen(grey, rung[0]), (), rung[1]), rung)

    def _look(
        self,
        grey: NDArray[np.uint8],
        ladder: list[Way],
        first: Way,
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
        ways = [first] if len(ladder) == 1 else [first, self.schedule.second_way(ladder, first)]
        for k, way in enumerate(ways):
            if k == 0 and looked:
                continue
            if k > 0 and self.budget.late(self.budget.quick_s):
                # no room for it: it is the next frame's first
                self.budget.skip(self.schedule.second_label(way))
                self.schedule.rung = way
                return ()
            found = self._quick_look(grey, way)
            if found:
                return self._found_by(found, way)
        if self.schedule.quick_only_for_now(self.settings.thorough_every):
            return ()
        if self.budget.late(self.budget.search_s):
            self.budget.skip("search")
            return ()
        # the quick look had OpenCV's widest threshold window: the other two make up the rest
        way = self.schedule.thorough_way(ladder, first)
        seen = self.search.seen(grey, way[0])
        found = self._thorough(seen, (), way[1], detector=self.search.quads.rest)
        return self._found_by(self.fitting.fit_found(grey, seen, found), way)

    def _quick_look(self, grey: NDArray[np.uint8], way: Way) -> tuple[MarkerDetection, ...]:
        """The markers a quick look at the whole frame finds ``way``, with those it lacks that
        the target's plane through them puts in view (``_with_predicted``), fitted; () where
        it finds none. Through the pinhole view, what the quick look finds (corners mapped
        back to the frame)."""
        clip_level, view = way
        seen = self.search.seen(grey, clip_level)
        t0 = time.perf_counter()
        if view == "rectified":
            found = self.search.find(seen, (), "rectified", detector=self.search.quads.quick)
        else:
            quick = self.search.quads.find(seen, "raw", detector=self.search.quads.quick)
            found = tuple(quick[i] for i in sorted(quick))
        self.budget.quick_s = learnt(self.budget.quick_s, time.perf_counter() - t0)
        if not found:
            return ()
        if view == "raw":
            found = self._with_predicted(seen, found)
        return self.fitting.fit_found(grey, seen, found)

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
            if i not in have and self.search.may_be_found(q, i, hinted=False)
        }
        if missing:
            for index, det in self.search.window_pass(
                seen, missing, self.settings.tracking_side_px
            ).items():
                if index in missing:
                    have.setdefault(index, det)
        if self.search.rectify and len(have) < len(self.target.markers):
            have = self.search.rectified_refind(seen, have, None)
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
        found = self.search.find(
            seen, hint, view, refind_curved=False, whole=whole, detector=detector
        )
        self.budget.search_s = learnt(self.budget.search_s, time.perf_counter() - t0)
        self.schedule.quick_only = 0
        return found

    def _found_by(
        self, found: tuple[MarkerDetection, ...], rung: Way
    ) -> tuple[MarkerDetection, ...]:
        """``found``; where it holds a marker, the next frame starts the way ``rung`` says,
        but with ``cornerSubPix`` corners in the frame itself: their pinhole view is searched
        at full size, two to three times the cost of the frame, and is needed only while no
        quad closes there."""
        if found:
            self.schedule.found(rung, self.settings.corners)
        return found

    def _interval_search(self, cost_s: float) -> bool:
        """Whether the interval's whole-frame look, of ``cost_s`` predicted, runs now: not
        where the budget has no room for it (it is then put off to the next frame)."""
        if self.budget.late(cost_s):
            self.budget.skip("interval search")
            return False
        self.schedule.tracked_frames = 0
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
            self.schedule.tracked_frames = 0
            return tracked
        if not self._interval_search(self.budget.search_s * CHECK_SCALE**2):
            return tracked
        found = self.search.quads.find(seen, "raw", scale=CHECK_SCALE)
        new = [d for i, d in found.items() if i not in have]
        fitted_px = max((d.side_px for d in tracked), default=0.0)
        for index, fitted in self.fitting.fit_all(grey, new, fitted_px=fitted_px).items():
            if fitted is not None:  # a shrunk image's quad is no corners to keep unfitted
                have[index] = fitted
        return tuple(have[i] for i in sorted(have))

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
        self.fitting.fitter.forget_blur()
        result = self.fitting.fit_direct(grey, list(hint), self.settings.direct_side_px)
        blur_px = self.fitting.fitter.blur_px if result else None
        hinted = {d.marker_index for d in hint}
        left = {
            i: q
            for i, q in quads.items()
            if i not in result and self.search.may_be_found(q, i, i in hinted, blur_px)
        }
        found = self.search.window_pass(seen, left, self.settings.tracking_side_px) if left else {}
        required: list[int] = []
        fitted_px = max((d.side_px for d in result.values()), default=0.0)
        searched = {i: d for i, d in found.items() if i not in result}
        for index, fitted in self.fitting.fit_all(
            grey, searched.values(), fitted_px=fitted_px
        ).items():
            det = searched[index]
            if fitted is None and self.search.rectify and det.side_px >= CURVED_SIDE_PX:
                required.append(index)  # a curved quad too far off for the fit
            else:
                # where the fit fails, the quad's cornerSubPix corners (on blurred frames they
                # can be pixels off; the prediction's own fit failed or read wrong before)
                result[index] = fitted or self.fitting.unfitted(det)
        # a marker predicted across the image's border is leaving the view: no quad closes there
        missing = [
            d for d in hint if d.marker_index not in result and self.search.in_view(d.corners_px)
        ]
        required += [d.marker_index for d in missing if d.side_px >= SMALL_MARKER_SIDE_PX]
        again = [d.marker_index for d in missing]
        again += [i for i in required if i not in result and i not in again]
        if again and self.search.rectify:
            retry = [quads[i] for i in again if i in quads]
            for det in self.search.rectified_tracking(seen, retry):
                if det.marker_index in again and det.marker_index not in result:
                    result[det.marker_index] = self.fitting.fit_corners(
                        grey, det
                    ) or self.fitting.unfitted(det)
        if any(index not in result for index in required):
            return None, bool(found)
        return tuple(result[i] for i in sorted(result)), bool(found)
