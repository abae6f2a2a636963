import math
from dataclasses import dataclass, replace

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from perchpose import CameraModel
from perchpose.geometry import facing_pose
from perchpose.sim.render import ImageQuality, Occluder, Renderer, grid_rays


def test_same_seed_same_frame(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    T = facing_pose(0.0, 0.0, 0.5, 0.3)
    a = r.render(T, ImageQuality(), np.random.default_rng(5))
    b = r.render(T, ImageQuality(), np.random.default_rng(5))
    c = r.render(T, ImageQuality(), np.random.default_rng(6))
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)


def test_renderers_of_one_camera_share_its_rays_and_other_lenses_get_their_own() -> None:
    webcam = CameraModel.preset("webcam")
    rays = grid_rays(webcam, 2)
    assert grid_rays(CameraModel.preset("webcam"), 2) is rays  # an equal camera, made again
    assert not rays.flags.writeable
    assert rays.shape == (480 * 2 * 640 * 2, 3)
    # the grid's first sample is a quarter pixel up and left of pixel (0, 0)'s centre
    np.testing.assert_allclose(rays[0], webcam.pixel_rays(np.array([[-0.25, -0.25]]))[0], 1e-6)
    assert grid_rays(webcam, 3).shape == (480 * 3 * 640 * 3, 3)
    shifted = replace(webcam, K=webcam.K + np.array([[0, 0, 1.0], [0, 0, 0], [0, 0, 0]]))
    other = grid_rays(shifted, 2)
    assert other is not rays
    assert not np.allclose(other, rays)


