"""Nested-marker targets: specification, presets, geometry and albedo.

Target frame: origin at the common centre of the markers, x to the right and y up as printed
(looking at the printed face), z out of the printed face. A marker's corners are listed in
OpenCV's ArUco order as printed: top-left, top-right, bottom-right, bottom-left.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml
from numpy.typing import NDArray

from perchpose import safe_yaml
from perchpose.errors import TargetSpecError
from perchpose.geometry import invert_transform, make_transform, rot_z

if TYPE_CHECKING:
    import cv2

Array = NDArray[np.float64]


def aruco_dictionary(name: str) -> cv2.aruco.Dictionary:
    """OpenCV's predefined dictionary called ``name`` (e.g. ``DICT_4X4_1000``); OpenCV is
    imported here, so that a vehicle link can hold a target without loading it."""
    import cv2

    code = getattr(cv2.aruco, name, None) if name.startswith("DICT_") else None
    if not isinstance(code, int):
        raise TargetSpecError(f"unknown ArUco dictionary {name!r}")
    return cv2.aruco.getPredefinedDictionary(code)


MAX_SIDE_MM = 10_000.0  # a marker's side, and its centre's offset: 10 m is no print


@dataclass(frozen=True)
class MarkerSpec:
    """One square marker of a target.

    dictionary : OpenCV dictionary name, e.g. ``DICT_ARUCO_ORIGINAL``.
    marker_id : id within that dictionary.
    side_mm : outer side of the marker's black border, millimetres.
    centre_mm : (x, y) of the marker centre in the target frame, millimetres.
    rotation_deg : rotation of the marker about the target's z axis, counter-clockwise as printed.
    """

    dictionary: str
    marker_id: int
    side_mm: float
    centre_mm: tuple[float, float] = (0.0, 0.0)
    rotation_deg: float = 0.0

    def __post_init__(self) -> None:
        d = aruco_dictionary(self.dictionary)
        n_ids = int(d.bytesList.shape[0])
        if not 0 <= self.marker_id < n_ids:
            raise TargetSpecError(
                f"marker id {self.marker_id} is not in {self.dictionary} (ids 0-{n_ids - 1})"
            )
        if not (math.isfinite(self.side_mm) and self.side_mm > 0):
            raise TargetSpecError(f"marker {self.label}: side_mm must be positive")
        if self.side_mm > MAX_SIDE_MM:
            raise TargetSpecError(
                f"marker {self.label}: side_mm {self.side_mm:g} is over {MAX_SIDE_MM:g} mm "
                "(10 m): not a print"
            )
        if not all(math.isfinite(c) for c in self.centre_mm) or not math.isfinite(
            self.rotation_deg
        ):
            raise TargetSpecError(f"marker {self.label}: centre and rotation must be finite")
        if max(abs(c) for c in self.centre_mm) > MAX_SIDE_MM:
            raise TargetSpecError(
                f"marker {self.label}: a centre over {MAX_SIDE_MM:g} mm from the target's: "
                "not a print"
            )

    @property
    def label(self) -> str:
        """Short name, e.g. ``DICT_4X4_1000:997``."""
        return f"{self.dictionary}:{self.marker_id}"

    @property
    def side_m(self) -> float:
        """Side in metres."""
        return self.side_mm / 1000.0

    @cached_property
    def cells(self) -> NDArray[np.uint8]:
        """(n+2, n+2) uint8, 1 = white, 0 = black; row 0 is the top as printed; border included."""
        d = aruco_dictionary(self.dictionary)
        n = int(d.markerSize) + 2
        img = d.generateImageMarker(self.marker_id, n, borderBits=1)
        return np.asarray(img > 127, dtype=np.uint8)

    @cached_property
    def T_target_marker(self) -> Array:
        """(4, 4) pose of the marker frame (centre, x right, y up, z out) in the target frame."""
        t = np.array([self.centre_mm[0] / 1000.0, self.centre_mm[1] / 1000.0, 0.0])
        return make_transform(rot_z(math.radians(self.rotation_deg)), t)

    @cached_property
    def T_marker_target(self) -> Array:
        """(4, 4) the inverse of ``T_target_marker``."""
        return invert_transform(self.T_target_marker)

    @cached_property
    def corners_marker_m(self) -> Array:
        """(4, 3) corners in the marker frame, metres, ArUco order (IPPE_SQUARE's order)."""
        h = self.side_m / 2.0
        return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])

    @cached_property
    def corners_target_m(self) -> Array:
        """(4, 3) corners in the target frame, metres, ArUco order as printed."""
        T = self.T_target_marker
        return np.asarray((T[:3, :3] @ self.corners_marker_m.T).T + T[:3, 3])

    def to_dict(self) -> dict[str, Any]:
        """The YAML mapping of this marker."""
        return {
            "dictionary": self.dictionary,
            "id": self.marker_id,
            "side_mm": float(self.side_mm),
            "centre_mm": [float(self.centre_mm[0]), float(self.centre_mm[1])],
            "rotation_deg": float(self.rotation_deg),
        }


