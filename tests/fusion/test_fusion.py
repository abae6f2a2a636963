import json
import math
from pathlib import Path

import numpy as np
import pytest

from perchpose.detection.detector import MarkerDetector
from perchpose.errors import FusionFileError
from perchpose.filters.kalman import CovarianceFilterSettings, KalmanSettings, MarkerFilters
from perchpose.fusion.base import STAGE_BOTH, STAGE_INNER, STAGE_NONE, STAGE_OUTER, stage_of
from perchpose.fusion.covariance import CovarianceFusion
from perchpose.fusion.paper import FusionSigmas, PaperFusion, fuse_paper
from perchpose.geometry import facing_pose
from perchpose.pose.marker import solve_marker_pose
from perchpose.sim.render import Renderer
from perchpose.values import MarkerDetection, MarkerPose


def test_stages() -> None:
    assert stage_of(set()) == STAGE_NONE
    assert stage_of({0}) == STAGE_OUTER
    assert stage_of({0, 1}) == STAGE_BOTH
    assert stage_of({1}) == STAGE_INNER
    assert stage_of({1, 2}) == STAGE_INNER


def test_stage_two_weights_each_component_by_its_sigma() -> None:
    outer = np.array([0.0, 0.10, 0.20, 1.00])
    inner = np.array([0.0, 0.20, 0.40, 0.80])
    fused, stage = fuse_paper({0: outer, 1: inner}, FusionSigmas())
    assert stage == STAGE_BOTH
    np.testing.assert_allclose(
        fused[1:],
        [0.275 * 0.10 + 0.725 * 0.20, 0.306 * 0.20 + 0.694 * 0.40, 0.728 * 1.00 + 0.272 * 0.80],
    )


def test_stage_two_yaw_is_averaged_on_the_circle() -> None:
    outer = np.array([math.radians(179.0), 0, 0, 1])
    inner = np.array([math.radians(-179.0), 0, 0, 1])
    fused, _ = fuse_paper({0: outer, 1: inner}, FusionSigmas(yaw=0.5))
    assert abs(math.degrees(abs(fused[0])) - 180.0) < 1e-9


def test_single_marker_stages_pass_the_pose_through() -> None:
    p = np.array([0.3, 0.01, 0.02, 0.5])
    assert fuse_paper({0: p}, FusionSigmas())[0] == pytest.approx(p)
    assert fuse_paper({1: p}, FusionSigmas())[0] == pytest.approx(p)
    fused, stage = fuse_paper({}, FusionSigmas())
    assert stage == STAGE_NONE
    assert np.isnan(fused).all()


def test_sigma_range_is_checked() -> None:
    with pytest.raises(ValueError, match="sigma_z"):
        FusionSigmas(z=1.2)


def _measured(renderer: Renderer, T: np.ndarray) -> tuple[tuple, dict[int, MarkerPose]]:
    """The markers of one rendered frame: detections and their per-marker poses."""
    grey = renderer.render(T, rng=np.random.default_rng(0))
    detections = MarkerDetector(renderer.camera, renderer.target).detect(grey).markers
    poses = {
        d.marker_index: solve_marker_pose(
            renderer.camera, renderer.target.markers[d.marker_index], d.marker_index, d.corners_px
        )
        for d in detections
    }
    assert all(isinstance(p, MarkerPose) for p in poses.values())
    return detections, poses  # type: ignore[return-value]


def _advance(markers: MarkerFilters, measurements: dict[int, MarkerPose], t_s: float) -> None:
    markers.advance({i: m.filter_z for i, m in measurements.items()}, t_s)