def test_clean_render_levels_and_geometry(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    q = ImageQuality.preset("clean")
    T = facing_pose(0.0, 0.0, 1.0)
    img = r.render(T, q)
    assert img.dtype == np.uint8
    assert img.shape == (480, 640)
    # far from the target: the surround; outer marker's black border; the white centre cells
    assert img[5, 5] == round(q.black_level + (q.white_level - q.black_level) * q.surround)
    corners = r.corners_px(T)[0]
    assert corners is not None
    inside_border = np.round(corners[0] + [3, 3]).astype(int)
    assert img[inside_border[1], inside_border[0]] == q.black_level
    centre_white = np.round(corners.mean(axis=0) + [20, 0]).astype(int)
    assert img[centre_white[1], centre_white[0]] == q.white_level


def test_edge_is_antialiased_where_the_geometry_puts_it(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    q = ImageQuality.preset("clean")
    T = facing_pose(0.0, 0.0, 1.0)
    refl = r.reflectance(T)
    left = r.corners_px(T)[0][0, 0]  # x of the outer marker's left edge, pixels
    col = math.floor(left + 0.5)  # the pixel the edge runs through
    row = 240
    mean = np.nanmean(refl[row, :, col, :])
    # that pixel is part surround (0.45 in clean quality is applied later), part black:
    # the fraction of samples left of the edge matches the edge position to a sample
    fraction_outside = np.mean(np.isnan(refl[row, :, col, :]) | (refl[row, :, col, :] > 0.5))
    expected = left - (col - 0.5)
    assert fraction_outside == pytest.approx(expected, abs=1 / 3 + 1e-9)
    assert 0.0 <= mean <= 1.0
    _ = q


@dataclass(frozen=True)
class _HalfPlane:
    """Black for x < 0, white for x >= 0, on a 1 m square sheet (1 mm texels)."""

    texture: tuple[NDArray[np.float32], float]
    sheet_half_extent_m: float = 0.5


def _half_plane() -> _HalfPlane:
    texture = np.zeros((1000, 1000), np.float32)
    texture[:, 500:] = 1.0
    return _HalfPlane((texture, 0.001))


def _white_area(
    normal: np.ndarray, offset: float, cols: np.ndarray, rows: np.ndarray
) -> np.ndarray:
    """Exact area of each pixel's square on the side ``normal . p >= offset`` (the square
    clipped by the line, then the shoelace formula)."""
    out = np.zeros(len(cols))
    for k, (x, y) in enumerate(zip(cols, rows, strict=True)):
        square = np.array(
            [[x - 0.5, y - 0.5], [x + 0.5, y - 0.5], [x + 0.5, y + 0.5], [x - 0.5, y + 0.5]]
        )
        kept = []
        for i in range(4):
            p, q = square[i], square[(i + 1) % 4]
            fp, fq = float(normal @ p) - offset, float(normal @ q) - offset
            if fp >= 0:
                kept.append(p)
            if fp * fq < 0:
                kept.append(p + (q - p) * fp / (fp - fq))
        if len(kept) >= 3:
            P = np.array(kept)
            out[k] = 0.5 * abs(P[:, 0] @ np.roll(P[:, 1], 1) - P[:, 1] @ np.roll(P[:, 0], 1))
    return out


@pytest.mark.parametrize("yaw_deg", [0.0, 26.57, 45.0])
def test_edge_pixels_hold_the_exact_area_at_any_angle(yaw_deg: float) -> None:
    """A straight edge through a pinhole camera: each pixel's grey level is the area of its
    square on the white side to 0.03, and along the edge the error averages under 0.006 px.
    A regular 3 x 3 grid of rays alone is off by 0.05-0.17 px along the whole edge at these
    angles, where its steps repeat with the pixels."""
    camera = _pinhole()
    q = ImageQuality(
        black_level=0.0, white_level=255.0, surround=0.0, blur_sigma_px=0.0, noise_sigma=0.0
    )
    T = facing_pose(0.0013, 0.0007, 1.0, math.radians(yaw_deg))
    ends, _ = camera.project(
        (T[:3, :3] @ np.array([[0.0, -0.1, 0.0], [0.0, 0.1, 0.0]]).T).T + T[:3, 3]
    )
    along = (ends[1] - ends[0]) / np.linalg.norm(ends[1] - ends[0])
    normal = np.array([-along[1], along[0]])
    white, _ = camera.project((T[:3, :3] @ np.array([0.05, 0.0, 0.0]) + T[:3, 3])[None])
    if normal @ white[0] < normal @ ends[0]:
        normal = -normal
    offset = float(normal @ ends[0])
    rows, cols = (g.ravel() for g in np.mgrid[140:340, 220:420])
    near = np.abs(np.stack([cols, rows], 1) @ normal - offset) < 1.0
    exact = _white_area(normal, offset, cols[near], rows[near])
    on_edge = (exact > 0.01) & (exact < 0.99)
    lattice = Renderer(camera, _half_plane()).render(T, q)
    grid = Renderer(camera, _half_plane(), edge_samples=0).render(T, q)
    error = lattice[rows[near], cols[near]] / 255.0 - exact
    grid_error = grid[rows[near], cols[near]] / 255.0 - exact
    assert np.max(np.abs(error)) < 0.03
    assert abs(float(np.mean(error[on_edge]))) < 0.006
    assert abs(float(np.mean(grid_error[on_edge]))) > 0.05


def _pinhole() -> CameraModel:
    return CameraModel(
        np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]), np.zeros(5), 640, 480
    )


@pytest.mark.parametrize("phase_px", [0.15, 0.35, 0.5, 0.65, 0.95])
def test_blur_acts_before_the_pixels_integrate(phase_px: float) -> None:
    """Across a straight edge, each pixel holds a blurred step integrated over its square:
    sigma * (psi((x + 1/2 - e) / sigma) - psi((x - 1/2 - e) / sigma)) with
    psi(t) = t Phi(t) + phi(t), to 0.006 of the contrast wherever the edge falls in a pixel.
    Blurring the pixels instead (a sampled kernel on already integrated pixels) is off by
    0.02-0.06."""
    camera, sigma = _pinhole(), 0.6
    renderer = Renderer(camera, _half_plane())
    levels = {"black_level": 0.0, "white_level": 255.0, "surround": 0.0, "noise_sigma": 0.0}
    T = facing_pose(phase_px / 500.0 + 0.0003, 0.0, 1.0)
    ((edge_px, _),), _ = camera.project(T[:3, 3][None])
    cols = np.arange(int(edge_px) - 4, int(edge_px) + 6)

    def psi(t: np.ndarray) -> np.ndarray:
        cdf = 0.5 * (1.0 + np.vectorize(math.erf)(t / math.sqrt(2.0)))
        return np.asarray(t * cdf + np.exp(-0.5 * t * t) / math.sqrt(2.0 * math.pi))

    exact = sigma * (psi((cols + 0.5 - edge_px) / sigma) - psi((cols - 0.5 - edge_px) / sigma))
    blurred = renderer.render(T, ImageQuality(blur_sigma_px=sigma, **levels))
    sharp = renderer.render(T, ImageQuality(blur_sigma_px=0.0, **levels)).astype(np.float32)
    on_pixels = cv2.GaussianBlur(sharp, (0, 0), sigma)
    assert np.max(np.abs(blurred[240, cols] / 255.0 - exact)) < 0.006
    assert np.max(np.abs(on_pixels[240, cols] / 255.0 - exact)) > 0.015