def _check_nesting(big: MarkerSpec, small: MarkerSpec, target: str) -> None:
    """A smaller marker lies wholly outside a larger one, or wholly on its white cells (as the
    paper's 25 mm marker sits on the white centre of the 150 mm one); anything else prints
    over the larger marker's border or data and neither can be read."""
    u = np.linspace(-0.499, 0.499, 25) * small.side_m
    gx, gy = np.meshgrid(u, u)
    points = small.T_target_marker @ np.stack(
        [gx.ravel(), gy.ravel(), np.zeros(gx.size), np.ones(gx.size)]
    )
    local = invert_transform(big.T_target_marker) @ points
    n = big.cells.shape[0]
    col = np.floor(local[0] / big.side_m * n + n / 2).astype(int)
    row = np.floor(n / 2 - local[1] / big.side_m * n).astype(int)
    inside = (col >= 0) & (col < n) & (row >= 0) & (row < n)
    if not inside.any():
        return
    where = f"target {target!r}: marker {small.label} ({small.side_mm:g} mm)"
    if not inside.all():
        raise TargetSpecError(f"{where} straddles the edge of marker {big.label}")
    if not np.all(big.cells[row, col] == 1):
        raise TargetSpecError(
            f"{where} covers black cells of marker {big.label} ({big.side_mm:g} mm): a nested "
            "marker must sit on the larger marker's white cells"
        )


def _print_marker(
    m: MarkerSpec, x_m: NDArray[np.float32], y_m: NDArray[np.float32], values: NDArray[np.float32]
) -> None:
    """Print marker ``m`` over ``values`` at target-frame points (float32 metres): its cell's
    value (1 white, 0 black) where a point falls inside it, untouched elsewhere."""
    T = m.T_target_marker
    dx = x_m - np.float32(T[0, 3])
    dy = y_m - np.float32(T[1, 3])
    c, s = np.float32(T[0, 0]), np.float32(T[1, 0])
    n = m.cells.shape[0]
    scale = np.float32(n / m.side_m)
    col = np.floor((c * dx + s * dy) * scale + np.float32(n / 2)).astype(np.int32)
    row = np.floor(np.float32(n / 2) - (c * dy - s * dx) * scale).astype(np.int32)
    inside = np.flatnonzero((col >= 0) & (col < n) & (row >= 0) & (row < n))
    values[inside] = m.cells[row[inside], col[inside]]


def _texel_span(centres_m: Array, low_m: float, high_m: float, texel_m: float) -> slice:
    """The texels whose centres (monotonic) lie within [low_m, high_m], a texel more each
    side."""
    near = np.flatnonzero((centres_m >= low_m - texel_m) & (centres_m <= high_m + texel_m))
    if near.size == 0:
        return slice(0, 0)
    return slice(int(near[0]), int(near[-1]) + 1)


