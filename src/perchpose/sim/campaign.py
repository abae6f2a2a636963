"""Monte-Carlo perching: many runs from random starts, on local processes or a Dask cluster
(their statistics and files: ``perchpose.evaluation.perching``).

A run depends only on its setup and seed, so the same seeds give the same runs whatever runs
them. Results come back as each run finishes, for the caller to write down at once.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import os
import sys
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import replace

import cv2
import numpy as np
from tqdm import tqdm

from perchpose.errors import SchedulerError
from perchpose.sim.perch import PerchResult, PerchSetup, run_perch
from perchpose.sim.render import Renderer
from perchpose.target import TargetSpec

Job = tuple[PerchSetup, int]
_RENDERERS: dict[tuple[object, ...], Renderer[TargetSpec]] = {}
SCHEDULER_TIMEOUT_S = 10


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


def run_job(job: Job) -> tuple[PerchSetup, PerchResult]:
    """One run, reusing the worker's renderer and the camera's cached tables (ray directions,
    rectification maps) across runs: each job arrives as a fresh copy of the setup."""
    cv2.setNumThreads(1)  # runs are spread over processes; OpenCV's threads would compete
    setup, seed = job
    key = _camera_key(setup)
    renderer = _RENDERERS.get(key)
    if renderer is None:
        renderer = setup.renderer()
        _RENDERERS.clear()
        _RENDERERS[key] = renderer
    flown = setup
    if renderer.camera is not setup.camera or renderer.target is not setup.target:
        flown = replace(setup, camera=renderer.camera, target=renderer.target)
    return setup, run_perch(flown, seed, renderer)


def _exit_with_parent() -> None:
    """A worker's initializer: a thread that ends the worker as soon as the process that
    started it is gone. A parent killed outright (SIGKILL, the out-of-memory killer) cannot
    cancel its jobs, and its workers would otherwise wait for work forever."""
    parent = multiprocessing.parent_process()
    if parent is None:
        return
    sentinel = parent.sentinel

    def watch() -> None:
        multiprocessing.connection.wait([sentinel])
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def worker_pool(workers: int) -> ProcessPoolExecutor:
    """Local processes for runs, each ending with the process that started it."""
    return ProcessPoolExecutor(max_workers=workers, initializer=_exit_with_parent)


def _local(jobs: list[Job], workers: int) -> Iterator[tuple[PerchSetup, PerchResult]]:
    if workers <= 1:
        for job in jobs:
            yield run_job(job)
        return
    with worker_pool(workers) as pool:
        futures = [pool.submit(run_job, job) for job in jobs]
        try:
            for future in as_completed(futures):
                yield future.result()
        finally:
            for future in futures:
                future.cancel()


def _dask(
    jobs: list[Job], scheduler: str, workers: int
) -> Iterator[tuple[PerchSetup, PerchResult]]:
    try:
        from dask.distributed import Client, LocalCluster
        from dask.distributed import as_completed as dask_completed
    except ImportError as exc:
        raise SchedulerError(
            f'--scheduler {scheduler}: Dask is not installed (pip install "dask[distributed]")'
        ) from exc
    cluster = None
    try:
        if scheduler == "local":
            cluster = LocalCluster(  # type: ignore[no-untyped-call]
                n_workers=max(1, workers), threads_per_worker=1, dashboard_address=None
            )
            client = Client(cluster)  # type: ignore[no-untyped-call]
        else:
            client = Client(  # type: ignore[no-untyped-call]
                scheduler, timeout=f"{SCHEDULER_TIMEOUT_S}s"
            )
    except (OSError, TimeoutError, ValueError) as exc:
        if cluster is not None:
            cluster.close()
        raise SchedulerError(
            f"--scheduler {scheduler}: no Dask scheduler answered within "
            f"{SCHEDULER_TIMEOUT_S} s ({exc.__class__.__name__})"
        ) from exc
    except MemoryError as exc:
        # another service (ssh, say) speaks first: Dask reads its banner as a frame length
        raise SchedulerError(
            f"--scheduler {scheduler}: the service there is not a Dask scheduler (what it "
            "sent reads as a message of exabytes)"
        ) from exc
    try:
        futures = client.map(run_job, jobs, pure=False)
        try:
            for future in dask_completed(futures):  # type: ignore[no-untyped-call]
                yield future.result()
        finally:
            client.cancel(futures)  # type: ignore[no-untyped-call]
    finally:
        client.close()  # type: ignore[no-untyped-call]
        if cluster is not None:
            cluster.close()


def execute(
    jobs: list[Job],
    *,
    workers: int = 1,
    scheduler: str | None = None,
    progress: bool = False,
    label: str = "perch",
) -> Iterator[tuple[PerchSetup, PerchResult]]:
    """Fly ``jobs``, yielding (setup, result) as each run finishes.

    scheduler : None for local processes (``workers`` of them; 1 runs in this process),
    ``"local"`` for a Dask ``LocalCluster`` of ``workers`` processes, or the address of an
    existing Dask scheduler (``tcp://HOST:PORT``).
    """
    runner = _local(jobs, workers) if scheduler is None else _dask(jobs, scheduler, workers)
    bar = tqdm(
        total=len(jobs), desc=label, unit="run", disable=not progress, file=sys.stderr, leave=False
    )
    try:
        for item in runner:
            bar.update(1)
            yield item
    finally:
        bar.close()


def run_campaign(
    setup: PerchSetup,
    runs: int,
    seed: int = 0,
    workers: int = 1,
    progress: bool = False,
    label: str = "perch",
    scheduler: str | None = None,
) -> list[PerchResult]:
    """``runs`` runs with seeds ``seed .. seed + runs - 1``; results in seed order."""
    jobs = [(setup, seed + k) for k in range(runs)]
    results = [
        r
        for _, r in execute(
            jobs, workers=workers, scheduler=scheduler, progress=progress, label=label
        )
    ]
    return sorted(results, key=lambda r: r.seed)


def campaign_jobs(
    setups: list[PerchSetup],
    runs: int,
    seed: int,
    done: Callable[[PerchSetup, int], bool] = lambda _s, _k: False,
) -> list[Job]:
    """Every setup (estimator, wind) with seeds ``seed .. seed + runs - 1``, less the runs
    ``done`` says are finished."""
    return [(setup, k) for setup in setups for k in range(seed, seed + runs) if not done(setup, k)]