def test_paper_fusion_fuses_the_filtered_markers_and_coasts_on_them(
    renderers: dict[str, Renderer],
) -> None:
    r = renderers["fpv"]
    detections, measurements = _measured(r, facing_pose(0.02, -0.01, 0.5, 0.3))
    assert set(measurements) == {0, 1}
    markers = MarkerFilters(2, KalmanSettings())
    fusion = PaperFusion(FusionSigmas(), markers)
    _advance(markers, measurements, 0.0)
    seen = fusion.fuse(0.0, detections, measurements)
    expected, _ = fuse_paper(markers.contributing({0, 1}), FusionSigmas())
    assert seen.stage == STAGE_BOTH
    assert seen.contributing == {0, 1}
    assert seen.age_s == 0.0
    np.testing.assert_allclose(seen.pose, expected)
    _advance(markers, {}, 1 / 30)
    coasting = fusion.fuse(1 / 30, (), {})
    assert coasting.stage == STAGE_BOTH
    assert coasting.age_s == pytest.approx(1 / 30)
    assert fusion.predicted_pose(1 / 30) is None  # no filter of its own


def test_covariance_fusion_owns_one_filter_of_the_joint_pose(
    renderers: dict[str, Renderer],
) -> None:
    r = renderers["fpv"]
    T = facing_pose(0.02, -0.01, 0.5, 0.3)
    detections, measurements = _measured(r, T)
    fusion = CovarianceFusion(r.camera, r.target, CovarianceFilterSettings())
    assert fusion.predicted_pose(0.0) is None
    seen = fusion.fuse(0.0, detections, measurements)
    assert seen.stage == STAGE_BOTH
    assert seen.age_s == 0.0
    np.testing.assert_allclose(seen.pose[1:], T[:3, 3], atol=1e-3)
    # a frame without markers: its own filter coasts and predicts
    coasting = fusion.fuse(1 / 30, (), {})
    assert coasting.stage == STAGE_BOTH
    assert coasting.age_s == pytest.approx(1 / 30)
    predicted = fusion.predicted_pose(2 / 30)
    assert predicted is not None
    np.testing.assert_allclose(predicted[1:], T[:3, 3], atol=1e-3)
    # without the filter, a frame without markers has no pose
    raw = CovarianceFusion(r.camera, r.target, CovarianceFilterSettings(), use_filter=False)
    nothing = raw.fuse(1 / 30, (), {})
    assert nothing.stage == STAGE_NONE
    assert np.isnan(nothing.pose).all()


def test_corners_noisier_than_assumed_move_the_filter_less(
    renderers: dict[str, Renderer],
) -> None:
    """The filter assumes ``corner_sigma_px`` of noise on every corner, or a marker's own
    where its covariance says more (a quad whose corners could not be fitted): a frame whose
    corners are shifted by 2 px then moves the estimate a fraction as far."""
    from dataclasses import replace

    r = renderers["fpv"]
    T = facing_pose(0.02, -0.01, 0.5, 0.3)
    detections, measurements = _measured(r, T)
    outer = tuple(d for d in detections if d.marker_index == 0)
    moved: dict[bool, float] = {}
    for noisy in (False, True):
        fusion = CovarianceFusion(r.camera, r.target, CovarianceFilterSettings())
        for k in range(11):
            before = fusion.fuse(k / 30, outer, {0: measurements[0]}).pose
        shifted = outer[0].corners_px + np.array([2.0, 0.0])
        cov = 1.5**2 * np.eye(8) if noisy else None
        off = replace(outer[0], corners_px=shifted, corner_covariance_px2=cov)
        pose = solve_marker_pose(r.camera, r.target.markers[0], 0, shifted)
        assert isinstance(pose, MarkerPose)
        after = fusion.fuse(11 / 30, (off,), {0: pose}).pose
        moved[noisy] = float(np.linalg.norm(after[1:] - before[1:]))
    # 2 px at 0.5 m is 3.4 mm: the filter, tuned to follow a drone's accelerations, takes
    # nearly all of it on 0.1 px corners, and under a third (0.29 of it) on 1.5 px ones
    assert moved[False] > 3e-3
    assert moved[True] < 0.4 * moved[False]


