import math

import cv2
import numpy as np
import pytest

from perchpose import CameraModel, MarkerSpec, TargetSpec
from perchpose.detection.detector import (
    CHECK_SCALE,
    DIRECT_SIDE_PX,
    MarkerDetector,
    target_dictionaries,
)
from perchpose.detection.finding import QuadSearch
from perchpose.detection.fitting import UNFITTED_SD_CELLS, Fitting
from perchpose.geometry import facing_pose
from perchpose.sim.render import Renderer
from perchpose.target import aruco_dictionary


@pytest.mark.parametrize(
    ("camera_name", "z_m", "expected"),
    [("webcam", 0.5, {0, 1}), ("webcam", 0.15, {1}), ("webcam", 2.0, {0}), ("fpv", 0.3, {0, 1})],
)
def test_finds_the_visible_markers_with_subpixel_corners(
    renderers: dict[str, Renderer], camera_name: str, z_m: float, expected: set[int]
) -> None:
    r = renderers[camera_name]
    T = facing_pose(0.01, -0.01, z_m, math.radians(20))
    detections = MarkerDetector(r.camera, r.target).detect(r.render(T)).markers
    assert {d.marker_index for d in detections} == expected
    truth = r.corners_px(T)
    for d in detections:
        corners = truth[d.marker_index]
        assert corners is not None
        assert np.max(np.linalg.norm(d.corners_px - corners, axis=1)) < 0.6


def test_large_marker_on_a_fisheye_comes_from_the_rectified_pass(
    renderers: dict[str, Renderer],
) -> None:
    r = renderers["fpv_wide"]
    T = facing_pose(0.06, -0.05, 0.18, 0.0)
    detector = MarkerDetector(r.camera, r.target)
    assert detector.rectify
    image = r.render(T)
    by_index = {d.marker_index: d for d in detector.detect(image).markers}
    outer = by_index[0]
    assert outer.image_pass == "rectified"
    truth = r.corners_px(T)[0]
    assert truth is not None
    assert np.max(np.linalg.norm(outer.corners_px - truth, axis=1)) < 0.5
    # the plain pass on the curved image returns a quad pulled several pixels inwards
    corners, ids, _, dict_indices = detector.quads.search.detector.detectMarkersMultiDict(image)
    raw = [
        c
        for c, i, d in zip(corners, ids.reshape(-1), dict_indices.reshape(-1), strict=True)
        if detector.quads.dict_marker_index[d][i] == 0
    ]
    if raw:
        assert np.max(np.linalg.norm(raw[0].reshape(4, 2) - truth, axis=1)) > 2.0


