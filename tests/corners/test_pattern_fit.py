"""The whole-pattern corner fit of small blurred markers, against the renderer's true corners."""

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from perchpose.corners.edge_fit import EdgeFit, fit_marker_edges
from perchpose.corners.pattern_fit import (
    PatternFitSettings,
    printed_pattern,
    refine_corners_pattern,
)
from perchpose.corners.pattern_model import banded
from perchpose.detection.detector import MarkerDetector
from perchpose.evaluation.corner_accuracy import corner_error_px
from perchpose.geometry import facing_pose
from perchpose.sim.render import ImageQuality, Renderer
from perchpose.target import MarkerSpec, TargetSpec


def _outer_marker_edges(
    r: Renderer,
    side_px: float,
    quality: ImageQuality,
    rng: np.random.Generator,
    noise: np.random.Generator | None = None,
) -> tuple[NDArray[np.uint8], NDArray[np.float64], EdgeFit]:
    """A frame of the outer marker at about ``side_px`` (a random offset, heading and small
    tilt from ``rng``), its true corners and its edge fit from the detector's quad."""
    z = r.camera.focal_px * 0.15 / side_px
    x, y = rng.uniform(-0.1, 0.1, 2) * z
    T = facing_pose(x, y, z, rng.uniform(-3, 3), rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3))
    image = r.render(T, quality, noise)
    true = r.corners_px(T)[0]
    assert true is not None
    detector = MarkerDetector(r.camera, r.target, "subpix")
    (det,) = [d for d in detector.detect(image).markers if d.marker_index == 0]
    cells = r.target.markers[0].cells
    margins = r.target.white_margin_cells(0)
    edges = fit_marker_edges(image, det.corners_px, r.camera, cells, margin_cells=margins)
    assert edges is not None
    return image, true, edges


def test_the_paper_targets_printed_pattern(paper_target: TargetSpec) -> None:
    outer = printed_pattern(paper_target, 0)
    assert outer is not None
    assert outer.n_cells == 6
    # its own cell edges, the inner marker's (one cell wide and centred, 7 cells across) and
    # the sheet's edge 0.8 cells (the 20 mm quiet zone) beyond the border
    expected = [*range(7), -0.8, 6.8, *(2.5 + np.arange(8) / 7)]
    for lines in (outer.lines_u, outer.lines_v):
        assert all(np.min(np.abs(lines - x)) < 1e-9 for x in expected)
    assert outer.sheet_cells == pytest.approx((0.8, 0.8, 0.8, 0.8))
    cells = paper_target.markers[0].cells
    for row in range(6):
        for col in range(6):
            if 2 <= row <= 3 and 2 <= col <= 3:
                continue  # the centre holds the inner marker
            iu = int(np.searchsorted(outer.lines_u, col + 0.5)) - 1
            iv = int(np.searchsorted(outer.lines_v, row + 0.5)) - 1
            assert outer.code[iv, iu] == cells[row, col]
    assert outer.code[0, 0] == -1  # off the sheet
    # the inner marker: finer cells printed within the outer one's
    assert len(outer.fine) == 1
    assert outer.fine[0] == pytest.approx((2.5, 3.5, 2.5, 3.5))
    inner = printed_pattern(paper_target, 1)
    assert inner is not None
    assert inner.sheet_cells == (math.inf,) * 4
    assert inner.fine == ()


def test_a_marker_printed_at_an_angle_within_reach_is_refused() -> None:
    target = TargetSpec(
        markers=(
            MarkerSpec("DICT_4X4_1000", 997, 150.0),
            MarkerSpec("DICT_ARUCO_ORIGINAL", 5, 25.0, rotation_deg=30.0),
        )
    )
    assert printed_pattern(target, 0) is None
    assert printed_pattern(target, 1) is None


def test_a_flat_image_has_no_pattern(
    paper_target: TargetSpec, renderers: dict[str, Renderer]
) -> None:
    camera = renderers["webcam"].camera
    flat = np.full((camera.height_px, camera.width_px), 128, np.uint8)
    square = np.array([[200.0, 150.0], [220.0, 150.0], [220.0, 170.0], [200.0, 170.0]])
    pattern = printed_pattern(paper_target, 0)
    assert pattern is not None
    assert refine_corners_pattern(flat, square, camera, pattern) is None


def test_small_blurred_markers_are_unbiased(renderers: dict[str, Renderer]) -> None:
    """Outer markers of 16-24 px, blur 1.1 px, no noise: cells of 2.7-4 px, under 4 blur
    sigmas. The one-edge model pulls the corners inwards; the pattern fit does not."""
    r = renderers["fpv"]
    quality = ImageQuality(blur_sigma_px=1.1, noise_sigma=0.0)
    pattern = printed_pattern(r.target, 0)
    assert pattern is not None
    rng = np.random.default_rng(21)
    edge_radial, fit_radial, fit_ms = [], [], []
    for side_px in np.linspace(16.0, 24.0, 8):
        image, true, edges = _outer_marker_edges(r, side_px, quality, rng)
        fit = refine_corners_pattern(
            image, edges.corners_px, r.camera, pattern, blur_px=edges.blur_px
        )
        assert fit is not None
        fitted = fit.corners_px
        edge_radial.append(corner_error_px(edges.corners_px, true)[1])
        ms, radial = corner_error_px(fitted, true)
        fit_radial.append(radial)
        fit_ms.append(ms)
    assert float(np.mean(edge_radial)) < -0.06
    assert abs(float(np.mean(fit_radial))) < 0.01
    assert math.sqrt(float(np.mean(fit_ms))) < 0.04


