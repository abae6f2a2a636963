"""A camera's frames sent as a live video stream: H.264 (libx264, ``ultrafast`` and
``zerolatency``: no B-frames, no look-ahead) in MPEG-TS, over UDP by default
(``udp://127.0.0.1:5600``, the port ArduPilot's and PX4's simulated cameras use), written by
PyAV on a thread of its own so that whoever sends never waits on the encoder.

A key frame each second lets a reader that joins late start within a second; each packet is
flushed as muxed. Frames that come while the encoder is still busy with two others are
dropped (``dropped`` counts them), as a camera's driver drops frames nobody reads.
"""

from __future__ import annotations

import threading
from collections import deque
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import numpy as np
from numpy.typing import NDArray

from perchpose.errors import SourceError

QUEUE_LENGTH = 2


class H264Stream:
    """Gray or BGR frames of ``size`` (width, height) at ``fps`` to ``url`` (any URL or file
    FFmpeg can write MPEG-TS to)."""

    def __init__(self, url: str, fps: float, size: tuple[int, int]) -> None:
        if "libx264" not in av.codecs_available:
            raise SourceError("this PyAV has no libx264 encoder: cannot stream H.264")
        self.url = url
        if "://" not in url and not Path(url).parent.is_dir():
            raise SourceError(f"cannot write the video stream {url}: no folder {Path(url).parent}")
        try:
            self._container: Any = av.open(
                url, mode="w", format="mpegts", options={"flush_packets": "1"}
            )
        except (av.error.FFmpegError, OSError) as exc:
            raise SourceError(f"cannot open the video stream {url}: {exc}") from exc
        rate = Fraction(fps).limit_denominator(1001)
        self._stream: Any = self._container.add_stream("libx264", rate=rate)
        self._stream.width, self._stream.height = size
        self._stream.pix_fmt = "yuv420p"
        key_every = str(max(1, round(fps)))
        self._stream.options = {"preset": "ultrafast", "tune": "zerolatency", "g": key_every}
        self._time_base = Fraction(1) / rate
        self._queue: deque[tuple[int, NDArray[np.uint8]]] = deque()
        self._lock = threading.Condition()
        self._closing = False
        self.sent = 0
        self.dropped = 0
        self.error = ""
        self._thread = threading.Thread(target=self._encode, name="h264-stream", daemon=True)
        self._thread.start()

    def send(self, index: int, image: NDArray[np.uint8]) -> None:
        """Queue frame ``index`` (its presentation time is ``index / fps``)."""
        with self._lock:
            if len(self._queue) >= QUEUE_LENGTH:
                self._queue.popleft()
                self.dropped += 1
            self._queue.append((index, image))
            self._lock.notify()

    def _encode(self) -> None:
        while True:
            with self._lock:
                while not self._queue and not self._closing:
                    self._lock.wait()
                if not self._queue:
                    break
                index, image = self._queue.popleft()
            try:
                self._write(index, image)
            except (av.error.FFmpegError, OSError, ValueError) as exc:
                self.error = str(exc)
                return
        try:
            for packet in self._stream.encode():
                self._container.mux(packet)
        except (av.error.FFmpegError, OSError, ValueError) as exc:
            self.error = self.error or str(exc)

    def _write(self, index: int, image: NDArray[np.uint8]) -> None:
        layout = "gray" if image.ndim == 2 else "bgr24"
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format=layout)
        frame = frame.reformat(format="yuv420p")
        frame.pts = index
        frame.time_base = self._time_base
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self.sent += 1

    def close(self) -> None:
        """Encode what is queued, then end the stream."""
        with self._lock:
            self._closing = True
            self._lock.notify()
        self._thread.join()
        self._container.close()
