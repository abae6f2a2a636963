"""``perchpose simulate``: a rendered sequence with its camera and truth."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from perchpose.app.inputs import load_camera, load_target


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
class Simulated:
    """The folder written and its number of frames."""

    path: Path
    frames: int


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
