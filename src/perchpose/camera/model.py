"""Camera models: intrinsics, lens distortion, projection, and calibration file I/O.

Pixel convention is OpenCV's: the centre of the top-left pixel is (0, 0).
Two distortion models are supported:

- ``plumb_bob``: OpenCV's standard model with 4, 5, 8, 12 or 14 coefficients
  (ROS calls the 8-coefficient form ``rational_polynomial``);
- ``equidistant``: OpenCV's fisheye model, 4 coefficients (k1..k4), for wide FPV lenses.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from perchpose import safe_yaml
from perchpose.camera import plumb_bob
from perchpose.camera.lens import (
    EQUIDISTANT,
    PLUMB_BOB,
    Lens,
    all_within,
    equidistant_project_with_jacobian,
    equidistant_rays,
    lens_normalize,
    lens_project,
    lens_project_rigid_with_jacobian,
)
from perchpose.errors import CameraFileError, ImageError

Array = NDArray[np.float64]
DistortionModel = Literal["plumb_bob", "equidistant"]

_MODEL_ALIASES: dict[str, DistortionModel] = {
    "plumb_bob": "plumb_bob",
    "rational_polynomial": "plumb_bob",
    "radtan": "plumb_bob",
    "pinhole": "plumb_bob",
    "equidistant": "equidistant",
    "fisheye": "equidistant",
    "kannala_brandt": "equidistant",
}


@dataclass(frozen=True, eq=False)
class CameraModel:
    """A calibrated camera.

    K : (3, 3) float64 intrinsic matrix, pixels.
    dist : (N,) float64 distortion coefficients of ``model``.
    width_px, height_px : image size the calibration belongs to.
    """

    K: Array
    dist: Array
    width_px: int
    height_px: int
    model: DistortionModel = "plumb_bob"
    name: str = "camera"
    _cache: dict[str, Any] = field(default_factory=dict, init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise CameraFileError(f"camera {self.name!r}: K must be a finite 3x3 matrix")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0:
            raise CameraFileError(f"camera {self.name!r}: K needs fx > 0, fy > 0 and K[2,2] = 1")
        if self.model not in ("plumb_bob", "equidistant"):
            raise CameraFileError(f"camera {self.name!r}: unknown distortion model {self.model!r}")
        if self.model == "equidistant" and dist.size != 4:
            raise CameraFileError(
                f"camera {self.name!r}: equidistant needs 4 coefficients, got {dist.size}"
            )
        if self.model == "plumb_bob":
            if dist.size == 0:
                dist = np.zeros(5)
            if dist.size not in plumb_bob.LENGTHS:
                raise CameraFileError(
                    f"camera {self.name!r}: plumb_bob needs 4, 5, 8, 12 or 14 coefficients, "
                    f"got {dist.size}"
                )
        if not np.all(np.isfinite(dist)):
            raise CameraFileError(f"camera {self.name!r}: distortion coefficients are not finite")
        if self.width_px <= 0 or self.height_px <= 0:
            raise CameraFileError(f"camera {self.name!r}: image size must be positive")
        _check_plausible(K, dist, self.width_px, self.height_px, self.name)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)

    # ------------------------------------------------------------------ properties
    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels, OpenCV's order."""
        return (self.width_px, self.height_px)

    @property
    def focal_px(self) -> float:
        """Mean focal length in pixels."""
        return 0.5 * float(self.K[0, 0] + self.K[1, 1])

    def in_image(self, uv_px: Array, margin_px: float = 0.0) -> bool:
        """Whether all points ``uv_px`` (N, 2) lie in the image, ``margin_px`` from its
        border (pixel centres at 0 .. width - 1 and 0 .. height - 1)."""
        points = np.ascontiguousarray(np.asarray(uv_px, np.float64).reshape(-1, 2))
        return all_within(points, margin_px, self.width_px - 1 - margin_px,
                           self.height_px - 1 - margin_px)  # fmt: skip

    # ------------------------------------------------------------------ projection
    def project(self, points_camera_m: Array) -> tuple[Array, NDArray[np.bool_]]:
        """Project 3-D points of the camera frame to pixels.

        points_camera_m : (N, 3) float, metres, camera frame.
        Returns uv_px : (N, 2) float64 and in_front : (N,) bool. Points behind an ordinary
        camera (z <= 0) or beyond 180 deg field of view of a fisheye get ``in_front`` False.
        """
        p = np.ascontiguousarray(np.asarray(points_camera_m, dtype=np.float64).reshape(-1, 3))
        kind, K, coefficients = self.compiled_lens
        return lens_project(kind, p, K, coefficients)

    def project_with_jacobian(
        self, points_camera_m: Array
    ) -> tuple[Array, Array, NDArray[np.bool_]]:
        """``project``, and how each pixel moves with its point: ``duv_dq`` (N, 2, 3),
        d(u, v) / d(x, y, z) of the camera-frame point (rows of points not ``in_front`` are
        meaningless)."""
        p = np.ascontiguousarray(np.asarray(points_camera_m, dtype=np.float64).reshape(-1, 3))
        kind, K, coefficients = self.compiled_lens
        if kind == EQUIDISTANT:
            return equidistant_project_with_jacobian(p, K, coefficients)
        return plumb_bob.project_with_jacobian(p, K, coefficients)

    def project_rigid_with_jacobian(
        self, points_m: Array, R: Array, t_m: Array
    ) -> tuple[Array, Array, Array, NDArray[np.bool_]]:
        """``project_with_jacobian`` of the points ``R p + t`` (``points_m`` (N, 3) in their
        own frame), and the rotated points ``R p`` (N, 3) that a pose's Jacobian needs:
        (uv_px, duv_dq, R p, in_front)."""
        p = np.ascontiguousarray(points_m, np.float64)
        R = np.ascontiguousarray(R, np.float64)
        t = np.ascontiguousarray(t_m, np.float64).reshape(3)
        return lens_project_rigid_with_jacobian(self.compiled_lens, p, R, t)

    def normalize(self, uv_px: Array) -> Array:
        """Undistort pixels to normalised image coordinates (x/z, y/z).

        uv_px : (N, 2) float pixels. Returns (N, 2) float64.
        """
        uv = np.ascontiguousarray(np.asarray(uv_px, dtype=np.float64).reshape(-1, 2))
        kind, K, coefficients = self.compiled_lens
        return lens_normalize(kind, uv, K, coefficients)

    @property
    def compiled_lens(self) -> Lens:
        """The lens model as compiled code takes it (``lens_project``, ``lens_normalize``,
        ``lens_project_rigid_with_jacobian``)."""
        if self.model == "equidistant":
            return Lens(EQUIDISTANT, self.K, self.dist)
        cached = self._cache.get("plumb_bob")
        if cached is None:
            cached = self._cache["plumb_bob"] = plumb_bob.padded(self.dist)
        return Lens(PLUMB_BOB, self.K, np.asarray(cached, np.float64))

    def pixel_rays(self, uv_px: Array) -> Array:
        """Unit viewing rays (N, 3) in the camera frame for pixels (N, 2).

        For the equidistant model this also covers rays beyond 90 deg from the axis.
        """
        uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
        if self.model == "equidistant":
            return equidistant_rays(np.ascontiguousarray(uv), self.K, self.dist)
        xy = self.normalize(uv)
        rays = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
        return np.asarray(rays / np.linalg.norm(rays, axis=1, keepdims=True))

    def max_distortion_px(self) -> float:
        """Largest distance between a pixel and its pinhole position, over the image border."""
        cached = self._cache.get("max_distortion_px")
        if cached is not None:
            return float(cached)
        w, h = self.width_px, self.height_px
        edge = np.linspace(0.0, 1.0, 33)
        border = np.concatenate(
            [
                np.stack([edge * (w - 1), np.zeros_like(edge)], 1),
                np.stack([edge * (w - 1), np.full_like(edge, h - 1)], 1),
                np.stack([np.zeros_like(edge), edge * (h - 1)], 1),
                np.stack([np.full_like(edge, w - 1), edge * (h - 1)], 1),
            ]
        )
        rays = self.pixel_rays(border)
        ok = rays[:, 2] > 0.05
        pin = (self.K @ (rays[ok] / rays[ok, 2:3]).T).T[:, :2]
        value = float(np.max(np.linalg.norm(pin - border[ok], axis=1))) if np.any(ok) else math.inf
        if np.count_nonzero(ok) < border.shape[0]:
            value = math.inf
        self._cache["max_distortion_px"] = value
        return value

    # ------------------------------------------------------------------ checks
    def check_image(self, image: object, name: str = "image") -> NDArray[np.uint8]:
        """Return ``image`` as a grey, C-ordered, writable uint8 (H, W) array (a copy where it
        is not one), or raise ImageError naming ``name``.

        Accepts grey (H, W) or BGR (H, W, 3) / BGRA (H, W, 4) uint8 arrays whose size is the
        calibration's.
        """
        if not isinstance(image, np.ndarray):
            raise ImageError(f"{name}: expected a numpy array, got {type(image).__name__}")
        if image.dtype != np.uint8:
            raise ImageError(f"{name}: expected uint8 pixels, got {image.dtype}")
        if image.ndim == 3 and image.shape[2] in (3, 4):
            code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
            grey = cv2.cvtColor(image, code)
        elif image.ndim == 2:
            grey = image
        else:
            raise ImageError(f"{name}: expected a grey or BGR image, got shape {image.shape}")
        h, w = grey.shape
        if (w, h) != self.size:
            raise ImageError(
                f"{name}: image is {w}x{h} but camera {self.name!r} is calibrated for "
                f"{self.width_px}x{self.height_px}"
            )
        # the kernels are built for C-ordered, writable pixels: a read-only frame (a ROS
        # message's buffer) or a strided view would build another machine code mid-run
        return np.require(grey, np.uint8, ("C_CONTIGUOUS", "WRITEABLE"))

    # ------------------------------------------------------------------ presets
    @staticmethod
    def preset(name: str) -> CameraModel:
        """Synthetic cameras for tests and simulation.

        ``webcam``: 640x480 pinhole-like webcam, f = 554 px (60 deg horizontal), mild barrel.
        ``fpv``: 640x480 wide FPV lens like the paper's, equidistant, about 150 deg diagonal.
        ``fpv_wide``: 640x480 very wide FPV fisheye, equidistant, about 200 deg diagonal.
        """
        if name == "webcam":
            return CameraModel(
                K=np.array([[554.0, 0.0, 320.0], [0.0, 554.0, 240.0], [0.0, 0.0, 1.0]]),
                dist=np.array([-0.05, 0.08, 0.0, 0.0, 0.0]),
                width_px=640,
                height_px=480,
                model="plumb_bob",
                name="webcam",
            )
        if name == "fpv":
            return CameraModel(
                K=np.array([[300.0, 0.0, 322.0], [0.0, 300.0, 238.0], [0.0, 0.0, 1.0]]),
                dist=np.array([0.02, -0.01, 0.003, -0.0005]),
                width_px=640,
                height_px=480,
                model="equidistant",
                name="fpv",
            )
        if name == "fpv_wide":
            return CameraModel(
                K=np.array([[215.0, 0.0, 318.0], [0.0, 215.0, 243.0], [0.0, 0.0, 1.0]]),
                dist=np.array([0.03, -0.008, 0.002, -0.0003]),
                width_px=640,
                height_px=480,
                model="equidistant",
                name="fpv_wide",
            )
        raise CameraFileError(f"unknown camera preset {name!r} (choose webcam, fpv or fpv_wide)")

    # ------------------------------------------------------------------ file I/O
    @staticmethod
    def from_camera_info(data: dict[str, Any], where: str) -> CameraModel:
        """A camera from the fields of a ROS ``CameraInfo`` (``k``, ``d``,
        ``distortion_model``, ``width``, ``height``; either case), as a message or a
        camera_info YAML gives them; ``where`` names it in errors (``CameraFileError``)."""
        return _from_ros_mapping(data, Path(where))

    @staticmethod
    def load(path: str | Path) -> CameraModel:
        """Read a ROS camera_info YAML or an OpenCV FileStorage YAML/XML calibration."""
        p = Path(path)
        if not p.is_file():
            raise CameraFileError(f"{p}: camera file not found")
        try:
            text = p.read_text(encoding="utf-8", errors="replace")
        except OSError as exc:
            raise CameraFileError(f"{p}: cannot read camera file ({exc.strerror})") from exc
        if text.lstrip().startswith(("%YAML", "<?xml", "<opencv_storage")):
            _check_nesting(text, p)  # OpenCV's parser recurses per level: deep files crash it
            return _load_opencv_storage(p)
        try:
            data = safe_yaml.load(text)
        except yaml.YAMLError as exc:
            raise CameraFileError(f"{p}: not valid YAML ({_first_line(exc)})") from exc
        if not isinstance(data, dict):
            raise CameraFileError(f"{p}: expected a mapping of camera_info fields")
        return _from_ros_mapping(data, p)

    def to_ros_dict(self) -> dict[str, Any]:
        """The ROS camera_info YAML mapping of this camera."""
        P = np.zeros((3, 4))
        P[:3, :3] = self.K
        ros_model = (
            "equidistant"
            if self.model == "equidistant"
            else ("plumb_bob" if self.dist.size <= 5 else "rational_polynomial")
        )
        return {
            "image_width": self.width_px,
            "image_height": self.height_px,
            "camera_name": self.name,
            "camera_matrix": {"rows": 3, "cols": 3, "data": _floats(self.K)},
            "distortion_model": ros_model,
            "distortion_coefficients": {
                "rows": 1,
                "cols": int(self.dist.size),
                "data": _floats(self.dist),
            },
            "rectification_matrix": {"rows": 3, "cols": 3, "data": _floats(np.eye(3))},
            "projection_matrix": {"rows": 3, "cols": 4, "data": _floats(P)},
        }

    def save(self, path: str | Path) -> None:
        """Write this camera as ROS camera_info YAML."""
        try:
            Path(path).write_text(
                yaml.safe_dump(self.to_ros_dict(), sort_keys=False), encoding="utf-8"
            )
        except OSError as exc:
            raise CameraFileError(f"{path}: cannot write ({exc.strerror})") from exc


