"""The ``perchpose`` command line. Each command parses, calls one library function, prints.

Errors in a user's input come back from the library as PerchposeError; they are printed as one
line on stderr and the command exits with code 2.
"""

from __future__ import annotations

import json
import logging
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import click

from perchpose.camera import CameraModel
from perchpose.errors import PerchposeError
from perchpose.target import TargetSpec


def _load_camera(value: str) -> CameraModel:
    if value.startswith("preset:"):
        return CameraModel.preset(value.split(":", 1)[1])
    return CameraModel.load(value)


def _load_target(value: str | None) -> TargetSpec:
    return TargetSpec.paper() if value is None else TargetSpec.load(value)


CAMERA_HELP = "ROS camera_info or OpenCV YAML; or preset:webcam, preset:fpv, preset:fpv_wide"
target_option = click.option(
    "--target", "target_file", default=None, help="Target YAML (default: the paper's)."
)
camera_option_fpv = click.option(
    "--camera", "camera_file", default="preset:fpv", show_default=True, help=CAMERA_HELP
)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="perchpose")
def cli() -> None:
    """Pose of a nested-marker perching target from one camera."""


@cli.command()
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(dir_okay=False),
    help="Output file: .svg, .pdf or .png.",
)
@target_option
@click.option("--dpi", default=600, show_default=True, help="Resolution of a PNG.")
@click.option(
    "--save-spec",
    default=None,
    type=click.Path(dir_okay=False),
    help="Also write the target's YAML specification here.",
)
def target(out: str, target_file: str | None, dpi: int, save_spec: str | None) -> None:
    """Write the printable target at true scale, with a 100 mm scale bar."""
    from perchpose.printable import write_target_sheet

    spec = _load_target(target_file)
    path = write_target_sheet(spec, out, dpi=dpi)
    if save_spec:
        spec.save(save_spec)
    click.echo(f"wrote {path}: print at 100 % and check that the scale bar measures 100 mm")


@cli.command()
@click.argument("scenario")
@camera_option_fpv
@target_option
@click.option(
    "--out", "out", required=True, type=click.Path(file_okay=False), help="Output folder."
)
@click.option(
    "--quality",
    default="default",
    show_default=True,
    type=click.Choice(["clean", "default", "analog_fpv"]),
    help="Image degradation.",
)
@click.option("--seed", default=0, show_default=True, help="Noise seed.")
@click.option(
    "--frames", "max_frames", default=None, type=int, help="Keep only the first N frames."
)
def simulate(
    scenario: str,
    camera_file: str,
    target_file: str | None,
    out: str,
    quality: str,
    seed: int,
    max_frames: int | None,
) -> None:
    """Render SCENARIO (approach or static) to frames, camera.yaml and truth.csv."""
    from perchpose.sim.render import ImageQuality
    from perchpose.sim.scenarios import scenario_by_name, truncated
    from perchpose.sim.sequence import write_sequence

    cam = _load_camera(camera_file)
    spec = _load_target(target_file)
    scen = scenario_by_name(scenario, ImageQuality.preset(quality))
    if max_frames is not None:
        scen = truncated(scen, max_frames)
    path = write_sequence(scen, cam, spec, out, seed=seed, progress=sys.stderr.isatty())
    click.echo(f"wrote {len(scen)} frames, camera.yaml and truth.csv to {path}")


def _warn(message: str) -> None:
    click.echo(f"perchpose: {message}", err=True)


@contextmanager
def _vehicle_links(
    target: TargetSpec,
    mavlink_url: str | None,
    mavlink_frame: str,
    crazyflie_uri: str | None,
    mount_file: str | None,
) -> Iterator[list[Callable[[Any, float], None]]]:
    """The per-frame hooks of the requested vehicle links; lands and closes them at the end."""
    from perchpose.control import ControllerSettings, PerchingController, load_T_body_camera

    T_body_camera = load_T_body_camera(mount_file) if mount_file else None
    hooks: list[Callable[[Any, float], None]] = []
    closers: list[Callable[[], None]] = []
    pilot = None
    try:
        if mavlink_url is not None:
            from perchpose.io.mavlink import LandingTargetSink

            sink = LandingTargetSink(
                mavlink_url,
                frame=mavlink_frame,
                T_body_camera=T_body_camera,
                target=target,
                report=_warn,
            )
            closers.append(sink.close)
            hooks.append(sink)
        if crazyflie_uri is not None:
            from perchpose.io.crazyflie import connect

            # cflib logs its connection failures with tracebacks; the error below says it once
            logging.getLogger("cflib").addHandler(logging.NullHandler())
            link = connect(crazyflie_uri, report=_warn)
            closers.append(link.close)
            settings = (
                ControllerSettings()
                if T_body_camera is None
                else ControllerSettings(T_body_camera=T_body_camera)
            )
            pilot = link.pilot(controller=PerchingController(settings))
            hooks.append(pilot)
        try:
            yield hooks
        finally:
            if pilot is not None:  # source ended, an error, or Ctrl-C: land
                pilot.abort(pilot.last_t_s, "tracking ended")
                pilot.land()
    finally:
        for close in reversed(closers):
            close()


