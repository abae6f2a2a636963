"""Overlay video: marker outlines, target axes and the pose text on each frame."""

from __future__ import annotations

import math
import os
from fractions import Fraction
from pathlib import Path

import av
import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.errors import PerchposeError
from perchpose.io.native import native_stderr_silenced
from perchpose.values import Estimate

GREEN = (0, 200, 0)
RED = (0, 0, 255)
BLUE = (255, 80, 0)
YELLOW = (0, 220, 255)
STAGE_NAMES = {0: "no target", 1: "stage 1 outer", 2: "stage 2 both", 3: "stage 3 inner"}


def draw_overlay(
    image: NDArray[np.uint8],
    estimate: Estimate | None,
    camera: CameraModel,
    axis_m: float = 0.03,
    note: str = "",
) -> NDArray[np.uint8]:
    """A BGR copy of ``image`` with detected marker outlines (green), each measured marker's
    axes (x red, y green, z blue, as OpenCV draws them) and the pose text at the bottom left."""
    if image.ndim == 2:
        out = np.asarray(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), dtype=np.uint8)
    else:
        out = np.ascontiguousarray(image[:, :, :3]).copy()
    if estimate is not None:
        for m in estimate.markers:
            if m.detection is not None:
                quad = np.round(m.detection.corners_px).astype(np.int32)
                cv2.polylines(out, [quad], True, GREEN, 2, cv2.LINE_AA)
                cv2.circle(out, tuple(int(v) for v in quad[0]), 4, YELLOW, -1, cv2.LINE_AA)
            if m.measurement is not None:
                _draw_axes(out, camera, m.measurement.T_camera_target, axis_m)
    _draw_text(out, estimate, note)
    return out


def _draw_axes(
    out: NDArray[np.uint8], camera: CameraModel, T: NDArray[np.float64], axis_m: float
) -> None:
    pts = np.array([[0, 0, 0], [axis_m, 0, 0], [0, axis_m, 0], [0, 0, axis_m]], np.float64)
    p = (T[:3, :3] @ pts.T).T + T[:3, 3]
    uv, ok = camera.project(p)
    if not np.all(ok) or not np.all(np.isfinite(uv)):
        return
    o = (int(round(uv[0, 0])), int(round(uv[0, 1])))
    for k, colour in ((1, RED), (2, GREEN), (3, BLUE)):
        end = (int(round(uv[k, 0])), int(round(uv[k, 1])))
        cv2.line(out, o, end, colour, 2, cv2.LINE_AA)


def _evidence(estimate: Estimate) -> str:
    """What a valid pose rests on: the markers this frame measured, or the filter's
    prediction and how far ahead of its newest measurement."""
    if estimate.predicted:
        return f", predicted {estimate.age_s * 1000:.0f} ms on"
    return f", measured {estimate.measured_label}" if estimate.detected else ""


def _draw_text(out: NDArray[np.uint8], estimate: Estimate | None, note: str) -> None:
    if estimate is None or not estimate.valid:
        lines = [note or "no estimate"]
    else:
        lines = [
            f"x {estimate.x_cm:6.1f} cm  y {estimate.y_cm:6.1f} cm",
            f"z {estimate.z_cm:6.1f} cm  yaw {estimate.yaw_deg:6.1f} deg",
            STAGE_NAMES.get(estimate.stage, "")
            + _evidence(estimate)
            + (f"  {note}" if note else ""),
        ]
    # white text on a darkened box: an outline drawn as thicker text would not sit under it
    # (OpenCV's Hershey glyphs advance further the thicker they are, which reads as doubled)
    h, w = out.shape[:2]
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.55
    width = max(cv2.getTextSize(text, font, scale, 1)[0][0] for text in lines)
    top = max(0, h - 10 - 20 * (len(lines) - 1) - 16)
    box = out[top : h - 4, 4 : min(w, 16 + width)]
    box[:] = (box * 0.45).astype(np.uint8)
    for i, text in enumerate(reversed(lines)):
        y = h - 10 - 20 * i
        cv2.putText(out, text, (10, y), font, scale, (255, 255, 255), 1, cv2.LINE_AA)


CODECS = {".mp4": "mp4v", ".m4v": "mp4v", ".avi": "MJPG", ".mkv": "MJPG"}
H264_SUFFIXES = (".mp4", ".m4v")


