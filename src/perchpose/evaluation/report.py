"""``perchpose evaluate paper``: the paper's experiments on rendered frames, written as
report.md, results.json and PNG figures."""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from perchpose.camera import CameraModel
from perchpose.errors import PerchposeError
from perchpose.evaluation import experiments as ex
from perchpose.evaluation.bound import BoundRow, bound_markdown, bound_rows
from perchpose.evaluation.corner_accuracy import CornerRow, corner_accuracy, corners_markdown
from perchpose.evaluation.fusion_data import write_fusion_csv
from perchpose.evaluation.plots import (
    ablation_figure,
    fusion_figure,
    kalman_figure,
    ranges_figure,
)
from perchpose.sim.render import ImageQuality, Renderer
from perchpose.sim.scenarios import Scenario, approach
from perchpose.target import TargetSpec

RANGE_DISTANCES_CM = (3, 4, 5, 6, 8, 10, 12, 15, 18, 22, 27, 33, 40, 50, 60, 75, 90, 110, 130,
                      160, 200, 250, 300)  # fmt: skip


@dataclass(frozen=True)
class EvalPlan:
    """Sizes of each experiment."""

    range_distances_cm: tuple[float, ...]
    range_frames: int
    range_qualities: tuple[str, ...]
    table_frames: int
    fusion_positions: int
    fusion_frames: int
    moves_s: float
    dropout_at_s: float
    dropout_s: float
    approach_s: float
    corner_poses: int
    bound_distances_m: tuple[float, ...]
    bound_frames: int
    bound_poses: int

    @staticmethod
    def make(quick: bool) -> EvalPlan:
        """The full plan, or the reduced ``--quick`` one."""
        if quick:
            return EvalPlan(
                range_distances_cm=(3, 6, 12, 25, 50, 100, 200),
                range_frames=2,
                range_qualities=("clean", "analog_fpv"),
                table_frames=3,
                fusion_positions=10,
                fusion_frames=3,
                moves_s=3.0,
                dropout_at_s=1.5,
                dropout_s=1.0,
                approach_s=2.0,
                corner_poses=12,
                bound_distances_m=(0.2, 0.6, 1.5),
                bound_frames=3,
                bound_poses=1,
            )
        return EvalPlan(
            range_distances_cm=RANGE_DISTANCES_CM,
            range_frames=20,
            range_qualities=("clean", "analog_fpv"),
            table_frames=40,
            fusion_positions=10,
            fusion_frames=100,
            moves_s=21.0,
            dropout_at_s=17.5,
            dropout_s=1.0,
            approach_s=8.0,
            corner_poses=60,
            bound_distances_m=(0.1, 0.2, 0.35, 0.6, 1.0, 1.5, 2.0),
            bound_frames=15,
            bound_poses=4,
        )

    def renders(self) -> int:
        """Frames this plan renders (for the progress bar)."""
        n = len(self.range_distances_cm) * self.range_frames * len(self.range_qualities)
        n += self.table_frames * (len(ex.PAPER_TABLE1) + len(ex.PAPER_TABLE2))
        n += self.fusion_positions * self.fusion_frames
        n += int(round(self.moves_s * 30)) + int(round(self.approach_s * 30))
        n += 2 * self.corner_poses
        n += 2 * len(self.bound_distances_m) * self.bound_frames * self.bound_poses
        return n


@dataclass(frozen=True)
class EvaluationResult:
    """Where the report went, and the numbers in it."""

    out_dir: Path
    report: Path
    results: dict[str, Any]


