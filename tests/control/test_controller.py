import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from perchpose.control import (
    ControllerConfigError,
    ControllerSettings,
    Odometry,
    PerchingController,
    default_T_body_camera,
    load_T_body_camera,
)
from perchpose.control.controller import phase_margin_deg
from perchpose.geometry import invert_transform, make_transform
from perchpose.values import Estimate


def _estimate(
    x_cm: float, y_cm: float, z_cm: float, yaw_deg: float = 0.0, valid: bool = True
) -> Estimate:
    if not valid:
        return Estimate.none(0.0)
    return Estimate.of_pose(0.0, (x_cm / 100, y_cm / 100, z_cm / 100), math.radians(yaw_deg))


def _camera_view(settings: ControllerSettings, target_body_m: np.ndarray) -> Estimate:
    """What the camera would report for a target at a body-frame point, facing down."""
    T_camera_body = invert_transform(settings.T_body_camera)
    p = T_camera_body[:3, :3] @ target_body_m + T_camera_body[:3, 3]
    return _estimate(*(p * 100.0), yaw_deg=0.0)


def test_magnet_to_target_undoes_the_mounting() -> None:
    s = ControllerSettings()
    c = PerchingController(s)
    target_body = np.array([0.05, -0.02, 0.6])
    d, _ = c.magnet_to_target(_camera_view(s, target_body), np.eye(3))
    np.testing.assert_allclose(d, target_body - np.array(s.p_body_magnet_m), atol=1e-9)
    yawed = make_transform(
        np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), np.zeros(3)
    )[:3, :3]
    d_yawed, _ = c.magnet_to_target(_camera_view(s, target_body), yawed)
    np.testing.assert_allclose(d_yawed, yawed @ d, atol=1e-9)


def test_aligns_before_climbing_and_commits_at_the_end() -> None:
    s = ControllerSettings()
    c = PerchingController(s)
    far_off = c.update(_camera_view(s, np.array([0.10, 0.0, 0.8])), 0.0, np.eye(3))
    assert far_off.phase == "align"
    assert far_off.v_mps[0] > 0
    assert far_off.v_mps[2] == 0.0
    centred = c.update(_camera_view(s, np.array([0.0, 0.0, 0.5])), 0.1, np.eye(3))
    assert centred.phase == "climb"
    assert centred.v_mps[2] == pytest.approx(s.max_z_mps)
    close_view = _camera_view(s, np.array([0.001, 0.0, 0.035]))
    first = c.update(close_view, 0.2, np.eye(3))
    assert first.phase == "climb"  # one frame is no evidence
    c.update(close_view, 0.23, np.eye(3))
    close = c.update(close_view, 0.27, np.eye(3))
    assert close.phase == "commit"
    assert close.v_mps[2] == pytest.approx(s.commit_speed_mps)
    blind = c.update(None, 0.3, np.eye(3))
    assert blind.phase == "commit"


def test_out_of_the_cone_near_the_plate_backs_down() -> None:
    """Near the plate, holding height off-centre is not enough (the climb's momentum would
    carry the vehicle into the plate): outside the cone it descends; further down it holds."""
    s = ControllerSettings()
    magnet = np.array(s.p_body_magnet_m)
    near = PerchingController(s).update(
        _camera_view(s, magnet + np.array([0.012, 0.0, 0.03])), 0.0, np.eye(3)
    )
    assert near.phase == "align"
    assert near.v_mps[2] == pytest.approx(-s.descend_mps)
    lower = PerchingController(s).update(
        _camera_view(s, magnet + np.array([0.05, 0.0, 0.3])), 0.0, np.eye(3)
    )
    assert lower.phase == "align"
    assert lower.v_mps[2] == 0.0
    centred = PerchingController(s).update(
        _camera_view(s, magnet + np.array([0.001, 0.0, 0.03])), 0.0, np.eye(3)
    )
    assert centred.phase == "climb"
    assert centred.v_mps[2] > 0


