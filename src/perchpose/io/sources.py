"""Frame sources: a folder of images, a glob, a video file, a single image, a camera index, or a
network stream (``rtsp://``, ``udp://``, ``http://`` and FFmpeg's other schemes), reopened when
it drops. Video files and streams are decoded by PyAV (``perchpose.io.decoding``), which says
which frames rest on damaged data; cameras are read through OpenCV."""

from __future__ import annotations

import glob as globlib
import math
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.errors import SourceError
from perchpose.io.capture_clock import DeviceClock, SourceClock, StreamClock
from perchpose.io.decoding import AvCapture
from perchpose.io.frames import IMAGE_SUFFIXES, Frame, FrameSource, natural_key
from perchpose.io.native import native_stderr_silenced, opencv_reason

VIDEO_SUFFIXES = frozenset(
    {".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg", ".ts", ".m2ts", ".flv"}
)
STREAM_SCHEMES = ("rtsp://", "rtsps://", "rtmp://", "udp://", "tcp://", "http://", "https://")
STREAM_TIMEOUT_MS = 5000  # opening, and each read, of a network stream
RECONNECT_FOR_S = 10.0  # a dropped stream is reopened for this long before the source ends
RECONNECT_PERIOD_S = 0.5


class ImageFilesSource(FrameSource):
    """Image files in the given order; t_s = index / fps."""

    def __init__(self, paths: list[Path], fps: float, description: str) -> None:
        super().__init__(description, len(paths), fps)
        self.paths = paths

    def __iter__(self) -> Iterator[Frame]:
        for i, path in enumerate(self.paths):
            t_s = i / self.fps
            grabbed = time.monotonic()
            why = f"{path}: cannot read image"
            try:
                image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            except cv2.error as exc:  # OpenCV refuses, e.g., a header claiming 2^30 pixels
                image, why = None, f"{why} ({opencv_reason(exc)})"
            if image is None or image.size == 0:
                self.lost += 1
                yield Frame(i, t_s, None, path.name, why, str(path))
                continue
            yield Frame(i, t_s, _to_uint8(image), path.name, _damage(path), str(path), grabbed)


Capture = cv2.VideoCapture | AvCapture


