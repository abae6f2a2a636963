"""The detector's search schedule: the ways a whole frame can be searched (the frame itself, its
pinhole view through a strongly distorted lens, under glare each clip level), which one a frame
tries first and next while the target is lost, how often a lost target gets a thorough search,
and when tracking looks at the whole frame for the markers it lacks. State across frames, no
image work: ``MarkerDetector`` asks, and tells it what was found."""

from __future__ import annotations

from perchpose.detection.quads import ImagePass
from perchpose.values import MarkerDetection

Way = tuple[int | None, ImagePass]

# Glare: a frame with at least GLARE_FRACTION of its pixels at GLARE_LEVEL or above has its
# quads searched in copies clipped at these levels (None: the frame as it is), tried in this
# order, the next one whenever the current one finds nothing: a level between the black
# border's grey and the white margin's works, and these cover white margins from about 50 to
# 230 grey levels.
GLARE_CLIP_LEVELS: tuple[int | None, ...] = (None, 108, 72, 162, 48, 224)


class SearchSchedule:
    """Which way, and how thoroughly, a detector searches; ``rectify``: the lens gets the
    pinhole view; ``full_search_every`` as ``DetectorSettings`` says."""

    def __init__(self, rectify: bool, full_search_every: int | None) -> None:
        self.rectify = rectify
        self.full_search_every = full_search_every
        # the way of searching a whole frame tried first (``ladder``): the one that found the
        # target last, or the next one to try
        self.rung: Way = (None, "raw")
        # where in the ladder the search for a lost target has got to
        self.explored = 0
        # thorough whole-frame searches, and frames looked at a second way, since the target
        # was last found
        self.thorough_turn = 0
        self.second_turn = 0
        # frames in a row without the target that had only quick looks (None: none has been
        # searched thoroughly since ``restart``)
        self.quick_only: int | None = None
        self.tracked_frames = 0
        # whether this frame's tracking also searches the whole frame (``interval_due``)
        self.check = False

    def restart(self) -> None:
        """A new run of frames: the next frame without the target is searched thoroughly, and
        the other ways of the ladder are gone through from its start."""
        self.quick_only = None
        self.thorough_turn = self.second_turn = 0

    def first_way(self, glare: bool) -> tuple[list[Way], Way]:
        """This frame's ladder and the way it tries first."""
        ladder = self.ladder(glare)
        if self.rung not in ladder:
            self.rung = ladder[0]
        return ladder, self.rung

    def found(self, rung: Way, corners: str) -> None:
        """The target found ``rung``'s way: the next frame starts that way, but with
        ``cornerSubPix`` corners in the frame itself: their pinhole view is searched at full
        size, two to three times the cost of the frame, and is needed only while no quad
        closes there."""
        self.rung = rung if corners == "edges" else (rung[0], "raw")
        self.quick_only = 0
        self.thorough_turn = self.second_turn = 0

    def quick_only_for_now(self, thorough_every: int | None) -> bool:
        """Whether a frame whose quick looks found nothing goes without the thorough search
        (``thorough_every``: only every that many-th such frame has it); counts it."""
        every, quick = thorough_every, self.quick_only
        if every is not None and quick is not None and quick < every - 1:
            self.quick_only = quick + 1
            return True
        return False

    def next_way(
        self, ladder: list[tuple[int | None, ImagePass]], first: tuple[int | None, ImagePass]
    ) -> tuple[int | None, ImagePass]:
        """The next way of the ladder not yet tried in this run of frames without the target
        (never ``first``)."""
        self.explored = (self.explored + 1) % len(ladder)
        if ladder[self.explored] == first:
            self.explored = (self.explored + 1) % len(ladder)
        return ladder[self.explored]

    def second_way(
        self, ladder: list[tuple[int | None, ImagePass]], first: tuple[int | None, ImagePass]
    ) -> tuple[int | None, ImagePass]:
        """The way a frame without the target is looked at after ``first``: on every other
        such frame the ladder's first way but ``first`` (under glare, the first clip level of
        the frame), else the next other way not yet tried (``_next_way``). A target that one way
        finds on some frames only (small and noisy) is then found within a few frames, not
        once the whole ladder has been gone through (twelve frames through a fisheye under
        glare)."""
        priority = next(way for way in ladder if way != first)
        self.second_turn += 1
        if self.second_turn % 2 == 1 or len(ladder) <= 2:
            return priority
        way = self.next_way(ladder, first)
        return self.next_way(ladder, first) if way == priority else way

    @staticmethod
    def second_label(rung: tuple[int | None, ImagePass]) -> str:
        """What ``skipped`` calls the second way of searching a frame, left out."""
        return "glare search" if rung[0] is not None else "second search"

    def thorough_way(
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
        way = same_view[(start + self.thorough_turn) % len(same_view)]
        self.thorough_turn += 1
        return way

    def ladder(self, glare: bool) -> list[tuple[int | None, ImagePass]]:
        """The ways of searching a whole frame, in the order they are tried: (clip level or
        None, ``raw`` or ``rectified``)."""
        levels = GLARE_CLIP_LEVELS if glare else (None,)
        views: tuple[ImagePass, ...] = ("raw", "rectified") if self.rectify else ("raw",)
        return [(level, view) for view in views for level in levels]

    def interval_due(self, hint: tuple[MarkerDetection, ...]) -> bool:
        """Whether ``full_search_every`` tracked frames have passed since the last
        whole-frame look (``_with_unseen``); it stays due until one is made."""
        every = self.full_search_every
        if not hint or every is None:
            self.tracked_frames = 0
            return False
        self.tracked_frames += 1
        return self.tracked_frames >= every
