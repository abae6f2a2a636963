"""The ``perchpose`` command line: one module per command, each only parsing, calling one library
function and printing. Errors in a user's input come back from the library as
``PerchposeError``; ``main`` prints them as one line on stderr and exits with code 2.
"""

from perchpose.cli import (  # noqa: F401  (each module registers its command on the group)
    bench,
    board,
    calibrate,
    demo,
    evaluate,
    fit_fusion,
    latency,
    perch,
    ros2,
    sim_vehicle,
    simulate,
    target,
    track,
    warmup,
)
from perchpose.cli.group import group
from perchpose.cli.main import main, run

__all__ = ["group", "main", "run"]