def test_occluder_hides_the_target(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    box = Occluder(np.array([[0, 0], [640, 0], [640, 480], [0, 480]], float), grey=40)
    img = r.render(facing_pose(0, 0, 0.5), ImageQuality.preset("clean"), occluders=(box,))
    assert np.all(img == 40)


def test_fisheye_render_shows_a_large_field_of_view(renderers: dict[str, Renderer]) -> None:
    r = renderers["fpv_wide"]
    # a target 60 degrees off the axis is still imaged
    z = 0.3
    T = facing_pose(z * math.tan(math.radians(60)), 0.0, z)
    corners = r.corners_px(T)[0]
    assert corners is not None
    assert np.all((corners[:, 0] > 0) & (corners[:, 0] < 640))


def test_quality_presets() -> None:
    assert ImageQuality.preset("analog_fpv").jpeg_quality == 70
    with pytest.raises(ValueError, match="unknown image quality"):
        ImageQuality.preset("vhs")


def test_degradations_change_the_image(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    T = facing_pose(0.0, 0.0, 0.5)
    clean = r.render(T, ImageQuality.preset("clean")).astype(float)
    for q in (
        ImageQuality(blur_sigma_px=1.5, noise_sigma=0),
        ImageQuality(motion_blur_px=7, motion_angle_deg=30, noise_sigma=0, blur_sigma_px=0),
        ImageQuality.preset("analog_fpv"),
    ):
        other = r.render(T, q, np.random.default_rng(0)).astype(float)
        assert np.mean(np.abs(other - clean)) > 0.5


def test_box_rendering_equals_whole_frame_blur(renderers: dict[str, Renderer]) -> None:
    """Light levels and blur computed in the sheet's box give the frame a whole-frame blur
    gives (an occluder forces the whole-frame path; one outside the sheet changes nothing
    else)."""
    r = renderers["fpv"]
    q = ImageQuality(noise_sigma=0.0, blur_sigma_px=1.1)
    T = facing_pose(0.03, -0.02, 0.6, 0.4, 0.2, -0.1)
    boxed = r.render(T, q).astype(int)
    far_corner = Occluder(np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]]), grey=90)
    whole = r.render(T, q, occluders=(far_corner,)).astype(int)
    assert np.max(np.abs(boxed[20:, 20:] - whole[20:, 20:])) <= 1


def test_noise_bank_is_white_seeded_and_changes_per_frame(renderers: dict[str, Renderer]) -> None:
    fresh = renderers["webcam"]
    banked = Renderer(fresh.camera, fresh.target, supersample=1, noise_bank=True)
    T = facing_pose(0.0, 0.0, 3.0)  # a small target: the frame is mostly surround
    q = ImageQuality(blur_sigma_px=0.0, noise_sigma=4.0)
    clean = banked.render(T, ImageQuality(blur_sigma_px=0.0, noise_sigma=0.0)).astype(float)
    rng = np.random.default_rng(2)
    a = banked.render(T, q, rng).astype(float) - clean
    b = banked.render(T, q, rng).astype(float) - clean
    again = banked.render(T, q, np.random.default_rng(2)).astype(float) - clean
    np.testing.assert_array_equal(a, again)
    assert abs(float(np.std(a[:100])) - 4.0) < 0.1
    # no correlation between frames, or between neighbouring pixels
    assert abs(float(np.corrcoef(a.ravel(), b.ravel())[0, 1])) < 0.02
    assert abs(float(np.corrcoef(a[:, 1:].ravel(), a[:, :-1].ravel())[0, 1])) < 0.02