class VideoSource(FrameSource):
    """A video file, a network stream or a camera.

    Files: t_s = index / fps; cameras and streams: seconds since the first frame. A frame that
    decoded but rests on damaged data (``AvCapture.damage``) comes with its image, ``damaged``
    set and the reason in ``error``. ``clock``: a live source's own clock
    (``perchpose.io.capture_clock``), which dates its frames where it can (``Frame.stamped_s``);
    None: the grab dates them.
    """

    def __init__(
        self,
        capture: Capture,
        fps: float,
        description: str,
        live: bool,
        reopen: Callable[[], Capture | None] | None = None,
        reconnect_for_s: float = RECONNECT_FOR_S,
        clock: SourceClock | None = None,
    ) -> None:
        super().__init__(description, None if live else _frame_count(capture), fps)
        self.capture = capture
        self.live = live
        self.clock = clock
        self.reopen = reopen
        self.reconnect_for_s = reconnect_for_s
        self.reconnects = 0
        self.gave_up = False  # a dropped stream that never came back

    def __iter__(self) -> Iterator[Frame]:
        if self.live:
            yield from self._live()
            return
        i = 0
        try:
            while True:
                with native_stderr_silenced():
                    ok, image = self.capture.read()
                grabbed = time.monotonic()
                if not ok or image is None:
                    if self.count is None or i >= self.count:
                        break
                    # a damaged or truncated file: one row per frame the header promises; the
                    # demuxer moves on by itself to whatever can still be decoded
                    self.lost += 1
                    yield self._lost_frame(i)
                    i += 1
                    continue
                # frames the decoder skipped over: their timestamps say where it resumed
                while i < self._index_of_last_read(i):
                    self.lost += 1
                    yield self._lost_frame(i)
                    i += 1
                damage = self._damage()
                self.damaged += bool(damage)
                yield Frame(
                    i,
                    i / self.fps,
                    _to_uint8(image),
                    f"frame {i}",
                    damage,
                    file=f"{self.description}#{i}",
                    grabbed_s=grabbed,
                    damaged=bool(damage),
                )
                i += 1
        finally:
            self.capture.release()

    def _live(self) -> Iterator[Frame]:
        """A camera's frames, grabbed on a thread of their own (``LatestFrame``): each is the
        newest when the caller asks; those a newer one overtook come as stale frames, without
        an image. t_s: seconds from the first frame's grab to this one's."""
        grabber = LatestFrame(self.capture, self._reconnect if self.reopen else None, self.clock)
        t0: float | None = None
        clock = "" if self.clock is None else self.clock.name
        try:
            for index, grabbed, stamped, image, damage in grabber:
                t0 = grabbed if t0 is None else t0
                name, file = f"frame {index}", f"{self.description}#{index}"
                if image is None:
                    self.stale += 1
                    yield Frame(
                        index, grabbed - t0, None, name, file=file, grabbed_s=grabbed, stale=True
                    )
                    continue
                dated = clock if math.isfinite(stamped) else ""
                why = self._damage_note(damage)
                self.damaged += bool(damage)
                yield Frame(
                    index,
                    grabbed - t0,
                    _to_uint8(image),
                    name,
                    why,
                    file=file,
                    grabbed_s=grabbed,
                    damaged=bool(damage),
                    stamped_s=stamped,
                    clock=dated,
                )
        finally:
            grabber.close()
            grabber.capture.release()
        if grabber.failed:
            raise SourceError(
                f"{self.description}: stopped delivering frames (unplugged, or taken by another "
                "program); tracking stopped there"
            )
        if self.gave_up:
            raise SourceError(
                f"{self.description}: the stream dropped and did not come back within "
                f"{self.reconnect_for_s:g} s; tracking stopped there"
            )

    def _reconnect(self) -> Capture | None:
        """A dropped stream, opened again (None: it stayed down ``reconnect_for_s``, and the
        source ends with a ``SourceError`` after its last frame)."""
        assert self.reopen is not None
        deadline = time.monotonic() + self.reconnect_for_s
        while time.monotonic() < deadline:
            capture = self.reopen()
            if capture is not None:
                self.reconnects += 1
                return capture
            time.sleep(RECONNECT_PERIOD_S)
        self.gave_up = True
        return None

    def _damage(self) -> str:
        """Why the frame just read rests on damaged data, or ''."""
        if not isinstance(self.capture, AvCapture):
            return ""
        return self._damage_note(self.capture.damage)

    def _damage_note(self, damage: str) -> str:
        """A damaged frame's ``error`` ('' for a whole one)."""
        return f"{self.description}: {damage}; not measured" if damage else ""

    def _index_of_last_read(self, expected: int) -> int:
        """The index of the frame just read, from its presentation time (``AvCapture.index``;
        ``expected`` from a capture that does not say)."""
        if isinstance(self.capture, AvCapture):
            return max(expected, self.capture.index)
        return expected

    def _lost_frame(self, i: int) -> Frame:
        why = f"{self.description}: frame {i} cannot be decoded (damaged or truncated video)"
        return Frame(i, i / self.fps, None, f"frame {i}", why, f"{self.description}#{i}")