def test_commit_needs_consistent_frames_and_ends_on_far_evidence() -> None:
    s = ControllerSettings()
    c = PerchingController(s)
    far = _camera_view(s, np.array([0.0, 0.0, 0.6]))
    near = _camera_view(s, np.array([0.0, 0.0, 0.03]))
    phases = [
        c.update(e, k / 30, np.eye(3)).phase for k, e in enumerate([far, near, far, near, far])
    ]
    assert "commit" not in phases
    phases = [c.update(near, (5 + k) / 30, np.eye(3)).phase for k in range(3)]
    assert phases == ["climb", "climb", "commit"]
    # one frame that puts the target far again ends the final climb
    back = c.update(far, 8 / 30, np.eye(3))
    assert back.phase == "climb"
    assert back.v_mps[2] == pytest.approx(s.max_z_mps)


def test_blind_commit_needs_consistent_frames() -> None:
    s = ControllerSettings()
    c = PerchingController(s)
    c.update(_camera_view(s, np.array([0.0, 0.0, 0.6])), 0.0, np.eye(3))
    c.update(_camera_view(s, np.array([0.0, 0.0, 0.6])), 1 / 30, np.eye(3))
    c.update(_camera_view(s, np.array([0.0, 0.0, 0.08])), 2 / 30, np.eye(3))  # an outlier
    assert c.update(None, 3 / 30, np.eye(3)).phase == "lost"
    c2 = PerchingController(s)
    for k in range(3):
        c2.update(_camera_view(s, np.array([0.0, 0.0, 0.10 - 0.005 * k])), k / 30, np.eye(3))
    assert c2.update(None, 3 / 30, np.eye(3)).phase == "commit"


def test_a_final_climb_that_never_ends_backs_off() -> None:
    s = ControllerSettings(commit_timeout_s=1.0)
    c = PerchingController(s)
    for k in range(3):
        c.update(_camera_view(s, np.array([0.0, 0.0, 0.03])), k / 30, np.eye(3))
    assert c.phase == "commit"
    assert c.update(None, 0.9, np.eye(3)).phase == "commit"
    backed = c.update(None, 1.2, np.eye(3))
    assert backed.phase == "lost"
    np.testing.assert_array_equal(backed.v_mps, 0.0)


def test_stale_and_non_finite_estimates_count_as_no_target() -> None:
    s = ControllerSettings(max_estimate_age_s=0.5)
    c = PerchingController(s)
    seen = _camera_view(s, np.array([0.10, 0.0, 0.6]))
    assert c.update(seen, 0.0, np.eye(3)).phase == "align"
    old = Estimate.of_pose(1.0, seen.t_camera_target_m, 0.0, age_s=0.6)
    assert c.update(old, 1.0, np.eye(3)).phase == "lost"
    late = Estimate.of_pose(1.0, seen.t_camera_target_m, 0.0)
    assert c.update(late, 1.6, np.eye(3)).phase == "lost"  # captured 0.6 s before
    inf = Estimate.of_pose(1.7, (math.inf, 0.0, 0.6), 0.0)
    command = c.update(inf, 1.7, np.eye(3))
    assert command.phase == "lost"
    assert np.all(np.isfinite(command.v_mps))


def test_lost_target_holds_then_descends() -> None:
    s = ControllerSettings(hold_s=1.0)
    c = PerchingController(s)
    assert c.update(None, 0.0, np.eye(3)).phase == "search"
    c.update(_camera_view(s, np.array([0.05, 0.0, 0.8])), 0.0, np.eye(3))
    hold = c.update(_estimate(0, 0, 0, valid=False), 0.5, np.eye(3))
    assert hold.phase == "lost"
    np.testing.assert_array_equal(hold.v_mps, 0.0)
    c.update(_estimate(0, 0, 0, valid=False), 1.0, np.eye(3))
    later = c.update(_estimate(0, 0, 0, valid=False), 2.1, np.eye(3))
    assert later.v_mps[2] == pytest.approx(-s.descend_mps)