def _floats(a: Array) -> list[float]:
    return [float(v) for v in np.asarray(a).reshape(-1)]


MAX_FOCAL_PER_SIDE = 100.0  # fx, fy over the image's longer side: a 0.6 deg field of view
MAX_DISTORTION = 1e4  # no lens model's coefficient comes near this
MAX_ASPECT = 10.0  # fy / fx (or fx / fy): pixels no camera has
MAX_NESTING = 64  # levels of a camera file; a calibration has 2 or 3


def _check_plausible(K: Array, dist: Array, width: int, height: int, name: str) -> None:
    """Refuse intrinsics no camera has (they pass every other check and give garbage)."""
    side = max(width, height)
    for axis, f in (("fx", K[0, 0]), ("fy", K[1, 1])):
        if not f >= 1.0:
            raise CameraFileError(
                f"camera {name!r}: {axis} = {f:g} px is under a pixel: no lens focuses so short"
            )
        if not f <= MAX_FOCAL_PER_SIDE * side:
            raise CameraFileError(
                f"camera {name!r}: {axis} = {f:g} px is over {MAX_FOCAL_PER_SIDE:g} times the "
                f"image's {side} px: not a camera"
            )
    aspect = max(K[0, 0], K[1, 1]) / min(K[0, 0], K[1, 1])
    if aspect > MAX_ASPECT:
        raise CameraFileError(
            f"camera {name!r}: fy / fx = {K[1, 1] / K[0, 0]:g}, pixels over {MAX_ASPECT:g} times "
            "taller than wide (or wider than tall): not a camera"
        )
    if abs(K[0, 1]) > K[0, 0]:
        raise CameraFileError(
            f"camera {name!r}: a skew of {K[0, 1]:g} px is over fx ({K[0, 0]:g} px), more than a "
            "pixel sideways per pixel up: not a camera"
        )
    for axis, c, size in (("cx", K[0, 2], width), ("cy", K[1, 2], height)):
        if not -size <= c <= 2 * size:
            raise CameraFileError(
                f"camera {name!r}: {axis} = {c:g} px lies more than an image's size outside "
                f"the {width} x {height} image"
            )
    if np.abs(dist).max(initial=0.0) > MAX_DISTORTION:
        raise CameraFileError(
            f"camera {name!r}: a distortion coefficient of {np.abs(dist).max():g} is over "
            f"{MAX_DISTORTION:g}: not a lens"
        )


