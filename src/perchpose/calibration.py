"""Camera calibration with a ChArUco board: the board, its printable sheet, and ``calibrate``.

Board frame (OpenCV's): origin at the board's top-left corner as printed, x right, y down,
z into the board. For rendering, the board also offers a centred, y-up ``texture`` like a target.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel, DistortionModel
from perchpose.errors import CalibrationError, PerchposeError, SolverFailedError
from perchpose.target import aruco_dictionary

Array = NDArray[np.float64]

MIN_CORNERS_PER_VIEW = 6
MIN_VIEWS = {"plumb_bob": 3, "equidistant": 4}
GOOD_VIEWS = 10
GOOD_COVERAGE = 0.5


@dataclass(frozen=True)
class CharucoBoardSpec:
    """A ChArUco board: ``squares`` (columns, rows), square and marker sides in millimetres,
    OpenCV dictionary name.

    The default, 5x7 squares of 30 mm with 15 mm DICT_6X6_250 markers, prints at 100 % on A4
    and on Letter (a 170 x 260 mm sheet with its scale bar); it is OpenCV's tutorial board
    (5x7, 40 mm, 20 mm) at three quarters. Any scale calibrates the lens (the intrinsics do not
    depend on it); give the printed square's measured side so that board poses are true."""

    squares: tuple[int, int] = (5, 7)
    square_mm: float = 30.0
    marker_mm: float = 15.0
    dictionary: str = "DICT_6X6_250"
    margin_mm: float = 10.0

    def __post_init__(self) -> None:
        sx, sy = self.squares
        if sx < 2 or sy < 2:
            raise CalibrationError(f"a board needs at least 2x2 squares, got {sx}x{sy}")
        if not (self.square_mm > 0 and 0 < self.marker_mm < self.square_mm):
            raise CalibrationError(
                f"need 0 < marker ({self.marker_mm} mm) < square ({self.square_mm} mm)"
            )
        d = aruco_dictionary(self.dictionary)
        needed = (sx * sy) // 2
        if needed > int(d.bytesList.shape[0]):
            raise CalibrationError(
                f"a {sx}x{sy} board needs {needed} markers; {self.dictionary} has "
                f"{d.bytesList.shape[0]}"
            )

    @staticmethod
    def parse_squares(text: str) -> tuple[int, int]:
        """``"5x7"`` -> (5, 7)."""
        try:
            a, b = text.lower().split("x")
            return int(a), int(b)
        except ValueError as exc:
            raise CalibrationError(f"--squares must look like 5x7, got {text!r}") from exc

    @cached_property
    def cv_board(self) -> cv2.aruco.CharucoBoard:
        """OpenCV's board object, sizes in metres."""
        return cv2.aruco.CharucoBoard(
            self.squares,
            self.square_mm / 1000.0,
            self.marker_mm / 1000.0,
            aruco_dictionary(self.dictionary),
        )

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the squares area in metres."""
        return (
            self.squares[0] * self.square_mm / 1000.0,
            self.squares[1] * self.square_mm / 1000.0,
        )

    @property
    def sheet_half_extent_m(self) -> float:
        """Half side of a square centred on the board holding the board and its white margin."""
        return max(self.size_m) / 2.0 + self.margin_mm / 1000.0

    @cached_property
    def texture(self) -> tuple[NDArray[np.float32], float]:
        """Square float32 image centred on the board centre (x right, y up as printed),
        1 white, 0 black, -1 off the sheet; and its texel size in metres."""
        per_square = 128
        texel = self.square_mm / 1000.0 / per_square
        sx, sy = self.squares
        board = self.cv_board.generateImage(
            (sx * per_square, sy * per_square), marginSize=0, borderBits=1
        )
        n = 2 * math.ceil(self.sheet_half_extent_m / texel)
        tex = np.full((n, n), -1.0, np.float32)
        margin = int(round(self.margin_mm / 1000.0 / texel))
        h, w = board.shape
        r0 = n // 2 - h // 2
        c0 = n // 2 - w // 2
        tex[r0 - margin : r0 + h + margin, c0 - margin : c0 + w + margin] = 1.0
        tex[r0 : r0 + h, c0 : c0 + w] = (board > 127).astype(np.float32)
        return tex, texel

    def T_pattern_board(self) -> Array:
        """Maps OpenCV board points (origin top-left, y down) to the centred y-up pattern."""
        w, h = self.size_m
        T = np.diag([1.0, -1.0, -1.0, 1.0])
        T[0, 3] = -w / 2.0
        T[1, 3] = h / 2.0
        return T

    def describe(self) -> str:
        """One line naming the board's parameters."""
        return (
            f"ChArUco {self.squares[0]}x{self.squares[1]} squares of {self.square_mm:g} mm, "
            f"markers {self.marker_mm:g} mm, {self.dictionary}"
        )


