"""How far single harsh frames at 150 cm are from what their pixels allow.

    .venv/bin/python benchmarks/bench_harsh_bound.py [--frame 0] [--draws 30] [--camera fpv]

Takes one pose of the rendered approach of ``perchpose bench`` (frame 0: 150 cm, the outer
marker about 30 px, where the pattern fit runs) and, for the harsh preset with some of its
effects left out, compares two things:

- the Cramer-Rao bound of the range (the distance along the line of sight) from the pixels
  the pattern fit reads (the outer marker and 0.7 of a cell around it) under white noise of
  the preset's 8 grey levels: from the derivatives by the pose of ``Renderer.mean_image`` (the
  frame before the sensor's noise; central differences of 1 mm and 1 mrad). Interference and
  JPEG are not white noise: where they are on, the bound is a lower bound that no estimator
  reaches;
- the range error of a fresh ``PerchingEstimator`` on ``--draws`` frames of that pose, each
  with its own draw of the noise (and interference): mean, spread and largest.

The spread over the bound says how much of what the pixels hold the estimate leaves unused.
"""

from __future__ import annotations

import argparse
import dataclasses
import math

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose import CameraModel, PerchingEstimator, TargetSpec
from perchpose.sim.render import ImageQuality, Renderer
from perchpose.sim.scenarios import approach

Array = NDArray[np.float64]

STILL = {"motion_blur_px": 0.0, "rolling_shutter_px": 0.0, "bloom": 0.0}
VARIANTS: dict[str, dict[str, object]] = {
    "noise alone": {**STILL, "interference": 0.0, "jpeg_quality": None},
    "+ motion, shutter, glare": {"interference": 0.0, "jpeg_quality": None},
    "+ JPEG 40": {"interference": 0.0},
    "harsh (+ interference)": {},
}
STEP_M, STEP_RAD = 1e-3, 1e-3
OUT_CELLS = 0.7


def moved(T: Array, k: int, step: float) -> Array:
    """``T`` moved by ``step`` along translation k (0-2, metres) or rotation k - 3 (radians,
    about the camera's axes)."""
    out = T.copy()
    if k < 3:
        out[k, 3] += step
    else:
        axis = np.zeros(3)
        axis[k - 3] = step
        out[:3, :3] = cv2.Rodrigues(axis)[0] @ T[:3, :3]
    return out


def fitted_region(renderer: Renderer[TargetSpec], T: Array) -> NDArray[np.bool_]:
    """The pixels within ``OUT_CELLS`` of the outer marker (what its pattern fit reads)."""
    marker = renderer.target.markers[0]
    corners = marker.corners_target_m
    centre = corners.mean(axis=0)
    grow = 1.0 + 2.0 * OUT_CELLS / marker.cells.shape[0]
    outline = centre + (corners - centre) * grow
    px, _ = renderer.camera.project((T[:3, :3] @ outline.T).T + T[:3, 3])
    mask = np.zeros((renderer.camera.height_px, renderer.camera.width_px), np.uint8)
    cv2.fillPoly(mask, [np.round(px * 16).astype(np.int32)], 1, shift=4)
    return mask > 0


def range_bound_pct(
    renderer: Renderer[TargetSpec], T: Array, quality: ImageQuality, sigma: float
) -> float:
    """The Cramer-Rao bound of the range (% of the distance) from the fitted region's pixels
    under white noise ``sigma``, the pose's 6 parameters unknown."""
    region = fitted_region(renderer, T)
    columns = []
    for k in range(6):
        step = STEP_M if k < 3 else STEP_RAD
        ahead = renderer.mean_image(moved(T, k, step), quality).astype(np.float64)
        behind = renderer.mean_image(moved(T, k, -step), quality).astype(np.float64)
        columns.append(((ahead - behind) / (2.0 * step))[region])
    J = np.stack(columns, axis=1)
    covariance = np.linalg.inv(J.T @ J / sigma**2)
    distance = float(np.linalg.norm(T[:3, 3]))
    along = T[:3, 3] / distance
    return 100.0 * math.sqrt(float(along @ covariance[:3, :3] @ along)) / distance


def range_errors_pct(
    renderer: Renderer[TargetSpec], T: Array, quality: ImageQuality, draws: int
) -> Array:
    """A fresh estimator's range error (% of the distance) on ``draws`` noisy frames of
    ``T`` (NaN where it gives no pose)."""
    rng = np.random.default_rng(0)
    distance = float(np.linalg.norm(T[:3, 3]))
    along = T[:3, 3] / distance
    errors = []
    for _ in range(draws):
        image = renderer.render(T, quality, rng)
        estimate = PerchingEstimator(renderer.camera, renderer.target).update(image, 0.0)
        if not estimate.valid:
            errors.append(math.nan)
            continue
        miss = np.asarray(estimate.t_m) - T[:3, 3]
        errors.append(100.0 * float(miss @ along) / distance)
    return np.array(errors)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frame", type=int, default=0)
    parser.add_argument("--draws", type=int, default=30)
    parser.add_argument("--camera", default="fpv")
    args = parser.parse_args()
    renderer = Renderer(CameraModel.preset(args.camera), TargetSpec.paper())
    harsh = ImageQuality.preset("harsh")
    T = approach(duration_s=8.0, quality=harsh).poses[args.frame]
    distance = float(np.linalg.norm(T[:3, 3]))
    print(
        f"harsh approach frame {args.frame} ({100 * distance:.0f} cm), camera "
        f"'{args.camera}', {args.draws} noise draws each"
    )
    print("images                     bound %   range error %: mean  spread  largest  spread/bound")
    for name, change in VARIANTS.items():
        quality = dataclasses.replace(harsh, **change)  # type: ignore[arg-type]
        bound = range_bound_pct(renderer, T, quality, harsh.noise_sigma)
        e = range_errors_pct(renderer, T, quality, args.draws)
        spread = float(np.nanstd(e))
        print(
            f"{name:26s} {bound:7.3f} {np.nanmean(e):+20.2f} {spread:7.2f} "
            f"{np.nanmax(np.abs(e)):8.2f} {spread / bound:12.1f}"
            + (f"   ({int(np.isnan(e).sum())} without a pose)" if np.isnan(e).any() else ""),
            flush=True,
        )


if __name__ == "__main__":
    main()
