"""Corner fits from a start (``perchpose.corners.refinement``): what the flags ask of a start."""

from dataclasses import replace

import numpy as np
import pytest

from perchpose.corners.refinement import CornerFitter
from perchpose.detection.detector import MarkerDetector
from perchpose.geometry import facing_pose
from perchpose.sim.render import ImageQuality, Renderer
from perchpose.values import MarkerDetection


def test_a_fit_that_requires_edges_runs_no_pattern_fit_without_them(
    renderers: dict[str, Renderer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A 22 px marker gets the pattern fit from its quad where its edges cannot be fitted,
    unless the call requires edges: then there is no answer, and no pattern fit ran."""
    r = renderers["fpv"]
    T = facing_pose(0.01, 0.0, r.camera.focal_px * 0.15 / 22.0, 0.4)
    image = r.render(T, ImageQuality(blur_sigma_px=1.1, noise_sigma=2.0), np.random.default_rng(5))
    (det,) = [
        d
        for d in MarkerDetector(r.camera, r.target, "subpix").detect(image).markers
        if d.marker_index == 0
    ]
    fitter = CornerFitter(r.camera, r.target)
    assert fitter.fit_corners(image, det) is not None
    monkeypatch.setattr(fitter, "fit_edges", lambda grey, d: None)
    from_pattern = fitter.fit_corners(image, det)
    assert from_pattern is not None
    assert fitter.pattern_s > 0
    truth = r.corners_px(T)[0]
    assert truth is not None
    assert np.max(np.abs(from_pattern.corners_px - truth)) < 0.2
    assert fitter.fit_corners(image, det, require_edges=True) is None
    assert fitter.pattern_s == 0


@pytest.mark.parametrize(
    ("quality", "side_px", "settles"),
    [(ImageQuality(), 46.0, True), (ImageQuality.preset("harsh"), 75.0, False)],
)
def test_a_predicted_start_is_settled_only_where_its_pull_matters(
    renderers: dict[str, Renderer],
    monkeypatch: pytest.MonkeyPatch,
    quality: ImageQuality,
    side_px: float,
    settles: bool,
) -> None:
    """A prediction 0.8 px outside the edges pulls the edge fit's corners inwards by about
    0.02 px (``STRADDLE_PULL_PX``): on a clean frame that is several times their noise, and
    the fit runs again from its own corners; on a harsh frame (corners 0.3-0.5 px off, the
    fit's own standard deviation about 0.1 px; no pattern fit at 75 px) it is not, and the
    first fit stands."""
    r = renderers["fpv"]
    T = facing_pose(0.01, 0.0, r.camera.focal_px * 0.15 / side_px, 0.3)
    image = r.render(T, quality, np.random.default_rng(2))
    truth = r.corners_px(T)[0]
    assert truth is not None
    outward = (truth - truth.mean(axis=0)) / np.linalg.norm(truth - truth.mean(axis=0), axis=1)[
        :, None
    ]
    start = MarkerDetection(0, truth + 0.8 * outward, "tracked")
    fitter = CornerFitter(r.camera, r.target)
    fitter.pattern_settings = replace(fitter.pattern_settings, max_side_px=0.0)  # edges alone
    fits = []
    fit_edges = fitter.fit_edges
    monkeypatch.setattr(fitter, "fit_edges", lambda grey, d: fits.append(d) or fit_edges(grey, d))
    fitted = fitter.fit_corners(image, start, predicted=True)
    assert fitted is not None
    assert len(fits) == (2 if settles else 1)
    if settles:
        # settled, the corners are as near the truth as from the truth itself
        from_truth = fitter.fit_corners(image, replace(start, corners_px=truth), predicted=True)
        assert from_truth is not None
        assert np.max(np.abs(fitted.corners_px - from_truth.corners_px)) < 0.01


@pytest.mark.parametrize(
    ("sd_px", "apart_px", "kept"),
    [(0.01, 0.25, True), (0.01, 0.35, False), (0.1, 0.45, True), (0.1, 0.55, False)],
)
def test_a_second_fit_may_land_apart_by_the_first_fits_own_noise(
    renderers: dict[str, Renderer],
    monkeypatch: pytest.MonkeyPatch,
    sd_px: float,
    apart_px: float,
    kept: bool,
) -> None:
    """The second edge fit of a predicted marker must land within ``SETTLE_PX`` (0.3 px) of
    the first, or within ``SETTLE_SDS`` (5) of the first's standard deviations where that
    is more (harsh frames: about 0.1 px)."""
    from perchpose.corners.edge_fit import EdgeFit

    r = renderers["fpv"]
    T = facing_pose(0.01, 0.0, 0.6, 0.3)
    truth = r.corners_px(T)[0]
    assert truth is not None
    first = EdgeFit(truth, 1.0, sd_px**2 * np.eye(8))
    second = EdgeFit(truth + np.array([apart_px, 0.0]), 1.0, first.covariance_px2)
    fitter = CornerFitter(r.camera, r.target)
    monkeypatch.setattr(fitter, "fit_edges", lambda grey, d: second)
    image = np.zeros((r.camera.height_px, r.camera.width_px), np.uint8)
    settled = fitter._settled(image, MarkerDetection(0, truth, "tracked"), first)
    assert (settled is second) == kept
    assert (settled is None) == (not kept)


def test_a_quad_start_may_be_most_of_a_cell_off(
    renderers: dict[str, Renderer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without fitted edges the pattern fit starts from the quad's own corners, which on
    harsh frames can be 0.7 of a cell off: it may move a corner up to a cell from there."""
    r = renderers["fpv"]
    T = facing_pose(0.01, 0.0, r.camera.focal_px * 0.15 / 30.0, 0.4)
    image = r.render(T, ImageQuality(blur_sigma_px=1.3, noise_sigma=2.0), np.random.default_rng(6))
    truth = r.corners_px(T)[0]
    assert truth is not None
    cell_px = 30.0 / r.target.markers[0].cells.shape[0]
    off = truth.copy()
    off[0] += 0.8 * cell_px * np.array([0.6, -0.8])  # 0.8 of a cell off
    fitter = CornerFitter(r.camera, r.target)
    monkeypatch.setattr(fitter, "fit_edges", lambda grey, d: None)
    fitted = fitter.fit_corners(image, MarkerDetection(0, off, "raw"))
    assert fitted is not None
    assert np.max(np.abs(fitted.corners_px - truth)) < 0.2
    fitter.pattern_settings = replace(fitter.pattern_settings, max_shift_quad_cells=0.6)
    assert fitter.fit_corners(image, MarkerDetection(0, off, "raw")) is None


def test_once_a_fit_finds_the_video_banded_the_next_fits_take_the_bands_in(
    renderers: dict[str, Renderer],
) -> None:
    """Interference belongs to the link: after a fit whose residuals show bands over the
    rows, the next ``banded_fits`` pattern fits model them from the first round."""
    r = renderers["fpv"]
    T = facing_pose(0.01, 0.0, r.camera.focal_px * 0.15 / 36.0, 0.4)
    rng = np.random.default_rng(7)
    fitter = CornerFitter(r.camera, r.target)
    clean = r.render(T, ImageQuality(blur_sigma_px=2.0, noise_sigma=4.0), rng)
    banded = r.render(T, ImageQuality(blur_sigma_px=2.0, noise_sigma=4.0, interference=8.0), rng)
    start = r.corners_px(T)[0]
    assert start is not None
    det = MarkerDetection(0, start, "raw")
    assert fitter.fit_corners(clean, det) is not None
    assert fitter.banded_fits_left == 0
    assert fitter.fit_corners(banded, det) is not None
    assert fitter.banded_fits_left == fitter.pattern_settings.banded_fits
    assert fitter.fit_corners(clean, det) is not None
    assert fitter.banded_fits_left == fitter.pattern_settings.banded_fits - 1