def _clean(value: Any) -> Any:
    """JSON-safe: NaN and inf become null, numpy scalars plain numbers, tuples lists."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _fmt(v: float, digits: int = 2) -> str:
    return "-" if not math.isfinite(v) else f"{v:.{digits}f}"


def _triple(v: tuple[float, ...], digits: int = 2) -> str:
    return "(" + ", ".join(_fmt(x, digits) for x in v[:3]) + ")"


def _row_dict(row: ex.StaticRow) -> dict[str, Any]:
    d = asdict(row)
    d["in_view"] = list(row.in_view)
    d["stages"] = list(row.stages)
    return d


@dataclass(frozen=True)
class _Outcomes:
    """What the experiments found, before anything is written."""

    curves: list[ex.RangeCurve]
    t1: list[ex.StaticRow]
    t2: list[ex.StaticRow]
    moves_run: ex.SequenceRun
    drop: ex.DropoutResult
    samples: ex.FusionSamples
    fit: ex.FusionFit | None
    approach_scenario: Scenario
    ablations: list[ex.AblationRow]
    bounds: list[BoundRow]
    corner_rows: list[CornerRow]


def _run_experiments(
    cam: CameraModel,
    quality_name: str,
    plan: EvalPlan,
    seeds: dict[str, int],
    tick: Callable[[int], None],
    say: Callable[[str], None],
) -> _Outcomes:
    """Every experiment of the paper, in order, on rendered frames of ``cam``."""
    target = TargetSpec.paper()
    quality = ImageQuality.preset(quality_name)
    renderer = Renderer(cam, target)
    say("detection ranges")
    curves = [
        ex.detection_ranges(
            renderer,
            q,
            ImageQuality.preset(q),
            np.array(plan.range_distances_cm, np.float64),
            plan.range_frames,
            np.random.default_rng(seeds["ranges"] + k),
            tick,
        )
        for k, q in enumerate(plan.range_qualities)
    ]
    say("Table 1 and Table 2")
    t1 = ex.table1(
        renderer, quality, plan.table_frames, np.random.default_rng(seeds["table1"]), tick
    )
    t2 = ex.table2(
        renderer, quality, plan.table_frames, np.random.default_rng(seeds["table2"]), tick
    )
    say("Kalman filter across a dropout")
    moves = ex.moves_scenario(plan.moves_s, plan.dropout_at_s, plan.dropout_s, quality)
    moves_frames = ex.render_scenario(renderer, moves, np.random.default_rng(seeds["moves"]), tick)
    from perchpose.estimator import PerchingEstimator

    moves_run = ex.run_sequence(PerchingEstimator(cam, target), moves, moves_frames)
    drop = ex.dropout_summary(moves_run)
    say("fusion fit")
    samples = ex.fusion_samples(
        renderer,
        quality,
        plan.fusion_positions,
        plan.fusion_frames,
        np.random.default_rng(seeds["fusion"]),
        (0.15, 0.6),
        tick,
    )
    fit = ex.fit_fusion(samples) if samples.truth.shape[0] >= 2 else None
    say("ablations on an approach")
    appr = approach(duration_s=plan.approach_s, dropouts=(), quality=quality)
    appr_frames = ex.render_scenario(renderer, appr, np.random.default_rng(seeds["approach"]), tick)
    appr_detections = {
        method: ex.detect_all(renderer, appr_frames, method) for method in ("edges", "subpix")
    }
    ablations = [
        ex.ablation(renderer, appr, appr_detections[str(opts.get("corners", "edges"))], name, opts)
        for name, opts in ex.ABLATIONS.items()
    ]
    say("the physical limit")
    bounds = _bound_rows(cam, target, plan, seeds["bound"], tick)
    say("corner accuracy")
    corner_rows = corner_accuracy(
        Renderer(cam, target, supersample=3),
        {"default": ImageQuality.preset("default"), quality_name: quality},
        plan.corner_poses,
        np.random.default_rng(seeds["corners"]),
        tick,
    )
    return _Outcomes(
        curves, t1, t2, moves_run, drop, samples, fit, appr, ablations, bounds, corner_rows
    )


def _bound_rows(
    cam: CameraModel, target: TargetSpec, plan: EvalPlan, seed: int, tick: Callable[[int], None]
) -> list[BoundRow]:
    """The physical limit's rows for ``cam`` and the webcam (seeds from ``seed`` on)."""
    bound_cameras = [cam] + ([] if cam.name == "webcam" else [CameraModel.preset("webcam")])
    return [
        row
        for k, c in enumerate(bound_cameras)
        for row in bound_rows(
            Renderer(c, target, supersample=3),
            ImageQuality.preset("default"),
            plan.bound_distances_m,
            plan.bound_frames,
            np.random.default_rng(seed + k),
            tick,
            plan.bound_poses,
        )
    ]