def test_heading_error_turns_towards_the_target() -> None:
    s = ControllerSettings()
    c = PerchingController(s)
    est = _camera_view(s, np.array([0.0, 0.0, 0.5]))
    turned = _estimate(est.x_cm, est.y_cm, est.z_cm, yaw_deg=20.0)
    _, err = c.magnet_to_target(turned, np.eye(3))
    assert abs(math.degrees(err)) == pytest.approx(20.0, abs=1e-6)


def test_unstable_gains_are_refused() -> None:
    with pytest.raises(ControllerConfigError, match="unstable"):
        ControllerSettings(k_xy=10.0)
    with pytest.raises(ControllerConfigError, match=r"k_xy \* commit_gain = 9 /s is unstable"):
        ControllerSettings(k_xy=3.0, commit_gain=3.0)  # stable, but not stiffened for the climb
    with pytest.raises(ControllerConfigError, match="must be positive"):
        ControllerSettings(max_z_mps=-1.0)
    with pytest.raises(ControllerConfigError, match="commit_observer_rate = 60"):
        ControllerSettings(commit_observer_rate=60.0)  # 50 Hz odometry: under 50 rad/s


def test_mount_file(tmp_path: Path) -> None:
    T = default_T_body_camera()
    T[:3, 3] = [0.02, -0.01, 0.03]
    good = tmp_path / "mount.yaml"
    good.write_text(yaml.safe_dump({"T_body_camera": T.tolist()}))
    assert np.allclose(load_T_body_camera(good), T)
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"T_body_camera": (2 * T).tolist()}))
    with pytest.raises(ControllerConfigError, match=r"bad\.yaml"):
        load_T_body_camera(bad)
    other = tmp_path / "other.yaml"
    other.write_text("a: 1")
    with pytest.raises(ControllerConfigError, match="no T_body_camera"):
        load_T_body_camera(other)
    with pytest.raises(ControllerConfigError, match="cannot read"):
        load_T_body_camera(tmp_path / "missing.yaml")


def _seen(settings: ControllerSettings, target_body_m: list[float], t_s: float) -> Estimate:
    """The camera's report of a frame captured at ``t_s``."""
    return replace(_camera_view(settings, np.array(target_body_m)), t_s=t_s)


def _odometry(t_s: float, x_m: float = 0.0, vx_mps: float = 0.0) -> Odometry:
    return Odometry(t_s, np.array([x_m, 0.0, 1.0]), np.array([vx_mps, 0.0, 0.0]))


def test_odometry_takes_the_cameras_latency_out() -> None:
    s = ControllerSettings(observer_rate=0.0)
    with_odometry, without = PerchingController(s), PerchingController(s)
    # captured at t = 0 with the target 1 cm ahead; by t = 1/30 the vehicle has moved 1 cm on
    with_odometry.update(None, 0.0, np.eye(3), _odometry(0.0))
    seen = _seen(s, [0.01, 0.0, 0.6], 0.0)
    late = with_odometry.update(seen, 1 / 30, np.eye(3), _odometry(1 / 30, x_m=0.01))
    stale = without.update(seen, 1 / 30, np.eye(3))
    assert stale.v_mps[0] == pytest.approx(s.k_xy * 0.01, rel=1e-6)
    assert abs(late.v_mps[0]) < 1e-6  # it is there already


def test_the_last_centimetres_are_flown_on_odometry() -> None:
    s = ControllerSettings(observer_rate=0.0)
    c = PerchingController(s)
    for k in range(3):
        t = k / 30
        c.update(_seen(s, [0.0, 0.0, 0.05], t), t, np.eye(3), _odometry(t))
    assert c.phase == "commit"
    # the camera is too close to see; the vehicle drifts 5 mm aside (inside the cone's exit):
    # it steers back
    blind = c.update(None, 4 / 30, np.eye(3), _odometry(4 / 30, x_m=0.005))
    assert blind.phase == "commit"
    assert blind.v_mps[0] == pytest.approx(-s.k_xy * s.commit_gain * 0.005, abs=2e-3)
    assert blind.v_mps[2] == pytest.approx(s.commit_speed_mps)