# ------------------------------------------------------------------------- detection
@dataclass(frozen=True)
class BoardView:
    """The board found in one image: ChArUco corners (N, 2) px and their ids (N,)."""

    name: str
    corners_px: Array
    ids: NDArray[np.int32]
    markers: int


# a board with corners missing is searched again in the image enlarged these many times:
# OpenCV's marker search reads small markers (a pixel or two a bit) far better there
UPSCALES = (2, 4)


def _small_marker_parameters() -> cv2.aruco.DetectorParameters:
    """Marker search settings for the enlarged images, where a bit spans a pixel or two of
    the original: each cell is read from 8 px of the rectified marker instead of 4, only its
    middle 40 % instead of 74 % (blur mixes the neighbours into the rest), and a code is
    accepted up to the dictionary's whole correcting distance. On 90 rendered views of boards
    80-130 px across (fpv lens) that finds 2.3 times the ChArUco corners of the defaults;
    a misread marker's corners are caught by the board's own consistency checks and, failing
    those, by the per-view outlier rule of the calibration."""
    parameters = cv2.aruco.DetectorParameters()
    parameters.perspectiveRemovePixelPerCell = 8
    parameters.perspectiveRemoveIgnoredMarginPerCell = 0.3
    parameters.errorCorrectionRate = 1.0
    return parameters


def detect_board(board: CharucoBoardSpec, image: NDArray[np.uint8], name: str) -> BoardView | str:
    """The board's ChArUco corners in ``image``, or a string saying why there are none.

    While corners are missing the image is searched again enlarged (bicubic, ``UPSCALES``)
    and the search that gives the most corners wins; its corners are mapped back to the
    image's pixels."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    found = _detect_board_at(board, grey, name, 1)
    all_corners = (board.squares[0] - 1) * (board.squares[1] - 1)
    for scale in UPSCALES:
        if isinstance(found, BoardView) and found.ids.size == all_corners:
            break
        enlarged = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
        again = _detect_board_at(board, enlarged, name, scale)
        if isinstance(again, BoardView) and (
            isinstance(found, str) or again.ids.size > found.ids.size
        ):
            found = again
    return found


def _detect_board_at(
    board: CharucoBoardSpec,
    grey: NDArray[np.integer[Any] | np.floating[Any]],
    name: str,
    scale: int,
) -> BoardView | str:
    """``detect_board`` on an image enlarged ``scale`` times; corners in the original's px."""
    detector = (
        cv2.aruco.CharucoDetector(board.cv_board)
        if scale == 1
        else cv2.aruco.CharucoDetector(
            board.cv_board, cv2.aruco.CharucoParameters(), _small_marker_parameters()
        )
    )
    corners, ids, _marker_corners, marker_ids = detector.detectBoard(grey)
    n_markers = 0 if marker_ids is None else len(marker_ids)
    if n_markers == 0:
        return "no board markers found"
    if ids is None or len(ids) < MIN_CORNERS_PER_VIEW:
        found = 0 if ids is None else len(ids)
        return f"{n_markers} markers but only {found} ChArUco corners (need {MIN_CORNERS_PER_VIEW})"
    # pixel centres: x in the enlarged image is (x + 0.5) * scale - 0.5 in this one
    corners = (np.asarray(corners, np.float64).reshape(-1, 2) + 0.5) / scale - 0.5
    ids = np.asarray(ids, np.int32).reshape(-1)
    if board.cv_board.checkCharucoCornersCollinear(ids):
        return "ChArUco corners are collinear"
    return BoardView(name, corners, ids, n_markers)


