"""Where the camera sits on the body: ``T_body_camera`` (body FLU: x forward, y left, z up;
camera: OpenCV optical frame), its default and its file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray

from perchpose import safe_yaml
from perchpose.errors import ControllerConfigError, PerchposeError
from perchpose.geometry import check_transform, make_transform

Array = NDArray[np.float64]


def default_T_body_camera() -> Array:
    """Camera on top of the body looking up, its axes parallel to the body's (image x along the
    body's front, optical axis up), 15 mm ahead of and 12 mm above the body centre. With it, the
    estimate's yaw is the heading error between the body and the target."""
    return make_transform(np.eye(3), np.array([0.015, 0.0, 0.012]))


def downward_T_body_camera() -> Array:
    """Camera under the body looking down, as autopilots' precision landing expects: the
    optical axis along the body's -z, the image's top toward the body's front (image x to the
    body's right, image y to its back), 15 mm ahead of and 12 mm below the body centre."""
    R = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    return make_transform(R, np.array([0.015, 0.0, -0.012]))


MOUNT_PRESETS = {"up": default_T_body_camera, "down": downward_T_body_camera}


def mount_T_body_camera(value: str) -> Array:
    """``T_body_camera`` of a preset (``up``: the default, on top looking up, for perching;
    ``down``: under the body looking down, for landing) or of a YAML file
    (``load_T_body_camera``)."""
    preset = MOUNT_PRESETS.get(value)
    return preset() if preset is not None else load_T_body_camera(value)


def load_T_body_camera(path: str | Path) -> Array:
    """``T_body_camera`` from a YAML file holding a 4x4 matrix under that key (body FLU: x
    forward, y left, z up; camera: OpenCV optical frame)."""
    where = Path(path)
    try:
        data = safe_yaml.load(where.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ControllerConfigError(f"{where}: cannot read ({exc.strerror})") from exc
    except UnicodeDecodeError as exc:
        raise ControllerConfigError(f"{where}: not a text file (a YAML mount)") from exc
    except yaml.YAMLError as exc:
        raise ControllerConfigError(f"{where}: not YAML ({exc})") from exc
    if not isinstance(data, dict) or "T_body_camera" not in data:
        raise ControllerConfigError(f"{where}: no T_body_camera (a 4x4 matrix, metres)")
    try:
        return check_transform(np.asarray(data["T_body_camera"], dtype=float), "T_body_camera")
    except (ValueError, TypeError, PerchposeError) as exc:
        raise ControllerConfigError(f"{where}: T_body_camera: {exc}") from exc


def require_upward(T_body_camera: Array, flag: str) -> None:
    """The perching pilot flies up onto a target above it: refuse a camera whose optical axis
    does not point up (a downward camera would make it climb away from a target below)."""
    up_component = float(T_body_camera[2, 2])  # the optical axis's body-z component
    if not up_component > 0.0:
        raise ControllerConfigError(
            f"{flag} perches on a target above the vehicle, so the camera must look up "
            f"(--mount up, or a T_body_camera whose optical axis points up); this mount's axis "
            f"points {'down' if up_component < 0 else 'sideways'}"
        )
