"""The bottom of ``io/``: a frame as every source yields it (``Frame``), the source's interface
(``FrameSource``), a frame's time as a message stamp (``stamp_ns``), and how files of frames are
told and ordered (``IMAGE_SUFFIXES``, ``natural_key``). Sources, sinks, bags and
the live view import these; nothing here imports them."""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

IMAGE_SUFFIXES = frozenset(
    {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp"}
)


@dataclass(frozen=True)
class Frame:
    """One input frame.

    index : position in the source, from 0. t_s : capture time, seconds.
    image : (H, W) or (H, W, 3) uint8, or None when it could not be read (``error`` says why).
    name : file name, or ``frame N`` for videos and cameras.
    file : where the frame came from: the image file's path, or ``VIDEO#N`` / ``camera K#N``.
    grabbed_s : ``time.monotonic()`` when the frame was grabbed (a live camera: before it was
        decoded) or read (files); the start of its latency.
    stale : a live camera's frame that was dropped unprocessed because a newer one was ready
        (``image`` is None).
    stamp_ns : the source's own stamp in integer nanoseconds (a bag's or a ROS message's
        header), which outputs carry exactly; None where the source has none (``t_s`` then
        gives it, ``stamp_ns``).
    frame_id : the camera's frame id as the source names it (a ROS header's), or "".
    stamped_s : a live frame's stamp by its source's own clock, on the clock of ``grabbed_s``
        (a V4L2 buffer's, a stream's presentation time mapped to the host:
        ``perchpose.io.capture_clock``); NaN where the source gave none. ``clock`` names it
        ("v4l2", "stream"; "" for none). ``dated_s`` is what the camera latency counts back
        from: this stamp where there is one, else the grab.
    damaged : the image decoded but rests on damaged data: a video frame that decoded with
        errors, or one predicted from such a frame or from a missing one (``error`` says
        which). Its pixels are wrong wherever the damage moved, in ways that look like a
        picture, so it is shown but not measured. (A truncated JPEG is not ``damaged``: the
        part that decoded is exact, and the decoder greys out the rest.)
    """

    index: int
    t_s: float
    image: NDArray[np.uint8] | None
    name: str
    error: str = ""
    file: str = ""
    grabbed_s: float = math.nan
    stale: bool = False
    stamp_ns: int | None = None
    frame_id: str = ""
    damaged: bool = False
    stamped_s: float = math.nan
    clock: str = ""

    @property
    def dated_s(self) -> float:
        """The time the camera latency counts back from: the source's own stamp, or the
        grab (NaN where neither is known)."""
        return self.stamped_s if math.isfinite(self.stamped_s) else self.grabbed_s


class FrameSource:
    """Iterable of ``Frame``; ``count`` is the number of frames when known in advance.
    ``lost`` counts the frames that could not be decoded (each still yields a ``Frame`` with
    ``image`` None and the reason in ``error``); ``stale`` a live camera's frames dropped for
    a newer one (each yields a ``Frame`` with ``stale`` set); ``damaged`` the frames that
    decoded but rest on damaged data (``Frame.damaged``). ``live``: a camera or stream,
    which runs in real time (a recording does not)."""

    live = False

    def __init__(self, description: str, count: int | None, fps: float) -> None:
        self.description = description
        self.count = count
        self.fps = fps
        self.lost = 0
        self.stale = 0
        self.damaged = 0

    def __iter__(self) -> Iterator[Frame]:
        raise NotImplementedError


def stamp_ns(t_s: float) -> int:
    """A frame time as a message stamp: integer nanoseconds, never negative."""
    return max(0, round(t_s * 1e9))


CAMERA_FRAME = "camera"
TARGET_FRAME = "target"


@dataclass(frozen=True)
class Stamp:
    """A frame's time and frame as its outputs (bags, the live view, ROS messages) carry them:
    ``t_s`` seconds (CSV rows), ``t_ns`` the source's integer nanoseconds, never rebuilt from
    ``t_s`` where the source gave its own, and the camera's ``frame_id``."""

    t_s: float
    t_ns: int
    frame_id: str = CAMERA_FRAME

    @staticmethod
    def of(frame: Frame, camera_frame: str | None = None) -> Stamp:
        """``frame``'s stamp, in ``camera_frame`` if given, else the frame id the source gave,
        else ``camera``."""
        t_ns = stamp_ns(frame.t_s) if frame.stamp_ns is None else frame.stamp_ns
        return Stamp(frame.t_s, t_ns, camera_frame or frame.frame_id or CAMERA_FRAME)

    @staticmethod
    def of_message(t_ns: int, frame_id: str, camera_frame: str | None = None) -> Stamp:
        """A ROS message's own stamp (integer nanoseconds) and frame id, as ``of`` takes a
        bag frame's (``t_s`` from ``t_ns`` as the bag reader gives it)."""
        return Stamp(t_ns / 1_000_000_000, t_ns, camera_frame or frame_id or CAMERA_FRAME)

    @property
    def sec_nanosec(self) -> tuple[int, int]:
        """(sec, nanosec) of a ROS or Foxglove time stamp."""
        sec, nanosec = divmod(self.t_ns, 1_000_000_000)
        return sec, nanosec


def natural_key(path: Path) -> tuple[tuple[int, int | str], ...]:
    """Sort key of a file name as a person reads it: runs of digits by value (``img_2`` before
    ``img_10``), the rest case-insensitively."""
    parts = re.split(r"(\d+)", path.name)
    return tuple((0, int(p)) if p.isdigit() else (1, p.lower()) for p in parts if p)