def test_harsh_preset_saturates_the_surround_and_bleeds_over_the_sheet(
    renderers: dict[str, Renderer],
) -> None:
    from dataclasses import replace

    r = renderers["webcam"]
    T = facing_pose(0.0, 0.0, 0.6)
    harsh = ImageQuality.preset("harsh")
    still = replace(
        harsh,
        noise_sigma=0.0,
        interference=0.0,
        jpeg_quality=None,
        motion_blur_px=0.0,
        rolling_shutter_px=0.0,
        vignetting=0.0,
    )
    image = r.render(T, still).astype(float)
    # the surround saturates; the sheet's printed white sits far below it
    assert np.mean(image >= 250) > 0.5
    centre = image[240, 320]
    assert centre < 150
    # glare lifts the sheet's pixels next to the bright surround, more near its edge
    no_bloom = r.render(T, replace(still, bloom=0.0)).astype(float)
    lifted = image - no_bloom
    assert lifted.max() > 5
    assert lifted[240, 320] < 1.0


def test_rolling_shutter_shifts_rows_from_the_middle_one(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    T = facing_pose(0.0, 0.0, 0.15, 0.3)  # the sheet's edges cross every row
    clean = ImageQuality.preset("clean")
    from dataclasses import replace

    sheared = r.render(T, replace(clean, rolling_shutter_px=8.0)).astype(float)
    straight = r.render(T, clean).astype(float)
    h = straight.shape[0]

    def edge_x(image: NDArray[np.float64], row: int) -> float:
        """Sub-pixel column of the strongest horizontal step in ``row``."""
        profile = image[row]
        step = np.abs(np.diff(profile))
        return float(np.sum(np.arange(len(step)) * step) / np.sum(step))

    rows = (60, h // 2, h - 61)
    shifts = [edge_x(sheared, y) - edge_x(straight, y) for y in rows]
    expected = [8.0 * (y / (h - 1) - 0.5) for y in rows]
    assert shifts == pytest.approx(expected, abs=0.15)


def test_interference_bands_and_streaks_are_seeded(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    T = facing_pose(0.0, 0.0, 2.0)
    q = ImageQuality(noise_sigma=0.0, blur_sigma_px=0.0, interference=6.0)
    a = r.render(T, q, np.random.default_rng(3))
    b = r.render(T, q, np.random.default_rng(3))
    c = r.render(T, q, np.random.default_rng(4))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    # rows away from the sheet: a band of about 6 levels either way around the surround
    plain = r.render(T, ImageQuality(noise_sigma=0.0, blur_sigma_px=0.0)).astype(float)
    rows = np.median((a.astype(float) - plain)[:, :100], axis=1)
    assert 10.0 <= rows.max() - rows.min() <= 13.0


def test_the_mean_image_is_the_frame_before_the_sensor(renderers: dict[str, Renderer]) -> None:
    """``mean_image`` is what ``render`` rounds where there is no noise, and the mean of its
    noisy frames where there is (the harsh preset's optics: glare, vignetting, motion blur,
    rolling shutter; the surround saturates)."""
    r = renderers["fpv"]
    T = facing_pose(0.02, -0.01, 1.2, 0.3)
    harsh = ImageQuality.preset("harsh")
    quiet = replace(harsh, noise_sigma=0.0, interference=0.0, jpeg_quality=None)
    mean = r.mean_image(T, quiet)
    assert mean.dtype == np.float32
    assert float(mean.max()) == 255.0
    assert np.max(np.abs(r.render(T, quiet).astype(np.float64) - mean)) <= 0.5 + 1e-4
    noisy = replace(quiet, noise_sigma=8.0)
    assert np.array_equal(r.mean_image(T, noisy), mean)
    rng = np.random.default_rng(9)
    frames = np.mean([r.render(T, noisy, rng).astype(np.float64) for _ in range(64)], axis=0)
    unclipped = (mean > 30) & (mean < 225)  # rounding at 0 and 255 biases the mean there
    assert abs(float(np.mean((frames - mean)[unclipped]))) < 0.05
    assert float(np.std((frames - mean)[unclipped])) < 1.2  # 8 / sqrt(64) = 1