def _write_figures(
    out: Path, cam: CameraModel, quality_name: str, plan: EvalPlan, o: _Outcomes
) -> None:
    """ranges.png, kalman.png, ablation.png and (with a fit) fusion.png."""
    target = TargetSpec.paper()
    curves, moves_run, ablations, fit = o.curves, o.moves_run, o.ablations, o.fit
    appr = o.approach_scenario
    ranges_figure(
        str(out / "ranges.png"),
        [(f"{c.quality} images, {cam.name} camera", c.distances_cm, c.probability) for c in curves],
        {"z1": 115.0, "z2": 25.0, "z3": 15.0},
    )
    raw = {target.marker_name(i): v for i, v in moves_run.raw.items()}
    kalman_figure(
        str(out / "kalman.png"),
        moves_run.t_s,
        raw,
        moves_run.filtered,
        moves_run.truth,
        moves_run.dropout,
        f"Raw per-marker poses and the filtered estimate ({cam.name} camera, "
        f"{quality_name} images, {plan.dropout_s:.0f} s dropout)",
    )
    position_series, yaw_series = {}, {}
    for a in ablations:
        sel = a.run.valid & a.run.truth_in_view
        err = a.run.errors()
        position_series[a.name] = (a.run.truth[sel, 2], np.linalg.norm(err[sel, :3], axis=1))
        yaw_series[a.name] = (a.run.truth[sel, 2], np.abs(err[sel, 3]))
    ablation_figure(
        str(out / "ablation.png"),
        position_series,
        yaw_series,
        f"Approach {appr.poses[0][2, 3] * 100:.0f} cm to contact, {cam.name} camera, "
        f"{quality_name} images",
    )
    names = list(ex.COMPONENT_NAMES)
    if fit is not None:
        fusion_figure(
            str(out / "fusion.png"),
            names,
            [fit.least_squares[n] for n in names],
            [fit.lms[n] for n in names],
            [ex.PAPER_SIGMAS[n] for n in names],
        )


def _results(
    o: _Outcomes,
    cam: CameraModel,
    quality_name: str,
    plan: EvalPlan,
    config: dict[str, Any],
) -> dict[str, Any]:
    """results.json's content: ``config`` (the run's settings) and every experiment's
    numbers beside the paper's."""
    curves, t1, t2, drop, fit, ablations = o.curves, o.t1, o.t2, o.drop, o.fit, o.ablations
    corner_rows, bounds = o.corner_rows, o.bounds
    headline = curves[-1]
    results: dict[str, Any] = {
        "config": config,
        "ranges": {
            **{
                name: {"z_max_cm": headline.z_max_cm(name), "z_min_cm": headline.z_min_cm(name)}
                for name in ("outer", "inner", "fused")
            },
            "quality": headline.quality,
            "by_quality": {
                c.quality: {
                    "distances_cm": c.distances_cm.tolist(),
                    **{
                        n: {
                            "probability": p.tolist(),
                            "z_max_cm": c.z_max_cm(n),
                            "z_min_cm": c.z_min_cm(n),
                        }
                        for n, p in c.probability.items()
                    },
                }
                for c in curves
            },
            "paper": ex.PAPER_RANGES_CM,
        },
        "table1": [
            {**_row_dict(r), "paper_estimated": list(p[1]), "paper_error": list(p[2])}
            for r, p in zip(t1, ex.PAPER_TABLE1, strict=True)
        ],
        "table2": [
            {**_row_dict(r), "paper_estimated": p[1], "paper_error": p[2]}
            for r, p in zip(t2, ex.PAPER_TABLE2, strict=True)
        ],
        "fusion_fit": None
        if fit is None
        else {
            "least_squares": fit.least_squares,
            "lms": fit.lms,
            "lms_passes": fit.lms_passes,
            "samples": fit.samples,
            "paper": ex.PAPER_SIGMAS,
        },
        "dropout": asdict(drop),
        "ablations": [{k: v for k, v in asdict(a).items() if k != "run"} for a in ablations],
        "corners": [asdict(r) for r in corner_rows],
        "bound": [
            {**asdict(r), "joint_over_bound": r.ratio, "yaw_over_bound": r.yaw_ratio}
            for r in bounds
        ],
    }
    return results


