"""Monte-Carlo perching: many runs from random starts, in parallel, and their statistics."""

from __future__ import annotations

import math
import sys
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace

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


@dataclass(frozen=True)
class CampaignSummary:
    """Statistics of a set of runs of one estimator."""

    estimator: str
    runs: int
    success_rate: float
    reasons: dict[str, int]
    contact_offset_mm: dict[str, float]
    time_to_perch_s: dict[str, float]


def _percentiles(values: list[float]) -> dict[str, float]:
    finite = np.array([v for v in values if math.isfinite(v)])
    if finite.size == 0:
        return {"p50": math.nan, "p90": math.nan, "p95": math.nan, "max": math.nan}
    return {
        "p50": float(np.percentile(finite, 50)),
        "p90": float(np.percentile(finite, 90)),
        "p95": float(np.percentile(finite, 95)),
        "max": float(finite.max()),
    }


def summarise(results: list[PerchResult]) -> CampaignSummary:
    """Success rate, failure reasons and percentiles of contact offset and time to perch."""
    if not results:
        raise ValueError("no runs to summarise")
    return CampaignSummary(
        estimator=results[0].estimator,
        runs=len(results),
        success_rate=sum(r.success for r in results) / len(results),
        reasons=dict(Counter(r.reason for r in results)),
        contact_offset_mm=_percentiles([r.contact_offset_mm for r in results]),
        time_to_perch_s=_percentiles([r.time_to_perch_s for r in results if r.success]),
    )


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


def write_campaign(
    out_dir: str, results: dict[str, list[PerchResult]], setup: PerchSetup
) -> dict[str, object]:
    """Write ``runs.csv``, ``perch.json`` and ``trajectories.png`` into ``out_dir``; return the
    JSON content."""
    import csv
    import json
    from pathlib import Path

    from perchpose.evaluation.plots import perch_figure
    from perchpose.sim.perch import CONTACT_RADIUS_MM

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with (out / "runs.csv").open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(
            [
                "estimator",
                "seed",
                "success",
                "reason",
                "contact_offset_mm",
                "contact_speed_mps",
                "time_to_perch_s",
            ]
        )
        for name, rs in results.items():
            for r in rs:
                w.writerow(
                    [
                        name,
                        r.seed,
                        int(r.success),
                        r.reason,
                        f"{r.contact_offset_mm:.3f}",
                        f"{r.contact_speed_mps:.4f}",
                        f"{r.time_to_perch_s:.3f}",
                    ]
                )
    content = summary_json(results, setup)
    (out / "perch.json").write_text(json.dumps(content, indent=2), encoding="utf-8")
    first = next(iter(results.values()))
    perch_figure(
        str(out / "trajectories.png"),
        [
            (f"{r.estimator} seed {r.seed} ({r.reason})", r.t_s, r.p_magnet_m, r.stage)
            for r in first[:5]
        ],
        setup.plate_z_m,
        CONTACT_RADIUS_MM,
    )
    return content


def summary_json(results: dict[str, list[PerchResult]], setup: PerchSetup) -> dict[str, object]:
    """The figures of a campaign: per estimator, and the first estimator's at the top level
    (``success_rate``, ``runs``, ``contact_offset_mm``, ``time_to_perch_s``)."""
    per = {name: summarise(rs) for name, rs in results.items()}
    first = next(iter(per.values()))

    def clean(d: dict[str, float]) -> dict[str, float | None]:
        return {k: (v if math.isfinite(v) else None) for k, v in d.items()}

    return {
        "estimator": first.estimator,
        "success_rate": first.success_rate,
        "runs": first.runs,
        "contact_offset_mm": clean(first.contact_offset_mm),
        "time_to_perch_s": clean(first.time_to_perch_s),
        "by_estimator": {
            name: {
                "success_rate": s.success_rate,
                "runs": s.runs,
                "reasons": s.reasons,
                "contact_offset_mm": clean(s.contact_offset_mm),
                "time_to_perch_s": clean(s.time_to_perch_s),
            }
            for name, s in per.items()
        },
        "setup": {
            "camera": setup.camera.name,
            "wind": setup.wind,
            "fps": setup.fps,
            "latency_frames": setup.latency_frames,
            "drop_probability": setup.drop_probability,
            "start_below_m": list(setup.start_below_m),
            "start_lateral_fraction": setup.start_lateral_fraction,
            "ceiling_effect": setup.ceiling_effect,
        },
    }
