"""Reading a marker's cells back through fitted corners: the check that keeps a corner fit made
without a quad search."""

import numpy as np
import pytest

from perchpose import TargetSpec
from perchpose.detection.verification import CellPattern, read_cells
from perchpose.geometry import facing_pose
from perchpose.sim.render import ImageQuality, Renderer


def test_cells_covered_by_a_nested_marker_are_left_out(paper_target: TargetSpec) -> None:
    """The paper's outer marker (6 x 6 cells with its border) carries the inner marker on its
    four central cells: those are mixed in print and left out; the inner marker's 7 x 7 are
    all used. Each used cell's shade is the marker's own bit there."""
    outer, inner = CellPattern.of(paper_target, 0), CellPattern.of(paper_target, 1)
    assert (outer.n_cells, len(outer.uv)) == (6, 32)
    assert (inner.n_cells, len(inner.uv)) == (7, 49)
    cells = paper_target.markers[0].cells
    rows, cols = outer.uv[:, 1].astype(int), outer.uv[:, 0].astype(int)
    assert np.array_equal(cells[rows, cols] == 1, outer.white)
    assert not np.any((rows >= 2) & (rows <= 3) & (cols >= 2) & (cols <= 3))


@pytest.mark.parametrize("quality", ["default", "harsh"])
def test_the_true_corners_read_as_printed_and_wrong_ones_do_not(
    renderers: dict[str, Renderer], quality: str
) -> None:
    """On the marker's true corners its cells read as printed (harsh images too); the same
    corners a quarter turn round, shifted by a cell, or given to the other marker do not."""
    r = renderers["fpv"]
    T = facing_pose(0.02, -0.01, 0.3, 0.3)
    image = r.render(T, ImageQuality.preset(quality), np.random.default_rng(3))
    true = r.corners_px(T)
    patterns = [CellPattern.of(r.target, i) for i in range(2)]
    for i in range(2):
        corners = true[i]
        assert corners is not None
        reading = read_cells(image, corners, r.camera, patterns[i])
        assert reading is not None
        assert reading.matches(), reading
        turned = read_cells(image, np.roll(corners, 1, axis=0), r.camera, patterns[i])
        assert turned is not None
        assert not turned.matches()
        cell = (corners[1] - corners[0]) / patterns[i].n_cells
        shifted = read_cells(image, corners + cell, r.camera, patterns[i])
        assert shifted is not None
        assert not shifted.matches()
    other = read_cells(image, true[0], r.camera, patterns[1])
    assert other is not None
    assert not other.matches()


def test_corners_outside_the_image_give_no_reading(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    image = np.full((r.camera.size[1], r.camera.size[0]), 128, np.uint8)
    corners = np.array([[-50.0, -50.0], [10.0, -50.0], [10.0, 10.0], [-50.0, 10.0]])
    assert read_cells(image, corners, r.camera, CellPattern.of(r.target, 0)) is None
