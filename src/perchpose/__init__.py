"""perchpose: the pose of a nested-marker perching target from one camera.

The names below load on first use, so a vehicle link or the controller imports without OpenCV
or the vision pipeline."""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from perchpose.camera import CameraModel
    from perchpose.errors import PerchposeError
    from perchpose.estimator import PerchingEstimator
    from perchpose.target import MarkerSpec, TargetSpec
    from perchpose.values import Estimate

_WHERE = {
    "CameraModel": "perchpose.camera",
    "Estimate": "perchpose.values",
    "MarkerSpec": "perchpose.target",
    "PerchingEstimator": "perchpose.estimator",
    "PerchposeError": "perchpose.errors",
    "TargetSpec": "perchpose.target",
}

__all__ = [
    "CameraModel",
    "Estimate",
    "MarkerSpec",
    "PerchingEstimator",
    "PerchposeError",
    "TargetSpec",
]
__version__ = "0.1.0"


def __getattr__(name: str) -> object:
    where = _WHERE.get(name)
    if where is None:
        raise AttributeError(f"module 'perchpose' has no attribute {name!r}")
    value = getattr(import_module(where), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_WHERE])
