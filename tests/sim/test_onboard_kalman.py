import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from perchpose.app.inputs import load_camera
from perchpose.app.perch import PerchCampaign, PerchOptions, run
from perchpose.control.lean import CRAZYFLIE_KALMAN_LAG_S
from perchpose.errors import PerchposeError, SensingConfigError
from perchpose.sim import onboard_kalman
from perchpose.sim.flow_deck import FlowDeck
from perchpose.sim.onboard_kalman import CrazyflieKalman, KalmanSenses, range_std_m
from perchpose.sim.perch import run_perch
from perchpose.sim.quadrotor import Quadrotor, QuadrotorParams

DT = 1 / 500


def _flown(
    wind_mps: tuple[float, float, float], seconds: float, seed: int = 3
) -> tuple[Quadrotor, CrazyflieKalman, np.ndarray]:
    """A vehicle whose own loops fly on the firmware's Kalman filter, asked to weave
    (0.3 m/s along x, 0.2 m/s along y, slowly), in a steady wind; the filter's velocity
    error (world x, y, z) at each step after the first second."""
    fw = pytest.importorskip("cffirmware")
    q = Quadrotor.hovering(QuadrotorParams(), np.array([0.1, 0.2, 1.0]), 0.3)
    kalman = CrazyflieKalman(fw, KalmanSenses(), FlowDeck(), np.random.default_rng(seed), q)
    kalman.settle(q)
    q.estimator = kalman
    q.wind_mps = wind_mps
    errors = []
    for i in range(round(seconds / DT)):
        t = i * DT
        v_sp = np.array([0.3 * math.sin(t), 0.2 * math.cos(0.7 * t), 0.0])
        q.fly(DT, 1, v_sp, 0.0, np.zeros(3))
        if t >= 1.0:
            errors.append(kalman.velocity_mps - q.v_mps)
    return q, kalman, np.array(errors)


def test_the_vehicle_flies_on_the_firmware_kalman_fed_by_imu_flow_and_range() -> None:
    """In still air the filter's velocity stays within a few cm/s of the truth and its
    position within a few cm (it drifts: nothing fixes the position), the vehicle's own loops
    fly on its estimate, and the flow and range are fused at the deck's rates."""
    q, kalman, errors = _flown((0.0, 0.0, 0.0), 6.0)
    rms = np.sqrt(np.mean(errors**2, axis=0))
    assert np.all(rms[:2] < 0.06), rms
    assert abs(float(kalman.position[2]) - float(q.p_m[2])) < 0.03
    assert np.linalg.norm(kalman.position_m[:2] - q.p_m[:2]) < 0.2
    flown_s = onboard_kalman.SETTLE_MS / 1000 + 6.0
    assert kalman.flow_reads == pytest.approx(flown_s * 100, abs=2)
    assert kalman.range_reads == pytest.approx(flown_s * 40, abs=2)
    R_err = q.R_world_body.T @ kalman.R_world_body
    assert math.degrees(math.acos(min(1.0, (np.trace(R_err) - 1) / 2))) < 3.0
    # the loops follow the filter: the vehicle's velocity is the setpoint less its error
    assert q.R_estimate == pytest.approx(kalman.R_world_body)


def test_in_a_steady_wind_the_drag_free_filter_biases_its_velocity() -> None:
    """The firmware's filter, flying, takes the accelerometer's z alone and models no drag:
    held against a 3 m/s wind the vehicle leans, the filter reads the lean as acceleration
    and the flow pulls it back a time constant later, so its velocity lags the truth upwind by
    tens of cm/s (the vehicle drifts downwind by as much, the loops flying the estimate)."""
    _, _, still = _flown((0.0, 0.0, 0.0), 4.0)
    _, _, windy = _flown((3.0, 0.0, 0.0), 4.0)
    assert abs(float(np.mean(still[:, 0]))) < 0.05
    assert float(np.mean(windy[:, 0])) < -0.1  # the estimate says slower downwind than true


def test_the_range_spread_is_the_deck_drivers() -> None:
    assert range_std_m(2.5) == pytest.approx(0.005)
    assert range_std_m(4.0) == pytest.approx(0.2025)
    assert range_std_m(0.5) < range_std_m(1.5) < range_std_m(3.0)