def _homography_residual_px(board: CharucoBoardSpec, view: BoardView) -> float:
    """RMS residual of a homography from board to image (large when the board parameters do
    not match the printed board, or the lens is strongly distorted)."""
    obj = np.asarray(board.cv_board.getChessboardCorners(), np.float64)[view.ids][:, :2]
    H, _ = cv2.findHomography(obj, view.corners_px, 0)
    if H is None:
        return math.inf
    p = np.concatenate([obj, np.ones((obj.shape[0], 1))], 1) @ H.T
    uv = p[:, :2] / p[:, 2:3]
    return float(np.sqrt(np.mean(np.sum((uv - view.corners_px) ** 2, axis=1))))


# ------------------------------------------------------------------------- calibration
@dataclass(frozen=True)
class CalibrationResult:
    """A calibration and how it was made.

    per_view_rms_px : view name -> RMS reprojection error of its corners.
    rejected : view name -> why it was not used.
    coverage : fraction of a 10x10 grid of image cells holding at least one used corner.
    warnings : reasons not to trust the result.
    corners_left_out : view name -> how many of its corners were left out of the fit as
    strays (``stray_corners``).
    """

    camera: CameraModel
    rms_px: float
    per_view_rms_px: dict[str, float]
    used: tuple[str, ...]
    rejected: dict[str, str]
    coverage: float
    corners_px: Array = field(repr=False)
    warnings: tuple[str, ...] = ()
    corners_left_out: dict[str, int] = field(default_factory=dict)


def coverage_grid(corners_px: Array, size: tuple[int, int], cells: int = 10) -> NDArray[np.int64]:
    """(cells, cells) count of corners per image cell."""
    w, h = size
    grid = np.zeros((cells, cells), np.int64)
    if corners_px.size == 0:
        return grid
    cx = np.clip((corners_px[:, 0] / w * cells).astype(int), 0, cells - 1)
    cy = np.clip((corners_px[:, 1] / h * cells).astype(int), 0, cells - 1)
    np.add.at(grid, (cy, cx), 1)
    return grid


def _collect_views(
    images: Iterable[tuple[str, NDArray[np.uint8]]], board: CharucoBoardSpec
) -> tuple[list[BoardView], dict[str, str], tuple[int, int], bool]:
    """The views that show the board, the others with the reason, the image size, and whether
    any image showed a marker of the board's dictionary. Raises CalibrationError for images of
    different sizes or none at all."""
    views: list[BoardView] = []
    rejected: dict[str, str] = {}
    size: tuple[int, int] | None = None
    size_from = ""
    saw_markers = False
    for view_name, image in images:
        h, w = image.shape[:2]
        if size is None:
            size, size_from = (w, h), view_name
        elif (w, h) != size:
            raise CalibrationError(
                f"{view_name}: image is {w}x{h} but {size_from} is {size[0]}x{size[1]}; "
                "all views must come from one camera mode"
            )
        found = detect_board(board, image, view_name)
        if isinstance(found, str):
            rejected[view_name] = found
            saw_markers |= not found.startswith("no board")
            continue
        saw_markers = True
        views.append(found)
    if size is None:
        raise CalibrationError("no images to calibrate from")
    return views, rejected, size, saw_markers


def check_model(model: str) -> None:
    """Raises CalibrationError unless ``model`` is one the calibration solves."""
    if model not in MIN_VIEWS:
        raise CalibrationError(f"unknown model {model!r} (plumb_bob or equidistant)")


