import math

import numpy as np
import pytest

from perchpose.fusion import (
    STAGE_BOTH,
    STAGE_INNER,
    STAGE_NONE,
    STAGE_OUTER,
    FusionSigmas,
    fuse_paper,
    stage_of,
)


def test_stages() -> None:
    assert stage_of(set()) == STAGE_NONE
    assert stage_of({0}) == STAGE_OUTER
    assert stage_of({0, 1}) == STAGE_BOTH
    assert stage_of({1}) == STAGE_INNER
    assert stage_of({1, 2}) == STAGE_INNER


def test_stage_two_weights_each_component_by_its_sigma() -> None:
    outer = np.array([0.0, 0.10, 0.20, 1.00])
    inner = np.array([0.0, 0.20, 0.40, 0.80])
    fused, stage = fuse_paper({0: outer, 1: inner}, FusionSigmas())
    assert stage == STAGE_BOTH
    np.testing.assert_allclose(
        fused[1:],
        [0.275 * 0.10 + 0.725 * 0.20, 0.306 * 0.20 + 0.694 * 0.40, 0.728 * 1.00 + 0.272 * 0.80],
    )


def test_stage_two_yaw_is_averaged_on_the_circle() -> None:
    outer = np.array([math.radians(179.0), 0, 0, 1])
    inner = np.array([math.radians(-179.0), 0, 0, 1])
    fused, _ = fuse_paper({0: outer, 1: inner}, FusionSigmas(yaw=0.5))
    assert abs(math.degrees(abs(fused[0])) - 180.0) < 1e-9


def test_single_marker_stages_pass_the_pose_through() -> None:
    p = np.array([0.3, 0.01, 0.02, 0.5])
    assert fuse_paper({0: p}, FusionSigmas())[0] == pytest.approx(p)
    assert fuse_paper({1: p}, FusionSigmas())[0] == pytest.approx(p)
    fused, stage = fuse_paper({}, FusionSigmas())
    assert stage == STAGE_NONE
    assert np.isnan(fused).all()


def test_sigma_range_is_checked() -> None:
    with pytest.raises(ValueError, match="sigma_z"):
        FusionSigmas(z=1.2)
