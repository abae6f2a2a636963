"""``perchpose ros2``: the target's pose as a ROS 2 node (``perchpose.io.ros.node``)."""

from __future__ import annotations

import shutil
from dataclasses import dataclass


@dataclass(frozen=True)
class Ros2Options:
    """The node's ROS arguments (after ``--ros-args``), or, with ``params_out``, only the
    shipped parameters file copied there."""

    ros_args: tuple[str, ...] = ()
    params_out: str | None = None


def run(options: Ros2Options) -> str | None:
    """Run the node until it is shut down (rclpy is imported only then); or write the
    parameters file and return its path."""
    if options.params_out is not None:
        from perchpose.io.ros.node import PARAMS_FILE

        shutil.copyfile(PARAMS_FILE, options.params_out)
        return options.params_out
    from perchpose.io.ros.node import run as run_node

    run_node(list(options.ros_args))
    return None