def calibrate(
    images: Iterable[tuple[str, NDArray[np.uint8]]],
    board: CharucoBoardSpec,
    model: DistortionModel = "plumb_bob",
    name: str = "camera",
) -> CalibrationResult:
    """Calibrate from (name, image) pairs showing ``board``.

    Views where the board is missing, has fewer than 6 corners, collinear corners, or corners
    that no board of these parameters could give are rejected with a reason; so are views on
    which the solver stops (ill-conditioned) and views whose reprojection error stands out
    (``calibrate_views``). Raises CalibrationError when images differ in size, when no image
    shows the board, or when fewer views than the model needs remain.
    """
    check_model(model)
    views, rejected, size, saw_markers = _collect_views(images, board)
    if not saw_markers:
        raise CalibrationError(
            f"no marker of {board.dictionary} found in any of the {len(rejected)} images: "
            "check --dictionary"
        )
    if not views:
        raise CalibrationError(
            f"markers of {board.dictionary} were found but no view gave {MIN_CORNERS_PER_VIEW} "
            f"consistent ChArUco corners: check --squares, --square-mm and --marker-mm "
            f"(now {board.describe()})"
        )
    return calibrate_views(views, board, size, model, name, rejected)


def calibrate_views(
    views: list[BoardView],
    board: CharucoBoardSpec,
    size: tuple[int, int],
    model: DistortionModel = "plumb_bob",
    name: str = "camera",
    rejected: dict[str, str] | None = None,
) -> CalibrationResult:
    """Calibrate from board views already found in images of ``size`` (width, height) px.

    When the solver stops on a view (ill-conditioned) or a view's reprojection error stands
    out from the others' (``outlier_views``), the view whose removal mends it is found by
    solving without each suspect in turn, dropped with the reason in ``rejected`` (which also
    holds the views rejected before, by name), and the rest solved again. Raises
    CalibrationError when fewer views than the model needs are left, or when the solver
    fails on every set without one view."""
    check_model(model)
    rejected = {} if rejected is None else dict(rejected)
    needed = MIN_VIEWS[model]
    if len(views) < needed:
        raise CalibrationError(
            f"only {len(views)} usable views; the {model} model needs at least {needed} "
            f"(rejected: {'; '.join(f'{k}: {v}' for k, v in rejected.items()) or 'none'})"
        )
    views, solution = _solve_without_bad_views(views, board, size, model, name, rejected)
    views, solution, lost = _without_stray_corners(views, solution, board, size, model, name)
    camera, per_view, rms, _errors = solution
    all_corners = np.concatenate([v.corners_px for v in views])
    grid = coverage_grid(all_corners, size)
    coverage = float(np.count_nonzero(grid) / grid.size)
    warnings = []
    if len(views) < GOOD_VIEWS:
        warnings.append(f"only {len(views)} views: use {GOOD_VIEWS} or more, tilted and spread")
    if coverage < GOOD_COVERAGE:
        warnings.append(
            f"corners cover {coverage:.0%} of the image: move the board into the corners and "
            "edges, or the distortion there is a guess"
        )
    mismatched = [v.name for v in views if _homography_residual_px(board, v) > 25.0]
    if mismatched and model == "plumb_bob" and len(mismatched) == len(views):
        warnings.append("no view fits a plane well: is the board flat, and the lens a fisheye?")
    return CalibrationResult(
        camera,
        rms,
        per_view,
        tuple(v.name for v in views),
        rejected,
        coverage,
        all_corners,
        tuple(warnings),
        lost,
    )


# a view whose corners reproject this many times worse than the median view's, and worse than
# OUTLIER_FLOOR_PX, does not fit the model: wrong ids, motion blur, a bent board, or a pose
# that the solver could not find
OUTLIER_FACTOR = 5.0
OUTLIER_FLOOR_PX = 1.0

# a corner whose reprojection error is over STRAY_FACTOR times the corners' typical error (per
# axis, from their median) and over STRAY_FLOOR_PX is left out of the fit: on a board seen
# steeply, the corner finder's window takes in the neighbouring squares and pulls a corner by
# up to a pixel while the others sit within a tenth of one
STRAY_FACTOR = 5.0
STRAY_FLOOR_PX = 0.3
STRAY_ROUNDS = 8
# the median of the length of a 2D error with sigma per axis is sigma * sqrt(2 ln 2)
_RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))


