"""Monte-Carlo perching: many runs from random starts, in parallel (their statistics and files:
``perchpose.evaluation.perching``)."""

from __future__ import annotations

import sys
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import cv2
import numpy as np
from tqdm import tqdm

from perchpose.sim.perch import PerchResult, PerchSetup, run_perch
from perchpose.sim.render import Renderer
from perchpose.target import TargetSpec

_RENDERERS: dict[tuple[object, ...], Renderer[TargetSpec]] = {}


def _camera_key(setup: PerchSetup) -> tuple[object, ...]:
    c = setup.camera
    return (
        c.model,
        c.width_px,
        c.height_px,
        tuple(np.asarray(c.K).ravel().tolist()),
        tuple(np.asarray(c.dist).ravel().tolist()),
        setup.supersample,
        setup.target,  # frozen, compared by value
    )


def _run_one(job: tuple[PerchSetup, int]) -> PerchResult:
    """One run, reusing the worker's renderer and the camera's cached tables (ray directions,
    rectification maps) across runs: each job arrives as a fresh copy of the setup."""
    setup, seed = job
    key = _camera_key(setup)
    renderer = _RENDERERS.get(key)
    if renderer is None:
        renderer = setup.renderer()
        _RENDERERS.clear()
        _RENDERERS[key] = renderer
    if renderer.camera is not setup.camera or renderer.target is not setup.target:
        setup = replace(setup, camera=renderer.camera, target=renderer.target)
    return run_perch(setup, seed, renderer)


def _worker_init() -> None:
    # the runs are spread over processes; OpenCV's own threads would only compete with them
    cv2.setNumThreads(1)


def run_campaign(
    setup: PerchSetup,
    runs: int,
    seed: int = 0,
    workers: int = 1,
    progress: bool = False,
    label: str = "perch",
) -> list[PerchResult]:
    """``runs`` runs with seeds ``seed .. seed + runs - 1``; results in seed order. The same
    seed gives the same runs whatever the number of workers."""
    jobs = [(setup, seed + k) for k in range(runs)]
    bar = tqdm(
        total=runs, desc=label, unit="run", disable=not progress, file=sys.stderr, leave=False
    )
    results: list[PerchResult] = []
    if workers <= 1:
        for job in jobs:
            results.append(_run_one(job))
            bar.update(1)
    else:
        with ProcessPoolExecutor(max_workers=workers, initializer=_worker_init) as pool:
            for result in pool.map(_run_one, jobs, chunksize=1):
                results.append(result)
                bar.update(1)
    bar.close()
    return results


def compare(
    setup: PerchSetup,
    estimators: list[str],
    runs: int,
    seed: int,
    workers: int,
    progress: bool,
    say: Callable[[str], None] = print,
) -> dict[str, list[PerchResult]]:
    """The same starts (seeds) flown with each estimator."""
    out = {}
    for name in estimators:
        say(f"{runs} runs with the {name} estimator")
        out[name] = run_campaign(
            replace(setup, estimator=name), runs, seed, workers, progress, label=name
        )
    return out
