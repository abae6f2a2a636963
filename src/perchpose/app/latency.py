"""``perchpose latency SOURCE``: a live camera's glass-to-grab latency, measured by filming a
screen of time-coded markers (``perchpose.evaluation.latency``). The screen is refreshed on
this thread at the display rate; the camera's frames are read and decoded on a second."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.errors import DisplayError, SourceError
from perchpose.evaluation.latency import (
    LatencyMeter,
    LatencySummary,
    MarkerReader,
    count_of,
    display_image,
)
from perchpose.io.frames import Frame
from perchpose.io.sources import is_live, open_source

WINDOW = "perchpose latency"


class Screen(Protocol):
    """Where the time-coded markers are shown."""

    def show(self, image: NDArray[np.uint8]) -> float:
        """Hand ``image`` to the display; the monotonic time it was handed over."""
        ...

    def close(self) -> None: ...


class OpenCvScreen:
    """A full-screen OpenCV window (HighGUI)."""

    def __init__(self) -> None:
        try:
            cv2.namedWindow(WINDOW, cv2.WINDOW_NORMAL)
            cv2.setWindowProperty(WINDOW, cv2.WND_PROP_FULLSCREEN, cv2.WINDOW_FULLSCREEN)
        except cv2.error as exc:
            why = "this OpenCV has no GUI" if "not implemented" in str(exc) else "no display"
            raise DisplayError(
                f"cannot open a window to show the markers ({why}): run on a machine with a "
                "display and an OpenCV built with one (opencv-python, not -headless)"
            ) from exc

    def show(self, image: NDArray[np.uint8]) -> float:
        cv2.imshow(WINDOW, image)
        cv2.waitKey(1)  # HighGUI draws on its event loop
        return time.monotonic()

    def close(self) -> None:
        cv2.destroyWindow(WINDOW)


@dataclass(frozen=True)
class LatencyOptions:
    """source : a camera index or a stream URL. seconds : how long to measure. display_hz :
    how often the markers change (at most the screen's refresh rate). display_lag_ms : the
    display's own lag, taken off where known. fps : the rate asked of a camera."""

    source: str
    seconds: float = 10.0
    display_hz: float = 30.0
    display_lag_ms: float = 0.0
    fps: float | None = None

    def __post_init__(self) -> None:
        if not is_live(self.source):
            raise SourceError(
                f"{self.source}: latency needs a live camera (an index) or a stream; a "
                "recording has no glass-to-grab time"
            )
        checks = (
            ("--seconds", self.seconds, 1.0, 600.0),
            ("--display-hz", self.display_hz, 1.0, 240.0),
            ("--display-lag-ms", self.display_lag_ms, 0.0, 500.0),
        )
        for flag, value, low, high in checks:
            if not (math.isfinite(value) and low <= value <= high):
                raise SourceError(f"{flag} must be within {low:g}-{high:g}, got {value}")


def measure(
    options: LatencyOptions,
    screen: Screen,
    frames: Iterable[Frame],
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> LatencySummary:
    """Show a new count every display period for ``options.seconds`` while the camera's
    ``frames`` are read on a thread; their latencies."""
    period = 1.0 / options.display_hz
    meter = LatencyMeter(period, options.display_lag_ms / 1000.0)
    lock = threading.Lock()
    stop = threading.Event()
    failed: list[BaseException] = []

    def read() -> None:
        reader = MarkerReader()
        try:
            for frame in frames:
                if stop.is_set():
                    return
                if frame.image is None:
                    continue
                count = count_of(reader.ids(frame.image))
                with lock:
                    meter.clock = frame.clock
                    meter.seen(count, frame.dated_s)
        except Exception as exc:  # handed to the caller's thread
            failed.append(exc)

    reading = threading.Thread(target=read, name="perchpose-latency-camera", daemon=True)
    count = 0
    with lock:
        meter.shown(count, screen.show(display_image(count)))
    reading.start()
    start = next_s = clock()
    try:
        while clock() - start < options.seconds and not failed:
            next_s += period
            sleep(max(0.0, next_s - clock()))
            count += 1
            image = display_image(count)
            with lock:
                meter.shown(count, screen.show(image))
    finally:
        stop.set()
        screen.close()
        reading.join(timeout=2.0)
    if failed:
        raise failed[0]
    with lock:
        return meter.summary()


def run(options: LatencyOptions) -> LatencySummary:
    """Measure on the user's screen and camera."""
    screen = OpenCvScreen()
    try:
        source = open_source(options.source, options.fps)
    except BaseException:
        screen.close()
        raise
    return measure(options, screen, source)
