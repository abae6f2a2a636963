"""``perchpose perch``: perching campaigns in simulation, one estimator and wind per cell,
written run by run and resumable."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from perchpose.app.inputs import load_camera
from perchpose.camera import CameraModel
from perchpose.control.lean import CRAZYFLIE_KALMAN_LAG_S
from perchpose.control.pilot_settings import COMMANDS, DEFAULT_COMMAND, PilotSettings
from perchpose.errors import PerchposeError
from perchpose.evaluation.perching import CampaignLog, RunRecord, run_key, write_reports
from perchpose.sim.campaign import campaign_jobs, execute
from perchpose.sim.disturbances import Disturbances
from perchpose.sim.firmware import FLIGHT_CONTROLLERS, check_flight_controller, load_firmware
from perchpose.sim.onboard_kalman import ONBOARD_ESTIMATORS
from perchpose.sim.perch import CONTACT_MODES, ESTIMATORS, PerchResult, PerchSetup
from perchpose.sim.sensing import ODOMETRY_ERRORS, Sensing
from perchpose.sim.wind import WIND_LEVELS
from perchpose.target import TargetSpec

TRAJECTORIES = 5
TIME_OFFSETS = ("correct", "report")  # what the controller does with its time-offset estimate
POSITION_FIXES = ("send", "off")  # whether the pilot hands its fixes to the vehicle's estimator


@dataclass(frozen=True)
class PerchCampaign:
    """The cells of a campaign (a setup per wind and estimator) and its runs."""

    setups: tuple[PerchSetup, ...]
    runs: int
    seed: int

    @staticmethod
    def from_options(
        camera: CameraModel,
        *,
        estimators: str,
        runs: int,
        seed: int = 0,
        wind: str = "none",
        wind_mps: float | None = None,
        gust_mps: float | None = None,
        sweep: str | None = None,
        disturbances: bool = True,
        fps: float = 30.0,
        latency_ms: float | None = None,
        sensing: str = "realistic",
        stamps: str = "live",
        faults: str = "",
        odometry: str = "white",
        flight_controller: str = "model",
        latency_error_ms: float = 10.0,
        time_offset: str = "correct",
        onboard_estimator: str = "model",
        position_fixes: str = "send",
        command: str = DEFAULT_COMMAND,
        contact: str = "hold",
        duration_s: float | None = None,
        hover_s: float = PerchSetup.hover_s,
    ) -> PerchCampaign:
        """Check the options as a user gave them; raise ``PerchposeError`` naming the one at
        fault. ``duration_s``: how long a run may fly (None: ``PerchSetup.duration_s``, or
        ``FAULT_RUN_S`` with faults). ``hover_s``: how long each vehicle hovers in its wind
        before the pilot takes over."""
        names = list(comma_list(estimators))
        injected = comma_list(faults)
        unknown = [n for n in names if n not in ESTIMATORS]
        if unknown or not names:
            raise PerchposeError(
                f"--estimator: unknown {unknown or names} (choose from {', '.join(ESTIMATORS)})"
            )
        if len(set(names)) != len(names):
            raise PerchposeError(f"--estimator: {estimators!r} names an estimator twice")
        if runs < 1:
            raise PerchposeError(f"--runs must be >= 1, got {runs}")
        check_vehicle_options(flight_controller, onboard_estimator, sensing, odometry)
        if position_fixes not in POSITION_FIXES:
            raise PerchposeError(
                f"--position-fixes: unknown {position_fixes!r} "
                f"(choose {' or '.join(POSITION_FIXES)})"
            )
        if command not in COMMANDS:
            raise PerchposeError(f"--command: unknown {command!r} (choose {', '.join(COMMANDS)})")
        if contact not in CONTACT_MODES:
            raise PerchposeError(
                f"--contact: unknown {contact!r} (choose {' or '.join(CONTACT_MODES)})"
            )
        if odometry not in ODOMETRY_ERRORS:
            raise PerchposeError(
                f"--odometry: unknown {odometry!r} (choose {' or '.join(ODOMETRY_ERRORS)})"
            )
        if time_offset not in TIME_OFFSETS:
            raise PerchposeError(
                f"--time-offset: unknown {time_offset!r} (choose {' or '.join(TIME_OFFSETS)})"
            )
        if not (math.isfinite(latency_error_ms) and 0.0 <= latency_error_ms <= 200.0):
            raise PerchposeError(
                f"--latency-error-ms must be between 0 and 200, got {latency_error_ms:g}"
            )
        if not (math.isfinite(hover_s) and 0.0 <= hover_s <= MAX_HOVER_S):
            raise PerchposeError(
                f"--hover-s must be between 0 and {MAX_HOVER_S:g} s, got {hover_s:g}"
            )
        if sweep == "wind" and (wind_mps is not None or gust_mps is not None):
            raise PerchposeError("--sweep wind flies the named levels: drop --wind-mps/--gust-mps")
        if sweep == "latency" and latency_ms is not None:
            raise PerchposeError("--sweep latency flies 0-200 ms: drop --latency-ms")
        base = PerchSetup(
            camera,
            TargetSpec.paper(),
            estimator=names[0],
            disturbances=Disturbances() if disturbances else Disturbances.none(),
            stamps=stamps,
            duration_s=run_length_s(duration_s, faulty=bool(injected)),
            hover_s=hover_s,
            flight_controller=flight_controller,
            onboard_estimator=onboard_estimator,
            pilot=PilotSettings(
                command=command,
                lean_lag_s=(
                    CRAZYFLIE_KALMAN_LAG_S if onboard_estimator == "crazyflie-kalman" else 0.0
                ),
            ),
            contact_mode=contact,
        )
        latencies = SWEEP_LATENCIES_MS if sweep == "latency" else (latency_ms,)
        timed = [
            fixes_setup(
                offset_setup(
                    replace(timed_setup(base, sensing, fps, ms, odometry), faults=injected),
                    latency_error_ms,
                    time_offset,
                ),
                position_fixes,
            )
            for ms in latencies
        ]
        winds = list(WIND_LEVELS) if sweep == "wind" else [wind]
        setups = tuple(
            replace(t, estimator=e, wind=w, wind_mps=wind_mps, gust_mps=gust_mps)
            for t in timed
            for w in winds
            for e in names
        )
        return PerchCampaign(setups, runs, seed)

    def fly(
        self,
        out: str,
        *,
        workers: int = 1,
        scheduler: str | None = None,
        resume: bool = False,
        overwrite: bool = False,
        progress: bool = False,
        say: Callable[[str], None] = print,
    ) -> dict[str, object]:
        """Fly every run not already in ``out`` (with ``resume``), writing each as it
        finishes; then the reports. Returns the summary JSON."""
        base = self.setups[0]
        with CampaignLog(out, base, resume=resume, overwrite=overwrite) as log:
            done = log.done
            jobs = campaign_jobs(
                list(self.setups), self.runs, self.seed, lambda s, k: run_key(s, k) in done
            )
            wanted = {
                run_key(s, k) for s in self.setups for k in range(self.seed, self.seed + self.runs)
            }
            if resume and log.records:
                kept = sum(r.key in wanted for r in log.records)
                others = len(log.records) - kept
                aside = (
                    f" ({others} rows of other seeds or cells stay in it, out of the reports)"
                    if others
                    else ""
                )
                say(f"{kept} runs kept from {log.path}{aside}; {len(jobs)} to fly")
            cells = len(self.setups)
            plural = "s" * (cells > 1)
            flown = (
                ""
                if base.flight_controller == "model"
                else f"; the Crazyflie firmware's {base.flight_controller} controller flies it"
            )
            if base.onboard_estimator == "crazyflie-kalman":
                flown += (
                    "; the firmware's Kalman filter estimates its state from a simulated IMU, "
                    "Flow deck and range sensor"
                )
            if base.pilot.command == "full-state":
                flown += (
                    "; the pilot sends full-state setpoints, which the vehicle's position loop "
                    "holds"
                )
            elif base.pilot.command == "attitude":
                flown += (
                    "; the pilot sends attitude setpoints (a lean and a height) and flies the "
                    "horizontal velocity loop itself"
                )
            say(
                f"{len(jobs)} runs: {cells} cell{plural} of {self.runs} runs; {senses(base)}{flown}"
            )
            trajectories: list[PerchResult] = []
            for setup, result in execute(
                jobs, workers=workers, scheduler=scheduler, progress=progress
            ):
                log.add(RunRecord.of(result, setup))
                cell = (setup.estimator, setup.wind, setup.latency_label)
                if cell == (base.estimator, base.wind, base.latency_label):
                    trajectories.append(result)
            trajectories.sort(key=lambda r: r.seed)
            return write_reports(log, base, trajectories[:TRAJECTORIES], wanted)


SWEEP_LATENCIES_MS = (0.0, 50.0, 100.0, 150.0, 200.0)  # --sweep latency
FAULT_RUN_S = 40.0  # a run with a fault goes on through its landing
MAX_RUN_S = 600.0  # the longest run --duration-s flies (a Crazyflie's battery lasts about 7 min)
MAX_HOVER_S = 60.0  # the longest hover before a run --hover-s flies (its CPU: a run's worth)


@dataclass(frozen=True)
class PerchOptions:
    """A campaign as ``perchpose perch`` takes it: the cells (``PerchCampaign.from_options``'
    arguments, the camera as the commands name it), where to write (``out``, and the summary
    JSON also to ``json_out``), and how to fly (``workers``, a Dask ``scheduler``, ``resume``)."""

    out: str = "perch"
    estimators: str = "covariance,paper,truth"
    runs: int = 200
    seed: int = 0
    wind: str = "none"
    wind_mps: float | None = None
    gust_mps: float | None = None
    sweep: str | None = None
    disturbances: bool = True
    sensing: str = "realistic"
    fps: float = 30.0
    latency_ms: float | None = None
    camera_file: str = "preset:fpv"
    json_out: str | None = None
    workers: int = 2
    scheduler: str | None = None
    resume: bool = False
    progress: bool = False
    stamps: str = "live"
    overwrite: bool = False
    faults: str = ""
    odometry: str = "white"
    flight_controller: str = "model"
    latency_error_ms: float = 10.0
    time_offset: str = "correct"
    onboard_estimator: str = "model"
    position_fixes: str = "send"
    command: str = DEFAULT_COMMAND
    contact: str = "hold"
    duration_s: float | None = None
    hover_s: float = PerchSetup.hover_s


def run(options: PerchOptions, say: Callable[[str], None] = print) -> dict[str, object]:
    """Plan the campaign, fly it and write its reports; the summary JSON."""
    campaign = PerchCampaign.from_options(
        load_camera(options.camera_file),
        estimators=options.estimators,
        runs=options.runs,
        seed=options.seed,
        wind=options.wind,
        wind_mps=options.wind_mps,
        gust_mps=options.gust_mps,
        sweep=options.sweep,
        disturbances=options.disturbances,
        fps=options.fps,
        latency_ms=options.latency_ms,
        sensing=options.sensing,
        stamps=options.stamps,
        faults=options.faults,
        odometry=options.odometry,
        flight_controller=options.flight_controller,
        latency_error_ms=options.latency_error_ms,
        time_offset=options.time_offset,
        onboard_estimator=options.onboard_estimator,
        position_fixes=options.position_fixes,
        command=options.command,
        contact=options.contact,
        duration_s=options.duration_s,
        hover_s=options.hover_s,
    )
    content = campaign.fly(
        options.out,
        workers=max(1, options.workers),
        scheduler=options.scheduler,
        resume=options.resume,
        overwrite=options.overwrite,
        progress=options.progress,
        say=say,
    )
    if options.json_out:
        text = json.dumps(content, indent=2, default=str)
        Path(options.json_out).write_text(text, encoding="utf-8")
    return content


def run_length_s(duration_s: float | None, *, faulty: bool) -> float:
    """How long a run may fly: ``duration_s`` as asked (checked), or the default
    (``PerchSetup.duration_s``; ``FAULT_RUN_S`` with faults, which fly on through the
    landing)."""
    if duration_s is None:
        return FAULT_RUN_S if faulty else PerchSetup.duration_s
    if not (math.isfinite(duration_s) and 0.0 < duration_s <= MAX_RUN_S):
        raise PerchposeError(
            f"--duration-s must be more than 0 and at most {MAX_RUN_S:g} s, got {duration_s:g}"
        )
    return duration_s


def comma_list(text: str) -> tuple[str, ...]:
    """The names of a comma-separated option (``covariance,truth``), blanks dropped."""
    return tuple(name.strip() for name in text.split(",") if name.strip())


def timed_setup(
    base: PerchSetup,
    sensing: str,
    fps: float,
    latency_ms: float | None,
    odometry: str = "white",
) -> PerchSetup:
    """``base`` with the senses, frame rate and latency asked for (None: the senses' own) and
    the realistic odometry's error (``odometry``)."""
    if not (math.isfinite(fps) and fps > 0):
        raise PerchposeError(f"--fps must be a positive number, got {fps:g}")
    try:
        if sensing == "ideal":
            return base.with_timing(fps, latency_frames(fps, latency_ms))
        senses = Sensing(odometry=odometry)
        if latency_ms is not None:
            senses = senses.with_latency(latency_seconds(latency_ms))
        return base.with_sensing(senses).with_timing(fps, 1)
    except PerchposeError as exc:  # the controller's or the simulation's own check
        raise PerchposeError(f"--fps / --latency-ms: {exc}") from exc


def offset_setup(setup: PerchSetup, latency_error_ms: float, time_offset: str) -> PerchSetup:
    """``setup`` with the user's latency measure off by up to ``latency_error_ms`` (realistic
    senses), and the controller correcting the frames' stamps by its online time-offset
    estimate (``correct``) or only estimating it (``report``)."""
    controller = replace(setup.controller, correct_time_offset=time_offset == "correct")
    if setup.sensing.is_ideal:
        return replace(setup, controller=controller)
    sensing = replace(setup.sensing, latency_error_s=latency_error_ms / 1000.0)
    return replace(setup, sensing=sensing, controller=controller)


def check_vehicle_options(
    flight_controller: str, onboard_estimator: str, sensing: str, odometry: str
) -> None:
    """Check the vehicle's onboard loops and estimator as the user named them (the
    firmware's need its module); raise ``PerchposeError`` naming the option at fault."""
    if flight_controller not in FLIGHT_CONTROLLERS:
        raise PerchposeError(
            f"--flight-controller: unknown {flight_controller!r} "
            f"(choose {', '.join(FLIGHT_CONTROLLERS)})"
        )
    try:
        check_flight_controller(flight_controller)
    except PerchposeError as exc:
        raise PerchposeError(f"--flight-controller: {exc}") from exc
    if flight_controller != "model":
        try:
            load_firmware()
        except PerchposeError as exc:
            raise PerchposeError(f"--flight-controller {flight_controller}: {exc}") from exc
    if onboard_estimator not in ONBOARD_ESTIMATORS:
        raise PerchposeError(
            f"--onboard-estimator: unknown {onboard_estimator!r} "
            f"(choose {', '.join(ONBOARD_ESTIMATORS)})"
        )
    if onboard_estimator != "model":
        if sensing == "ideal":
            raise PerchposeError(
                f"--onboard-estimator {onboard_estimator} flies on realistic senses: "
                "drop --sensing ideal"
            )
        if odometry != "white":
            raise PerchposeError(
                f"--odometry {odometry} is the model estimator's error; with "
                f"--onboard-estimator {onboard_estimator} the odometry is the filter's own: "
                "drop --odometry"
            )
        try:
            load_firmware()
        except PerchposeError as exc:
            raise PerchposeError(f"--onboard-estimator {onboard_estimator}: {exc}") from exc


def fixes_setup(setup: PerchSetup, position_fixes: str) -> PerchSetup:
    """``setup`` with the pilot handing its fixes to the vehicle's estimator (``send``; only
    a Kalman filter in the loop takes them) or not (``off``)."""
    fixes = replace(setup.controller.position_fixes, send=position_fixes == "send")
    return replace(setup, controller=replace(setup.controller, position_fixes=fixes))


def senses(setup: PerchSetup) -> str:
    """The campaign's senses in words."""
    if setup.sensing.is_ideal:
        frames = setup.latency_frames
        return (
            f"ideal senses, camera at {setup.fps:g} fps, {setup.latency_s * 1000:.0f} ms of "
            f"latency ({frames} frame{'s' * (frames != 1)})"
        )
    low, high = (v * 1000.0 for v in setup.latency_range_s)
    latency = f"{low:.0f} ms" if low == high else f"{low:.0f}-{high:.0f} ms"
    odometry = "flow-deck (correlated)" if setup.sensing.odometry == "flow-deck" else "white-noise"
    if setup.onboard_estimator == "crazyflie-kalman":
        fused = ", the camera's fixes fused" if setup.controller.position_fixes.send else ""
        odometry = f"Kalman-filter (the firmware's{fused})"
    error_ms = setup.sensing.latency_error_s * 1000.0
    stamps = (
        "frames stamped as live sources stamp them, the latency set off by up to "
        f"{error_ms:g} ms (--stamps exact: their true capture time)"
        if setup.stamps == "live"
        else "frames stamped with their true capture time"
    )
    if setup.controller.correct_time_offset:
        stamps += "; the time offset estimated online and corrected"
    else:
        stamps += "; the time offset estimated online, not corrected (--time-offset report)"
    return (
        f"realistic senses, camera at {setup.fps:g} fps with {latency} of latency, {odometry} "
        "odometry and attitude late and noisy, calibration, mount and print off (--sensing "
        f"ideal: none); {stamps}"
    )


def latency_seconds(latency_ms: float) -> float:
    if not (math.isfinite(latency_ms) and latency_ms >= 0):
        raise PerchposeError(f"--latency-ms must be >= 0, got {latency_ms}")
    return latency_ms / 1000.0


def latency_frames(fps: float, latency_ms: float | None) -> int:
    """Whole frames of camera latency for ``latency_ms`` at ``fps`` (None: one frame, the
    fastest a frame can be captured, sent and measured); the simulated camera delivers a frame
    on a later frame's tick, so a latency between ticks rounds to the nearest."""
    if not (math.isfinite(fps) and fps > 0):
        raise PerchposeError(f"--fps must be a positive number, got {fps}")
    if latency_ms is None:
        return 1
    return round(latency_seconds(latency_ms) * fps)


def summary_table(content: dict[str, object]) -> str:
    """The terminal's table: one line per cell (wind, estimator and, where several were
    flown, latency)."""
    cells = content["cells"]
    assert isinstance(cells, dict)
    lines = [
        f"{'wind':9} {'estimator':10} {'latency':>8} {'runs':>5} {'perched':>8} "
        f"{'95 % interval':>15} {'offset p50/p95 (mm)':>20} {'clock p95 (ms)':>14}  failures"
    ]

    def num(v: object) -> str:
        return f"{v:.1f}" if isinstance(v, float) and math.isfinite(v) else "-"

    for name, c in cells.items():
        wind, estimator, *latency = name.split("/")
        low, high = c["success_interval_95"]
        off = c["contact_offset_mm"]
        fails = ", ".join(f"{k} {v}" for k, v in c["reasons"].items() if k != "perched" and v)
        clock = c["time_offset"]["error_ms"]["p95"]  # the time-offset estimate's error at 3 s
        lines.append(
            f"{wind:9} {estimator:10} {(latency or [content['latency_label']])[0]:>8} "
            f"{c['runs']:5d} {c['success_rate']:8.1%} "
            f"{low:6.1%} - {high:6.1%} {num(off['p50']):>9}/{num(off['p95']):<10} "
            f"{num(clock):>14}  {fails or 'none'}"
        )
    for name, c in cells.items():
        checks = c.get("runs_with_seat_drops", 0)
        refused = c.get("leans_refused", 0)
        if checks or refused:
            lines.append(
                f"{name}: the magnet did not hold the vehicle in {c['seat_drops']} checks before "
                f"a stop, in {checks} runs (flown on); the vehicle did not fly the leans sent "
                f"in {refused} runs (velocities sent instead)"
            )
    outcomes = content.get("fault_outcomes") or {}
    assert isinstance(outcomes, dict)
    for kind, o in outcomes.items():
        ended = ", ".join(f"{k} {v}" for k, v in o["ended"].items())
        lines.append(
            f"{kind}: {o['runs']} runs ({ended}); motor stops above 5 cm: "
            f"{o['motor_stops_above_5cm']}; longest without a setpoint: "
            f"{o['max_setpoint_gap_s']:.3f} s"
        )
    return "\n".join(lines) + "\n"
