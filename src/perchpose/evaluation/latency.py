"""A camera's glass-to-grab latency, measured by filming a screen that shows time-coded markers.

The screen shows two ArUco markers (OpenCV's ``DICT_4X4_50``, read at a glance even through a
blurred or small view): the display count's ones digit in base 25 (ids 0-24) and its 25s
digit (ids 25-49), so a count is known for 625 display frames (about 21 s at 30 Hz) before
it repeats. Each display frame's time is taken when it was handed to the screen. A frame that
the camera grabbed at ``grabbed_s`` and in which both markers are read shows count ``c``: it
was captured while ``c`` was on screen, between its display time and the next's, so
``grabbed_s - shown_s(c) - period / 2`` is the latency from the glass to the grab, plus the
display's own lag (the compositor and the panel: not known here, given as ``display_lag_s``
where the user has measured it). A marker is on screen for one display period: single
samples spread by up to half a period either way, which their mean averages out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.io.capture_clock import CLOCK_NAMES
from perchpose.target import aruco_dictionary

DIGITS = 25  # ids per marker: the fine marker is 0-24, the coarse one 25-49
CYCLE = DIGITS * DIGITS  # display counts before a count repeats
MARKER_PX = 360  # each marker's side on the display image
QUIET_PX = 60  # white margin around and between the markers
INLIER_S = 0.1  # samples this far from the median are counted apart as misreads


@cache
def dictionary() -> cv2.aruco.Dictionary:
    return aruco_dictionary("DICT_4X4_50")


def display_image(count: int) -> NDArray[np.uint8]:
    """The screen's picture for display count ``count``: the fine marker left, the coarse one
    right, on white."""
    fine, coarse = count % DIGITS, DIGITS + (count // DIGITS) % DIGITS
    side = MARKER_PX
    image = np.full((side + 2 * QUIET_PX, 2 * side + 3 * QUIET_PX), 255, np.uint8)
    for k, marker_id in enumerate((fine, coarse)):
        x = QUIET_PX + k * (side + QUIET_PX)
        image[QUIET_PX : QUIET_PX + side, x : x + side] = cv2.aruco.generateImageMarker(
            dictionary(), marker_id, side
        )
    return image


def count_of(ids: list[int]) -> int | None:
    """The display count (modulo ``CYCLE``) that ids read in one camera frame say, or None
    where it is not one fine and one coarse marker."""
    fine = {i for i in ids if 0 <= i < DIGITS}
    coarse = {i - DIGITS for i in ids if DIGITS <= i < 2 * DIGITS}
    if len(fine) != 1 or len(coarse) != 1:
        return None
    return coarse.pop() * DIGITS + fine.pop()


class MarkerReader:
    """OpenCV's ArUco detector for the time-coded markers."""

    def __init__(self) -> None:
        self._detector = cv2.aruco.ArucoDetector(dictionary(), cv2.aruco.DetectorParameters())

    def ids(self, image: NDArray[np.uint8]) -> list[int]:
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        _corners, ids, _rejected = self._detector.detectMarkers(gray)
        return [] if ids is None else [int(i) for i in ids.reshape(-1)]


@dataclass(frozen=True)
class LatencySummary:
    """What a measurement found (seconds). samples : frames that gave a latency; misread :
    of them, those further than ``INLIER_S`` from the median (a frame that caught the change
    from one count to the next and read one marker of each); unread : camera frames in which
    no count was read. mean, std, p5, p95 : of the inliers, the display's lag taken off.
    display_period_s, display_lag_s : the display's, as run. clock : what dated the camera's
    frames, which the latency runs to (``Frame.clock``: "" the grab, "v4l2" the driver's
    buffer stamp, "stream" the stream's presentation time)."""

    samples: int
    misread: int
    unread: int
    median_s: float
    mean_s: float
    std_s: float
    p5_s: float
    p95_s: float
    display_period_s: float
    display_lag_s: float
    clock: str = ""

    def describe(self) -> str:
        if self.samples == 0:
            return (
                f"no latency measured: the markers were read in none of {self.unread} frames "
                "(point the camera at the screen, the markers filling a good part of the view)"
            )
        lag = (
            f"the display's own lag of {self.display_lag_s * 1000:.0f} ms taken off"
            if self.display_lag_s > 0
            else "the display's own lag (compositor and panel, often 10-50 ms) included: give "
            "it with --display-lag-ms where it is known"
        )
        to = CLOCK_NAMES.get(self.clock, self.clock)
        return (
            f"latency from the glass to {to}: {self.mean_s * 1000:.1f} ms mean "
            f"(median {self.median_s * 1000:.1f}, std {self.std_s * 1000:.1f}, "
            f"p5-p95 {self.p5_s * 1000:.1f}-{self.p95_s * 1000:.1f}) over "
            f"{self.samples - self.misread} frames ({self.misread} misread, "
            f"{self.unread} unread); each sample is within "
            f"half a display period ({self.display_period_s * 500:.0f} ms) of its own truth; "
            f"{lag}. Track with --camera-latency-ms {self.mean_s * 1000:.0f}"
        )


class LatencyMeter:
    """Display times in, camera frames' counts out: the latency samples."""

    def __init__(self, display_period_s: float, display_lag_s: float = 0.0) -> None:
        self.display_period_s = display_period_s
        self.display_lag_s = display_lag_s
        self._shown: dict[int, float] = {}  # count modulo CYCLE -> when it was last shown
        self.samples_s: list[float] = []
        self.unread = 0
        self.clock = ""  # what dated the frames seen (``Frame.clock``)

    def shown(self, count: int, t_s: float) -> None:
        """Display count ``count`` was handed to the screen at ``t_s``."""
        self._shown[count % CYCLE] = t_s

    def seen(self, count: int | None, grabbed_s: float) -> float | None:
        """A camera frame grabbed at ``grabbed_s`` read ``count`` (None: nothing read). Its
        latency sample, or None where it gives none (unread, or a count not shown in the
        last cycle before the grab)."""
        if count is None or count not in self._shown:
            self.unread += 1
            return None
        latency = grabbed_s - self._shown[count] - 0.5 * self.display_period_s
        latency -= self.display_lag_s
        if not -self.display_period_s <= latency < CYCLE * self.display_period_s:
            self.unread += 1
            return None
        self.samples_s.append(latency)
        return latency

    def summary(self) -> LatencySummary:
        values = np.asarray(self.samples_s, np.float64)
        nan = math.nan
        if values.size == 0:
            return LatencySummary(
                0,
                0,
                self.unread,
                nan,
                nan,
                nan,
                nan,
                nan,
                self.display_period_s,
                self.display_lag_s,
                self.clock,
            )
        median = float(np.median(values))
        inliers = values[np.abs(values - median) <= INLIER_S]
        return LatencySummary(
            samples=int(values.size),
            misread=int(values.size - inliers.size),
            unread=self.unread,
            median_s=median,
            mean_s=float(inliers.mean()),
            std_s=float(inliers.std()),
            p5_s=float(np.percentile(inliers, 5)),
            p95_s=float(np.percentile(inliers, 95)),
            display_period_s=self.display_period_s,
            display_lag_s=self.display_lag_s,
            clock=self.clock,
        )