def test_the_observer_is_faster_only_in_the_final_climb() -> None:
    s = ControllerSettings()
    c = PerchingController(s)
    rates = []
    for k in range(5):
        t = k / 30
        c.update(_seen(s, [0.0, 0.0, 0.05 if k >= 2 else 0.3], t), t, np.eye(3), _odometry(t))
        rates.append((c.phase, c.observer_rate))
    assert rates[0] == ("climb", s.observer_rate)
    assert rates[-1] == ("commit", s.commit_observer_rate)
    assert s.commit_observer_rate > s.observer_rate


def test_a_climb_out_of_the_cone_backs_off_and_gives_up_after_its_tries() -> None:
    s = ControllerSettings(observer_rate=0.0, max_tries=2)
    c = PerchingController(s)
    t = 0.0
    for attempt in range(2):
        for _ in range(3):
            c.update(_seen(s, [0.0, 0.0, 0.05], t), t, np.eye(3), _odometry(t))
            t += 1 / 30
        assert c.phase == "commit"
        # odometry says the vehicle is 4 cm aside: outside the magnet's reach
        command = c.update(None, t, np.eye(3), _odometry(t, x_m=0.04))
        t += 1 / 30
        if attempt == 0:
            assert command.phase == "retreat"
            assert command.v_mps[2] < 0  # down, to align again
            # below retry_below_m the vehicle aligns again
            far = c.update(_seen(s, [0.0, 0.0, 0.3], t), t, np.eye(3), _odometry(t))
            assert far.phase in ("align", "climb")
            t += 1 / 30
    assert command.phase == "give-up"
    assert c.tries == 2
    assert c.update(_seen(s, [0.0, 0.0, 0.05], t), t, np.eye(3), _odometry(t)).phase == "give-up"


def test_no_final_climb_while_sliding_sideways() -> None:
    s = ControllerSettings(observer_rate=0.0)
    c = PerchingController(s)
    # sliding at 10 cm/s, though each frame sees the target centred
    for k in range(5):
        t = k / 30
        command = c.update(
            _seen(s, [0.0, 0.0, 0.05], t), t, np.eye(3), _odometry(t, x_m=0.1 * t, vx_mps=0.1)
        )
        assert command.phase != "commit"
    # it stops and its velocity reads zero at once; the climb waits until the odometry's
    # positions over the last speed_window_s agree (a noisy velocity alone does not decide)
    t = 5 / 30
    for k in range(6, 12):
        t = k / 30
        command = c.update(_seen(s, [0.0, 0.0, 0.05], t), t, np.eye(3), _odometry(t, x_m=0.5 / 30))
        if command.phase == "commit":
            break
    assert command.phase == "commit"
    assert t - 5 / 30 >= s.speed_window_s - 1e-9


def test_a_camera_dropout_mid_approach_holds_height_on_odometry() -> None:
    s = ControllerSettings(observer_rate=0.0)
    c = PerchingController(s)
    c.update(_seen(s, [0.0, 0.0, 0.6], 0.0), 0.0, np.eye(3), _odometry(0.0))
    gap = c.update(None, 0.2, np.eye(3), _odometry(0.2, x_m=-0.01))
    assert gap.phase in ("align", "climb")
    assert gap.v_mps[2] == 0.0
    assert gap.v_mps[0] > 0  # back towards the held target
    lost = c.update(None, 0.2 + s.hold_target_s + 0.1, np.eye(3), _odometry(1.5))
    assert lost.phase == "lost"


