import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from perchpose.app.latency import LatencyOptions, measure
from perchpose.cli import main
from perchpose.io.frames import Frame


class FilmedScreen:
    """A screen and a camera filming it: the camera's frame grabbed at t shows what the
    screen was showing at t - ``delay_s`` (the glass-to-grab latency)."""

    def __init__(
        self, delay_s: float, film: Callable[[np.ndarray, np.random.Generator], np.ndarray]
    ) -> None:
        self.delay_s = delay_s
        self.film = film
        self.shown: list[tuple[float, np.ndarray]] = []
        self.lock = threading.Lock()
        self.closed = False

    def show(self, image: np.ndarray) -> float:
        t = time.monotonic()
        with self.lock:
            self.shown.append((t, image))
        return t

    def close(self) -> None:
        self.closed = True

    def frames(self, fps: float) -> Iterator[Frame]:
        rng = np.random.default_rng(7)
        for i in range(10_000):
            time.sleep(1.0 / fps)
            grabbed = time.monotonic()
            with self.lock:
                on = [image for t, image in self.shown if t <= grabbed - self.delay_s]
            if not on:
                continue
            yield Frame(i, i / fps, self.film(on[-1], rng), f"frame {i}", grabbed_s=grabbed)
            if self.closed:
                return


def test_a_camera_80_ms_behind_the_screen_measures_80_ms(
    film_screen: Callable[[np.ndarray, np.random.Generator], np.ndarray],
) -> None:
    """Two seconds of a 30 Hz display filmed at 30 fps with 80 ms between the glass and the
    grab: the mean is 80 ms within the half display period that single samples spread by."""
    screen = FilmedScreen(0.08, film_screen)
    options = LatencyOptions("0", seconds=2.0, display_hz=30.0)
    summary = measure(options, screen, screen.frames(30.0))
    assert screen.closed
    assert summary.samples >= 20
    assert summary.misread == 0
    assert summary.mean_s == pytest.approx(0.08, abs=0.012)
    assert summary.p95_s - summary.p5_s < 1.0 / 30 + 0.01


def test_a_recording_and_bad_settings_are_refused_in_one_line(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["latency", "flight.mp4"]) == 2
    assert "a recording has no glass-to-grab time" in capsys.readouterr().err
    assert main(["latency", "0", "--display-hz", "0"]) == 2
    assert "--display-hz must be within 1-240" in capsys.readouterr().err