class Solution(NamedTuple):
    """One solve: the camera, each view's RMS error, the RMS over all corners (px), and each
    view's corners' reprojection errors (px, in the view's corner order)."""

    camera: CameraModel
    per_view_rms_px: dict[str, float]
    rms_px: float
    errors_px: dict[str, Array]


def outlier_views(per_view_rms_px: dict[str, float]) -> list[str]:
    """Names of the views whose RMS error stands out from the median view's, worst first."""
    limit = max(OUTLIER_FLOOR_PX, OUTLIER_FACTOR * _median_view_rms_px(per_view_rms_px))
    bad = [view for view, e in per_view_rms_px.items() if not e <= limit]
    return sorted(bad, key=lambda view: -per_view_rms_px[view])


def _median_view_rms_px(per_view_rms_px: dict[str, float]) -> float:
    """The median of the views' finite RMS errors (0 when none is finite)."""
    return float(np.median([e for e in per_view_rms_px.values() if math.isfinite(e)] or [0.0]))


def _solve_without_bad_views(
    views: list[BoardView],
    board: CharucoBoardSpec,
    size: tuple[int, int],
    model: DistortionModel,
    name: str,
    rejected: dict[str, str],
) -> tuple[list[BoardView], Solution]:
    """Solve, and while the solver fails or views stand out (``outlier_views``), drop the one
    view whose removal mends it best (among all views when the solver failed, among those
    standing out otherwise) and solve again; then offer each dropped view back to the final
    fit (a view can look bad only because the fit it was judged by was wrong). The views left
    out are named in ``rejected`` with why. Stops dropping when the model's minimum number of
    views would not remain; raises CalibrationError when the solver fails on every set of
    views it may try."""
    needed = MIN_VIEWS[model]
    kept = list(views)
    dropped: dict[str, tuple[BoardView, str]] = {}
    while True:
        solution, failure = _try_solve(kept, board, size, model, name)
        if solution is not None:
            suspects = outlier_views(solution[1])
            if not suspects:
                break
        else:
            suspects = [v.name for v in kept]
        mend = (
            _best_removal(kept, suspects, board, size, model, name) if len(kept) > needed else None
        )
        if mend is None:
            if solution is not None:
                break  # the views that stand out stay: too few would be left, or none mends it
            raise CalibrationError(
                f"{failure} on these {len(kept)} views and on every set without one of them: "
                "add views with the board nearer the image centre and tilted less"
            )
        view = next(v for v in kept if v.name == mend)
        dropped[mend] = (view, _why_dropped(view, solution, failure))
        kept = [v for v in kept if v.name != mend]
    for view_name, (view, _why) in list(dropped.items()):
        trial, _ = _try_solve([*kept, view], board, size, model, name)
        if trial is not None and not outlier_views(trial[1]):
            kept.append(view)
            del dropped[view_name]
            solution = trial
    rejected.update({view_name: why for view_name, (_view, why) in dropped.items()})
    order = [v.name for v in views]
    kept.sort(key=lambda v: order.index(v.name))
    per_view = {v.name: solution.per_view_rms_px[v.name] for v in kept}
    return kept, solution._replace(per_view_rms_px=per_view)


def _try_solve(
    views: list[BoardView],
    board: CharucoBoardSpec,
    size: tuple[int, int],
    model: DistortionModel,
    name: str,
) -> tuple[Solution | None, str]:
    """``_solve``, or None and what the solver said when it stopped."""
    try:
        return _solve(views, board, size, model, name), ""
    except SolverFailedError as exc:
        return None, str(exc)


