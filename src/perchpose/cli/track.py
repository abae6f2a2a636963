"""``perchpose track``: the target in a folder, video or camera, and the vehicle links that
fly on it."""

from __future__ import annotations

from typing import TYPE_CHECKING

import click

from perchpose.cli.common import (
    CAMERA_HELP,
    budget_option,
    quiet_option,
    show_progress,
    target_option,
    warn,
)
from perchpose.cli.group import group
from perchpose.control.pilot_settings import COMMANDS
from perchpose.errors import SourceError

if TYPE_CHECKING:
    from perchpose.app.links import LinkOptions
    from perchpose.app.track import TrackSummary


@group.command()
@click.argument("source")
@click.option(
    "--camera",
    "camera_file",
    default=None,
    help=f"{CAMERA_HELP}. Required, except for a ROS bag with a CameraInfo topic.",
)
@click.option(
    "--image-topic",
    default=None,
    help="For a ROS bag (.bag, .mcap or a ROS 2 bag folder): the topic of its images "
    "(sensor_msgs/Image or CompressedImage).",
)
@click.option(
    "--camera-info-topic",
    default=None,
    help="For a ROS bag without --camera: the CameraInfo topic (default: the bag's only one).",
)
@target_option
@click.option(
    "--fps",
    default=None,
    type=float,
    help="Frame rate for t_s = frame / fps (default 30; a video's own rate).",
)
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(),
    help="Pose file (.csv or .jsonl), or a ROS 2 bag: run.mcap, or a folder name (pose with "
    "covariance, /tf, the overlay and each frame's row; extra [ros]).",
)
@click.option(
    "--overlay",
    default=None,
    type=click.Path(dir_okay=False),
    help="Also write an overlay video (.mp4 or .avi).",
)
@quiet_option
@click.option(
    "--mavlink",
    "mavlink_url",
    default=None,
    help="Send LANDING_TARGET over this pymavlink connection, e.g. udpout:127.0.0.1:14550 "
    "or /dev/ttyUSB0,57600.",
)
@click.option(
    "--mavlink-frame",
    type=click.Choice(["body_frd", "local_ned"]),
    default="body_frd",
    show_default=True,
    help="LANDING_TARGET frame: body_frd (ArduPilot) or local_ned (PX4; uses the vehicle's "
    "ATTITUDE and LOCAL_POSITION_NED).",
)
@click.option(
    "--mavlink-target-relative",
    is_flag=True,
    help="Also send TARGET_RELATIVE (PX4's vision target estimator) with the covariance's "
    "standard deviations, in --mavlink-frame.",
)
@click.option(
    "--mavlink-distance-sensor",
    "mavlink_distance",
    is_flag=True,
    help="Also send DISTANCE_SENSOR: the target's distance along the body's vertical axis, "
    "for a vehicle without a rangefinder.",
)
@click.option(
    "--mavlink-pilot",
    is_flag=True,
    help="Perch with the autopilot behind --mavlink: velocity and yaw-rate setpoints "
    "(SET_POSITION_TARGET_LOCAL_NED) from the perching controller, only while the vehicle is "
    "armed in GUIDED (ArduPilot) or OFFBOARD (PX4); instead of LANDING_TARGET.",
)
@click.option(
    "--target-system",
    type=click.IntRange(1, 255),
    default=None,
    help="The vehicle's MAVLink system id (default: the first autopilot heard); messages from "
    "other systems are ignored and nothing is sent to them.",
)
@click.option(
    "--crazyflie",
    "crazyflie_uri",
    default=None,
    help="Fly a Crazyflie onto the target with the perching controller, e.g. "
    "radio://0/80/2M/E7E7E7E7E7.",
)
@click.option(
    "--command",
    "pilot_command",
    type=click.Choice(list(COMMANDS)),
    default=None,
    help="What the flying pilot sends a Crazyflie: attitude setpoints (the default: a roll, a "
    "pitch and a height, send_zdistance_setpoint; the pilot flies the horizontal velocity "
    "loop itself on the camera's fixes and the accelerometer), velocity ones "
    "(send_velocity_world_setpoint), or full-state ones (a position and yaw its own position "
    "loop holds on its estimate: send_full_state_setpoint). A MAVLink autopilot is sent "
    "velocities.",
)
@click.option(
    "--position-fixes/--no-position-fixes",
    default=True,
    show_default=True,
    help="The flying pilot hands each camera fix to the vehicle's own estimator as an "
    "external position (a Crazyflie's Kalman filter: cflib's send_extpos), which corrects a "
    "Flow deck's drifting velocity; MAVLink autopilots take none.",
)
@click.option(
    "--mount",
    "mount_file",
    default=None,
    help="Where the camera sits: 'up' (on top looking up, for perching; the default), "
    "'down' (under the body looking down, for landing with an autopilot), or a YAML file with "
    "T_body_camera (4x4, body x forward, y left, z up).",
)
@click.option(
    "--sigmas",
    "sigmas_file",
    default=None,
    type=click.Path(dir_okay=False),
    help="Fuse the markers with the paper's fusion and these weights (the JSON that "
    "'fit-fusion --json' writes) instead of the joint pose.",
)
@click.option(
    "--view",
    is_flag=True,
    help="Serve a live view for Foxglove (ws://127.0.0.1:PORT): the overlay, the pose, /tf, "
    "a 3D scene and plots (extra [view]).",
)
@click.option("--view-port", default=8765, show_default=True, help="Port of the live view.")
@click.option(
    "--view-origin",
    "view_origins",
    multiple=True,
    help="Also let web pages of this Origin connect to the live view (repeatable; pages of "
    "other origins are refused, so that no web page opened on this machine can read it).",
)
@click.option(
    "--camera-latency-ms",
    default=0.0,
    type=float,
    show_default=True,
    help="A live camera's latency, as `perchpose latency` measures it: each frame was "
    "captured this long before its source's own stamp (a V4L2 camera's buffer stamp, a "
    "stream's presentation time), or before its grab where it has none. The pilots and "
    "LANDING_TARGET date poses from the capture.",
)
@click.option(
    "--realtime",
    is_flag=True,
    help="Replay a recording (folder, video, bag) at the rate its time stamps say, for the "
    "live view and the vehicle links (same as --rate 1).",
)
@click.option(
    "--rate",
    type=float,
    default=None,
    help="Replay a recording at this many times its recorded speed (0.5: half speed).",
)
@click.option(
    "--camera-frame",
    default=None,
    help="The camera's frame id in bags and the live view (default: the image's own frame "
    "id, else 'camera').",
)
@click.option(
    "--target-frame",
    default="target",
    show_default=True,
    help="The target's frame id in /tf (bags, live view).",
)
@budget_option(
    "Time budget per frame: past it the detection leaves out what it can (a pattern fit, "
    "a whole-frame search) and the track file's 'skipped' column says what."
)
def track(
    source: str,
    camera_file: str,
    target_file: str | None,
    fps: float | None,
    out: str,
    overlay: str | None,
    quiet: bool,
    mavlink_url: str | None,
    mavlink_frame: str,
    mavlink_target_relative: bool,
    mavlink_distance: bool,
    mavlink_pilot: bool,
    target_system: int | None,
    crazyflie_uri: str | None,
    mount_file: str | None,
    pilot_command: str | None,
    position_fixes: bool,
    sigmas_file: str | None,
    budget_ms: float | None,
    image_topic: str | None,
    camera_info_topic: str | None,
    view: bool,
    view_port: int,
    view_origins: tuple[str, ...],
    camera_latency_ms: float,
    realtime: bool,
    rate: float | None,
    camera_frame: str | None,
    target_frame: str,
) -> None:
    """Track the target in SOURCE: a folder of images, a glob, a video file, a camera index,
    a network stream (rtsp://, udp://, http://...; reopened when it drops), or a ROS bag
    (with --image-topic).

    With --mavlink or --crazyflie, each frame's estimate also goes to the vehicle.
    """
    from perchpose.app.track import TrackOptions, run

    if realtime and rate is not None and rate != 1.0:
        raise click.UsageError("--realtime is --rate 1: give one of them.")
    links = _link_options(
        mavlink_url,
        mavlink_frame,
        mavlink_pilot,
        mavlink_target_relative,
        mavlink_distance,
        target_system,
        crazyflie_uri,
        mount_file,
        position_fixes,
        pilot_command,
    )
    options = TrackOptions(
        source,
        out,
        camera_file=camera_file,
        camera_info_topic=camera_info_topic,
        image_topic=image_topic,
        target_file=target_file,
        fps=fps,
        overlay=overlay,
        sigmas_file=sigmas_file,
        budget_ms=budget_ms,
        view=view,
        view_port=view_port,
        view_origins=view_origins,
        rate=1.0 if realtime else rate,
        camera_frame=camera_frame,
        target_frame=target_frame,
        links=links,
        progress=show_progress(quiet),
        camera_latency_s=camera_latency_ms / 1000.0,
    )
    summary = run(options, warn)
    _print_summary(summary)
    if summary.frames and summary.bad_frames == summary.frames:
        # the rows are written, each with its reason; the run itself found nothing to track
        raise SourceError(
            f"{source}: none of its {summary.frames} frames could be read (the warnings above "
            "say why)"
        )


