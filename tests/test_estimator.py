import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from perchpose import CameraModel, PerchingEstimator, TargetSpec
from perchpose.errors import ImageError, TimestampError
from perchpose.evaluation.metrics import normalised_error
from perchpose.geometry import facing_pose, wrap_angle_deg, yaw_rad
from perchpose.io.sources import open_source
from perchpose.sim.render import ImageQuality, Renderer
from perchpose.sim.scenarios import approach, markers_in_view, random_motion
from perchpose.sim.sequence import dropout_occluder, rendered_frames
from perchpose.values import Estimate

# The paper's Table 1 positions (cm) and Table 2 headings (deg).
TABLE1_CM = [(0, 0, 24), (3, 5, 16), (5, 8, 11), (10, 12, 7), (6, -5, 18)]
TABLE2_DEG = [175, -160, 135, 90, 30, 10, 5, 0]


def _track_static(r: Renderer, T: np.ndarray, frames: int, seed: int) -> list:
    est = PerchingEstimator(r.camera, r.target)
    rng = np.random.default_rng(seed)
    return [est.update(r.render(T, rng=rng), k / 30) for k in range(frames)]


@pytest.mark.parametrize("camera_name", ["webcam", "fpv", "fpv_wide"])
def test_table1_positions_in_view_within_2_mm_and_half_a_degree(
    renderers: dict[str, Renderer], camera_name: str
) -> None:
    r = renderers[camera_name]
    in_view = 0
    for x, y, z in TABLE1_CM:
        T = facing_pose(x / 100, y / 100, z / 100, 0.0)
        if not any(markers_in_view(r.camera, r.target, T)):
            continue
        estimates = _track_static(r, T, 6, seed=x + y + z)
        if not estimates[-1].valid:
            continue  # in view but too oblique to detect: counted below
        in_view += 1
        for e in estimates:
            assert e.valid
            # every frame; the paper reports 0.6 cm and 3 deg
            assert abs(e.x_cm - x) <= 0.2
            assert abs(e.y_cm - y) <= 0.2
            assert abs(e.z_cm - z) <= 0.2
            assert abs(wrap_angle_deg(e.yaw_deg)) <= 0.5
    assert in_view >= 3


@pytest.mark.parametrize("camera_name", ["webcam", "fpv_wide"])
def test_table2_headings_within_half_a_degree(
    renderers: dict[str, Renderer], camera_name: str
) -> None:
    r = renderers[camera_name]
    for heading in TABLE2_DEG:
        T = facing_pose(0.01, -0.01, 0.2, math.radians(heading))
        for e in _track_static(r, T, 4, seed=heading % 7):
            assert e.valid
            assert abs(wrap_angle_deg(e.yaw_deg - heading)) <= 0.5  # the paper: 3 deg


