"""The inputs every command names the same way: a camera (a calibration file, or
``preset:NAME``) and a target (a target file, or the paper's)."""

from __future__ import annotations

from perchpose.camera import CameraModel
from perchpose.target import TargetSpec


def load_camera(value: str) -> CameraModel:
    """A camera file, or ``preset:NAME``."""
    if value.startswith("preset:"):
        return CameraModel.preset(value.split(":", 1)[1])
    return CameraModel.load(value)


def load_target(value: str | None) -> TargetSpec:
    """A target file, or the paper's target."""
    return TargetSpec.paper() if value is None else TargetSpec.load(value)
