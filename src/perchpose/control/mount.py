"""Where the camera sits on the body: ``T_body_camera`` (body FLU: x forward, y left, z up;
camera: OpenCV optical frame), its default and its file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray

from perchpose.errors import ControllerConfigError, PerchposeError
from perchpose.geometry import check_transform, make_transform

Array = NDArray[np.float64]


def default_T_body_camera() -> Array:
    """Camera on top of the body looking up, its axes parallel to the body's (image x along the
    body's front, optical axis up), 15 mm ahead of and 12 mm above the body centre. With it, the
    estimate's yaw is the heading error between the body and the target."""
    return make_transform(np.eye(3), np.array([0.015, 0.0, 0.012]))


def load_T_body_camera(path: str | Path) -> Array:
    """``T_body_camera`` from a YAML file holding a 4x4 matrix under that key (body FLU: x
    forward, y left, z up; camera: OpenCV optical frame)."""
    where = Path(path)
    try:
        data = yaml.safe_load(where.read_text())
    except OSError as exc:
        raise ControllerConfigError(f"{where}: cannot read ({exc.strerror})") from exc
    except yaml.YAMLError as exc:
        raise ControllerConfigError(f"{where}: not YAML ({exc})") from exc
    if not isinstance(data, dict) or "T_body_camera" not in data:
        raise ControllerConfigError(f"{where}: no T_body_camera (a 4x4 matrix, metres)")
    try:
        return check_transform(np.asarray(data["T_body_camera"], dtype=float), "T_body_camera")
    except (ValueError, TypeError, PerchposeError) as exc:
        raise ControllerConfigError(f"{where}: T_body_camera: {exc}") from exc
