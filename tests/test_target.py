import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from perchpose import MarkerSpec, TargetSpec
from perchpose.errors import PerchposeError, TargetSpecError
from perchpose.printable import sheet_size_mm, write_target_sheet


def test_paper_target(paper_target: TargetSpec) -> None:
    outer, inner = paper_target.markers
    assert (outer.dictionary, outer.marker_id, outer.side_mm) == ("DICT_4X4_1000", 997, 150.0)
    assert (inner.dictionary, inner.marker_id, inner.side_mm) == ("DICT_ARUCO_ORIGINAL", 5, 25.0)
    assert inner.centre_mm == (0.0, 0.0)
    # the inner marker sits in the outer marker's white central 2x2 cells
    assert outer.cells[2:4, 2:4].all()


def test_corners_follow_aruco_order_as_printed(paper_target: TargetSpec) -> None:
    c = paper_target.outer.corners_target_m
    np.testing.assert_allclose(c[0], [-0.075, 0.075, 0.0])  # top-left: x left, y up
    np.testing.assert_allclose(c[2], [0.075, -0.075, 0.0])  # bottom-right


def test_rotated_offset_marker_geometry() -> None:
    m = MarkerSpec("DICT_4X4_50", 3, 20.0, centre_mm=(10.0, -5.0), rotation_deg=90.0)
    # rotated 90 deg counter-clockwise: the printed top-left corner moves to bottom-left
    np.testing.assert_allclose(m.corners_target_m[0], [0.0, -0.015, 0.0], atol=1e-12)


def test_yaml_round_trip(tmp_path: Path) -> None:
    spec = TargetSpec(
        (
            MarkerSpec("DICT_5X5_100", 7, 30.0, (100.0, 2.0), 15.0),  # beside the large one
            MarkerSpec("DICT_4X4_1000", 12, 120.0),
        ),
        name="custom",
        quiet_zone_mm=12.0,
    )
    assert spec.outer.marker_id == 12  # largest first
    spec.save(tmp_path / "t.yaml")
    assert TargetSpec.load(tmp_path / "t.yaml") == spec


@pytest.mark.parametrize(
    ("markers", "message"),
    [
        ([{"dictionary": "DICT_4X4_100", "id": 997, "side_mm": 150}], "not in DICT_4X4_100"),
        ([{"dictionary": "DICT_NOPE", "id": 1, "side_mm": 10}], "unknown ArUco dictionary"),
        ([{"dictionary": "DICT_4X4_50", "id": 1, "side_mm": -3}], "side_mm must be positive"),
        ([{"dictionary": "DICT_4X4_50", "id": 1, "side_mm": 1e300}], "side_mm 1e+300 is over"),
        (
            [{"dictionary": "DICT_4X4_50", "id": 1, "side_mm": 30, "centre_mm": [1e12, 0]}],
            "a centre over 10000 mm",
        ),
        ([{"dictionary": "DICT_4X4_50", "side_mm": 3}], "lacks field 'id'"),
        (
            [{"dictionary": "DICT_4X4_50", "id": 1, "side_mm": 3}] * 2,
            "lists marker DICT_4X4_50:1 twice",
        ),
        ([], "has no markers"),
    ],
)
def test_bad_target_files(tmp_path: Path, markers: list[dict[str, object]], message: str) -> None:
    path = tmp_path / "t.yaml"
    path.write_text(yaml.safe_dump({"markers": markers}))
    with pytest.raises(TargetSpecError, match=re.escape(message)):
        TargetSpec.load(path)


def test_albedo(paper_target: TargetSpec) -> None:
    a = paper_target.albedo(np.array([0.0, 0.074, 0.03, 0.5]), np.array([0.0, 0.074, 0.0, 0.0]))
    # centre of the inner marker is a payload cell, the outer's corner is black border,
    # (30 mm, 0) is in the outer's white centre, 0.5 m is off the sheet
    assert a[1] == 0.0
    assert a[2] == 1.0
    assert np.isnan(a[3])


def _sheets() -> list[TargetSpec]:
    """The paper's target (a marker printed over another), and turned markers off the centre
    of a wide white sheet (the texture prints each marker over its own bounding box)."""
    turned = MarkerSpec("DICT_4X4_50", 3, 100.0, rotation_deg=30.0, centre_mm=(40.0, -25.0))
    small = MarkerSpec("DICT_4X4_50", 7, 20.0, rotation_deg=-15.0, centre_mm=(-90.0, 70.0))
    return [TargetSpec.paper(), TargetSpec((turned, small), quiet_zone_mm=150.0)]


@pytest.mark.parametrize("target", _sheets(), ids=["paper", "turned"])
def test_texture_matches_the_analytic_albedo(target: TargetSpec) -> None:
    tex, texel = target.texture
    n = tex.shape[0]
    rng = np.random.default_rng(0)
    ij = rng.integers(0, n, size=(20000, 2))
    x = (ij[:, 1] + 0.5 - n / 2) * texel
    y = -(ij[:, 0] + 0.5 - n / 2) * texel
    expected = target.albedo(x, y)
    np.testing.assert_array_equal(tex[ij[:, 0], ij[:, 1]], np.nan_to_num(expected, nan=-1.0))
    assert 0 < np.count_nonzero(expected == 0.0) < np.count_nonzero(expected == 1.0)


