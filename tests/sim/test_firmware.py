import json
import math
from pathlib import Path

import numpy as np
import pytest

from perchpose.app.perch import PerchOptions, run
from perchpose.errors import PerchposeError, VehicleConfigError
from perchpose.sim import firmware
from perchpose.sim.quadrotor import Quadrotor, QuadrotorParams

DT = 1 / 500


@pytest.mark.usefixtures("without_cffirmware")
def test_without_the_firmware_module_the_error_says_how_to_build_it(tmp_path: Path) -> None:
    with pytest.raises(VehicleConfigError, match="install-cffirmware"):
        firmware.load_firmware()
    options = PerchOptions(
        str(tmp_path), estimators="truth", runs=1, flight_controller="crazyflie-pid"
    )
    with pytest.raises(PerchposeError, match=r"--flight-controller crazyflie-pid: .*cffirmware"):
        run(options)
    with pytest.raises(PerchposeError, match="--flight-controller: unknown 'crazyflie-bogus'"):
        run(PerchOptions(str(tmp_path), runs=1, flight_controller="crazyflie-bogus"))


def test_a_physics_rate_the_firmware_loop_cannot_divide_is_refused() -> None:
    pytest.importorskip("cffirmware")
    with pytest.raises(VehicleConfigError, match="divides it, got 300 Hz"):
        firmware.FirmwareQuadrotor("crazyflie-pid", 300.0)


def test_controllers_that_need_position_setpoints_are_refused(tmp_path: Path) -> None:
    with pytest.raises(VehicleConfigError, match="crazyflie-mellinger holds thrust only on"):
        firmware.check_flight_controller("crazyflie-mellinger")
    options = PerchOptions(str(tmp_path), runs=1, flight_controller="crazyflie-lee")
    with pytest.raises(PerchposeError, match="--flight-controller: crazyflie-lee holds thrust"):
        run(options)


def _settled_firmware(
    start: np.ndarray, yaw_rad: float = 0.0, controller: str = "crazyflie-pid"
) -> Quadrotor:
    """A vehicle hovering at ``start`` on the firmware's ``controller``, its integrators
    settled as after a take-off (``FirmwareQuadrotor.settle``)."""
    q = firmware.FirmwareQuadrotor.hovering_on_firmware(
        controller, 500.0, QuadrotorParams(), start, yaw_rad
    )
    q.settle()
    return q


def test_the_firmware_flies_the_velocity_and_yaw_rate_cflib_sends() -> None:
    """Settled in a hover, the firmware's controller holds height, follows a 0.3 m/s world
    velocity along x and then y, and turns counter-clockwise for a positive yaw rate, as
    cflib's send_velocity_world_setpoint asks of it."""
    pytest.importorskip("cffirmware")
    start = np.array([0.2, -0.1, 1.0])
    q = _settled_firmware(start, 0.4)
    np.testing.assert_allclose(q.p_m, start)

    def fly(seconds: float, v_sp: tuple[float, float, float], yaw_rate: float = 0.0) -> None:
        for _ in range(round(seconds / DT)):
            q.fly(DT, 1, np.array(v_sp), yaw_rate, q.v_mps)

    fly(1.0, (0.0, 0.0, 0.0))
    assert abs(q.p_m[2] - 1.0) < 0.02  # the integrators hold the hover of a 39 g vehicle
    assert np.linalg.norm(q.v_mps) < 0.02
    fly(1.5, (0.3, 0.0, 0.0))
    np.testing.assert_allclose(q.v_mps, [0.3, 0.0, 0.0], atol=0.04)
    fly(1.5, (0.0, 0.3, 0.0))
    np.testing.assert_allclose(q.v_mps, [0.0, 0.3, 0.0], atol=0.04)
    yaw_before = q.yaw_rad
    fly(1.0, (0.0, 0.0, 0.0), yaw_rate=0.5)
    turned = math.remainder(q.yaw_rad - yaw_before, math.tau)
    assert 0.3 < turned < 0.6  # about 0.5 rad, counter-clockwise
    assert all(0 < m <= firmware.FULL_COMMAND for m in q.motor_command)
    # a pilot's velocity gain reaches the firmware's velocity PID as a param write would
    assert q.set_velocity_gain(6.0)
    assert q.set_velocity_gain(None)


def test_a_campaign_flown_by_the_firmware_says_so(tmp_path: Path) -> None:
    pytest.importorskip("cffirmware")
    out = tmp_path / "fw"
    said: list[str] = []
    options = PerchOptions(
        str(out),
        estimators="truth",
        runs=2,
        seed=700000,
        workers=1,
        flight_controller="crazyflie-pid",
    )
    content = run(options, say=said.append)
    summary = json.loads((out / "perch.json").read_text())
    assert summary["flight_controller"] == "crazyflie-pid"
    assert summary["onboard_estimator"] == "model"
    assert any("crazyflie-pid controller flies it" in line for line in said)
    assert content["runs"] == 2


