"""perchpose: the pose of a nested-marker perching target from one camera."""

from perchpose.camera import CameraModel
from perchpose.errors import PerchposeError
from perchpose.estimator import PerchingEstimator
from perchpose.target import MarkerSpec, TargetSpec
from perchpose.values import Estimate

__all__ = [
    "CameraModel",
    "Estimate",
    "MarkerSpec",
    "PerchingEstimator",
    "PerchposeError",
    "TargetSpec",
]
__version__ = "0.1.0"