def test_between_frames_the_lateral_loop_steers_on_odometry() -> None:
    s = ControllerSettings(observer_rate=0.0, k_i_xy=0.0)
    c = PerchingController(s)
    assert c.between_frames(0.0, np.eye(3), _odometry(0.0)) is None  # nothing held yet
    frame = c.update(_seen(s, [0.0, 0.0, 0.5], 0.0), 0.0, np.eye(3), _odometry(0.0))
    assert frame.phase == "climb"
    # a gust pushes the vehicle 8 mm on before the next frame: it steers back at once,
    # climbing as the frame said and in the frame's phase
    tick = c.between_frames(0.02, np.eye(3), _odometry(0.02, x_m=0.008))
    assert tick is not None
    assert tick.phase == "climb"
    assert tick.v_mps[0] == pytest.approx(-s.k_xy * 0.008, rel=1e-6)
    assert tick.v_mps[2] == pytest.approx(frame.v_mps[2])
    assert c.phase == "climb"
    # the camera stalls: still aligned on odometry, but no longer climbing blind
    stalled = c.between_frames(0.2, np.eye(3), _odometry(0.2, x_m=0.008))
    assert stalled is not None
    assert stalled.v_mps[0] == pytest.approx(-s.k_xy * 0.008, rel=1e-6)
    assert stalled.v_mps[2] == 0.0
    assert c.between_frames(0.1 + s.hold_target_s, np.eye(3), _odometry(1.1)) is None
    # a lost target steers on nothing between frames
    c.update(None, 2.0, np.eye(3), _odometry(2.0))
    assert c.phase == "lost"
    assert c.between_frames(2.02, np.eye(3), _odometry(2.02)) is None


def test_timing_outside_what_was_verified_is_refused() -> None:
    """15-60 fps and up to 200 ms of latency fly the default gains with odometry; outside that
    envelope, or without odometry where the camera's delay takes the phase margin, the
    settings say why."""
    for fps, latency_s in ((15.0, 0.2), (60.0, 0.2), (30.0, 0.0), (15.0, 0.0)):
        ControllerSettings(camera_period_s=1.0 / fps, camera_latency_s=latency_s)
    with pytest.raises(ControllerConfigError, match=r"10 fps is outside what was verified"):
        ControllerSettings(camera_period_s=0.1)
    with pytest.raises(ControllerConfigError, match=r"latency of 250 ms is outside"):
        ControllerSettings(camera_latency_s=0.25)
    ControllerSettings(odometry_period_s=None)  # 30 fps, a frame late: fine without odometry
    with pytest.raises(ControllerConfigError, match=r"k_xy = 2.5 /s is unstable with a 0.067 s"):
        ControllerSettings(camera_period_s=1 / 15, camera_latency_s=0.2, odometry_period_s=None)
    with pytest.raises(ControllerConfigError, match="odometry_period_s must be positive"):
        ControllerSettings(odometry_period_s=0.0)


def test_phase_margin_of_the_position_loop() -> None:
    """gain / (s (lag s + 1)) without delay: crossover where gain = w sqrt(1 + (lag w)^2) and
    a margin of 90 deg - atan(lag w); each second of delay takes w radians more."""
    gain, lag = 2.0, 0.25
    w = math.sqrt((math.sqrt(1 + 4 * lag**2 * gain**2) - 1) / (2 * lag**2))
    expected = 90.0 - math.degrees(math.atan(lag * w))
    assert phase_margin_deg(gain, lag, 0.0) == pytest.approx(expected, abs=1e-6)
    assert phase_margin_deg(gain, lag, 0.1) == pytest.approx(
        expected - math.degrees(0.1 * w), abs=1e-6
    )


def test_a_late_fix_is_placed_with_the_attitude_at_its_capture() -> None:
    """The vehicle rolled 10 deg and turned 20 deg between a frame's capture and its arrival:
    the fix is turned into the world with the attitude it was captured at, and its heading
    error carried to now by the turn."""
    s = ControllerSettings()
    rolled = Rotation.from_euler("ZX", [20.0, 10.0], degrees=True).as_matrix()
    estimate = _estimate(2.0, -1.0, 40.0, yaw_deg=30.0)  # captured at t = 0, level
    late = PerchingController(s)
    late.update(None, 0.0, np.eye(3))  # level at the capture
    command = late.update(replace(estimate, t_s=0.0), 0.1, rolled)
    d_capture, heading_capture = late.magnet_to_target(estimate, np.eye(3))
    assert command.error_m == pytest.approx(d_capture, abs=1e-12)
    expected_rate = s.k_yaw * (heading_capture - math.radians(20.0))
    assert command.yaw_rate_rad_s == pytest.approx(expected_rate, abs=1e-9)
    d_now, _ = late.magnet_to_target(estimate, rolled)
    assert np.linalg.norm(d_now - d_capture) > 0.05  # what the arrival's attitude would give


