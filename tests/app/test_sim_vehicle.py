"""The sim-vehicle: the world of ``perch`` flown by a stand-in autopilot, stepped here without
the network; and end to end, its MAVLink link and video stream perched on by ``track``'s
pilot in the same process."""

import csv
import math
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from perchpose.app.sim_vehicle import (
    SimulatedVehicle,
    SimVehicleOptions,
    serve,
    sim_setup,
)
from perchpose.camera import CameraModel
from perchpose.cli import main
from perchpose.errors import VehicleConfigError
from perchpose.target import TargetSpec
from perchpose.warmup import warm_up

GUIDED_SETPOINT = 3527  # position, acceleration and yaw ignored: velocity and yaw rate


def _world(autopilot: str = "ardupilot", hand_over_s: float | None = 2.0, wind: str = "none"):
    frames: list[int] = []
    setup = sim_setup(SimVehicleOptions(wind=wind))
    lines: list[str] = []
    world = SimulatedVehicle(
        setup, 4, autopilot, hand_over_s, lambda k, _image: frames.append(k), lines.append
    )
    return world, frames, lines


def _velocity(vx: float, vy: float, vz: float) -> SimpleNamespace:
    """SET_POSITION_TARGET_LOCAL_NED as pymavlink gives it: velocity in NED."""
    return SimpleNamespace(
        coordinate_frame=1,
        type_mask=1479,
        x=0.0,
        y=0.0,
        z=0.0,
        vx=vx,
        vy=vy,
        vz=vz,
        yaw_rate=0.0,
        target_system=1,
    )


def _command(command: int, *params: float) -> SimpleNamespace:
    p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
    return SimpleNamespace(command=command, **{f"param{i + 1}": v for i, v in enumerate(p)})


def test_it_hovers_in_its_hold_mode_streams_its_camera_and_is_handed_over():
    world, frames, lines = _world()
    start = world.vehicle.p_m
    world.advance_to(3.0)
    assert np.linalg.norm(world.vehicle.p_m - start) < 0.05
    assert len(frames) == pytest.approx(90, abs=1)
    assert frames == sorted(frames)
    assert world.autopilot.mode == "GUIDED"
    assert any("mode GUIDED (the operator's switch)" in line for line in lines)


def test_px4_is_handed_over_only_once_setpoints_stream():
    world, _, lines = _world("px4", hand_over_s=0.5)
    world.advance_to(1.0)
    assert world.autopilot.mode == "POSCTL"
    assert any("PX4 needs one" in line for line in lines)
    for _ in range(30):
        world.setpoint(_velocity(0.0, 0.0, 0.0))
        world.advance_to(world.t_s + 0.05)
    assert world.autopilot.mode == "OFFBOARD"


def test_a_climb_in_guided_meets_the_plate_and_the_plate_stops_it():
    world, _, lines = _world()
    under_the_plate = np.array([0.005, -0.01, 1.2])
    world.vehicle.p_m = world.odometry.p_m = world.autopilot.hold_p_m = under_the_plate
    world.advance_to(2.1)
    plate_z = world.setup.plate_z_m
    top = 0.0
    for _ in range(400):  # 0.4 m/s up (NED: negative down) for up to 8 s
        assert world.setpoint(_velocity(0.0, 0.0, -0.4)) == ""
        world.advance_to(world.t_s + 0.02)
        magnet = world.vehicle.point_in_world(world.setup.controller.p_body_magnet_m)
        top = max(top, magnet[2])
    assert world.outcome.contact is not None
    assert world.outcome.verdict
    assert top <= plate_z + 0.003  # it never went through
    assert any("touched the plate" in line for line in lines)


def test_only_a_forced_disarm_stops_it_in_the_air_and_then_it_falls():
    world, _, lines = _world()
    world.advance_to(1.0)
    assert world.command(_command(400, 0.0)) == (400, 2)  # denied: in the air
    assert world.autopilot.armed
    assert world.command(_command(400, 0.0, 21196.0)) == (400, 0)
    height = world.outcome.motor_stop_height_m
    assert height > 0.4
    world.advance_to(world.t_s + 2.0)
    assert world.resting
    assert world.outcome.crashed
    assert any("crashed into the floor" in line for line in lines)


def test_a_mode_change_over_the_link_is_taken_and_land_brings_it_down_disarmed():
    world, _, _ = _world(hand_over_s=None)
    land = world.autopilot.modes["LAND"]
    assert world.command(_command(176, 1.0, float(land))) == (176, 0)
    world.advance_to(world.t_s + 5.0)
    assert world.resting
    assert not world.autopilot.armed
    assert not world.outcome.crashed
    assert world.outcome.motor_stop_height_m == 0.0
    assert world.command(_command(511, 30.0)) == (511, 3)  # unsupported here


def test_bad_options_are_one_line_each():
    with pytest.raises(VehicleConfigError, match="unknown autopilot"):
        serve(SimVehicleOptions(autopilot="inav"), print)
    with pytest.raises(VehicleConfigError, match="fps"):
        serve(SimVehicleOptions(fps=math.nan), print)


@pytest.mark.slow
def test_track_perches_on_it_end_to_end(tmp_path: Path, udp_port: int):
    """Its stream tracked and its link flown by ``track --mavlink-pilot``: the pilot takes
    over in GUIDED and the vehicle climbs to the plate (on this loaded machine, real time)."""
    pytest.importorskip("pymavlink")
    warm_up(TargetSpec.paper(), [CameraModel.preset("fpv")])  # the compile is not the vehicle's
    video_port = udp_port + 1 if udp_port < 65000 else udp_port - 1
    lines: list[str] = []
    options = SimVehicleOptions(
        mavlink=f"udpin:127.0.0.1:{udp_port}",
        video=f"udp://127.0.0.1:{video_port}",
        duration_s=20.0,
        hand_over_s=1.0,
    )
    vehicle = threading.Thread(target=serve, args=(options, lines.append), daemon=True)
    vehicle.start()
    time.sleep(0.3)
    out = tmp_path / "run.csv"
    argv = [
        "track",
        f"udp://127.0.0.1:{video_port}",
        "--camera",
        "preset:fpv",
        "--out",
        str(out),
        "--mavlink",
        f"udpout:127.0.0.1:{udp_port}",
        "--mavlink-pilot",
        "--quiet",
    ]
    tracker = threading.Thread(target=main, args=(argv,), daemon=True)
    tracker.start()
    vehicle.join(timeout=40.0)
    assert not vehicle.is_alive()
    text = "\n".join(lines)
    assert "mode GUIDED" in text, text
    assert "touched the plate" in text, text
    flown = int(text.split(" setpoints received (")[1].split(" flown")[0])
    assert flown > 50, text
    tracker.join(timeout=30.0)  # the stream's end ends the track
    assert not tracker.is_alive()
    with out.open() as f:
        offsets = [r["time_offset_ms"] for r in csv.DictReader(f)]
    # the pilot's online estimate of the camera-to-vehicle time offset, in the rows once made
    assert any(offsets), "no time-offset estimate in the track rows"