class LatestFrame:
    """A live capture read on a thread of its own, so that grabbing never waits for the
    estimator and the estimator never works on an old frame: iterating gives (index, grab
    time, stamp, image, damage) for the newest frame, and (index, grab time, NaN, None, '')
    first for each frame a newer one overtook before it was taken (stale: dropped, not
    queued). ``damage``: why the frame rests on damaged data (``AvCapture.damage``; '' when
    whole). Grab times are ``time.monotonic()`` just after ``grab()``, before the frame is
    decoded. The stamp: with a ``clock``, the source's own stamp of the frame on the clock of
    the grab times (``SourceClock.stamp``: NaN where it has none; the clock is reset at a
    reconnection); without one, NaN. Ends when the capture stops delivering (and
    ``reconnect``, when given, cannot open it again) or ``close`` is called."""

    def __init__(
        self,
        capture: Capture,
        reconnect: Callable[[], Capture | None] | None = None,
        clock: SourceClock | None = None,
    ) -> None:
        self.capture = capture
        self.reconnect = reconnect
        self.clock = clock
        self._ready = threading.Condition()
        self._newest: tuple[int, float, float, NDArray[Any], str] | None = None
        self._overtaken: list[tuple[int, float]] = []
        self._ended = False
        self._closing = threading.Event()
        self.failed = False  # the capture stopped delivering (not closed, nothing to reopen)
        self._thread = threading.Thread(target=self._grab, name="perchpose-capture", daemon=True)
        self._thread.start()

    def _grab(self) -> None:
        index = 0
        try:
            while not self._closing.is_set():
                ok = self.capture.grab()
                grabbed = time.monotonic()
                stamped = self._stamp(grabbed) if ok else math.nan
                image = self.capture.retrieve()[1] if ok else None
                if image is None:
                    if self._closing.is_set():
                        break
                    if self.reconnect is None:
                        self.failed = True  # a camera that stopped delivering
                        break
                    self.capture.release()
                    capture = self.reconnect()
                    if capture is None:
                        break
                    self.capture = capture
                    if self.clock is not None:
                        self.clock.reset()
                    continue
                damage = self.capture.damage if isinstance(self.capture, AvCapture) else ""
                with self._ready:
                    if self._newest is not None:
                        self._overtaken.append(self._newest[:2])
                    self._newest = (index, grabbed, stamped, image, damage)
                    self._ready.notify()
                index += 1
        finally:
            with self._ready:
                self._ended = True
                self._ready.notify()

    def _stamp(self, grabbed_s: float) -> float:
        """The source's own stamp of the frame just grabbed, on the host's clock (NaN)."""
        if self.clock is None:
            return math.nan
        if isinstance(self.capture, AvCapture):
            source_s = self.capture.pts_s
        else:
            source_s = self.capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        return self.clock.stamp(source_s, grabbed_s)

    def __iter__(self) -> Iterator[tuple[int, float, float, NDArray[Any] | None, str]]:
        while True:
            with self._ready:
                while self._newest is None and not self._ended:
                    self._ready.wait()
                overtaken, self._overtaken = self._overtaken, []
                newest, self._newest = self._newest, None
            for index, grabbed in overtaken:
                yield index, grabbed, math.nan, None, ""
            if newest is None:
                return
            yield newest

    @property
    def running(self) -> bool:
        """The grabbing thread is still alive."""
        return self._thread.is_alive()

    def close(self) -> None:
        """Stop grabbing and wait for the thread (it ends after its current grab)."""
        self._closing.set()
        self._thread.join(timeout=2.0)


def _damage(path: Path) -> str:
    """Why an image that decoded may still be incomplete ('' when nothing is known): a JPEG
    without its end-of-image marker was cut short, and its decoder greys out the rest."""
    if path.suffix.lower() not in (".jpg", ".jpeg"):
        return ""
    try:
        with path.open("rb") as f:
            f.seek(max(0, path.stat().st_size - 64))
            tail = f.read()
    except OSError as exc:
        return f"{path}: cannot read ({exc.strerror})"
    if b"\xff\xd9" not in tail:
        return f"{path}: truncated JPEG (no end-of-image marker); the image is incomplete"
    return ""


def _frame_count(capture: Capture) -> int | None:
    """The frames a recording's container promises (None where it does not say)."""
    if isinstance(capture, AvCapture):
        return capture.count
    return int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) or None


