"""Does the estimate's covariance match the spread of its errors? On a rendered approach.

    .venv/bin/python benchmarks/bench_covariance.py [--camera fpv] [--quality default]
        [--demo]

Renders the approach (3 s from 90 cm with a 0.4 s dropout at 1 s, or with ``--demo`` the
demo's 8 s from 150 cm; seed 1), runs the estimator on it with and without the filter, and
prints per component (x, y, z, yaw) the standard deviation of the errors over their reported
standard deviations, over the frames with a measured (not predicted) estimate: 1 is a
covariance that matches the spread, under 1 a conservative one.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from perchpose import CameraModel, PerchingEstimator, TargetSpec
from perchpose.geometry import yaw_rad
from perchpose.sim.render import ImageQuality, Renderer
from perchpose.sim.scenarios import approach


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--camera", default="fpv")
    parser.add_argument("--quality", default="default")
    parser.add_argument("--demo", action="store_true")
    args = parser.parse_args()
    camera = CameraModel.preset(args.camera)
    quality = ImageQuality.preset(args.quality)
    scenario = (
        approach(quality=quality)
        if args.demo
        else approach(duration_s=3.0, start_z_m=0.9, dropouts=((1.0, 0.4),), quality=quality)
    )
    target = TargetSpec.paper()
    renderer = Renderer(camera, target)
    rng = np.random.default_rng(1)
    images = [
        None if scenario.dropout[i] else renderer.render(T, quality, rng)
        for i, T in enumerate(scenario.poses)
    ]
    for use_filter in (True, False):
        estimator = PerchingEstimator(camera, target, use_filter=use_filter)
        normalised = []
        for i, T in enumerate(scenario.poses):
            image = images[i]
            if image is None:
                continue
            e = estimator.update(image, float(scenario.t_s[i]))
            if not e.valid or e.predicted:
                continue
            yaw_error = math.remainder(e.yaw_rad - yaw_rad(T[:3, :3]), 2 * math.pi)
            d = np.array([*(e.t_m - T[:3, 3]), yaw_error])
            normalised.append(d / np.array(e.std))
        spread = np.array(normalised).std(axis=0)
        print(
            f"{args.camera}, {args.quality}, {'demo' if args.demo else '3 s'} approach, "
            f"{'filtered' if use_filter else 'without the filter'}: {len(normalised)} frames, "
            "spread x, y, z, yaw " + ", ".join(f"{v:.2f}" for v in spread)
        )


if __name__ == "__main__":
    main()