def run_paper_evaluation(
    out_dir: str | Path,
    camera: CameraModel | None = None,
    *,
    quick: bool = False,
    seed: int = 0,
    quality_name: str = "analog_fpv",
    progress: bool = True,
    say: Callable[[str], None] = print,
) -> EvaluationResult:
    """Run every experiment of the paper on rendered frames of ``camera`` (default: the
    ``fpv`` preset, a 640x480 equidistant FPV lens like the paper's) and write the report."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PerchposeError(f"{out}: cannot create folder ({exc.strerror})") from exc
    cam = camera or CameraModel.preset("fpv")
    quality = ImageQuality.preset(quality_name)
    plan = EvalPlan.make(quick)
    started = time.perf_counter()
    bar = tqdm(
        total=plan.renders(),
        desc="evaluate",
        unit="frame",
        disable=not progress,
        file=sys.stderr,
        leave=False,
    )

    def tick(n: int) -> None:
        bar.update(n)

    seeds = {
        "ranges": seed,
        "table1": seed + 1,
        "table2": seed + 2,
        "moves": seed + 3,
        "fusion": seed + 4,
        "approach": seed + 5,
        "corners": seed + 6,
        "bound": seed + 7,
    }

    outcomes = _run_experiments(cam, quality_name, plan, seeds, tick, say)
    bar.close()
    elapsed = time.perf_counter() - started
    write_fusion_csv(out / "fusion_data.csv", outcomes.samples)
    _write_figures(out, cam, quality_name, plan, outcomes)
    config = {
        "camera": cam.to_ros_dict(),
        "quality": quality_name,
        "quality_settings": asdict(quality),
        "quick": quick,
        "seed": seed,
        "seeds": seeds,
        "plan": asdict(plan),
        "renders": plan.renders(),
        "elapsed_s": elapsed,
    }
    results = _clean(_results(outcomes, cam, quality_name, plan, config))
    (out / "results.json").write_text(json.dumps(results, indent=2), encoding="utf-8")
    report = out / "report.md"
    report.write_text(
        _markdown(results, cam, quality_name, outcomes, plan, elapsed)
        + corners_markdown(outcomes.corner_rows)
        + bound_markdown(outcomes.bounds),
        encoding="utf-8",
    )
    return EvaluationResult(out, report, results)


def _md_ranges(o: _Outcomes, plan: EvalPlan) -> list[str]:
    """Detection ranges: report.md's section."""
    curves = o.curves
    L: list[str] = []
    L += [
        "## Detection ranges",
        "",
        f"Single frames ({plan.range_frames} per distance, random heading, lateral offset up "
        "to 8 % of the distance, tilt up to 5 deg); a marker counts when it gives a pose. "
        "z_max / z_min: the largest / smallest distance with probability >= 0.5.",
        "",
        "| images | outer z_max (paper z1 115) | inner z_max (paper z2 25) | outer z_min "
        "(paper z3 15) | inner z_min | estimate z_max | estimate z_min |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in curves:
        L.append(
            f"| {c.quality} | {_fmt(c.z_max_cm('outer'), 0)} | {_fmt(c.z_max_cm('inner'), 0)}"
            f" | {_fmt(c.z_min_cm('outer'), 0)} | {_fmt(c.z_min_cm('inner'), 0)} | "
            f"{_fmt(c.z_max_cm('fused'), 0)} | {_fmt(c.z_min_cm('fused'), 0)} |"
        )
    L += [
        "",
        "Distances are sampled at " + ", ".join(f"{d:g}" for d in plan.range_distances_cm) + " cm.",
        "",
        "![detection probability](ranges.png)",
        "",
    ]
    return L


def _md_tables(o: _Outcomes, plan: EvalPlan) -> list[str]:
    """Tables 1 and 2: report.md's section."""
    t1, t2 = o.t1, o.t2
    L: list[str] = []
    L += [
        "## Table 1: position (cm)",
        "",
        f"Each position held for {plan.table_frames} frames with the filter running; "
        "estimate = mean of the valid frames; p2p = peak-to-peak of the per-frame error; "
        "max = largest per-frame |error|.",
        "",
        "| actual | paper estimate | paper error | estimate | error | p2p | max | stages | "
        "markers in view |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r, p in zip(t1, ex.PAPER_TABLE1, strict=True):
        view = ", ".join(n for n, v in zip(("outer", "inner"), r.in_view, strict=False) if v)
        note = view or "none (out of the camera's view)"
        L.append(
            f"| {_triple(r.actual, 0)} | {p[1]} | {p[2]} | {_triple(r.estimated)} | "
            f"{_triple(r.error)} | {_triple(r.peak_to_peak)} | {_triple(r.max_abs_error)} | "
            f"{', '.join(map(str, r.stages)) or '-'} | {note} |"
        )
    L += [
        "",
        "## Table 2: heading (deg)",
        "",
        f"At ({', '.join(f'{v:g}' for v in ex.TABLE2_POSITION_CM)}) cm, {plan.table_frames} "
        "frames each.",
        "",
        "| actual | paper estimate | paper error | estimate | error | p2p | max |",
        "|---|---|---|---|---|---|---|",
    ]
    for r, q in zip(t2, ex.PAPER_TABLE2, strict=True):
        L.append(
            f"| {r.actual[3]:.0f} | {q[1]} | {q[2]} | {_fmt(r.estimated[3])} | "
            f"{_fmt(r.error[3])} | {_fmt(r.peak_to_peak[3])} | {_fmt(r.max_abs_error[3])} |"
        )
    return L


def _md_dropout(o: _Outcomes, plan: EvalPlan) -> list[str]:
    """The Kalman filter across a dropout: report.md's section."""
    drop = o.drop
    L: list[str] = []
    L += [
        "",
        "## Kalman filter across a dropout",
        "",
        f"A {plan.moves_s:g} s sequence moving between positions 35-60 cm from the target, "
        f"with no marker visible for {plan.dropout_s:g} s from t = {plan.dropout_at_s:g} s.",
        "",
        f"- dropout frames: {drop.dropout_frames}; frames bridged by the filter: "
        f"{drop.frames_coasted} (the paper's n_max = 8)",
        f"- largest position error while bridging: {_fmt(drop.max_position_error_cm)} cm "
        f"(in the second before the dropout: {_fmt(drop.max_position_error_before_cm)} cm); "
        f"largest yaw error: {_fmt(drop.max_yaw_error_deg)} deg",
        f"- marker measurements on the wrong IPPE solution over the whole sequence: "
        f"{drop.wrong_branch}",
        "",
        "![Kalman filter](kalman.png)",
        "",
    ]
    return L


def _md_fusion(o: _Outcomes, plan: EvalPlan) -> list[str]:
    """The fusion coefficients: report.md's section."""
    fit = o.fit
    L: list[str] = []
    L += ["## Fusion coefficients", ""]
    if fit is None:
        L += ["Too few frames had both markers measured to fit the coefficients.", ""]
    else:
        L += [
            f"{plan.fusion_positions} random positions (15-60 cm, random heading) x "
            f"{plan.fusion_frames} frames; {fit.samples} frames had both markers measured. "
            "Closed-form least squares against the paper's iterative LMS:",
            "",
            "| | least squares | LMS | LMS passes | paper |",
            "|---|---|---|---|---|",
        ]
        for n in ex.COMPONENT_NAMES:
            L.append(
                f"| {n} | {fit.least_squares[n]:.3f} | {fit.lms[n]:.3f} | "
                f"{fit.lms_passes[n]} | {ex.PAPER_SIGMAS[n]:.3f} |"
            )
        L += [
            "",
            "A sigma is the weight of the outer marker; the fit depends on the camera, the "
            "image quality and the distances sampled. "
            + (
                "Here the outer marker is measured better, and the fit leans towards it."
                if float(np.mean(list(fit.least_squares.values()))) > 0.5
                else "Here the inner marker is measured better, and the fit leans towards it."
            )
            + " A sigma above 1 means both markers err the same way and the inner one more.",
            "",
            "![fusion fit](fusion.png)",
            "",
        ]
    return L


def _md_ablations(o: _Outcomes, plan: EvalPlan) -> list[str]:
    """The ablations on an approach: report.md's section."""
    ablations = o.ablations
    L: list[str] = []
    L += [
        "## Ablations on an approach",
        "",
        f"The same {len(ablations[0].run.t_s)} rendered frames of an approach from "
        f"{ablations[0].run.truth[0, 2]:.0f} cm to contact for each variant; errors over the "
        "frames where a marker is in view; coverage = share of those frames with an estimate.",
        "",
        "| variant | coverage | position median (cm) | position p95 (cm) | position p95 "
        "(% of distance) | yaw median (deg) | yaw p95 (deg) | largest jump (cm) | largest "
        "jump as a marker enters or leaves (cm) | wrong IPPE branch |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for a in ablations:
        L.append(
            f"| {a.name} | {a.coverage:.2f} | {_fmt(a.median_position_error_cm)} | "
            f"{_fmt(a.p95_position_error_cm)} | {_fmt(a.p95_relative_error_pct)} | "
            f"{_fmt(a.median_yaw_error_deg)} | {_fmt(a.p95_yaw_error_deg)} | "
            f"{_fmt(a.max_jump_cm)} | {_fmt(a.handover_jump_cm)} | {a.flips} |"
        )
    L += ["", "![error against distance](ablation.png)", ""]
    return L


def _markdown(
    results: dict[str, Any],
    cam: CameraModel,
    quality_name: str,
    o: _Outcomes,
    plan: EvalPlan,
    elapsed: float,
) -> str:
    L: list[str] = []
    cfg = results["config"]
    L += ["# perchpose: the paper's experiments on rendered frames", ""]
    L += [
        f"Camera `{cam.name}`: {cam.width_px}x{cam.height_px}, model `{cam.model}`, "
        f"fx {cam.K[0, 0]:.1f} px, fy {cam.K[1, 1]:.1f} px, cx {cam.K[0, 2]:.1f}, "
        f"cy {cam.K[1, 2]:.1f}, distortion {np.round(cam.dist, 5).tolist()}.",
        f"Images for the tables, the dropout, the fusion fit and the ablations: `{quality_name}` "
        f"({', '.join(f'{k} {v}' for k, v in cfg['quality_settings'].items())}).",
        f"Target: the paper's (DICT_4X4_1000 id 997, 150 mm; DICT_ARUCO_ORIGINAL id 5, 25 mm). "
        f"Seed {cfg['seed']} (per experiment: {cfg['seeds']}); "
        f"{'quick' if cfg['quick'] else 'full'} "
        f"run, {cfg['renders']} rendered frames, {elapsed:.0f} s. The same seed gives the same "
        "numbers.",
        "",
    ]
    for section in (_md_ranges, _md_tables, _md_dropout, _md_fusion, _md_ablations):
        L += section(o, plan)
    return "\n".join(L)
