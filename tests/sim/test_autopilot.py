"""The stand-in autopilot's modes, arming and setpoints, at ArduCopter's and PX4's rules."""

import numpy as np
import pytest

from perchpose.errors import VehicleConfigError
from perchpose.sim.autopilot import MODES, StandInAutopilot

UP = np.array([0.0, 0.0, 0.3])
HERE = np.array([0.1, -0.2, 1.0])


def test_it_starts_armed_in_its_hold_mode_and_holds_where_it_started():
    for kind, mode in (("ardupilot", "LOITER"), ("px4", "POSCTL")):
        ap = StandInAutopilot(kind, HERE)
        assert ap.armed
        assert ap.mode == mode
        v, yaw_rate = ap.command(0.0, HERE + np.array([0.1, 0.0, -0.05]), False)
        assert v[0] == pytest.approx(-0.1)
        assert v[2] == pytest.approx(0.05)
        assert yaw_rate == 0.0


def test_setpoints_are_flown_only_in_guided_and_guided_stops_after_3_s_of_silence():
    ap = StandInAutopilot("ardupilot", HERE)
    assert not ap.setpoint(UP, 0.2, 0.0)  # LOITER: not flown
    assert ap.set_mode(MODES["ardupilot"]["GUIDED"][0], 0.1, HERE, "test") == ""
    assert ap.setpoint(UP, 0.2, 0.2)
    v, yaw_rate = ap.command(1.0, HERE, False)
    assert np.allclose(v, UP)
    assert yaw_rate == 0.2
    moved = HERE + np.array([0.0, 0.0, 0.5])
    v, yaw_rate = ap.command(3.3, moved, False)  # 3.1 s without a setpoint: it holds there
    assert np.allclose(v, 0.0)
    assert yaw_rate == 0.0
    assert ap.mode == "GUIDED"
    assert "no setpoint for 3 s" in ap.events[-1]


def test_px4_enters_offboard_only_on_a_setpoint_stream_and_leaves_it_when_they_stop():
    ap = StandInAutopilot("px4", HERE)
    offboard = ap.modes["OFFBOARD"]
    assert "no setpoint stream" in ap.set_mode(offboard, 0.0, HERE, "test")
    for k in range(5):  # 10 Hz for half a second
        ap.setpoint(UP, 0.0, 0.1 * k)
    assert ap.set_mode(offboard, 0.45, HERE, "test") == ""
    ap.setpoint(UP, 0.0, 0.5)
    assert np.allclose(ap.command(1.4, HERE, False)[0], UP)
    ap.command(1.6, HERE, False)  # 1.1 s after the last: COM_OF_LOSS_T
    assert ap.mode == "POSCTL"


def test_a_position_setpoint_is_flown_to():
    ap = StandInAutopilot("ardupilot", HERE)
    ap.set_mode(ap.modes["GUIDED"], 0.0, HERE, "test")
    assert ap.position_setpoint(HERE + np.array([0.0, 0.3, 0.0]), 0.0, 0.1)
    v, _ = ap.command(0.2, HERE, False)
    assert v[1] == pytest.approx(0.3)
    assert v[0] == pytest.approx(0.0)


def test_a_non_finite_setpoint_and_an_unknown_mode_are_refused():
    ap = StandInAutopilot("ardupilot", HERE)
    ap.set_mode(ap.modes["GUIDED"], 0.0, HERE, "test")
    assert not ap.setpoint(np.array([np.nan, 0.0, 0.0]), 0.0, 0.1)
    assert "non-finite" in ap.events[-1]
    assert "not one this stand-in flies" in ap.set_mode(99, 0.2, HERE, "test")
    with pytest.raises(VehicleConfigError, match="unknown autopilot"):
        StandInAutopilot("betaflight", HERE)


def test_only_a_forced_disarm_is_taken_in_the_air_and_land_disarms_on_the_ground():
    ap = StandInAutopilot("ardupilot", HERE)
    assert "forced" in ap.disarm(False, on_ground=False)
    assert ap.armed
    assert ap.disarm(True, on_ground=False) == ""
    assert not ap.armed
    ap = StandInAutopilot("px4", HERE)
    ap.set_mode(ap.modes["AUTO.LAND"], 0.0, HERE, "test")
    v, _ = ap.command(0.1, HERE, False)
    assert v[2] == pytest.approx(-0.5)
    ap.command(5.0, HERE * [1, 1, 0], True)
    assert not ap.armed
    assert ap.events[-1] == "disarmed"
    assert ap.arm(True, HERE * [1, 1, 0]) == ""
    assert ap.mode == "POSCTL"
