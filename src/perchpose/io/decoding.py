"""Video files and network streams decoded by PyAV (FFmpeg's own libraries), with what FFmpeg
knows of each frame: its presentation time, whether it is a key frame, and whether its own data
decoded with errors.

FFmpeg flags only the frame whose data was damaged. The frames predicted from it until the next
key frame decode without complaint, and so does the frame after a packet lost whole (the decoder
predicts it from the wrong reference): ``ReferenceChain`` carries the damage forward itself.
OpenCV's FFmpeg backend reports neither, which is why videos and streams are read here."""

from __future__ import annotations

import os
import statistics
from collections import deque
from collections.abc import Generator
from fractions import Fraction
from typing import Any

import av
import av.error
import numpy as np
from numpy.typing import NDArray

OPTIONS_VARIABLE = "OPENCV_FFMPEG_CAPTURE_OPTIONS"  # a stream's FFmpeg options, as OpenCV's
# a stream's frames are decoded by slices on a live stream (no frame of delay) and by whole
# frames in parallel from a file (faster, a few frames of delay that nothing waits for)
LIVE_THREADS = "SLICE"
FILE_THREADS = "AUTO"
# a gap between presentation times over this many typical frame intervals has frames missing
GAP_INTERVALS = 1.5
INTERVALS_KEPT = 15  # the typical interval: the median of the last this many
NOMINAL_TOLERANCE = 0.15  # a stream within this of its nominal interval runs at its rate


class ReferenceChain:
    """Which decoded frames rest on damaged data, in the order they come out of the decoder.

    ``frame`` takes each frame's index (from its presentation time), whether FFmpeg marks it a
    key frame, whether it decoded with errors, and how many frames are missing just before it;
    it answers why the frame is damaged ('' when whole). A frame with errors, a packet the
    demuxer marked corrupt (``packet_damaged``), or a missing frame (a packet lost whole, or one
    that did not decode) break the chain: every frame after it is damaged until a key frame
    decodes whole. A frame's damage names the frame where the chain broke.

    Where the demuxer marked a packet corrupt (MPEG-TS: a continuity counter skipped, data
    lost), the lost data may have held the start of the next frame, whose rest the demuxer then
    hands over as part of the corrupt one or as a frame of its own: the first frame after a
    corrupt packet is damaged too, even a key frame that decodes without complaint.

    A stream with intra refresh (low-latency encoders) has no key frame after its first: it
    marks ``access_point`` packets instead (a recovery point, where a refresh cycle starts), and
    the picture is whole again only once a whole cycle has run after the damage, that is at the
    second access point after it (one cycle may have begun before the damage)."""

    def __init__(self) -> None:
        self._broken_at: int | None = None  # the first damaged or missing frame
        self._pending: int | None = None  # a damaged packet's frame, not yet decoded
        self._after_corrupt: int | None = None  # the frame the next one may be the rest of
        self._access_points = 0  # access points since the chain last broke

    def packet_damaged(self, index: int) -> None:
        """The packet of frame ``index`` came marked corrupt from the demuxer: that frame is
        damaged when it comes (and missing when it does not), and so what follows it."""
        self._pending = index if self._pending is None else min(self._pending, index)

    def frame(
        self,
        index: int,
        *,
        key: bool,
        corrupt: bool,
        missing_before: int = 0,
        access_point: bool = False,
    ) -> str:
        """Why frame ``index`` rests on damaged data, or ''."""
        cut_at, self._after_corrupt = self._after_corrupt, None
        if self._pending is not None and index >= self._pending:
            if index == self._pending:
                corrupt, self._after_corrupt = True, index
            else:  # the corrupt packet's frame never came out of the decoder
                cut_at = self._pending
                missing_before = max(missing_before, index - self._pending)
            self._pending = None
        if corrupt:
            self._break(index)
            return f"frame {index} decoded with errors (its own data is damaged)"
        if cut_at is not None:
            self._break(cut_at)
            return f"frame {index} follows data lost at frame {cut_at} and may hold its rest"
        if key:
            self._broken_at = None
            return ""
        if missing_before > 0:
            self._break(index - missing_before)
        if self._broken_at is None:
            return ""
        if access_point:
            self._access_points += 1
            if self._access_points >= 2:
                self._broken_at = None
                return ""
        return (
            f"frame {index} is predicted from damaged or missing frames (since frame "
            f"{self._broken_at}, until the next key frame)"
        )

    def _break(self, index: int) -> None:
        """The chain breaks at ``index`` (the first break stays named); a refresh cycle must
        start afresh after it."""
        self._broken_at = index if self._broken_at is None else self._broken_at
        self._access_points = 0

    @property
    def broken(self) -> bool:
        """Frames decoded now rest on damaged data."""
        return self._broken_at is not None


