"""Every compiled kernel built before a live source's first frame.

numba compiles a kernel on its first call with each kind of argument (or loads it from the disk
cache beside its module, which takes a fraction of a second each). Left to the frames, that
happens mid-approach, the first time a path runs: the first frame, the first blurred marker,
the first inner-only frame, the first dropout. ``warm_up`` runs the estimator, both fusions,
over a rendered approach from 1.8 m to 3.5 cm (sharp and harsh frames in pairs, the second
followed by the tracker, a blank one between)
through the user's camera and both lens models (the webcam preset's plumb-bob and the FPV
preset's equidistant), so that each of those paths has its machine code in this process
before the first real frame. ``KERNELS`` in ``perchpose.numeric.jit`` is what it builds.

In one process the work is done once for each camera model and target: a second call returns
at once.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from perchpose.camera import CameraModel
from perchpose.estimator import FUSION_METHODS, PerchingEstimator
from perchpose.geometry import facing_pose
from perchpose.numeric.jit import KERNELS
from perchpose.target import TargetSpec

# metres from the camera: far (outer marker only), both, near, the inner marker alone
DISTANCES_M = (1.8, 0.5, 0.12, 0.035)
QUALITIES = ("harsh",)
_warm: set[tuple[object, ...]] = set()  # what this process has already run through


@dataclass(frozen=True)
class Warmup:
    """What ``warm_up`` did: ``seconds`` it took, ``frames`` it measured, ``kernels`` called
    from Python with machine code after it (of ``total``; the others run inside them),
    ``already``: nothing was left to do."""

    seconds: float
    frames: int
    kernels: int
    total: int
    already: bool

    def describe(self) -> str:
        """One line for the user."""
        if self.already:
            return "compiled kernels already built in this process"
        return (
            f"compiled kernels ready in {self.seconds:.1f} s, before the first frame "
            "(built once and cached on disk: `perchpose warmup` does it ahead of a flight)"
        )


def _key(camera: CameraModel, target: TargetSpec) -> tuple[object, ...]:
    """What decides which kernels a camera and target run: the lens model and its number of
    coefficients, and the target's markers."""
    return (camera.model, len(camera.dist), repr(target.markers))


def warm_up(target: TargetSpec, cameras: Sequence[CameraModel] = ()) -> Warmup:
    """Run every estimator path once through ``cameras`` and the two preset lenses, with
    ``target``; cheap once done (see the module's note)."""
    from perchpose.sim.render import ImageQuality, Renderer

    start = time.monotonic()
    todo: list[CameraModel] = []
    for camera in (*cameras, CameraModel.preset("webcam"), CameraModel.preset("fpv")):
        key = _key(camera, target)
        if key not in _warm:
            _warm.add(key)
            todo.append(camera)
    frames = 0
    rng = np.random.default_rng(0)
    for camera in todo:
        renderer = Renderer(camera, target)
        images = [np.full((camera.height_px, camera.width_px), 128, np.uint8)]
        for quality in QUALITIES:
            for k, z_m in enumerate(DISTANCES_M):
                for step in (1.0, 0.98):  # a frame, then one the tracker follows it into
                    pose = facing_pose(0.01 * (k % 3 - 1), 0.005, z_m * step, 0.3)
                    images.append(renderer.render(pose, ImageQuality.preset(quality), rng))
            images.append(images[0])  # a dropout: the filters coast
        for fusion in FUSION_METHODS:
            estimator = PerchingEstimator(camera, target, fusion=fusion)
            for i, image in enumerate(images):
                estimator.update(image, i / 30.0)
                frames += 1
    built = sum(1 for kernel in KERNELS if kernel.signatures)
    return Warmup(time.monotonic() - start, frames, built, len(KERNELS), not todo)
