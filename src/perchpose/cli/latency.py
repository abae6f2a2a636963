"""``perchpose latency``: a live camera's glass-to-grab latency, for ``--camera-latency-ms``."""

from __future__ import annotations

import click

from perchpose.cli.group import group


@group.command()
@click.argument("source")
@click.option("--seconds", default=10.0, show_default=True, help="How long to measure.")
@click.option(
    "--display-hz",
    default=30.0,
    show_default=True,
    help="How often the markers change (at most the screen's refresh rate).",
)
@click.option(
    "--display-lag-ms",
    default=0.0,
    show_default=True,
    help="The display's own lag (compositor and panel), taken off where known.",
)
@click.option("--fps", type=float, default=None, help="Frame rate to ask of a camera.")
def latency(
    source: str, seconds: float, display_hz: float, display_lag_ms: float, fps: float | None
) -> None:
    """Measure a live camera's (or stream's) glass-to-grab latency: a full-screen window shows
    two time-coded markers, which the camera SOURCE films (point it at the screen, the markers
    filling a good part of its view); each frame's stamp less the time its markers were
    shown is one sample. The stamp is the source's own where it has one (a V4L2 camera's
    buffer stamp, a stream's presentation time on this host's clock), else the grab, as track
    dates frames. Give the mean to track, the node and the pilots as --camera-latency-ms."""
    from perchpose.app.latency import LatencyOptions, run

    click.echo(run(LatencyOptions(source, seconds, display_hz, display_lag_ms, fps)).describe())
