"""What each of the harsh preset's image effects costs the range estimate, one at a time.

    .venv/bin/python benchmarks/bench_harsh_effects.py [--frames 75] [--seed 0] [--camera fpv]
        [--effects all none motion rolling_shutter glare harsh]

The rendered approach of ``perchpose bench`` (240 frames from 150 cm, 30 fps) is rendered
with the ``harsh`` preset's optics and exposure (a target in shadow against a surround 3
times brighter, optical blur 1.3 px, vignetting) but without its noise, interference and
JPEG, so that what is left is a bias, not scatter; then with one effect at a time added:

- ``none``: none of the three below;
- ``motion``: the 5 px motion blur at 30 deg;
- ``rolling_shutter``: the 4 px shear of the last row against the first;
- ``glare``: the light of the surround (3 times brighter than the print) bleeding over the
  sheet's edges (bloom);
- ``all``: all three (the harsh preset without its noise);
- ``harsh``: the harsh preset itself, noise and all.

The first ``--frames`` frames (150 cm down to about 85 cm for 75, where the outer marker is
30-57 px and gets the pattern fit) go through a default ``PerchingEstimator``; each line gives
the range error of its estimates (the error's part along the line of sight, % of the
distance): mean, RMS and largest, and every 5th frame's.
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from perchpose import CameraModel, PerchingEstimator, TargetSpec
from perchpose.app.bench import rendered_frames
from perchpose.sim.render import ImageQuality

QUIET = {"noise_sigma": 0.0, "interference": 0.0, "jpeg_quality": None}
ALONE = {"bloom": 0.0, "motion_blur_px": 0.0, "rolling_shutter_px": 0.0}
EFFECTS: dict[str, dict[str, object]] = {
    "none": {**QUIET, **ALONE},
    "motion": {**QUIET, **ALONE, "motion_blur_px": 5.0},
    "rolling_shutter": {**QUIET, **ALONE, "rolling_shutter_px": 4.0},
    "glare": {**QUIET, **ALONE, "bloom": 0.6},
    "all": dict(QUIET),
    "harsh": {},
}


def range_errors_pct(
    camera: CameraModel, quality: ImageQuality, frames: int, seed: int
) -> list[float]:
    """The range error (% of the distance) of the estimate of each of the approach's first
    ``frames`` frames that has a true pose (NaN where there is no estimate)."""
    target = TargetSpec.paper()
    approach = rendered_frames(camera, target, 240, quality, seed)
    estimator = PerchingEstimator(camera, target)
    errors: list[float] = []
    seen = zip(
        approach.images[:frames], approach.t_s[:frames], approach.truth[:frames], strict=True
    )
    for image, t_s, T in seen:
        estimate = estimator.update(image, t_s)
        if T is None:
            continue
        distance = float(np.linalg.norm(T[:3, 3]))
        if not estimate.valid:
            errors.append(float("nan"))
            continue
        along = T[:3, 3] / distance
        miss = np.asarray(estimate.t_m) - T[:3, 3]
        errors.append(100.0 * float(miss @ along) / distance)
    return errors


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=75)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--camera", default="fpv")
    parser.add_argument("--effects", nargs="+", choices=list(EFFECTS), default=list(EFFECTS))
    args = parser.parse_args()
    camera = CameraModel.preset(args.camera)
    harsh = ImageQuality.preset("harsh")
    print(f"harsh approach, first {args.frames} frames, camera '{args.camera}', seed {args.seed}")
    print("effect            range % of distance: mean    rms    max   (every 5th frame)")
    for name in args.effects:
        quality = dataclasses.replace(harsh, **EFFECTS[name])  # type: ignore[arg-type]
        e = np.array(range_errors_pct(camera, quality, args.frames, args.seed))
        shown = " ".join(f"{x:+.2f}" for x in e[::5])
        print(
            f"{name:16s} {np.nanmean(e):+27.2f} {np.sqrt(np.nanmean(e**2)):6.2f} "
            f"{np.nanmax(np.abs(e)):6.2f}   {shown}",
            flush=True,
        )


if __name__ == "__main__":
    main()
