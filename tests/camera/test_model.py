import dataclasses
import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from perchpose import CameraModel
from perchpose.errors import CameraFileError, ImageError


def test_loads_the_opencv_filestorage_calibration(charuco_dir: Path) -> None:
    cam = CameraModel.load(charuco_dir / "tutorial_camera_charuco.yml")
    assert cam.size == (640, 480)
    assert cam.model == "plumb_bob"
    assert cam.K[0, 0] == pytest.approx(452.51, abs=0.01)
    assert cam.K[1, 1] == pytest.approx(456.77, abs=0.01)
    assert cam.K[0, 2] == pytest.approx(317.70, abs=0.01)
    assert cam.dist.shape == (5,)
    assert cam.dist[4] == pytest.approx(2.9543, abs=1e-4)


@pytest.mark.parametrize("name", ["webcam", "fpv", "fpv_wide"])
def test_ros_yaml_round_trip(tmp_path: Path, name: str) -> None:
    cam = CameraModel.preset(name)
    path = tmp_path / "camera.yaml"
    cam.save(path)
    data = yaml.safe_load(path.read_text())
    assert data["distortion_model"] == cam.model
    loaded = CameraModel.load(path)
    np.testing.assert_array_equal(loaded.K, cam.K)
    np.testing.assert_array_equal(loaded.dist, cam.dist)
    assert (loaded.size, loaded.model) == (cam.size, cam.model)


@pytest.mark.parametrize("name", ["webcam", "fpv", "fpv_wide"])
def test_project_and_unproject_are_inverse(name: str) -> None:
    cam = CameraModel.preset(name)
    rng = np.random.default_rng(0)
    uv = np.stack([rng.uniform(0, 639, 500), rng.uniform(0, 479, 500)], 1)
    rays = cam.pixel_rays(uv)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    back, ok = cam.project(rays * 0.7)
    assert ok.all()
    np.testing.assert_allclose(back, uv, atol=1e-6)


@pytest.mark.parametrize("name", ["webcam", "fpv", "fpv_wide"])
def test_the_projection_jacobian_is_what_small_moves_of_the_point_do(name: str) -> None:
    camera = CameraModel.preset(name)
    rng = np.random.default_rng(4)
    points = np.column_stack(
        [rng.uniform(-0.3, 0.3, 30), rng.uniform(-0.3, 0.3, 30), rng.uniform(0.1, 1.0, 30)]
    )
    points[0] = (0.0, 0.0, 0.4)  # on the axis
    uv, duv_dq, in_front = camera.project_with_jacobian(points)
    assert in_front.all()
    np.testing.assert_array_equal(uv, camera.project(points)[0])
    step = 1e-7
    for k in range(3):
        delta = np.zeros(3)
        delta[k] = step
        expected = (camera.project(points + delta)[0] - camera.project(points - delta)[0]) / (
            2 * step
        )
        np.testing.assert_allclose(duv_dq[:, :, k], expected, rtol=1e-5, atol=1e-3)


def test_equidistant_covers_rays_beyond_ninety_degrees() -> None:
    cam = CameraModel.preset("fpv_wide")
    corner_ray = cam.pixel_rays(np.array([[0.0, 0.0]]))[0]
    assert math.degrees(math.acos(corner_ray[2])) > 90.0
    uv, ok = cam.project(corner_ray[None, :])
    assert ok[0]
    np.testing.assert_allclose(uv[0], [0.0, 0.0], atol=1e-6)


def test_points_behind_a_pinhole_camera_are_flagged() -> None:
    cam = CameraModel.preset("webcam")
    _, ok = cam.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]))
    assert ok.tolist() == [False, True]


def test_missing_camera_file(tmp_path: Path) -> None:
    with pytest.raises(CameraFileError, match="camera file not found"):
        CameraModel.load(tmp_path / "nope.yaml")


