"""Perching campaigns as results: success rates, failure causes, percentiles, and the files a
campaign writes (``runs.csv``, ``perch.json``, ``trajectories.png``)."""

from __future__ import annotations

import csv
import json
import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from perchpose.evaluation.plots import perch_figure
from perchpose.sim.perch import CONTACT_RADIUS_MM, PerchResult, PerchSetup


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


def write_campaign(
    out_dir: str, results: dict[str, list[PerchResult]], setup: PerchSetup
) -> dict[str, object]:
    """Write ``runs.csv``, ``perch.json`` and ``trajectories.png`` into ``out_dir``; return the
    JSON content."""
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
