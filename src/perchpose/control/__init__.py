"""Closed-loop control shared by the simulation and the vehicle links: the perching controller,
the phase machine that flies it, the mounting of the camera, and the last check on setpoints."""

from perchpose.control.controller import (
    Command,
    ControllerSettings,
    Odometry,
    PerchingController,
    Phase,
    usable,
)
from perchpose.control.mount import (
    MOUNT_PRESETS,
    default_T_body_camera,
    downward_T_body_camera,
    load_T_body_camera,
    mount_T_body_camera,
)
from perchpose.control.pilot import (
    PerchingPilot,
    PilotSettings,
    PilotState,
    PilotStep,
    PositionFixSender,
    SenseAges,
    VehicleCommander,
)
from perchpose.control.position_fix import PositionFixSettings
from perchpose.control.setpoint import Setpoint, SetpointLimits, safe_setpoint
from perchpose.errors import ControllerConfigError

__all__ = [
    "MOUNT_PRESETS",
    "Command",
    "ControllerConfigError",
    "ControllerSettings",
    "Odometry",
    "PerchingController",
    "PerchingPilot",
    "Phase",
    "PilotSettings",
    "PilotState",
    "PilotStep",
    "PositionFixSender",
    "PositionFixSettings",
    "SenseAges",
    "Setpoint",
    "SetpointLimits",
    "VehicleCommander",
    "default_T_body_camera",
    "downward_T_body_camera",
    "load_T_body_camera",
    "mount_T_body_camera",
    "safe_setpoint",
    "usable",
]