@pytest.mark.parametrize("controller", ["model", "crazyflie-pid"])
def test_a_full_state_setpoint_is_held_on_the_vehicles_own_estimate(controller: str) -> None:
    """A full-state setpoint held by the model's loops and by the firmware's PID position
    loop (given as cflib's send_full_state_setpoint decodes), on the vehicle's own position
    estimate, which reads 5 cm too far along x: the vehicle settles where its estimate puts the
    setpoint (5 cm short of it in truth), at the yaw asked, within 5 s."""
    from perchpose.sim.quadrotor import PositionHold, Quadrotor

    start = np.array([0.0, 0.0, 1.0])
    if controller == "model":
        q = Quadrotor.hovering(QuadrotorParams(), start, 0.0)
    else:
        pytest.importorskip("cffirmware")
        q = _settled_firmware(start, 0.0, controller)
    offset = np.array([0.05, 0.0, 0.0])
    target = (0.2, -0.1, 1.1)
    for _ in range(round(5.0 / 0.01)):  # the estimate comes at 100 Hz
        p_est = q.p_m + offset
        q.hold = PositionHold(target, 0.3, (float(p_est[0]), float(p_est[1]), float(p_est[2])))
        q.fly(DT, 5, np.zeros(3), 0.0, q.v_mps)
    expected = np.array(target) - offset
    np.testing.assert_allclose(q.p_m[:2], expected[:2], atol=0.01)
    # the firmware's height loop overshoots a 10 cm climb by about 2 cm and its integrators
    # take it back over seconds
    assert abs(q.p_m[2] - expected[2]) < 0.03
    assert abs(math.remainder(q.yaw_rad - 0.3, math.tau)) < 0.03
    assert np.linalg.norm(q.v_mps) < 0.03


@pytest.mark.parametrize("controller", ["model", "crazyflie-pid"])
def test_an_attitude_setpoint_is_flown_as_a_lean_at_the_height_asked(controller: str) -> None:
    """An attitude setpoint (cflib's send_zdistance_setpoint as the commander decodes it) held
    by the model's loops and by the firmware's PID: heading 0.5 rad, a 4 deg nose-down pitch
    and a 2 deg roll to the left (negative), at a height 10 cm up on the vehicle's own
    estimate (5 cm high). The body leans as asked within 0.5 deg, and at 0.5 s (0.3 m/s, drag
    still small) it accelerates along the heading and to its left as ``leaned`` says, within
    15 %; within 3 s it holds the height its estimate puts at the setpoint (the firmware's
    PID resets its integrators at the change of setpoint mode, and sinks 4 cm before its
    height loop wins it back). Then a yaw rate asked is flown within 1 s."""
    from perchpose.geometry import leaned, roll_pitch_rad
    from perchpose.sim.quadrotor import AttitudeHold, Quadrotor

    yaw0 = 0.5
    start = np.array([0.0, 0.0, 1.0])
    if controller == "model":
        q = Quadrotor.hovering(QuadrotorParams(), start, yaw0)
    else:
        pytest.importorskip("cffirmware")
        q = _settled_firmware(start, yaw0, controller)
    offset = np.array([0.0, 0.0, 0.05])

    def hold(roll: float, pitch: float, yaw_rate: float) -> None:
        p_est = q.p_m + offset
        p = (float(p_est[0]), float(p_est[1]), float(p_est[2]))
        q.hold = AttitudeHold(roll, pitch, yaw_rate, 1.1, p)
        q.fly(DT, 5, np.zeros(3), 0.0, q.v_mps)  # the estimate comes at 100 Hz

    roll, pitch = math.radians(-2.0), math.radians(4.0)
    for _ in range(50):
        hold(roll, pitch, 0.0)
    got_roll, got_pitch = roll_pitch_rad(q.R_world_body)
    assert math.degrees(got_roll) == pytest.approx(-2.0, abs=0.5)
    assert math.degrees(got_pitch) == pytest.approx(4.0, abs=0.5)
    v0 = q.v_mps
    hold(roll, pitch, 0.0)
    a_xy = (q.v_mps[:2] - v0[:2]) / (5 * DT)
    expected = 9.81 * np.array(leaned(roll, pitch, q.yaw_rad))
    assert np.linalg.norm(a_xy - expected) < 0.15 * np.linalg.norm(expected)
    for _ in range(250):
        hold(roll, pitch, 0.0)
    assert abs(q.p_m[2] - 1.05) < 0.01
    for _ in range(100):
        hold(0.0, 0.0, 0.5)
    assert q.omega_rad_s[2] == pytest.approx(0.5, abs=0.05)


