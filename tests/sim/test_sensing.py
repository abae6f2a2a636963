"""The vehicle's senses drawn per run: their ranges, their delays, and what they change."""

import math
from dataclasses import replace

import numpy as np
import pytest

from perchpose import CameraModel, TargetSpec
from perchpose.errors import SensingConfigError, VehicleConfigError
from perchpose.geometry import rot_z
from perchpose.sim.perch import PerchSetup, run_perch
from perchpose.sim.sensing import (
    Accelerometer,
    SensedState,
    Sensing,
    SensingDraw,
    mean_glass_to_grab_s,
)


def test_draws_stay_in_their_ranges_and_repeat_with_the_seed() -> None:
    camera = CameraModel.preset("fpv")
    sensing = Sensing()
    draws = [SensingDraw.draw(sensing, camera, np.random.default_rng(s)) for s in range(200)]
    again = SensingDraw.draw(sensing, camera, np.random.default_rng(7))
    assert again.latency_s == draws[7].latency_s
    np.testing.assert_array_equal(again.camera.K, draws[7].camera.K)
    latency = np.array([d.latency_s for d in draws])
    assert 0.04 <= latency.min() < 0.06
    assert 0.13 < latency.max() <= 0.15
    assert all(50.0 <= d.odometry_hz <= 100.0 for d in draws)
    assert all(0.01 <= d.odometry_delay_s <= 0.03 for d in draws)
    assert all(abs(d.clock_offset_s) <= 0.005 for d in draws)
    focal = np.array([d.camera.K[0, 0] / camera.K[0, 0] for d in draws])
    assert 0.99 <= focal.min() < 0.995
    assert 1.005 < focal.max() <= 1.01
    shift = np.array([d.camera.K[:2, 2] - camera.K[:2, 2] for d in draws])
    assert np.abs(shift).max() <= 3.0
    for d in draws:
        mount = d.T_true_believed
        angle = math.degrees(math.acos((np.trace(mount[:3, :3]) - 1) / 2))
        assert angle <= math.sqrt(3) * 1.0 + 1e-9
        assert np.abs(mount[:3, 3]).max() <= 0.001
        assert abs(d.target_scale - 1.0) <= 0.005


def test_samples_reach_the_pilot_late() -> None:
    state = SensedState(attitude_delay_s=0.01, odometry_delay_s=0.02)
    for i in range(10):
        t = i * 0.01
        state.record(t, np.eye(3) * (i + 1), np.array([t, 0, 0]), np.array([i, 0, 0]))
    assert state.attitude(0.05)[0, 0] == 5.0  # made at 0.04, 10 ms before
    p, v = state.odometry(0.05)
    assert p[0] == pytest.approx(0.03)
    assert v[0] == 3.0
    assert state.odometry(0.0)[1][0] == 0.0  # before the first is old enough: the oldest


def test_bad_sensing_is_refused() -> None:
    with pytest.raises(SensingConfigError, match="latency_s must be 0 <= low <= high"):
        Sensing(latency_s=(0.2, 0.1))
    with pytest.raises(SensingConfigError, match="flow_noise_mps must be a non-negative"):
        Sensing(flow_noise_mps=-1.0)
    with pytest.raises(SensingConfigError, match="unknown sensing"):
        Sensing(name="perfect")
    assert Sensing().with_latency(0.1).latency_s == (0.1, 0.1)


def test_ideal_senses_fly_as_before_and_realistic_ones_differ() -> None:
    """Ideal senses leave every run as it was (their generator is a third one, beside the
    world's and the camera's); realistic ones record their draw and move the contact."""
    setup = PerchSetup(CameraModel.preset("fpv"), TargetSpec.paper(), estimator="truth")
    ideal = run_perch(setup, 3)
    assert ideal.senses is None
    realistic_setup = setup.with_sensing(Sensing())
    assert realistic_setup.controller.camera_latency_s == pytest.approx(0.15)
    realistic = run_perch(realistic_setup, 3)
    assert realistic.senses is not None
    assert realistic.contact_offset_mm != ideal.contact_offset_mm
    again = run_perch(realistic_setup, 3)
    assert again.contact_offset_mm == realistic.contact_offset_mm  # seeded
    exact = replace(
        Sensing(),
        latency_s=(1 / 30, 1 / 30),
        latency_jitter_s=0.0,
        odometry_hz=(50.0, 50.0),
        odometry_delay_s=(0.0, 0.0),
        flow_noise_mps=0.0,
        attitude_noise_deg=0.0,
        attitude_delay_s=(0.0, 0.0),
        clock_offset_s=0.0,
        focal_error=0.0,
        principal_point_px=0.0,
        k1_error=0.0,
        mount_deg=0.0,
        mount_mm=0.0,
        target_scale_error=0.0,
        uplink_delay_s=(0.0, 0.0),
        accel_noise_mps2=0.0,
        accel_bias_mps2=0.0,
    )
    # realistic machinery with every error at zero flies the ideal run again (with the true
    # capture times: live stamps date a frame that came a frame late by its grab)
    zero = run_perch(replace(setup, stamps="exact").with_sensing(exact), 3)
    assert zero.contact_offset_mm == pytest.approx(ideal.contact_offset_mm, abs=1e-9)


