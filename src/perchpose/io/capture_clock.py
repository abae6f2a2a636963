"""A live frame's stamp from its source's own clock, where the source has one.

A live frame's capture time is its stamp less the camera latency the user measured (``perchpose
latency`` measures it against the same stamp). Without a clock of the source's own, the stamp is
the host's ``time.monotonic()`` just after the grab, which carries every delay between the
sensor and the grab: the driver's queue, the network, the decoder's buffer. Two sources say
more:

- **A V4L2 camera** (OpenCV's V4L2 backend, a USB or CSI camera on Linux): the kernel stamps
  each buffer when the frame starts to arrive (UVC: its first packet) on ``CLOCK_MONOTONIC``,
  the clock of ``time.monotonic()``; OpenCV gives it as ``CAP_PROP_POS_MSEC`` after a grab.
  ``DeviceClock`` takes it where it is plausible: not after the grab, nor over
  ``PLAUSIBLE_DELAY_S`` before it (a driver on another clock, or no stamp: 0).
- **A video stream** (RTSP/RTP, UDP MPEG-TS, RTMP): the encoder's presentation times run on the
  camera's clock, without the network's and the decoder's jitter. ``StreamClock`` maps them
  onto the host's clock by the smallest delay seen (each frame's grab time less its
  presentation time; the least delayed frame is the one the network and the buffers held up
  least, as NTP takes its least delayed exchange), over the last ``WINDOW_S`` so that the two
  clocks' drift (tens of ppm: a few ms a minute) is followed. A frame held up by over
  ``RESTART_S`` more than that is refused (a stalled network, then a burst); presentation
  times that go back, jump ahead by over ``RESTART_S`` or stay held up for as long (the
  sender restarted) start the mapping afresh, as a reconnection does. An RTSP camera's RTCP
  sender reports (its wall-clock time) are not read: they would date a frame only where the
  camera's clock is synchronised with this host's.

A stamp a clock cannot give is NaN, and the grab dates that frame (``refused`` counts them).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Protocol

# what dated a frame (``Frame.clock``), in words
CLOCK_NAMES = {
    "": "the grab",
    "v4l2": "the driver's buffer stamp",
    "stream": "the stream's presentation time on this host's clock",
}
PLAUSIBLE_DELAY_S = 1.0  # a device stamp this long before its grab, or after it, is refused
WINDOW_S = 30.0  # the stream mapping's memory: its smallest delay over this long
RESTART_S = 1.0  # a stream whose delay jumps by this much has restarted its clock


class SourceClock(Protocol):
    """Turns a source's own stamp of a frame (seconds, its clock) into the host's monotonic
    clock, or NaN where it cannot."""

    name: str  # what dates the frames: "v4l2", "stream"
    refused: int  # frames it could not date

    def stamp(self, source_s: float | None, grabbed_s: float) -> float: ...

    def reset(self) -> None: ...


class DeviceClock:
    """A V4L2 buffer's stamp, already on the host's monotonic clock (see the module's note)."""

    name = "v4l2"

    def __init__(self) -> None:
        self.refused = 0

    def stamp(self, source_s: float | None, grabbed_s: float) -> float:
        if source_s is None or not math.isfinite(source_s) or source_s <= 0.0:
            self.refused += 1
            return math.nan
        if not 0.0 <= grabbed_s - source_s <= PLAUSIBLE_DELAY_S:
            self.refused += 1
            return math.nan
        return source_s

    def reset(self) -> None:
        """Nothing to forget: the kernel's clock does not restart."""


class StreamClock:
    """A stream's presentation times on the host's clock, by the smallest delay over
    ``window_s`` (see the module's note). ``restarts`` counts the mappings started afresh."""

    name = "stream"

    def __init__(self, window_s: float = WINDOW_S, restart_s: float = RESTART_S) -> None:
        self.window_s = window_s
        self.restart_s = restart_s
        self.refused = 0
        self.restarts = 0
        # (grab time, delay) with delays increasing from the left: the left one is the smallest
        # of the window (a monotonic queue; a delay is dropped once a later one is smaller)
        self._delays: deque[tuple[float, float]] = deque()
        self._late_since_s: float | None = None  # frames held up by over restart_s since
        self._last_source_s: float | None = None

    def stamp(self, source_s: float | None, grabbed_s: float) -> float:
        if source_s is None or not math.isfinite(source_s) or not math.isfinite(grabbed_s):
            self.refused += 1
            return math.nan
        delay_s = grabbed_s - source_s
        went_back = self._last_source_s is not None and source_s < self._last_source_s
        self._last_source_s = source_s
        if self._delays and (went_back or delay_s < self._delays[0][1] - self.restart_s):
            self._restart()  # presentation times that went back, or jumped ahead: a new clock
        elif self._delays and delay_s > self._delays[0][1] + self.restart_s:
            # held up (a stalled network, then a burst), or presentation times that stopped:
            # refused until it has lasted ``restart_s``, then a new clock
            self._late_since_s = grabbed_s if self._late_since_s is None else self._late_since_s
            if grabbed_s - self._late_since_s < self.restart_s:
                self.refused += 1
                return math.nan
            self._restart()
        self._late_since_s = None
        while self._delays and self._delays[-1][1] >= delay_s:
            self._delays.pop()
        self._delays.append((grabbed_s, delay_s))
        while self._delays[0][0] < grabbed_s - self.window_s:
            self._delays.popleft()
        return source_s + self._delays[0][1]

    def _restart(self) -> None:
        self._delays.clear()
        self._late_since_s = None
        self.restarts += 1

    def reset(self) -> None:
        """A new connection: its presentation times start on a clock of their own."""
        self._delays.clear()
        self._late_since_s = None
        self._last_source_s = None
