"""No compile after the warm-up: every kernel a track runs is built before its first frame."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from perchpose.cli import main

_SCRIPT = """
import json, sys
from pathlib import Path
import cv2
import numpy as np
from perchpose import CameraModel, PerchingEstimator, TargetSpec
from perchpose.numeric.jit import KERNELS
from perchpose.warmup import warm_up

target = TargetSpec.paper()
done = warm_up(target)
before = {id(k): len(k.overloads) for k in KERNELS}
again = warm_up(target)
measured = 0
for folder in sys.argv[1:]:
    camera = CameraModel.load(Path(folder) / "camera.yaml")
    for budget_ms in (None, 10.0):
        estimator = PerchingEstimator.configured(camera, target, budget_ms=budget_ms)
        for i, path in enumerate(sorted(Path(folder).glob("frame_*.png"))):
            image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if i % 3 == 1:  # a ROS message's buffer is read-only
                image.setflags(write=False)
            elif i % 3 == 2:  # a strided view of the same pixels
                image = np.repeat(image, 2, axis=1)[:, ::2]
            measured += estimator.update(image, i / 30.0).valid
grown = [k.py_func.__qualname__ for k in KERNELS if len(k.overloads) != before[id(k)]]
print(json.dumps({"grown": grown, "measured": measured, "again": again.already,
                  "first": done.already, "frames": done.frames}))
"""


def test_no_kernel_is_built_after_the_warm_up(
    approach_webcam_dir: Path, approach_fpv_dir: Path
) -> None:
    """In a fresh process: after ``warm_up``, tracking the rendered approaches through both
    lens models (far, near, the inner marker alone, a dropout), with and without a budget,
    from writable, read-only and strided frames alike, builds or loads no kernel's machine
    code; a second warm-up has nothing to do."""
    done = subprocess.run(
        [sys.executable, "-c", _SCRIPT, str(approach_webcam_dir), str(approach_fpv_dir)],
        check=False,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["grown"] == []
    assert result["measured"] > 250  # most of 2 x 2 x 90 frames (a dropout in each)
    assert not result["first"]
    assert result["again"]
    assert result["frames"] > 0


def test_warmup_command(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["warmup", "--camera", "preset:fpv_wide"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1
    assert out[0].startswith(("compiled kernels ready in", "compiled kernels already built"))