def test_the_mean_glass_to_grab_latency_a_user_would_measure() -> None:
    """50 ms at 30 fps without jitter comes at the second frame's tick (66.7 ms); a tenth of
    the frames a frame later adds a tenth of a frame; 8 ms of jitter pushes the frames whose
    jitter passes 16.7 ms (4 %) to a third frame."""
    assert mean_glass_to_grab_s(0.05, 0.0, 30.0, 0.0) == pytest.approx(2 / 30)
    assert mean_glass_to_grab_s(0.05, 0.0, 30.0, 0.1) == pytest.approx(2.1 / 30)
    tail = 2 * (1 - 0.9815)  # P(|N(0, 8 ms)| > 16.67 ms)
    assert mean_glass_to_grab_s(0.05, 0.008, 30.0, 0.0) == pytest.approx(
        (2 + tail) / 30, abs=0.01 / 30
    )


def test_live_stamps_date_frames_by_their_grab_less_the_measured_latency() -> None:
    """With live stamps the pilot is given the run's mean glass-to-grab latency, off by at
    most ``latency_error_s``; the same world and senses with exact stamps fly otherwise."""
    setup = PerchSetup(CameraModel.preset("fpv"), TargetSpec.paper(), estimator="truth")
    realistic = setup.with_sensing(Sensing())
    assert realistic.stamps == "live"
    live = run_perch(realistic, 4)
    exact = run_perch(replace(realistic, stamps="exact"), 4)
    assert live.senses is not None
    assert exact.senses is not None
    measured = mean_glass_to_grab_s(
        live.senses.latency_s,
        Sensing().latency_jitter_s,
        realistic.fps,
        realistic.disturbances.latency_jitter,
    )
    assert abs(live.senses.latency_configured_s - measured) <= Sensing().latency_error_s
    assert live.senses.latency_configured_s != measured
    assert exact.senses.latency_s == live.senses.latency_s  # the same draw
    assert live.contact_offset_mm != exact.contact_offset_mm
    with pytest.raises(VehicleConfigError, match="unknown stamps 'grabbed'"):
        replace(realistic, stamps="grabbed")


def test_the_accelerometer_comes_with_the_odometry_and_has_its_errors() -> None:
    state = SensedState(attitude_delay_s=0.0, odometry_delay_s=0.02)
    for i in range(5):
        t = 0.01 * i
        state.record(t, np.eye(3), np.zeros(3), np.zeros(3), np.array([float(i), 0.0, 9.81]))
    f = state.specific_force(0.04)
    assert f is not None
    assert f[0] == 2.0  # the sample made 20 ms before, as the odometry's
    rng = np.random.default_rng(0)
    accelerometer = Accelerometer(0.2, 0.1, rng)
    assert np.all(np.abs(accelerometer.bias_mps2) <= 0.1)
    reads = np.array([accelerometer.read(np.array([0.5, 0.0, 9.81])) for _ in range(2000)])
    np.testing.assert_allclose(
        reads.mean(axis=0), [0.5, 0.0, 9.81] + accelerometer.bias_mps2, atol=0.02
    )
    np.testing.assert_allclose(reads.std(axis=0), 0.2, rtol=0.1)


def test_the_gyro_is_integrated_as_its_samples_arrive_each_once_in_order() -> None:
    """Logged with the attitude, the gyro reaches the pilot after the attitude's delay; each
    sample that has arrived is integrated once, however often the pilot asks."""
    state = SensedState(attitude_delay_s=0.05, odometry_delay_s=0.05)
    assert state.gyro_reading(0.0) is None
    rate_dps = np.array([0.0, 0.0, 30.0])
    for k in range(11):  # 0 to 0.2 s at 50 Hz, turning at 30 deg/s about z
        state.record(k * 0.02, np.eye(3), np.zeros(3), np.zeros(3), None, rate_dps)
        if k == 5:
            state.gyro_reading(0.1)  # asked once midway
    reading = state.gyro_reading(0.1)  # samples made by 0.05 s have arrived: 0.04 s of turn
    assert reading is not None
    np.testing.assert_allclose(reading.R_ref_body, rot_z(math.radians(30.0 * 0.04)), atol=1e-9)
    state.gyro_reading(0.1)
    reading = state.gyro_reading(0.25)  # all of them: 0.2 s
    assert reading is not None
    np.testing.assert_allclose(reading.R_ref_body, rot_z(math.radians(30.0 * 0.2)), atol=1e-9)
    assert reading.restarts == 0
