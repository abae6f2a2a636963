"""Faults injected into perching runs: the deployed pilot's watchdogs in the loop, and runs that
go on through the landing until the motors stop."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from perchpose import CameraModel, TargetSpec
from perchpose.cli import main
from perchpose.errors import VehicleConfigError
from perchpose.sim.faults import DURATIONS_S, FAULTS, START_S, Fault, check_faults
from perchpose.sim.perch import FALL_M, PerchResult, PerchSetup, run_perch
from perchpose.sim.sensing import Sensing

BOUND_S = 0.2  # the longest a Crazyflie may go without a setpoint before its watchdog acts


def _run(fault: str, seed: int) -> PerchResult:
    setup = PerchSetup(
        CameraModel.preset("fpv"),
        TargetSpec.paper(),
        estimator="truth",
        wind="moderate",
        duration_s=40.0,
    ).with_sensing(Sensing())
    return run_perch(replace(setup, faults=(fault,)), seed)


def _states(result: PerchResult) -> list[str]:
    return [part.split("@")[0] for part in result.pilot_states.split(";")]


def test_faults_are_drawn_in_their_ranges() -> None:
    rng = np.random.default_rng(0)
    drawn = [Fault.draw(FAULTS, rng) for _ in range(400)]
    assert {f.kind for f in drawn if f is not None} == set(FAULTS)
    for f in drawn:
        assert f is not None
        assert START_S[0] <= f.start_s <= START_S[1]
        low, high = DURATIONS_S[f.kind]
        assert low <= f.duration_s <= high
        assert f.active(f.start_s)
        assert not f.active(f.start_s + f.duration_s)
    assert Fault.draw((), rng) is None
    with pytest.raises(VehicleConfigError, match="unknown fault 'gps-loss'"):
        check_faults(("camera-stall", "gps-loss"))
    with pytest.raises(VehicleConfigError, match="names a fault twice"):
        check_faults(("link-loss", "link-loss"))


def test_a_camera_that_stalls_for_good_lands_the_vehicle_on_its_floor() -> None:
    """A stall of 4 s: the pilot's clock goes on without frames (no setpoint gap over the
    watchdog's bound), holds, loses the target, lands 4 s after the last sighting and stops
    the motors only once the vehicle stands on the floor."""
    result = _run("camera-stall", 500001)
    assert result.fault is not None
    assert result.fault.kind == "camera-stall"
    assert result.fault.duration_s > 4.0
    assert _states(result)[-3:] == ["lost", "landing", "landed"]
    assert result.motor_stop_height_m == 0.0
    assert result.max_setpoint_gap_s < BOUND_S
    assert not result.success


def test_a_short_camera_stall_is_flown_through() -> None:
    result = _run("camera-stall", 500004)
    assert result.fault is not None
    assert result.fault.duration_s < 1.5
    assert result.success
    assert "landing" not in _states(result)
    assert result.max_setpoint_gap_s < BOUND_S


def test_odometry_that_stops_lands_the_vehicle() -> None:
    """The odometry stream stops for 1.6 s: the pilot hovers after 0.25 s, lands after 1 s
    and stops the motors on the floor."""
    result = _run("odometry-stall", 500001)
    assert result.fault is not None
    assert result.fault.duration_s > 1.0
    assert _states(result)[-2:] == ["landing", "landed"]
    assert result.motor_stop_height_m == 0.0


def test_a_link_lost_past_the_crazyflie_watchdog_stops_its_motors_in_the_air() -> None:
    """The firmware's own watchdog stops the motors 2 s after the last setpoint, wherever the
    vehicle is: no pilot on the ground can prevent it, and the run says where it fell from."""
    result = _run("link-loss", 500000)
    assert result.fault is not None
    assert result.fault.duration_s > 2.0
    assert result.reason == "crash"
    assert result.motor_stop_height_m > FALL_M


def test_perch_with_faults_reports_how_each_run_ended(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "f"
    argv = ["perch", "--runs", "2", "--estimator", "truth", "--workers", "1", "--quiet"]
    assert main([*argv, "--faults", "camera-stall", "--out", str(out), "--seed", "7"]) == 0
    text = capsys.readouterr().out
    assert "camera-stall: 2 runs (" in text
    assert "motor stops above 5 cm:" in text
    rows = (out / "runs.csv").read_text().splitlines()
    header = rows[0].split(",")
    assert {"fault", "motor_stop_height_m", "pilot_states", "max_setpoint_gap_s"} <= set(header)
    assert all(r.split(",")[header.index("fault")] == "camera-stall" for r in rows[1:])
    for bad, message in (
        ("gps-loss", "unknown fault 'gps-loss'"),
        ("odometry-stall --sensing ideal", "needs realistic senses"),
    ):
        code = main([*argv, "--faults", *bad.split(), "--out", str(tmp_path / "x")])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2
        assert len(err) == 1
        assert message in err[0]