def _check_nesting(text: str, path: Path) -> None:
    """Refuse a FileStorage file nested deeper than ``MAX_NESTING`` (XML elements, YAML flow
    brackets or indentation steps), which OpenCV's recursive parser would crash on (a
    segmentation fault, not an exception) before perchpose could say a word."""
    depth = deepest = 0
    for m in re.finditer(r"<(/?)[A-Za-z_][^<>]*?(/?)>|[\[{]|[\]}]", text):
        token = m.group(0)
        if token in "[{":
            depth += 1
        elif token in "]}" or m.group(1):
            depth -= 1
        elif not m.group(2):
            depth += 1
        deepest = max(deepest, depth)
        if deepest > MAX_NESTING:
            break
    indents = {len(line) - len(line.lstrip(" ")) for line in text.splitlines() if line.strip()}
    if deepest > MAX_NESTING or len(indents) > MAX_NESTING:
        raise CameraFileError(
            f"{path}: nested over {MAX_NESTING} levels deep: not a camera calibration"
        )


def _first_line(exc: Exception) -> str:
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


def _matrix_field(data: dict[str, Any], keys: tuple[str, ...], path: Path) -> Array:
    for key in keys:
        if key in data:
            value = data[key]
            raw = value.get("data") if isinstance(value, dict) else value
            try:
                return np.asarray(raw, dtype=np.float64).reshape(-1)
            except (TypeError, ValueError) as exc:
                raise CameraFileError(f"{path}: field {key!r} is not a list of numbers") from exc
    raise CameraFileError(f"{path}: missing field {keys[0]!r}")


