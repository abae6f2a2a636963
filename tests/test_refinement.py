"""Corner fits from a start (``perchpose.refinement``): what the flags ask of a start."""

import numpy as np
import pytest

from perchpose.detection import MarkerDetector
from perchpose.geometry import facing_pose
from perchpose.refinement import CornerFitter
from perchpose.sim.render import ImageQuality, Renderer


def test_a_fit_that_requires_edges_runs_no_pattern_fit_without_them(
    renderers: dict[str, Renderer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A 22 px marker gets the pattern fit from its quad where its edges cannot be fitted,
    unless the call requires edges: then there is no answer, and no pattern fit ran."""
    r = renderers["fpv"]
    T = facing_pose(0.01, 0.0, r.camera.focal_px * 0.15 / 22.0, 0.4)
    image = r.render(T, ImageQuality(blur_sigma_px=1.1, noise_sigma=2.0), np.random.default_rng(5))
    (det,) = [
        d for d in MarkerDetector(r.camera, r.target, "subpix").detect(image) if d.marker_index == 0
    ]
    fitter = CornerFitter(r.camera, r.target)
    assert fitter.fit_corners(image, det) is not None
    monkeypatch.setattr(fitter, "fit_edges", lambda grey, d: None)
    from_pattern = fitter.fit_corners(image, det)
    assert from_pattern is not None
    assert fitter.pattern_s > 0
    truth = r.corners_px(T)[0]
    assert truth is not None
    assert np.max(np.abs(from_pattern.corners_px - truth)) < 0.2
    assert fitter.fit_corners(image, det, require_edges=True) is None
    assert fitter.pattern_s == 0