def test_estimate_carries_markers_and_timings(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    (e,) = _track_static(r, facing_pose(0.0, 0.0, 0.45, 0.5), 1, seed=0)
    assert e.stage == 2
    assert e.detected == (0, 1)
    assert [m.label for m in e.markers] == ["DICT_4X4_1000:997", "DICT_ARUCO_ORIGINAL:5"]
    for m in e.markers:
        assert m.measurement is not None
        assert m.filtered_pose is not None
        assert m.contributing
        assert m.measurement.reproj_rms_px < 1.0
    assert e.timings.total_ms >= e.timings.detect_ms > 0
    assert e.timings.corners_ms > 0
    assert e.timings.fuse_ms > 0
    stages = [e.timings.stage_ms(stage) for stage in e.timings.STAGES]
    assert min(stages) >= 0
    # the stages partition the update: each clock reading ends one and starts the next
    assert sum(stages) == pytest.approx(e.timings.total_ms, abs=1e-6)


def _through_a_dropout(
    r: Renderer, est: PerchingEstimator
) -> tuple[list[Estimate], list[Estimate], Estimate]:
    """A still target at 60 cm: 5 frames seen, 10 with both markers hidden, then 1 seen."""
    rng = np.random.default_rng(0)
    T = facing_pose(0.02, 0.0, 0.6, 0.2)
    hidden = (dropout_occluder(r.camera, r.target, T),)
    seen = [est.update(r.render(T, rng=rng), k / 30) for k in range(5)]
    lost = [est.update(r.render(T, rng=rng, occluders=hidden), k / 30) for k in range(5, 15)]
    back = est.update(r.render(T, rng=rng), 15 / 30)
    return seen, lost, back


def test_stays_valid_for_exactly_eight_lost_frames(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    seen, lost, back = _through_a_dropout(r, PerchingEstimator(r.camera, r.target))
    assert all(e.valid and e.stage == 2 for e in seen)
    assert [e.valid for e in lost] == [True] * 8 + [False] * 2
    assert [e.stage for e in lost] == [2] * 8 + [0] * 2
    assert all(e.markers[0].missed_frames == k + 1 for k, e in enumerate(lost[:8]))
    coasting = lost[7]
    assert abs(coasting.x_cm - 2.0) < 0.5  # coasted from a still target: stays put
    assert back.valid
    assert back.stage == 2
    assert back.markers[0].missed_frames == 0
    assert abs(back.z_cm - 60.0) < 0.5


@pytest.mark.parametrize("fusion", ["covariance", "paper"])
def test_a_camera_stall_ends_the_estimate(renderers: dict[str, Renderer], fusion: str) -> None:
    """Frames at 0-1 s of a target approaching at 30 cm/s, then one frame without it at 6 s:
    the filter must not extrapolate over the 5 s gap (it once gave z = -76 cm, valid)."""
    r = renderers["webcam"]
    est = PerchingEstimator(r.camera, r.target, fusion=fusion)  # type: ignore[arg-type]
    rng = np.random.default_rng(1)
    for k in range(31):
        t = k / 30
        e = est.update(r.render(facing_pose(0.02, 0.0, 0.8 - 0.3 * t, 0.1), rng=rng), t)
        assert e.valid
        assert e.age_s == 0.0
    hidden = facing_pose(0.02, 0.0, 0.5, 0.1)
    blank = r.render(hidden, rng=rng, occluders=(dropout_occluder(r.camera, r.target, hidden),))
    coasting = est.update(blank, 31 / 30)
    assert coasting.valid  # one frame later: coasting is what the filter is for
    assert coasting.age_s == pytest.approx(1 / 30)
    stale = est.update(blank, 6.0)
    assert not stale.valid
    assert stale.stage == 0
    assert math.isnan(stale.z_cm)
    # seen again after the gap: a fresh track at the new measurement, not a jump from the old
    again = est.update(r.render(facing_pose(0.0, 0.0, 0.4, 0.1), rng=rng), 6.1)
    assert again.valid
    assert abs(again.z_cm - 40.0) < 0.3


@pytest.mark.parametrize("fusion", ["covariance", "paper"])
def test_a_jump_is_followed_at_once(renderers: dict[str, Renderer], fusion: str) -> None:
    """A still target at 25 cm, then (re-acquired, or another sequence) at 150 cm: the first
    frame after the jump is already there, where a filter that smooths it lagged by over a
    metre and took 11 frames to settle."""
    r = renderers["webcam"]
    est = PerchingEstimator(r.camera, r.target, fusion=fusion)  # type: ignore[arg-type]
    rng = np.random.default_rng(3)
    near, far = facing_pose(0.01, 0.0, 0.25, 0.3), facing_pose(-0.05, 0.02, 1.5, 0.3)
    for k in range(15):
        assert est.update(r.render(near, rng=rng), k / 30).valid
    assert est.reinitialised == 0
    after = [est.update(r.render(far, rng=rng), k / 30) for k in range(15, 20)]
    assert est.reinitialised >= 1
    for e in after:
        assert e.valid
        assert abs(e.z_cm - 150.0) < 1.5
        assert abs(e.x_cm + 5.0) < 0.5


@pytest.mark.parametrize("fusion", ["covariance", "paper"])
def test_an_approach_never_restarts_a_filter_nor_drops_a_marker(
    approach_fpv_dir: Path, fusion: str
) -> None:
    """The impossible-innovation gate and the markers' consistency test stay silent on a
    rendered approach with a dropout."""
    camera = CameraModel.load(approach_fpv_dir / "camera.yaml")
    est = PerchingEstimator(camera, TargetSpec.paper(), fusion=fusion)  # type: ignore[arg-type]
    frames = open_source(str(approach_fpv_dir))
    valid = 0
    for frame in frames:
        assert frame.image is not None
        e = est.update(frame.image, frame.t_s)
        valid += e.valid
        assert not any("disagrees" in m.rejected for m in e.markers)
    assert valid > 60
    assert est.reinitialised == 0


def test_timestamps_must_be_finite_and_not_go_backwards(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    est = PerchingEstimator(r.camera, r.target)
    image = r.render(facing_pose(0.0, 0.0, 0.5))
    est.update(image, 1.0)
    with pytest.raises(TimestampError, match="goes backwards"):
        est.update(image, 0.5)
    with pytest.raises(TimestampError, match="not finite"):
        est.update(image, math.nan)
    for bad in ("soon", None, [1.0]):
        with pytest.raises(TimestampError, match="is not a number"):
            est.update(image, bad)  # type: ignore[arg-type]
    est.update(image, 1.0)  # the same time again is allowed


def test_image_of_the_wrong_size_is_an_error(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    est = PerchingEstimator(r.camera, r.target)
    with pytest.raises(ImageError, match="calibrated for 640x480"):
        est.update(np.zeros((240, 320), np.uint8), 0.0)


def test_blank_frame_is_no_estimate(renderers: dict[str, Renderer]) -> None:
    r = renderers["fpv"]
    e = PerchingEstimator(r.camera, r.target).update(np.full((480, 640), 128, np.uint8), 0.0)
    assert not e.valid
    assert e.stage == 0
    assert math.isnan(e.x_cm)
    assert math.isnan(e.yaw_deg)


def test_covariance_fusion_keeps_the_dropout_rule(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    est = PerchingEstimator(r.camera, r.target, fusion="covariance")
    seen, lost, back = _through_a_dropout(r, est)
    assert all(e.valid and e.stage == 2 for e in seen)
    assert [e.valid for e in lost] == [True] * 8 + [False] * 2
    assert abs(lost[7].x_cm - 2.0) < 0.2
    assert back.valid
    assert abs(back.z_cm - 60.0) < 0.2


def test_covariance_fusion_follows_an_approach_better_than_the_papers(
    renderers: dict[str, Renderer],
) -> None:
    """Both fusions on the same rendered approach (1.2 m to 0.15 m, decelerating)."""
    r = renderers["fpv"]
    rng = np.random.default_rng(4)
    n = 60
    z = 0.15 + 1.05 * (1 - np.linspace(0, 1, n)) ** 2
    poses = [
        facing_pose(0.03 * zk, -0.02 * zk, float(zk), 0.3 + 0.01 * k) for k, zk in enumerate(z)
    ]
    frames = [r.render(T, rng=rng) for T in poses]
    errors = {}
    stages = []
    for fusion in ("paper", "covariance"):
        est = PerchingEstimator(r.camera, r.target, fusion=fusion)
        err, offsets = [], []
        for k, (T, image) in enumerate(zip(poses, frames, strict=True)):
            e = est.update(image, k / 30)
            assert e.valid
            d = np.array([e.x_cm, e.y_cm, e.z_cm]) / 100 - T[:3, 3]
            err.append(np.linalg.norm(d) / T[2, 3])
            offsets.append(d)
            stages.append(e.stage)
        errors[fusion] = np.array(err)
        if fusion == "covariance":
            # no jump of the estimate beyond the target's own motion, including where the inner
            # marker comes into view (stage 1 -> 2)
            jumps = np.linalg.norm(np.diff(np.array(offsets), axis=0), axis=1)
            assert jumps.max() < 0.005
    assert {1, 2} <= set(stages)
    # relative position error: p95 within 1 % of the distance, and no worse than the paper's
    assert np.percentile(errors["covariance"], 95) < 0.01
    assert np.median(errors["covariance"]) <= np.median(errors["paper"])


@pytest.mark.parametrize("camera_name", ["webcam", "fpv_wide"])
def test_single_frames_up_to_two_metres(renderers: dict[str, Renderer], camera_name: str) -> None:
    """One frame each, a fresh estimator, random tilted poses from 12 cm to 2 m: position
    within 1.5 % of the distance and yaw within 1 deg."""
    r = renderers[camera_name]
    rng = np.random.default_rng(2)
    for z in np.geomspace(0.12, 2.0, 16):
        x, y = rng.uniform(-0.1, 0.1, 2) * z
        T = facing_pose(x, y, z, rng.uniform(-3, 3), rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2))
        e = PerchingEstimator(r.camera, r.target).update(r.render(T, rng=rng), 0.0)
        assert e.valid
        error = np.linalg.norm(np.array([e.x_cm, e.y_cm, e.z_cm]) / 100 - T[:3, 3])
        assert error <= 0.015 * z
        yaw_true = math.degrees(math.atan2(T[1, 0], T[0, 0]))
        assert abs(wrap_angle_deg(e.yaw_deg - yaw_true)) <= 1.0


@pytest.mark.parametrize("fusion", ["covariance", "paper"])
def test_the_stage_sequence_of_an_approach_is_pinned(approach_fpv_dir: Path, fusion: str) -> None:
    """The stages of the rendered 3 s approach, run-length encoded: the outer marker alone, the
    inner one glimpsed once, both, the 12-frame dropout (8 coasted frames at stage 2, then
    none), both again, the inner marker alone at the end. Both fusions report the same."""
    camera = CameraModel.load(approach_fpv_dir / "camera.yaml")
    est = PerchingEstimator(camera, TargetSpec.paper(), fusion=fusion)  # type: ignore[arg-type]
    stages = [est.update(f.image, f.t_s).stage for f in open_source(str(approach_fpv_dir))]
    runs = [(stage, len(list(group))) for stage, group in itertools.groupby(stages)]
    assert runs == [(1, 6), (2, 1), (1, 5), (2, 26), (0, 4), (2, 29), (3, 19)]


def test_a_budget_leaves_out_the_pattern_fit_and_says_so(renderers: dict[str, Renderer]) -> None:
    """At 60 cm through the webcam the inner marker spans about 23 px and gets the pattern
    fit; within a budget it cannot meet, the frame goes without it and says so, and the pose
    is still there, near the unhurried one."""
    r = renderers["webcam"]
    T = facing_pose(0.02, -0.01, 0.6, 0.3)
    image = r.render(T, rng=np.random.default_rng(4))
    full = PerchingEstimator(r.camera, r.target, fusion="paper").update(image, 0.0)
    hurried = PerchingEstimator(r.camera, r.target, fusion="paper", budget_ms=1e-3).update(
        image, 0.0
    )
    assert full.skipped == ()
    assert hurried.skipped == ("pattern fit m1",)
    assert hurried.stage == full.stage == 2
    assert np.linalg.norm(hurried.t_m - full.t_m) < 1e-3
    with pytest.raises(ValueError, match="budget_ms"):
        PerchingEstimator(r.camera, r.target, budget_ms=0.0)


def test_a_budget_skips_the_search_after_tracking_lost_a_marker(
    renderers: dict[str, Renderer],
) -> None:
    """Tracking loses the markers (a blank frame): without a budget the whole frame is
    searched again; within one spent already the frame skips that search, the filter coasts
    and the estimate says what was skipped."""
    r = renderers["webcam"]
    image = r.render(facing_pose(0.0, 0.0, 0.5, 0.2), rng=np.random.default_rng(1))
    blank = np.full_like(image, 128)
    for budget, expected in ((None, ()), (1e-3, ("search",))):
        est = PerchingEstimator(r.camera, r.target, budget_ms=budget)
        assert est.update(image, 0.0).valid
        coasted = est.update(blank, 1 / 30)
        assert coasted.skipped == expected
        assert coasted.valid
        assert coasted.predicted


def test_a_budget_does_not_keep_the_target_from_being_found_under_glare(
    renderers: dict[str, Renderer],
) -> None:
    """Under glare the frame as it is shows no marker and a spent budget leaves no room for a
    second search in the same frame; the next frame starts from the next clip level, so the
    target is found within a few frames all the same."""
    from perchpose.detection.detector import GLARE_CLIP_LEVELS
    from perchpose.sim.render import ImageQuality

    r = renderers["fpv"]
    T = facing_pose(0.03, -0.02, 1.0, 0.7)
    image = r.render(T, ImageQuality.preset("harsh"), np.random.default_rng(1))
    est = PerchingEstimator(r.camera, r.target, budget_ms=1e-3)
    estimates = [est.update(image, k / 30) for k in range(len(GLARE_CLIP_LEVELS))]
    assert "glare search" in estimates[0].skipped
    assert estimates[-1].valid
    assert np.linalg.norm(estimates[-1].t_m - T[:3, 3]) < 0.01


@pytest.mark.parametrize("fusion", ["covariance", "paper"])
def test_the_whole_pose_and_its_covariance(renderers: dict[str, Renderer], fusion: str) -> None:
    """A tilted target: the estimate's full rotation (yaw, roll and pitch) and position come
    back, with a symmetric, positive definite covariance whose standard deviations are
    positive; a frame without a pose has none."""
    r = renderers["fpv"]
    T = facing_pose(0.03, -0.02, 0.5, 2.4, 0.25, -0.15)
    est = PerchingEstimator(r.camera, r.target, fusion=fusion)
    e = est.update(r.render(T, rng=np.random.default_rng(2)), 0.0)
    assert e.valid
    R_error = e.T_camera_target[:3, :3] @ T[:3, :3].T
    assert math.degrees(math.acos(min(1.0, (np.trace(R_error) - 1) / 2))) < 0.2
    assert np.allclose(e.T_camera_target[:3, 3], T[:3, 3], atol=2e-3)
    C = e.covariance
    assert C.shape == (6, 6)
    assert np.allclose(C, C.T)
    assert np.all(np.linalg.eigvalsh(C) > 0)
    assert all(0 < s < 0.01 for s in e.std)
    assert np.all(np.isnan(Estimate.none(0.0).covariance))
    assert np.all(np.isnan(Estimate.none(0.0).T_camera_target))


def test_the_joint_poses_covariance_follows_the_spread_of_its_errors(
    approach_fpv_dir: Path,
) -> None:
    """On a rendered approach, without the filter, the errors over their standard deviations
    (x, y, z, yaw) spread by 0.75-1.25 (the goal is 0.8-1.2; this approach measures
    0.95-1.02). The covariance comes from the corners' own covariances (the edge fit's, with
    neighbouring corners correlated through the side they share, scaled up where the fit's
    residuals say they err more); with the corners taken as independent at the residuals'
    pooled noise it was 0.24-0.43, and at the filter's fixed 0.1 px 0.05-0.2."""
    import csv

    camera = CameraModel.load(approach_fpv_dir / "camera.yaml")
    est = PerchingEstimator(camera, TargetSpec.paper(), use_filter=False)
    with (approach_fpv_dir / "truth.csv").open() as f:
        truth = {int(row["frame"]): row for row in csv.DictReader(f)}
    normalised = []
    for frame in open_source(str(approach_fpv_dir)):
        assert frame.image is not None
        e = est.update(frame.image, frame.t_s)
        row = truth[frame.index]
        if not e.valid or e.predicted or row["valid"] != "1":
            continue
        t_true = np.array([float(row[k]) for k in ("x_cm", "y_cm", "z_cm")]) / 100.0
        yaw_error = math.radians(wrap_angle_deg(e.yaw_deg - float(row["yaw_deg"])))
        d = np.concatenate([e.t_m - t_true, [yaw_error]])
        sigma = np.array(e.std)
        normalised.append(d / sigma)
    spread = np.array(normalised).std(axis=0)
    assert len(normalised) > 50
    assert np.all((spread > 0.75) & (spread < 1.25)), spread


def test_the_filtered_covariance_follows_the_spread_on_motion_the_filter_models(
    renderers: dict[str, Renderer],
) -> None:
    """A target moving as the filter's motion model says (white-noise acceleration held in
    view by a weak spring; rendered, default images): the filtered estimate's errors over
    their standard deviations spread by 0.75-1.25 per component (this sequence: 0.85-1.05;
    seeds 3 and 4: 0.92-1.17). The filter's gains come from its assumed 0.1 px corners;
    scaling its covariance by how the corners' own covariances compare with that (as before)
    made it 1.9-3.3 times optimistic on such motion."""
    r = renderers["fpv"]
    scenario = random_motion(seed=2, duration_s=4.0)
    rng = np.random.default_rng(2)
    est = PerchingEstimator(r.camera, r.target)
    normalised = []
    for k, T in enumerate(scenario.poses):
        e = est.update(r.render(T, rng=rng), float(scenario.t_s[k]))
        if k < 10 or not e.valid or e.predicted:
            continue
        normalised.append(normalised_error(e, T))
    spread = np.array(normalised).std(axis=0)
    assert len(normalised) > 100
    assert np.all((spread > 0.75) & (spread < 1.25)), spread


def test_tracking_hints_move_on_at_the_pace_of_the_last_two_frames() -> None:
    """The hint for the next frame carries each corner on at the velocity it had between the
    last two frames; a marker seen once stays where it was, and a gap longer than twice the
    frames' spacing leaves every marker where it was."""
    from perchpose.detection.windows import extrapolated
    from perchpose.values import MarkerDetection

    square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    earlier = (MarkerDetection(0, square, "raw"),)
    hint = (MarkerDetection(0, square + [2.0, 1.0], "raw"), MarkerDetection(1, square, "raw"))
    moved = extrapolated(hint, 0.1, earlier, 0.0, 0.2)
    assert np.allclose(moved[0].corners_px, square + [4.0, 2.0])
    assert np.array_equal(moved[1].corners_px, square)
    half = extrapolated(hint, 0.1, earlier, 0.0, 0.15)
    assert np.allclose(half[0].corners_px, square + [3.0, 1.5])
    assert extrapolated(hint, 0.1, earlier, 0.0, 0.35) is hint
    assert extrapolated(hint, 0.1, (), 0.0, 0.2) is hint


def test_a_small_target_under_glare_is_found_within_a_few_frames() -> None:
    """The harsh approach through the wide fisheye: at 150 cm the outer marker is 20-23 px,
    the bright surround hides it in the frame itself, and only the first clip level shows it,
    on some frames (a quick look there finds it on 17 of the first 30). Looking at that level
    on every other frame, the estimator has it by the third frame and keeps it; going through
    the whole ladder first, one way a frame, it took eleven."""
    camera, target = CameraModel.preset("fpv_wide"), TargetSpec.paper()
    scenario = approach(duration_s=8.0, quality=ImageQuality.preset("harsh"))
    est = PerchingEstimator(camera, target)
    valid = []
    for i, image in rendered_frames(scenario, camera, target, 0, False):
        e = est.update(image, float(scenario.t_s[i]))
        valid.append(e.valid)
        if e.valid:
            T = scenario.poses[i]
            assert np.linalg.norm(e.t_m - T[:3, 3]) < 0.05 * np.linalg.norm(T[:3, 3])
        if i == 5:
            break
    assert valid[3:] == [True, True, True]


def test_a_rotation_chosen_on_a_tie_does_not_choose_the_next() -> None:
    """The harsh approach (seed 9) starts with a 30 px marker whose two IPPE solutions
    reproject alike (0.135 px both): the first frame takes one by chance, 15 deg from the true
    rotation and 1 deg of yaw off. The next frame's corners favour the other (0.12 against
    0.20 px); a toss-up is no reference to hold that frame to, so it takes the other, within
    0.5 deg of the true yaw (held to the first frame's choice, 1.3 deg off)."""
    camera, target = CameraModel.preset("fpv"), TargetSpec.paper()
    scenario = approach(duration_s=8.0, quality=ImageQuality.preset("harsh"))
    est = PerchingEstimator(camera, target)
    for i, image in rendered_frames(scenario, camera, target, 9, False):
        e = est.update(image, float(scenario.t_s[i]))
        measurement = e.markers[0].measurement
        assert measurement is not None
        if i == 0:
            assert measurement.ambiguous
        if i == 1:
            true_yaw = math.degrees(yaw_rad(scenario.poses[i][:3, :3]))
            assert abs(wrap_angle_deg(math.degrees(measurement.yaw_rad) - true_yaw)) < 0.5
            assert abs(wrap_angle_deg(e.yaw_deg - true_yaw)) < 0.5
            break
