"""Render the target as a camera sees it, with known pose.

The image is built on a grid of ``supersample`` x ``supersample`` cells per pixel. Each cell is
one ray through the lens model, intersected with the target plane; cells within one cell of an
edge (where those rays disagree) are traced again with ``edge_samples`` rays on a Fibonacci
lattice, so each cell holds its area's mean to a small fraction of its size at every edge angle
and corners sit where the geometry puts them, for both distortion models and at any distance.
The optical blur is applied to the cells, which are then averaged into pixels: blur before the
pixels integrate the light, as in a camera. Exposure and contrast come first; vignetting, motion
blur, noise and JPEG after, on the pixels; occluders are drawn before the blur.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Generic, Protocol, TypeVar

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.geometry import check_transform
from perchpose.target import TargetSpec

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ImageQuality:
    """Photometric settings of a rendered frame.

    black_level, white_level : grey level of printed black and white at exposure 1.
    surround : reflectance of everything that is not the printed sheet (plate, ceiling).
    exposure : gain on the light reaching the sensor.
    blur_sigma_px : Gaussian optical blur, pixels.
    motion_blur_px, motion_angle_deg : length and direction of a linear motion blur, pixels.
    noise_sigma : standard deviation of additive Gaussian sensor noise, grey levels.
    jpeg_quality : JPEG compression quality 1-100, or None for none.
    vignetting : relative darkening at the image corners (0 none, 0.4 strong).
    bloom_sigma_px, bloom : light above the sensor's saturation (a surround brighter than the
        printed white: lamps or sky above the plate) spreading over its neighbours, as a lens's
        veiling glare does: that excess, blurred by a Gaussian of bloom_sigma_px and scaled by
        bloom, is added back (0: none).
    interference : analog interference, grey levels: horizontal bands of that amplitude at a
        period and phase drawn per frame, and a few rows per frame streaked with bright noise.
    rolling_shutter_px : how far the last row is shifted sideways against the first (a camera
        turning while its rows are read out); the middle row stays where the pose puts it.
    """

    black_level: float = 25.0
    white_level: float = 225.0
    surround: float = 0.45
    exposure: float = 1.0
    blur_sigma_px: float = 0.6
    motion_blur_px: float = 0.0
    motion_angle_deg: float = 0.0
    noise_sigma: float = 2.0
    jpeg_quality: int | None = None
    vignetting: float = 0.0
    bloom_sigma_px: float = 0.0
    bloom: float = 0.0
    interference: float = 0.0
    rolling_shutter_px: float = 0.0

    @staticmethod
    def preset(name: str) -> ImageQuality:
        """``clean``, ``default``, ``analog_fpv`` (noise, blur, low contrast, JPEG) or
        ``harsh`` (an analog link on a moving vehicle under a bright sky: the target in shadow
        and the auto-exposure set by the surround, which is 3 times brighter than the printed
        white and bleeds over the sheet's edges; 5 px of motion blur, 1.3 px of optical blur,
        noise of 8 grey levels, interference, 4 px of rolling shutter, JPEG 40)."""
        if name == "clean":
            return ImageQuality(blur_sigma_px=0.0, noise_sigma=0.0)
        if name == "default":
            return ImageQuality()
        if name == "analog_fpv":
            return ImageQuality(
                black_level=55.0,
                white_level=190.0,
                blur_sigma_px=1.1,
                noise_sigma=6.0,
                jpeg_quality=70,
                vignetting=0.3,
            )
        if name == "harsh":
            return ImageQuality(
                black_level=55.0,
                white_level=190.0,
                surround=3.0,
                exposure=0.6,
                blur_sigma_px=1.3,
                motion_blur_px=5.0,
                motion_angle_deg=30.0,
                noise_sigma=8.0,
                jpeg_quality=40,
                vignetting=0.3,
                bloom_sigma_px=6.0,
                bloom=0.6,
                interference=6.0,
                rolling_shutter_px=4.0,
            )
        raise ValueError(f"unknown image quality preset {name!r}")


@dataclass(frozen=True)
class Occluder:
    """A dark polygon drawn over the image (pixels), e.g. a hand or a wire."""

    polygon_px: Array
    grey: int = 30


class PlanarPattern(Protocol):
    """Something printed on a plane: a target or a calibration board.

    texture : a square float32 image centred on the pattern's origin (x right, y up as printed;
        -1 off the sheet) and its texel size in metres.
    sheet_half_extent_m : half side of a square, centred on the origin, that holds the sheet.
    """

    @property
    def texture(self) -> tuple[NDArray[np.float32], float]: ...

    @property
    def sheet_half_extent_m(self) -> float: ...


P = TypeVar("P", bound=PlanarPattern)


NOISE_BANK_SEED = 20240601
# the grey level (before quantisation) above which a sensor's pixels saturate and the excess
# light spreads as glare (``ImageQuality.bloom``)
SATURATION = 255.0


# the supersampled grid's rays of the last few cameras rendered through, shared by every
# renderer of the process (each is tens of MB and 0.1-0.7 s to compute; a campaign's or a
# test's renderers mostly share one camera)
_GRID_RAYS: OrderedDict[tuple[object, ...], NDArray[np.float32]] = OrderedDict()
_GRID_RAYS_LOCK = threading.Lock()  # renderers in several threads (a simulated vehicle's video)
GRID_RAYS_KEPT = 4


def grid_rays(camera: CameraModel, supersample: int) -> NDArray[np.float32]:
    """(H n W n, 3) unit rays, row by row and read-only, through the centres of an ``n`` x
    ``n`` grid of samples in every pixel (``n`` = ``supersample``), computed once per lens,
    image size and ``n`` and kept for the next renderer of the same camera."""
    key = (
        camera.model,
        camera.width_px,
        camera.height_px,
        np.asarray(camera.K, np.float64).tobytes(),
        np.asarray(camera.dist, np.float64).tobytes(),
        supersample,
    )
    with _GRID_RAYS_LOCK:
        rays = _GRID_RAYS.get(key)
        if rays is not None:
            _GRID_RAYS.move_to_end(key)
            return rays
        n = supersample
        w, h = camera.size
        offsets = (np.arange(n) + 0.5) / n - 0.5
        us = (np.arange(w)[:, None] + offsets[None, :]).reshape(-1)
        vs = (np.arange(h)[:, None] + offsets[None, :]).reshape(-1)
        u, v = np.meshgrid(us, vs)
        rays = camera.pixel_rays(np.stack([u.reshape(-1), v.reshape(-1)], 1)).astype(np.float32)
        rays.flags.writeable = False
        _GRID_RAYS[key] = rays
        while len(_GRID_RAYS) > GRID_RAYS_KEPT:
            _GRID_RAYS.popitem(last=False)
        return rays


@dataclass
class Renderer(Generic[P]):
    """Draws ``target`` (a TargetSpec, or any PlanarPattern) through ``camera``; the rays of its
    sample grid are computed once per camera and shared (``grid_rays``).

    noise_bank : draw each frame's sensor noise as a window, at an offset drawn from the frame's
        generator, of one bank of Gaussian noise twice the frame's size each way (drawn once,
        with a fixed seed), instead of drawing fresh noise for every pixel. Each frame's noise
        is still white with the set deviation, and two frames' windows almost never overlap
        in alignment; it costs a tenth of fresh noise. For long closed-loop runs; the
        evaluation draws fresh noise.
    edge_samples : rays per cell, on a Fibonacci lattice, for the cells within one cell of an
        edge; 0 keeps the single ray there too. Needs ``supersample`` > 1 to find the edges. A
        regular 3 x 3 grid of rays places an edge only to a third of a pixel along each axis;
        along a whole edge those steps average out at most angles, but not near the angles
        where the edge's steps repeat with the grid (0, 27, 45, 90 deg...), where a whole edge
        came out up to 0.17 px off and a 22 px marker's corners up to 0.07 px. The lattice's
        rays all have distinct offsets along both axes, so a straight edge at any angle is
        placed to about 1 / (``supersample`` * ``edge_samples``) of a pixel.
    """

    camera: CameraModel
    target: P
    supersample: int = 3
    noise_bank: bool = False
    edge_samples: int = 34
    _rays: NDArray[np.float32] | None = field(default=None, repr=False)
    _vignette: NDArray[np.float32] | None = field(default=None, repr=False)
    _bank: NDArray[np.float32] | None = field(default=None, repr=False)

    def _camera_rays(self) -> NDArray[np.float32]:
        if self._rays is None:
            self._rays = grid_rays(self.camera, self.supersample)
        return self._rays

    def _sheet_pixel_box(self, T: Array) -> tuple[int, int, int, int] | None:
        """Pixel box (x0, y0, x1, y1), end exclusive, holding the printed sheet's image, or None
        when the sheet is not wholly in front of the camera (then the whole frame is traced)."""
        half = self.target.sheet_half_extent_m
        edge = np.linspace(-half, half, 17)
        ring = np.concatenate(
            [
                np.stack([edge, np.full_like(edge, half)], 1),
                np.stack([edge, np.full_like(edge, -half)], 1),
                np.stack([np.full_like(edge, half), edge], 1),
                np.stack([np.full_like(edge, -half), edge], 1),
            ]
        )
        points = np.concatenate([ring, np.zeros((ring.shape[0], 1))], 1)
        uv, ok = self.camera.project((T[:3, :3] @ points.T).T + T[:3, 3])
        if not np.all(ok) or not np.all(np.isfinite(uv)):
            return None
        w, h = self.camera.size
        margin = 3.0  # a sheet edge bows between the sampled points; blur needs room too
        x0 = int(np.clip(np.floor(uv[:, 0].min() - margin), 0, w))
        x1 = int(np.clip(np.ceil(uv[:, 0].max() + margin) + 1, 0, w))
        y0 = int(np.clip(np.floor(uv[:, 1].min() - margin), 0, h))
        y1 = int(np.clip(np.ceil(uv[:, 1].max() + margin) + 1, 0, h))
        return (x0, y0, x1, y1)

    def reflectance(self, T_camera_target: Array) -> NDArray[np.float32]:
        """(H, n, W, n) reflectance of each of the n x n samples of every pixel, NaN off the
        sheet, for the target at ``T_camera_target``.

        Only the pixels around the sheet's image are traced when the sheet lies wholly in front
        of the camera; a lens whose border bends the sheet's edge outside the sampled outline
        falls back to the whole frame.
        """
        n = self.supersample
        w, h = self.camera.size
        out = np.full((h, n, w, n), math.nan, dtype=np.float32)
        box, samples = self._trace(T_camera_target, math.nan)
        x0, y0, x1, y1 = box
        out[y0:y1, :, x0:x1, :] = samples
        return out

    def _trace(
        self, T_camera_target: Array, off_sheet: float
    ) -> tuple[tuple[int, int, int, int], NDArray[np.float32]]:
        """The pixel box (x0, y0, x1, y1) traced and the (y1 - y0, n, x1 - x0, n) reflectance
        samples in it, ``off_sheet`` where a ray misses the sheet; every pixel outside the box
        misses it."""
        T = check_transform(T_camera_target, "T_camera_target")
        n = self.supersample
        w, h = self.camera.size
        box = self._sheet_pixel_box(T)
        x0, y0, x1, y1 = box if box is not None else (0, 0, w, h)
        if x1 <= x0 or y1 <= y0:
            return (0, 0, 0, 0), np.zeros((0, n, 0, n), np.float32)
        rays = self._camera_rays().reshape(h * n, w * n, 3)[y0 * n : y1 * n, x0 * n : x1 * n]
        refl = self._look_up(T, rays)
        refl[refl < 0] = off_sheet
        return (x0, y0, x1, y1), np.asarray(refl, np.float32).reshape(y1 - y0, n, x1 - x0, n)

    def _look_up(self, T: Array, rays: NDArray[np.float32]) -> NDArray[np.float32]:
        """Reflectance seen along each ray of a (rows, cols, 3) array; -1 where a ray misses
        the sheet."""
        R = T[:3, :3]
        o_t = -R.T @ T[:3, 3]  # camera centre in the target frame
        tex, texel = self.target.texture
        c = tex.shape[0] / 2 - 0.5
        # A ray d (camera frame) meets the plane z = 0 at o + lam R^T d with lam = -o_z / d_z;
        # in homogeneous form (o_x d_z - o_z d_x, o_y d_z - o_z d_y, d_z) with d = R^T d, and
        # then scaled to texture coordinates: one 3x3 matrix for every pixel. remap's nearest
        # lookup rounds, so texel j is [j - 0.5, j + 0.5) in map coordinates.
        to_plane = np.array([[-o_t[2], 0.0, o_t[0]], [0.0, -o_t[2], o_t[1]], [0.0, 0.0, 1.0]])
        to_texture = np.array([[1.0 / texel, 0.0, c], [0.0, -1.0 / texel, c], [0.0, 0.0, 1.0]])
        A = (to_texture @ to_plane @ R.T).astype(np.float32)
        uvw = cv2.transform(np.ascontiguousarray(rays), A)
        wz = uvw[..., 2]
        # rays parallel to or away from the plane (lam <= 0) see the surround
        misses = ~(wz * np.float32(o_t[2]) < 0)
        wz[misses] = np.float32(1.0)
        map_u = np.asarray(uvw[..., 0] / wz, np.float32)
        map_v = np.asarray(uvw[..., 1] / wz, np.float32)
        map_u[misses] = np.float32(-1e6)
        map_v[misses] = np.float32(-1e6)
        refl = cv2.remap(
            tex,
            map_u,
            map_v,
            cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=-1.0,
        )
        return np.asarray(refl, np.float32)

    def _cell_means(
        self,
        T_camera_target: Array,
        origin_px: tuple[int, int],
        samples: NDArray[np.float32],
        off_sheet: float,
    ) -> NDArray[np.float32]:
        """(h n, w n): the mean reflectance over each sample's cell (1/n of a pixel a side):
        the sample itself where it and its eight neighbours agree, the mean of the edge
        lattice's rays through the cell where they do not."""
        h, n, w, _ = samples.shape
        cells = np.array(samples.reshape(h * n, w * n), np.float32)
        if n == 1 or self.edge_samples <= 0:
            return cells
        # a cell whose neighbours' samples all agree with its own is uniform: an edge through
        # it would cross a line between two of those samples
        ring = np.ones((3, 3), np.uint8)
        lowest = cv2.erode(cells, ring, borderType=cv2.BORDER_REPLICATE)
        highest = cv2.dilate(cells, ring, borderType=cv2.BORDER_REPLICATE)
        rows, cols = np.nonzero(highest > lowest)
        if rows.size == 0:
            return cells
        rays = self._lattice_rays(rows + origin_px[1] * n, cols + origin_px[0] * n)
        # remap takes maps under 32767 a side: fold the rays into rows of 4096
        width = 4096
        padded = np.zeros((-(-rays.shape[0] // width) * width, 3), np.float32)
        padded[: rays.shape[0]] = rays
        padded[rays.shape[0] :, 2] = 1.0
        T = check_transform(T_camera_target, "T_camera_target")
        refl = self._look_up(T, padded.reshape(-1, width, 3)).reshape(-1)[: rays.shape[0]]
        refl[refl < 0] = off_sheet
        cells[rows, cols] = refl.reshape(rows.size, -1).mean(axis=1, dtype=np.float32)
        return cells

    def _lattice_rays(self, rows: NDArray[np.intp], cols: NDArray[np.intp]) -> NDArray[np.float32]:
        """(len(rows) * edge_samples, 3) rays through the edge lattice of the cells (rows,
        cols) of the ``supersample`` grid (whole frame).

        Across one pixel the lens bends a ray by a second-order amount far below the lattice's
        spacing, so each cell's rays come from an affine fit to its pixel's cached grid of rays
        instead of the lens model."""
        n = self.supersample
        w, h = self.camera.size
        lattice = _fibonacci_lattice(self.edge_samples) / n
        offsets = (np.arange(n) + 0.5) / n - 0.5
        spread = n * np.sum(offsets * offsets)
        grid_rays = self._camera_rays().reshape(h, n, w, n, 3)
        out = np.empty((rows.size, lattice.shape[0], 3), np.float32)
        sub_v, sub_u = rows % n, cols % n
        for i in range(n):
            for j in range(n):
                here = np.nonzero((sub_v == i) & (sub_u == j))[0]
                if here.size == 0:
                    continue
                grid = grid_rays[rows[here] // n, :, cols[here] // n, :]  # (P, n, n, 3)
                # ray k = the grid's mean + u_k * its slope along u + v_k * its slope along v:
                # one (samples, n * n) weight matrix for the cells at this place in a pixel
                u, v = offsets[j] + lattice[:, 0], offsets[i] + lattice[:, 1]
                weights = (
                    1.0 / (n * n)
                    + u[:, None, None] * offsets[None, None, :] / spread
                    + v[:, None, None] * offsets[None, :, None] / spread
                ).reshape(-1, n * n)
                out[here] = np.matmul(weights.astype(np.float32), grid.reshape(-1, n * n, 3))
        return out.reshape(-1, 3)

    def render(
        self,
        T_camera_target: Array,
        quality: ImageQuality | None = None,
        rng: np.random.Generator | None = None,
        occluders: tuple[Occluder, ...] = (),
    ) -> NDArray[np.uint8]:
        """A grey (H, W) uint8 frame of the target at ``T_camera_target`` (metres).

        The optical blur acts on the light before the pixels integrate it: it is applied to
        the ``supersample`` grid's cells, which are then averaged into pixels (a blur applied to
        the pixels instead shifts an edge by up to 0.03 px, depending on where it falls within
        a pixel). Everything outside the sheet's pixel box is the uniform surround, so the blur
        is computed in the box grown by its reach; occluders take the whole frame. Vignetting,
        motion blur, noise and JPEG follow, on the pixels."""
        q = quality or ImageQuality()
        return self._sense(self._light(T_camera_target, q, occluders), q, rng)

    def _light(
        self, T_camera_target: Array, q: ImageQuality, occluders: tuple[Occluder, ...]
    ) -> NDArray[np.float32]:
        """The light on the pixels (``render`` before the sensor), not yet clipped."""
        w, h = self.camera.size
        n = self.supersample
        gain = np.float32(q.exposure * (q.white_level - q.black_level))
        dark = np.float32(q.exposure * q.black_level)
        background = dark + gain * np.float32(q.surround)
        (x0, y0, x1, y1), samples = self._trace(T_camera_target, q.surround)
        in_view = x1 > x0 and y1 > y0
        light = (
            dark + gain * self._cell_means(T_camera_target, (x0, y0), samples, q.surround)
            if in_view
            else None
        )
        img: NDArray[np.float32] = np.full((h, w), background, np.float32)
        if q.blur_sigma_px > 0 and (in_view or occluders):
            if occluders or not in_view:
                bx0, by0, bx1, by1 = 0, 0, w, h
            else:
                # beyond the box the frame is uniform: blurring the box and a ring as wide as
                # the kernel's reach gives the whole-frame blur there and changes nothing outside
                reach = int(math.ceil(4.0 * q.blur_sigma_px)) + 1
                bx0, by0 = max(0, x0 - reach), max(0, y0 - reach)
                bx1, by1 = min(w, x1 + reach), min(h, y1 + reach)
            canvas = np.full(((by1 - by0) * n, (bx1 - bx0) * n), background, np.float32)
            if light is not None:
                canvas[(y0 - by0) * n : (y1 - by0) * n, (x0 - bx0) * n : (x1 - bx0) * n] = light
            for occ in occluders:
                # pixel u holds cells n u .. n u + n - 1, whose centres are at n u + (n - 1) / 2
                polygon = (occ.polygon_px - [bx0, by0]) * n + (n - 1) / 2.0
                cv2.fillPoly(canvas, [np.round(polygon).astype(np.int32)], float(occ.grey))
            canvas = np.asarray(cv2.GaussianBlur(canvas, (0, 0), q.blur_sigma_px * n), np.float32)
            img[by0:by1, bx0:bx1] = _bin(canvas, n)
        else:
            if light is not None:
                img[y0:y1, x0:x1] = _bin(light, n)
            for occ in occluders:
                cv2.fillPoly(img, [np.round(occ.polygon_px).astype(np.int32)], float(occ.grey))
        return self._after_lens(img, q)

    def mean_image(
        self,
        T_camera_target: Array,
        quality: ImageQuality | None = None,
        occluders: tuple[Occluder, ...] = (),
    ) -> NDArray[np.float32]:
        """The grey (H, W) float32 frame ``render`` draws before the sensor's noise,
        interference, 8-bit rounding and JPEG, clipped to [0, 255] as the sensor saturates:
        the mean of the frames it renders with noise alone, whose derivatives by the pose
        bound any estimate from them (the Cramer-Rao bound)."""
        light = self._light(T_camera_target, quality or ImageQuality(), occluders)
        return np.asarray(np.clip(light, 0.0, 255.0), np.float32)

    def _after_lens(self, img: NDArray[np.float32], q: ImageQuality) -> NDArray[np.float32]:
        """What happens to the light after the lens: glare, vignetting, motion blur and
        rolling shutter."""
        if q.bloom > 0 and q.bloom_sigma_px > 0:
            excess = np.maximum(img - np.float32(SATURATION), np.float32(0.0))
            if float(excess.max()) > 0:
                glow = cv2.GaussianBlur(excess, (0, 0), q.bloom_sigma_px)
                img = np.asarray(img + np.float32(q.bloom) * glow, np.float32)
        if q.vignetting > 0:
            img *= 1.0 - np.float32(q.vignetting) * self._vignette_map()
        if q.motion_blur_px >= 1.0:
            kernel = _motion_kernel(q.motion_blur_px, q.motion_angle_deg)
            img = np.asarray(cv2.filter2D(img, -1, kernel), np.float32)
        if q.rolling_shutter_px != 0:
            img = _rolling_shutter(img, q.rolling_shutter_px)
        return img

    def _sense(
        self, img: NDArray[np.float32], q: ImageQuality, rng: np.random.Generator | None
    ) -> NDArray[np.uint8]:
        """What the sensor and the link do to the light: noise and interference, 8-bit
        quantisation and JPEG."""
        w, h = self.camera.size
        generator = rng if rng is not None else np.random.default_rng(0)
        if q.noise_sigma > 0:
            if self.noise_bank:
                bank = self._noise_bank()
                oy, ox = int(generator.integers(0, h + 1)), int(generator.integers(0, w + 1))
                img = np.asarray(
                    cv2.scaleAdd(bank[oy : oy + h, ox : ox + w], float(q.noise_sigma), img),
                    np.float32,
                )
            else:
                # OpenCV's generator, seeded from ``rng``, draws noise 4x faster than numpy's
                noise = np.empty(img.shape, np.float32)
                cv2.setRNGSeed(int(generator.integers(1, 2**31 - 1)))
                cv2.randn(noise, np.zeros(1), np.full(1, float(q.noise_sigma)))
                img += noise
        if q.interference > 0:
            img = _interference(img, q.interference, generator)
        # round half to even and saturate, as numpy's round-and-clip would
        np.maximum(img, np.float32(0.0), out=img)
        out = np.asarray(cv2.convertScaleAbs(img), np.uint8)
        if q.jpeg_quality is not None:
            ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(q.jpeg_quality)])
            if ok:
                out = np.asarray(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE), np.uint8)
        return out

    def _noise_bank(self) -> NDArray[np.float32]:
        if self._bank is None:
            w, h = self.camera.size
            bank = np.empty((2 * h, 2 * w), np.float32)
            cv2.setRNGSeed(NOISE_BANK_SEED)
            cv2.randn(bank, np.zeros(1), np.ones(1))
            self._bank = bank
        return self._bank

    def _vignette_map(self) -> NDArray[np.float32]:
        if self._vignette is None:
            w, h = self.camera.size
            u, v = np.meshgrid(np.arange(w), np.arange(h))
            r2 = ((u - w / 2) ** 2 + (v - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
            self._vignette = r2.astype(np.float32)
        return self._vignette

    def corners_px(self, T_camera_target: Array) -> list[Array | None]:
        """True corner pixels (4, 2) of each marker, or None where a corner cannot be imaged."""
        if not isinstance(self.target, TargetSpec):
            raise TypeError("corners_px needs a TargetSpec")
        T = check_transform(T_camera_target, "T_camera_target")
        out: list[Array | None] = []
        for m in self.target.markers:
            p = (T[:3, :3] @ m.corners_target_m.T).T + T[:3, 3]
            uv, ok = self.camera.project(p)
            out.append(uv if bool(np.all(ok)) else None)
        return out


def _bin(cells: NDArray[np.float32], n: int) -> NDArray[np.float32]:
    """The mean of each n x n block of ``cells``."""
    if n == 1:
        return cells
    h, w = cells.shape[0] // n, cells.shape[1] // n
    return np.asarray(cv2.resize(cells, (w, h), interpolation=cv2.INTER_AREA), np.float32)


def _fibonacci_lattice(count: int) -> Array:
    """``count`` offsets (count, 2) in [-0.5, 0.5)^2, pixels: a Fibonacci lattice rule when
    ``count`` is a Fibonacci number, otherwise the rule with the step nearest count / phi that
    is prime to it; either way the offsets are distinct along each axis."""
    a, b = 1, 1
    while b < count:
        a, b = b, a + b
    step = a
    if b != count:
        near = count / 1.618033988749895
        step = min(
            (s for s in range(1, max(2, count)) if math.gcd(s, count) == 1),
            key=lambda s: abs(s - near),
        )
    k = np.arange(count)
    u = (k + 0.5) / count
    v = ((k * step) % count + 0.5) / count
    return np.stack([u, v], 1) - 0.5


def _rolling_shutter(img: NDArray[np.float32], shift_px: float) -> NDArray[np.float32]:
    """Each row shifted sideways in proportion to its distance from the middle row, the last
    row ``shift_px`` from the first (bilinear; the border row repeated)."""
    h, w = img.shape
    rows = (np.arange(h, dtype=np.float32) / max(1, h - 1) - 0.5) * np.float32(shift_px)
    map_x = np.arange(w, dtype=np.float32)[None, :] - rows[:, None]
    map_y = np.repeat(np.arange(h, dtype=np.float32)[:, None], w, axis=1)
    return np.asarray(
        cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE),
        np.float32,
    )


def _interference(
    img: NDArray[np.float32], amplitude: float, rng: np.random.Generator
) -> NDArray[np.float32]:
    """Analog interference: horizontal bands of ``amplitude`` grey levels (a period of 20-120
    rows, drifting phase) and 2-6 rows streaked with bright noise over part of their width."""
    h, w = img.shape
    period = float(rng.uniform(20.0, 120.0))
    phase = float(rng.uniform(0.0, 2.0 * math.pi))
    bands = amplitude * np.sin(2.0 * math.pi * np.arange(h) / period + phase)
    out = img + bands.astype(np.float32)[:, None]
    for _ in range(int(rng.integers(2, 7))):
        row = int(rng.integers(0, h))
        start = int(rng.integers(0, w))
        length = int(rng.integers(w // 8, w // 2))
        stop = min(w, start + length)
        out[row, start:stop] += np.float32(4.0 * amplitude) * rng.random(stop - start).astype(
            np.float32
        )
    return np.asarray(out, np.float32)


def _motion_kernel(length_px: float, angle_deg: float) -> NDArray[np.float32]:
    size = int(np.ceil(length_px)) | 1
    kernel = np.zeros((size, size), np.float32)
    c = size // 2
    a = np.deg2rad(angle_deg)
    for s in np.linspace(-length_px / 2, length_px / 2, 4 * size):
        x = int(round(c + s * np.cos(a)))
        y = int(round(c + s * np.sin(a)))
        kernel[y, x] += 1.0
    return np.asarray(kernel / kernel.sum(), dtype=np.float32)
