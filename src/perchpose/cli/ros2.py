"""``perchpose ros2``: the target's pose as a ROS 2 node."""

from __future__ import annotations

import click

from perchpose.cli.group import group


@group.command(
    context_settings={"ignore_unknown_options": True, "allow_extra_args": True},
    add_help_option=True,
)
@click.option(
    "--write-params",
    "params_out",
    type=click.Path(dir_okay=False, writable=True),
    default=None,
    help="Write the node's parameters file (every parameter with its default) to FILE, to "
    "edit and pass as --ros-args --params-file FILE, and exit.",
)
@click.argument("ros_args", nargs=-1, type=click.UNPROCESSED)
def ros2(params_out: str | None, ros_args: tuple[str, ...]) -> None:
    """Run perchpose as a ROS 2 node: images from image_raw (or image_raw/compressed) and
    camera_info, the pose on /perchpose/pose (PoseWithCovarianceStamped, the image's stamp and
    frame id), the track row on /perchpose/track, /tf and /diagnostics. ROS arguments follow
    --ros-args, e.g. -r image_raw:=/cam/image_raw -p target_frame:=plate. Needs rclpy (a ROS 2
    install, or the ros2 extra)."""
    from perchpose.app.ros2 import Ros2Options, run

    written = run(Ros2Options(ros_args, params_out))
    if written is not None:
        click.echo(f"wrote {written}")
