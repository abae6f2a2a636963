"""The compiled kernels (``perchpose.numeric.jit``) on a plain install."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

_SCRIPT = """
import sys
sys.modules["scipy"] = None  # as on a plain install (scipy comes only with the dev extras)
import numpy as np
from perchpose import CameraModel, TargetSpec
from perchpose.estimator import PerchingEstimator
from perchpose.geometry import facing_pose
from perchpose.sim.render import ImageQuality, Renderer
r = Renderer(CameraModel.preset("fpv"), TargetSpec.paper())
est = PerchingEstimator(r.camera, r.target)
for k, z in enumerate((0.9, 0.89)):
    T = facing_pose(0.01, 0.0, z, 0.2)
    image = r.render(T, ImageQuality.preset("harsh"), np.random.default_rng(k))
    estimate = est.update(image, k / 30)
assert estimate.valid
"""


@pytest.mark.slow
def test_the_kernels_compile_and_run_without_scipy(tmp_path: Path) -> None:
    """numba's matrix products and linear algebra call scipy's BLAS, which ``pip install .``
    does not bring: every kernel a frame runs through (the fisheye lens, the edge fit, the
    pattern fit of a blurred marker, the cell reading) compiles afresh and runs without it.
    (Without LLVM's optimisations, ``NUMBA_OPT=0``: whether scipy is needed is settled before
    them, and they take a third of the compile time.)"""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path), NUMBA_OPT="0")
    done = subprocess.run(
        [sys.executable, "-c", _SCRIPT],
        check=False,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