def _lean_step_deg(q: Quadrotor, at_s: tuple[float, ...]) -> list[float]:
    """The pitch (deg) at each of ``at_s`` after a 5 deg nose-down pitch is asked of a vehicle
    settled in a hover, its height held where it is (the truth as its estimate)."""
    from perchpose.geometry import roll_pitch_rad
    from perchpose.sim.quadrotor import AttitudeHold

    pitch_deg = []
    for k in range(round(max(at_s) / DT)):
        p = (float(q.p_m[0]), float(q.p_m[1]), float(q.p_m[2]))
        q.hold = AttitudeHold(0.0, math.radians(5.0), 0.0, 1.0, p)
        q.fly(DT, 1, np.zeros(3), 0.0, q.v_mps)
        if any(round(t / DT) == k + 1 for t in at_s):
            pitch_deg.append(math.degrees(roll_pitch_rad(q.R_world_body)[1]))
    return pitch_deg


def test_the_models_attitude_loop_leans_as_the_firmwares_pid() -> None:
    """A 5 deg lean asked of a hover: the model's attitude loop, on the firmware's attitude
    PID gains (``pidPitch`` kp 6 /s, ki 3 /s^2, its integral within 20 deg s), leans as the
    firmware's PID does within 0.2 deg at 0.1, 0.2, 0.4 and 1 s, the integral's overshoot
    included (the model's 8 /s before, without the integral, was 0.45 deg ahead at 0.1 s)."""
    pytest.importorskip("cffirmware")
    start = np.array([0.0, 0.0, 1.0])
    at_s = (0.1, 0.2, 0.4, 1.0)
    by_firmware = _lean_step_deg(_settled_firmware(start), at_s)
    by_model = _lean_step_deg(Quadrotor.hovering(QuadrotorParams(), start, 0.0), at_s)
    np.testing.assert_allclose(by_model, by_firmware, atol=0.2)
    assert by_firmware[-1] > 5.1  # the firmware's integral overshoots, and so does the model's


def _heights_mm(q: Quadrotor, plan: tuple[tuple[float, float], ...]) -> np.ndarray:
    """The height (mm, from the start) at each step of ``plan``'s attitude setpoints, each a
    (seconds, pitch in deg) held at the starting height."""
    from perchpose.sim.quadrotor import AttitudeHold

    z0_m, z_m = float(q.p_m[2]), []
    for seconds, pitch_deg in plan:
        for _ in range(round(seconds / DT)):
            p = (float(q.p_m[0]), float(q.p_m[1]), float(q.p_m[2]))
            q.hold = AttitudeHold(0.0, math.radians(pitch_deg), 0.0, z0_m, p)
            q.fly(DT, 1, np.zeros(3), 0.0, q.v_mps)
            z_m.append(float(q.p_m[2]))
    return 1000.0 * (np.array(z_m) - z0_m)


def _model_as_before(start: np.ndarray) -> Quadrotor:
    """The model's loops before they took the firmware's height loop: the thrust divided by
    the tilt's cosine, 4.3 /s and 2 /s^2, no height integral, the weight fed forward."""
    from dataclasses import replace

    params = QuadrotorParams()
    q = Quadrotor.hovering(params, start, 0.0)
    q.gains = replace(
        q.gains,
        tilt_compensated=True,
        k_velocity_z=4.3,
        k_velocity_i=(0.17, 2.0),
        k_height_i=0.0,
        thrust_base_n=params.weight_n,
    )
    return q


def test_the_models_height_loop_sinks_at_a_take_over_as_the_firmwares_pid() -> None:
    """A height-and-lean setpoint after the velocity ones a hover was flown on: the firmware's
    PID reinitialises on the change of mode (``controller_pid.c``), its vertical integral is
    gone and the thrust falls to ``thrustBase`` (36000: 33 g of the vehicle's 39), and the
    vehicle sinks about 85 mm before the integrals make it up. The model's loops do the same
    within 10 mm at 0.25, 0.5, 0.75, 1, 2 and 4 s; before, they did not sink at all."""
    pytest.importorskip("cffirmware")
    start = np.array([0.0, 0.0, 1.0])
    at = [round(t / DT) - 1 for t in (0.25, 0.5, 0.75, 1.0, 2.0, 4.0)]
    plan = ((4.0, 0.0),)
    by_firmware = _heights_mm(_settled_firmware(start), plan)[at]
    by_model = _heights_mm(Quadrotor.hovering(QuadrotorParams(), start, 0.0), plan)[at]
    assert by_firmware.min() < -70.0
    np.testing.assert_allclose(by_model, by_firmware, atol=10.0)
    assert abs(_heights_mm(_model_as_before(start), plan)[at]).max() < 1.0


