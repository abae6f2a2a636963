"""The ``perchpose`` command group; each command registers itself from its own module."""

from __future__ import annotations

import click


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="perchpose")
def group() -> None:
    """Pose of a nested-marker perching target from one camera."""
