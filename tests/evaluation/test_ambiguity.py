import numpy as np

from perchpose import CameraModel, PerchingEstimator, TargetSpec
from perchpose.evaluation import experiments as ex
from perchpose.sim.render import ImageQuality, Renderer
from perchpose.sim.scenarios import approach


def test_no_marker_takes_the_wrong_ippe_branch_on_an_approach() -> None:
    """The evaluation's quick approach (analog images, fpv lens): the small inner marker seen
    head-on once took the IPPE solution 13 deg off while the other was 4 deg off; the outer
    marker's rotation in the same frame now settles it."""
    camera = CameraModel.preset("fpv")
    target = TargetSpec.paper()
    renderer = Renderer(camera, target)
    scenario = approach(duration_s=2.0, dropouts=(), quality=ImageQuality.preset("analog_fpv"))
    frames = ex.render_scenario(renderer, scenario, np.random.default_rng(5), lambda _n: None)
    detections = ex.detect_all(renderer, frames)
    run = ex.run_sequence(PerchingEstimator(camera, target), scenario, detections)
    assert run.valid.sum() > 50
    assert run.flips == 0