def _int_field(data: dict[str, Any], keys: tuple[str, ...], path: Path) -> int:
    for key in keys:
        if key in data:
            try:
                return int(data[key])
            except (TypeError, ValueError, OverflowError) as exc:
                raise CameraFileError(f"{path}: field {key!r} is not an integer") from exc
    raise CameraFileError(f"{path}: missing field {keys[0]!r}")


def _model_name(raw: object, path: Path) -> DistortionModel:
    name = str(raw).strip().lower()
    if name not in _MODEL_ALIASES:
        raise CameraFileError(f"{path}: unknown distortion_model {raw!r}")
    return _MODEL_ALIASES[name]


def _from_ros_mapping(data: dict[str, Any], path: Path) -> CameraModel:
    K = _matrix_field(data, ("camera_matrix", "K", "k"), path)
    if K.size != 9:
        raise CameraFileError(f"{path}: camera_matrix must have 9 numbers, got {K.size}")
    dist = _matrix_field(data, ("distortion_coefficients", "D", "d"), path)
    model = _model_name(data.get("distortion_model", "plumb_bob"), path)
    width = _int_field(data, ("image_width", "width"), path)
    height = _int_field(data, ("image_height", "height"), path)
    try:
        return CameraModel(
            K.reshape(3, 3), dist, width, height, model, str(data.get("camera_name", path.stem))
        )
    except CameraFileError as exc:
        raise CameraFileError(f"{path}: {exc}") from exc