def _why_dropped(view: BoardView, solution: Solution | None, failure: str) -> str:
    """The report's line for a view left out of the fit."""
    if solution is None:
        return f"{failure} with this view and not without it (ill-conditioned): dropped"
    per_view = solution[1]
    if math.isfinite(per_view[view.name]):
        return (
            f"reprojection error {per_view[view.name]:.2f} px against a median view's "
            f"{_median_view_rms_px(per_view):.2f} px: dropped"
        )
    return f"no pose of the board fits its {view.ids.size} corners: dropped"


def _best_removal(
    views: list[BoardView],
    suspects: list[str],
    board: CharucoBoardSpec,
    size: tuple[int, int],
    model: DistortionModel,
    name: str,
) -> str | None:
    """Of the ``suspects``, the view without which the solver succeeds with the lowest RMS
    error; None when it fails without each of them."""
    best: tuple[float, str] | None = None
    for suspect in suspects:
        solution, _ = _try_solve([v for v in views if v.name != suspect], board, size, model, name)
        if solution is not None and (best is None or solution[2] < best[0]):
            best = (solution[2], suspect)
    return None if best is None else best[1]


def equidistant_focal_guess_px(
    views: list[BoardView], board: CharucoBoardSpec, size: tuple[int, int]
) -> float:
    """A first focal length (px) for the equidistant model, so that the fisheye solver starts
    near the answer (from a guess far off, it fails on views near the edge of a wide lens).

    For each trial focal length the views' corners are unprojected with the principal point at
    the image centre and no distortion (angle from the axis = radius / f), a homography from
    the board is fitted to each, and its points are projected back: the focal length whose
    planes reproject best over all views wins (a log grid, then a finer one around the best).
    A view that no trial focal length makes a plane of has no say; with none left, the guess
    is a third of the image width, OpenCV's usual start.
    """
    obj_all = np.asarray(board.cv_board.getChessboardCorners(), np.float64)[:, :2]
    centre = np.array([size[0] / 2.0, size[1] / 2.0])
    diagonal = math.hypot(*size)
    grid = np.geomspace(diagonal / 20.0, diagonal * 2.0, 48)
    table = np.array([[_plane_misfit_px2(v, obj_all, centre, f) for f in grid] for v in views])
    heard = [k for k in range(len(views)) if np.any(np.isfinite(table[k]))]
    total = table[heard].sum(axis=0) if heard else np.full(grid.size, math.inf)
    if not np.any(np.isfinite(total)):
        return size[0] / 3.0
    best = float(grid[int(np.argmin(total))])
    fine = np.geomspace(best / 1.1, best * 1.1, 21)
    fine_total = [sum(_plane_misfit_px2(views[k], obj_all, centre, f) for k in heard) for f in fine]
    return float(fine[int(np.argmin(fine_total))])


def _plane_misfit_px2(view: BoardView, obj_xy: Array, centre_px: Array, f_px: float) -> float:
    """Sum of squared px by which ``view``'s corners miss the best plane through them, for an
    undistorted equidistant lens of focal length ``f_px`` centred at ``centre_px``; inf when
    no plane in front of such a lens can show them."""
    d = view.corners_px - centre_px
    r = np.linalg.norm(d, axis=1)
    theta = r / f_px
    if np.any(theta > math.radians(85.0)):
        return math.inf  # a plane in front of the lens cannot reach so far out
    scale = np.divide(np.tan(theta), r, out=np.full_like(r, 1.0 / f_px), where=r > 0)
    H, _ = cv2.findHomography(obj_xy[view.ids], d * scale[:, None], 0)
    if H is None:
        return math.inf
    q = np.concatenate([obj_xy[view.ids], np.ones((view.ids.size, 1))], 1) @ H.T
    if not (np.all(q[:, 2] > 1e-12) or np.all(q[:, 2] < -1e-12)):
        return math.inf  # the plane would pass through the lens
    m = q[:, :2] / q[:, 2:3]
    rm = np.linalg.norm(m, axis=1)
    back = np.divide(np.arctan(rm) * f_px, rm, out=np.full_like(rm, f_px), where=rm > 0)
    total = float(np.sum((m * back[:, None] - d) ** 2))
    return total if math.isfinite(total) else math.inf


