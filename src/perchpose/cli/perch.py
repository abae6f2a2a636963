"""``perchpose perch``: perching campaigns in simulation."""

from __future__ import annotations

import click

from perchpose.cli.common import camera_option_fpv, quiet_option, show_progress
from perchpose.cli.group import group
from perchpose.control.pilot_settings import COMMANDS, DEFAULT_COMMAND
from perchpose.sim.firmware import FLIGHT_CONTROLLERS
from perchpose.sim.onboard_kalman import ONBOARD_ESTIMATORS


@group.command()
@click.option("--runs", default=200, show_default=True, help="Runs per estimator and wind.")
@click.option("--seed", default=0, show_default=True, help="Seed of the first run.")
@click.option(
    "--wind",
    default="none",
    show_default=True,
    type=click.Choice(["none", "light", "moderate", "strong"]),
    help="Wind level: mean / turbulence 0 / 0, 1.5 / 0.5, 3 / 1, 4.5 / 1.5 m/s (Dryden).",
)
@click.option(
    "--wind-mps", type=float, default=None, help="Mean wind speed instead of the level's."
)
@click.option(
    "--gust-mps", type=float, default=None, help="Turbulence intensity instead of the level's."
)
@click.option(
    "--sweep",
    type=click.Choice(["wind", "latency"]),
    default=None,
    help="Fly every wind level (wind.png), or camera latencies of 0, 50, 100, 150 and 200 ms "
    "at --wind (latency.png), for every estimator.",
)
@click.option(
    "--estimator",
    "estimators",
    default="covariance,paper,truth",
    show_default=True,
    help="Comma-separated: paper, outer, inner, covariance (joint PnP, covariance filter), truth.",
)
@click.option(
    "--disturbances/--no-disturbances",
    default=True,
    show_default=True,
    help="Draw per run: motor mismatch, attitude bias, latency jitter, dropout bursts, battery "
    "sag, odometry drift (off: a clean lab).",
)
@click.option(
    "--sensing",
    type=click.Choice(["realistic", "ideal"]),
    default="realistic",
    show_default=True,
    help="The vehicle's senses: realistic (drawn per run: camera latency 40-150 ms with jitter, "
    "flow-deck-like odometry 10-30 ms late, attitude noise and delay, clock offset, "
    "calibration, mount and print errors) or ideal (exact, one frame of latency).",
)
@click.option(
    "--fps",
    default=30.0,
    show_default=True,
    type=float,
    help="Camera frame rate (15-60 fps verified); the controller is told of it.",
)
@click.option(
    "--latency-ms",
    default=None,
    type=float,
    help="Camera latency, capture to estimate (default: drawn, 40-150 ms; with --sensing "
    "ideal one frame, and whole frames); up to 200 ms verified.",
)
@click.option(
    "--flight-controller",
    type=click.Choice(list(FLIGHT_CONTROLLERS)),
    default="model",
    show_default=True,
    help="The vehicle's onboard loops: model (this package's) or the Crazyflie firmware's own "
    "controller (needs its Python module cffirmware: ../shared/firmware/install-cffirmware, "
    "GPL-3.0).",
)
@click.option(
    "--onboard-estimator",
    type=click.Choice(list(ONBOARD_ESTIMATORS)),
    default="model",
    show_default=True,
    help="The vehicle's own state estimate: model (the truth with the --odometry error) or "
    "the Crazyflie firmware's Kalman filter fed by a simulated IMU, Flow deck and range "
    "sensor (needs cffirmware, as --flight-controller does).",
)
@click.option(
    "--command",
    type=click.Choice(list(COMMANDS)),
    default=DEFAULT_COMMAND,
    show_default=True,
    help="What the pilot sends the vehicle: velocity (cflib's send_velocity_world_setpoint), "
    "full-state (send_full_state_setpoint: a position and yaw its own position loop holds "
    "on its own estimate) or attitude (send_zdistance_setpoint: a roll, a pitch and a height; "
    "the pilot flies the horizontal velocity loop itself on the camera's fixes and the "
    "accelerometer).",
)
@click.option(
    "--position-fixes",
    type=click.Choice(["send", "off"]),
    default="send",
    show_default=True,
    help="Hand each camera fix to the vehicle's own estimator as an external position (as "
    "cflib's send_extpos does on a Crazyflie); only --onboard-estimator crazyflie-kalman "
    "takes them.",
)
@click.option(
    "--odometry",
    type=click.Choice(["white", "flow-deck"]),
    default="white",
    show_default=True,
    help="The realistic odometry's horizontal error: white (3 cm/s per sample) or flow-deck "
    "(a PMW3901 flow deck under a Kalman filter: correlated over 50-250 ms, growing with "
    "height and yaw rate; the pilot's inertial filter corrects for it).",
)
@click.option(
    "--stamps",
    type=click.Choice(["live", "exact"]),
    default="live",
    show_default=True,
    help="How frames are dated: live (as the live sources stamp them: the grab, less the "
    "camera latency the user measured, off by up to 10 ms) or exact (the true capture time, "
    "for comparison).",
)
@click.option(
    "--contact",
    type=click.Choice(["hold", "first-touch"]),
    default="hold",
    show_default=True,
    help="How a contact with the plate ends a run: hold (the flight goes on through it: the "
    "plate's face, friction and the magnet's pull act, the pilot senses the contact and stops "
    "the motors, and a perch is the magnet seated and holding 1 s later) or first-touch (scored "
    "at the first touch by the contact rules, as campaigns before it were).",
)
@click.option(
    "--latency-error-ms",
    default=10.0,
    show_default=True,
    type=float,
    help="With --stamps live: how far off (up to, either way) the camera latency the user "
    "measured is, drawn per run.",
)
@click.option(
    "--time-offset",
    type=click.Choice(["correct", "report"]),
    default="correct",
    show_default=True,
    help="The camera-to-vehicle time offset estimated online from the motion: correct the "
    "stamps by it once it is sure (to 5 ms), or only report it (runs.csv time_offset_*).",
)
@click.option(
    "--faults",
    default="",
    help="Inject one of these faults per run, at a random time: camera-stall, "
    "odometry-stall, attitude-stall, link-loss (comma-separated; runs then go on through the "
    "landing until the motors stop, up to 40 s).",
)
@click.option(
    "--duration-s",
    default=None,
    type=float,
    help="How long each run may fly, seconds (default 20; 40 with --faults); a run not "
    "perched by then ends as a timeout. The camera's dropouts are drawn over the run's "
    "length, so a seed flies another world at another length.",
)
@click.option(
    "--hover-s",
    default=3.0,
    show_default=True,
    type=float,
    help="How long each vehicle hovers in its run's wind on its own loops (and estimator) "
    "before the pilot takes over; 0: the wind strikes a still, level vehicle as the run "
    "starts, as campaigns before this option flew.",
)
@camera_option_fpv
@click.option(
    "--out",
    "out",
    default="perch",
    show_default=True,
    type=click.Path(file_okay=False),
    help="Folder for runs.csv (written run by run), perch.json, perch.md and figures.",
)
@click.option(
    "--json",
    "json_out",
    default=None,
    type=click.Path(dir_okay=False),
    help="Also write the summary JSON here.",
)
@click.option("--workers", default=2, show_default=True, help="Processes to run in parallel.")
@click.option(
    "--scheduler",
    default=None,
    help="Run on Dask: 'local' (a LocalCluster of --workers processes) or tcp://HOST:PORT.",
)
@click.option("--resume", is_flag=True, help="Keep the runs already in --out; fly the rest.")
@click.option(
    "--overwrite",
    is_flag=True,
    help="Delete the runs and reports already in --out and start afresh (without it, or "
    "--resume, a folder with runs is refused).",
)
@quiet_option
def perch(
    runs: int,
    seed: int,
    wind: str,
    wind_mps: float | None,
    gust_mps: float | None,
    sweep: str | None,
    estimators: str,
    disturbances: bool,
    sensing: str,
    fps: float,
    latency_ms: float | None,
    stamps: str,
    contact: str,
    odometry: str,
    flight_controller: str,
    onboard_estimator: str,
    command: str,
    position_fixes: str,
    latency_error_ms: float,
    time_offset: str,
    faults: str,
    duration_s: float | None,
    hover_s: float,
    camera_file: str,
    out: str,
    json_out: str | None,
    workers: int,
    scheduler: str | None,
    resume: bool,
    overwrite: bool,
    quiet: bool,
) -> None:
    """Closed-loop perching in simulation from random starts 60-150 cm below the target."""
    from perchpose.app.perch import PerchOptions, run, summary_table

    options = PerchOptions(
        out,
        estimators,
        runs,
        seed,
        wind,
        wind_mps,
        gust_mps,
        sweep,
        disturbances,
        sensing,
        fps,
        latency_ms,
        camera_file,
        json_out,
        workers,
        scheduler,
        resume,
        progress=show_progress(quiet),
        stamps=stamps,
        contact=contact,
        odometry=odometry,
        flight_controller=flight_controller,
        onboard_estimator=onboard_estimator,
        position_fixes=position_fixes,
        command=command,
        overwrite=overwrite,
        faults=faults,
        latency_error_ms=latency_error_ms,
        time_offset=time_offset,
        duration_s=duration_s,
        hover_s=hover_s,
    )
    content = run(options, say=lambda m: click.echo(m, err=True))
    click.echo(summary_table(content), nl=False)
    click.echo(f"wrote {out}/runs.csv, perch.json, perch.md and figures")
