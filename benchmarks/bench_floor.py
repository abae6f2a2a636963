"""How much of a tracked frame is compiled code and OpenCV, and how much Python between them.

    .venv/bin/python benchmarks/bench_floor.py [--camera fpv] [--quality default] [--seed 0]
        [--repeat 3] [--budget-ratio 0.1]

The rendered approach of ``perchpose bench`` (240 frames from 150 cm, 30 fps) goes through a
tracking ``PerchingEstimator`` on one thread, ``--repeat`` times; each frame's time is the
least of its runs. In those runs every compiled function of the package that Python calls
(numba dispatchers, looked up in each module's namespace) and the OpenCV calls of the pipeline
(``QuadPass.run``, which is the detector's call and a few lines, and the ``cv2`` functions
named below) are timed from the call to the return: the frame's *floor*, what it would cost
with no Python between those calls. Entering a compiled function from Python costs about a
microsecond or more (its arguments are unboxed), which the floor includes; a run first goes
over the frames once so that every path is compiled or loaded before the timing.

It prints the median of each frame's time and of its floor, how many frames' floors are over
``--budget-ratio`` times OpenCV's ``detectMarkers`` median on the same frames (the tracking
goal of 0.1x), and how many such calls a frame makes.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import time
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
from numba.core.registry import CPUDispatcher

import perchpose
from perchpose import CameraModel, PerchingEstimator, TargetSpec
from perchpose.app.bench import BASELINE, default_methods, rendered_frames
from perchpose.detection.quads import QuadPass
from perchpose.sim.render import ImageQuality

CV2_CALLS = (
    "adaptiveThreshold",
    "cornerSubPix",
    "countNonZero",
    "findHomography",
    "perspectiveTransform",
    "remap",
    "resize",
    "solvePnPGeneric",
    "threshold",
)


class Stopwatch:
    """Seconds spent inside the calls it wraps, and how many, since ``reset``."""

    def __init__(self) -> None:
        self.spent_s = 0.0
        self.calls = 0

    def reset(self) -> None:
        self.spent_s, self.calls = 0.0, 0

    def wrap(self, function: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            self.calls += 1
            t0 = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                self.spent_s += time.perf_counter() - t0

        return timed


def time_compiled_and_opencv(watch: Stopwatch) -> int:
    """Put ``watch`` around every compiled function the package's modules hold, the
    pipeline's ``cv2`` calls and ``QuadPass.run``; how many compiled functions it wraps.
    Compiled code calling compiled code is not wrapped (it calls the machine code)."""
    wrapped: dict[int, Callable[..., Any]] = {}
    for info in pkgutil.walk_packages(perchpose.__path__, "perchpose."):
        if info.name.endswith("__main__"):
            continue
        module = importlib.import_module(info.name)
        for name, value in list(vars(module).items()):
            if isinstance(value, CPUDispatcher):
                timed = wrapped.setdefault(id(value), watch.wrap(value))
                setattr(module, name, timed)
    for name in CV2_CALLS:
        setattr(cv2, name, watch.wrap(getattr(cv2, name)))
    QuadPass.run = watch.wrap(QuadPass.run)  # type: ignore[method-assign]
    return len(wrapped)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--camera", default="fpv")
    parser.add_argument("--quality", default="default")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--budget-ratio", type=float, default=0.1)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    camera, target = CameraModel.preset(args.camera), TargetSpec.paper()
    approach = rendered_frames(camera, target, 240, ImageQuality.preset(args.quality), args.seed)
    frames = list(zip(approach.images, approach.t_s, strict=True))
    opencv = default_methods(camera, target)[BASELINE]
    opencv_ms = np.full(len(frames), np.inf)
    warm = PerchingEstimator(camera, target)
    for grey, t_s in frames:  # every path compiled or loaded before anything is timed
        warm.update(grey, t_s)
    watch = Stopwatch()
    n_compiled = time_compiled_and_opencv(watch)
    total_ms = np.full(len(frames), np.inf)
    floor_ms = np.zeros(len(frames))
    calls = np.zeros(len(frames), dtype=int)
    for _ in range(args.repeat):
        estimator = PerchingEstimator(camera, target)
        for k, (grey, t_s) in enumerate(frames):
            t0 = time.perf_counter()
            opencv(grey, t_s)
            opencv_ms[k] = min(opencv_ms[k], (time.perf_counter() - t0) * 1e3)
            watch.reset()
            t0 = time.perf_counter()
            estimator.update(grey, t_s)
            spent_ms = (time.perf_counter() - t0) * 1e3
            if spent_ms < total_ms[k]:
                total_ms[k], floor_ms[k], calls[k] = spent_ms, watch.spent_s * 1e3, watch.calls
    budget_ms = args.budget_ratio * float(np.median(opencv_ms))
    print(
        f"{args.camera}, {args.quality}, seed {args.seed}: {len(frames)} frames, least of "
        f"{args.repeat} runs, {n_compiled} compiled functions timed"
    )
    print(f"OpenCV detectMarkers median {np.median(opencv_ms):.3f} ms")
    print(
        f"perchpose tracking median {np.median(total_ms):.3f} ms "
        f"({np.median(total_ms) / np.median(opencv_ms):.2f}x)"
    )
    print(
        f"its floor (compiled and OpenCV calls) median {np.median(floor_ms):.3f} ms "
        f"({np.median(floor_ms) / np.median(opencv_ms):.2f}x), p25 "
        f"{np.percentile(floor_ms, 25):.3f}, p75 {np.percentile(floor_ms, 75):.3f}; "
        f"{np.median(floor_ms / total_ms):.2f} of each frame's time at the median"
    )
    over = int(np.count_nonzero(floor_ms > budget_ms))
    print(
        f"frames whose floor is over {args.budget_ratio:g}x OpenCV's median "
        f"({budget_ms:.3f} ms): {over} of {len(frames)}"
    )
    print(f"calls timed per frame: median {int(np.median(calls))}, max {int(calls.max())}")


if __name__ == "__main__":
    main()