def test_a_late_odometry_sample_is_carried_to_now_by_its_velocity() -> None:
    """Odometry that describes the vehicle 50 ms ago, moving at 0.1 m/s along x: the held
    target is steered to from where the vehicle is now, 5 mm further along."""
    s = ControllerSettings()
    c = PerchingController(s)
    still = Odometry(0.0, np.zeros(3), np.zeros(3))
    est = _camera_view(s, np.array([0.0, 0.0, 0.5]))
    first = c.update(est, 0.0, np.eye(3), still)
    assert first.error_m is not None
    late = Odometry(0.05, np.zeros(3), np.array([0.1, 0.0, 0.0]))  # arrives at 0.1
    command = c.between_frames(0.1, np.eye(3), late)
    assert command is not None
    assert command.error_m is not None
    np.testing.assert_allclose(command.error_m - first.error_m, [-0.005, 0.0, 0.0], atol=1e-12)


def test_a_measured_push_is_leant_against_at_once() -> None:
    """The accelerometer says the air pushes along +x at 1.3 m/s^2: the setpoints between
    frames lean against it by the (low-passed) push over the velocity loop's gain, before the
    odometry has seen any drift; without ``push_feedforward``, or without an accelerometer,
    they do not."""
    push = np.array([1.3, 0.0, 0.0])
    sent = {}
    for on, measured in ((True, push), (False, push), (True, None)):
        s = ControllerSettings(push_feedforward=on, observer_rate=0.0)
        c = PerchingController(s)
        c.update(_seen(s, [0.0, 0.0, 0.3], 0.0), 0.0, np.eye(3), _odometry(0.0))
        for k in range(1, 6):
            command = c.between_frames(
                k / 50, np.eye(3), replace(_odometry(k / 50), push_mps2=measured)
            )
            assert command is not None
        sent[on, measured is not None] = command.v_mps
    s = ControllerSettings()
    filtered = 1.0 - math.exp(-5 * 0.02 / s.push_filter_s)
    leaning = sent[True, True] - sent[False, True]
    np.testing.assert_allclose(
        leaning, [-filtered * 1.3 / s.onboard_velocity_gain, 0, 0], atol=1e-9
    )
    np.testing.assert_allclose(sent[True, False], sent[False, True], atol=1e-12)


def test_a_vehicle_leaning_into_a_gust_waits_under_the_plate_for_a_lull() -> None:
    """Centred 3.5 cm under the plate: level, three consistent frames start the final climb;
    leaning 14 deg into a gust (more than ``max_commit_tilt_deg``), the same frames do not,
    and the vehicle backs down instead of climbing into the plate at a tilt the magnet cannot
    seat at; at 6 cm it holds its height. Upright again, it climbs."""
    s = ControllerSettings()
    magnet = np.array(s.p_body_magnet_m)

    def view(R: np.ndarray, d_world: list[float], t_s: float) -> Estimate:
        return replace(_camera_view(s, magnet + R.T @ np.array(d_world)), t_s=t_s)

    level = np.eye(3)
    leaning = Rotation.from_euler("x", 14.0, degrees=True).as_matrix()
    for R, expect in ((level, "commit"), (leaning, "climb")):
        c = PerchingController(s)
        for k in range(3):
            command = c.update(view(R, [0.0005, 0.0, 0.035], k / 30), k / 30, R)
        assert command.phase == expect
    assert command.v_mps[2] == pytest.approx(-s.descend_mps)
    c = PerchingController(s)
    holding = c.update(view(leaning, [0.0, 0.0, 0.06], 0.0), 0.0, leaning)
    assert holding.phase == "climb"
    assert holding.v_mps[2] == 0.0
    climbing = c.update(view(level, [0.0, 0.0, 0.06], 1 / 30), 1 / 30, level)
    assert climbing.v_mps[2] > 0.1


