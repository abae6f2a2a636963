"""The package face: public names load on first use, and the vehicle side imports light."""

import subprocess
import sys

import pytest

import perchpose

_HEAVY = ("cv2", "numba", "scipy", "perchpose.estimator", "perchpose.detection")


def _loaded_after(statement: str) -> list[str]:
    probe = f"import sys\n{statement}\nprint(' '.join(m for m in {_HEAVY!r} if m in sys.modules))"
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True, timeout=120
    )
    return done.stdout.split()


def test_public_names_resolve_to_their_modules() -> None:
    from perchpose.estimator import PerchingEstimator
    from perchpose.values import Estimate

    assert perchpose.PerchingEstimator is PerchingEstimator
    assert perchpose.Estimate is Estimate
    assert set(perchpose.__all__) <= set(dir(perchpose))
    with pytest.raises(AttributeError, match="no attribute 'Detector'"):
        _ = perchpose.Detector  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    "module",
    [
        "perchpose",
        "perchpose.control",
        "perchpose.io.mavlink_link",
        "perchpose.io.mavlink_pilot",
        "perchpose.io.crazyflie",
    ],
)
def test_the_controller_and_the_links_import_without_opencv_or_the_pipeline(
    module: str,
) -> None:
    assert _loaded_after(f"import {module}") == []


def test_the_estimator_still_comes_with_the_package_face() -> None:
    assert "perchpose.estimator" in _loaded_after("from perchpose import PerchingEstimator")