def check_overlay_path(path: str | Path) -> Path:
    """An overlay video path that can be written: a known suffix and a writable folder, made
    if missing (checked before the first frame, so that a run with a vehicle link never fails
    on it later)."""
    where = Path(path)
    if where.suffix.lower() not in CODECS:
        raise PerchposeError(f"{where}: overlay must end in .mp4, .m4v, .avi or .mkv")
    folder = where.parent if str(where.parent) else Path(".")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PerchposeError(f"{where}: cannot make the folder {folder} ({exc.strerror})") from exc
    if not os.access(folder, os.W_OK):
        raise PerchposeError(f"{where}: overlay folder {folder} is not writable")
    return where


class _H264File:
    """An MP4 of H.264 written by PyAV's libx264: yuv420p without B-frames (``ultrafast``:
    what every browser plays), 2-3 ms a 640x480 frame, about OpenCV's MPEG-4 Part 2, so that
    writing keeps up with tracking.

    The MP4 is fragmented (``movflags=frag_keyframe+empty_moov``, a key frame every second):
    each second is written whole as it ends, so a run that is killed (SIGKILL, a power cut)
    leaves a video that plays up to its last second, not a file without its index."""

    def __init__(self, path: Path, rate: float, size: tuple[int, int]) -> None:
        try:
            self._container = av.open(
                str(path),
                "w",
                format="mp4",
                options={
                    "movflags": "frag_keyframe+empty_moov+default_base_moof",
                    "flush_packets": "1",
                },
            )
            self._stream = self._container.add_stream(
                "libx264", rate=Fraction(rate).limit_denominator(1001)
            )
        except (av.error.FFmpegError, OSError) as exc:
            raise PerchposeError(f"{path}: cannot open a video writer ({exc})") from exc
        self._stream.width, self._stream.height = size
        self._stream.pix_fmt = "yuv420p"
        key_every = str(max(1, round(rate)))
        self._stream.options = {"preset": "ultrafast", "crf": "23", "g": key_every}

    def write(self, frame_bgr: NDArray[np.uint8]) -> None:
        frame = av.VideoFrame.from_ndarray(frame_bgr, format="bgr24")
        for packet in self._stream.encode(frame):
            self._container.mux(packet)

    def release(self) -> None:
        """Flush the encoder and finish the file (``cv2.VideoWriter``'s name for it)."""
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()


class OverlayWriter:
    """Writes BGR frames to an MP4 or AVI (``MJPG``) file. An MP4 is H.264 (``avc1``, which
    browsers play) through PyAV's libx264, else (a PyAV built without it) MPEG-4 Part 2
    (``mp4v``, which media players play and browsers mostly do not) through OpenCV; ``codec``
    says which. H.264 in yuv420p needs an even width and height: an odd one is written one
    pixel smaller."""

    def __init__(self, path: str | Path, fps: float, size: tuple[int, int]) -> None:
        self.path = check_overlay_path(path)
        rate = fps if math.isfinite(fps) and fps > 0 else 30.0
        suffix = self.path.suffix.lower()
        self.codec = CODECS[suffix]
        self.size = size
        self._writer: cv2.VideoWriter | _H264File
        if suffix in H264_SUFFIXES and "libx264" in av.codecs_available:
            self.codec = "avc1"
            self.size = (size[0] - size[0] % 2, size[1] - size[1] % 2)
            self._writer = _H264File(self.path, rate, self.size)
            return
        self._writer = cv2.VideoWriter()
        with native_stderr_silenced():
            self._writer.open(str(self.path), cv2.VideoWriter.fourcc(*self.codec), rate, size)
        if not self._writer.isOpened():
            raise PerchposeError(f"{self.path}: cannot open a video writer")

    def write(self, frame_bgr: NDArray[np.uint8]) -> None:
        """Append one frame; a frame of another size is scaled to the video's size."""
        if (frame_bgr.shape[1], frame_bgr.shape[0]) != self.size:
            frame_bgr = np.asarray(cv2.resize(frame_bgr, self.size), dtype=np.uint8)
        self._writer.write(frame_bgr)

    def close(self) -> None:
        """Finish the file."""
        self._writer.release()


def encode_jpeg(image: NDArray[np.uint8], quality: int) -> bytes | None:
    """``image`` as a JPEG of ``quality`` (1-100), or None if OpenCV cannot encode it."""
    ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    return jpeg.tobytes() if ok else None