def test_a_large_marker_the_frame_shows_is_fitted_from_its_own_quad_on_a_fisheye(
    renderers: dict[str, Renderer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Through the fisheye a 120 px marker's edges are curved, but its quad from the frame
    itself is close enough for the edge fit through the lens model: no pinhole view is
    built, and its corners are as good as any."""
    from perchpose.detection import detector as detection

    r = renderers["fpv_wide"]
    T = facing_pose(0.04, -0.03, 0.25, 0.3)
    image = r.render(T, rng=np.random.default_rng(3))
    remapped: list[object] = []
    real = detection.cv2.remap

    def remap(*args: object, **kwargs: object) -> object:
        remapped.append(args)
        return real(*args, **kwargs)  # type: ignore[call-overload]

    monkeypatch.setattr(detection.cv2, "remap", remap)
    found = {d.marker_index: d for d in MarkerDetector(r.camera, r.target).detect(image).markers}
    assert set(found) == {0, 1}
    assert found[0].image_pass == "raw"
    assert found[0].side_px > 100
    assert remapped == []
    truth = r.corners_px(T)
    for index, det in found.items():
        corners = truth[index]
        assert corners is not None
        assert np.max(np.abs(det.corners_px - corners)) < 0.05


def test_markers_not_in_the_target_are_ignored(webcam: CameraModel) -> None:
    # render a target holding the paper's markers plus a stranger beside them
    stranger = MarkerSpec("DICT_4X4_1000", 42, 60.0, centre_mm=(-160.0, 0.0))
    scene = TargetSpec((*TargetSpec.paper().markers, stranger), quiet_zone_mm=200.0)
    image = Renderer(webcam, scene).render(facing_pose(0.05, 0.0, 0.9))
    ids = {d.marker_index for d in MarkerDetector(webcam, TargetSpec.paper()).detect(image).markers}
    assert ids == {0, 1}
    everything = MarkerDetector(webcam, scene).detect(image).markers
    assert len(everything) == 3


def test_plumb_bob_with_little_distortion_needs_no_rectified_pass(webcam: CameraModel) -> None:
    assert not MarkerDetector(webcam, TargetSpec.paper()).rectify


def test_grey_and_bgr_give_the_same_corners(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    grey = r.render(facing_pose(0.0, 0.0, 0.6))
    det = MarkerDetector(r.camera, r.target)
    bgr = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    a = det.detect(grey).markers
    b = det.detect(r.camera.check_image(bgr)).markers
    assert len(a) == len(b) == 2
    for da, db in zip(a, b, strict=True):
        np.testing.assert_allclose(da.corners_px, db.corners_px)


def test_target_dictionaries_hold_only_the_targets_markers() -> None:
    target = TargetSpec.paper()
    dictionaries, members = target_dictionaries(target)
    assert [d.bytesList.shape[0] for d in dictionaries] == [1, 1]
    assert members == [[0], [1]]
    for marker, dictionary in zip(target.markers, dictionaries, strict=True):
        full = aruco_dictionary(marker.dictionary)
        assert np.array_equal(dictionary.bytesList[0], full.bytesList[marker.marker_id])
        assert dictionary.maxCorrectionBits == full.maxCorrectionBits
        # the subset reads the printed marker as its entry 0
        image = np.full((200, 200), 255, np.uint8)
        image[40:160, 40:160] = cv2.aruco.generateImageMarker(full, marker.marker_id, 120)
        _, ids, _ = cv2.aruco.ArucoDetector(dictionary).detectMarkers(image)
        assert ids is not None
        assert ids.reshape(-1).tolist() == [0]


@pytest.mark.parametrize("camera_name", ["webcam", "fpv", "fpv_wide"])
def test_tracking_finds_what_the_full_search_finds(
    renderers: dict[str, Renderer], camera_name: str
) -> None:
    """The tracking windows (and on a fisheye the rectified-only search of large markers) see
    every marker that searching each frame from scratch sees, with the same corners; a marker
    at the edge of detection (9-10 px) that only the window around its last place finds must be
    where the marker is."""
    r = renderers[camera_name]
    detector = MarkerDetector(r.camera, r.target)
    rng = np.random.default_rng(5)
    hint: tuple = ()
    tracked = 0
    for k, z in enumerate(np.linspace(1.0, 0.12, 16)):
        T = facing_pose(0.05 * z * math.sin(k / 3), 0.04 * z, float(z), 0.2 * k)
        image = r.render(T, rng=rng)
        with_hint = {d.marker_index: d for d in detector.detect(image, hint).markers}
        fresh = {d.marker_index: d for d in detector.detect(image).markers}
        assert set(fresh) <= set(with_hint)
        for i, d in with_hint.items():
            if i in fresh:
                assert np.max(np.abs(d.corners_px - fresh[i].corners_px)) < 0.05
            else:
                assert d.side_px < 12.0
                assert np.max(np.abs(d.corners_px - r.corners_px(T)[i])) < 0.5
        tracked += bool(hint)
        hint = tuple(with_hint.values())
    assert tracked >= 14


def test_a_marker_running_out_of_a_fisheye_image_gives_no_false_quad(
    renderers: dict[str, Renderer],
) -> None:
    """10 cm under the target, tilted, the outer marker runs out of the bottom of the image;
    the rectified view (black beyond the image) must not close it into a quad along the
    image's edge (it once did, 25 px off)."""
    r = renderers["fpv"]
    T = np.array(
        [
            [-0.682031, -0.693282, 0.232795, 0.003749],
            [-0.731115, 0.638788, -0.239625, -0.01022],
            [0.017421, -0.333632, -0.942542, 0.104155],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    T[:3, :3] = np.linalg.svd(T[:3, :3])[0] @ np.linalg.svd(T[:3, :3])[2]
    truth = r.corners_px(T)
    for seed in range(3):
        detector = MarkerDetector(r.camera, r.target)
        found = detector.detect(r.render(T, rng=np.random.default_rng(seed))).markers
        assert 1 in {d.marker_index for d in found}
        for d in found:
            true = truth[d.marker_index]
            assert true is not None
            assert np.max(np.abs(d.corners_px - true)) < 1.0


def _sheet_pixels(target: TargetSpec, px: int) -> tuple[np.ndarray, float]:
    """The printed sheet as a (px, px) uint8 picture and the metres per pixel."""
    half = target.sheet_half_extent_m
    centres = (np.arange(px) + 0.5 - px / 2) * (2 * half / px)
    xx, yy = np.meshgrid(centres, -centres)
    albedo = np.nan_to_num(target.albedo(xx, yy), nan=1.0)
    return (30 + 190 * albedo).astype(np.uint8), 2 * half / px


def _paste(canvas: np.ndarray, sheet: np.ndarray, corners_px: np.ndarray) -> None:
    n = sheet.shape[0]
    src = np.array([[0, 0], [n, 0], [n, n], [0, n]], np.float32)
    H = cv2.getPerspectiveTransform(src, corners_px.astype(np.float32))
    size = (canvas.shape[1], canvas.shape[0])
    warped = cv2.warpPerspective(sheet, H, size, flags=cv2.INTER_AREA)
    mask = cv2.warpPerspective(np.full_like(sheet, 255), H, size) > 128
    canvas[mask] = warped[mask]


def test_two_copies_in_view_are_never_fused(webcam: CameraModel, paper_target: TargetSpec) -> None:
    """A large copy whose inner marker is covered, and a small, turned copy fully visible: the
    small copy's inner marker is not where the large copy's outer marker puts it, so it is
    left out (the largest quad per marker alone fused the two into a phantom pose)."""
    sheet, _ = _sheet_pixels(paper_target, 600)
    covered = sheet.copy()
    covered[270:330, 270:330] = 220  # white over the large copy's inner marker
    canvas = np.full((480, 640), 90, np.uint8)
    _paste(canvas, covered, np.array([[20, 40], [340, 60], [330, 380], [30, 370]]))
    turned = np.array([[470, 200], [600, 230], [570, 360], [440, 330]])
    _paste(canvas, sheet, turned)
    detector = MarkerDetector(webcam, paper_target)
    found = detector.detect(canvas).markers
    by_index = {d.marker_index: d for d in found}
    assert set(by_index) == {0}
    assert by_index[0].corners_px[:, 0].max() < 400  # the large copy's outer marker
    # each copy alone is found whole
    alone = np.full((480, 640), 90, np.uint8)
    _paste(alone, sheet, turned)
    assert {d.marker_index for d in detector.detect(alone).markers} == {0, 1}


def test_a_small_marker_beside_a_large_one_skips_the_pattern_fit(
    renderers: dict[str, Renderer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """At 90 cm through the webcam the outer marker spans about 90 px and the inner one 15 px:
    with ``pattern_beside_ratio`` the inner keeps its edge-fitted corners (no pattern fit),
    which stay within a tenth of a pixel of the pattern-fitted ones."""
    from perchpose.corners import refinement

    calls: list[float] = []
    fit = refinement.refine_corners_pattern

    def counted(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(1.0)
        return fit(*args, **kwargs)

    monkeypatch.setattr(refinement, "refine_corners_pattern", counted)
    r = renderers["webcam"]
    T = facing_pose(0.01, -0.02, 0.9, 0.4)
    image = r.render(T, rng=np.random.default_rng(2))
    full = {d.marker_index: d for d in MarkerDetector(r.camera, r.target).detect(image).markers}
    assert len(calls) == 1
    assert full[1].side_px < 20
    assert full[0].side_px > 80
    skipping = MarkerDetector(r.camera, r.target, pattern_beside_ratio=4.0)
    skipped = {d.marker_index: d for d in skipping.detect(image).markers}
    assert len(calls) == 1
    assert np.array_equal(skipped[0].corners_px, full[0].corners_px)
    assert not np.array_equal(skipped[1].corners_px, full[1].corners_px)
    assert np.max(np.abs(skipped[1].corners_px - full[1].corners_px)) < 0.1


def test_glare_around_a_target_in_shadow_is_clipped_away(
    renderers: dict[str, Renderer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Under the harsh preset the surround saturates and the sheet's white margin thresholds
    as dark beside it: no quad closes in the frame as it is. The clipped search finds the outer
    marker, and its corners (fitted to the frame itself) sit where the geometry puts them."""
    from perchpose.detection import detector as detection
    from perchpose.sim.render import ImageQuality

    r = renderers["fpv"]
    T = facing_pose(0.03, -0.02, 1.0, 0.7)
    image = r.render(T, ImageQuality.preset("harsh"), np.random.default_rng(1))
    assert detection.has_glare(image)
    truth = r.corners_px(T)[0]
    assert truth is not None
    detector = MarkerDetector(r.camera, r.target)
    found = {d.marker_index: d for d in detector.detect(image).markers}
    assert 0 in found
    assert np.max(np.abs(found[0].corners_px - truth)) < 0.5
    # the same frame without the clipped search: nothing
    monkeypatch.setattr(detection, "has_glare", lambda grey: False)
    assert MarkerDetector(r.camera, r.target).detect(image).markers == ()


def test_without_glare_the_frame_is_searched_as_it_is(renderers: dict[str, Renderer]) -> None:
    from perchpose.detection import detector as detection

    r = renderers["fpv"]
    image = r.render(facing_pose(0.0, 0.0, 0.5), rng=np.random.default_rng(0))
    assert not detection.has_glare(image)
    assert detection.has_glare(np.full((480, 640), 255, np.uint8))


def test_a_shrunk_search_finds_the_quads_near_their_full_size_corners(
    renderers: dict[str, Renderer],
) -> None:
    """The tracking pass searches large markers shrunk: the quads it finds at a quarter of the
    size map back to within a pixel and a half of the full-size search's corners (a start for
    the edge fit, which needs one within 0.6 of a cell: 20 px here)."""
    from perchpose.detection.quads import QuadFinder

    r = renderers["webcam"]
    image = r.render(facing_pose(0.01, 0.02, 0.4, 0.6), rng=np.random.default_rng(3))
    finder = QuadFinder(r.target, 640)
    full = finder.find(image, "raw")
    assert set(full) == {0, 1}
    lo = np.floor(full[0].corners_px.min(axis=0)).astype(int) - 40
    hi = np.ceil(full[0].corners_px.max(axis=0)).astype(int) + 40
    window = image[lo[1] : hi[1], lo[0] : hi[0]]
    shrunk = finder.find(window, "raw", (int(lo[0]), int(lo[1])), finder.tracking, 0.25)
    assert 0 in shrunk
    assert np.max(np.abs(shrunk[0].corners_px - full[0].corners_px)) < 1.5


def test_tracking_searches_the_whole_frame_at_an_interval_for_what_it_lacks(
    renderers: dict[str, Renderer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Tracking looks in windows, but every ``full_search_every`` frames it searches the whole
    frame, shrunk, for the markers it has not got and adds those it finds (here the windows
    are kept from looking for the inner marker); with every marker tracked there is nothing
    to look for; under a spent budget it puts the search off to the next frame and says so
    (and says nothing where there was nothing to look for)."""
    from perchpose.detection.quads import QuadFinder

    r = renderers["webcam"]
    image = r.render(facing_pose(0.0, 0.01, 0.4, 0.2), rng=np.random.default_rng(0))
    whole: list[float] = []
    find = QuadFinder.find

    def counted(self, grey, image_pass, offset=(0, 0), detector=None, scale=1.0):  # type: ignore[no-untyped-def]
        # the whole frame searched (tracking's own passes aside: they search windows)
        if detector not in (self.tracking, self.tracking_small) and grey.shape == image.shape:
            whole.append(scale)
        return find(self, grey, image_pass, offset, detector, scale)

    monkeypatch.setattr(QuadFinder, "find", counted)
    detector = MarkerDetector(r.camera, r.target, full_search_every=5)
    first = detector.detect(image).markers
    assert {d.marker_index for d in first} == {0, 1}
    assert whole == [1.0]
    # both tracked: the interval finds nothing to look for
    hint = first
    for _ in range(10):
        hint = detector.detect(image, hint).markers
        assert {d.marker_index for d in hint} == {0, 1}
    assert whole == [1.0]
    # the inner marker dropped, and the windows kept from it: the interval's search finds it
    monkeypatch.setattr(QuadSearch, "may_be_found", lambda *args: False)
    hint = tuple(d for d in hint if d.marker_index == 0)
    seen: list[set[int]] = []
    for _ in range(5):
        hint = detector.detect(image, hint).markers
        seen.append({d.marker_index for d in hint})
    assert seen == [{0}, {0}, {0}, {0}, {0, 1}]
    assert whole == [1.0, CHECK_SCALE]
    inner = next(d for d in hint if d.marker_index == 1)
    assert inner.corner_covariance_px2 is not None  # fitted, not a shrunk image's quad
    truth = r.corners_px(facing_pose(0.0, 0.01, 0.4, 0.2))[1]
    assert truth is not None
    assert np.max(np.abs(inner.corners_px - truth)) < 0.2
    late = MarkerDetector(r.camera, r.target, full_search_every=2)
    hint = tuple(d for d in late.detect(image).markers if d.marker_index == 0)
    hint = late.detect(image, hint).markers
    whole.clear()
    detected = late.detect(image, hint, deadline_s=0.0)
    hint = detected.markers
    assert "interval search" in detected.skipped
    assert whole == []
    # put off, not dropped: the next frame with room for it searches
    late.detect(image, hint)
    assert whole == [CHECK_SCALE]
    # with both markers tracked there is nothing to put off
    full = MarkerDetector(r.camera, r.target, full_search_every=2)
    hint = full.detect(image).markers
    hint = full.detect(image, hint).markers
    assert "interval search" not in full.detect(image, hint, deadline_s=0.0).skipped


def test_a_marker_the_tracking_pass_misses_is_fitted_from_its_prediction(
    renderers: dict[str, Renderer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """When the window's quad pass finds nothing (as on blurred, noisy frames), a hinted
    marker a pixel or so from where it was (what carrying the hint on leaves) is fitted from
    there and kept because its cells read as printed, with corners as close to the truth as
    the found quad's; a blank frame gives nothing (the search then runs) and so does a hint
    turned by a quarter."""
    from perchpose.detection.quads import QuadFinder

    r = renderers["fpv"]
    T0 = facing_pose(0.01, 0.0, 0.3, 0.2)
    T1 = facing_pose(0.0105, 0.0002, 0.299, 0.205)
    rng = np.random.default_rng(8)
    first, second = r.render(T0, rng=rng), r.render(T1, rng=rng)
    detector = MarkerDetector(r.camera, r.target)
    hint = detector.detect(first).markers
    found = {d.marker_index: d for d in detector.detect(second, hint).markers}
    find = QuadFinder.find

    def blind(self, grey, image_pass, offset=(0, 0), detector=None, scale=1.0):  # type: ignore[no-untyped-def]
        if detector is not None:  # the tracking passes see nothing
            return {}
        return find(self, grey, image_pass, offset, None, scale)

    monkeypatch.setattr(QuadFinder, "find", blind)
    tracked = {d.marker_index: d for d in detector.detect(second, hint).markers}
    true = r.corners_px(T1)
    assert set(tracked) == set(found) == {0, 1}
    for i, d in tracked.items():
        assert d.image_pass == "tracked"
        t = true[i]
        assert t is not None
        error = np.max(np.linalg.norm(d.corners_px - t, axis=1))
        assert error < 0.05
        assert error < 2.0 * np.max(np.linalg.norm(found[i].corners_px - t, axis=1)) + 0.01
    blank = np.full_like(second, 128)
    assert detector._track_edges(blank, blank, hint)[0] is None
    turned = tuple(
        type(d)(d.marker_index, np.roll(d.corners_px, 1, axis=0), d.image_pass) for d in hint
    )
    assert detector.fitting.fit_direct(second, list(turned), DIRECT_SIDE_PX) == {}


def test_hinted_markers_are_fitted_from_their_prediction_without_a_quad_search(
    renderers: dict[str, Renderer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """While tracking, markers of 20 px or more that were found a frame before are fitted
    straight from where they were (no quad search runs) and match the corners that a search
    of the frame from scratch gives; a marker too small for that still gets its window, and
    the outer marker whatever its white margin (0.8 cells)."""
    from perchpose.detection.quads import QuadFinder

    r = renderers["fpv"]
    rng = np.random.default_rng(4)
    searched: list[tuple[int, ...]] = []
    find = QuadFinder.find

    def counted(self, grey, image_pass, offset=(0, 0), detector=None, scale=1.0):  # type: ignore[no-untyped-def]
        searched.append(grey.shape)
        return find(self, grey, image_pass, offset, detector, scale)

    detector = MarkerDetector(r.camera, r.target)
    first = r.render(facing_pose(0.01, 0.0, 0.3, 0.2), rng=rng)
    second = r.render(facing_pose(0.0102, 0.0001, 0.2995, 0.202), rng=rng)
    hint = detector.detect(first).markers
    assert {d.side_px >= 20 for d in hint} == {True}
    fresh = {d.marker_index: d for d in detector.detect(second).markers}
    monkeypatch.setattr(QuadFinder, "find", counted)
    tracked = {d.marker_index: d for d in detector.detect(second, hint).markers}
    assert searched == []
    assert set(tracked) == set(fresh) == {0, 1}
    for i, d in tracked.items():
        assert d.image_pass == "tracked"
        assert np.max(np.abs(d.corners_px - fresh[i].corners_px)) < 0.05
    # further away (110 px) the inner marker is under 20 px: it alone is searched, in a small
    # window
    far = MarkerDetector(r.camera, r.target)
    image = r.render(facing_pose(0.01, 0.0, 0.4, 0.2), rng=rng)
    hint = far.detect(image).markers
    assert sorted(d.side_px < 20 for d in hint) == [False, True]
    searched.clear()
    tracked = {d.marker_index: d for d in far.detect(image, hint).markers}
    assert set(tracked) == {0, 1}
    assert len(searched) == 1
    assert searched[0][0] * searched[0][1] < 0.05 * image.shape[0] * image.shape[1]


@pytest.mark.parametrize("thorough_every", [None, 3])
def test_a_lost_target_is_looked_for_every_way_in_turn(
    renderers: dict[str, Renderer], monkeypatch: pytest.MonkeyPatch, thorough_every: int | None
) -> None:
    """A frame under glare with no target in it: each frame takes a quick look at it (one
    threshold window) the way that found the target last (none yet: the frame as it is) and
    one way more: on every other frame the ladder's next (the first clip level), and between
    them each other way in turn, every clip level of the frame itself, then each through the
    lens's pinhole view (searched at half its size). It searches the frame thoroughly, with
    OpenCV's other two windows, on every frame, or with ``thorough_every`` on the first and
    then every that many, each time at the next clip level of the frame itself."""
    from perchpose.detection import detector as detection

    r = renderers["fpv"]
    detector = MarkerDetector(r.camera, r.target, thorough_every=thorough_every)
    assert detector.rectify
    frame = np.full((r.camera.height_px, r.camera.width_px), 40, np.uint8)
    frame[:, : r.camera.width_px // 2] = 255
    assert detection.has_glare(frame)
    searched: list[tuple[str, int, tuple[int, ...], str]] = []
    real = detector.quads.find
    passes = {id(detector.quads.quick): "quick", id(detector.quads.rest): "rest"}

    def find(grey: np.ndarray, image_pass: str, *args: object, **kwargs: object) -> object:
        which = passes.get(id(kwargs.get("detector")), "other")
        searched.append((image_pass, int(grey.max()), grey.shape, which))
        return real(grey, image_pass, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(detector.quads, "find", find)
    ladder = detector.search_ladder(glare=True)
    assert len(ladder) == 2 * len(detection.GLARE_CLIP_LEVELS)
    per_frame = []
    for _ in range(2 * (len(ladder) - 2)):
        searched.clear()
        assert detector.detect(frame).markers == ()
        per_frame.append(list(searched))
    ways = [(view, 255 if level is None else level) for level, view in ladder]
    n_levels = len(detection.GLARE_CLIP_LEVELS)
    thorough = 0
    for k, frame_searches in enumerate(per_frame):
        tried = [(view, level, which) for view, level, _, which in frame_searches]
        second = ways[1] if k % 2 == 0 else ways[k // 2 + 2]
        expected = [(*ways[0], "quick"), (*second, "quick")]
        if thorough_every is None or k % thorough_every == 0:
            expected.append((*ways[thorough % n_levels], "rest"))
            thorough += 1
        assert tried == expected
    rectified_shape = detector.search.rectification.coarse_maps[0].shape
    for frame_searches in per_frame:
        for view, _, shape, _ in frame_searches:
            expected_shape = rectified_shape if view == "rectified" else frame.shape
            assert shape == expected_shape
    detector.restart()
    searched.clear()
    assert detector.detect(frame).markers == ()
    assert [which for *_, which in searched] == ["quick", "quick", "rest"]


def test_a_target_gone_from_its_window_is_looked_for_quickly(
    renderers: dict[str, Renderer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The target tracked, then a frame without it: the tracking pass sees no quad in the
    window where it should be, so the whole frame gets the quick look (its window is not
    searched thoroughly first), and the thorough search of the whole frame waits for the
    estimator's third frame without it."""
    r = renderers["webcam"]
    image = r.render(facing_pose(0.0, 0.01, 0.5, 0.2), rng=np.random.default_rng(0))
    blank = np.full_like(image, 128)
    detector = MarkerDetector(r.camera, r.target, thorough_every=3)
    hint = detector.detect(image).markers
    hint = detector.detect(image, hint).markers
    assert {d.marker_index for d in hint} == {0, 1}
    passes = {
        id(detector.quads.quick): "quick",
        id(detector.quads.rest): "rest",
        id(detector.quads.tracking): "tracking",
        id(detector.quads.tracking_small): "tracking",
    }
    used: list[str] = []
    real = detector.quads.find

    def find(grey: np.ndarray, image_pass: str, *args: object, **kwargs: object) -> object:
        chosen = kwargs.get("detector", args[1] if len(args) > 1 else None)
        used.append(passes.get(id(chosen), "thorough"))
        return real(grey, image_pass, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(detector.quads, "find", find)
    per_frame = []
    for _ in range(3):
        used.clear()
        assert detector.detect(blank, hint).markers == ()
        hint = ()
        per_frame.append(list(used))
    assert per_frame == [["tracking", "quick"], ["quick"], ["quick", "rest"]]


def test_a_quick_look_finds_what_the_thorough_search_finds(
    renderers: dict[str, Renderer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """At 85 cm the inner marker is 10 px across: the quick look at the whole frame (one
    23 px threshold window) finds the outer marker only, and a search of the window where the
    target's plane through it puts the inner one (as tracking's, with a 3 px window for a
    small marker) adds it. The same markers as the thorough search of the whole frame (which
    never ran), at the same corners."""
    from perchpose.detection.quads import QuadFinder

    r = renderers["fpv"]
    T = facing_pose(0.02, -0.01, 0.85, 0.4, 0.1, -0.1)
    image = r.render(T, rng=np.random.default_rng(3))
    quads = QuadFinder(r.target, max(r.camera.size))
    assert set(quads.find(image, "raw", detector=quads.quick)) == {0}
    assert set(quads.find(image, "raw")) == {0, 1}
    detector = MarkerDetector(r.camera, r.target)
    shapes: list[tuple[int, ...]] = []
    real = detector.quads.find

    def find(grey: np.ndarray, image_pass: str, *args: object, **kwargs: object) -> object:
        if kwargs.get("detector") is not detector.quads.quick:
            shapes.append(grey.shape)
        return real(grey, image_pass, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(detector.quads, "find", find)
    looked = detector.detect(image).markers
    assert shapes
    assert all(s[0] * s[1] < 0.2 * image.size for s in shapes)
    monkeypatch.undo()
    thorough = MarkerDetector(r.camera, r.target)
    found = thorough.search.find(image, refind_curved=False)
    whole = thorough.fitting.fit_found(image, image, found)
    assert [d.marker_index for d in looked] == [d.marker_index for d in whole] == [0, 1]
    for a, b in zip(looked, whole, strict=True):
        assert np.max(np.abs(a.corners_px - b.corners_px)) < 0.02


def test_a_tracked_marker_whose_prediction_cannot_be_fitted_is_fitted_from_its_quad(
    renderers: dict[str, Renderer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """While tracking, a marker whose fit from its prediction fails is searched in its
    window and fitted from the quad found there; where that fit fails too, it keeps the
    quad's own corners, with a covariance of a fair part of a cell."""

    r = renderers["fpv"]
    rng = np.random.default_rng(6)
    detector = MarkerDetector(r.camera, r.target)
    T = facing_pose(0.01, 0.0, 1.3, 0.2)  # the outer marker about 35 px
    hint = tuple(d for d in detector.detect(r.render(T, rng=rng)).markers if d.marker_index == 0)
    assert len(hint) == 1
    assert hint[0].side_px < 40  # under CURVED_SIDE_PX: no pinhole view
    T1 = facing_pose(0.0102, 0.0001, 1.299, 0.201)
    image = r.render(T1, rng=rng)
    truth = r.corners_px(T1)[0]
    assert truth is not None
    fit_corners = Fitting.fit_corners
    predictions: list[bool] = []

    def predictions_refused(self, grey, det, **kwargs):  # type: ignore[no-untyped-def]
        predictions.append(bool(kwargs.get("predicted")))
        if kwargs.get("predicted"):
            return None
        return fit_corners(self, grey, det, **kwargs)

    monkeypatch.setattr(Fitting, "fit_corners", predictions_refused)
    (tracked,) = [d for d in detector.detect(image, hint).markers if d.marker_index == 0]
    assert predictions == [True, False]
    assert tracked.image_pass == "raw"
    assert tracked.corner_covariance_px2 is not None  # edge-fitted
    assert np.max(np.abs(tracked.corners_px - truth)) < 0.1
    # nor the quad: its cornerSubPix corners
    monkeypatch.setattr(Fitting, "fit_corners", lambda self, grey, det, **kwargs: None)
    (kept,) = [d for d in detector.detect(image, hint).markers if d.marker_index == 0]
    assert kept.image_pass == "raw"
    assert np.max(np.abs(kept.corners_px - truth)) < 1.0
    # with the covariance that says so: independent, UNFITTED_SD_CELLS of a cell
    cell_px = kept.side_px / r.target.markers[0].cells.shape[0]
    assert kept.corner_covariance_px2 is not None
    np.testing.assert_allclose(
        kept.corner_covariance_px2, (UNFITTED_SD_CELLS * cell_px) ** 2 * np.eye(8)
    )


def test_a_marker_near_its_margin_is_fitted_from_its_prediction(
    renderers: dict[str, Renderer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The outer marker at about 75 px (the profiles reach near the end of its white margin)
    is fitted straight from its prediction on clean and harsh frames (blur, noise, JPEG). On
    the harsh frame the inner marker, 12 px with cells of under 1.8 blur sigmas, is not
    searched for: no quad search runs at all; on the clean frame it is, in a small window."""
    from perchpose.detection.quads import QuadFinder
    from perchpose.sim.render import ImageQuality

    r = renderers["fpv"]
    searched: list[tuple[int, ...]] = []
    find = QuadFinder.find

    def counted(self, grey, image_pass, offset=(0, 0), detector=None, scale=1.0):  # type: ignore[no-untyped-def]
        searched.append(grey.shape)
        return find(self, grey, image_pass, offset, detector, scale)

    T0 = facing_pose(0.01, 0.0, 0.6, 0.2)
    T1 = facing_pose(0.0102, 0.0001, 0.599, 0.202)
    truth = r.corners_px(T1)[0]
    assert truth is not None
    # within each quality's corner noise (harsh: 0.2-0.6 px RMS on the fpv approach)
    for quality, harsh, tolerance_px in (
        (ImageQuality.preset("harsh"), True, 0.5),
        (ImageQuality(), False, 0.05),
    ):
        rng = np.random.default_rng(8)
        detector = MarkerDetector(r.camera, r.target)
        hint = tuple(
            d for d in detector.detect(r.render(T0, quality, rng)).markers if d.marker_index == 0
        )
        assert len(hint) == 1
        assert 60 < hint[0].side_px < 80
        searched.clear()
        monkeypatch.setattr(QuadFinder, "find", counted)
        image = r.render(T1, quality, rng)
        tracked = {d.marker_index: d for d in detector.detect(image, hint).markers}
        monkeypatch.setattr(QuadFinder, "find", find)
        assert tracked[0].image_pass == "tracked"
        assert np.sqrt(np.mean((tracked[0].corners_px - truth) ** 2)) < tolerance_px
        if harsh:
            assert searched == []
        else:
            assert len(searched) == 1
            assert searched[0][0] * searched[0][1] < 0.05 * image.shape[0] * image.shape[1]


def test_a_marker_predicted_across_the_border_is_let_go_without_a_search(
    renderers: dict[str, Renderer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """While tracking, a hinted marker predicted across the image's border (leaving the view:
    OpenCV keeps no quad there) is neither searched for nor required: the frame is tracked
    with the marker still in view, and no quad search runs at all."""
    from dataclasses import replace

    from perchpose.detection.quads import QuadFinder

    r = renderers["fpv"]
    image = r.render(facing_pose(-0.18, 0.0, 0.2, 0.0), rng=np.random.default_rng(9))
    detector = MarkerDetector(r.camera, r.target)
    hint = {d.marker_index: d for d in detector.detect(image).markers}
    assert set(hint) == {0, 1}
    assert hint[1].side_px >= 20  # fitted from its prediction
    leaving = replace(hint[0], corners_px=hint[0].corners_px - np.array([60.0, 0.0]))
    assert not r.camera.in_image(leaving.corners_px)
    searched: list[tuple[int, ...]] = []
    find = QuadFinder.find

    def counted(self, grey, image_pass, offset=(0, 0), detector=None, scale=1.0):  # type: ignore[no-untyped-def]
        searched.append(grey.shape)
        return find(self, grey, image_pass, offset, detector, scale)

    monkeypatch.setattr(QuadFinder, "find", counted)
    tracked = detector.detect(image, (leaving, hint[1])).markers
    assert [(d.marker_index, d.image_pass) for d in tracked] == [(1, "tracked")]
    assert searched == []