def test_bad_senses_and_estimators_are_refused(tmp_path: Path) -> None:
    with pytest.raises(SensingConfigError, match="gyro_noise_dps"):
        KalmanSenses(gyro_noise_dps=-1.0)
    with pytest.raises(SensingConfigError, match="unknown onboard estimator 'ekf'"):
        onboard_kalman.check_onboard_estimator("ekf")
    with pytest.raises(PerchposeError, match="--onboard-estimator: unknown 'ekf'"):
        run(PerchOptions(str(tmp_path), runs=1, onboard_estimator="ekf"))
    kalman = "crazyflie-kalman"
    with pytest.raises(PerchposeError, match="flies on realistic senses"):
        run(PerchOptions(str(tmp_path), runs=1, onboard_estimator=kalman, sensing="ideal"))
    with pytest.raises(PerchposeError, match="drop --odometry"):
        run(PerchOptions(str(tmp_path), runs=1, onboard_estimator=kalman, odometry="flow-deck"))


@pytest.mark.usefixtures("without_cffirmware")
def test_without_the_firmware_module_the_estimator_says_how_to_build_it(tmp_path: Path) -> None:
    options = PerchOptions(
        str(tmp_path), estimators="truth", runs=1, onboard_estimator="crazyflie-kalman"
    )
    with pytest.raises(PerchposeError, match=r"--onboard-estimator crazyflie-kalman: .*cffirmware"):
        run(options)


def test_a_campaign_on_the_firmware_kalman_says_so(tmp_path: Path) -> None:
    pytest.importorskip("cffirmware")
    said: list[str] = []
    options = PerchOptions(
        str(tmp_path),
        estimators="truth",
        runs=1,
        seed=5,
        onboard_estimator="crazyflie-kalman",
        workers=1,
    )
    content = run(options, say=said.append)
    assert content["onboard_estimator"] == "crazyflie-kalman"
    assert "the firmware's Kalman filter estimates its state" in said[-1]
    assert "Kalman-filter (the firmware's, the camera's fixes fused) odometry" in said[-1]
    written = json.loads((tmp_path / "perch.json").read_text())
    assert written["setup"]["onboard_estimator"] == "crazyflie-kalman"
    assert written["lean_lag_s"] == CRAZYFLIE_KALMAN_LAG_S  # its attitude misses the lean
    assert written["gyro_blend_s"] == written["setup"]["gyro_blend_s"] == 3.0


def test_the_fixes_fused_by_the_filter_are_what_lets_it_perch() -> None:
    """Still air, the true pose, realistic senses, velocity setpoints: on the firmware's
    filter the pilot perches when its fixes reach the filter and, the same run without them,
    flying the filter's odometry as it comes, never meets the capture cone (the filter's
    drift, which only the camera sees). (The pilot's inertial filter, which corrects that
    drift itself, is left out of the second run.)"""
    pytest.importorskip("cffirmware")
    campaign = PerchCampaign.from_options(
        load_camera("preset:fpv"),
        estimators="truth",
        runs=1,
        onboard_estimator="crazyflie-kalman",
        command="velocity",
    )
    # scored at the first touch: the magnet's pull forgives a touch 14 mm off-centre, which
    # the run without fixes makes once the magnet catches it; the cone is what this is about
    setup = replace(campaign.setups[0], contact_mode="first-touch")
    fused = run_perch(setup, 960002)
    assert fused.success, fused.reason
    off = replace(setup.controller.position_fixes, send=False)
    inertial_off = replace(setup.controller.inertial, enabled=False)
    controller = replace(setup.controller, position_fixes=off, inertial=inertial_off)
    alone = run_perch(replace(setup, controller=controller), 960002)
    assert alone.reason == "timeout"


def test_in_moderate_wind_the_pilot_perches_once_it_takes_out_the_lean_the_filter_misses() -> None:
    """Moderate wind, the firmware's PID on its Kalman filter, the true pose, velocity
    setpoints: the filter reads the lean into the wind as acceleration and corrects its
    attitude toward level, so the pilot, turning the camera's view into the world with that
    attitude, puts the target centimetres off and never meets the capture cone. With the lean
    the push needs taken out (``PilotSettings.lean_lag_s``, which the campaign sets for this
    filter) the run perches."""
    pytest.importorskip("cffirmware")
    campaign = PerchCampaign.from_options(
        load_camera("preset:fpv"),
        estimators="truth",
        runs=1,
        wind="moderate",
        flight_controller="crazyflie-pid",
        onboard_estimator="crazyflie-kalman",
        command="velocity",
    )
    setup = campaign.setups[0]
    assert setup.pilot.lean_lag_s == CRAZYFLIE_KALMAN_LAG_S
    corrected = run_perch(setup, 1960004)
    assert corrected.success, corrected.reason
    # the same pilot believing the filter's tilt (at the vehicle's own gain, as it keeps
    # on this filter: without a lean to take out it would raise it)
    believing = replace(setup.pilot, lean_lag_s=0.0, velocity_gain_per_s=None)
    as_it_says = run_perch(replace(setup, pilot=believing), 1960004)
    assert as_it_says.reason == "timeout"