@cli.command()
@click.argument("source")
@click.option("--camera", "camera_file", required=True, help=CAMERA_HELP)
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
    type=click.Path(dir_okay=False),
    help="Pose file: .csv or .jsonl.",
)
@click.option(
    "--overlay",
    default=None,
    type=click.Path(dir_okay=False),
    help="Also write an overlay video (.mp4 or .avi).",
)
@click.option("--quiet", is_flag=True, help="No progress bar.")
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
    "--crazyflie",
    "crazyflie_uri",
    default=None,
    help="Fly a Crazyflie onto the target with the perching controller, e.g. "
    "radio://0/80/2M/E7E7E7E7E7.",
)
@click.option(
    "--mount",
    "mount_file",
    default=None,
    type=click.Path(dir_okay=False),
    help="YAML with T_body_camera (4x4, body x forward, y left, z up); default: camera on top "
    "looking up.",
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
    crazyflie_uri: str | None,
    mount_file: str | None,
) -> None:
    """Track the target in SOURCE: a folder of images, a glob, a video file or a camera index.

    With --mavlink or --crazyflie, each frame's estimate also goes to the vehicle.
    """
    from perchpose.io.overlay import check_overlay_path
    from perchpose.track import track as run_track

    cam = _load_camera(camera_file)
    spec = _load_target(target_file)
    if overlay is not None:
        check_overlay_path(overlay)  # before any vehicle link takes over
    with _vehicle_links(spec, mavlink_url, mavlink_frame, crazyflie_uri, mount_file) as hooks:
        summary = run_track(
            source,
            cam,
            spec,
            out,
            fps=fps,
            overlay=overlay,
            progress=not quiet and sys.stderr.isatty(),
            on_frame=hooks,
        )
    stages = ", ".join(f"stage {k}: {v}" for k, v in summary.stage_counts.items() if v)
    click.echo(
        f"{summary.frames} frames, {summary.valid} valid ({stages}), "
        f"{summary.bad_frames} unreadable; {summary.mean_ms:.1f} ms per frame; "
        f"wrote {summary.out}"
    )


@cli.command()
@click.option(
    "--out",
    "out",
    default="perchpose-demo",
    show_default=True,
    type=click.Path(file_okay=False),
    help="Output folder.",
)
@camera_option_fpv
@click.option("--seconds", default=8.0, show_default=True, help="Length of the approach.")
@click.option("--seed", default=0, show_default=True, help="Noise seed.")
def demo(out: str, camera_file: str, seconds: float, seed: int) -> None:
    """Render an approach with dropouts, track it and compare with the truth."""
    from perchpose.demo import run_demo
    from perchpose.evaluation.metrics import format_stage_table

    result = run_demo(
        out,
        _load_camera(camera_file),
        duration_s=seconds,
        seed=seed,
        progress=sys.stderr.isatty(),
        say=click.echo,
    )
    click.echo("")
    click.echo(format_stage_table(result.table))
    click.echo("")
    dropouts = int(result.errors.dropout.sum())
    click.echo(
        f"dropout frames: {dropouts}, of which {result.coasted_valid_frames} were bridged "
        f"by the filter (at most 8 in a row stay valid)"
    )
    click.echo(f"wrote {result.out_dir / 'poses.csv'}, {result.overlay}, {result.figure}")


