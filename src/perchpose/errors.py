"""The package's exception hierarchy.

The library raises these; only the command line turns them into one-line messages and exit codes.
"""

from __future__ import annotations

import math
from collections.abc import Iterable


class PerchposeError(Exception):
    """Base class of every error perchpose raises for a user's input or configuration."""


class CameraFileError(PerchposeError):
    """A camera calibration file is missing, unparsable or lacks a field."""


class TargetSpecError(PerchposeError):
    """A target specification is missing, unparsable or geometrically invalid."""


class ImageError(PerchposeError):
    """An image cannot be read, or does not match the camera it is used with."""


class SourceError(PerchposeError):
    """A frame source (folder, glob, video, camera) cannot be opened or is empty."""


class DisplayError(PerchposeError):
    """A window cannot be shown (no display, or an OpenCV built without one)."""


class TimestampError(PerchposeError):
    """A frame timestamp is not finite or goes backwards."""


class ScenarioError(PerchposeError):
    """A simulation scenario name or setting is unknown or invalid."""


class LinkError(PerchposeError):
    """A vehicle link (MAVLink, Crazyflie) cannot be set up: a missing optional dependency, a
    malformed connection string, or a frame the link cannot serve."""


class FusionFileError(PerchposeError):
    """A fusion weights file (``fit-fusion --json``) that cannot be read or holds weights the
    paper's fusion cannot use."""


class ControllerConfigError(PerchposeError):
    """Controller or pilot settings that cannot work (negative limits, an unstable loop), or a
    mounting file that cannot be read."""


class CampaignError(PerchposeError):
    """A campaign that cannot start or go on: a resume file from another setup, a scheduler
    that does not answer."""


class CalibrationError(PerchposeError):
    """A calibration that cannot be made from the given images or board."""


class SolverFailedError(CalibrationError):
    """OpenCV's solver stopped on this set of views (an ill-conditioned view)."""


class SensingConfigError(PerchposeError):
    """Sensing settings outside their meaning (a negative spread, a range upside down)."""


class WindConfigError(PerchposeError):
    """A wind level, speed or turbulence intensity that cannot be flown."""


class SchedulerError(PerchposeError):
    """A Dask scheduler that cannot be reached or used."""


class VehicleConfigError(PerchposeError):
    """Physically impossible or unstable vehicle or controller settings."""


class DisturbanceConfigError(PerchposeError):
    """Disturbance settings outside their meaning (a negative spread, a probability over 1)."""


def require_positive(
    settings: object, names: Iterable[str], error: type[PerchposeError], prefix: str = ""
) -> None:
    """Raise ``error`` naming the first of the fields ``names`` of ``settings`` that is not
    above zero (NaN included): ``"{prefix}{name} must be positive, got {value}"``."""
    for name in names:
        value = getattr(settings, name)
        if not value > 0:
            raise error(f"{prefix}{name} must be positive, got {value}")


def require_non_negative(
    settings: object, names: Iterable[str], error: type[PerchposeError], prefix: str = ""
) -> None:
    """Raise ``error`` naming the first of the fields ``names`` of ``settings`` that is not a
    finite number of zero or more: ``"{prefix}{name} must be a non-negative number, got
    {value}"``."""
    for name in names:
        value = getattr(settings, name)
        if not (math.isfinite(value) and value >= 0):
            raise error(f"{prefix}{name} must be a non-negative number, got {value}")