def _solve(
    views: list[BoardView],
    board: CharucoBoardSpec,
    size: tuple[int, int],
    model: DistortionModel,
    name: str,
) -> Solution:
    """One solve over ``views``; raises SolverFailedError when OpenCV's solver stops."""
    obj_all = np.asarray(board.cv_board.getChessboardCorners(), np.float64)
    obj = [obj_all[v.ids] for v in views]
    img = [v.corners_px for v in views]
    w, h = size
    if model == "plumb_bob":
        try:
            _, K, dist, rvecs, tvecs = cv2.calibrateCamera(
                [o.astype(np.float32) for o in obj],
                [i.astype(np.float32) for i in img],
                size,
                None,
                None,
                flags=0,
            )
        except cv2.error as exc:
            raise SolverFailedError("the pinhole solver stops") from exc
        dist = np.asarray(dist, np.float64).reshape(-1)[:5]
    else:
        flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW | cv2.CALIB_USE_INTRINSIC_GUESS
        f0 = equidistant_focal_guess_px(views, board, size)
        K0 = np.array([[f0, 0, w / 2.0], [0, f0, h / 2.0], [0, 0, 1.0]])
        criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-10)
        try:
            _, K, dist, rvecs, tvecs = cv2.fisheye.calibrate(
                [o.reshape(1, -1, 3) for o in obj],
                [i.reshape(1, -1, 2) for i in img],
                size,
                K0,
                np.zeros(4),
                flags=flags,
                criteria=criteria,
            )
        except cv2.error as exc:
            raise SolverFailedError("the fisheye solver stops") from exc
        dist = np.asarray(dist, np.float64).reshape(-1)
    try:
        camera = CameraModel(np.asarray(K, np.float64), dist, w, h, model, name)
    except PerchposeError as exc:
        raise SolverFailedError(f"the solver gives no valid camera ({exc})") from exc
    per_view = {}
    errors = {}
    for v, o, rvec, tvec in zip(views, obj, rvecs, tvecs, strict=True):
        R, _ = cv2.Rodrigues(np.asarray(rvec, np.float64))
        uv, ok = camera.project((R @ o.T).T + np.asarray(tvec, np.float64).reshape(3))
        e = np.where(ok, np.linalg.norm(uv - v.corners_px, axis=1), math.inf)
        errors[v.name] = e
        per_view[v.name] = float(np.sqrt(np.mean(e**2)))
    rms_all = float(np.sqrt(np.mean(np.concatenate(list(errors.values())) ** 2)))
    return Solution(camera, per_view, rms_all, errors)


def stray_corners(errors_px: dict[str, Array]) -> dict[str, NDArray[np.bool_]]:
    """Per view, its worst corner when its reprojection error stands out from all corners'
    typical error (``STRAY_FACTOR``, ``STRAY_FLOOR_PX``); only views with such a corner."""
    finite = [e[np.isfinite(e)] for e in errors_px.values()]
    typical = float(np.median(np.concatenate(finite))) if finite else 0.0
    limit = max(STRAY_FLOOR_PX, STRAY_FACTOR * typical / _RAYLEIGH_MEDIAN)
    stray = {}
    for name, e in errors_px.items():
        # the worst one only: a stray bends its view's pose and with it its neighbours'
        # errors, which the next round judges on a fit without it
        worst = int(np.argmax(np.where(np.isfinite(e), e, np.inf))) if e.size else 0
        if e.size and not e[worst] <= limit:
            out = np.zeros(e.shape, np.bool_)
            out[worst] = True
            stray[name] = out
    return stray


