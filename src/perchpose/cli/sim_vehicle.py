"""``perchpose sim-vehicle``: a simulated drone that speaks MAVLink and streams its camera."""

from __future__ import annotations

import click

from perchpose.cli.group import group


@group.command("sim-vehicle")
@click.option(
    "--mavlink",
    default="udpin:127.0.0.1:14550",
    show_default=True,
    help="Where the vehicle listens for its companion (pymavlink URL).",
)
@click.option(
    "--video",
    default="udp://127.0.0.1:5600",
    show_default=True,
    help="Where its camera streams (H.264 in MPEG-TS; any URL or .ts file FFmpeg writes).",
)
@click.option(
    "--autopilot",
    type=click.Choice(["ardupilot", "px4"]),
    default="ardupilot",
    show_default=True,
    help="Whose modes and rules it follows (ArduCopter or PX4).",
)
@click.option(
    "--wind",
    default="light",
    show_default=True,
    help="none, light, moderate or strong (as perch's).",
)
@click.option("--seed", default=0, show_default=True, help="Draws the start and the wind.")
@click.option(
    "--hand-over-s",
    type=float,
    default=2.0,
    show_default=True,
    help="When the operator switches to GUIDED (ArduPilot) or OFFBOARD (PX4, once setpoints "
    "stream); a negative value: never, switch with MAV_CMD_DO_SET_MODE.",
)
@click.option(
    "--duration-s",
    type=float,
    default=None,
    help="Stop after this long (default: run until Ctrl-C).",
)
@click.option("--fps", type=float, default=30.0, show_default=True, help="Camera frame rate.")
@click.option(
    "--camera",
    "camera_file",
    default="preset:fpv",
    show_default=True,
    help="Its camera (give track the same).",
)
@click.option("--target", "target_file", default=None, help="Target YAML (default: the paper's).")
def sim_vehicle(
    mavlink: str,
    video: str,
    autopilot: str,
    wind: str,
    seed: int,
    hand_over_s: float,
    duration_s: float | None,
    fps: float,
    camera_file: str,
    target_file: str | None,
) -> None:
    """A simulated drone to try the links on: perch's vehicle hovering in wind under the
    perching plate, speaking MAVLink as ArduCopter or PX4 (HEARTBEAT with modes, ATTITUDE,
    LOCAL_POSITION_NED, EXTENDED_SYS_STATE, TIMESYNC; velocity and position targets in
    GUIDED/OFFBOARD; arm, disarm, mode changes; LANDING_TARGET counted) and streaming its
    upward camera as H.264 over UDP. In another terminal:

    perchpose track udp://127.0.0.1:5600 --camera preset:fpv --out run.csv
    --mavlink udpout:127.0.0.1:14550 --mavlink-pilot
    """
    from perchpose.app.sim_vehicle import SimVehicleOptions, serve

    options = SimVehicleOptions(
        mavlink=mavlink,
        video=video,
        autopilot=autopilot,
        wind=wind,
        seed=seed,
        hand_over_s=None if hand_over_s < 0 else hand_over_s,
        duration_s=duration_s,
        fps=fps,
        camera_file=camera_file,
        target_file=target_file,
    )
    serve(options, click.echo)
