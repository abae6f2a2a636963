import numpy as np

from perchpose import CameraModel
from perchpose.detection.rectification import Rectification


def test_pixels_go_to_the_view_and_back() -> None:
    camera = CameraModel.preset("fpv")
    rect = Rectification.of(camera)
    corners = np.array([[100.0, 80.0], [540.0, 90.0], [520.0, 400.0], [120.0, 380.0]])
    back, ok = rect.to_original(rect.to_rectified(corners))
    assert ok
    np.testing.assert_allclose(back, corners, atol=1e-6)
    h, w = rect.size
    assert (w, h) == (960, 720)
    # the view is a pinhole camera: points on a line of the view are rays in one plane, which
    # the lens bends in the image but the normalised plane shows straight again
    line = np.array([[200.0, 150.0], [480.0, 300.0], [760.0, 450.0]])
    image_px, ok = rect.to_original(line)
    assert ok
    xy = camera.normalize(image_px)
    cross = (xy[1, 0] - xy[0, 0]) * (xy[2, 1] - xy[0, 1]) - (xy[1, 1] - xy[0, 1]) * (
        xy[2, 0] - xy[0, 0]
    )
    assert abs(cross) < 1e-9


def test_one_camera_builds_its_tables_once() -> None:
    first = Rectification.of(CameraModel.preset("fpv"))
    again = Rectification.of(CameraModel.preset("fpv"))  # an equal camera, another object
    assert again is first
    assert Rectification.of(CameraModel.preset("fpv_wide")) is not first
