"""Corner refinement from the fitted border edges, against the renderer's true corners."""

import math

import numpy as np
import pytest

from perchpose.corners import refine_corners_edges
from perchpose.detection import MarkerDetector
from perchpose.geometry import facing_pose
from perchpose.sim.render import ImageQuality, Renderer


def corner_errors(
    renderer: Renderer, quality: ImageQuality, seed: int, distances_m: np.ndarray | None = None
) -> dict[str, list[tuple[float, float, float]]]:
    """Per detected marker: (side px, RMS corner error px, mean radial error px) for the
    cornerSubPix corners and for the edge fit, over random poses (default: 18 from 1.8 m to
    8 cm)."""
    rng = np.random.default_rng(seed)
    detector = MarkerDetector(renderer.camera, renderer.target, "subpix")
    out: dict[str, list[tuple[float, float, float]]] = {"subpix": [], "edges": []}
    zs = np.geomspace(1.8, 0.08, 18) if distances_m is None else distances_m
    for z in zs:
        x, y = rng.uniform(-0.1, 0.1, 2) * z
        T = facing_pose(x, y, z, rng.uniform(-3, 3), rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3))
        image = renderer.render(T, quality, rng)
        truth = renderer.corners_px(T)
        for det in detector.detect(image):
            true = truth[det.marker_index]
            assert true is not None
            cells = int(renderer.target.markers[det.marker_index].cells.shape[0])
            fitted = refine_corners_edges(image, det.corners_px, renderer.camera, cells)
            outward = true - true.mean(axis=0)
            outward /= np.linalg.norm(outward, axis=1, keepdims=True)
            for name, corners in (("subpix", det.corners_px), ("edges", fitted)):
                if corners is None:
                    continue
                err = corners - true
                rms = math.sqrt(float(np.mean(np.sum(err * err, axis=1))))
                out[name].append((det.side_px, rms, float(np.mean(np.sum(err * outward, axis=1)))))
    return out


def summary(rows: list[tuple[float, float, float]], lo: float, hi: float) -> tuple[float, float]:
    sel = [r for r in rows if lo <= r[0] < hi]
    assert len(sel) >= 5
    return math.sqrt(float(np.mean([r[1] ** 2 for r in sel]))), float(np.mean([r[2] for r in sel]))


@pytest.mark.parametrize("camera_name", ["webcam", "fpv_wide"])
def test_edge_fit_is_unbiased_and_precise(renderers: dict[str, Renderer], camera_name: str) -> None:
    rows = corner_errors(renderers[camera_name], ImageQuality(), seed=11)
    rms, radial = summary(rows["edges"], 21.0, 400.0)
    assert rms <= 0.06
    assert abs(radial) <= 0.03
    # the same markers through cornerSubPix: pulled inwards by a tenth of a pixel or more
    rms_subpix, radial_subpix = summary(rows["subpix"], 21.0, 400.0)
    assert radial_subpix < -0.08
    assert rms < 0.4 * rms_subpix
    assert len(rows["edges"]) >= 0.9 * len(rows["subpix"])
    # the smallest markers the detector finds (the inner marker at 15-21 px): noisier
    r = renderers[camera_name]
    f = r.camera.focal_px
    small = corner_errors(
        r, ImageQuality(), seed=13, distances_m=np.linspace(f * 0.025 / 20, f * 0.025 / 15.5, 10)
    )
    rms_small, _ = summary(small["edges"], 14.0, 21.0)
    assert rms_small <= 0.12


def test_blurred_noisy_frames(renderers: dict[str, Renderer]) -> None:
    rows = corner_errors(
        renderers["fpv"], ImageQuality(blur_sigma_px=1.2, noise_sigma=3.0), seed=12
    )
    rms, radial = summary(rows["edges"], 40.0, 400.0)
    assert rms <= 0.08
    assert abs(radial) <= 0.04
    rms_subpix, _ = summary(rows["subpix"], 40.0, 400.0)
    assert rms < 0.5 * rms_subpix


def test_no_edge_no_corners(renderers: dict[str, Renderer]) -> None:
    camera = renderers["webcam"].camera
    flat = np.full((camera.height_px, camera.width_px), 128, np.uint8)
    square = np.array([[200.0, 150.0], [300.0, 150.0], [300.0, 250.0], [200.0, 250.0]])
    assert refine_corners_edges(flat, square, camera, 6) is None


def test_a_start_off_by_a_fraction_of_a_pixel_converges(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    T = facing_pose(0.0, 0.0, 0.6, 0.2)
    image = r.render(T)
    true = r.corners_px(T)[0]
    assert true is not None
    fitted = refine_corners_edges(image, true + 0.3, r.camera, 6)
    assert fitted is not None
    assert np.max(np.abs(fitted - true)) < 0.1
    # a start half a cell off is beyond the fit's reach: refused rather than moved that far
    cell = float(np.linalg.norm(true[1] - true[0])) / 6
    far = refine_corners_edges(image, true + [0.5 * cell, 0.5 * cell], r.camera, 6)
    assert far is None or np.max(np.abs(far - true)) < 0.1