def test_the_filter_assumes_each_markers_own_noise_where_larger(
    renderers: dict[str, Renderer],
) -> None:
    """Per marker, the corner noise the filter assumes: ``corner_sigma_px`` at least; a
    marker with a covariance its corners' standard deviation; one without, the noise pooled
    from the joint poses' residuals."""
    r = renderers["fpv"]
    fusion = CovarianceFusion(r.camera, r.target, CovarianceFilterSettings(corner_sigma_px=0.1))
    corners = np.zeros((4, 2))
    bare = MarkerDetection(0, corners, "raw")
    quiet = MarkerDetection(1, corners, "raw", 0.02**2 * np.eye(8))
    noisy = MarkerDetection(1, corners, "raw", 0.7**2 * np.eye(8))
    np.testing.assert_allclose(fusion._assumed_sigma_px((bare, quiet, noisy)), [0.1, 0.1, 0.7])
    for _ in range(200):  # residuals of 0.5 px per axis
        fusion.noise.add(0.5**2 * 10, 10)
    assert fusion._assumed_sigma_px((bare, quiet))[0] == pytest.approx(0.5, rel=0.05)
    assert fusion._assumed_sigma_px((bare, quiet))[1] == 0.1


def test_weights_load_from_the_file_fit_fusion_writes(tmp_path: Path) -> None:
    path = tmp_path / "fit.json"
    sigmas = FusionSigmas(x=0.3, y=0.4, z=0.9, yaw=1.0)
    path.write_text(json.dumps({**sigmas.to_dict(), "samples": 12}))
    assert FusionSigmas.load(path) == sigmas


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ('{"x": 0.3, "y": 0.4, "z": 0.9}', "missing yaw"),
        ('{"x": 0.3, "y": 0.4, "z": 1.2, "yaw": 0.5}', "sigma_z must be in"),
        ('{"x": "0.3", "y": 0.4, "z": 0.9, "yaw": 0.5}', "x must be a number"),
        ('{"sigma_x": 0.3}', "missing x, y, z, yaw"),
        ("[0.3, 0.4]", "expected an object"),
        ("not json", "not a JSON file"),
        ("[" * 100_000 + "]" * 100_000, "nested too deep"),
    ],
)
def test_bad_weight_files_name_the_file_and_the_field(
    tmp_path: Path, content: str, message: str
) -> None:
    path = tmp_path / "fit.json"
    path.write_text(content)
    with pytest.raises(FusionFileError, match=message) as caught:
        FusionSigmas.load(path)
    assert str(path) in str(caught.value)
    with pytest.raises(FusionFileError, match="file not found"):
        FusionSigmas.load(tmp_path / "none.json")


def test_corner_noise_pools_the_residuals_and_forgets_slowly() -> None:
    from perchpose.fusion.covariance import CornerNoise

    noise = CornerNoise(prior_px=0.1, frames=30.0, prior_dof=1.0, floor_px=0.005)
    assert noise.variance_px2 == pytest.approx(0.01)
    # 8 corners, 10 degrees of freedom each frame, residuals of 0.02 px per axis
    for _ in range(300):
        noise.add(0.02**2 * 10, 10)
    assert math.sqrt(noise.variance_px2) == pytest.approx(0.02, rel=1e-3)
    # the noise grows: within a few time constants the pool says so
    for _ in range(90):
        noise.add(0.1**2 * 10, 10)
    assert math.sqrt(noise.variance_px2) == pytest.approx(0.1, rel=0.05)
    # a noise-free frame never makes it certain; a frame without dof changes nothing
    quiet = CornerNoise(prior_px=0.1, prior_dof=1.0, floor_px=0.005)
    for _ in range(300):
        quiet.add(0.0, 10)
    assert quiet.variance_px2 == pytest.approx(0.005**2)
    before = quiet.variance_px2
    quiet.add(1.0, 0)
    assert quiet.variance_px2 == before


def test_variance_factor_is_pooled_and_never_under_one() -> None:
    from perchpose.fusion.covariance import VarianceFactor

    misfit = VarianceFactor(frames=30.0)
    assert misfit.factor == 1.0
    for _ in range(50):
        misfit.add(0.5, 2.0)  # residuals smaller than the covariance says: kept at 1
    assert misfit.factor == 1.0
    for _ in range(300):
        misfit.add(18.0, 2.0)
    misfit.add(math.nan, 2.0)  # a degenerate frame: left out
    assert misfit.factor == pytest.approx(9.0, rel=1e-3)