def _link_options(
    mavlink_url: str | None,
    mavlink_frame: str,
    mavlink_pilot: bool,
    target_relative: bool,
    distance_sensor: bool,
    target_system: int | None,
    crazyflie_uri: str | None,
    mount_file: str | None,
    position_fixes: bool = True,
    command: str | None = None,
) -> LinkOptions:
    """The vehicle links asked for; a MAVLink flag without ``--mavlink`` is a usage error."""
    from perchpose.app.links import LinkOptions

    extras = {
        "--mavlink-pilot": mavlink_pilot,
        "--mavlink-target-relative": target_relative,
        "--mavlink-distance-sensor": distance_sensor,
        "--target-system": target_system is not None,
    }
    asked = [flag for flag, on in extras.items() if on]
    if asked and mavlink_url is None:
        raise click.UsageError(f"{asked[0]} needs --mavlink URL (the autopilot's link).")
    return LinkOptions(
        mavlink_url=mavlink_url,
        mavlink_frame=mavlink_frame,
        mavlink_pilot=mavlink_pilot,
        target_relative=target_relative,
        distance_sensor=distance_sensor,
        target_system=target_system,
        crazyflie_uri=crazyflie_uri,
        mount=mount_file,
        position_fixes=position_fixes,
        command=command,
    )


def _print_summary(summary: TrackSummary) -> None:
    stages = ", ".join(f"stage {k}: {v}" for k, v in summary.stage_counts.items() if v)
    extra = ""
    if summary.stale_frames:
        extra += f", {summary.stale_frames} stale (dropped for a newer frame)"
    if summary.damaged_frames:
        extra += f", {summary.damaged_frames} damaged (decoded from damaged data, not measured)"
    if summary.budget_frames:
        extra += f", {summary.budget_frames} over budget (see 'skipped')"
    if any(summary.dated):  # a live source with a clock of its own
        from perchpose.io.capture_clock import CLOCK_NAMES

        extra += "; dated by " + ", ".join(
            f"{CLOCK_NAMES.get(clock, clock)} ({n})" for clock, n in summary.dated.items()
        )
    click.echo(
        f"{summary.frames} frames, {summary.valid} valid ({stages}), "
        f"{summary.bad_frames} unreadable{extra}; {summary.mean_ms:.1f} ms per frame, "
        f"latency p95 {summary.p95_latency_ms:.1f} ms; wrote {summary.out}"
    )