def _load_opencv_storage(path: Path) -> CameraModel:
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:
        # OpenCV's parser reports malformed XML as cv2.error, which its Python binding can
        # surface wrapped in a SystemError
        raise CameraFileError(f"{path}: malformed OpenCV FileStorage file") from exc
    try:
        if not fs.isOpened():
            raise CameraFileError(f"{path}: not a readable OpenCV FileStorage file")

        def node(*names: str) -> Any:
            for n in names:
                nd = fs.getNode(n)
                if not nd.empty():
                    return nd
            raise CameraFileError(f"{path}: missing field {names[0]!r}")

        K = node("camera_matrix", "cameraMatrix", "K").mat()
        dist = node("distortion_coefficients", "dist_coeffs", "distCoeffs", "D").mat()
        if K is None or dist is None:
            raise CameraFileError(
                f"{path}: camera_matrix or distortion_coefficients is not a matrix"
            )
        if np.asarray(K).size != 9:
            raise CameraFileError(
                f"{path}: camera_matrix must be 3 x 3, got {' x '.join(map(str, K.shape))}"
            )
        width = _size_field(node("image_width", "width"), "image_width", path)
        height = _size_field(node("image_height", "height"), "image_height", path)
        model_node = fs.getNode("distortion_model")
        model = _model_name(model_node.string() if not model_node.empty() else "plumb_bob", path)
        try:
            return CameraModel(
                np.asarray(K, np.float64).reshape(3, 3),
                np.asarray(dist, np.float64).reshape(-1),
                width,
                height,
                model,
                path.stem,
            )
        except CameraFileError as exc:
            raise CameraFileError(f"{path}: {exc}") from exc
    except cv2.error as exc:
        raise CameraFileError(f"{path}: malformed OpenCV FileStorage file") from exc
    finally:
        fs.release()


def _size_field(node: Any, name: str, path: Path) -> int:
    """An image size in pixels from a FileStorage node: a whole number from 1 to 100000."""
    if not (node.isInt() or node.isReal()):
        raise CameraFileError(f"{path}: {name} is not a number")
    value = float(node.real())
    if not (math.isfinite(value) and value == int(value) and 0 < value <= 100_000):
        raise CameraFileError(f"{path}: {name} must be a whole number of pixels, got {value:g}")
    return int(value)
