"""What a frame costs (the ``perchpose bench`` command): perchpose's pipeline against OpenCV's
``detectMarkers`` and the paper's pipeline on the same frames, in the same run, on one thread.

Each method runs over every frame, the methods taking turns frame by frame (in a rotating
order, so none always runs on a warm cache); the whole sequence is run ``repeat`` times with
fresh methods, and each frame's time is the least of its repeats (what the frame costs, without
the machine's hiccups). Times are wall-clock from the frame in memory to the method's answer:
the latency a caller sees. Ratios divide a method's percentile by the baseline's same
percentile; the worst frame is the largest of a frame's time over the baseline's time on that
frame.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from perchpose.app.inputs import load_camera, load_target
from perchpose.app.startup import StartupTime, measure_startup
from perchpose.camera import CameraModel
from perchpose.errors import PerchposeError, SourceError
from perchpose.estimator import PerchingEstimator
from perchpose.geometry import wrap_angle_deg, yaw_rad
from perchpose.io.sources import open_source
from perchpose.sim.render import ImageQuality
from perchpose.sim.scenarios import approach, markers_in_view
from perchpose.sim.sequence import rendered_frames as rendered_sequence
from perchpose.target import TargetSpec, aruco_dictionary
from perchpose.values import Estimate, Timings
from perchpose.warmup import warm_up

if TYPE_CHECKING:
    from matplotlib.figure import Figure

Array = NDArray[np.float64]

BASELINE = "opencv"
PERCENTILES = (50, 95, 99, 100)
# how many of its slowest frames (against the baseline) the report names per method
WORST_FRAMES = 5
# a tracking method's frame over this many times its median is a stall, unless it searched the
# whole frame because the frame before it measured nothing (the first frame, after a loss)
STALL_OVER_MEDIAN = 3.0


@dataclass(frozen=True)
class BenchFrames:
    """Grey frames to time, their capture times and, for rendered frames, the true pose of
    the target in each (None where unknown) and whether any marker is in view."""

    description: str
    images: list[NDArray[np.uint8]]
    t_s: list[float]
    truth: list[Array | None]
    in_view: list[bool]


def rendered_frames(
    camera: CameraModel,
    target: TargetSpec,
    frames: int = 240,
    quality: ImageQuality | None = None,
    seed: int = 0,
    progress: bool = False,
) -> BenchFrames:
    """An approach from 150 cm to contact at 30 fps (the demo's, with its two dropouts),
    rendered through ``camera``."""
    if frames < 2:
        raise PerchposeError(f"--frames must be at least 2, got {frames}")
    scenario = approach(duration_s=frames / 30.0, quality=quality)
    images, truth, in_view = [], [], []
    for i, image in rendered_sequence(scenario, camera, target, seed, progress):
        images.append(camera.check_image(image))
        T = scenario.poses[i]
        truth.append(T)
        in_view.append(not scenario.dropout[i] and any(markers_in_view(camera, target, T)))
    return BenchFrames(
        f"rendered approach, {len(images)} frames, camera '{camera.name}'",
        images,
        [float(t) for t in scenario.t_s],
        truth,
        in_view,
    )


def source_frames(source: str, camera: CameraModel, max_frames: int | None = None) -> BenchFrames:
    """Up to ``max_frames`` readable frames of a folder, glob, video or camera, read into
    memory first (reading and decoding are not timed)."""
    frames = open_source(source, None, camera.size)
    images: list[NDArray[np.uint8]] = []
    t_s: list[float] = []
    for frame in frames:
        if max_frames is not None and len(images) >= max_frames:
            break
        if frame.image is None:
            continue
        images.append(camera.check_image(frame.image))
        t_s.append(frame.t_s)
    if not images:
        raise SourceError(f"{source}: no readable frame to time")
    unknown: list[Array | None] = [None] * len(images)
    return BenchFrames(
        f"{frames.description}, {len(images)} frames", images, t_s, unknown, [True] * len(images)
    )


class _OpenCV:
    """OpenCV's ``ArucoDetector.detectMarkers`` with the dictionary of the target's first
    marker (all of it) and its SUBPIX corners: the baseline."""

    description = "OpenCV detectMarkers, one dictionary, SUBPIX corners"

    def __init__(self, target: TargetSpec) -> None:
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        dictionary = aruco_dictionary(target.markers[0].dictionary)
        self.detector = cv2.aruco.ArucoDetector(dictionary, params)

    def __call__(self, grey: NDArray[np.uint8], t_s: float) -> Estimate | None:
        self.detector.detectMarkers(grey)
        return None

    def warm(self, grey: NDArray[np.uint8]) -> None:
        self.detector.detectMarkers(grey)


class _Pipeline:
    """A ``PerchingEstimator``; ``cold`` forgets every frame before the next (no tracking)."""

    def __init__(self, description: str, estimator: PerchingEstimator, cold: bool) -> None:
        self.description = description
        self.estimator = estimator
        self.cold = cold

    def __call__(self, grey: NDArray[np.uint8], t_s: float) -> Estimate | None:
        if self.cold:
            self.estimator.reset()
        return self.estimator.update(grey, t_s)

    def warm(self, grey: NDArray[np.uint8]) -> None:
        """Build what is built once per camera (rectification maps, tables), then forget."""
        self.estimator.update(grey, 0.0)
        self.estimator.reset()


Method = _OpenCV | _Pipeline


def default_methods(
    camera: CameraModel, target: TargetSpec, budget_ms: float | None = None
) -> dict[str, Method]:
    """The baseline, perchpose tracking and cold, the paper's pipeline, and with
    ``budget_ms`` perchpose tracking under that budget."""
    methods: dict[str, Method] = {
        BASELINE: _OpenCV(target),
        "perchpose": _Pipeline(
            "perchpose default (tracking from the previous frame)",
            PerchingEstimator(camera, target),
            cold=False,
        ),
        "perchpose-cold": _Pipeline(
            "perchpose default, every frame searched whole (no previous frame)",
            PerchingEstimator(camera, target),
            cold=True,
        ),
        "paper": _Pipeline(
            "the paper's pipeline (fusion paper, corners subpix)",
            PerchingEstimator(camera, target, fusion="paper", corners="subpix"),
            cold=False,
        ),
    }
    if budget_ms is not None:
        methods["perchpose-budget"] = _Pipeline(
            f"perchpose default within a {budget_ms:g} ms budget per frame",
            PerchingEstimator(camera, target, budget_ms=budget_ms),
            cold=False,
        )
    return methods


@dataclass(frozen=True)
class MethodResult:
    """One method's per-frame times (ms, the least of the repeats), the estimates of its last
    repeat, and its description."""

    name: str
    description: str
    ms: Array
    estimates: list[Estimate | None]


@dataclass(frozen=True)
class FrameErrors:
    """One method's error against the rendered truth on each frame: the position's as a
    percentage of the distance and the yaw's (deg), NaN where the frame has no truth, no
    marker in view or no pose; ``without_pose``: a marker in view and no pose."""

    position_pct: Array
    yaw_deg: Array
    without_pose: NDArray[np.bool_]


@dataclass(frozen=True)
class BenchReport:
    """What ``bench`` measured. ``stages_ms``: the default pipeline's per-frame time in each
    stage (``Timings.STAGES``), the least of the repeats; ``warm_up_s``: building or loading
    the compiled kernels before the first frame, as a live ``track`` does; ``startup``: a fresh
    process's time to its first pose, cold and warm (``--startup``)."""

    frames: BenchFrames
    repeat: int
    methods: dict[str, MethodResult]
    stages_ms: dict[str, Array] = field(repr=False)
    warm_up_s: float = math.nan
    startup: tuple[StartupTime, ...] = ()

    def percentiles(self, name: str) -> dict[str, float]:
        ms = self.methods[name].ms
        return {_label(q): float(np.percentile(ms, q)) for q in PERCENTILES}

    def ratios(self, name: str) -> dict[str, float]:
        """The method's median, p99 and max over the baseline's, and its worst frame."""
        mine, base = self.methods[name].ms, self.methods[BASELINE].ms
        out = {
            _label(q): float(np.percentile(mine, q) / np.percentile(base, q)) for q in (50, 99, 100)
        }
        out["worst_frame"] = float(np.max(mine / base))
        return out

    def worst_frames(self, name: str, count: int = WORST_FRAMES) -> list[dict[str, float]]:
        """The ``count`` frames on which the method took longest over the baseline, worst
        first: each frame's index, its time (ms) and that ratio."""
        mine, base = self.methods[name].ms, self.methods[BASELINE].ms
        ratio = mine / base
        order = np.argsort(-ratio, kind="stable")[:count]
        return [{"frame": int(k), "ms": float(mine[k]), "ratio": float(ratio[k])} for k in order]

    def slow_frames(self, name: str) -> dict[str, Any]:
        """The method's frames over ``STALL_OVER_MEDIAN`` times its median: ``after_loss``
        those whose previous frame found no marker (the first frame, a dropout's end: nothing
        to track, so the whole frame is searched), ``stalls`` the others (each frame's index
        and ms)."""
        result = self.methods[name]
        limit_ms = STALL_OVER_MEDIAN * float(np.median(result.ms))
        after_loss: list[dict[str, float]] = []
        stalls: list[dict[str, float]] = []
        for k in np.nonzero(result.ms > limit_ms)[0]:
            before = result.estimates[k - 1] if k > 0 else None
            lost = before is None or all(m.detection is None for m in before.markers)
            frame = {"frame": int(k), "ms": float(result.ms[k])}
            (after_loss if lost else stalls).append(frame)
        return {"limit_ms": limit_ms, "after_loss": after_loss, "stalls": stalls}

    def errors(self, name: str) -> FrameErrors | None:
        """Each frame's error against the rendered truth (``FrameErrors``); None for the
        baseline or frames without truth."""
        result = self.methods[name]
        if name == BASELINE or all(T is None for T in self.frames.truth):
            return None
        n = len(self.frames.images)
        position_pct, yaw_deg = np.full(n, math.nan), np.full(n, math.nan)
        without_pose = np.zeros(n, dtype=bool)
        for k, (estimate, T, seen) in enumerate(
            zip(result.estimates, self.frames.truth, self.frames.in_view, strict=True)
        ):
            if T is None or estimate is None or not seen:
                continue  # a pose coasted through a dropout is the filter's guess
            if not estimate.valid:
                without_pose[k] = True
                continue
            distance = float(np.linalg.norm(T[:3, 3]))
            error = float(np.linalg.norm(estimate.t_m - T[:3, 3]))
            position_pct[k] = 100.0 * error / distance
            yaw_deg[k] = abs(wrap_angle_deg(estimate.yaw_deg - math.degrees(yaw_rad(T[:3, :3]))))
        return FrameErrors(position_pct, yaw_deg, without_pose)

    def accuracy(self, name: str) -> dict[str, float] | None:
        """Against the rendered truth, on the frames with a marker in view: those without a
        pose, the largest position error as a percentage of the distance, and the largest yaw
        error (deg); None for the baseline or frames without truth."""
        errors = self.errors(name)
        if errors is None:
            return None
        position_pct = [float(v) for v in errors.position_pct if math.isfinite(v)]
        yaw_deg = [float(v) for v in errors.yaw_deg if math.isfinite(v)]
        return {
            "in_view_without_pose": float(np.count_nonzero(errors.without_pose)),
            "max_position_error_pct": max(position_pct, default=math.nan),
            "p95_position_error_pct": _p95(position_pct),
            "max_yaw_error_deg": max(yaw_deg, default=math.nan),
            "p95_yaw_error_deg": _p95(yaw_deg),
        }

    def to_json(self) -> dict[str, Any]:
        """The report as plain JSON values."""
        methods: dict[str, Any] = {}
        for name, result in self.methods.items():
            entry: dict[str, Any] = {
                "description": result.description,
                "ms": self.percentiles(name),
                "mean_ms": float(np.mean(result.ms)),
                "ms_per_frame": [float(v) for v in result.ms],
            }
            if name != BASELINE:
                entry["ratio_to_opencv"] = self.ratios(name)
                entry["worst_frames"] = self.worst_frames(name)
                if name.startswith("perchpose") and not name.endswith("-cold"):
                    entry["over_3x_median"] = self.slow_frames(name)
                entry["frames_with_pose"] = sum(
                    1 for e in result.estimates if e is not None and e.valid
                )
                entry["frames_over_budget"] = sum(
                    1 for e in result.estimates if e is not None and e.skipped
                )
                accuracy = self.accuracy(name)
                if accuracy is not None:
                    entry["accuracy"] = accuracy
            methods[name] = entry
        startup = {("cold" if t.cold else "warm"): t.to_json() for t in self.startup}
        return {
            "source": self.frames.description,
            "frames": len(self.frames.images),
            "repeat": self.repeat,
            "threads": 1,
            "baseline": BASELINE,
            "times": "wall-clock ms from the frame in memory to the answer, least of the repeats",
            "warm_up_s": self.warm_up_s,
            "startup": startup,
            "methods": methods,
            "stages_ms": {
                stage: {_label(q): float(np.percentile(ms, q)) for q in PERCENTILES}
                for stage, ms in self.stages_ms.items()
                if np.all(np.isfinite(ms))
            },
        }


def _label(q: int) -> str:
    return "max" if q == 100 else f"p{q}"


def _p95(values: list[float]) -> float:
    return float(np.percentile(values, 95)) if values else math.nan


@contextmanager
def _one_thread() -> Iterator[None]:
    previous = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(previous)


def bench(
    frames: BenchFrames,
    camera: CameraModel,
    target: TargetSpec,
    repeat: int = 3,
    progress: bool = False,
    methods: Callable[[CameraModel, TargetSpec], dict[str, Method]] = default_methods,
) -> BenchReport:
    """Time every method on every frame of ``frames``, ``repeat`` times, on one thread;
    ``methods`` builds them afresh for each repeat (``default_methods``)."""
    if repeat < 1:
        raise PerchposeError(f"--repeat must be at least 1, got {repeat}")
    n = len(frames.images)
    names = list(methods(camera, target))
    # as a live track: the kernels built (or loaded) before the first frame, not in it
    warm_up_s = warm_up(target, [camera]).seconds
    best = {name: np.full(n, np.inf) for name in names}
    stages = {stage: np.full(n, np.inf) for stage in Timings.STAGES}
    last: dict[str, list[Estimate | None]] = {}
    descriptions: dict[str, str] = {}
    bar = tqdm(total=repeat * n, desc="bench", unit="frame", disable=not progress, file=sys.stderr)
    with _one_thread(), bar:
        for _ in range(repeat):
            fresh = methods(camera, target)
            for method in fresh.values():  # what is built once per camera is not timed
                method.warm(frames.images[0])
            descriptions = {name: m.description for name, m in fresh.items()}
            last = {name: [] for name in names}
            for k, (grey, t_s) in enumerate(zip(frames.images, frames.t_s, strict=True)):
                turn = names[k % len(names) :] + names[: k % len(names)]
                for name in turn:
                    t0 = time.perf_counter()
                    estimate = fresh[name](grey, t_s)
                    spent_ms = (time.perf_counter() - t0) * 1e3
                    best[name][k] = min(best[name][k], spent_ms)
                    last[name].append(estimate)
                    if name == "perchpose" and estimate is not None:
                        for stage in Timings.STAGES:
                            stages[stage][k] = min(
                                stages[stage][k], estimate.timings.stage_ms(stage)
                            )
                bar.update(1)
    return BenchReport(
        frames,
        repeat,
        {name: MethodResult(name, descriptions[name], best[name], last[name]) for name in names},
        stages,
        warm_up_s,
    )


def format_report(report: BenchReport) -> str:
    """The report as text: a table of the methods, then the default pipeline's stages."""
    data = report.to_json()
    lines = [
        f"{data['source']}; one thread, least of {report.repeat} runs per frame "
        f"(kernels ready in {report.warm_up_s:.1f} s before the first)",
        "",
        f"{'method':16s} {'p50 ms':>8s} {'p95 ms':>8s} {'p99 ms':>8s} {'max ms':>8s} "
        f"{'p50 x':>7s} {'p99 x':>7s} {'worst x':>8s} {'poses':>6s}",
    ]
    for name, entry in data["methods"].items():
        ms = entry["ms"]
        ratio = entry.get("ratio_to_opencv", {})
        poses = entry.get("frames_with_pose")
        lines.append(
            f"{name:16s} {ms['p50']:8.2f} {ms['p95']:8.2f} {ms['p99']:8.2f} {ms['max']:8.2f} "
            + (
                f"{ratio['p50']:7.2f} {ratio['p99']:7.2f} {ratio['worst_frame']:8.2f} {poses:6d}"
                if ratio
                else f"{'1':>7s} {'1':>7s} {'1':>8s} {'-':>6s}"
            )
        )
    lines += ["", "x: the method's time over OpenCV's (same percentile; worst: per frame)"]
    for name, entry in data["methods"].items():
        if name.startswith("perchpose") and "worst_frames" in entry:
            worst = ", ".join(f"{w['frame']} ({w['ratio']:.1f}x)" for w in entry["worst_frames"])
            lines.append(f"  {name} worst frames: {worst}")
    for name, entry in data["methods"].items():
        if "over_3x_median" in entry:
            slow = entry["over_3x_median"]
            stalls = ", ".join(f"{f['frame']} ({f['ms']:.1f} ms)" for f in slow["stalls"])
            lines.append(
                f"  {name} over 3x its median ({slow['limit_ms']:.1f} ms): "
                f"{len(slow['after_loss'])} searches after a loss, "
                f"{len(slow['stalls'])} other" + (f": {stalls}" if stalls else "")
            )
    if "perchpose" in report.methods:
        lines += ["", f"perchpose by stage {'p50 ms':>10s} {'p95 ms':>8s} {'max ms':>8s}"]
        for stage, ms in data["stages_ms"].items():
            lines.append(f"  {stage:22s} {ms['p50']:8.2f} {ms['p95']:8.2f} {ms['max']:8.2f}")
    if report.startup:
        lines += ["", "from a fresh process's start to its first pose, as a live track starts:"]
        lines += [f"  {t.describe()}" for t in report.startup]
    accurate = {n: e["accuracy"] for n, e in data["methods"].items() if "accuracy" in e}
    if accurate:
        lines += [
            "",
            f"against the truth {'in view, no pose':>18s} {'position p95/max %':>20s} "
            f"{'yaw p95/max deg':>16s}",
        ]
        for name, a in accurate.items():
            lines.append(
                f"  {name:16s} {int(a['in_view_without_pose']):16d} "
                f"{a['p95_position_error_pct']:9.2f}/{a['max_position_error_pct']:<9.2f} "
                f"{a['p95_yaw_error_deg']:7.2f}/{a['max_yaw_error_deg']:<7.2f}"
            )
    return "\n".join(lines)


def write_figure(report: BenchReport, path: str) -> Figure:
    """The report frame by frame as a figure (``plots.bench_figure``; the format follows the
    suffix: .png, .svg or .pdf). matplotlib is imported here, not with the module: a run
    without a figure does not pay for it."""
    from perchpose.evaluation.plots import bench_figure

    errors: dict[str, tuple[Array, Array]] = {}
    for name in report.methods:
        frame_errors = report.errors(name)
        if frame_errors is not None:
            errors[name] = (frame_errors.position_pct, frame_errors.yaw_deg)
    out_of_view = ~np.asarray(report.frames.in_view, dtype=bool)
    ms = {name: result.ms for name, result in report.methods.items()}
    return bench_figure(path, ms, BASELINE, report.stages_ms, out_of_view, errors)


@dataclass(frozen=True)
class BenchOptions:
    """The frames (``source``: a folder, glob, video or camera, with its calibration in
    ``camera_file``; None: an approach rendered at ``quality`` with ``seed``), the target, how
    many frames and repeats, where to write the JSON and the figure (None: nowhere), and a
    time budget for perchpose (``perchpose-budget``; None: not timed)."""

    source: str | None = None
    camera_file: str = "preset:fpv"
    target_file: str | None = None
    frames: int = 240
    quality: str = "default"
    repeat: int = 3
    seed: int = 0
    json_out: str | None = None
    plot_out: str | None = None
    budget_ms: float | None = None
    progress: bool = False
    startup: bool = False


def run(options: BenchOptions) -> BenchReport:
    """Time the methods on the frames asked for; write the JSON and the figure where asked."""
    if options.source is not None and options.camera_file.startswith("preset:"):
        raise PerchposeError("a SOURCE needs its calibration: --camera camera.yaml")
    if options.plot_out is not None:
        from perchpose.printable import check_output_format

        check_output_format(Path(options.plot_out))  # before the run, not after it
    camera = load_camera(options.camera_file)
    target = load_target(options.target_file)
    if options.source is None:
        quality = ImageQuality.preset(options.quality)
        data = rendered_frames(
            camera, target, options.frames, quality, options.seed, options.progress
        )
    else:
        data = source_frames(options.source, camera, options.frames)
    budget = options.budget_ms
    report = bench(
        data,
        camera,
        target,
        options.repeat,
        options.progress,
        lambda cam, spec: default_methods(cam, spec, budget),
    )
    if options.startup:  # warm first: the run above filled the disk cache
        first = data.images[0]
        timed = tuple(measure_startup(camera, target, first, cold) for cold in (False, True))
        report = replace(report, startup=timed)
    if options.json_out is not None:
        path = Path(options.json_out)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(report.to_json(), indent=2) + "\n")
    if options.plot_out is not None:
        Path(options.plot_out).parent.mkdir(parents=True, exist_ok=True)
        write_figure(report, options.plot_out)
    return report