def ffmpeg_options(text: str) -> dict[str, str]:
    """FFmpeg options written as OpenCV reads ``OPENCV_FFMPEG_CAPTURE_OPTIONS``: ``key;value``
    pairs separated by ``|`` (``rtsp_transport;tcp|stimeout;5000000``). OpenCV's own
    ``video_codec`` key is not an FFmpeg option and is left out, as are pairs without a key."""
    options: dict[str, str] = {}
    for pair in text.split("|"):
        key, _, value = pair.partition(";")
        if key.strip() and key.strip() != "video_codec":
            options[key.strip()] = value.strip()
    return options


class AvCapture:
    """A video file or network stream decoded by PyAV, read one frame at a time (``read``, or
    ``grab`` then ``retrieve`` as ``LatestFrame`` reads a live source).

    After each frame: ``index`` is its place in the stream (from its presentation time and the
    stream's frame rate, counted from the first frame), ``damage`` why it rests on damaged data
    ('' when whole: ``ReferenceChain``). Packets that do not decode are skipped: the frames they
    held are missing from the indices. Frames count as missing before a frame whose time from
    the frame before is over 1.5 intervals: the nominal interval while the stream keeps to it
    (the median of the last 15 within 15 % of it), else that median. A camera whose frame
    times jitter by up to a fifth of a frame (7 ms at 30 fps), or whose rate drifts, is not
    taken for a lossy stream. ``count``: the frames the container promises (None where it does
    not say); ``fps``: the stream's nominal frame rate (None where unknown)."""

    def __init__(self, container: Any, live: bool) -> None:
        self._container = container
        self._stream = container.streams.video[0]
        self._stream.codec_context.thread_type = LIVE_THREADS if live else FILE_THREADS
        # FFmpeg's guess of the nominal rate (the container's frame rate unless the time stamps
        # say otherwise): the average rate falls short by the frames a damaged file lacks
        rate = self._stream.guessed_rate or self._stream.average_rate
        self.fps: float | None = float(rate) if rate else None
        self.count: int | None = int(self._stream.frames) or None
        self._time_base: Fraction | None = self._stream.time_base
        self._start_pts: int | None = self._stream.start_time
        self._chain = ReferenceChain()
        self._intervals_s: deque[float] = deque(maxlen=INTERVALS_KEPT)
        self._last_s: float | None = None
        self._frames = self._decoded()
        self._frame: Any = None
        self.index = -1
        self.damage = ""

    @staticmethod
    def open(source: str, live: bool, timeout_s: float | None = None) -> AvCapture | None:
        """``source`` (a path or URL) opened, or None when FFmpeg cannot open it or it holds
        no video stream. ``timeout_s`` bounds the opening and each read of a network stream,
        which also gets the FFmpeg options of ``OPENCV_FFMPEG_CAPTURE_OPTIONS``
        (``ffmpeg_options``)."""
        timeout = None if timeout_s is None else (timeout_s, timeout_s)
        options = ffmpeg_options(os.environ.get(OPTIONS_VARIABLE, "")) if live else {}
        try:
            container = av.open(source, mode="r", timeout=timeout, options=options)
        except (av.error.FFmpegError, OSError, ValueError):
            return None
        if not container.streams.video:
            container.close()
            return None
        return AvCapture(container, live)

    def _index_of(self, pts: int | None, previous: int) -> int:
        """A frame's index from its presentation time (the next index without one)."""
        if pts is None or self._time_base is None or self.fps is None:
            return previous + 1
        if self._start_pts is None:
            self._start_pts = pts
        return round((pts - self._start_pts) * self._time_base * self.fps)

    def _missing_before(self, pts: int | None) -> int:
        """How many frames are missing between the frame before and this one, from the time
        between them (``_reference_interval_s``)."""
        if pts is None or self._time_base is None:
            return 0
        t_s = float(pts * self._time_base)
        last_s, self._last_s = self._last_s, t_s
        if last_s is None or not t_s > last_s:
            return 0
        interval_s = t_s - last_s
        reference_s = self._reference_interval_s()
        self._intervals_s.append(interval_s)
        if reference_s is None or interval_s <= GAP_INTERVALS * reference_s:
            return 0
        return max(1, round(interval_s / reference_s) - 1)

    def _reference_interval_s(self) -> float | None:
        """A frame's interval as this stream runs: the nominal one while the typical interval
        (the median of the last ``INTERVALS_KEPT``) is within ``NOMINAL_TOLERANCE`` of it or
        fewer than that many are known, else the typical one (a rate that drifted)."""
        nominal_s = None if self.fps is None else 1.0 / self.fps
        if len(self._intervals_s) < INTERVALS_KEPT:
            return nominal_s
        typical_s = statistics.median(self._intervals_s)
        if nominal_s is not None and abs(typical_s / nominal_s - 1.0) < NOMINAL_TOLERANCE:
            return nominal_s
        return typical_s

    def _decoded(self) -> Generator[tuple[int, Any, str], None, None]:
        """(index, frame, damage) of each frame, in presentation order; ends at the stream's
        end, or where the demuxer cannot go on (a truncated file, a dropped connection)."""
        previous = -1
        access_points: set[int] = set()  # the times of packets a decoder may start from
        try:
            for packet in self._container.demux(self._stream):
                if packet.is_keyframe and packet.pts is not None:
                    access_points.add(packet.pts)
                if packet.is_corrupt and packet.pts is not None:
                    self._chain.packet_damaged(self._index_of(packet.pts, previous))
                try:
                    frames = packet.decode()
                except av.error.FFmpegError:
                    continue  # its frame is missing from the indices, which says so
                for frame in frames:
                    index = self._index_of(frame.pts, previous)
                    if index <= previous:  # a time stamp that does not move on
                        index = previous + 1
                    damage = self._chain.frame(
                        index,
                        key=bool(frame.key_frame),
                        corrupt=bool(frame.is_corrupt),
                        missing_before=self._missing_before(frame.pts),
                        access_point=frame.pts in access_points,
                    )
                    access_points.discard(frame.pts)
                    previous = index
                    yield index, frame, damage
        except (av.error.FFmpegError, OSError):
            return

    def grab(self) -> bool:
        """Decode the next frame; False at the end of the stream."""
        item = next(self._frames, None)
        if item is None:
            self._frame = None
            return False
        self.index, self._frame, self.damage = item
        return True

    @property
    def pts_s(self) -> float | None:
        """The presentation time of the frame just grabbed, in seconds on the stream's own
        clock (None where it has none)."""
        if self._frame is None or self._frame.pts is None or self._time_base is None:
            return None
        return float(self._frame.pts * self._time_base)

    def retrieve(self) -> tuple[bool, NDArray[np.uint8] | None]:
        """The frame just grabbed as a BGR image."""
        if self._frame is None:
            return False, None
        image: NDArray[np.uint8] = self._frame.to_ndarray(format="bgr24")
        return True, image

    def read(self) -> tuple[bool, NDArray[np.uint8] | None]:
        """``grab`` and ``retrieve`` in one."""
        if not self.grab():
            return False, None
        return self.retrieve()

    def release(self) -> None:
        """Close the container (what is being decoded ends)."""
        self._frames.close()
        self._container.close()
