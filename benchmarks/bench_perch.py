"""CPU cost of closed-loop perching runs, per simulated second and per part.

    .venv/bin/python benchmarks/bench_perch.py [--runs 6] [--camera fpv]

Runs the perching simulation single-threaded (as one campaign worker does) and reports the CPU
time per simulated second, the cost of a 20 s run at that rate, and how the time splits between
rendering, the estimator and the vehicle's physics. The one-off set-up of a worker (ray tables,
rectification maps, the target's texture) is measured separately.

As a baseline measured on the same frames in the same run, every frame the estimator sees also
goes through OpenCV's own detector as the paper used it (``detectMarkers`` with the default
parameters, the full dictionaries and ``CORNER_REFINE_SUBPIX``); the estimator's cost is
reported as a ratio to it, which varies far less between runs on a noisy machine than the
seconds do.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import cv2

from perchpose import CameraModel, PerchingEstimator, TargetSpec
from perchpose.sim.perch import PerchSetup, run_perch
from perchpose.sim.quadrotor import Quadrotor
from perchpose.sim.render import Renderer
from perchpose.target import aruco_dictionary


def timed(cls: type, name: str, key: str, spent: Counter[str]) -> None:
    """Wrap ``cls.name`` to add its CPU time to ``spent[key]``."""
    original: Callable[..., Any] = getattr(cls, name)

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t0 = time.process_time()
        try:
            return original(*args, **kwargs)
        finally:
            spent[key] += time.process_time() - t0

    setattr(cls, name, wrapper)


def opencv_baseline(target: TargetSpec) -> list[cv2.aruco.ArucoDetector]:
    """OpenCV's detector as the paper used it: one per dictionary of the target, the full
    dictionary, default parameters, SUBPIX corners."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return [cv2.aruco.ArucoDetector(aruco_dictionary(name), params) for name in target.dictionaries]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=6)
    parser.add_argument("--camera", default="fpv")
    parser.add_argument("--seed", type=int, default=100)
    args = parser.parse_args()
    cv2.setNumThreads(1)

    setup = PerchSetup(CameraModel.preset(args.camera), TargetSpec.paper())
    t0 = time.process_time()
    renderer = setup.renderer()
    run_perch(setup, args.seed - 1, renderer)  # warms every cache a worker keeps
    setup_cpu = time.process_time() - t0

    spent: Counter[str] = Counter()
    timed(Renderer, "render", "render", spent)
    timed(PerchingEstimator, "update", "estimator", spent)
    baseline = opencv_baseline(setup.target)
    original_update = PerchingEstimator.update

    def update_with_baseline(self: PerchingEstimator, image: Any, t_s: float) -> Any:
        t0 = time.process_time()
        for detector in baseline:
            detector.detectMarkers(image)
        spent["baseline"] += time.process_time() - t0
        return original_update(self, image, t_s)

    PerchingEstimator.update = update_with_baseline  # type: ignore[method-assign]
    timed(Quadrotor, "fly", "physics", spent)
    t0 = time.process_time()
    results = [run_perch(setup, args.seed + k, renderer) for k in range(args.runs)]
    # the run's own CPU: the baseline's detections are not part of it
    cpu = time.process_time() - t0 - spent["baseline"]
    sim_s = sum(len(r.t_s) for r in results) / setup.fps
    per_sim_s = cpu / sim_s
    print(f"camera {args.camera}, {args.runs} runs, {sim_s:.1f} s simulated, {cpu:.1f} s CPU")
    print(f"  CPU per simulated second: {per_sim_s:.3f} s  (a 20 s run: {20 * per_sim_s:.1f} s)")
    for key in ("render", "estimator", "physics"):
        print(f"  {key:10s} {spent[key] / sim_s:.3f} s per simulated second")
    other = cpu - sum(spent[k] for k in ("render", "estimator", "physics"))
    print(f"  {'other':10s} {other / sim_s:.3f} s per simulated second")
    print(
        f"  estimator / OpenCV detectMarkers with SUBPIX on the same frames: "
        f"{spent['estimator'] / spent['baseline']:.2f}"
    )
    print(f"  the whole run / that baseline: {cpu / spent['baseline']:.2f}")
    print(f"  worker set-up and a first run: {setup_cpu:.1f} s CPU (once per worker)")
    print(f"  outcomes: {Counter(r.reason for r in results)}")


if __name__ == "__main__":
    main()