@pytest.mark.parametrize("camera_name", ["webcam", "fpv"])
def test_analog_markers_of_15_to_25_px_within_a_tenth_of_a_pixel(
    renderers: dict[str, Renderer], camera_name: str
) -> None:
    """The evaluation's analog images (low contrast, blur 1.1 px, noise, JPEG, vignetting),
    both markers at 15-25 px, through the detector's default corners."""
    r = renderers[camera_name]
    quality = ImageQuality.preset("analog_fpv")
    subpix = MarkerDetector(r.camera, r.target, "subpix")
    rng = np.random.default_rng(22)
    radial, ms, found, fitted_count = [], [], 0, 0
    for index, marker in enumerate(r.target.markers):
        for side_px in rng.uniform(15.0, 25.0, 12):
            z = r.camera.focal_px * marker.side_m / side_px
            x, y = rng.uniform(-0.1, 0.1, 2) * z
            yaw = rng.uniform(-3, 3)
            T = facing_pose(x, y, z, yaw, rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3))
            image = r.render(T, quality, rng)
            true = r.corners_px(T)[index]
            dets = [d for d in subpix.detect(image).markers if d.marker_index == index]
            if true is None or not dets or not 15.0 <= dets[0].side_px < 25.0:
                continue
            found += 1
            fit = subpix.fit_corners(image, dets[0])
            if fit is None:
                continue
            fitted_count += 1
            mean_sq, radial_px = corner_error_px(fit.corners_px, true)
            radial.append(radial_px)
            ms.append(mean_sq)
    assert found >= 16
    assert fitted_count >= 0.9 * found
    assert math.sqrt(float(np.mean(ms))) <= 0.1
    assert abs(float(np.mean(radial))) <= 0.02


def test_under_heavy_blur_the_fit_runs_on_2x2_blocks_as_well_as_on_pixels(
    renderers: dict[str, Renderer],
) -> None:
    """Outer markers of 30-50 px under a blur of 2 px (cells of 5-8 px, under 5 blur
    sigmas), with noise: the fit on 2x2 blocks (the default from a blur of 1.5 px) lands
    where the fit on single pixels does, within a fraction of their error, and neither is
    biased."""
    r = renderers["fpv"]
    quality = ImageQuality(blur_sigma_px=2.0, noise_sigma=4.0)
    pattern = printed_pattern(r.target, 0)
    assert pattern is not None
    pixels = PatternFitSettings(bin_above_blur_px=math.inf)
    rng = np.random.default_rng(23)
    binned_error, pixel_error, apart = [], [], []
    for side_px in np.linspace(30.0, 50.0, 6):
        image, true, edges = _outer_marker_edges(r, side_px, quality, rng, rng)
        assert edges.blur_px > 1.5
        fits = [
            refine_corners_pattern(image, edges.corners_px, r.camera, pattern, s, edges.blur_px)
            for s in (None, pixels)
        ]
        assert fits[0] is not None
        assert fits[1] is not None
        binned, single = fits[0].corners_px, fits[1].corners_px
        binned_error.append(corner_error_px(binned, true))
        pixel_error.append(corner_error_px(single, true))
        apart.append(float(np.mean(np.sum((binned - single) ** 2, axis=1))))
    rms_binned = math.sqrt(float(np.mean([e[0] for e in binned_error])))
    rms_pixels = math.sqrt(float(np.mean([e[0] for e in pixel_error])))
    assert rms_binned < 1.2 * rms_pixels
    assert math.sqrt(float(np.mean(apart))) < 0.5 * rms_pixels
    for errors in (binned_error, pixel_error):
        assert abs(float(np.mean([e[1] for e in errors]))) < 0.02


def test_bands_of_analog_interference_are_fitted_where_the_residuals_show_them(
    renderers: dict[str, Renderer],
) -> None:
    """Outer markers of 30-50 px under a blur of 2 px and the harsh preset's interference
    (horizontal bands of 6 grey levels, streaked rows): a fit that never takes the bands in
    leaves the corners several times further off than one that does where its score test
    finds them. Without interference the test finds none, and the corners are those of the
    fit without the band model."""
    r = renderers["fpv"]
    pattern = printed_pattern(r.target, 0)
    assert pattern is not None
    settings = PatternFitSettings()
    never = PatternFitSettings(banded_above=math.inf)
    rng = np.random.default_rng(24)
    for interference in (6.0, 0.0):
        quality = ImageQuality(blur_sigma_px=2.0, noise_sigma=4.0, interference=interference)
        default_ms, never_ms, found = [], [], []
        for side_px in np.linspace(30.0, 50.0, 8):
            image, true, edges = _outer_marker_edges(r, side_px, quality, rng, rng)
            fit = refine_corners_pattern(
                image, edges.corners_px, r.camera, pattern, blur_px=edges.blur_px
            )
            plain = refine_corners_pattern(
                image, edges.corners_px, r.camera, pattern, never, edges.blur_px
            )
            assert fit is not None
            assert plain is not None
            found.append(banded(fit.banding, settings.banded_above))
            default_ms.append(corner_error_px(fit.corners_px, true)[0])
            never_ms.append(corner_error_px(plain.corners_px, true)[0])
            if not found[-1]:
                assert np.array_equal(fit.corners_px, plain.corners_px)
        if interference > 0:
            assert np.mean(found) >= 0.75
            rms, rms_never = (
                math.sqrt(float(np.mean(default_ms))),
                math.sqrt(float(np.mean(never_ms))),
            )
            assert rms < 0.5 * rms_never
        else:
            assert not any(found)
