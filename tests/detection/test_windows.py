"""Where to search (``perchpose.detection.windows``)."""

import numpy as np

from perchpose.detection.rectification import Rectification
from perchpose.detection.windows import rectified_windows
from perchpose.geometry import facing_pose
from perchpose.sim.render import Renderer
from perchpose.values import MarkerDetection


def test_the_pinhole_view_is_searched_for_a_missing_marker_only_where_it_is_in_view(
    renderers: dict[str, Renderer],
) -> None:
    """Around where the plane through a found marker puts a missing one: a window of the
    rectified view where that lies in the image (3 px from its border, as OpenCV keeps its
    quads), none where it crosses the border (near contact the outer marker leaves the view,
    and its window would be most of the view)."""
    r = renderers["fpv"]
    rectification = Rectification.of(r.camera)
    for x_m, in_view in ((0.0, True), (0.13, False)):
        outer, inner = r.corners_px(facing_pose(x_m, 0.0, 0.1, 0.0))
        assert outer is not None
        assert inner is not None
        assert r.camera.in_image(outer, 3.0) == in_view
        assert r.camera.in_image(inner, 3.0)
        found = {1: MarkerDetection(1, inner, "raw")}
        windows = rectified_windows(rectification, r.target, found, np.inf, 3.0)
        assert len(windows) == (1 if in_view else 0)
        if in_view:
            x0, y0, x1, y1 = windows[0]
            corners = rectification.to_rectified(outer)
            assert np.all(corners >= [x0, y0])
            assert np.all(corners <= [x1, y1])