def test_unparsable_camera_file(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("camera_matrix: [1, 2\n  - :")
    with pytest.raises(CameraFileError, match=r"bad\.yaml: not valid YAML"):
        CameraModel.load(path)


@pytest.mark.parametrize(
    "field", ["camera_matrix", "distortion_coefficients", "image_width", "image_height"]
)
def test_camera_file_lacking_a_field_names_it(tmp_path: Path, field: str) -> None:
    data = CameraModel.preset("webcam").to_ros_dict()
    del data[field]
    path = tmp_path / "cam.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(CameraFileError, match=f"cam.yaml: missing field '{field}'"):
        CameraModel.load(path)


def test_wrong_number_of_fisheye_coefficients(tmp_path: Path) -> None:
    data = CameraModel.preset("fpv").to_ros_dict()
    data["distortion_coefficients"]["data"] = [0.1, 0.2, 0.0, 0.0, 0.0]
    path = tmp_path / "cam.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(CameraFileError, match="equidistant needs 4 coefficients"):
        CameraModel.load(path)


def test_broken_opencv_storage(tmp_path: Path) -> None:
    path = tmp_path / "cam.yml"
    path.write_text("%YAML:1.0\n---\nimage_width: 640\n")
    with pytest.raises(CameraFileError, match="missing field"):
        CameraModel.load(path)


def test_image_size_must_match_the_calibration() -> None:
    cam = CameraModel.preset("webcam")
    with pytest.raises(ImageError, match=r"image is 320x240 but camera 'webcam' is calibrated"):
        cam.check_image(np.zeros((240, 320), np.uint8))
    with pytest.raises(ImageError, match="uint8"):
        cam.check_image(np.zeros((480, 640), np.float32))
    grey = cam.check_image(np.zeros((480, 640, 3), np.uint8))
    assert grey.shape == (480, 640)


def test_unknown_preset() -> None:
    with pytest.raises(CameraFileError, match="unknown camera preset"):
        CameraModel.preset("hubble")


_XML_MATRICES = (
    '<camera_matrix type_id="opencv-matrix"><rows>3</rows><cols>3</cols><dt>d</dt>'
    "<data>500 0 320 0 500 240 0 0 1</data></camera_matrix>"
    '<distortion_coefficients type_id="opencv-matrix"><rows>1</rows><cols>5</cols><dt>d</dt>'
    "<data>0 0 0 0 0</data></distortion_coefficients>"
)


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (f"<image_width>abc</image_width><image_height>480</image_height>{_XML_MATRICES}",
         "image_width is not a number"),
        (f"<image_width>1e308</image_width><image_height>480</image_height>{_XML_MATRICES}",
         "image_width must be a whole number"),
        (f"<image_width>640</image_width><image_height>-4</image_height>{_XML_MATRICES}",
         "image_height must be a whole number"),
        ("<image_width>640</image_width><camera_matrix><rows>3</rows><data>1 2",
         "malformed OpenCV FileStorage"),
    ],
)  # fmt: skip
def test_malformed_opencv_xml_is_one_clear_error(tmp_path: Path, body: str, message: str) -> None:
    path = tmp_path / "cam.xml"
    path.write_text(f'<?xml version="1.0"?>\n<opencv_storage>\n{body}\n</opencv_storage>\n')
    with pytest.raises(CameraFileError, match=message):
        CameraModel.load(path)


def test_in_image_keeps_its_margin_and_refuses_nan() -> None:
    camera = CameraModel.preset("fpv")
    w, h = camera.size
    inside = np.array([[2.0, 2.0], [w - 3.0, h - 3.0]])
    assert camera.in_image(inside, 2.0)
    assert not camera.in_image(inside, 2.5)
    assert not camera.in_image(np.array([[10.0, np.nan]]))
    assert camera.in_image(np.zeros((0, 2)))


@pytest.mark.parametrize("name", ["fpv", "webcam"])
def test_normalize_is_the_rays_on_the_plane(name: str) -> None:
    camera = CameraModel.preset(name)
    w, h = camera.size
    uv = np.array([[0.0, 0.0], [w / 2, h / 2], [w - 1.0, 10.0], [37.5, h - 1.0]])
    rays = camera.pixel_rays(uv)
    np.testing.assert_allclose(camera.normalize(uv), rays[:, :2] / rays[:, 2:], rtol=1e-12)


