"""Writing a rendered scenario to disk: frames, camera.yaml and truth.csv."""

from __future__ import annotations

import csv
import math
import sys
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from perchpose.calibration import CharucoBoardSpec
from perchpose.camera import CameraModel
from perchpose.errors import PerchposeError
from perchpose.fusion.base import stage_of
from perchpose.geometry import yaw_rad
from perchpose.sim.render import ImageQuality, Occluder, Renderer
from perchpose.sim.scenarios import Scenario, markers_in_view, spread_board_poses
from perchpose.target import TargetSpec
from perchpose.values import POSE_COLUMNS

Array = np.ndarray


def truth_columns(target: TargetSpec) -> tuple[str, ...]:
    """Columns of truth.csv: the track columns, then ``dropout`` and ``m{i}_in_view``."""
    return (*POSE_COLUMNS, "dropout", *(f"m{i}_in_view" for i in range(len(target.markers))))


def dropout_occluder(camera: CameraModel, target: TargetSpec, T: Array) -> Occluder:
    """A dark shape hiding the whole printed sheet (or the whole image if the sheet is not fully
    in front of the camera)."""
    half = target.sheet_half_extent_m * 1.2
    ring = np.array(
        [
            [half * math.cos(a), half * math.sin(a), 0.0]
            for a in np.linspace(0, 2 * math.pi, 48, endpoint=False)
        ]
    )
    p = (T[:3, :3] @ ring.T).T + T[:3, 3]
    uv, ok = camera.project(p)
    w, h = camera.size
    if not np.all(ok):
        return Occluder(np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64))
    hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    return Occluder(hull)


def render_frame(
    renderer: Renderer[TargetSpec], scenario: Scenario, i: int, rng: np.random.Generator
) -> np.ndarray:
    """Frame ``i`` of ``scenario``: rendered at its pose, hidden if it is a dropout frame."""
    T = scenario.poses[i]
    occluders: tuple[Occluder, ...] = ()
    if scenario.dropout[i]:
        occluders = (dropout_occluder(renderer.camera, renderer.target, T),)
    return renderer.render(T, scenario.quality, rng, occluders)


def rendered_frames(
    scenario: Scenario,
    camera: CameraModel,
    target: TargetSpec,
    seed: int = 0,
    progress: bool = False,
) -> Iterator[tuple[int, NDArray[np.uint8]]]:
    """Each frame of ``scenario`` rendered (``render_frame``), in order, from one generator
    seeded with ``seed``; a progress bar on stderr with ``progress``."""
    renderer = Renderer(camera, target)
    rng = np.random.default_rng(seed)
    for i in tqdm(
        range(len(scenario)),
        desc="render",
        unit="frame",
        disable=not progress,
        file=sys.stderr,
        leave=False,
    ):
        yield i, render_frame(renderer, scenario, i, rng)


def truth_row(
    camera: CameraModel, target: TargetSpec, scenario: Scenario, i: int
) -> dict[str, object]:
    """The truth.csv row of frame ``i``."""
    T = scenario.poses[i]
    in_view = markers_in_view(camera, target, T)
    seen = set() if scenario.dropout[i] else {k for k, v in enumerate(in_view) if v}
    stage = stage_of(seen)
    row: dict[str, object] = {
        "frame": i,
        "t_s": f"{scenario.t_s[i]:.6f}",
        "valid": int(stage > 0),
        "stage": stage,
        "x_cm": f"{T[0, 3] * 100:.4f}",
        "y_cm": f"{T[1, 3] * 100:.4f}",
        "z_cm": f"{T[2, 3] * 100:.4f}",
        "yaw_deg": f"{math.degrees(yaw_rad(T[:3, :3])):.3f}",
        "dropout": int(scenario.dropout[i]),
    }
    for k, v in enumerate(in_view):
        row[f"m{k}_in_view"] = int(v)
    return row


def write_board_views(
    board: CharucoBoardSpec,
    camera: CameraModel,
    out_dir: str | Path,
    views: int,
    quality: ImageQuality,
    seed: int = 0,
) -> Path:
    """Render ``views`` views of a ChArUco ``board`` as a person waves one in front of the
    camera (``scenarios.spread_board_poses``: anywhere in the image, turned and tilted) into
    ``out_dir``: ``view_00.png`` ... and the true ``camera.yaml`` that a calibration of them
    should find. Returns the folder."""
    out = _folder(out_dir)
    rng = np.random.default_rng(seed)
    renderer = Renderer(camera, board)
    poses = spread_board_poses(camera, board.size_m[0], views, rng)
    for k, T in enumerate(poses):
        name = out / f"view_{k:02d}.png"
        if not cv2.imwrite(str(name), renderer.render(T, quality, rng)):
            raise PerchposeError(f"{name}: cannot write image")
    camera.save(out / "camera.yaml")
    return out


def _folder(out_dir: str | Path) -> Path:
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PerchposeError(f"{out}: cannot create folder ({exc.strerror})") from exc
    return out


def write_sequence(
    scenario: Scenario,
    camera: CameraModel,
    target: TargetSpec,
    out_dir: str | Path,
    seed: int = 0,
    progress: bool = True,
    image_format: str = "png",
) -> Path:
    """Render ``scenario`` into ``out_dir``: ``frame_000000.png`` ..., ``camera.yaml``,
    ``target.yaml`` and ``truth.csv``. Returns the folder."""
    out = _folder(out_dir)
    camera.save(out / "camera.yaml")
    target.save(out / "target.yaml")
    with (out / "truth.csv").open("w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=list(truth_columns(target)))
        writer.writeheader()
        for i, image in rendered_frames(scenario, camera, target, seed, progress):
            name = out / f"frame_{i:06d}.{image_format}"
            if not cv2.imwrite(str(name), image):
                raise PerchposeError(f"{name}: cannot write image")
            writer.writerow(truth_row(camera, target, scenario, i))
    return out