def _without_stray_corners(
    views: list[BoardView],
    solution: Solution,
    board: CharucoBoardSpec,
    size: tuple[int, int],
    model: DistortionModel,
    name: str,
) -> tuple[list[BoardView], Solution, dict[str, int]]:
    """Leave the corner that stands out most in each view (``stray_corners``) out and solve
    again, for up to ``STRAY_ROUNDS`` rounds; a view keeps at least
    ``MIN_CORNERS_PER_VIEW`` corners, and a solve that fails keeps the last one. Returns the
    views, the solution and how many corners each view lost."""
    lost: dict[str, int] = {}
    for _ in range(STRAY_ROUNDS):
        stray = stray_corners(solution.errors_px)
        trimmed = []
        lost_now: dict[str, int] = {}
        for view in views:
            out = stray.get(view.name)
            if out is None or out.size - int(np.count_nonzero(out)) < MIN_CORNERS_PER_VIEW:
                trimmed.append(view)
                continue
            keep = ~out
            trimmed.append(replace(view, corners_px=view.corners_px[keep], ids=view.ids[keep]))
            lost_now[view.name] = int(np.count_nonzero(out))
        if not lost_now:  # no strays, or none a view can spare
            break
        again, _ = _try_solve(trimmed, board, size, model, name)
        if again is None:
            break
        views, solution = trimmed, again
        for view_name, n in lost_now.items():
            lost[view_name] = lost.get(view_name, 0) + n
    return views, solution, lost


# two views whose common board corners lie this far apart at the median (a fraction of the
# image diagonal: about 16 px at 640x480) or closer show the board in the same pose
SAME_VIEW_FRACTION = 0.02


def view_distance(a: BoardView, b: BoardView, diagonal_px: float) -> float:
    """How far apart two views put the board: the median distance between the corners both
    saw, over the image diagonal (1 when they share none). It grows with the board's move,
    its scale and its tilt alike."""
    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    if common.size == 0:
        return 1.0
    moved = np.linalg.norm(a.corners_px[ia] - b.corners_px[ib], axis=1)
    return float(np.median(moved)) / diagonal_px


def select_views(
    frames: Iterable[tuple[str, NDArray[np.uint8]]],
    board: CharucoBoardSpec,
    max_views: int = 30,
    stride: int = 1,
) -> tuple[list[tuple[str, NDArray[np.uint8]]], int]:
    """Pick sharp, distinct views of the board from a video's frames.

    Every ``stride``-th frame is searched; frames with the board whose sharpness (variance of
    the Laplacian over the board) is at least half the median are candidates; from them, the
    sharpest first, then repeatedly the one farthest (``view_distance``) from those already
    picked, while it differs from all of them by more than ``SAME_VIEW_FRACTION``: a video
    that holds the board still gives one view, not many copies of it. Returns the views and
    how many frames were searched.
    """
    candidates: list[tuple[str, NDArray[np.uint8], BoardView, float]] = []
    searched = 0
    diagonal = 1.0
    for k, (name, image) in enumerate(frames):
        if k % max(1, stride):
            continue
        searched += 1
        view = detect_board(board, image, name)
        if isinstance(view, str):
            continue
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        diagonal = math.hypot(*grey.shape)
        x0, y0 = np.floor(view.corners_px.min(axis=0)).astype(int)
        x1, y1 = np.ceil(view.corners_px.max(axis=0)).astype(int)
        patch = grey[max(0, y0) : y1 + 1, max(0, x0) : x1 + 1]
        sharpness = float(cv2.Laplacian(patch, cv2.CV_64F).var()) if patch.size else 0.0
        candidates.append((name, image, view, sharpness))
    if not candidates:
        return [], searched
    floor = 0.5 * float(np.median([c[3] for c in candidates]))
    pool = [c for c in candidates if c[3] >= floor]
    picked = [max(pool, key=lambda c: c[3])]
    nearest = {id(c): view_distance(c[2], picked[0][2], diagonal) for c in pool}
    while len(picked) < max_views:
        best = max(
            (c for c in pool if all(c is not p for p in picked)),
            key=lambda c: nearest[id(c)],
            default=None,
        )
        if best is None or nearest[id(best)] <= SAME_VIEW_FRACTION:
            break
        picked.append(best)
        for c in pool:
            nearest[id(c)] = min(nearest[id(c)], view_distance(c[2], best[2], diagonal))
    return [(c[0], c[1]) for c in picked], searched
