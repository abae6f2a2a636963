"""Time from a process's start to its first pose (``perchpose bench --startup``), as a live
``track`` starts: import, load the camera and target, build the compiled kernels (``warm_up``),
then the first frame.

``cold``: the kernels' disk cache empty (a fresh install, another Python or numba: each kernel
is compiled); warm: loaded from the cache ``perchpose warmup`` fills. The process is a fresh
interpreter, timed from its launch by this one.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.errors import PerchposeError
from perchpose.target import TargetSpec

_CHILD = """
import json, sys
import cv2
from perchpose import CameraModel, PerchingEstimator, TargetSpec
from perchpose.warmup import warm_up
camera = CameraModel.load(sys.argv[1])
target = TargetSpec.load(sys.argv[2])
image = cv2.imread(sys.argv[3], cv2.IMREAD_UNCHANGED)
warm = warm_up(target, [camera])
estimate = PerchingEstimator.configured(camera, target).update(image, 0.0)
print(json.dumps({"warm_up_s": warm.seconds, "valid": bool(estimate.valid)}), flush=True)
"""


@dataclass(frozen=True)
class StartupTime:
    """``first_pose_s`` from the launch to the first frame's answer (``valid``: a pose), of
    which ``warm_up_s`` building or loading the kernels."""

    cold: bool
    first_pose_s: float
    warm_up_s: float
    valid: bool

    def to_json(self) -> dict[str, float | bool]:
        return {
            "first_pose_s": self.first_pose_s,
            "warm_up_s": self.warm_up_s,
            "valid": self.valid,
        }

    def describe(self) -> str:
        kernels = "compiled" if self.cold else "loaded from the disk cache"
        pose = "" if self.valid else " (no pose in that frame)"
        return (
            f"{'cold' if self.cold else 'warm'}: {self.first_pose_s:.1f} s to the first "
            f"pose{pose}, {self.warm_up_s:.1f} s of it with the kernels {kernels}"
        )


def measure_startup(
    camera: CameraModel, target: TargetSpec, image: NDArray[np.uint8], cold: bool
) -> StartupTime:
    """Launch a fresh process that starts as a live ``track`` does and answers ``image``;
    ``cold`` gives it an empty kernel cache."""
    with tempfile.TemporaryDirectory(prefix="perchpose-startup-") as folder:
        where = Path(folder)
        camera.save(where / "camera.yaml")
        target.save(where / "target.yaml")
        if not cv2.imwrite(str(where / "frame.png"), image):
            raise PerchposeError("--startup: cannot write the first frame for the timed process")
        env = dict(os.environ)
        if cold:
            (where / "kernels").mkdir()
            env["NUMBA_CACHE_DIR"] = str(where / "kernels")
        args = [str(where / name) for name in ("camera.yaml", "target.yaml", "frame.png")]
        t0 = time.monotonic()
        child = subprocess.Popen(
            [sys.executable, "-c", _CHILD, *args],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        line = child.stdout.readline() if child.stdout is not None else ""
        first_pose_s = time.monotonic() - t0  # the answer printed, not the exit
        _, stderr = child.communicate()
    if child.returncode != 0 or not line:
        last = (stderr.strip().splitlines() or ["no message"])[-1]
        raise PerchposeError(f"--startup: the timed process failed ({last})")
    answer = json.loads(line)
    return StartupTime(cold, first_pose_s, float(answer["warm_up_s"]), bool(answer["valid"]))