def _to_uint8(image: NDArray[Any]) -> NDArray[np.uint8]:
    if image.dtype == np.uint16:
        image = (image // 256).astype(np.uint8)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    return np.asarray(image, dtype=np.uint8)


def _camera(index: str, rate: float, size: tuple[int, int] | None) -> VideoSource:
    """Camera ``index``, asked for ``size``."""
    with native_stderr_silenced():
        capture = cv2.VideoCapture(int(index))
    if not capture.isOpened():
        raise SourceError(f"camera {index}: cannot be opened")
    if size is not None:
        capture.set(cv2.CAP_PROP_FRAME_WIDTH, float(size[0]))
        capture.set(cv2.CAP_PROP_FRAME_HEIGHT, float(size[1]))
    clock = DeviceClock() if capture.getBackendName() == "V4L2" else None
    return VideoSource(capture, rate, f"camera {index}", live=True, clock=clock)


def _open_stream(url: str) -> AvCapture | None:
    """``url`` decoded by PyAV, with open and read timeouts; None if it cannot be opened
    now."""
    return AvCapture.open(url, live=True, timeout_s=STREAM_TIMEOUT_MS / 1000)


def _stream(url: str, rate: float) -> VideoSource:
    """A network stream, read live (``LatestFrame``: each frame's grab time, stale frames
    dropped) and reopened for ``RECONNECT_FOR_S`` when it drops."""
    capture = _open_stream(url)
    if capture is None:
        raise SourceError(
            f"{url}: cannot open the stream (nothing answers, or FFmpeg cannot read it) "
            f"within {STREAM_TIMEOUT_MS / 1000:g} s"
        )
    return VideoSource(
        capture, rate, url, live=True, reopen=lambda: _open_stream(url), clock=StreamClock()
    )


def _image_files(source: str) -> list[Path] | None:
    """The image files a glob or a folder names, in natural order; None for anything else."""
    if any(ch in source for ch in "*?["):
        paths = sorted(
            (Path(p) for p in globlib.glob(source) if Path(p).is_file()), key=natural_key
        )
        if not paths:
            raise SourceError(f"{source}: the pattern matches no file")
        return paths
    path = Path(source)
    if not path.is_dir():
        return None
    paths = sorted(
        (p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
        key=natural_key,
    )
    if not paths:
        raise SourceError(f"{path}: the folder holds no image files")
    return paths


def is_live(source: str) -> bool:
    """``source`` names a live camera (an index) or a network stream, not a recording."""
    return source.isdigit() or source.lower().startswith(STREAM_SCHEMES)


def open_source(
    source: str,
    fps: float | None = None,
    size: tuple[int, int] | None = None,
    image_topic: str | None = None,
) -> FrameSource:
    """Open ``source``: a folder of images (in natural order: ``img_2`` before ``img_10``), a
    glob (the same order), a video file, one image
    file, or a camera index such as ``0``.

    fps : frame rate used for t_s = index / fps where the source has no clock (default 30;
        a video file's own rate when not given).
    size : (width, height) to ask a live camera for (the calibration's); a driver that gives
        another size is caught at the first frame (``CameraModel.check_image``).
    image_topic : for a ROS bag (``perchpose.io.ros.rosbag``), the topic of its images.
    """
    from perchpose.io.ros import rosbag

    if rosbag.is_bag(source):
        if image_topic is None:
            raise SourceError(f"{source}: a ROS bag needs --image-topic (the images' topic)")
        return rosbag.BagSource(source, image_topic)
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise SourceError(f"--fps must be a positive number, got {fps}")
    rate = fps or 30.0
    if source.isdigit():
        return _camera(source, rate, size)
    if is_live(source):
        return _stream(source, rate)
    images = _image_files(source)
    if images is not None:
        described = str(Path(source)) if Path(source).is_dir() else source
        return ImageFilesSource(images, rate, described)
    path = Path(source)
    if not path.exists():
        raise SourceError(f"{path}: no such file or folder")
    if path.suffix.lower() in IMAGE_SUFFIXES:
        return ImageFilesSource([path], rate, str(path))
    capture = AvCapture.open(str(path), live=False)
    if capture is None:
        raise SourceError(f"{path}: not a readable video or image file")
    if fps is None:
        video_fps = capture.fps or math.nan
        rate = video_fps if math.isfinite(video_fps) and video_fps > 0 else 30.0
    return VideoSource(capture, rate, str(path), live=False)
