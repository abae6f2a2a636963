"""The camera: ``CameraModel`` (intrinsics, lens distortion, projection and the calibration
files, in ``model``), the lens models in compiled code (``lens``, ``plumb_bob``)."""

from perchpose.camera.model import CameraModel, DistortionModel

__all__ = ["CameraModel", "DistortionModel"]