@pytest.mark.parametrize("name", ["fpv", "webcam"])
def test_a_rigid_projection_is_the_projection_of_the_moved_points(name: str) -> None:
    from perchpose.geometry import rot_x, rot_z

    camera = CameraModel.preset(name)
    points = np.array([[-0.05, 0.05, 0.0], [0.05, 0.05, 0.0], [0.05, -0.05, 0.0], [0.0, 0.0, 0.0]])
    R = rot_z(0.4) @ rot_x(2.9)
    t = np.array([0.03, -0.02, 0.6])
    uv, duv_dq, s, in_front = camera.project_rigid_with_jacobian(points, R, t)
    np.testing.assert_allclose(s, points @ R.T, atol=1e-15)
    expected = camera.project_with_jacobian(points @ R.T + t)
    np.testing.assert_allclose(uv, expected[0], atol=1e-10)
    np.testing.assert_allclose(duv_dq, expected[1], rtol=1e-10, atol=1e-8)
    np.testing.assert_array_equal(in_front, expected[2])


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"fx": 1e300}, "fx = 1e+300 px is over 100 times"),
        ({"cx": 1e9}, "cx = 1e+09 px lies more than an image's size outside"),
        ({"k1": 1e300}, "distortion coefficient of 1e+300 is over 10000"),
        ({"fx": 1e-9}, "fx = 1e-09 px is under a pixel"),
        ({"fx": 4.0}, "fy / fx = 100, pixels over 10 times taller than wide"),
        ({"skew": 1e6}, "a skew of 1e+06 px is over fx (400 px)"),
    ],
)
def test_intrinsics_no_camera_has_are_refused(change: dict[str, float], message: str) -> None:
    K = np.array([[400.0, 0.0, 320.0], [0.0, 400.0, 240.0], [0.0, 0.0, 1.0]])
    dist = np.zeros(5)
    K[0, 0] = change.get("fx", K[0, 0])
    K[0, 2] = change.get("cx", K[0, 2])
    K[0, 1] = change.get("skew", 0.0)
    dist[0] = change.get("k1", 0.0)
    with pytest.raises(CameraFileError, match=re.escape(message)):
        CameraModel(K, dist, 640, 480)


def test_an_opencv_file_with_a_2x2_camera_matrix_is_named(tmp_path: Path) -> None:
    path = tmp_path / "cam.xml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", np.array([[400.0, 0.0], [0.0, 400.0]]))
    fs.write("distortion_coefficients", np.zeros((5, 1)))
    fs.release()
    with pytest.raises(CameraFileError, match=r"cam\.xml: camera_matrix must be 3 x 3, got 2 x 2"):
        CameraModel.load(path)


def test_a_camera_file_nested_too_deep_for_opencv_is_refused_before_it(tmp_path: Path) -> None:
    """OpenCV's FileStorage parser recurses per level and crashes the process on a file
    nested 100,000 deep (a segmentation fault): such a file is refused first, by name."""
    deep = tmp_path / "deep.xml"
    deep.write_text(
        '<?xml version="1.0"?>\n<opencv_storage>\n'
        + "<a>" * 100_000
        + "</a>" * 100_000
        + "\n</opencv_storage>\n"
    )
    with pytest.raises(CameraFileError, match=r"deep\.xml: nested over 64 levels deep"):
        CameraModel.load(deep)
    flow = tmp_path / "deep.yaml"
    flow.write_text("%YAML:1.0\n---\nimage_width: " + "[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(CameraFileError, match=r"deep\.yaml: nested over 64 levels deep"):
        CameraModel.load(flow)


def test_an_infinite_image_size_is_not_an_integer(tmp_path: Path) -> None:
    path = tmp_path / "inf.yaml"
    path.write_text(
        "image_width: .inf\nimage_height: 480\n"
        "camera_matrix: {rows: 3, cols: 3, data: [400, 0, 320, 0, 400, 240, 0, 0, 1]}\n"
        "distortion_coefficients: {rows: 1, cols: 5, data: [0, 0, 0, 0, 0]}\n"
    )
    with pytest.raises(CameraFileError, match="field 'image_width' is not an integer"):
        CameraModel.load(path)


def test_a_camera_replaced_with_other_coefficients_keeps_no_cache_of_the_original() -> None:
    """``dataclasses.replace`` builds a camera with its own cache: what the original worked
    out for its own coefficients (its largest distortion) is not read back for another's."""
    barrel = CameraModel(
        np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]),
        np.array([-0.2, 0.05, 0.0, 0.0, 0.0]),
        640,
        480,
    )
    first = barrel.max_distortion_px()
    straight = dataclasses.replace(barrel, dist=np.zeros(5))
    assert straight.max_distortion_px() < 1e-9 < first