def _fly_with_stamps_off(settings: ControllerSettings, offset_s: float) -> PerchingController:
    """A controller fed the vehicle's samples at 100 Hz and fixes at 30 fps of a vehicle
    rocking under the target, each frame stamped ``offset_s`` before its capture."""
    c = PerchingController(settings)
    target_world = np.array([0.0, 0.0, 1.0])

    def R_at(t_s: float) -> np.ndarray:
        wobble = [0.05 * math.sin(8.0 * t_s), 0.04 * math.sin(5.7 * t_s + 1.0), 0.2]
        return Rotation.from_rotvec(wobble).as_matrix()

    def p_at(t_s: float) -> np.ndarray:
        return np.array([0.04 * math.sin(3.1 * t_s), 0.03 * math.cos(4.4 * t_s), 0.1 * t_s])

    rng = np.random.default_rng(3)
    captures = list(np.arange(0.0, 5.0, 1.0 / 30.0))
    for t in (0.01 * i for i in range(530)):
        odometry = Odometry(t, p_at(t), np.zeros(3))
        while captures and captures[0] + 0.1 <= t:
            captured = float(captures.pop(0))
            body = R_at(captured).T @ (target_world - p_at(captured))
            seen = _camera_view(settings, body + rng.normal(0.0, 0.0005, 3))
            c.update(replace(seen, t_s=captured - offset_s), t, R_at(t), odometry)
        c.between_frames(t, R_at(t), odometry)
    return c


def test_the_stamps_offset_is_estimated_and_corrected_once_sure() -> None:
    settings = ControllerSettings()
    c = _fly_with_stamps_off(settings, 0.06)
    found = c.time_offset
    assert found is not None
    assert found.offset_s == pytest.approx(0.06, abs=0.004)
    assert found.sigma_s < settings.time_offset.trusted_sigma_s
    frame = Estimate.of_pose(10.0, (0.0, 0.0, 0.5), 0.0)
    assert c.capture_time(frame) == pytest.approx(10.0 + found.offset_s)
    # asked only to report it, the controller estimates it alike and places fixes at the stamp
    reported = _fly_with_stamps_off(replace(settings, correct_time_offset=False), 0.06)
    assert reported.time_offset is not None
    assert reported.time_offset.offset_s == pytest.approx(found.offset_s, abs=0.002)
    assert reported.capture_time(frame) == 10.0


def test_a_target_held_by_the_inertial_filter_is_carried_on_when_it_drops_out(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Blind under the plate, the inertial filter puts the vehicle 1 cm from where the
    odometry's drift does; when it drops out the controller goes on from the filter's word,
    on the odometry's motion since, not from the odometry's own (a jump of centimetres
    mid-alignment, chased at full speed)."""
    s = ControllerSettings(observer_rate=0.0)
    c = PerchingController(s)
    for k in range(3):
        t = k / 30
        c.update(_seen(s, [0.0, 0.0, 0.3], t), t, np.eye(3), _odometry(t))
    held_by_odometry = c.update(None, 4 / 30, np.eye(3), _odometry(4 / 30)).error_m
    assert held_by_odometry is not None
    r_m = np.array([-0.01, 0.0]) - c._magnet_offset(np.eye(3))[:2]  # the filter: 1 cm along x
    monkeypatch.setattr(c.inertial, "state_at", lambda _t: (r_m, np.zeros(2)))
    by_filter = c.update(None, 5 / 30, np.eye(3), _odometry(5 / 30)).error_m
    assert by_filter is not None
    assert by_filter[0] == pytest.approx(held_by_odometry[0] + 0.01, abs=1e-9)
    monkeypatch.setattr(c.inertial, "state_at", lambda _t: None)  # dropped out
    carried_on = c.update(None, 6 / 30, np.eye(3), _odometry(6 / 30, x_m=0.002)).error_m
    assert carried_on is not None
    assert carried_on[0] == pytest.approx(by_filter[0] - 0.002, abs=1e-9)
    # a fix of its own again: the odometry's hold, as without the filter
    c.update(_seen(s, [0.0, 0.0, 0.3], 7 / 30), 7 / 30, np.eye(3), _odometry(7 / 30, x_m=0.002))
    assert c._inertial_gap is None