@dataclass(frozen=True)
class TargetSpec:
    """A target made of square markers, the largest first.

    quiet_zone_mm : white margin printed around the largest marker.
    """

    markers: tuple[MarkerSpec, ...]
    name: str = "target"
    quiet_zone_mm: float = 20.0

    def __post_init__(self) -> None:
        if not self.markers:
            raise TargetSpecError(f"target {self.name!r} has no markers")
        seen: set[tuple[str, int]] = set()
        for m in self.markers:
            key = (m.dictionary, m.marker_id)
            if key in seen:
                raise TargetSpecError(f"target {self.name!r} lists marker {m.label} twice")
            seen.add(key)
        ordered = tuple(sorted(self.markers, key=lambda m: -m.side_mm))
        object.__setattr__(self, "markers", ordered)
        if not (math.isfinite(self.quiet_zone_mm) and self.quiet_zone_mm >= 0):
            raise TargetSpecError(f"target {self.name!r}: quiet_zone_mm must be >= 0")
        for i, big in enumerate(self.markers):
            for small in self.markers[i + 1 :]:
                _check_nesting(big, small, self.name)

    # ------------------------------------------------------------------ presets
    @staticmethod
    def paper() -> TargetSpec:
        """The paper's target: DICT_4X4_1000 id 997 (150 mm) around DICT_ARUCO_ORIGINAL id 5
        (25 mm), centred, same axes.

        The paper names DICT_4X4_100, which has only ids 0-99; id 997 exists in DICT_4X4_1000,
        whose marker 997 has the white central 2x2 cells the inner marker is printed in.
        """
        return TargetSpec(
            markers=(
                MarkerSpec("DICT_4X4_1000", 997, 150.0),
                MarkerSpec("DICT_ARUCO_ORIGINAL", 5, 25.0),
            ),
            name="paper",
            quiet_zone_mm=20.0,
        )

    # ------------------------------------------------------------------ geometry
    @property
    def outer(self) -> MarkerSpec:
        """The largest marker."""
        return self.markers[0]

    def marker_name(self, index: int) -> str:
        """How figures name marker ``index``: ``m0 (outer)`` for the largest, ``m1 (inner)``
        and so on for the ones printed inside it (the track file's ``m{i}_*`` columns)."""
        return f"m{index} ({'outer' if index == 0 else 'inner'})"

    @property
    def dictionaries(self) -> tuple[str, ...]:
        """Distinct dictionary names, in marker order."""
        return tuple(dict.fromkeys(m.dictionary for m in self.markers))

    @property
    def sheet_half_extent_m(self) -> float:
        """Half side of the printed square (largest marker plus quiet zone), metres."""
        extent = max(float(np.max(np.abs(m.corners_target_m[:, :2]))) for m in self.markers)
        return extent + self.quiet_zone_mm / 1000.0

    def white_margin_cells(self, index: int, max_cells: float = 2.0) -> tuple[float, ...]:
        """How far the white around marker ``index`` reaches beyond each of its sides (ArUco
        order: from corner i to corner i + 1), in the marker's cells: up to the first printed
        black or the sheet's edge; inf where it is white for ``max_cells`` or more."""
        m = self.markers[index]
        corners = m.corners_target_m[:, :2]
        n = m.cells.shape[0]
        cell_m = m.side_m / n
        centre = corners.mean(axis=0)
        along = np.linspace(0.0, 1.0, 4 * n + 1)
        depth = np.arange(1, int(max_cells * 100) + 1) / 100.0  # cells, in steps of 0.01
        out = []
        for i in range(4):
            a, b = corners[i], corners[(i + 1) % 4]
            normal = np.array([b[1] - a[1], a[0] - b[0]]) / np.linalg.norm(b - a)
            if np.dot(normal, (a + b) / 2 - centre) < 0:
                normal = -normal
            points = a + along[:, None] * (b - a)  # (A, 2)
            grid = points[None, :, :] + depth[:, None, None] * cell_m * normal  # (D, A, 2)
            white = self.albedo(grid[..., 0], grid[..., 1]) > 0.5  # NaN (off the sheet): False
            blocked = np.flatnonzero(~np.all(white, axis=1))
            out.append(float(depth[blocked[0]] - 0.005) if blocked.size else math.inf)
        return tuple(out)

    def albedo(self, x_m: Array, y_m: Array) -> NDArray[np.float32]:
        """Printed reflectance at target-frame points: 1 white, 0 black, NaN off the sheet.

        x_m, y_m : float arrays of the same shape, metres in the target frame (NaN allowed).
        Returns float32 of that shape.
        """
        x = np.asarray(x_m, dtype=np.float32)
        y = np.asarray(y_m, dtype=np.float32)
        half = np.float32(self.sheet_half_extent_m)
        out = np.full(x.shape, np.nan, dtype=np.float32)
        on_sheet = np.flatnonzero((np.abs(x) <= half) & (np.abs(y) <= half))
        xs = x.reshape(-1)[on_sheet]
        ys = y.reshape(-1)[on_sheet]
        values = np.ones(on_sheet.size, dtype=np.float32)
        for m in self.markers:  # largest first; smaller markers are printed over it
            _print_marker(m, xs, ys, values)
        out.reshape(-1)[on_sheet] = values
        return out

    @cached_property
    def texture(self) -> tuple[NDArray[np.float32], float]:
        """The printed sheet as a float32 image for fast lookups, and its texel size in metres.

        Texel (i, j) covers x in [(j - N/2) * texel, (j + 1 - N/2) * texel) and y likewise from
        the top; every cell edge of an unrotated marker centred on a texel corner falls on a
        texel edge. Off-sheet texels hold -1.
        """
        smallest_cell_m = min(m.side_m / m.cells.shape[0] for m in self.markers)
        texel = smallest_cell_m / 32.0
        half = self.sheet_half_extent_m
        n = 2 * math.ceil(half / texel)
        if n > 8192:
            texel = 2.0 * half / 8192
            n = 8192
        centres = (np.arange(n) + 0.5 - n / 2) * texel
        # the sheet white, then each marker printed over the texels of its bounding box (a
        # texel more each side): the albedo's values, without evaluating a large sheet's
        # quiet zone texel by texel
        on_sheet = np.abs(centres.astype(np.float32)) <= np.float32(half)
        tex = np.where(on_sheet[:, None] & on_sheet[None, :], np.float32(1.0), np.float32(-1.0))
        for m in self.markers:
            xy = m.corners_target_m[:, :2]
            cols = _texel_span(centres, float(xy[:, 0].min()), float(xy[:, 0].max()), texel)
            rows = _texel_span(-centres, float(xy[:, 1].min()), float(xy[:, 1].max()), texel)
            xx, yy = np.meshgrid(centres[cols], -centres[rows])
            block = tex[rows, cols]
            values = block.reshape(-1).copy()
            x = xx.reshape(-1).astype(np.float32)
            _print_marker(m, x, yy.reshape(-1).astype(np.float32), values)
            tex[rows, cols] = np.where(block >= 0.0, values.reshape(block.shape), block)
        return tex.astype(np.float32, copy=False), texel

    # ------------------------------------------------------------------ file I/O
    def to_dict(self) -> dict[str, Any]:
        """The YAML mapping of this target."""
        return {
            "name": self.name,
            "quiet_zone_mm": float(self.quiet_zone_mm),
            "markers": [m.to_dict() for m in self.markers],
        }

    def save(self, path: str | Path) -> None:
        """Write the target as YAML."""
        try:
            Path(path).write_text(yaml.safe_dump(self.to_dict(), sort_keys=False), encoding="utf-8")
        except OSError as exc:
            raise TargetSpecError(f"{path}: cannot write ({exc.strerror})") from exc

    @staticmethod
    def load(path: str | Path) -> TargetSpec:
        """Read a target YAML written by ``save`` (or by hand)."""
        p = Path(path)
        if not p.is_file():
            raise TargetSpecError(f"{p}: target file not found")
        try:
            data = safe_yaml.load(p.read_text(encoding="utf-8", errors="replace"))
        except yaml.YAMLError as exc:
            reason = (str(exc).strip().splitlines() or ["no reason given"])[0]
            raise TargetSpecError(f"{p}: not valid YAML ({reason})") from exc
        try:
            return TargetSpec.from_dict(data)
        except TargetSpecError as exc:
            raise TargetSpecError(f"{p}: {exc}") from exc

    @staticmethod
    def from_dict(data: object) -> TargetSpec:
        """Build a target from its YAML mapping."""
        if not isinstance(data, dict) or not isinstance(data.get("markers"), list):
            raise TargetSpecError("expected a mapping with a list 'markers'")
        markers = []
        for i, raw in enumerate(data["markers"]):
            if not isinstance(raw, dict):
                raise TargetSpecError(f"markers[{i}] is not a mapping")
            try:
                centre = raw.get("centre_mm", [0.0, 0.0])
                markers.append(
                    MarkerSpec(
                        dictionary=str(raw["dictionary"]),
                        marker_id=int(raw["id"]),
                        side_mm=float(raw["side_mm"]),
                        centre_mm=(float(centre[0]), float(centre[1])),
                        rotation_deg=float(raw.get("rotation_deg", 0.0)),
                    )
                )
            except KeyError as exc:
                raise TargetSpecError(f"markers[{i}] lacks field {exc.args[0]!r}") from exc
            except (TypeError, ValueError, IndexError) as exc:
                raise TargetSpecError(f"markers[{i}] has a field of the wrong type") from exc
        try:
            quiet = float(data.get("quiet_zone_mm", 20.0))
        except (TypeError, ValueError) as exc:
            raise TargetSpecError("quiet_zone_mm is not a number") from exc
        return TargetSpec(tuple(markers), str(data.get("name", "target")), quiet)