@cli.command()
@click.argument("experiment", type=click.Choice(["paper"]))
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(file_okay=False),
    help="Output folder for report.md, results.json and the figures.",
)
@camera_option_fpv
@click.option(
    "--quality",
    default="analog_fpv",
    show_default=True,
    type=click.Choice(["clean", "default", "analog_fpv"]),
    help="Image degradation for the tables, the dropout, the fit and the ablations.",
)
@click.option("--quick", is_flag=True, help="A reduced run (under a minute) for smoke tests.")
@click.option("--seed", default=0, show_default=True, help="Base seed of every experiment.")
def evaluate(
    experiment: str, out: str, camera_file: str, quality: str, quick: bool, seed: int
) -> None:
    """Reproduce the paper's experiments (EXPERIMENT: paper) on rendered frames."""
    from perchpose.evaluation.report import run_paper_evaluation

    del experiment  # one experiment set so far
    result = run_paper_evaluation(
        out,
        _load_camera(camera_file),
        quick=quick,
        seed=seed,
        quality_name=quality,
        progress=sys.stderr.isatty(),
        say=lambda msg: click.echo(msg, err=True),
    )
    r = result.results
    ranges = r["ranges"]
    click.echo(
        f"ranges ({ranges['quality']} images): outer up to "
        f"{ranges['outer']['z_max_cm']} cm, inner up to {ranges['inner']['z_max_cm']} cm"
    )
    if r["fusion_fit"] is not None:
        ls = r["fusion_fit"]["least_squares"]
        click.echo(
            "fusion fit (least squares): " + ", ".join(f"{k} {v:.3f}" for k, v in ls.items())
        )
    click.echo(f"wrote {result.report}, {result.out_dir / 'results.json'} and figures")


@cli.command(name="fit-fusion")
@click.argument("data", type=click.Path(dir_okay=False))
@click.option(
    "--truth",
    "truth_file",
    default=None,
    type=click.Path(dir_okay=False),
    help="truth.csv of the frames, when DATA is a track file.",
)
@click.option(
    "--json",
    "json_out",
    default=None,
    type=click.Path(dir_okay=False),
    help="Also write the fitted sigmas as JSON.",
)
def fit_fusion(data: str, truth_file: str | None, json_out: str | None) -> None:
    """Fit the fusion sigmas from labelled data (least squares and the paper's LMS).

    DATA has columns true_x_cm, true_y_cm, true_z_cm, true_yaw_deg and each marker's raw
    measurement m0_* (outer) and m1_* (inner); or it is a track file and --truth gives the
    truth.csv of the same frames."""
    import json

    from perchpose.evaluation.experiments import COMPONENT_NAMES, PAPER_SIGMAS
    from perchpose.evaluation.experiments import fit_fusion as fit
    from perchpose.evaluation.fusion_data import load_fusion_samples

    samples = load_fusion_samples(data, truth_file)
    try:
        result = fit(samples)
    except ValueError as exc:
        raise PerchposeError(f"{data}: {exc}") from exc
    click.echo(f"{result.samples} frames with truth and both markers")
    click.echo(f"{'':10} {'least sq.':>10} {'LMS':>10} {'paper':>10}")
    for name in COMPONENT_NAMES:
        click.echo(
            f"{name:10} {result.least_squares[name]:10.3f} {result.lms[name]:10.3f} "
            f"{PAPER_SIGMAS[name]:10.3f}"
        )
    if json_out:
        Path(json_out).write_text(
            json.dumps(
                {
                    "least_squares": result.least_squares,
                    "lms": result.lms,
                    "samples": result.samples,
                },
                indent=2,
            ),
            encoding="utf-8",
        )


def board_options(command: Callable[..., None]) -> Callable[..., None]:
    """The ChArUco board options shared by ``board`` and ``calibrate``."""
    options = [
        click.option(
            "--squares", default="5x7", show_default=True, help="Squares across x down, e.g. 5x7."
        ),
        click.option(
            "--square-mm",
            default=40.0,
            show_default=True,
            help="Side of a square, mm (measure the print).",
        ),
        click.option("--marker-mm", default=20.0, show_default=True, help="Side of a marker, mm."),
        click.option(
            "--dictionary",
            default="DICT_6X6_250",
            show_default=True,
            help="OpenCV ArUco dictionary of the markers.",
        ),
    ]
    for option in reversed(options):
        command = option(command)
    return command


def _board(squares: str, square_mm: float, marker_mm: float, dictionary: str) -> Any:
    from perchpose.calibration import CharucoBoardSpec

    return CharucoBoardSpec(
        CharucoBoardSpec.parse_squares(squares), square_mm, marker_mm, dictionary
    )


@cli.command()
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(dir_okay=False),
    help="Output file: .svg, .pdf or .png.",
)
@board_options
@click.option("--dpi", default=600, show_default=True, help="Resolution of a PNG.")
def board(
    out: str, squares: str, square_mm: float, marker_mm: float, dictionary: str, dpi: int
) -> None:
    """Write a printable ChArUco calibration board at true scale."""
    from perchpose.printable import write_board_sheet

    spec = _board(squares, square_mm, marker_mm, dictionary)
    path = write_board_sheet(spec, out, dpi=dpi)
    click.echo(f"wrote {path} ({spec.describe()}): print at 100 % and glue it flat")