def test_printable_png_is_true_scale(tmp_path: Path, paper_target: TargetSpec) -> None:
    import cv2

    out = write_target_sheet(paper_target, tmp_path / "t.png", dpi=150)
    img = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
    w_mm, h_mm = sheet_size_mm(paper_target)
    assert img.shape == (int(h_mm / 25.4 * 150), int(w_mm / 25.4 * 150))  # truncated pixels
    # the outer marker's black border spans 150 mm = 885.8 px at 150 dpi
    row = img[img.shape[0] // 4] < 128
    cols = np.flatnonzero(row)
    assert (cols.max() - cols.min() + 1) == pytest.approx(150 / 25.4 * 150, abs=3)


def test_printable_pdf_page_size(tmp_path: Path, paper_target: TargetSpec) -> None:
    out = write_target_sheet(paper_target, tmp_path / "t.pdf")
    text = out.read_bytes().decode("latin-1")
    box = re.search(r"/MediaBox \[\s*0 0 ([\d.]+) ([\d.]+)\s*\]", text)
    assert box is not None
    w_mm, h_mm = sheet_size_mm(paper_target)
    assert float(box.group(1)) == pytest.approx(w_mm / 25.4 * 72, abs=0.5)
    assert float(box.group(2)) == pytest.approx(h_mm / 25.4 * 72, abs=0.5)


def test_printable_svg_and_bad_suffix(tmp_path: Path, paper_target: TargetSpec) -> None:
    svg = write_target_sheet(paper_target, tmp_path / "t.svg").read_text()
    w_mm, _ = sheet_size_mm(paper_target)
    width = re.search(r'<svg[^>]*width="([\d.]+)pt"', svg)
    assert width is not None
    assert float(width.group(1)) == pytest.approx(w_mm / 25.4 * 72, abs=0.5)
    with pytest.raises(PerchposeError, match=r"t\.gif: output must end in"):
        write_target_sheet(paper_target, tmp_path / "t.gif")


def test_printed_target_png_is_detected(tmp_path: Path, paper_target: TargetSpec) -> None:
    import cv2

    out = write_target_sheet(paper_target, tmp_path / "t.png", dpi=300)
    image = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
    found = set()
    for name, marker_id in (("DICT_4X4_1000", 997), ("DICT_ARUCO_ORIGINAL", 5)):
        detector = cv2.aruco.ArucoDetector(
            cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        )
        _, ids, _ = detector.detectMarkers(image)
        if ids is not None and marker_id in ids.reshape(-1).tolist():
            found.add(marker_id)
    assert found == {997, 5}


def test_white_margin_around_each_marker(paper_target: TargetSpec) -> None:
    # the outer marker: the 20 mm quiet zone in 25 mm cells; the inner one sits in the outer
    # marker's white centre, at least 12.5 mm of white around it (3.5 of its cells; more where
    # the outer marker's next cell is white too): beyond reach of the edge profiles
    assert paper_target.white_margin_cells(0) == pytest.approx((0.8,) * 4, abs=0.01)
    assert paper_target.white_margin_cells(1) == (math.inf,) * 4
    far = paper_target.white_margin_cells(1, max_cells=8.0)
    assert min(far) == pytest.approx(3.5, abs=0.01)
    assert all(m >= 3.49 for m in far)


@pytest.mark.parametrize(
    ("inner", "message"),
    [
        (MarkerSpec("DICT_ARUCO_ORIGINAL", 5, 60.0), "covers black cells"),
        (MarkerSpec("DICT_ARUCO_ORIGINAL", 5, 25.0, (80.0, 0.0)), "straddles the edge"),
        (MarkerSpec("DICT_ARUCO_ORIGINAL", 5, 25.0, (0.0, 40.0)), "covers black cells"),
    ],
)
def test_impossible_nesting_is_refused(inner: MarkerSpec, message: str) -> None:
    outer = MarkerSpec("DICT_4X4_1000", 997, 150.0)
    with pytest.raises(TargetSpecError, match=message):
        TargetSpec((outer, inner))


def test_an_inner_marker_listed_first_is_still_checked(tmp_path: Path) -> None:
    """A file whose 'inner' marker is larger than the 'outer' one: the small one then sits on
    the large one's data cells."""
    path = tmp_path / "t.yaml"
    path.write_text(
        "markers:\n"
        "  - {dictionary: DICT_ARUCO_ORIGINAL, id: 5, side_mm: 150}\n"
        "  - {dictionary: DICT_4X4_1000, id: 997, side_mm: 100}\n"
    )
    with pytest.raises(TargetSpecError, match=r"t\.yaml.*covers black cells"):
        TargetSpec.load(path)


def test_markers_side_by_side_are_fine() -> None:
    a = MarkerSpec("DICT_4X4_1000", 997, 100.0, (-60.0, 0.0))
    b = MarkerSpec("DICT_4X4_1000", 998, 100.0, (60.0, 0.0))
    assert len(TargetSpec((a, b)).markers) == 2
