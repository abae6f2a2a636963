"""``perchpose warmup``: the compiled kernels built ahead of a flight."""

from __future__ import annotations

import click

from perchpose.cli.common import CAMERA_HELP, target_option
from perchpose.cli.group import group


@group.command()
@click.option(
    "--camera", "camera_file", default=None, help=f"{CAMERA_HELP} (default: both presets' lenses)."
)
@target_option
def warmup(camera_file: str | None, target_file: str | None) -> None:
    """Build every compiled kernel and cache it on disk: run once on a companion computer after
    installing (and after each upgrade), so that no process compiles in flight. track and the
    ROS 2 node still load the cached kernels before their first frame."""
    from perchpose.app.warmup import WarmupOptions, run

    done = run(WarmupOptions(camera_file, target_file))
    click.echo(f"{done.describe()}; {done.frames} frames measured")
