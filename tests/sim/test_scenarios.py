import math

import numpy as np
import pytest

from perchpose import CameraModel, TargetSpec
from perchpose.errors import ScenarioError
from perchpose.geometry import yaw_rad
from perchpose.sim.scenarios import (
    approach,
    markers_in_view,
    scenario_by_name,
    spread_board_poses,
    static_grid,
    truncated,
)


def test_approach_goes_from_start_to_contact_across_the_yaw_wrap() -> None:
    s = approach()
    z = s.poses[:, 2, 3]
    assert z[0] == pytest.approx(1.5)
    assert z[-1] == pytest.approx(0.03)
    assert np.all(np.diff(z) < 0)
    yaws = np.array([math.degrees(yaw_rad(T[:3, :3])) for T in s.poses])
    assert yaws.max() > 170
    assert yaws.min() < -170
    assert len(s) == 240
    starts = np.flatnonzero(np.diff(s.dropout.astype(int)) == 1) + 1
    assert len(starts) == 2
    assert np.count_nonzero(s.dropout) == 21  # 0.2 s and 0.5 s at 30 fps


def test_static_grid_holds_each_pose() -> None:
    s = static_grid(frames_per_pose=3, z_m=(0.3,), offsets=(0.0,), yaws_deg=(0.0, 90.0))
    assert len(s) == 6
    np.testing.assert_array_equal(s.poses[0], s.poses[2])
    assert not np.allclose(s.poses[2], s.poses[3])


def test_markers_in_view() -> None:
    cam = CameraModel.preset("webcam")
    target = TargetSpec.paper()
    near = approach().poses[-1]
    assert markers_in_view(cam, target, near) == (False, False)
    far = approach().poses[0]
    assert markers_in_view(cam, target, far)[0]


def test_bad_scenarios() -> None:
    with pytest.raises(ScenarioError, match="unknown scenario"):
        scenario_by_name("loop")
    with pytest.raises(ScenarioError, match="contact_z_m"):
        approach(start_z_m=0.1, contact_z_m=0.2)
    with pytest.raises(ScenarioError, match="--frames"):
        truncated(approach(), 0)
    assert len(truncated(approach(), 10)) == 10


def test_spread_board_poses_cover_the_field_at_the_asked_size() -> None:
    camera = CameraModel.preset("fpv")
    rng = np.random.default_rng(0)
    poses = spread_board_poses(camera, 0.21, 200, rng, width_px=(110.0, 180.0), field=0.9)
    centres_px, _ = camera.project(np.array([T[:3, 3] for T in poses]))
    assert np.all(centres_px[:, 0] > 0.05 * 640 - 1e-6)
    assert np.all(centres_px[:, 0] < 0.95 * 640 + 1e-6)
    assert np.all(centres_px[:, 1] > 0.05 * 480 - 1e-6)
    assert np.all(centres_px[:, 1] < 0.95 * 480 + 1e-6)
    # the whole field is used, not only its middle
    assert centres_px[:, 0].min() < 0.15 * 640
    assert centres_px[:, 0].max() > 0.85 * 640
    distances_m = np.array([np.linalg.norm(T[:3, 3]) for T in poses])
    widths_px = 300.0 * 0.21 / distances_m
    assert widths_px.min() >= 110.0 - 1e-6
    assert widths_px.max() <= 180.0 + 1e-6
    tilts_deg = [math.degrees(math.acos(abs(T[2, 2]))) for T in poses]
    assert 0 < max(tilts_deg) < 50.0