def test_the_models_height_loop_sinks_in_a_lean_as_the_firmwares_pid() -> None:
    """A 20 deg lean held 1.5 s, then level 2 s, 3 s after the take-over: the firmware's PID
    sends its height loop's thrust as the collective, not divided by the tilt's cosine, so the
    vehicle sinks until the integral makes up the 6 % of lift lost, and climbs when it levels.
    The model's loops, on the firmware's vertical gains in SI, sink and climb within 8 mm of
    the firmware's; before, they were out by over 30 mm."""
    pytest.importorskip("cffirmware")
    start = np.array([0.0, 0.0, 1.0])
    plan = ((3.0, 0.0), (1.5, 20.0), (2.0, 0.0))
    begin = round(3.0 / DT) - 1

    def lowest_highest(q: Quadrotor) -> np.ndarray:
        z_mm = _heights_mm(q, plan)
        lean = z_mm[begin:] - z_mm[begin]
        return np.array([lean.min(), lean.max()])

    by_firmware = lowest_highest(_settled_firmware(start))
    by_model = lowest_highest(Quadrotor.hovering(QuadrotorParams(), start, 0.0))
    assert by_firmware[0] < -20.0
    assert by_firmware[1] > 20.0
    np.testing.assert_allclose(by_model, by_firmware, atol=8.0)
    assert abs(lowest_highest(_model_as_before(start)) - by_firmware).max() > 30.0


@pytest.mark.parametrize("controller", ["model", "crazyflie-pid"])
def test_a_level_thrust_is_flown_as_the_thrust_asked(controller: str) -> None:
    """A level thrust (cflib's legacy send_setpoint as the PID takes it: the height loop off)
    of a quarter of the hover's: the firmware's PID gives a quarter of its ``thrustBase``
    (36000 of 65535, the motors' units; 60 g at full), whatever the vehicle weighs, and so do
    the model's loops (``OnboardGains.thrust_base_n``). 0.2 s in, the vehicle falls at the
    acceleration that thrust leaves it, within 4 % (the motors' lag; a quarter of the weight
    is 5 % more thrust), and stays level within a degree."""
    from perchpose.geometry import lean_deg
    from perchpose.io.crazyflie import HOVER_THRUST
    from perchpose.sim.quadrotor import AttitudeHold, Quadrotor

    params = QuadrotorParams()
    start = np.array([0.0, 0.0, 1.0])
    if controller == "model":
        q = Quadrotor.hovering(params, start, 0.3)
    else:
        pytest.importorskip("cffirmware")
        q = _settled_firmware(start, 0.3, controller)
    thrust_n = 0.25 * HOVER_THRUST / firmware.FULL_COMMAND * 0.060 * 9.81
    for _ in range(20):
        p = (float(q.p_m[0]), float(q.p_m[1]), float(q.p_m[2]))
        q.hold = AttitudeHold(0.0, 0.0, 0.0, math.nan, p, 0.25)
        q.fly(DT, 5, np.zeros(3), 0.0, q.v_mps)
    v0 = q.v_mps
    q.fly(DT, 5, np.zeros(3), 0.0, q.v_mps)
    a_z = (q.v_mps[2] - v0[2]) / (5 * DT)
    expected = thrust_n / params.mass_kg - 9.81
    assert a_z == pytest.approx(expected, rel=0.04)
    assert lean_deg(q.R_world_body) < 1.0


def test_a_vehicle_flies_as_the_first_in_its_process_whatever_flew_before_it() -> None:
    """The firmware's PID keeps its integrators, filters and desired yaw in the module: a
    vehicle after another that ended tilted, yawed and wound up (as a campaign's worker flies
    run after run) starts from rest as the first one did, to the last bit."""
    pytest.importorskip("cffirmware")

    def flown(heading_rad: float, steps: int, v_sp: tuple[float, float, float]) -> np.ndarray:
        q = _settled_firmware(np.array([0.0, 0.0, 1.0]), heading_rad)
        for _ in range(steps):
            q.fly(DT, 1, np.array(v_sp), 0.8, q.v_mps)
        return np.concatenate([q.p_m, q.v_mps, q.R_world_body.ravel()])

    first = flown(0.4, 300, (0.2, -0.1, 0.05))
    flown(-2.5, 400, (-0.6, 0.5, 0.4))  # a different heading, speed and yaw to leave behind
    np.testing.assert_array_equal(flown(0.4, 300, (0.2, -0.1, 0.05)), first)
