"""``perchpose simulate``: a rendered sequence with its camera and truth."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from perchpose.app.inputs import load_camera, load_target
from perchpose.calibration import CharucoBoardSpec
from perchpose.errors import PerchposeError


@dataclass(frozen=True)
class SimulateOptions:
    """The scenario (``approach`` or ``static``), the output folder, the camera and target
    as the commands name them, the image quality preset, the noise seed and the most frames
    to keep (None: all)."""

    scenario: str
    out: str
    camera_file: str = "preset:fpv"
    target_file: str | None = None
    quality: str = "default"
    seed: int = 0
    max_frames: int | None = None
    progress: bool = False


@dataclass(frozen=True)
class BoardViewsOptions:
    """Views of a ChArUco ``board`` to try ``perchpose calibrate`` on: the output folder, the
    camera as the commands name it, how many views, the image quality preset and the seed."""

    out: str
    board: CharucoBoardSpec
    camera_file: str = "preset:fpv"
    views: int = 20
    quality: str = "default"
    seed: int = 0


MAX_BOARD_VIEWS = 500


@dataclass(frozen=True)
class Simulated:
    """The folder written and its number of frames."""

    path: Path
    frames: int
    lens: str = ""  # the camera's model, for the calibration of a board's views


def run_board(options: BoardViewsOptions) -> Simulated:
    """Render the board's views and the true camera file."""
    from perchpose.sim.render import ImageQuality
    from perchpose.sim.sequence import write_board_views

    if not 1 <= options.views <= MAX_BOARD_VIEWS:
        raise PerchposeError(f"--views must be 1 to {MAX_BOARD_VIEWS}, got {options.views}")
    camera = load_camera(options.camera_file)
    path = write_board_views(
        options.board,
        camera,
        options.out,
        options.views,
        ImageQuality.preset(options.quality),
        options.seed,
    )
    return Simulated(Path(path), options.views, camera.model)


def run(options: SimulateOptions) -> Simulated:
    """Render the scenario to frames, camera.yaml and truth.csv."""
    from perchpose.sim.render import ImageQuality
    from perchpose.sim.scenarios import scenario_by_name, truncated
    from perchpose.sim.sequence import write_sequence

    camera = load_camera(options.camera_file)
    spec = load_target(options.target_file)
    scenario = scenario_by_name(options.scenario, ImageQuality.preset(options.quality))
    if options.max_frames is not None:
        scenario = truncated(scenario, options.max_frames)
    path = write_sequence(
        scenario, camera, spec, options.out, seed=options.seed, progress=options.progress
    )
    return Simulated(Path(path), len(scenario))
