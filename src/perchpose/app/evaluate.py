"""``perchpose evaluate``: the paper's experiments on rendered frames, with their report."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from perchpose.app.inputs import load_camera
from perchpose.evaluation.report import EvaluationResult

EXPERIMENTS = ("paper",)


@dataclass(frozen=True)
class EvaluateOptions:
    """The experiment set (``paper``), the output folder, the camera as the commands name it,
    the image quality preset, a reduced run for smoke tests, the base seed of every
    experiment, and whether to show a progress bar."""

    out: str
    experiment: str = "paper"
    camera_file: str = "preset:fpv"
    quality: str = "analog_fpv"
    quick: bool = False
    seed: int = 0
    progress: bool = False


def run(options: EvaluateOptions, say: Callable[[str], None] = print) -> EvaluationResult:
    """Run the experiments and write report.md, results.json and the figures."""
    from perchpose.evaluation.report import run_paper_evaluation

    assert options.experiment in EXPERIMENTS  # one experiment set so far; the CLI chooses
    return run_paper_evaluation(
        options.out,
        load_camera(options.camera_file),
        quick=options.quick,
        seed=options.seed,
        quality_name=options.quality,
        progress=options.progress,
        say=say,
    )
