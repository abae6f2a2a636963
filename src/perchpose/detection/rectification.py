"""A pinhole view of a distorted camera's image, for finding markers whose edges the lens bends
too much for OpenCV's quad finder, and the maps between its pixels and the original's.

The remap tables take about a second to build for a fisheye camera, so each camera's are built
once and kept here (keyed by the camera's model, size and coefficients), for every detector of
that camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel

Array = NDArray[np.float64]
Maps = tuple[NDArray[np.float32], NDArray[np.float32]]

# Half the horizontal field of view the rectified image covers, and its largest size relative to
# the original image.
RECTIFIED_HALF_FOV_DEG = 60.0
RECTIFIED_MAX_SCALE = 1.5
_KEPT = 8  # cameras whose tables are kept
# The coarse view samples every this many pixels of the view (``Rectification.coarse_maps``).
COARSE_STEP = 2


@dataclass(frozen=True, eq=False)
class Rectification:
    """Remap tables from the original image to a pinhole view (``maps``: x and y of the original
    pixel for each pixel of the view) and that view's ``K_rect``.

    The view is up to 1.5 times the image's size and spans up to +/-60 deg horizontally, with
    the camera's own focal length where that fits."""

    camera: CameraModel
    maps: Maps
    K_rect: Array

    @property
    def size(self) -> tuple[int, int]:
        """(height, width) of the view."""
        h, w = self.maps[0].shape
        return h, w

    @cached_property
    def coarse_maps(self) -> Maps:
        """``maps`` at every ``COARSE_STEP``-th pixel of the view both ways: a view of the same
        lens at that fraction of the size (its pixel (i, j) is the view's (s i, s j)), for
        whole-view searches where the corners are fitted again in the original."""
        step = COARSE_STEP
        return (
            np.ascontiguousarray(self.maps[0][::step, ::step]),
            np.ascontiguousarray(self.maps[1][::step, ::step]),
        )

    @staticmethod
    def of(camera: CameraModel) -> Rectification:
        """The camera's rectification, built on first use and kept."""
        key = _key(camera)
        kept = _TABLES.get(key)
        if kept is None:
            kept = _build(camera)
            if len(_TABLES) >= _KEPT:
                _TABLES.pop(next(iter(_TABLES)))
            _TABLES[key] = kept
        return kept

    def to_rectified(self, corners_px: Array) -> Array:
        """Pixels of the original image -> pixels of the view."""
        xy = self.camera.normalize(corners_px)
        return np.asarray(xy * self.K_rect[0, 0] + self.K_rect[:2, 2], np.float64)

    def to_original(self, corners_rect_px: Array) -> tuple[Array, bool]:
        """Pixels of the view -> pixels of the original image, and whether all project."""
        K = self.K_rect
        rays = np.concatenate(
            [(corners_rect_px - K[:2, 2]) / K[0, 0], np.ones((corners_rect_px.shape[0], 1))], 1
        )
        uv, ok = self.camera.project(rays)
        return uv, bool(np.all(ok))


_TABLES: dict[tuple[object, ...], Rectification] = {}


def _key(camera: CameraModel) -> tuple[object, ...]:
    return (
        camera.model,
        camera.size,
        np.asarray(camera.K, np.float64).tobytes(),
        np.asarray(camera.dist, np.float64).tobytes(),
    )


def _build(camera: CameraModel) -> Rectification:
    w0, h0 = camera.size
    w = int(round(w0 * RECTIFIED_MAX_SCALE))
    h = int(round(h0 * RECTIFIED_MAX_SCALE))
    f = min(camera.focal_px, (w / 2.0) / math.tan(math.radians(RECTIFIED_HALF_FOV_DEG)))
    K_rect = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([(u - K_rect[0, 2]) / f, (v - K_rect[1, 2]) / f, np.ones_like(u)], -1)
    rays = rays.reshape(-1, 3) / np.linalg.norm(rays.reshape(-1, 3), axis=1, keepdims=True)
    uv, ok = camera.project(rays)
    inside = ok & (uv[:, 0] > -1) & (uv[:, 0] < w0) & (uv[:, 1] > -1) & (uv[:, 1] < h0)
    # a lens polynomial can fold rays from outside its field back into the image:
    # keep only pixels whose ray comes back unchanged
    back = camera.pixel_rays(uv[inside])
    inside[np.flatnonzero(inside)] = np.sum(back * rays[inside], axis=1) > np.cos(1e-3)
    uv[~inside] = -10.0
    map_xy = uv.reshape(h, w, 2).astype(np.float32)
    maps = (np.ascontiguousarray(map_xy[..., 0]), np.ascontiguousarray(map_xy[..., 1]))
    return Rectification(camera, maps, K_rect)