@cli.command()
@click.argument("source")
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(dir_okay=False),
    help="Camera file to write (ROS camera_info YAML).",
)
@board_options
@click.option(
    "--model",
    default="plumb_bob",
    show_default=True,
    type=click.Choice(["plumb_bob", "equidistant"]),
    help="Lens model: equidistant for fisheye / wide FPV lenses.",
)
@click.option("--max-views", default=30, show_default=True, help="Views to pick from a video.")
def calibrate(
    source: str,
    out: str,
    squares: str,
    square_mm: float,
    marker_mm: float,
    dictionary: str,
    model: str,
    max_views: int,
) -> None:
    """Calibrate a camera from ChArUco board images: a folder, a glob or a video."""
    from perchpose.calibrate_run import format_report, run_calibration

    spec = _board(squares, square_mm, marker_mm, dictionary)
    run = run_calibration(
        source,
        out,
        spec,
        "equidistant" if model == "equidistant" else "plumb_bob",
        max_video_views=max_views,
    )
    click.echo(format_report(run.result, spec, source, run.searched_frames), nl=False)
    click.echo(f"wrote {run.camera_file}, {run.report} and {run.coverage_png}")


@cli.command()
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
    type=click.Choice(["wind"]),
    default=None,
    help="Fly every wind level for every estimator; writes perch.md and wind.png.",
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
def perch(
    runs: int,
    seed: int,
    wind: str,
    wind_mps: float | None,
    gust_mps: float | None,
    sweep: str | None,
    estimators: str,
    disturbances: bool,
    camera_file: str,
    out: str,
    json_out: str | None,
    workers: int,
    scheduler: str | None,
    resume: bool,
) -> None:
    """Closed-loop perching in simulation from random starts 60-150 cm below the target."""
    from perchpose.app.perch import PerchCampaign, summary_table

    campaign = PerchCampaign.from_options(
        _load_camera(camera_file),
        estimators=estimators,
        runs=runs,
        seed=seed,
        wind=wind,
        wind_mps=wind_mps,
        gust_mps=gust_mps,
        sweep=sweep,
        disturbances=disturbances,
    )
    content = campaign.fly(
        out,
        workers=max(1, workers),
        scheduler=scheduler,
        resume=resume,
        progress=sys.stderr.isatty(),
        say=lambda m: click.echo(m, err=True),
    )
    click.echo(summary_table(content), nl=False)
    if json_out:
        Path(json_out).write_text(json.dumps(content, indent=2, default=str), encoding="utf-8")
    click.echo(f"wrote {out}/runs.csv, perch.json, perch.md and figures")


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, handled as Ctrl-C is: files closed whole, a flying vehicle landed."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _terminate(signum: int, _frame: object) -> None:
    raise Terminated(signum)


@contextmanager
def _signals_as_interrupts() -> Iterator[None]:
    """While a command runs, SIGTERM and SIGHUP unwind it as Ctrl-C does (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    wanted = [signal.SIGTERM] + ([signal.SIGHUP] if hasattr(signal, "SIGHUP") else [])
    previous = {sig: signal.signal(sig, _terminate) for sig in wanted}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _interrupted(exc: BaseException | None) -> int:
    """Say why the run stopped; the exit code is 128 + the signal's number (Ctrl-C: 130)."""
    if isinstance(exc, Terminated):
        click.echo(f"perchpose: terminated ({exc})", err=True)
        return 128 + exc.signum
    click.echo("perchpose: interrupted", err=True)
    return 130


def main(argv: list[str] | None = None) -> int:
    """Entry point: run the command, turn library errors into one line and exit code 2."""
    try:
        with _signals_as_interrupts():
            cli.main(args=argv, prog_name="perchpose", standalone_mode=False)
    except PerchposeError as exc:
        click.echo(f"perchpose: error: {exc}", err=True)
        return 2
    except OSError as exc:
        # the library wraps the files it names; this is the net for any other file trouble
        where = f"{exc.filename}: " if exc.filename else ""
        click.echo(f"perchpose: error: {where}{exc.strerror or exc}", err=True)
        return 2
    except click.exceptions.Abort as exc:
        return _interrupted(exc.__cause__)
    except click.ClickException as exc:
        exc.show()
        return exc.exit_code
    except KeyboardInterrupt as exc:
        return _interrupted(exc)
    return 0


if __name__ == "__main__":
    sys.exit(main())


def run() -> None:
    """Console-script entry point."""
    sys.exit(main())
