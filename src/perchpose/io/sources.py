"""Frame sources: a folder of images, a glob, a video file, a single image, or a camera index."""

from __future__ import annotations

import glob as globlib
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.errors import SourceError

IMAGE_SUFFIXES = frozenset(
    {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp"}
)
VIDEO_SUFFIXES = frozenset({".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg"})


@dataclass(frozen=True)
class Frame:
    """One input frame.

    index : position in the source, from 0. t_s : capture time, seconds.
    image : (H, W) or (H, W, 3) uint8, or None when it could not be read (``error`` says why).
    name : file name, or ``frame N`` for videos and cameras.
    """

    index: int
    t_s: float
    image: NDArray[np.uint8] | None
    name: str
    error: str = ""


class FrameSource:
    """Iterable of ``Frame``; ``count`` is the number of frames when known in advance."""

    def __init__(self, description: str, count: int | None, fps: float) -> None:
        self.description = description
        self.count = count
        self.fps = fps

    def __iter__(self) -> Iterator[Frame]:
        raise NotImplementedError


class ImageFilesSource(FrameSource):
    """Image files in the given order; t_s = index / fps."""

    def __init__(self, paths: list[Path], fps: float, description: str) -> None:
        super().__init__(description, len(paths), fps)
        self.paths = paths

    def __iter__(self) -> Iterator[Frame]:
        for i, path in enumerate(self.paths):
            t_s = i / self.fps
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if image is None:
                yield Frame(i, t_s, None, path.name, f"{path}: cannot read image")
                continue
            yield Frame(i, t_s, _to_uint8(image), path.name)


class VideoSource(FrameSource):
    """A video file or a camera.

    Files: t_s = index / fps; cameras: seconds since the first frame.
    """

    def __init__(self, capture: cv2.VideoCapture, fps: float, description: str, live: bool) -> None:
        count = None if live else int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) or None
        super().__init__(description, count, fps)
        self.capture = capture
        self.live = live

    def __iter__(self) -> Iterator[Frame]:
        i = 0
        t0 = time.monotonic()
        try:
            while True:
                ok, image = self.capture.read()
                if not ok or image is None:
                    break
                t_s = time.monotonic() - t0 if self.live else i / self.fps
                yield Frame(i, t_s, _to_uint8(image), f"frame {i}")
                i += 1
        finally:
            self.capture.release()


def _to_uint8(image: NDArray[Any]) -> NDArray[np.uint8]:
    if image.dtype == np.uint16:
        image = (image // 256).astype(np.uint8)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    return np.asarray(image, dtype=np.uint8)


def open_source(source: str, fps: float | None = None) -> FrameSource:
    """Open ``source``: a folder of images (sorted by name), a glob, a video file, one image
    file, or a camera index such as ``0``.

    fps : frame rate used for t_s = index / fps where the source has no clock (default 30;
        a video file's own rate when not given).
    """
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise SourceError(f"--fps must be a positive number, got {fps}")
    rate = fps or 30.0
    if source.isdigit():
        capture = cv2.VideoCapture(int(source))
        if not capture.isOpened():
            raise SourceError(f"camera {source}: cannot be opened")
        return VideoSource(capture, rate, f"camera {source}", live=True)
    path = Path(source)
    if any(ch in source for ch in "*?["):
        paths = sorted(Path(p) for p in globlib.glob(source) if Path(p).is_file())
        if not paths:
            raise SourceError(f"{source}: the pattern matches no file")
        return ImageFilesSource(paths, rate, source)
    if path.is_dir():
        paths = sorted(
            p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
        )
        if not paths:
            raise SourceError(f"{path}: the folder holds no image files")
        return ImageFilesSource(paths, rate, str(path))
    if not path.exists():
        raise SourceError(f"{path}: no such file or folder")
    if path.suffix.lower() in IMAGE_SUFFIXES:
        return ImageFilesSource([path], rate, str(path))
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise SourceError(f"{path}: not a readable video or image file")
    if fps is None:
        video_fps = float(capture.get(cv2.CAP_PROP_FPS))
        rate = video_fps if math.isfinite(video_fps) and video_fps > 0 else 30.0
    return VideoSource(capture, rate, str(path), live=False)
